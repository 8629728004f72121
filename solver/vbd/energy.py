"""The incremental potential G of one implicit Euler step, in Taichi.

    G(x) = sum_free m_i/(2h^2) |x_i - y_i|^2 + sum_tets vol Psi(F) + sum_free k_c/2 max(0, z0 - z_i)^2

(lecture notes, chapter 1), each term from its file in solver/physics/. The numpy twin is
`newton.StepProblem.energy`.
state (STATE_ROWS, N) 3-vectors; mass (N,); free (N,) int32; tets (M,) 4-vectors of int32;
Dm_inv (M,) 3x3 inverse rest edge matrices; volume (M,) rest volumes; params (PARAM_COUNT,).
"""
from .._ti import ti

from ..physics.ground import ground_energy
from ..physics.inertia import inertia_energy
from ..physics.material import deformation_gradient, psi
from .layout import GROUND, GROUND_HEIGHT, GROUND_STIFFNESS, LAM, MU, TIME_STEP, X, Y


@ti.kernel
def incremental_potential(state: ti.types.ndarray(), mass: ti.types.ndarray(), free: ti.types.ndarray(),
                          tets: ti.types.ndarray(), Dm_inv: ti.types.ndarray(), volume: ti.types.ndarray(),
                          params: ti.types.ndarray(), serial: ti.template()) -> ti.f64:
    """G(x) in J at the current positions x for the current step's y; serial: both loops on one thread
    (small meshes on the CPU, `vertex_solve.serial_sweep`), the sums then in a fixed order."""
    G = ti.cast(0.0, ti.f64)
    inv_h2 = 1 / params[TIME_STEP] ** 2
    ti.loop_config(serialize=serial)
    for i in range(state.shape[1]):
        if free[i]:
            G += ti.cast(inertia_energy(inv_h2 * mass[i], state[X, i], state[Y, i]), ti.f64)
            if params[GROUND] > 0:
                G += ti.cast(ground_energy(state[X, i][2], params[GROUND_HEIGHT], params[GROUND_STIFFNESS]), ti.f64)
    ti.loop_config(serialize=serial)
    for t in range(tets.shape[0]):
        a, b, c, d = tets[t][0], tets[t][1], tets[t][2], tets[t][3]
        F = deformation_gradient(state[X, a], state[X, b], state[X, c], state[X, d], Dm_inv[t])
        G += ti.cast(volume[t] * psi(F, params[MU], params[LAM]), ti.f64)
    return G
