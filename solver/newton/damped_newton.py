"""Damped Newton: the one Newton loop of the project, shared by the numpy oracle (`oracle.newton_solve`),
the Taichi Newton (`direct.GlobalNewton`) and Newton-PCG (`pcg.NewtonPCG`).

Each iteration takes a descent direction d from the caller (projected Newton, PCG, ...), backtracks
along it until G decreases enough (Armijo: G(x + alpha d) <= G(x) + c alpha g.d), and stops when

- the step alpha |d|_max is below `step_tolerance` times the body's size, or
- max_i |dG/dx_i| is below `force_tolerance` newtons (the relative test of `Simulation(tolerance=...)`,
  turned into newtons by the caller), or at round-off level (GRADIENT_ROUNDOFF times m_max size / h^2),

(lecture notes, chapter 2). The caller supplies G and dG/dx, so the oracle keeps its own numpy assembly
and stays independent of the Taichi kernels it checks.
"""
import time
import warnings
from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np

REFERENCE_TOLERANCE = 1e-10     # default step_tolerance of a reference solve: x* to about ten digits
ARMIJO_C = 1e-4                 # sufficient decrease: G(x + alpha d) <= G + ARMIJO_C alpha g.d
BACKTRACK = 0.5                 # alpha <- BACKTRACK alpha after a rejected trial step
SMALLEST_ALPHA = 1e-10          # the line search gives up below this step length
ENERGY_ROUNDOFF = 1e-15         # a trial within this fraction of |G| counts as no increase
GRADIENT_ROUNDOFF = 1e-13       # max |dG/dx| below this times m_max size / h^2: converged at round-off
STALL_GRADIENT = 1e-10          # a failed line search above this times m_max size / h^2 is worth a warning
MODEL_AGREEMENT = 0.25          # |actual / predicted decrease - 1| below which the quadratic model is trusted
MODEL_ROUNDOFF = 1e-12          # a predicted decrease below this fraction of |G| is trusted as it is
CHORD_ATTEMPT = 0.1             # a chord step is tried once the last step is this fraction of the one before
CHORD_CONTRACTION = 0.01        # ... and taken when it is at most this fraction of the last step


@dataclass(frozen=True)
class NewtonRecord:
    """After `iteration` Newton iterations: G in J, max_i |dG/dx_i| in N and the wall time so far (s)."""

    iteration: int
    energy: float
    max_gradient: float
    seconds: float


@dataclass
class NewtonResult:
    """x: (N, 3) solution; iterations; converged; history: one `NewtonRecord` per iterate;
    iterates: the positions after each iteration when asked for (`keep_iterates=True`); evaluations: how
    many times G and dG/dx were evaluated (line-search trials included)."""

    x: np.ndarray
    iterations: int
    converged: bool
    history: list = field(default_factory=list)
    iterates: list = field(default_factory=list)
    evaluations: int = 0


