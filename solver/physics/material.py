"""The stable Neo-Hookean energy that VBD uses, its stress, and its per-vertex force and Hessian.

    Psi(F) = mu/2 (tr(F^T F) - 3) + lam/2 (det F - alpha)^2,   alpha = 1 + mu / lam
    P(F)   = dPsi/dF = mu F + lam (det F - alpha) cof(F)

[Smith et al. 2018] without the log term, as in VBD [Chen et al. 2024] Sec. 3. `lam` here is the
Neo-Hookean lambda, `lam = lam_lame + mu`, so that small strains reproduce linear elasticity with
Young's modulus E and Poisson ratio nu (lecture notes, chapter 3).

Each formula exists twice: as `ti.func` for the kernels, and as batched numpy (`*_np`) for the
Newton reference and the tests, which check one against the other and against finite differences.
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
            if not isinstance(value, (int, float, np.floating, np.integer)) or not np.isfinite(value):
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
