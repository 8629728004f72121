"""Ground contact: a plane z = height with penalty contact and lagged, smoothed Coulomb friction.

    E_c(x_i) = k_c/2 d_i^2,   d_i = max(0, height - z_i)            (penetration depth)

Written once: the `ti.func`s below (depth, energy, gradient, the 3x3 block with friction for the VBD
sweep, the diagonal Hessian entry for the Newton Hessian, the PCG products and the translation
correction) and their numpy twins (`*_np`: the Newton reference, the two-level coarse operator). The
comparison of a vertex with the plane is `ground_depth` (`ground_depth_np`) and nowhere else.
Friction is not a potential: it acts on the tangential displacement u of the current step, with IPC's
smoothed Coulomb law below the sliding speed.
"""
from dataclasses import dataclass

import numpy as np
from .._ti import ti

from ..errors import ConfigError


@dataclass(frozen=True)
class Ground:
    """A ground plane z = height with penalty contact.

    height: z of the plane in m. stiffness: penalty k_c in N/m per vertex, energy k_c/2 d^2 for
    penetration depth d. friction: Coulomb coefficient mu_f (dimensionless, 0 = frictionless),
    smoothed below the sliding speed `friction_speed` (m/s) as in IPC's lagged friction.
    """

    height: float = 0.0
    stiffness: float = 1e5
    friction: float = 0.0
    friction_speed: float = 1e-3

    def __post_init__(self):
        for name in ("height", "stiffness", "friction", "friction_speed"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
                raise ConfigError(f"ground {name} must be a number, got {value!r}")
        if not np.isfinite(self.height):
            raise ConfigError(f"ground height must be finite, got {self.height}")
        if not (np.isfinite(self.stiffness) and self.stiffness > 0):
            raise ConfigError(f"ground stiffness must be > 0 N/m, got {self.stiffness}")
        if not (np.isfinite(self.friction) and self.friction >= 0):
            raise ConfigError(f"ground friction must be >= 0, got {self.friction}")
        if not (np.isfinite(self.friction_speed) and self.friction_speed > 0):
            raise ConfigError(f"friction_speed must be > 0 m/s, got {self.friction_speed}")


@ti.func
def friction_scale(s, eps_u):
    """f1(s)/s of IPC's smoothed Coulomb friction at tangential displacement s (m), in 1/m:
    (2 - s/eps_u)/eps_u below eps_u, 1/s above; friction force = -mu_f f_n f1(s)/s u_t."""
    scale = (2 - s / eps_u) / eps_u
    if s >= eps_u:
        scale = 1 / s
    return scale


@ti.func
def ground_depth(z_i, height):
    """Penetration depth d_i = max(0, height - z_i) in m of a vertex at height z_i: the one ground test."""
    return ti.max(height - z_i, 0)


@ti.func
def ground_energy(z_i, height, k_c):
    """Penalty energy k_c/2 d_i^2 of one vertex at height z_i (J)."""
    depth = ground_depth(z_i, height)
    return k_c / 2 * depth * depth


@ti.func
def ground_gradient_z(z_i, height, k_c):
    """dE_c/dz_i = -k_c d_i (N); the x and y components are 0."""
    return -k_c * ground_depth(z_i, height)


@ti.func
def ground_hessian_zz(z_i, height, k_c):
    """d2E_c/dz_i2 = k_c for a penetrating vertex, else 0 (N/m): the only nonzero entry of its 3x3 block."""
    k = k_c * 0
    if ground_depth(z_i, height) > 0:
        k = k_c
    return k


@ti.func
def ground_force_hessian(x_i, u, h, height, k_c, mu_f, friction_speed, dtype: ti.template()):
    """Contact force f (3,) and Hessian H (3x3) on a vertex at x_i that moved u = x_i - x_n,i this step.

    Penalty: f_z = k_c d, H_zz = k_c for depth d > 0. Friction (mu_f > 0): f = -k_f u_t with the
    tangential displacement u_t and k_f = mu_f k_c d f1(s)/s (`friction_scale`), s = |u_t|,
    eps_u = friction_speed h.
    """
    f = ti.Vector.zero(dtype, 3)
    H = ti.Matrix.zero(dtype, 3, 3)
    depth = ground_depth(x_i[2], height)
    if depth > 0:
        f[2] = k_c * depth
        H[2, 2] = k_c
        if mu_f > 0:
            u_t = ti.Vector([u[0], u[1], 0.0], dt=dtype)
            k_f = ti.cast(mu_f * k_c * depth * friction_scale(u_t.norm(), friction_speed * h), dtype)
            f -= k_f * u_t
            H[0, 0] += k_f
            H[1, 1] += k_f
    return f, H


def ground_depth_np(ground: Ground, x: np.ndarray, free: np.ndarray) -> np.ndarray:
    """(N,) penetration depth d_i of every free vertex (0 elsewhere); x (N, 3), free (N,) bool."""
    return np.where(free, np.maximum(ground.height - x[:, 2], 0.0), 0.0)


def ground_energy_np(ground: Ground, x: np.ndarray, free: np.ndarray) -> float:
    """sum_i k_c/2 d_i^2 over the free vertices, in J."""
    return float(0.5 * ground.stiffness * np.sum(ground_depth_np(ground, x, free) ** 2))


def ground_gradient_np(ground: Ground, x: np.ndarray, free: np.ndarray) -> np.ndarray:
    """(N, 3) dE_c/dx: -k_c d_i in z."""
    g = np.zeros_like(x)
    g[:, 2] = -ground.stiffness * ground_depth_np(ground, x, free)
    return g


def ground_hessian_diag_np(ground: Ground, x: np.ndarray, free: np.ndarray) -> np.ndarray:
    """(3N,) diagonal of d2E_c/dx2: k_c at the z coordinate of every penetrating free vertex."""
    diag = np.zeros(3 * len(x))
    diag[2::3] = ground.stiffness * (ground_depth_np(ground, x, free) > 0)
    return diag
