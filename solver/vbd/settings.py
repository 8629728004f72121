"""The live settings of a `Simulation`, validated in one place, and which method honours which.

`Settings` is frozen and checks every value when one is made (turning names of enums into members),
like `Material` and `Ground`; unlike them it is keyword-only (`Settings(dt=0.01)`: its fields have no
natural order, as Material(E, nu, rho) has). So `sim.dt = 0.01` is
`sim.settings = dataclasses.replace(sim.settings, dt=0.01)` and a bad value never reaches a kernel.

What each setting means for each method (`Method`; "auto" behaves as the method it chose):

    setting                 vbd                         multilevel                   newton, pcg
    iterations              VBD iterations per step     budget of fine sweeps:       Newton iterations per
                                                        iterations // 4 cycles of    step (the cap)
                                                        2 + coarse + 2 (the cap,
                                                        rounded down: 4 to 7 run
                                                        one cycle); below 4 refused
    tolerance               stop once max_i |f_i| <= tolerance x max(max_i |f_i| at the initial guess,
                            max_i m_i |g|) (or round-off): checked every check_every iterations (vbd),
                            after every cycle (multilevel), after every Newton iteration (newton, pcg);
                            None: vbd and multilevel run the whole budget, newton and pcg stop when the
                            Newton step is below NEWTON_STEP_TOLERANCE x the body's size
    check_every             iterations between checks   refused (checked after every cycle and Newton
                            (None: CHECK_EVERY)         iteration, where the residual is at hand)
    initial_guess           where the iterations (VBD sweeps, cycles, Newton iterations) start
    chebyshev_rho           Chebyshev acceleration      refused (it extrapolates VBD iterates only)
    damping, ground         as given                    damping > 0 and ground friction > 0 refused:
                                                        these methods minimise G, which has neither
    keep_orientation        limits guess and sweeps     refused (global steps are not limited)
    contact (a Simulation   Jacobi contact inside       multilevel, pcg: refused; newton: starts from VBD's
    property, not a field   a colour, bounds            guess clamped to the bounds (y may lie across a body),
    of Settings)                                        re-detects at every iterate, caps its line search by
                                                        the bounds; friction > 0 refused
    translation_correction, kinematic_motion, dt, gravity, record_history: every method (the translation
    correction changes nothing after an exact Newton step, which leaves no net force on a free body).
"""
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np

from ..errors import ConfigError, enum_value
from ..method import MULTILEVEL_CYCLE_SWEEPS, Method
from ..physics.ground import Ground
from .implicit_euler import InitialGuess

CHECK_EVERY = 5   # VBD iterations between two tolerance checks when check_every is None (a check ~ an iteration)
# The time steps h (s) that make physical sense, far wider than any real use: a nanosecond resolves elastic waves
# in steel (5 km/s) crossing 5 um cells, finer than any mesh this tool runs, and a step of 1000 s (a quarter of an
# hour, g h^2 = 10^7 m) is quasi-static for any body. Beyond them nothing is gained and floating point fails: h^2
# underflows (a singular M/h^2) or overflows near h = 1e-154 and 1e154.
DT_RANGE = (1e-9, 1e3)


def number(value, name: str, unit: str) -> float:
    """`value` as a finite float, else a ConfigError naming `name` and its unit."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ConfigError(f"{name} must be a number of {unit}, got {value!r}")
    if not np.isfinite(value):
        raise ConfigError(f"{name} must be finite, got {value!r}")
    return float(value)


def positive(value, name: str, unit: str) -> float:
    """`value` as a finite float > 0, else a ConfigError."""
    value = number(value, name, unit)
    if value <= 0:
        raise ConfigError(f"{name} must be a positive number of {unit}, got {value!r}")
    return value


def count(value, name: str) -> int:
    """`value` as an int >= 1, else a ConfigError."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ConfigError(f"{name} must be an integer >= 1, got {value!r}")
    return int(value)


def _flag(value, name: str) -> bool:
    if not isinstance(value, (bool, np.bool_)):
        raise ConfigError(f"{name} must be True or False, got {value!r}")
    return bool(value)


def _gravity(value) -> tuple:
    try:
        g = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        g = None
    if g is None or g.shape != (3,) or not np.isfinite(g).all():
        raise ConfigError(f"gravity must be three finite numbers in m/s^2, e.g. (0, 0, -9.81), got {value!r}")
    return tuple(float(c) for c in g)


