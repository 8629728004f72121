"""Numerical stress: a grid of time steps, stiffnesses, Poisson ratios and violent starting states.

Scene: a free bar 1 x 0.1 x 0.1 m (no pinned vertices), rho = 1000 kg/m^3, zero gravity, float64, no
Chebyshev, VBD with the adaptive initial guess and a fixed budget of --iterations per step.
Grid: dt in {1/1000, 1/240, 1/60, 1/10} s x E in {1e3, 1e4, 1e6, 1e8, 1e10} Pa x nu in {0, 0.3,
0.45, 0.49, 0.499} x start in {rest, noise, inverted, flat, velocity} x two resolutions.
Starting states: rest shape at rest; uniform noise of +-5 cm (half the bar's thickness) on every
coordinate; inverted: the body mirrored x -> -x (every tet inside out, no rotation undoes it);
flat: every vertex squashed onto the plane z = 5 cm (every tet has zero volume); velocity: random
per-vertex velocities of 10 m/s standard deviation.

Checks per cell:
  finite     positions stay finite through --steps steps;
  monotone   G never increases after a colour sweep (each colour's vertex solves are exact
             minimisations of G along that colour, so any rise beyond round-off is a bug);
  recovers   afterwards, in zero gravity with the velocity zeroed each step and a quasi-static
             step h_r = 50 / sqrt(E) s (inertia / element stiffness ~ 1e-3), the body is back at its
             rest shape up to a rigid motion: max |R x + t - X| <= 1 mm after the best rotation R and
             translation t (Kabsch), and every tet positively oriented, within --recovery-rounds x
             --recovery-iterations VBD iterations;
  error      ||x - x*|| / ||x* - x_n|| after the first step's budget, x* from global Newton
             (undefined for the rest state, which does not move in zero gravity: left empty).

By default the coarse mesh (144 tets) runs the whole grid (500 cells) and the fine mesh (1152 tets)
a sub-grid (dt in {1/240, 1/10}, E in {1e4, 1e8}, nu in {0.3, 0.49}, all starts: 40 cells);
--all runs all 1000 cells.

    python -m benchmarks.stability --out benchmarks/results/stability
    python -m benchmarks.stability --quick --out /tmp/stability
"""
import itertools
import math
import os
import time
import warnings

import numpy as np

from benchmarks.common import (init_taichi, nan_as, output_folder, parser, positive, print_written, progress,
                               provenance, table, write_csv)

DTS = (1 / 1000, 1 / 240, 1 / 60, 1 / 10)
MODULI = (1e3, 1e4, 1e6, 1e8, 1e10)
NUS = (0.0, 0.3, 0.45, 0.49, 0.499)
STATES = ("rest", "noise", "inverted", "flat", "velocity")
RESOLUTIONS = {"coarse": (6, 2, 2), "fine": (12, 4, 4)}
OUTPUTS = ("stability.csv", "stability.png", "summary.md")
COLUMNS = ["resolution", "tets", "dt", "E", "nu", "state", "finite", "monotone", "max_rise", "recovers",
           "recovery_iterations", "recovery_max_dev", "recovery_min_J", "newton_recovers", "error", "newton_converged",
           "passed", "seconds"]


def start_state(state, X, free, rng):
    """(x, v) of a starting state; pinned vertices at rest."""
    x, v = X.copy(), np.zeros_like(X)
    free = np.asarray(free, dtype=bool)
    if state == "noise":
        x[free] += rng.uniform(-0.05, 0.05, size=(free.sum(), 3))
    elif state == "inverted":
        x[free, 0] = -X[free, 0]
    elif state == "flat":
        x[free, 2] = 0.05
    elif state == "velocity":
        v[free] = rng.normal(0.0, 10.0, size=(free.sum(), 3))
    elif state != "rest":
        raise ValueError(state)
    return x, v


