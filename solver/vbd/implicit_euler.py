"""The time step around the VBD iterations: predict y, choose the initial guess, update velocities.

    y = x_n + h v_n + h^2 g                                  (VBD [Chen et al. 2024] Eq. 2)
    v_{n+1} = (x_{n+1} - x_n) / h                            (implicit Euler)

Module-level kernels over the arrays of `layout.py`, shared by every `Simulation`.
state (STATE_ROWS, N) 3-vectors; free (N,) int32, 1 for the vertices VBD solves; params (PARAM_COUNT,).
serial: every loop on one thread, for the small meshes whose sweep runs so on the CPU
(`vertex_solve.serial_sweep`): a parallel loop costs tens of microseconds to start and end there.
"""
from enum import Enum

from .._ti import ti

from .layout import GRAVITY_X, TIME_STEP, V, V_PREV, X, X_N, X_PREV, X_PREV2, Y


class InitialGuess(Enum):
    """Where the iterations of a step start (VBD [Chen et al. 2024] Sec. 3.7)."""

    PREVIOUS = "previous"    # x_n
    INERTIA = "inertia"      # x_n + h v_n
    INERTIAL = "inertial"    # y = x_n + h v_n + h^2 g
    ADAPTIVE = "adaptive"    # x_n + h v_n + h^2 a~ g, a~ = clamp(a_n . g / |g|^2, 0, 1)

    @property
    def code(self) -> int:
        """The integer `begin_step` receives for this guess."""
        return list(InitialGuess).index(self)


_PREVIOUS, _INERTIA, _INERTIAL = (InitialGuess.PREVIOUS.code, InitialGuess.INERTIA.code,
                                  InitialGuess.INERTIAL.code)


@ti.kernel
def begin_step(state: ti.types.ndarray(), free: ti.types.ndarray(), kinematic_ids: ti.types.ndarray(),
               kinematic_targets: ti.types.ndarray(), n_kinematic: ti.i32, params: ti.types.ndarray(),
               guess: ti.i32, dtype: ti.template(), serial: ti.template()):
    """Save x_n, move the kinematic vertices to their targets at t + h, predict y (Eq. 2) and set the
    initial guess (Sec. 3.7) of the free vertices; start the Chebyshev history at the guess.

    kinematic_ids (K,) int32 and kinematic_targets (K,) 3-vectors; only the first n_kinematic are used.
    guess: `InitialGuess.code` of the initial guess.
    """
    ti.loop_config(serialize=serial)
    for i in range(state.shape[1]):
        state[X_N, i] = state[X, i]
    ti.loop_config(serialize=serial)
    for k in range(n_kinematic):
        state[X, kinematic_ids[k]] = kinematic_targets[k]
    h = params[TIME_STEP]
    g = ti.Vector([params[GRAVITY_X], params[GRAVITY_X + 1], params[GRAVITY_X + 2]], dt=dtype)
    g2 = g.dot(g)
    ti.loop_config(serialize=serial)
    for i in range(state.shape[1]):
        state[Y, i] = state[X_N, i] + h * state[V, i] + h * h * g
        if free[i]:
            if guess == _PREVIOUS:
                state[X, i] = state[X_N, i]
            elif guess == _INERTIA:
                state[X, i] = state[X_N, i] + h * state[V, i]
            elif guess == _INERTIAL:
                state[X, i] = state[Y, i]
            else:
                a_tilde = ti.cast(0.0, dtype)
                if g2 > 0:
                    a_n = (state[V, i] - state[V_PREV, i]) / h
                    a_tilde = ti.math.clamp(a_n.dot(g) / g2, 0, 1)
                state[X, i] = state[X_N, i] + h * state[V, i] + h * h * a_tilde * g
        state[X_PREV, i] = state[X, i]
        state[X_PREV2, i] = state[X, i]


@ti.kernel
def largest_displacement(state: ti.types.ndarray(), serial: ti.template()) -> ti.f64:
    """max_i |x_i - x_n,i| in m over all vertices; +inf when any position is not finite."""
    result = ti.cast(0.0, ti.f64)
    ti.loop_config(serialize=serial)
    for i in range(state.shape[1]):
        d = ti.cast((state[X, i] - state[X_N, i]).norm(), ti.f64)
        if not d <= 1e300:    # NaN or inf
            d = ti.math.inf
        ti.atomic_max(result, d)
    return result


@ti.kernel
def end_step(state: ti.types.ndarray(), params: ti.types.ndarray(), serial: ti.template()):
    """v_{n+1} = (x - x_n) / h, keeping v_n for the adaptive guess of the next step."""
    ti.loop_config(serialize=serial)
    for i in range(state.shape[1]):
        state[V_PREV, i] = state[V, i]
        state[V, i] = (state[X, i] - state[X_N, i]) / params[TIME_STEP]


@ti.kernel
def return_to_start(state: ti.types.ndarray(), serial: ti.template()):
    """x = x_n: undo the iterations of the current step."""
    ti.loop_config(serialize=serial)
    for i in range(state.shape[1]):
        state[X, i] = state[X_N, i]
