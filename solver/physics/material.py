"""The stable Neo-Hookean energy that VBD uses, its stress, and its per-vertex force and Hessian.

    Psi(F) = mu/2 (tr(F^T F) - 3) + lam/2 (det F - alpha)^2,   alpha = 1 + mu / lam
    P(F)   = dPsi/dF = mu F + lam (det F - alpha) cof(F)

[Smith et al. 2018] without the log term, as in VBD [Chen et al. 2024] Sec. 3. `lam` here is the
Neo-Hookean lambda, `lam = lam_lame + mu`, so that small strains reproduce linear elasticity with
Young's modulus E and Poisson ratio nu (lecture notes, chapter 1).

Each formula exists twice: as `ti.func` for the kernels, and as batched numpy (`*_np`) for the
Newton reference and the tests, which check one against the other and against finite differences.
F = Ds Dm^-1 (`deformation_gradient`), the stress Hessian (`d2psi_dF2_entry`), the per-vertex gradients
B^T P (`vertex_gradients`) and the per-tet Hessian blocks (`tet_hessian_block`) are written here once;
every solver calls them.
"""
from dataclasses import dataclass

import numpy as np
from .._ti import ti

from ..errors import ConfigError


@dataclass(frozen=True)
class Material:
    """Homogeneous elastic material.

    youngs_modulus: E in Pa (> 0). poisson_ratio: nu, dimensionless, in (-1, 0.5); negative for
    auxetic materials, which widen when stretched. density: rho in kg/m^3 (> 0).
    """

    youngs_modulus: float
    poisson_ratio: float
    density: float = 1000.0

    def __post_init__(self):
        for name in ("youngs_modulus", "poisson_ratio", "density"):
            value = getattr(self, name)
            if (isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer))
                    or not np.isfinite(value)):
                raise ConfigError(f"{name} must be a finite number, got {value!r}")
        if self.youngs_modulus <= 0:
            raise ConfigError(f"youngs_modulus must be > 0 Pa, got {self.youngs_modulus}")
        if not -1.0 < self.poisson_ratio < 0.5:
            raise ConfigError(f"poisson_ratio must be in (-1, 0.5), got {self.poisson_ratio}; -1 has no shear "
                              "stiffness left and 0.5 is incompressible, neither is supported")
        if self.density <= 0:
            raise ConfigError(f"density must be > 0 kg/m^3, got {self.density}")

    @property
    def mu(self) -> float:
        """Shear modulus mu = E / (2 (1 + nu)) in Pa."""
        return self.youngs_modulus / (2.0 * (1.0 + self.poisson_ratio))

    @property
    def lam(self) -> float:
        """Neo-Hookean lambda = E nu / ((1 + nu)(1 - 2 nu)) + mu in Pa (Smith et al. 2018, Sec. 3.4)."""
        nu = self.poisson_ratio
        return self.youngs_modulus * nu / ((1.0 + nu) * (1.0 - 2.0 * nu)) + self.mu

    @property
    def alpha(self) -> float:
        """Rest-stability shift alpha = 1 + mu / lam, which makes P(I) = 0."""
        return 1.0 + self.mu / self.lam


# ---------------------------------------------------------------------------------------------
# Taichi functions used inside the VBD kernels.
# ---------------------------------------------------------------------------------------------
@ti.func
def cofactor(F):
    """cof(F) = det(F) F^-T = dJ/dF, built from cross products of the columns of F."""
    f0 = ti.Vector([F[0, 0], F[1, 0], F[2, 0]])
    f1 = ti.Vector([F[0, 1], F[1, 1], F[2, 1]])
    f2 = ti.Vector([F[0, 2], F[1, 2], F[2, 2]])
    return ti.Matrix.cols([f1.cross(f2), f2.cross(f0), f0.cross(f1)])


@ti.func
def psi(F, mu, lam):
    """Energy density Psi(F) in J/m^3."""
    alpha = 1 + mu / lam
    J = F.determinant()
    return mu / 2 * ((F * F).sum() - 3) + lam / 2 * (J - alpha) ** 2


@ti.func
def dpsi_dF(F, mu, lam):
    """First Piola-Kirchhoff stress P = dPsi/dF (3x3, Pa)."""
    alpha = 1 + mu / lam
    return mu * F + lam * (F.determinant() - alpha) * cofactor(F)


