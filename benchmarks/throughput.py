"""Throughput and scaling: nanoseconds per tet per VBD iteration from 1k to 1M tets.

For each mesh (a box of Kuhn-split cubes, 6 tets per cell) and each of float64/float32 and 1/2 CPU
threads (one worker process per thread count, since Taichi fixes the thread count at ti.init):
ns per tet per iteration of the VBD sweep, the colour count, the cost of colouring and of the rest of
the set-up (adjacency, uploads), and two machine limits measured with the same access pattern:
  * memory probe: a kernel that reads exactly the data one sweep reads (adjacency stream, the
    neighbours' positions) and does no arithmetic; all colours in one launch like the sweep;
  * arithmetic floor: the sweep's floating-point operations per tet (counted by hand, ~430)
    divided by the measured rate of a compute-bound Taichi kernel on this machine.
In the 2-thread worker also: the vectorised numpy VBD sweep (benchmarks/baselines.py), one global
Newton iteration (assembly + sparse solve + line search) of the numpy `newton_solve` and of the Taichi
`fast_newton_solve` (warm: its sparse pattern and symbolic analysis are built by a first call) on the
same meshes, and the fitted growth exponent of time per iteration with mesh size.

    python -m benchmarks.throughput --out benchmarks/results/throughput    # full run, about 10 min
    python -m benchmarks.throughput --quick --out /tmp/throughput
"""
import json
import os
import subprocess
import sys
import time
import warnings

import numpy as np

from benchmarks.common import (print_written, ROOT, init_taichi, output_folder, parser, positive, progress, provenance, seconds_per_call, table,
                               write_csv)

FULL_SIZES = [(12, 4, 4), (16, 6, 6), (20, 10, 10), (30, 14, 12), (40, 20, 20), (60, 30, 30), (100, 40, 42)]
QUICK_SIZES = [(6, 2, 2), (12, 4, 4)]
OUTPUTS = ("throughput.csv", "scaling_fit.csv", "throughput.png", "summary.md")
FLOPS_PER_ENTRY = 105      # per (vertex, tet) pair: kinematics ~48, force ~14, Hessian ~31, sums 12
FLOPS_PER_VERTEX = 80      # inertia terms, determinant, 3x3 inverse and product
COLUMNS = ["tets", "vertices", "cells", "precision", "threads", "n_colors", "ns_per_tet_iter",
           "ms_per_iter", "iterations_timed", "coloring_s", "setup_s", "first_iteration_s", "second_setup_s",
           "probe_ns_per_tet_iter",
           "arith_floor_ns_per_tet_iter", "numpy_ns_per_tet_iter", "numpy_speedup", "newton_iter_s",
           "fast_newton_iter_s", "newton_ns_per_tet", "fast_newton_ns_per_tet"]


def _probe_class():
    from solver._ti import ti

    from solver.vbd.layout import X, Y

    @ti.kernel
    def read_all_colors(state: ti.types.ndarray(), mass: ti.types.ndarray(), color_order: ti.types.ndarray(),
                        offsets: ti.types.ndarray(), others: ti.types.ndarray(), adj_f: ti.types.ndarray(),
                        color_starts: ti.types.ndarray(), out: ti.types.ndarray(), n_colors: ti.template()):
        for c in ti.static(range(n_colors)):
            for k in range(color_starts[c], color_starts[c + 1]):
                i = color_order[k]
                acc = state[X, i] + state[Y, i] * mass[i]
                first, last = offsets[k], offsets[k + 1]
                for e in range(first, last):
                    j = others[e]
                    a = adj_f[e]
                    acc += state[X, j[0]] + state[X, j[1]] + state[X, j[2]] + ti.Vector([a[0], a[1], a[2]])
                    acc[0] += a[3] + a[4] + a[5]
                out[k] = acc.sum()

    class MemoryProbe:
        """Reads what one VBD sweep reads, all colours in one launch like the sweep, and sums it:
        no arithmetic to speak of."""

        def __init__(self, sim):
            self.sim = sim
            self.out = ti.ndarray(sim.dtype, sim.topology.n_slots)

        def iterate(self, n):
            a = self.sim.arrays
            for _ in range(n):
                read_all_colors(a.state, a.mass, a.color_order, a.offsets, a.others, a.adj_f, a.color_starts,
                                self.out, self.sim.n_colors)

    return MemoryProbe


