"""Inertia: the term of G that keeps each free vertex near its inertial target y_i.

    E_I(x) = sum_free m_i/(2h^2) |x_i - y_i|^2,    y_i = x_n,i + h v_n,i + h^2 g    (lecture notes, ch. 1)

Written once: the `ti.func`s below take m_over_h2 = m_i/h^2 (kg/s^2 = N/m) and are called by the VBD
sweep, energy(), the Taichi Newton, the PCG products and the translation correction; the numpy twins
(`*_np`) by the two-level coarse operator and the tests. Its 3x3 block is m_i/h^2 I, the same at every x.
"""
import numpy as np

from .._ti import ti


@ti.func
def inertia_energy(m_over_h2, x_i, y_i):
    """m_i/(2h^2) |x_i - y_i|^2 of one vertex (J); x_i, y_i 3-vectors in m."""
    d = x_i - y_i
    return m_over_h2 / 2 * d.dot(d)


@ti.func
def inertia_gradient(m_over_h2, x_i, y_i):
    """dE_I/dx_i = m_i/h^2 (x_i - y_i) (3-vector, N)."""
    return m_over_h2 * (x_i - y_i)


@ti.func
def inertia_block(m_over_h2):
    """d2E_I/dx_i2 = m_i/h^2 I (3x3, N/m)."""
    return ti.Matrix.diag(3, m_over_h2)


def inertia_energy_np(masses: np.ndarray, h: float, x: np.ndarray, y: np.ndarray, free: np.ndarray) -> float:
    """sum over the free vertices of m_i/(2h^2) |x_i - y_i|^2 in J; masses (N,), x, y (N, 3), free (N,) bool."""
    d = np.where(free[:, None], x - y, 0.0)
    return float(0.5 / h ** 2 * np.sum(masses * np.sum(d * d, axis=1)))


def inertia_gradient_np(masses: np.ndarray, h: float, x: np.ndarray, y: np.ndarray, free: np.ndarray) -> np.ndarray:
    """(N, 3) dE_I/dx: m_i/h^2 (x_i - y_i) at the free vertices, 0 elsewhere."""
    return np.where(free[:, None], masses[:, None] / h ** 2 * (x - y), 0.0)


def inertia_hessian_diag_np(masses: np.ndarray, h: float, free: np.ndarray) -> np.ndarray:
    """(3N,) diagonal of d2E_I/dx2: m_i/h^2 on the three coordinates of every free vertex."""
    return np.repeat(np.where(free, masses / h ** 2, 0.0), 3)
