"""Two-level VBD against plain VBD and direct Newton: time, cycles and sweeps to a relative error.

One implicit Euler step of the pinned cantilever bar (1 x 0.1 x 0.1 m, cells (10n, n, n), 6 tets per
cell, nu = 0.3, rho = 1000 kg/m^3, h = 1/60 s, gravity -9.81 z, the x = 0 face fixed), from rest and
from a moving state (after `--frames` two-level steps of falling). Error: ||x - x*|| / ||x* - x_n||
against the converged global Newton solution x* (`solver.fast_newton_solve`, the Taichi Newton with
CHOLMOD, tolerance 1e-10; above `--newton-max-tets` the two-level method run to `--reference-cycles`
cycles stands in for it, and the CSV says so). Every curve is run `--repeats` times; times are the
medians, per checkpoint. The Newton time is that of one converged `fast_newton_solve` from y, warm (a
second call: the first orders and analyses the sparse pattern), its wall time, not a median.

    python -m benchmarks.multilevel --out benchmarks/results/multilevel               # a few minutes
    python -m benchmarks.multilevel --quick --out /tmp/multilevel                      # seconds
"""
import os
import sys
import time

import numpy as np

from benchmarks.common import (init_taichi, nan_as, output_folder, parser, positive, print_written, progress,
                               provenance, table, time_to_reach, write_csv)

FILES = ("multilevel.csv", "multilevel_summary.csv", "multilevel.png", "summary.md")
THRESHOLDS = (1e-2, 1e-4)
KEPT = "two-level VBD, kept H_c"


def prepare(sim, state, frames, coarsening):
    """Put `sim` into `state`; returns (x_n, v_n)."""
    from solver.newton.multilevel import TwoLevelVBD

    sim.reset()
    if state == "moving":
        mover = TwoLevelVBD(sim, coarsening=coarsening, cycles=5)
        mover.step(frames)
    elif state != "rest":
        raise ValueError(state)
    return sim.positions, sim.velocities


def load(sim, x_n, v_n):
    sim.reset()
    sim.set_positions(x_n)
    sim.set_velocities(v_n)


def vbd_curve(sim, x_n, v_n, x_star, checkpoints):
    """[(sweeps, seconds, error)] of plain VBD; seconds exclude the error evaluation."""
    import solver

    load(sim, x_n, v_n)
    sim.begin_step()
    out, done, seconds = [], 0, 0.0
    for k in checkpoints:
        start = time.perf_counter()
        sim.run_iterations(k - done)
        seconds += time.perf_counter() - start
        done = k
        out.append((k, k, seconds, solver.relative_error(sim.positions, x_star, x_n)))
    sim.end_step()
    return out


def two_level_curve(ml, x_n, v_n, x_star, cycles, stop_error=1e-9):
    """[(cycles, sweeps, seconds, error)] of two-level VBD (seconds include begin_step and the
    coarse assembly, not the error evaluation)."""
    import solver

    sim = ml.sim
    load(sim, x_n, v_n)
    start = time.perf_counter()
    ml.begin_step()
    seconds = time.perf_counter() - start
    out = [(0, 0, seconds, solver.relative_error(sim.positions, x_star, x_n))]
    for c in range(1, cycles + 1):
        start = time.perf_counter()
        ml.run_cycles(1)
        seconds += time.perf_counter() - start
        out.append((c, ml.history[-1].sweeps, seconds, solver.relative_error(sim.positions, x_star, x_n)))
        if out[-1][3] < stop_error:
            break
    ml.end_step()
    return out


def median_curve(runs):
    """Median seconds per checkpoint over repeated runs (errors are deterministic up to round-off)."""
    n = min(len(r) for r in runs)
    return [(runs[0][i][0], runs[0][i][1], float(np.median([r[i][2] for r in runs])), runs[0][i][3])
            for i in range(n)]


def first_reaching(curve, threshold):
    """(count, sweeps, seconds) at the first checkpoint with error <= threshold, NaNs if never."""
    for count, sweeps, seconds, err in curve:
        if err <= threshold:
            return count, sweeps, seconds
    return float("nan"), float("nan"), float("nan")


