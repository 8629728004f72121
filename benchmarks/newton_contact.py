"""Newton with contact: what the exact pair Hessians buy where the head_on balls meet.

The Taichi Newton (`GlobalNewton`) solves every step of the `head_on` scene (two soft balls meeting at
1 m/s each, contact radius 1 cm, no gravity) from x_n, as `Simulation.newton_reference()` does: step
tolerance 1e-8 of the body size, at most 100 iterations (the demo's cap with contact). The trajectory is
the scene's VBD one, so both variants solve the same problems. Two variants, solved in turn at every step:

  * exact: the pairs' exact Hessians b'' J J^T + b' d2d/dx2 tried first, the PSD parts b'' J J^T where the
    whole Hessian is not positive definite (the default, `GlobalNewton(exact_pairs=True)`);
  * psd: the PSD parts only (n held fixed, as the VBD vertex blocks).

Near-parallel edges make the distance bend within micrometres (its closest points slide); the PSD blocks
do not see it and the line search backtracks against the bend. Per step: Newton iterations, evaluations
of G (line-search trials included), whether it converged within the cap, wall seconds, the G reached, max_i |dG/dx_i| there (N) and
||x - x_exact|| / ||x_exact - x_n|| against the exact variant's solution; for each linear solver available
(QDLDL always, CHOLMOD with the optional cvxopt).

    python -m benchmarks.newton_contact --out benchmarks/results/newton_contact
    python -m benchmarks.newton_contact --quick --out /tmp/newton_contact
"""
import time
import warnings

import numpy as np

from benchmarks.common import (init_taichi, output_folder, parser, positive, print_written, provenance, table,
                               write_csv)

OUTPUTS = ("newton_contact.csv", "newton_contact.png", "summary.md")
COLUMNS = ["frame", "linear_solver", "pair_hessian", "contacts", "iterations", "evaluations", "converged", "seconds",
           "energy", "max_gradient", "x_vs_exact"]
SUMMARY = ["linear_solver", "pair_hessian", "solves", "iterations", "max_iterations", "evaluations", "capped",
           "seconds", "iterations_vs_psd", "seconds_vs_psd", "max_x_vs_exact"]
TOLERANCE = 1e-8            # relative step tolerance, as Simulation(method="newton") without a tolerance
CAP = 100                   # Newton iterations: the demo's cap with contact (demo.runner.newton_cap)


def linear_solvers(solver):
    """The linear solvers to compare: QDLDL, and CHOLMOD when cvxopt is installed."""
    kinds = [solver.LinearSolver.QDLDL]
    try:
        import cvxopt  # noqa: F401
        kinds.append(solver.LinearSolver.CHOLMOD)
    except ImportError:
        pass
    return kinds


def measure(solver, frames):
    """One row per (frame, linear solver, pair Hessian) over the first `frames` steps of head_on."""
    from demo import scenes
    from demo.runner import PanelSim
    from solver.newton.direct import GlobalNewton

    scene = scenes.get("head_on")
    sim = PanelSim(scene, scene.panels[0]).sim
    problem = sim.step_problem()
    variants = [(kind, exact, GlobalNewton(problem.tets, problem.free, kind, exact_pairs=exact))
                for kind in linear_solvers(solver) for exact in (True, False)]
    rows = []
    for frame in range(frames):
        problem = sim.step_problem()
        x_n = problem.constrained_positions
        for kind, exact, newton in variants:        # each solver's exact variant first
            start = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)        # capped solves are counted, not warned
                result = newton.solve(problem, x_n, TOLERANCE, CAP)
            seconds = time.perf_counter() - start
            if exact:
                x_exact = result.x
            rows.append(dict(frame=frame, linear_solver=kind.value, pair_hessian="exact" if exact else "psd",
                             contacts=sim.contact_count(), iterations=result.iterations,
                             evaluations=result.evaluations, converged=result.converged, seconds=seconds,
                             energy=result.history[-1].energy, max_gradient=result.history[-1].max_gradient,
                             x_vs_exact=solver.relative_error(result.x, x_exact, x_n)))
        sim.step()
    return rows


def summarise(rows):
    """One row per (linear solver, pair Hessian): totals over the solves after the first contact."""
    first = min((r["frame"] for r in rows if r["contacts"] > 0), default=np.inf)
    touching = [r for r in rows if r["frame"] >= first]
    out = []
    for kind in dict.fromkeys(r["linear_solver"] for r in rows):
        group = {h: [r for r in touching if r["linear_solver"] == kind and r["pair_hessian"] == h]
                 for h in ("exact", "psd")}
        totals = {h: dict(solves=len(g), iterations=sum(r["iterations"] for r in g),
                          max_iterations=max((r["iterations"] for r in g), default=0),
                          evaluations=sum(r["evaluations"] for r in g),
                          capped=sum(not r["converged"] for r in g), seconds=sum(r["seconds"] for r in g),
                          max_x_vs_exact=max((r["x_vs_exact"] for r in g if r["converged"]), default=0.0))
                  for h, g in group.items()}
        for h in ("exact", "psd"):
            t = totals[h]
            out.append(dict(linear_solver=kind, pair_hessian=h, **t,
                            iterations_vs_psd=t["iterations"] / max(totals["psd"]["iterations"], 1),
                            seconds_vs_psd=t["seconds"] / totals["psd"]["seconds"]))
    return out


def plot(rows, path):
    """Newton iterations per step, one line per variant."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3.6))
    for kind, (style, marker) in zip(dict.fromkeys(r["linear_solver"] for r in rows), (("-", "o"), (":", "x"))):
        for h, colour in (("exact", "tab:green"), ("psd", "tab:red")):
            g = [r for r in rows if r["linear_solver"] == kind and r["pair_hessian"] == h]
            ax.plot([r["frame"] for r in g], [r["iterations"] for r in g], style, color=colour, marker=marker,
                    markersize=4, label=f"{kind}, {h} pair Hessians")
    ax.axhline(CAP, color="0.6", lw=0.8)
    ax.set_xlabel("step of head_on (1/240 s)")
    ax.set_ylabel("Newton iterations")
    ax.set_title("Newton with contact: exact against PSD pair Hessians")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None):
    p = parser(__doc__.split("\n")[0], "benchmarks/results/newton_contact")
    # --quick: up to the balls' deepest press, steps 18-20
    p.add_argument("--frames", type=positive(int), default=36, quick=22,
                   help="steps of head_on solved by every variant")
    args = p.parse_args(argv)
    out = output_folder(args, OUTPUTS)
    frames = args.frames
    init_taichi()
    import solver

    rows = measure(solver, frames)
    summary = summarise(rows)
    text = table(summary, SUMMARY, title=f"Newton with contact on head_on's first {frames} steps, after the first "
                                         f"contact (float64, CPU)")
    print(text)
    write_csv(f"{out}/newton_contact.csv", rows, COLUMNS)
    plot(rows, f"{out}/newton_contact.png")
    with open(f"{out}/summary.md", "w") as fh:
        fh.write(f"{provenance()}\n\nPer linear solver and pair Hessian, summed over the steps from the first "
                 f"contact on: Newton iterations, the most in one step, evaluations of G, solves stopped by the cap "
                 f"of {CAP} iterations (capped) and wall seconds; *_vs_psd: over the PSD variant's; "
                 f"max_x_vs_exact: the largest ||x - x_exact|| / ||x_exact - x_n|| of a converged solve.\n\n{text}\n")
    print_written(args, OUTPUTS)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
