"""One time step of a `Simulation` by a global method: the thin driver between the lecture's solver and
the newton wing (imported on first use, so that VBD alone never loads it).

Both start from VBD's initial guess (`Simulation.begin_step`; with contact it is clamped to the contact
bounds, since y may lie across a body) and end with `Simulation.end_step` (translation correction,
velocities, clock); what each setting means for them is in `settings.py`.
"""
import os

from ..errors import ConfigError
from ..method import Method, multilevel_cycles
from .state import IterationRecord

# The global solvers (solver/newton/) are in this copy: the homework starter leaves them out.
HAS_GLOBAL_SOLVERS = os.path.isdir(os.path.join(os.path.dirname(os.path.dirname(__file__)), "newton"))


def require_global_solvers() -> None:
    """ConfigError in a copy without the global solvers."""
    if not HAS_GLOBAL_SOLVERS:
        raise ConfigError("this copy has no global solvers (solver/newton/ is not in the homework starter); "
                          "use method='vbd', and the stored reference results in grading/ for converged steps")

NEWTON_STEP_TOLERANCE = 1e-8   # without a tolerance: Newton stops when its step is below this x the body's size


def step(sim) -> None:
    """One time step of `sim` with its global method (newton, pcg or multilevel)."""
    if sim.method is Method.MULTILEVEL:
        two_level = _two_level(sim)
        two_level.begin_step()
        two_level.run_cycles(multilevel_cycles(sim.iterations))
        two_level.end_step()
    else:
        newton_step(sim)


def _two_level(sim):
    """The `TwoLevelVBD` of `sim`, built at its first step (the cage and its operator, once)."""
    from ..newton.multilevel import TwoLevelVBD

    if sim._two_level is None:
        sim._two_level = TwoLevelVBD(sim)
    return sim._two_level


def newton_step(sim) -> None:
    """Minimise G of the step with the Taichi Newton (method="newton") or Newton-PCG ("pcg"), at most
    `sim.iterations` Newton iterations, stopping at the relative residual `sim.tolerance` (or, without
    one, when the Newton step is below NEWTON_STEP_TOLERANCE x the body's size). That cap is the user's
    budget, so reaching it is not warned about. Both start from VBD's initial guess; with contact (newton
    only) that guess is clamped to the contact bounds from x_n and the kinematic vertices have reached
    their targets within them (`ContactStage.begin_step`), so no surface crosses there (y may lie across a
    body, and a kinematic target alone may too), and the iterations re-detect the pairs at every iterate."""
    from ..newton.direct import fast_newton_solve
    from ..newton.pcg import newton_pcg

    problem = sim.step_problem()
    sim.begin_step()
    force_tolerance = sim.stop_below
    step_tolerance = NEWTON_STEP_TOLERANCE if force_tolerance is None else 0.0
    if sim.method is Method.NEWTON:
        result = fast_newton_solve(problem, sim.positions, step_tolerance, sim.iterations,
                                   force_tolerance=force_tolerance, warn_at_cap=False)
    else:
        result = newton_pcg(problem.tets, problem.free).solve(problem, sim.positions, step_tolerance,
                                                                sim.iterations, force_tolerance=force_tolerance,
                                                                warn_at_cap=False)
    sim.set_positions(result.x)
    sim.last_iterations = result.iterations
    if sim.record_history:
        sim.history = [IterationRecord(r.iteration, r.energy, r.max_gradient) for r in result.history]
    sim.end_step()