@dataclass(frozen=True, kw_only=True)
class Settings:
    """How a `Simulation` steps; every field is live (used from the next iteration or step on).

    dt: time step h in s, within DT_RANGE (1e-9 to 1e3); gravity: (3,) g in m/s^2; iterations: the budget
    of a step (per method, see the module docstring); tolerance: relative residual at which a step stops
    early, or None;
    check_every: VBD iterations between two tolerance checks, None for CHECK_EVERY (vbd only);
    initial_guess: an `InitialGuess` or its name; chebyshev_rho: spectral radius estimate rho of
    Chebyshev acceleration (VBD Eq. 18-19), in (0, 1), or None; damping: k_d in s (VBD Eq. 10-11), 0 for
    none; ground: a `Ground` or None; translation_correction: end every step with the rigid-translation
    correction, one translation per body without fixed or kinematic vertices (`translation.py`; bodies
    with a fixed vertex get none); keep_orientation: never let an upright tet invert (VBD's guess and
    vertex steps are limited); kinematic_motion: (t, rest (K, 3)) -> (K, 3) positions of the kinematic
    vertices at time t, or None; record_history: keep G and max |f_i| after every iteration of the last
    step.
    """

    dt: float = 1 / 60
    gravity: tuple = (0.0, 0.0, -9.81)
    iterations: int = 100
    tolerance: Optional[float] = None
    check_every: Optional[int] = None
    initial_guess: InitialGuess = InitialGuess.ADAPTIVE
    chebyshev_rho: Optional[float] = None
    damping: float = 0.0
    ground: Optional[Ground] = None
    translation_correction: bool = True
    keep_orientation: bool = False
    kinematic_motion: Optional[Callable] = None
    record_history: bool = False

    def __post_init__(self):
        def put(name, value):
            object.__setattr__(self, name, value)

        dt = positive(self.dt, "dt", "seconds")
        if not DT_RANGE[0] <= dt <= DT_RANGE[1]:
            raise ConfigError(f"dt must be between {DT_RANGE[0]:g} and {DT_RANGE[1]:g} seconds, got {self.dt!r}; "
                              "use a time step in that range (1/60 s suits most scenes)")
        put("dt", dt)
        put("gravity", _gravity(self.gravity))
        put("iterations", count(self.iterations, "iterations"))
        if self.tolerance is not None:
            put("tolerance", positive(self.tolerance, "tolerance", "the initial residual (a fraction, e.g. 1e-4)"))
        if self.check_every is not None:
            put("check_every", count(self.check_every, "check_every"))
        put("initial_guess", enum_value(InitialGuess, self.initial_guess, "initial_guess (solver.InitialGuess)"))
        if self.chebyshev_rho is not None:
            rho = number(self.chebyshev_rho, "chebyshev_rho", "(dimensionless)")
            if not 0.0 < rho < 1.0:
                raise ConfigError(f"chebyshev_rho must be in (0, 1) or None, got {self.chebyshev_rho!r}")
            put("chebyshev_rho", rho)
        damping = number(self.damping, "damping", "seconds")
        if damping < 0:
            raise ConfigError(f"damping must be >= 0 seconds, got {self.damping!r}")
        put("damping", damping)
        if self.ground is not None and not isinstance(self.ground, Ground):
            raise ConfigError(f"ground must be a solver.Ground or None, got {type(self.ground).__name__}")
        for name in ("translation_correction", "keep_orientation", "record_history"):
            put(name, _flag(getattr(self, name), name))
        if self.kinematic_motion is not None and not callable(self.kinematic_motion):
            raise ConfigError("kinematic_motion must be a function (t, rest) -> (K, 3) positions")

    @property
    def vbd_check_every(self) -> int:
        """VBD iterations between two tolerance checks."""
        return CHECK_EVERY if self.check_every is None else self.check_every


def check_method(settings: Settings, method: Method) -> None:
    """Raise a one-line ConfigError for a setting `method` cannot honour (see the module docstring)."""
    if method is Method.VBD:
        return
    use = f"method={method.value!r}"
    if settings.damping > 0 or (settings.ground is not None and settings.ground.friction > 0):
        raise ConfigError(f"{use} minimises G, which has no damping or friction; "
                          "set damping=0 and ground friction=0, or use method='vbd'")
    if settings.chebyshev_rho is not None:
        raise ConfigError(f"chebyshev_rho extrapolates VBD iterates, which {use} does not take; "
                          "set chebyshev_rho=None, or use method='vbd'")
    if settings.check_every is not None:
        raise ConfigError(f"{use} checks the tolerance after every cycle or Newton iteration; "
                          "set check_every=None, or use method='vbd'")
    if settings.keep_orientation:
        raise ConfigError(f"keep_orientation limits VBD's vertex steps, and {use} takes global steps; "
                          "set keep_orientation=False, or use method='vbd'")
    if method is Method.MULTILEVEL and settings.iterations < MULTILEVEL_CYCLE_SWEEPS:
        raise ConfigError(f"{use} runs whole cycles of {MULTILEVEL_CYCLE_SWEEPS} fine sweeps (2 + coarse + 2), "
                          f"so it cannot stop after iterations={settings.iterations}; set iterations >= "
                          f"{MULTILEVEL_CYCLE_SWEEPS}, or use method='vbd'")