def main(argv=None):
    p = parser(__doc__.split("\n")[0], "benchmarks/results/multilevel")
    p.add_argument("--sizes", type=positive(int), nargs="+", default=[4, 8, 16], quick=[2],
                   help="bar resolutions n: cells (10n, n, n), 60 n^3 tets")
    p.add_argument("--moduli", type=positive(float), nargs="+", default=[1e6, 1e4], help="Young's moduli in Pa")
    p.add_argument("--states", nargs="+", default=["rest", "moving"], choices=["rest", "moving"],
                   help="starting states of the step: at rest, or moving after --frames steps of falling")
    p.add_argument("--coarsening", type=positive(int), default=2, help="cage cell size in fine cells per axis")
    p.add_argument("--cycles", type=positive(int), default=25, quick=12, help="two-level cycles per curve")
    p.add_argument("--max-sweeps", type=positive(int), default=3000, quick=300, help="plain VBD sweeps per curve")
    p.add_argument("--frames", type=positive(int), default=10, quick=2,
                   help="steps of falling before the 'moving' step")
    p.add_argument("--repeats", type=positive(int), default=3, quick=1, help="runs per curve; times are medians")
    p.add_argument("--newton-max-tets", type=positive(int), default=250_000,
                   help="largest mesh with a direct Newton reference; above, two-level run to convergence")
    p.add_argument("--reference-cycles", type=positive(int), default=40,
                   help="two-level cycles of the stand-in reference")
    args = p.parse_args(argv)
    output_folder(args, FILES)

    init_taichi()
    import solver
    from solver.method import wave_cells
    from solver.newton.multilevel import CoarseRefresh, TwoLevelVBD

    os.makedirs(args.out, exist_ok=True)
    checkpoints = [k for k in (1, 2, 3, 5, 7, 10, 15, 20, 30, 50, 70, 100, 150, 200, 300, 500, 700, 1000, 1500,
                               2000, 3000, 5000, 7000, 10000) if k <= args.max_sweeps]
    curves, summary = [], []
    cases = [(n, E, s) for n in args.sizes for E in args.moduli for s in args.states]
    for n, E, state in progress(cases, desc="cases", disable=args.no_progress):
        mesh = solver.box_mesh(size=(1.0, 0.1, 0.1), cells=(10 * n, n, n))
        sim = solver.Simulation(mesh, solver.Material(E, 0.3, 1000.0), dt=1 / 60,
                                fixed=mesh.vertices[:, 0] < 1e-9, iterations=1)
        ml = TwoLevelVBD(sim, coarsening=args.coarsening)
        x_n, v_n = prepare(sim, state, args.frames, args.coarsening)
        load(sim, x_n, v_n)
        problem = sim.step_problem()
        newton_seconds = float("nan")
        if mesh.n_tets <= args.newton_max_tets:
            solver.fast_newton_solve(problem, problem.y_with_constraints())
            start = time.perf_counter()
            x_star = solver.fast_newton_solve(problem, problem.y_with_constraints()).x
            newton_seconds = time.perf_counter() - start
            reference = "newton"
        else:
            load(sim, x_n, v_n)
            ml.begin_step()
            ml.run_cycles(args.reference_cycles)
            x_star = sim.positions
            ml.end_step()
            reference = f"two-level {args.reference_cycles} cycles"
        base = dict(E=E, tets=mesh.n_tets, newton_seconds=newton_seconds, N_c=wave_cells(mesh, sim.material, sim.dt), state=state,
                    reference=reference,
                    cage_cells="x".join(str(c) for c in ml.prolongation.cage_cells))
        kept = TwoLevelVBD(sim, coarsening=args.coarsening, refresh=CoarseRefresh.KEEP)
        vbd_curve(sim, x_n, v_n, x_star, checkpoints[:1])          # warm-up: compile every kernel
        two_level_curve(ml, x_n, v_n, x_star, 1)
        two_level_curve(kept, x_n, v_n, x_star, 1)                  # factorises H_c, kept from now on
        methods = {
            "VBD": median_curve([vbd_curve(sim, x_n, v_n, x_star, checkpoints) for _ in range(args.repeats)]),
            "two-level VBD": median_curve([two_level_curve(ml, x_n, v_n, x_star, args.cycles)
                                           for _ in range(args.repeats)]),
            KEPT: median_curve([two_level_curve(kept, x_n, v_n, x_star, args.cycles) for _ in range(args.repeats)]),
        }
        for method, curve in methods.items():
            for count, sweeps, seconds, err in curve:
                curves.append(dict(base, method=method, count=count, sweeps=sweeps, seconds=seconds, error=err))
            row = dict(base, method=method, final_error=curve[-1][3])
            for t in THRESHOLDS:
                count, sweeps, seconds = first_reaching(curve, t)
                row[f"count_to_{t:g}"] = count
                row[f"sweeps_to_{t:g}"] = sweeps
                # VBD: interpolated between its sparse checkpoints; two-level: the end of the first
                # cycle that gets there (its coarse step is not spread evenly over a cycle)
                row[f"seconds_to_{t:g}"] = (time_to_reach([c[2] for c in curve], [c[3] for c in curve], t)
                                            if method == "VBD" else seconds)
            summary.append(row)
    write_csv(os.path.join(args.out, FILES[0]), curves)
    write_csv(os.path.join(args.out, FILES[1]), summary)
    plot(curves, os.path.join(args.out, FILES[2]))
    text = "\n".join([
        provenance(argv), "",
        "The machine is shared (2 cores, several sessions): times are noisy; compare ratios.", "",
        report(summary), "", f"![error against time and sweeps]({FILES[2]})", ""])
    with open(os.path.join(args.out, FILES[3]), "w") as fh:
        fh.write(text)
    print(text)
    print_written(args, FILES)
    return 0


