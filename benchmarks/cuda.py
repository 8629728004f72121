"""The GPU columns: the VBD sweep, contact, and a pile of a million tets, on CUDA.

The CPU's numbers are in benchmarks/results/throughput and benchmarks/results/contact; this runs the same
scenes on the backend --arch names (gpu: CUDA, the default; cpu: the same code on the CPU, which is what
the tests run). Every timing waits for the kernels to finish (`ti.sync()`), since a CUDA launch returns
before its work is done. Three measurements, float64 unless a row says float32:
  * sweep: ns per tet per VBD iteration of benchmarks.throughput's boxes (1,152 to 1,008,000 tets), float64
    and float32, and the seconds of the first iteration (the kernels' compile for that backend);
  * contact: benchmarks.contact's 8 bodies of 3,072 tets set apart (nothing within query_radius), the
    sweep with contact on against contact=None (issue 17's target: at most 1.25x), and one detection
    against one sweep there and with the bodies touching (1.5 mm gaps);
  * pile: k^3 balls (benchmarks.contact's, 114 tets each; k = 21: 9,261 balls and 1.11M tets with the box)
    in layers 2 cm apart inside the fixed open box, friction 0.3, 20 iterations a step, falling for one
    untimed step (the compile) and --steps timed steps of 1/60 s: median seconds of the last half of them,
    full detections and refreshes of the bounds per step, active contacts and the least separation at the
    end, one detection against one sweep.
Each detection row also has the pairs that detection returned, its time per pair and the time per pair at
which it would cost one sweep (benchmarks.contact).

    python -m benchmarks.cuda --out benchmarks/results/cuda           # on a machine with a CUDA GPU
    python -m benchmarks.cuda --quick --arch cpu --out /tmp/cuda      # the same code, small, on the CPU
"""
import os
import subprocess
import time

import numpy as np

from benchmarks.common import (fail, init_taichi, output_folder, parser, positive, print_written, progress,
                               provenance, seconds_per_call, sync, table, write_csv)
from benchmarks.contact import (BALL_RESOLUTION, SOFT, _detect_and_sweep, _detection_columns, measure_apart,
                                measure_touching, pile_scene)
from benchmarks.throughput import FULL_SIZES, QUICK_SIZES

OUTPUTS = ("cuda.csv", "summary.md")
PARTS = ("sweep", "contact", "pile")
COLUMNS = ["measurement", "arch", "precision", "tets", "bodies", "ns_per_tet_iter", "ms_per_iter",
           "first_iteration_s", "contacts", "min_separation_mm", "detections_per_step", "refreshes_per_step",
           "step_ms", "pairs", "detect_ms", "detect_ns_per_pair", "sweep_ms", "break_even_ns_per_pair",
           "detect_per_sweep", "ns_per_tet_iter_none", "ns_per_tet_iter_contact", "contact_per_none"]


def measure_sweep(solver, cells, precision, min_seconds):
    """A box of cells (Kuhn-split cubes, 6 tets each) pinned at x = 0: one VBD iteration."""
    mesh = solver.box_mesh(size=tuple(c / 10 for c in cells), cells=cells)
    sim = solver.Simulation(mesh, solver.Material(1e5, 0.3, 1000.0), dt=1 / 60, fixed=mesh.vertices[:, 0] < 1e-9,
                            iterations=1, precision=precision)
    t = time.perf_counter()
    sim.begin_step()
    sim.run_iterations(1)
    sync()
    first_s = time.perf_counter() - t
    sec, _ = seconds_per_call(sim.run_iterations, min_seconds)
    return dict(measurement="sweep", precision=precision, tets=mesh.n_tets, ns_per_tet_iter=sec / mesh.n_tets * 1e9,
                ms_per_iter=sec * 1e3, first_iteration_s=first_s)


