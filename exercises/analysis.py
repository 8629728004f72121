"""Task 5 of the homework: two derivations checked numerically, and two measurements of the solver.

Derivations (lecture notes, chapter 3): why J = det F is affine in x_i (F is linear in x_i with a
constant derivative), and why every tet's H_i is symmetric positive definite (its eigenvalues in
closed form). Measurements (chapters 4, 5 and 6): what the colouring buys (the same vertex solves
without colours, Jacobi, against the coloured sweep), how many VBD iterations a step needs as the
material stiffens (N_c = h sqrt(E / rho) / dx grows), and which Chebyshev rho works best.

The measurements run on `BAR`, the cantilever `REFERENCE_CASES["stiff_long_bar"]` of demo/homework.py
(16 x 2 x 2 cubes, 0.8 m long), with the solver you built in tasks 1-4: `BAR.simulation(**settings)`
makes one, `sim.begin_step()` starts its first step, `sim.run_iterations(1)` runs one VBD iteration
and `sim.max_residual()` gives max_i |f_i| in newtons (solver/vbd/simulation.py);
`sim.local_systems()` gives every vertex's f_i (N, 3) and H_i (N, 3, 3) at the current positions,
`sim.positions` a copy of x (N, 3), `sim.set_positions(x)` writes it back and `sim.free_mask` (N,)
marks the vertices that are solved (f_i and H_i are zero at the pinned ones).
"""
from dataclasses import replace

import numpy as np

from demo.homework import REFERENCE_CASES

BAR = REFERENCE_CASES["stiff_long_bar"]
YOUNGS_MODULI = (1e4, 1e5, 1e6)             # Pa, for `iterations_needed`
REDUCTION = 1e-3                            # iterate until max_i |f_i| <= REDUCTION x its value at the start
MAX_ITERATIONS = 3000
RHO_GRID = (0.5, 0.7, 0.8, 0.9, 0.95, 0.98)  # Chebyshev rho candidates, for `best_rho`
RHO_ITERATIONS = 60
JACOBI_ITERATIONS = 50                      # iterations of each sweep, for `jacobi_against_coloring`
UNDER_RELAXATION = 0.5                      # omega of the under-relaxed Jacobi sweep
JACOBI_KEYS = ("start", "jacobi", "under_relaxed", "vbd")


def dF_dx(m: np.ndarray) -> np.ndarray:
    """(9, 3) derivative d vec(F) / d x_i of one tet, with vec(F) row by row (F[a, b] is entry 3a + b)
    and m (3,) the gradient row of vertex i (the row of Dm^-1 belonging to i, chapter 3).

    It depends on m only, not on any position: F is linear in x_i. That is why J = det F is affine
    along any move of x_i alone (a rank-one change of F) and d2J/dx_i2 = 0."""
    # BEGIN SOLUTION task=analysis
    return np.kron(np.eye(3), np.reshape(np.asarray(m, dtype=float), (3, 1)))
    # END SOLUTION


def hessian_eigenvalues(m_sq: float, w: np.ndarray, vol: float, mu: float, lam: float) -> np.ndarray:
    """(3,) eigenvalues, ascending, of one tet's H_i (task 1) in closed form, from m_sq = |m|^2,
    w = dJ/dx_i (3,), the rest volume vol and the material's mu, lam (all > 0). All three are
    positive for every F, inverted tets included: H_i is symmetric positive definite."""
    # BEGIN SOLUTION task=analysis
    smallest = vol * mu * m_sq
    return np.array([smallest, smallest, smallest + vol * lam * float(np.dot(w, w))])
    # END SOLUTION


def iterations_needed(youngs_modulus: float) -> int:
    """Plain VBD iterations (no acceleration) of the first step of `BAR` with this Young's modulus (Pa)
    until max_i |f_i| (`Simulation.max_residual`) is at most REDUCTION times its value at the start of
    the step; MAX_ITERATIONS if it never is. Compare the counts with N_c (`Simulation.wave_cells`)."""
    # BEGIN SOLUTION task=analysis
    bar = replace(BAR, youngs_modulus=youngs_modulus).simulation(iterations=1)
    bar.begin_step()
    start = bar.max_residual()
    for k in range(1, MAX_ITERATIONS + 1):
        bar.run_iterations(1)
        if bar.max_residual() <= REDUCTION * start:
            return k
    return MAX_ITERATIONS
    # END SOLUTION


def rho_residuals() -> dict:
    """{rho: max_i |f_i| after RHO_ITERATIONS Chebyshev-accelerated iterations of the first step of `BAR`
    (E = BAR.youngs_modulus)} for every rho of RHO_GRID; infinity where the iterations blow up."""
    # BEGIN SOLUTION task=analysis
    residuals = {}
    for rho in RHO_GRID:
        bar = BAR.simulation(iterations=RHO_ITERATIONS, chebyshev_rho=rho)
        bar.begin_step()
        bar.run_iterations(RHO_ITERATIONS)
        residual = bar.max_residual()
        residuals[rho] = residual if np.isfinite(residual) else np.inf
    return residuals
    # END SOLUTION


def best_rho() -> float:
    """The rho of RHO_GRID that `rho_residuals` finds best."""
    # BEGIN SOLUTION task=analysis
    measured = rho_residuals()
    return min(measured, key=measured.get)
    # END SOLUTION


def jacobi_against_coloring() -> dict:
    """What the colouring buys (chapter 4): max_i |f_i| in newtons after JACOBI_ITERATIONS iterations of
    the first step of `BAR` (E = BAR.youngs_modulus), as {"start": before any iteration, "jacobi": plain
    Jacobi, "under_relaxed": Jacobi with omega = UNDER_RELAXATION, "vbd": the coloured sweep}; infinity
    where the positions stop being finite.

    One Jacobi iteration solves every free vertex's 3x3 system H_i dx_i = f_i at once, all from the same
    positions (`sim.local_systems()`), then moves every free vertex by omega dx_i; omega = 1 is plain
    Jacobi. The coloured sweep is `sim.run_iterations`, which solves the colours one after the other."""
    # BEGIN SOLUTION task=analysis
    residuals = {}
    for key, omega in (("jacobi", 1.0), ("under_relaxed", UNDER_RELAXATION)):
        bar = BAR.simulation(iterations=JACOBI_ITERATIONS)
        bar.begin_step()
        residuals["start"] = bar.max_residual()
        free = bar.free_mask
        for _ in range(JACOBI_ITERATIONS):
            f_i, H_i = bar.local_systems()
            x = bar.positions
            x[free] = x[free] + omega * np.linalg.solve(H_i[free], f_i[free][:, :, np.newaxis])[:, :, 0]
            if not np.all(np.isfinite(x)):
                break
            bar.set_positions(x)
        residuals[key] = bar.max_residual() if np.all(np.isfinite(x)) else np.inf
    bar = BAR.simulation(iterations=JACOBI_ITERATIONS)
    bar.begin_step()
    bar.run_iterations(JACOBI_ITERATIONS)
    residuals["vbd"] = bar.max_residual()
    return residuals
    # END SOLUTION
