"""Speed of the Taichi global solvers against the numpy Newton reference (`solver.newton_solve`).

Three measurements on the pinned cantilever (nu = 0.3, rho = 1000 kg/m^3, h = 1/60 s, gravity -9.81 z,
E = 1e6 Pa; the 1,920-tet bar is the stiffness sweep's 0.5 x 0.1 x 0.1 m bar, the others 1 x 0.1 x 0.1 m):

1. a converged step (from y to tolerance 1e-10), warm (after a first call): `newton_solve` against
   the fast projected Newton (`solver.newton.direct`) with each sparse solver that is installed (the
   summary names those that are not: CHOLMOD and cholespy come with pip install -r requirements-cholmod.txt);
2. one Newton iteration (assembly, solve, line search) on the large bar, same methods;
3. time and iterations to relative error ||x - x*|| / ||x* - x_n|| <= 1e-4 (and 1e-6) of the direct
   Newton (with the fastest sparse solver installed, CHOLMOD or else QDLDL, and with SuperLU) and of
   Newton-PCG with each preconditioner (`solver.newton.pcg`), from rest and from a stretched state,
   where x* is the direct Newton solution to tolerance 1e-12.

Times are medians of --repeats runs in one process; on a shared machine they are noisy.

    python -m benchmarks.newton_speed --out benchmarks/results/newton_speed
    python -m benchmarks.newton_speed --quick --out /tmp/newton_speed
"""
import os
import sys
import time
import warnings

import numpy as np

from benchmarks.common import (format_seconds, init_taichi, nan_as, output_folder, parser, positive, print_written,
                               provenance, table, time_to_reach, write_csv)

FILES = ("newton_speed.csv", "pcg_curves.csv", "summary.md", "pcg.png")
THRESHOLDS = (1e-2, 1e-4, 1e-6)


def bar_problem(size, cells, youngs_modulus=1e6, state="rest"):
    """(problem, x_n): one implicit Euler step of the pinned bar from `state` ("rest" or "stretched":
    free vertices at 1.5x their rest x, at rest)."""
    import solver

    mesh = solver.box_mesh(size=size, cells=cells)
    fixed = mesh.vertices[:, 0] < 1e-9
    sim = solver.Simulation(mesh, solver.Material(youngs_modulus, 0.3, 1000.0), dt=1 / 60, fixed=fixed,
                            iterations=1)
    if state == "stretched":
        x = mesh.vertices.copy()
        x[~fixed, 0] *= 1.5
        sim.set_positions(x)
    elif state != "rest":
        raise ValueError(f"unknown state {state!r}")
    return sim.step_problem(), sim.positions


def solvers():
    """name -> function(problem) returning an object with .solve(problem, x0, tolerance, max_iterations,
    keep_iterates, time_budget): the direct Newton with each installed sparse solver (`missing_solvers()`
    says which are not) and Newton-PCG."""
    from solver.newton.direct import DirectSolver, LinearSolver, global_newton
    from solver.newton.pcg import Preconditioner, newton_pcg

    out = {f"Newton ({s.value})": (lambda p, s=s: global_newton(p.tets, p.free, s)) for s in LinearSolver
           if s is not LinearSolver.AUTO and DirectSolver.installed(s)}
    for pre in Preconditioner:
        out[f"Newton-PCG ({pre.value})"] = lambda p, pre=pre: newton_pcg(p.tets, p.free, pre)
    return out


def missing_solvers():
    """A sentence naming the sparse solvers that are not installed, so not measured, and how to install
    them; empty when all are. (DirectSolver would replace them by SuperLU, under their names.)"""
    from solver.newton.direct import DirectSolver, LinearSolver

    missing = [s for s in LinearSolver if not DirectSolver.installed(s)]
    if not missing:
        return ""
    files = sorted({"requirements.txt" if s is LinearSolver.QDLDL else "requirements-cholmod.txt" for s in missing})
    return (f"Skipped, not installed: {', '.join(f'Newton ({s.value})' for s in missing)}; to measure them: "
            f"pip install {' '.join(f'-r {f}' for f in files)}.")


