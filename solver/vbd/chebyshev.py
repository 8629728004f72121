"""Chebyshev semi-iterative acceleration of the VBD iterations (VBD [Chen et al. 2024] Eq. 18-19).

After iteration k, x^(k) = omega_k (x^(k) - x^(k-2)) + x^(k-2): an over-relaxation whose weight
follows the Chebyshev recurrence for an estimated spectral radius rho of the plain iteration
(lecture notes, chapter 6). rho too close to 1 over-shoots and diverges.
"""
from .._ti import ti

from .layout import X, X_PREV, X_PREV2


def chebyshev_omega(k: int, rho: float, omega_prev: float) -> float:
    """Chebyshev weight omega_k (VBD Eq. 19): 1, 2/(2 - rho^2), 4/(4 - rho^2 omega_{k-1})."""
    # BEGIN SOLUTION task=chebyshev
    if k == 1:
        return 1.0
    if k == 2:
        return 2.0 / (2.0 - rho * rho)
    return 4.0 / (4.0 - rho * rho * omega_prev)
    # END SOLUTION


@ti.func
def chebyshev_update(state: ti.template(), i, omega):
    """x_i = omega (x_i - x_i^(k-2)) + x_i^(k-2) (VBD Eq. 18), and shift the history x^(k-1), x^(k-2)."""
    # BEGIN SOLUTION task=chebyshev
    x_accel = omega * (state[X, i] - state[X_PREV2, i]) + state[X_PREV2, i]
    state[X_PREV2, i] = state[X_PREV, i]
    state[X_PREV, i] = x_accel
    state[X, i] = x_accel
    # END SOLUTION


@ti.kernel
def chebyshev_step(state: ti.types.ndarray(), color_order: ti.types.ndarray(), omega: ti.f64,
                   dtype: ti.template(), serial: ti.template()):
    """The Chebyshev step after one VBD iteration, for every free vertex (slot k of `color_order`), on one
    thread where serial (small meshes on the CPU, as their sweep); launched only when a simulation
    accelerates, so code without it never compiles `chebyshev_update`."""
    ti.loop_config(serialize=serial)
    for k in range(color_order.shape[0]):
        chebyshev_update(state, color_order[k], ti.cast(omega, dtype))