def _flop_rate(dtype, min_seconds):
    """Floating-point operations per second of a compute-bound Taichi kernel (dependent FMA chains
    on 3-vectors, many independent threads)."""
    from solver._ti import ti

    n = 1 << 14
    out = ti.field(dtype, n)
    steps = 2000

    @ti.kernel
    def fma():
        for t in range(n):
            a = ti.Vector([1.0, 1.1, 1.2], dt=dtype) * (1.0 + t * 1e-9)
            b = ti.Vector([0.9, 0.8, 0.7], dt=dtype)
            c = ti.Vector([0.3, 0.2, 0.1], dt=dtype)
            d = ti.Vector([0.5, 0.4, 0.6], dt=dtype)
            for _ in range(steps):
                a = a * 0.999 + c
                b = b * 0.999 + d
                c = c * 0.999 + a * 1e-6
                d = d * 0.999 + b * 1e-6
            out[t] = a.sum() + b.sum() + c.sum() + d.sum()

    def run(k):
        for _ in range(k):
            fma()
        out[0]

    sec, _ = seconds_per_call(run, min_seconds)
    return n * steps * 4 * 3 * 2 / sec    # 4 vectors x 3 lanes x (mul + add)


def worker(args):
    """Measure every mesh at one thread count; print one JSON list on stdout."""
    init_taichi(args.threads)
    import solver
    from benchmarks.baselines import NumpyVBD

    MemoryProbe = _probe_class()
    sizes = [tuple(c) for c in json.loads(args.sizes)]
    rows = []
    rates = {p: _flop_rate(solver.Precision(p).ti_dtype, args.min_seconds) for p in ("float64", "float32")}
    for cells in sizes:
        mesh = solver.box_mesh(size=(cells[0] / 10, cells[1] / 10, cells[2] / 10), cells=cells)
        fixed = mesh.vertices[:, 0] < 1e-9
        t = time.perf_counter()
        solver.color_vertices(mesh.tets, mesh.n_vertices)          # no cache: the real cost
        coloring_s = time.perf_counter() - t
        mat = solver.Material(1e5, 0.3, 1000.0)
        for precision in ("float64", "float32"):
            t = time.perf_counter()
            sim = solver.Simulation(mesh, mat, dt=1 / 60, fixed=fixed, iterations=1, precision=precision)
            setup_s = time.perf_counter() - t - sim.coloring.seconds
            t = time.perf_counter()
            sim.begin_step()
            sim.run_iterations(1)
            first_iteration_s = time.perf_counter() - t        # the kernels' JIT compile, first time only
            t = time.perf_counter()
            again = solver.Simulation(mesh, mat, dt=1 / 60, fixed=fixed, iterations=1, precision=precision)
            again.begin_step()
            again.run_iterations(1)
            second_setup_s = time.perf_counter() - t           # same mesh and settings: nothing to build
            del again
            sec, k = seconds_per_call(sim.run_iterations, args.min_seconds)
            probe = MemoryProbe(sim)
            probe_sec, _ = seconds_per_call(probe.iterate, args.min_seconds)
            n_free, n_entries = sim.topology.n_slots, sim.topology.n_entries
            flops = FLOPS_PER_ENTRY * n_entries + FLOPS_PER_VERTEX * n_free
            row = dict(tets=mesh.n_tets, vertices=mesh.n_vertices, cells="x".join(map(str, cells)),
                       precision=precision, threads=args.threads, n_colors=sim.n_colors,
                       ns_per_tet_iter=sec / mesh.n_tets * 1e9, ms_per_iter=sec * 1e3, iterations_timed=k,
                       coloring_s=coloring_s, setup_s=setup_s, first_iteration_s=first_iteration_s,
                       second_setup_s=second_setup_s,
                       probe_ns_per_tet_iter=probe_sec / mesh.n_tets * 1e9,
                       arith_floor_ns_per_tet_iter=flops / rates[precision] / mesh.n_tets * 1e9,
                       flop_rate=rates[precision], flops_per_tet=flops / mesh.n_tets,
                       bytes_per_tet=_bytes_per_tet(sim, precision))
            if args.extras and precision == "float64":
                x0, y = sim.positions, sim.y
                nv = NumpyVBD(sim)
                np_sec, _ = seconds_per_call(lambda kk: nv.sweep(x0, y, kk), args.min_seconds, repeats=1)
                row["numpy_ns_per_tet_iter"] = np_sec / mesh.n_tets * 1e9
                row["numpy_speedup"] = np_sec / sec
                if mesh.n_tets <= args.newton_max_tets:
                    sim.end_step()
                    problem = sim.step_problem()
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore")
                        t = time.perf_counter()
                        solver.newton_solve(problem, problem.y_with_constraints(), max_iterations=1)
                        newton_s = time.perf_counter() - t
                        fast_newton_s = median_seconds(lambda: solver.fast_newton_solve(
                            problem, problem.y_with_constraints(), max_iterations=1), repeats=3)
                    row["newton_iter_s"] = newton_s
                    row["newton_ns_per_tet"] = newton_s / mesh.n_tets * 1e9
                    row["fast_newton_iter_s"] = fast_newton_s
                    row["fast_newton_ns_per_tet"] = fast_newton_s / mesh.n_tets * 1e9
            rows.append(row)
            print(json.dumps(row), file=sys.stderr, flush=True)
            del sim
    print("RESULT " + json.dumps(rows), flush=True)