def damped_newton(problem, energy_gradient: Callable, direction: Callable, x0: np.ndarray,
                  step_tolerance: float = REFERENCE_TOLERANCE, max_iterations: int = 50, keep_iterates: bool = False,
                  time_budget: Optional[float] = None, chord: Optional[Callable] = None,
                  force_tolerance: Optional[float] = None, name: str = "Newton",
                  step_cap: Optional[Callable] = None, warn_at_cap: bool = True) -> NewtonResult:
    """Minimise G of `problem` (a `StepProblem`: free, constrained_positions, masses, h) from x0 (N, 3).

    energy_gradient(x, out) -> G: G(x) in J, dG/dx (N, 3) written into out (zero at constrained vertices).
    direction(x, g, iteration, trusted) -> d (N, 3): the step before the line search; trusted is False
    after a step that was not a full Newton step or whose quadratic model g.d / 2 mispredicted the decrease
    of G by more than MODEL_AGREEMENT (and the decrease was above G's round-off); True at the first
    iteration and otherwise (the direct Newton then uses the exact Hessian, see `GlobalNewton.solve`).
    chord(x, g) -> d or None: the step with the last factorised Hessian, a back substitution (Newton with a
    lagged Hessian). Once the steps shrink fast (the last trusted step at most CHORD_ATTEMPT times the one
    before), the chord step is tried first and taken if it is at most CHORD_CONTRACTION times the last
    step: the lagged Hessian is then as good as a new one, and the factorisation is saved.
    step_tolerance: relative to the body's size (0: never stop on the step); force_tolerance: N, or None;
    time_budget: stop (quietly, not converged) after the iteration that exceeds these seconds.
    step_cap(x, d) -> alpha in (0, 1], or None (alpha = 1): where the line search starts; with contact, the
    largest step that keeps every vertex within its conservative bound (`ContactTerm.step_cap`, or its
    Taichi twin `ContactPairs.step_cap`), so that no iterate crosses a surface.
    Warns when it stops without converging; `name` names the solver in the warnings. warn_at_cap=False: no
    warning for running all max_iterations, when they are the user's own budget (`Simulation(iterations=...)`)
    rather than a safety limit.
    """
    free = problem.free
    x = np.ascontiguousarray(np.where(free[:, None], x0, problem.constrained_positions), dtype=np.float64)
    size = float(np.ptp(x, axis=0).max()) or 1.0
    force_scale = float(np.max(problem.masses) / problem.h ** 2 * size)
    force_goal = GRADIENT_ROUNDOFF * force_scale
    if force_tolerance is not None:
        force_goal = max(force_goal, force_tolerance)
    start = time.perf_counter()
    g, g_new = np.empty_like(x), np.empty_like(x)
    G = energy_gradient(x, g)
    result = NewtonResult(x, 0, False, evaluations=1)
    result.history.append(NewtonRecord(0, G, float(np.abs(g).max()), 0.0))
    if np.abs(g).max() <= force_goal:
        result.converged = True
        return result
    x_new = np.empty_like(x)
    trusted, last_step, step_before = True, np.inf, np.inf
    for it in range(1, max_iterations + 1):
        d = None
        if chord is not None and trusted and np.isfinite(step_before) and last_step <= CHORD_ATTEMPT * step_before:
            d = chord(x, g)
            if d is not None and not (np.abs(d).max() <= CHORD_CONTRACTION * last_step and np.vdot(g, d) < 0):
                d = None
        if d is None:
            d = direction(x, g, it, trusted)
        if not np.isfinite(d).all():
            warnings.warn(f"{name} direction is not finite at iteration {it}; stopping at the last iterate",
                          stacklevel=3)
            break
        slope = float(np.vdot(g, d))
        alpha = 1.0 if step_cap is None else step_cap(x, d)     # with contact: no vertex past its bound
        while alpha >= SMALLEST_ALPHA:
            np.multiply(d, alpha, out=x_new)
            x_new += x
            G_new = energy_gradient(x_new, g_new)
            result.evaluations += 1
            if np.isfinite(G_new) and G_new <= G + ARMIJO_C * alpha * slope + ENERGY_ROUNDOFF * abs(G):
                break
            alpha *= BACKTRACK
        else:
            if np.abs(g).max() > STALL_GRADIENT * force_scale:
                warnings.warn(f"the line search could not decrease G at iteration {it} (max |dG/dx| = "
                              f"{np.abs(g).max():.2e} N); stopping at the last iterate", stacklevel=3)
            break
        predicted = 0.5 * slope
        trusted = alpha == 1.0 and (abs(G_new - G - predicted) <= MODEL_AGREEMENT * abs(predicted)
                                    or abs(predicted) <= MODEL_ROUNDOFF * abs(G))
        last_step, step_before = alpha * float(np.abs(d).max()), last_step
        x, x_new = x_new, x
        g, g_new = g_new, g
        G = G_new
        result.history.append(NewtonRecord(it, G, float(np.abs(g).max()), time.perf_counter() - start))
        if keep_iterates:
            result.iterates.append(x.copy())
        result.iterations = it
        if last_step <= step_tolerance * size or np.abs(g).max() <= force_goal:
            result.converged = True
            break
        if time_budget is not None and result.history[-1].seconds > time_budget:
            break
    result.x = x.copy()
    capped = result.iterations == max_iterations and not warn_at_cap
    if not result.converged and not capped and (time_budget is None or result.history[-1].seconds <= time_budget):
        warnings.warn(f"{name} did not converge ({result.iterations} iterations)", stacklevel=3)
    return result