def report(summary):
    """The summary table: "not reached" where a method never got to a threshold, "-" where no direct Newton
    reference was run (above --newton-max-tets)."""
    reached = [f"{what}_to_{t:g}" for t in THRESHOLDS for what in ("count", "sweeps", "seconds")]
    return table(summary, ["E", "tets", "N_c", "state", "method", "count_to_0.01", "seconds_to_0.01",
                           "count_to_0.0001", "sweeps_to_0.0001", "seconds_to_0.0001", "final_error", "newton_seconds",
                           "reference"],
                 title="count: cycles (two-level) or sweeps (VBD); kept H_c: the coarse factorisation of an "
                       "earlier step of the same state is reused, so its time leaves out the coarse assembly",
                 fmt=dict({c: nan_as("not reached") for c in reached}, newton_seconds=nan_as("-")))


def plot(curves, path):
    """Error against seconds (top) and against fine VBD sweeps (bottom), one column per (E, state);
    colour: mesh size; dashed: plain VBD, solid: two-level VBD, dotted: with the kept coarse factorisation;
    dotted vertical: direct Newton's time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = sorted({(r["E"], r["state"]) for r in curves}, key=lambda k: (-k[0], k[1]))
    sizes = sorted({r["tets"] for r in curves})
    fig, axes = plt.subplots(2, len(keys), figsize=(4.0 * len(keys), 6.4), squeeze=False)
    for col, (E, state) in enumerate(keys):
        for i, tets in enumerate(sizes):
            rgb = plt.cm.viridis(i / max(1, len(sizes) - 1) * 0.85)
            for method, style in (("VBD", "--"), ("two-level VBD", "-"), (KEPT, ":")):
                rows = [r for r in curves if r["E"] == E and r["state"] == state and r["tets"] == tets
                        and r["method"] == method and r["sweeps"] > 0]
                if not rows:
                    continue
                label = f"{method}, {tets} tets"
                errors = [max(r["error"], 1e-12) for r in rows]
                axes[0][col].loglog([r["seconds"] for r in rows], errors, style, color=rgb, label=label)
                axes[1][col].loglog([r["sweeps"] for r in rows], errors, style, color=rgb, label=label)
                if np.isfinite(rows[0]["newton_seconds"]):
                    axes[0][col].axvline(rows[0]["newton_seconds"], color=rgb, ls=":", lw=1)
        for row, xlabel in ((0, "seconds (dotted: direct Newton)"), (1, "fine VBD sweeps")):
            ax = axes[row][col]
            ax.axhline(1e-4, color="grey", lw=0.5)
            ax.set_xlabel(xlabel)
            ax.set_ylabel("relative error")
        axes[0][col].set_title(f"E = {E:g} Pa, from {state}")
    axes[1][0].legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