def median_seconds(run, repeats):
    """Median wall time of run() over `repeats` calls after one untimed call (compiles, builds caches)."""
    run()
    samples = []
    for _ in range(repeats):
        t = time.perf_counter()
        run()
        samples.append(time.perf_counter() - t)
    return float(np.median(samples))


def _bytes_per_tet(sim, precision):
    """Bytes one sweep streams per tet: the adjacency entries (3 int32 + 6 floats) and per vertex
    x, y, mass, slot index and offsets (neighbour positions are gathered and mostly cached)."""
    f = 8 if precision == "float64" else 4
    entries, slots = sim.topology.n_entries, sim.topology.n_slots
    return (entries * (12 + 6 * f) + slots * (2 * 3 * f + 3 * f + f + 4 + 4)) / sim.mesh.n_tets


def fit_exponent(tets, seconds):
    """Slope of log(time per iteration) against log(tets); empty (no fit) with fewer than two mesh sizes."""
    if len(set(tets)) < 2:
        return ""
    return float(np.polyfit(np.log(tets), np.log(seconds), 1)[0])


def main(argv=None):
    p = parser(__doc__.split("\n")[0], "benchmarks/results/throughput",
               quick=f"meshes of {' and '.join(f'{6 * np.prod(c):,}' for c in QUICK_SIZES)} tets")
    p.add_argument("--threads", type=positive(int), nargs="+", default=[1, 2], help="CPU thread counts, one worker each")
    p.add_argument("--min-seconds", type=positive(float), default=0.6, quick=0.03,
                   help="timing length of each measurement")
    p.add_argument("--newton-max-tets", type=positive(int), default=40_000,
                   help="largest mesh for the Newton iteration (sparse direct solve)")
    p.add_argument("--max-tets", type=positive(int), default=2_000_000, help="skip meshes larger than this")
    p.add_argument("--worker", action="store_true", help=argparse_hidden())
    p.add_argument("--extras", action="store_true", help=argparse_hidden())
    p.add_argument("--sizes", default=None, help=argparse_hidden())
    args = p.parse_args(argv)
    if args.worker:
        args.threads = args.threads[0]
        return worker(args)

    candidates = QUICK_SIZES if args.quick else FULL_SIZES
    sizes = [c for c in candidates if 6 * np.prod(c) <= args.max_tets]
    if not sizes:
        p.error(f"--max-tets {args.max_tets} leaves no mesh: the smallest has {6 * np.prod(candidates[0]):,} tets")
    output_folder(args, OUTPUTS)
    rows = []
    bar = progress(total=len(sizes) * 2 * len(args.threads), desc="throughput", disable=args.no_progress)
    for threads in args.threads:
        cmd = [sys.executable, "-m", "benchmarks.throughput", "--worker", "--threads", str(threads),
               "--sizes", json.dumps(sizes), "--min-seconds", str(args.min_seconds),
               "--newton-max-tets", str(args.newton_max_tets)]
        if threads == max(args.threads):
            cmd.append("--extras")
        proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        for line in proc.stderr:
            if line.startswith("{"):
                r = json.loads(line)
                bar.set_postfix_str(f"{r['tets']} tets {r['precision']} {threads} thr")
                bar.update(1)
        out, _ = proc.communicate()
        if proc.returncode != 0:
            raise RuntimeError(f"throughput worker failed ({' '.join(cmd)})")
        rows += json.loads(out.split("RESULT ", 1)[1])
    bar.close()
    for r in rows:
        r.setdefault("numpy_ns_per_tet_iter", "")
    fits = scaling_fits(rows, args.threads)
    write_csv(os.path.join(args.out, "throughput.csv"), rows, COLUMNS + ["flop_rate", "flops_per_tet",
                                                                       "bytes_per_tet"])
    write_csv(os.path.join(args.out, "scaling_fit.csv"), fits)
    plot(rows, os.path.join(args.out, "throughput.png"))
    text = report(rows, fits)
    with open(os.path.join(args.out, "summary.md"), "w") as fh:
        fh.write(f"Produced by {provenance()}.\n\n{text}\n")
    print(text)
    print_written(args, OUTPUTS)
    return rows, fits