def time_error_points(method, problem, x_star, x_n, budget, tolerance=1e-12, max_iterations=100):
    """Run `method` (an object from `solvers()`) on `problem` from y for at most `budget` seconds;
    returns [(seconds, relative error, Newton iterations, CG iterations so far)], one per iterate,
    starting with (0, error of y, 0, 0). The solve is run twice and the second (warm) run kept."""
    import solver

    x0 = problem.y_with_constraints()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        method.solve(problem, x0, tolerance, 1)
        result = method.solve(problem, x0, tolerance, max_iterations, keep_iterates=True, time_budget=budget)
    cg = np.cumsum(getattr(result, "cg_iterations", [0] * result.iterations))
    points = [(0.0, solver.relative_error(x0, x_star, x_n), 0, 0)]
    for record, x, k in zip(result.history[1:], result.iterates, cg):
        points.append((record.seconds, solver.relative_error(x, x_star, x_n), record.iteration, int(k)))
    return points


def pareto_curve(case, name, budget):
    """Rows (iteration, seconds, error, energy gap, measured seconds) of method `name` (a key of
    `solvers()`) on a `benchmarks.pareto.Case`, in the format of pareto's `add(...)`; iteration counts
    Newton iterations, seconds are the warm solve's wall time."""
    problem = case.problem
    method = solvers()[name](problem)
    x0 = problem.y_with_constraints()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        method.solve(problem, x0, 1e-12, 1)
        result = method.solve(problem, x0, 1e-12, 100, keep_iterates=True, time_budget=budget)
    rows = [(0, 0.0) + case.measure(x0) + (0.0,)]
    for record, x in zip(result.history[1:], result.iterates):
        rows.append((record.iteration, record.seconds) + case.measure(x) + (record.seconds,))
    return rows


def median_seconds(run, repeats):
    """Median wall time of run() over `repeats` calls, after one warm-up call."""
    run()
    samples = []
    for _ in range(repeats):
        start = time.perf_counter()
        run()
        samples.append(time.perf_counter() - start)
    return float(np.median(samples))


def measure_steps(rows, label, size, cells, repeats, max_iterations, names):
    """Section 1 / 2: newton_solve against the fast solvers for a converged step or one iteration."""
    import solver

    problem, _ = bar_problem(size, cells)
    x0 = problem.y_with_constraints()
    methods = solvers()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        reference = median_seconds(lambda: solver.newton_solve(problem, x0, 1e-10, max_iterations), repeats)
        rows.append(dict(section=label, tets=len(problem.tets), method="newton_solve (numpy)", seconds=reference,
                         speedup=1.0))
        for name in names:
            m = methods[name](problem)
            seconds = median_seconds(lambda: m.solve(problem, x0, 1e-10, max_iterations), repeats)
            rows.append(dict(section=label, tets=len(problem.tets), method=name, seconds=seconds,
                             speedup=reference / seconds))


def measure_curves(curve_rows, rows, size, cells, states, budget, names):
    """Section 3: time and iterations to reach each error threshold."""
    from solver.newton.direct import fast_newton_solve

    methods = solvers()
    for state in states:
        problem, x_n = bar_problem(size, cells, state=state)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            x_star = fast_newton_solve(problem, problem.y_with_constraints(), tolerance=1e-12).x
        case = f"{len(problem.tets)} tets, {state}"
        for name in names:
            points = time_error_points(methods[name](problem), problem, x_star, x_n, budget)
            for seconds, error, newton_it, cg_it in points:
                curve_rows.append(dict(case=case, method=name, seconds=seconds, error=error,
                                       newton_iterations=newton_it, cg_iterations=cg_it))
            times, errors = [p[0] for p in points], [p[1] for p in points]
            row = dict(section="time_to_error", case=case, tets=len(problem.tets), method=name,
                       final_error=errors[-1])
            for t in THRESHOLDS:
                row[f"t_{t:.0e}"] = time_to_reach(times, errors, t)
                hit = [p for p in points if p[1] <= t]
                row[f"newton_it_{t:.0e}"] = hit[0][2] if hit else float("nan")
                row[f"cg_it_{t:.0e}"] = hit[0][3] if hit else float("nan")
            rows.append(row)