@ti.func
def levi_civita(i, j, k):
    """eps_ijk for indices in 0..2: 1 for an even permutation, -1 for an odd one, 0 otherwise."""
    return (i - j) * (j - k) * (k - i) // 2


@ti.func
def d2psi_dF2_entry(F, C, J, a, b, c, d, mu, lam):
    """dP_ab/dF_cd (one entry of the 9x9 stress Hessian) at F with C = cof(F), J = det F:

        mu delta_ac delta_bd + lam C_ab C_cd + lam (J - alpha) eps_ace eps_bdf F_ef
    """
    alpha = 1 + mu / lam
    value = lam * C[a, b] * C[c, d]
    if a == c and b == d:
        value += mu
    if a != c and b != d:
        e, f = 3 - a - c, 3 - b - d
        value += lam * (J - alpha) * levi_civita(a, c, e) * levi_civita(b, d, f) * F[e, f]
    return value


@ti.func
def deformation_gradient(x0, x1, x2, x3, Dm_inv):
    """F = Ds Dm^-1 (3x3) of a tet with vertices x0..x3, Ds = [x1 - x0, x2 - x0, x3 - x0].

    Linear in x: with the variations v_k of the vertices in place of x_k it gives dF = B v.
    """
    return ti.Matrix.cols([x1 - x0, x2 - x0, x3 - x0]) @ Dm_inv


@ti.func
def vertex_gradients(P, Dm_inv):
    """B^T vec(P) (4x3): row k is P m_k, with m_k the row of Dm^-1 of local vertex k (k = 1..3) and
    m_0 = -(m_1 + m_2 + m_3). With P = dPsi/dF, vol times row k is d(vol Psi)/dx_k."""
    G = P @ Dm_inv.transpose()                      # column k - 1: P m_k
    g1 = ti.Vector([G[0, 0], G[1, 0], G[2, 0]])
    g2 = ti.Vector([G[0, 1], G[1, 1], G[2, 1]])
    g3 = ti.Vector([G[0, 2], G[1, 2], G[2, 2]])
    return ti.Matrix.rows([-(g1 + g2 + g3), g1, g2, g3])


@ti.func
def tet_hessian_block(F, J, cof_m_k, cof_m_l, m_k, m_l, vol, mu, lam):
    """Block (k, l) (3x3) of a tet's exact Hessian d2(vol Psi)/dx_k dx_l = vol B_k^T (dP/dF) B_l:

        vol (mu (m_k . m_l) I + lam (C m_k)(C m_l)^T + lam (J - alpha) eps_ace (F (m_k x m_l))_e)

    with C = cof(F), cof_m_k = C m_k (= dJ/dx_k), J = det F and m_k the rows of Dm^-1 (see
    `vertex_gradients`). Not projected: the Newton Hessian projects it (solver/newton/hessian.py).
    """
    alpha = 1 + mu / lam
    w = lam * (J - alpha) * (F @ m_k.cross(m_l))
    block = ti.Matrix.diag(3, mu * m_k.dot(m_l)) + lam * cof_m_k.outer_product(cof_m_l)
    block += ti.Matrix([[0.0, w[2], -w[1]], [-w[2], 0.0, w[0]], [w[1], -w[0], 0.0]])   # eps_ace w_e
    return vol * block


@ti.func
def vertex_force_hessian(Fm, J, w, m_sq, vol, mu, lam):
    """One tet's contribution (f, H) to the force f_i and Hessian H_i of one of its vertices i.

    With m = dF/dx_i direction (the row of Dm^-1 that belongs to vertex i), the energy of the tet
    depends on x_i only through F m, |F|^2 and J = det F. The arguments are
      Fm = F m;  J = det F;  w = dJ/dx_i = cof(F) m;  m_sq = |m|^2;  vol = rest volume;
    f is -d(vol Psi)/dx_i (3-vector) and H = d2(vol Psi)/dx_i2 (3x3); lecture notes, chapter 3.
    """
    # BEGIN SOLUTION task=force_hessian
    # f = -vol P m with P m = mu F m + lam (J - alpha) cof(F) m. H is exact: J is affine in x_i,
    # so d2J/dx_i2 = 0, and H is symmetric positive definite whenever m != 0.
    alpha = 1 + mu / lam
    f = -vol * (mu * Fm + lam * (J - alpha) * w)
    H = vol * (ti.Matrix.diag(3, mu * m_sq) + lam * w.outer_product(w))
    # END SOLUTION
    return f, H