def scaling_fits(rows, thread_counts):
    """Growth exponents of time per iteration with mesh size: VBD per precision and thread count over all
    sizes and over the meshes of 10k tets or more (empty with fewer than two of those), numpy VBD and the
    Newton iterations over all sizes."""
    fits = []
    for precision in ("float64", "float32"):
        for threads in thread_counts:
            rs = [r for r in rows if r["precision"] == precision and r["threads"] == threads]
            big = [r for r in rs if r["tets"] >= 10_000]
            fits.append(dict(series=f"VBD {precision} {threads} thread(s)",
                             exponent_all=fit_exponent([r["tets"] for r in rs], [r["ms_per_iter"] for r in rs]),
                             exponent_10k_up=fit_exponent([r["tets"] for r in big], [r["ms_per_iter"] for r in big])))
    np_rows = [r for r in rows if r.get("numpy_ns_per_tet_iter") not in ("", None)]
    if len(np_rows) > 1:
        fits.append(dict(series="numpy VBD", exponent_all=fit_exponent(
            [r["tets"] for r in np_rows], [r["numpy_ns_per_tet_iter"] * r["tets"] for r in np_rows])))
    nt_rows = [r for r in rows if r.get("newton_iter_s") not in ("", None)]
    if len(nt_rows) > 1:
        fits.append(dict(series="Newton iteration", exponent_all=fit_exponent(
            [r["tets"] for r in nt_rows], [r["newton_iter_s"] for r in nt_rows])))
        fits.append(dict(series="fast Newton iteration", exponent_all=fit_exponent(
            [r["tets"] for r in nt_rows], [r["fast_newton_iter_s"] for r in nt_rows])))
    return fits


def argparse_hidden():
    import argparse
    return argparse.SUPPRESS