def plot(curve_rows, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cases = list(dict.fromkeys(r["case"] for r in curve_rows))
    fig, axes = plt.subplots(1, len(cases), figsize=(5 * len(cases), 4), squeeze=False)
    for ax, case in zip(axes[0], cases):
        for method in dict.fromkeys(r["method"] for r in curve_rows if r["case"] == case):
            rs = [r for r in curve_rows if r["case"] == case and r["method"] == method and r["seconds"] > 0]
            ax.loglog([r["seconds"] for r in rs], np.clip([r["error"] for r in rs], 1e-16, None), marker="o",
                      ms=3, label=method)
        ax.axhline(1e-4, color="grey", lw=0.8, ls=":")
        ax.set_title(case, fontsize=9)
        ax.set_xlabel("wall time (s)")
        ax.set_ylabel("||x - x*|| / ||x* - x_n||")
        ax.grid(True, alpha=0.3)
    axes[0, 0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def report(rows):
    speed = [r for r in rows if r["section"] in ("converged step", "one iteration")]
    parts = [table(speed, ["section", "tets", "method", "seconds", "speedup"],
                   "Median wall time, and speed-up against newton_solve",
                   {"seconds": format_seconds, "speedup": lambda v: f"{float(v):.3g}x"})]
    curves = [r for r in rows if r["section"] == "time_to_error"]
    cols = ["case", "method"] + [f"t_{t:.0e}" for t in THRESHOLDS[1:]] + ["newton_it_1e-04", "cg_it_1e-04",
                                                                           "final_error"]
    fmt = {f"t_{t:.0e}": format_seconds for t in THRESHOLDS}
    fmt.update({c: nan_as("not reached") for c in ("newton_it_1e-04", "cg_it_1e-04")})
    fmt["final_error"] = lambda v: f"{float(v):.2g}"
    parts.append(table(curves, cols, "Time and iterations to relative error 1e-4 / 1e-6 (x* = direct Newton "
                       "to tolerance 1e-12)", fmt))
    return "\n\n".join(parts)


def main(argv=None):
    p = parser(__doc__.split("\n")[0], "benchmarks/results/newton_speed",
               quick="bars of 240 and 480 tets (not 1,920 to 30,720), from rest only")
    p.add_argument("--repeats", type=positive(int), default=5, quick=1, help="timed runs per measurement (median)")
    p.add_argument("--budget", type=positive(float), default=30.0, quick=5.0,
                   help="seconds per method and case in section 3")
    p.add_argument("--threads", type=positive(int), default=None, help="CPU threads for Taichi (default: all)")
    args = p.parse_args(argv)
    output_folder(args, FILES)
    init_taichi(args.threads)
    every = list(solvers())
    direct = [name for name in every if name.startswith("Newton (")]
    # time to error: the fastest direct solver installed (CHOLMOD, else QDLDL), SuperLU and Newton-PCG
    fastest = next(n for n in ("Newton (cholmod)", "Newton (qdldl)", "Newton (superlu)") if n in direct)
    curve_names = list(dict.fromkeys([fastest, "Newton (superlu)"]))
    curve_names += [n for n in every if n.startswith("Newton-PCG")]
    if args.quick:
        step_bar, iteration_bar = ((0.5, 0.1, 0.1), (10, 2, 2)), ((1.0, 0.1, 0.1), (20, 2, 2))
        curve_bars, states = [((1.0, 0.1, 0.1), (20, 2, 2))], ["rest"]
    else:
        step_bar, iteration_bar = ((0.5, 0.1, 0.1), (20, 4, 4)), ((1.0, 0.1, 0.1), (80, 8, 8))
        curve_bars = [((1.0, 0.1, 0.1), (40, 4, 4)), ((1.0, 0.1, 0.1), (80, 8, 8))]
        states = ["rest", "stretched"]
    os.makedirs(args.out, exist_ok=True)
    rows, curve_rows = [], []
    measure_steps(rows, "converged step", *step_bar, args.repeats, 50, direct)
    measure_steps(rows, "one iteration", *iteration_bar, args.repeats, 1, direct)
    for size, cells in curve_bars:
        measure_curves(curve_rows, rows, size, cells, states, args.budget, curve_names)
    write_csv(os.path.join(args.out, "newton_speed.csv"), rows)
    write_csv(os.path.join(args.out, "pcg_curves.csv"), curve_rows)
    plot(curve_rows, os.path.join(args.out, "pcg.png"))
    text = "\n\n".join(part for part in (report(rows), missing_solvers()) if part)
    with open(os.path.join(args.out, "summary.md"), "w") as fh:
        fh.write(f"Produced by {provenance()}.\n\n{text}\n")
    print(text)
    print_written(args, FILES)
    return 0


if __name__ == "__main__":
    sys.exit(main())
