"""The rigid-translation correction: the coarsest global channel, for free bodies.

Unconverged VBD leaves a residual f_i at every vertex, and the residuals do not sum to zero: each
step then adds a spurious momentum h sum_i f_i, and a ball dropped straight down drifts sideways
(lecture notes, chapter 5). Elastic forces are invariant under a translation of the whole body, so the
Newton step restricted to the three translation modes, x_i <- x_i + d with

    d = (sum_i m_i/h^2 I + K_c)^-1 sum_i f_i          (K_c: penalty contact stiffness),

makes the residuals sum to zero again at the cost of one force evaluation per step. It is a
Galerkin coarse correction whose coarse space is the translations; it only applies to bodies without
fixed or kinematic vertices, whose elastic energy is translation invariant. Friction is not a
potential and stays out of K_c (its lagged stiffness would block the correction on the ground).
"""
from .._ti import ti

from ..physics.ground import ground_hessian_zz
from ..physics.inertia import inertia_block
from .layout import GROUND, GROUND_HEIGHT, GROUND_STIFFNESS, TIME_STEP, X
from .vertex_solve import force_hessian


@ti.kernel
def translation_system(state: ti.types.ndarray(), mass: ti.types.ndarray(), color_order: ti.types.ndarray(),
                       offsets: ti.types.ndarray(), others: ti.types.ndarray(), adj_f: ti.types.ndarray(),
                       params: ti.types.ndarray(), out: ti.types.ndarray(), dtype: ti.template()):
    """out[0] = sum_i f_i and out[1] = the diagonal of sum_i m_i/h^2 I + K_c, over the free vertices.

    out: (2,) 3-vectors of float64.
    """
    out[0] = ti.Vector.zero(ti.f64, 3)
    out[1] = ti.Vector.zero(ti.f64, 3)
    inv_h2 = 1 / params[TIME_STEP] ** 2
    for k in range(color_order.shape[0]):
        i = color_order[k]
        f, H = force_hessian(state, mass, color_order, offsets, others, adj_f, params, k, dtype)
        M = inertia_block(ti.cast(inv_h2 * mass[i], dtype))
        K = ti.Vector([M[0, 0], M[1, 1], M[2, 2]])
        if params[GROUND] > 0:
            K[2] += ground_hessian_zz(state[X, i][2], params[GROUND_HEIGHT], params[GROUND_STIFFNESS])
        out[0] += ti.cast(f, ti.f64)
        out[1] += ti.cast(K, ti.f64)


@ti.kernel
def translate(state: ti.types.ndarray(), color_order: ti.types.ndarray(), out: ti.types.ndarray(),
              dtype: ti.template()):
    """x_i += d, d = out[0] / out[1] componentwise, for every free vertex (out as `translation_system`)."""
    d = ti.cast(out[0] / out[1], dtype)
    for k in range(color_order.shape[0]):
        state[X, color_order[k]] += d