# ---------------------------------------------------------------------------------------------
# Batched numpy versions: F has shape (..., 3, 3).
# ---------------------------------------------------------------------------------------------
def cofactor_np(F: np.ndarray) -> np.ndarray:
    """cof(F) for (..., 3, 3) arrays."""
    f0, f1, f2 = F[..., :, 0], F[..., :, 1], F[..., :, 2]
    return np.stack([np.cross(f1, f2), np.cross(f2, f0), np.cross(f0, f1)], axis=-1)


def psi_np(F: np.ndarray, mu: float, lam: float) -> np.ndarray:
    """Psi(F) for (..., 3, 3) arrays -> (...)."""
    alpha = 1.0 + mu / lam
    return 0.5 * mu * ((F * F).sum(axis=(-2, -1)) - 3.0) + 0.5 * lam * (np.linalg.det(F) - alpha) ** 2


def dpsi_dF_np(F: np.ndarray, mu: float, lam: float) -> np.ndarray:
    """P(F) for (..., 3, 3) arrays -> (..., 3, 3)."""
    alpha = 1.0 + mu / lam
    return mu * F + lam * (np.linalg.det(F) - alpha)[..., None, None] * cofactor_np(F)


_LEVI_CIVITA = np.zeros((3, 3, 3))
for _i, _j, _k in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
    _LEVI_CIVITA[_i, _j, _k], _LEVI_CIVITA[_i, _k, _j] = 1.0, -1.0


def d2psi_dF2_np(F: np.ndarray, mu: float, lam: float) -> np.ndarray:
    """dP/dF for (..., 3, 3) arrays -> (..., 3, 3, 3, 3), index [a, b, c, d] = d P_ab / d F_cd.

    mu I + lam cof(F) (x) cof(F) + lam (J - alpha) d2J/dF2, with
    d2J / dF_ab dF_cd = eps_ace eps_bdf F_ef.
    """
    alpha = 1.0 + mu / lam
    C = cofactor_np(F)
    J = np.linalg.det(F)
    eye = np.einsum("ac,bd->abcd", np.eye(3), np.eye(3))
    d2J = np.einsum("ace,bdf,...ef->...abcd", _LEVI_CIVITA, _LEVI_CIVITA, F, optimize=True)
    return (mu * eye + lam * np.einsum("...ab,...cd->...abcd", C, C)
            + lam * (J - alpha)[..., None, None, None, None] * d2J)


def deformation_gradient_np(x: np.ndarray, tets: np.ndarray, Dm_inv: np.ndarray) -> np.ndarray:
    """(M, 3, 3) F = Ds Dm^-1 of every tet; x (N, 3), tets (M, 4), Dm_inv (M, 3, 3)."""
    Ds = np.stack([x[tets[:, k]] - x[tets[:, 0]] for k in (1, 2, 3)], axis=-1)
    return Ds @ Dm_inv


def gradient_rows_np(Dm_inv: np.ndarray) -> np.ndarray:
    """(M, 4, 3) rows m_k of every tet: m_1..m_3 the rows of Dm^-1 (M, 3, 3), m_0 = -(m_1 + m_2 + m_3)."""
    return np.concatenate([-Dm_inv.sum(axis=1, keepdims=True), Dm_inv], axis=1)


def tet_gradients_np(F: np.ndarray, Dm_inv: np.ndarray, volumes: np.ndarray, mu: float, lam: float) -> np.ndarray:
    """(M, 4, 3) d(vol Psi)/dx_k = vol P m_k of every tet's four vertices; F, Dm_inv (M, 3, 3), volumes (M,)."""
    P = dpsi_dF_np(F, mu, lam)
    return volumes[:, None, None] * np.einsum("tab,tkb->tka", P, gradient_rows_np(Dm_inv))


def tet_hessian_blocks_np(F: np.ndarray, Dm_inv: np.ndarray, volumes: np.ndarray, mu: float,
                          lam: float) -> np.ndarray:
    """(M, 4, 4, 3, 3) exact blocks d2(vol Psi)/dx_k dx_l = vol B_k^T (dP/dF) B_l, not projected."""
    m = gradient_rows_np(Dm_inv)
    A = d2psi_dF2_np(F, mu, lam)
    return volumes[:, None, None, None, None] * np.einsum("tabcd,tkb,tld->tklac", A, m, m, optimize=True)