def report(rows, fits):
    cols = ["tets", "precision", "threads", "n_colors", "ns_per_tet_iter", "ms_per_iter",
            "probe_ns_per_tet_iter", "arith_floor_ns_per_tet_iter", "coloring_s", "setup_s", "first_iteration_s",
            "second_setup_s", "numpy_ns_per_tet_iter", "numpy_speedup", "newton_iter_s", "fast_newton_iter_s"]
    fmt = {"ns_per_tet_iter": lambda v: f"{v:.1f}", "probe_ns_per_tet_iter": lambda v: f"{v:.1f}",
           "arith_floor_ns_per_tet_iter": lambda v: f"{v:.1f}", "numpy_ns_per_tet_iter": lambda v: f"{v:.0f}",
           "numpy_speedup": lambda v: f"{v:.0f}x"}
    ordered = sorted(rows, key=lambda r: (r["precision"] != "float64", r["threads"], r["tets"]))
    parts = [table(ordered, cols, "ns per tet per VBD iteration (probe = memory-read floor, arith = "
                   "arithmetic floor; numpy, Newton (numpy) and fast Newton (Taichi) with 2 threads, float64)", fmt),
             table(fits, ["series", "exponent_all", "exponent_10k_up"],
                   "Fitted growth exponent of time per iteration with mesh size (1 = linear)")]
    return "\n\n".join(parts)


def plot(rows, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    for precision, ls in (("float64", "-"), ("float32", "--")):
        for threads in sorted({r["threads"] for r in rows}):
            rs = sorted([r for r in rows if r["precision"] == precision and r["threads"] == threads],
                        key=lambda r: r["tets"])
            t = [r["tets"] for r in rs]
            axes[0].loglog(t, [r["ns_per_tet_iter"] for r in rs], ls, marker="o",
                           label=f"VBD {precision}, {threads} thread(s)")
            axes[1].loglog(t, [r["ms_per_iter"] for r in rs], ls, marker="o",
                           label=f"VBD {precision}, {threads} thread(s)")
            if precision == "float64" and threads == max(r["threads"] for r in rows):
                axes[0].loglog(t, [r["probe_ns_per_tet_iter"] for r in rs], ":", color="grey",
                               label="memory-read probe (2 thr, f64)")
                axes[0].loglog(t, [r["arith_floor_ns_per_tet_iter"] for r in rs], "-.", color="grey",
                               label="arithmetic floor (2 thr, f64)")
    nr = sorted([r for r in rows if r.get("numpy_ns_per_tet_iter") not in ("", None)], key=lambda r: r["tets"])
    if nr:
        axes[0].loglog([r["tets"] for r in nr], [r["numpy_ns_per_tet_iter"] for r in nr], color="tab:orange",
                       marker="s", label="numpy VBD")
        axes[1].loglog([r["tets"] for r in nr], [r["numpy_ns_per_tet_iter"] * r["tets"] * 1e-6 for r in nr],
                       color="tab:orange", marker="s", label="numpy VBD")
    tr = sorted([r for r in rows if r.get("newton_iter_s") not in ("", None)], key=lambda r: r["tets"])
    if tr:
        axes[0].loglog([r["tets"] for r in tr], [r["newton_ns_per_tet"] for r in tr], color="tab:red",
                       marker="^", label="one numpy Newton iteration")
        axes[1].loglog([r["tets"] for r in tr], [r["newton_iter_s"] * 1e3 for r in tr], color="tab:red",
                       marker="^", label="one numpy Newton iteration")
        axes[0].loglog([r["tets"] for r in tr], [r["fast_newton_ns_per_tet"] for r in tr], color="tab:purple",
                       marker="v", label="one fast Newton iteration")
        axes[1].loglog([r["tets"] for r in tr], [r["fast_newton_iter_s"] * 1e3 for r in tr], color="tab:purple",
                       marker="v", label="one fast Newton iteration")
    axes[0].set_ylabel("ns per tet per iteration")
    axes[1].set_ylabel("ms per iteration")
    for ax in axes:
        ax.set_xlabel("tets")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].axhline(50, color="k", lw=0.8, alpha=0.5)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


if __name__ == "__main__":
    main()