def newton_or_none(solver, problem, x0, max_iterations):
    """The global Newton solve, or None when it breaks down (see the README: its line search can
    accept a non-finite iterate on extreme cells, and the next Hessian fails)."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            res = solver.newton_solve(problem, x0, tolerance=1e-10, max_iterations=max_iterations)
    except (np.linalg.LinAlgError, ValueError, RuntimeError):
        return None
    return res if np.isfinite(res.x).all() else None


def aligned_deviation(x, X):
    """max_i |R x_i + t - X_i| for the rotation R and translation t that best map x onto X."""
    xc, Xc = x - x.mean(axis=0), X - X.mean(axis=0)
    U, _, Vt = np.linalg.svd(xc.T @ Xc)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = (U @ D @ Vt).T
    return float(np.linalg.norm(xc @ R.T - Xc, axis=1).max())


def min_J(x, mesh):
    import solver.mesh.tetmesh as sm
    return float((sm.signed_volumes(x, mesh.tets) / mesh.rest_volumes()).min())


class Runner:
    """One Simulation per resolution, reused for every cell (material and dt are set per cell)."""

    def __init__(self, cells, iterations, steps, recovery_rounds, recovery_iterations):
        import solver

        self.solver = solver
        self.mesh = solver.box_mesh(size=(1.0, 0.1, 0.1), cells=cells)
        self.sim = solver.Simulation(self.mesh, solver.Material(1e4, 0.3, 1000.0), dt=1 / 60,
                                     gravity=(0.0, 0.0, 0.0), iterations=iterations)
        self.iterations, self.steps = iterations, steps
        self.recovery_rounds, self.recovery_iterations = recovery_rounds, recovery_iterations
        self.sim.step()   # compile
        self.sim.reset()

    def sweep_checked(self, G_scale):
        """One VBD iteration colour by colour; the largest relative rise of G after a colour sweep."""
        sim, rise = self.sim, 0.0
        G = sim.energy()
        for c in range(sim.n_colors):
            sim.solve_color(c)
            G_new = sim.energy()
            if not math.isfinite(G_new):
                return float("inf")
            rise = max(rise, (G_new - G) / G_scale)
            G = G_new
        return rise

    def cell(self, dt, E, nu, state, seed=0):
        solver, sim, mesh = self.solver, self.sim, self.mesh
        t0 = time.perf_counter()
        sim.set_material(solver.Material(E, nu, 1000.0))
        sim.dt = dt
        sim.reset()
        x0, v0 = start_state(state, mesh.vertices, sim.free_mask, np.random.default_rng(seed))
        sim.set_positions(x0)
        sim.set_velocities(v0)
        out = dict(tets=mesh.n_tets, dt=dt, E=E, nu=nu, state=state)
        # Newton reference of the first step.
        problem = sim.step_problem()
        ref = newton_or_none(solver, problem, problem.y_with_constraints(), 100)
        out["newton_converged"] = bool(ref is not None and ref.converged)
        finite, rise = True, 0.0
        for step in range(self.steps):
            sim.begin_step()
            G_scale = max(abs(sim.energy()), 1e-300)
            for _ in range(self.iterations):
                r = self.sweep_checked(G_scale)
                rise = max(rise, r)
                if not math.isfinite(r):
                    finite = False
                    break
            x = sim.positions
            if step == 0:
                moved = np.linalg.norm(ref.x - x0) if ref is not None else 0.0
                out["error"] = (float("inf") if not np.isfinite(x).all() else
                                solver.relative_error(x, ref.x, x0) if moved > 1e-9 else float("nan"))
                if ref is None or not ref.converged:
                    out["error"] = float("nan")     # no trustworthy reference
            sim.end_step()
            if not finite or not np.isfinite(x).all():
                finite = False
                break
        out["finite"] = finite
        out["max_rise"] = rise
        out["monotone"] = bool(finite and rise <= 1e-10)
        out.update(self.recover() if finite else dict(recovers=False, recovery_iterations=0,
                                                      recovery_max_dev=float("inf"), recovery_min_J=float("nan")))
        sim.dt = dt
        out["passed"] = bool(out["finite"] and out["monotone"] and out["recovers"])
        out["seconds"] = time.perf_counter() - t0
        return out

    def recover(self):
        sim, X = self.sim, self.mesh.vertices
        sim.dt = 50.0 / math.sqrt(sim.material.youngs_modulus)
        zero = np.zeros_like(X)
        dev, J, its = float("inf"), float("nan"), 0
        for _ in range(self.recovery_rounds):
            sim.set_velocities(zero)
            sim.begin_step()
            sim.run_iterations(self.recovery_iterations)
            sim.end_step()
            its += self.recovery_iterations
            x = sim.positions
            if not np.isfinite(x).all():
                break
            dev, J = aligned_deviation(x, X), min_J(x, self.mesh)
            if dev <= 1e-3 and J > 0:
                break
        ok = bool(dev <= 1e-3 and J > 0)
        out = dict(recovers=ok, recovery_iterations=its, recovery_max_dev=dev, recovery_min_J=J)
        if not ok and np.isfinite(x).all():
            out["newton_recovers"] = self.newton_recover(x)
        return out

    def newton_recover(self, x):
        """Cause of a failed recovery: does global Newton, from the same state and with the same
        quasi-static steps, get back to the rest shape? Yes: VBD converges too slowly; no: the
        energy itself holds the body in another configuration."""
        import dataclasses

        solver, sim, X = self.solver, self.sim, self.mesh.vertices
        sim.set_positions(x)
        sim.set_velocities(np.zeros_like(X))
        problem = sim.step_problem()
        for _ in range(self.recovery_rounds):
            problem = dataclasses.replace(problem, y=x.copy(), constrained_positions=x.copy())
            res = newton_or_none(solver, problem, x, 50)
            if res is None:
                return False
            x = res.x
            if aligned_deviation(x, X) <= 1e-3 and min_J(x, self.mesh) > 0:
                return True
        return False


def grid(quick=False, all_cells=False):
    if quick:
        return [("coarse", dt, E, nu, s) for dt, E, nu, s in
                itertools.product((1 / 60,), (1e4,), (0.3,), STATES)]
    cells = [("coarse",) + c for c in itertools.product(DTS, MODULI, NUS, STATES)]
    fine = itertools.product(DTS, MODULI, NUS, STATES) if all_cells else \
        itertools.product((1 / 240, 1 / 10), (1e4, 1e8), (0.3, 0.49), STATES)
    return cells + [("fine",) + c for c in fine]


def main(argv=None):
    p = parser(__doc__.split("\n")[0], "benchmarks/results/stability",
               quick=f"the coarse mesh at dt = 1/60 s, E = 1e4 Pa, nu = 0.3, from each of the {len(STATES)} states")
    p.add_argument("--all", action="store_true", not_quick="it runs a few cells of the coarse mesh",
                   help="the whole grid at both resolutions (1000 cells)")
    p.add_argument("--iterations", type=positive(int), default=20, help="VBD iterations per step")
    p.add_argument("--steps", type=positive(int), default=3, help="time steps per cell")
    p.add_argument("--recovery-rounds", type=positive(int), default=5, help="quasi-static recovery steps")
    p.add_argument("--recovery-iterations", type=positive(int), default=200, help="VBD iterations per recovery step")
    p.add_argument("--threads", type=positive(int), default=1, help="CPU threads (tiny meshes: 1 is fastest)")
    args = p.parse_args(argv)
    output_folder(args, OUTPUTS)
    init_taichi(args.threads)
    cells = grid(args.quick, args.all)
    runners = {}
    rows = []
    for cell in progress(cells, desc="stability", disable=args.no_progress):
        res = cell[0]
        if res not in runners:
            runners[res] = Runner(RESOLUTIONS[res], args.iterations, args.steps, args.recovery_rounds,
                                  args.recovery_iterations)
        row = runners[res].cell(*cell[1:])
        row["resolution"] = res
        rows.append(row)
    write_csv(os.path.join(args.out, "stability.csv"), rows, COLUMNS)
    plot(rows, os.path.join(args.out, "stability.png"))
    text = report(rows)
    with open(os.path.join(args.out, "summary.md"), "w") as fh:
        fh.write(f"Produced by {provenance()}.\n\n{text}\n")
    print(text)
    print_written(args, OUTPUTS)
    return rows


def _agg(rows, key):
    out = []
    for value in dict.fromkeys(r[key] for r in rows):
        rs = [r for r in rows if r[key] == value]
        errs = [r["error"] for r in rs if not math.isnan(r["error"])]
        out.append({key: value, "cells": len(rs), "finite": sum(r["finite"] for r in rs),
                    "monotone": sum(r["monotone"] for r in rs), "recovers": sum(r["recovers"] for r in rs),
                    "median error": float(np.median(errs)) if errs else float("nan"),
                    "worst error": max(errs) if errs else float("nan")})
    return out


def report(rows):
    cols = ["cells", "finite", "monotone", "recovers", "median error", "worst error"]
    undefined = {"median error": nan_as("-"), "worst error": nan_as("-")}     # the rest state's error
    parts = [table(_agg(rows, "resolution"), ["resolution"] + cols, "All cells by resolution "
                   "(counts of cells passing; error = ||x - x*|| / ||x* - x_n|| after the first step's budget)",
                   undefined)]
    for key in ("state", "nu", "E", "dt"):
        parts.append(table(_agg(rows, key), [key] + cols, f"By {key}", undefined))
    failing = [r for r in rows if not r["passed"]]
    slow = [r for r in failing if r["finite"] and r["monotone"] and r.get("newton_recovers") is True]
    trapped = [r for r in failing if r["finite"] and r["monotone"] and r.get("newton_recovers") is False]
    parts.append(f"Failures: {len(failing)} of {len(rows)} cells; not finite: "
                 f"{sum(not r['finite'] for r in rows)}; G rose after a colour sweep: "
                 f"{sum(r['finite'] and not r['monotone'] for r in rows)}; recovery too slow for VBD "
                 f"(Newton recovers from the same state): {len(slow)}; held in another configuration "
                 f"(Newton does not recover either): {len(trapped)}.")
    if failing:
        parts.append(table(failing[:60], ["resolution", "dt", "E", "nu", "state", "finite", "monotone",
                                          "max_rise", "recovers", "recovery_max_dev", "recovery_min_J",
                                          "newton_recovers"],
                           f"Failing cells ({len(failing)} of {len(rows)}; first 60)",
                           {"dt": lambda v: f"1/{round(1 / v)}"}))
    else:
        parts.append(f"All {len(rows)} cells pass.")
    return "\n\n".join(parts)


def plot(rows, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, len(STATES), figsize=(3.4 * len(STATES), 6.4), squeeze=False)
    Es = sorted({r["E"] for r in rows})
    nus = sorted({r["nu"] for r in rows})
    for col, state in enumerate(STATES):
        rs = [r for r in rows if r["state"] == state]
        passed = np.full((len(nus), len(Es)), np.nan)
        err = np.full((len(nus), len(Es)), np.nan)
        for a, nu in enumerate(nus):
            for b, E in enumerate(Es):
                cell = [r for r in rs if r["nu"] == nu and r["E"] == E]
                if cell:
                    passed[a, b] = np.mean([r["passed"] for r in cell])
                    e = [r["error"] for r in cell if math.isfinite(r["error"])]
                    err[a, b] = np.log10(np.median(e)) if e else np.nan
        for row, (data, cmap, vmin, vmax, label) in enumerate(
                ((passed, "RdYlGn", 0, 1, "fraction of cells passing"),
                 (err, "viridis", -8, 0, "log10 median error after budget"))):
            ax = axes[row, col]
            ax.imshow(data, cmap=cmap, vmin=vmin, vmax=vmax, origin="lower", aspect="auto")
            ax.set_xticks(range(len(Es)), [f"{E:.0e}" for E in Es], fontsize=7, rotation=45)
            ax.set_yticks(range(len(nus)), [f"{nu:g}" for nu in nus], fontsize=7)
            for a in range(len(nus)):
                for b in range(len(Es)):
                    if np.isfinite(data[a, b]):
                        ax.text(b, a, f"{data[a, b]:.2g}", ha="center", va="center", fontsize=6)
            ax.set_title(f"{state}: {label}", fontsize=8)
            ax.set_xlabel("E (Pa)", fontsize=7)
            if col == 0:
                ax.set_ylabel("nu", fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


if __name__ == "__main__":
    main()