def measure_falling_pile(solver, k, steps, min_seconds):
    """k^3 balls falling into the box for `steps` steps (see the module's docstring)."""
    mesh, n_walls = pile_scene(solver, k, apart=False, balls=BALL_RESOLUTION)
    fixed = np.arange(n_walls)
    sim = solver.Simulation(mesh, solver.Material(**SOFT), dt=1 / 60, fixed=fixed, iterations=20,
                            contact=solver.Contact(stiffness=1e4, radius=0.005, friction=0.3))
    stage = sim._contact_stage
    sim.step()                      # compiles the contact kernels: not timed
    seconds = []
    for i in range(steps):
        if i == steps // 2:
            counters = stage.detections, stage.refreshes
        t = time.perf_counter()
        sim.step()
        sync()
        seconds.append(time.perf_counter() - t)
    timed = steps - steps // 2
    return dict(measurement="falling pile", precision="float64", tets=mesh.n_tets, bodies=k ** 3,
                contacts=sim.contact_count(), min_separation_mm=sim.min_separation() * 1e3,
                detections_per_step=(stage.detections - counters[0]) / timed,
                refreshes_per_step=(stage.refreshes - counters[1]) / timed,
                step_ms=float(np.median(seconds[steps // 2:])) * 1e3,
                **_detection_columns(*_detect_and_sweep(solver, sim, mesh, fixed, min_seconds)))


def measure_all(solver, args, jobs, out, title, gpu, bar):
    """Run the jobs, writing the CSV and summary after each (see main)."""
    rows = []
    for done, (kind, cells, precision) in enumerate(bar, start=1):
        if kind == "sweep":
            rows.append(measure_sweep(solver, cells, precision, args.min_seconds))
        elif kind == "contact":
            for measure in (measure_apart, measure_touching):
                rows.append(dict(measure(solver, args.cells, args.min_seconds), precision="float64"))
        else:
            rows.append(measure_falling_pile(solver, args.pile, args.steps, args.min_seconds))
        for r in rows:
            r["arch"] = args.arch
        text = table(rows, [c for c in COLUMNS if any(c in r for r in rows)], title=title)
        write_csv(f"{out}/cuda.csv", rows, COLUMNS)     # after every measurement: a GPU lent for minutes
        with open(f"{out}/summary.md", "w") as fh:       # may be taken back before the last one
            so_far = "" if done == len(jobs) else f" (so far: {done} of {len(jobs)} measurements)"
            fh.write(f"{provenance()}{gpu}{so_far}\n\n{text}\n")
    print(text)


def gpu_name() -> str:
    """The GPU's name and memory as nvidia-smi gives them, or "" where it cannot be asked."""
    try:
        return subprocess.run(["nvidia-smi", "--query-gpu=name,memory.total", "--format=csv,noheader"],
                              capture_output=True, text=True, timeout=30).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return ""


def main(argv=None):
    p = parser(__doc__.split("\n")[0], "benchmarks/results/cuda",
               quick=f"boxes of {' and '.join(f'{6 * np.prod(c):,}' for c in QUICK_SIZES)} tets")
    p.add_argument("--arch", choices=["gpu", "cpu"], default="gpu",
                   help="backend: gpu (CUDA; refused where there is none) or cpu")
    p.add_argument("--max-tets", type=positive(int), default=1_100_000, help="skip sweep boxes larger than this")
    p.add_argument("--pile", type=positive(int), default=21, quick=2, help="balls per side of the falling pile")
    p.add_argument("--steps", type=positive(int), default=60, quick=2, help="steps of 1/60 s the pile falls")
    p.add_argument("--cells", type=positive(int), default=8, quick=2,
                   help="cells per side of each of the 8 contact bodies (6 tets per cell; 8: 24,576 tets)")
    p.add_argument("--min-seconds", type=positive(float), default=0.5, quick=0.02, help="least time per timing")
    p.add_argument("--parts", nargs="+", choices=PARTS, default=list(PARTS), help="the measurements to run")
    args = p.parse_args(argv)
    from solver._ti import is_arch_supported, ti

    ti.set_logging_level(ti.ERROR)      # the CUDA probe's own warning: the line below says what happened
    if args.arch == "gpu" and not is_arch_supported(ti.cuda):
        fail("no CUDA GPU on this machine; run it where there is one, or pass --arch cpu")
    candidates = QUICK_SIZES if args.quick else FULL_SIZES
    sizes = [c for c in candidates if 6 * np.prod(c) <= args.max_tets]
    if not sizes and "sweep" in args.parts:
        p.error(f"--max-tets {args.max_tets} leaves no box: the smallest has {6 * np.prod(candidates[0]):,} tets")
    out = output_folder(args, OUTPUTS)
    init_taichi(arch=args.arch)
    import solver

    jobs = [("sweep", cells, precision) for precision in ("float64", "float32") for cells in sizes]
    jobs = [job for job in jobs + [("contact", None, None), ("pile", None, None)] if job[0] in args.parts]
    title = f"VBD on {args.arch} (CUDA)" if args.arch == "gpu" else "VBD on the CPU"
    gpu = f", GPU: {gpu_name() or 'unknown'}" if args.arch == "gpu" else ""
    bar = progress(jobs, desc=f"cuda ({args.arch})", disable=args.no_progress)
    try:
        measure_all(solver, args, jobs, out, title, gpu, bar)
    except KeyboardInterrupt:
        bar.close()
        if not os.path.exists(f"{out}/cuda.csv"):
            fail("interrupted before the first measurement finished; nothing was written")
        fail(f"interrupted: {out}/cuda.csv and summary.md hold the measurements finished before it "
             "(the summary's first line says how many)")
    print_written(args, OUTPUTS)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
