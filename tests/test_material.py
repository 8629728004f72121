"""The stable Neo-Hookean energy: derivatives by finite differences, Taichi against numpy, and the
small-strain limit that makes E and nu mean what they say."""
import numpy as np
import pytest
import taichi as ti

import solver
from solver.physics.material import (cofactor, d2psi_dF2_np, dpsi_dF, dpsi_dF_np, psi, psi_np,
                             vertex_force_hessian)

pytestmark = pytest.mark.backend  # launches Taichi kernels: re-run on CUDA

MAT = solver.Material(youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0)
rng = np.random.default_rng(0)
RANDOM_F = np.eye(3) + 0.3 * rng.standard_normal((20, 3, 3))


def test_lame_parameters_follow_the_issue_formula():
    E, nu = MAT.youngs_modulus, MAT.poisson_ratio
    assert MAT.mu == pytest.approx(E / (2 * (1 + nu)))
    assert MAT.lam == pytest.approx(E * nu / ((1 + nu) * (1 - 2 * nu)) + MAT.mu)
    assert MAT.alpha == pytest.approx(1 + MAT.mu / MAT.lam)


def test_rest_and_rotations_are_stress_free():
    angles = rng.standard_normal((5, 3))
    for a in angles:
        K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
        w, V = np.linalg.eig(K)
        R = np.real(V @ np.diag(np.exp(w)) @ np.linalg.inv(V))
        np.testing.assert_allclose(dpsi_dF_np(R, MAT.mu, MAT.lam), 0.0, atol=1e-8 * MAT.mu)
        assert psi_np(R, MAT.mu, MAT.lam) == pytest.approx(psi_np(np.eye(3), MAT.mu, MAT.lam), abs=1e-6)
    assert psi_np(np.eye(3), MAT.mu, MAT.lam) == pytest.approx(0.5 * MAT.lam * (1 - MAT.alpha) ** 2)


def test_stress_is_the_derivative_of_the_energy():
    eps = 1e-6
    for F in RANDOM_F:
        P = dpsi_dF_np(F, MAT.mu, MAT.lam)
        fd = np.zeros((3, 3))
        for a in range(3):
            for b in range(3):
                dF = np.zeros((3, 3))
                dF[a, b] = eps
                fd[a, b] = (psi_np(F + dF, MAT.mu, MAT.lam) - psi_np(F - dF, MAT.mu, MAT.lam)) / (2 * eps)
        np.testing.assert_allclose(P, fd, rtol=1e-6, atol=1e-6 * MAT.mu)


def test_stress_hessian_is_the_derivative_of_the_stress():
    eps = 1e-6
    for F in RANDOM_F[:5]:
        A = d2psi_dF2_np(F, MAT.mu, MAT.lam)
        for c in range(3):
            for d in range(3):
                dF = np.zeros((3, 3))
                dF[c, d] = eps
                fd = (dpsi_dF_np(F + dF, MAT.mu, MAT.lam) - dpsi_dF_np(F - dF, MAT.mu, MAT.lam)) / (2 * eps)
                np.testing.assert_allclose(A[:, :, c, d], fd, rtol=1e-6, atol=1e-6 * MAT.mu)


def test_taichi_functions_match_numpy():
    n = len(RANDOM_F)
    Fs = ti.Matrix.field(3, 3, ti.f64, n)
    out_psi = ti.field(ti.f64, n)
    out_P = ti.Matrix.field(3, 3, ti.f64, n)
    out_C = ti.Matrix.field(3, 3, ti.f64, n)
    Fs.from_numpy(RANDOM_F)

    @ti.kernel
    def evaluate(mu: ti.f64, lam: ti.f64):
        for k in Fs:
            out_psi[k] = psi(Fs[k], mu, lam)
            out_P[k] = dpsi_dF(Fs[k], mu, lam)
            out_C[k] = cofactor(Fs[k])

    evaluate(MAT.mu, MAT.lam)
    np.testing.assert_allclose(out_psi.to_numpy(), psi_np(RANDOM_F, MAT.mu, MAT.lam), rtol=1e-12)
    np.testing.assert_allclose(out_P.to_numpy(), dpsi_dF_np(RANDOM_F, MAT.mu, MAT.lam), rtol=1e-12, atol=1e-9)
    dets = np.linalg.det(RANDOM_F)
    np.testing.assert_allclose(out_C.to_numpy(), dets[:, None, None] * np.linalg.inv(RANDOM_F).transpose(0, 2, 1),
                               rtol=1e-10, atol=1e-12)


def test_vertex_force_hessian_is_minus_vol_P_m_and_exact_hessian():
    """f = -vol P m and H = d2/dx_i2 of vol Psi(F(x_i)), with F = F0 + (x_i - x0_i) m^T."""
    F0 = RANDOM_F[3]
    m = np.array([0.7, -1.3, 0.4])
    vol = 0.01
    res_f = ti.Vector.field(3, ti.f64, ())
    res_H = ti.Matrix.field(3, 3, ti.f64, ())

    @ti.kernel
    def evaluate(F: ti.types.matrix(3, 3, ti.f64), m: ti.types.vector(3, ti.f64), mu: ti.f64, lam: ti.f64):
        C = cofactor(F)
        f, H = vertex_force_hessian(F @ m, F.determinant(), C @ m, m.dot(m), vol, mu, lam)
        res_f[None] = f
        res_H[None] = H

    evaluate(F0, m, MAT.mu, MAT.lam)
    f, H = res_f.to_numpy(), res_H.to_numpy()
    np.testing.assert_allclose(f, -vol * dpsi_dF_np(F0, MAT.mu, MAT.lam) @ m, rtol=1e-12)
    energy = lambda dx: vol * psi_np(F0 + np.outer(dx, m), MAT.mu, MAT.lam)  # noqa: E731
    eps = 1e-4
    fd = np.zeros((3, 3))
    for a in range(3):
        for b in range(3):
            ea, eb = np.eye(3)[a] * eps, np.eye(3)[b] * eps
            fd[a, b] = (energy(ea + eb) - energy(ea - eb) - energy(-ea + eb) + energy(-ea - eb)) / (4 * eps ** 2)
    np.testing.assert_allclose(H, fd, rtol=1e-6)
    # The local energy is exactly quadratic in x_i: the model is exact for a large step.
    dx = np.array([0.3, -0.2, 0.5])
    assert energy(dx) - energy(np.zeros(3)) == pytest.approx(-f @ dx + 0.5 * dx @ H @ dx, rel=1e-10)
    assert np.linalg.eigvalsh(H).min() > 0


@pytest.mark.parametrize("nu", [-0.5, 0.0, 0.3, 0.45])
def test_small_strain_limit_is_linear_elasticity(nu):
    """Uniaxial stress: stretch by e along x, let the sides relax; sigma_xx / e -> E, -e_yy / e -> nu
    (an auxetic material, nu < 0, widens)."""
    mat = solver.Material(youngs_modulus=2e6, poisson_ratio=nu, density=1.0)
    e = 1e-6

    def lateral_stress(t):
        F = np.diag([1 + e, 1 + t, 1 + t])
        return dpsi_dF_np(F, mat.mu, mat.lam)[1, 1]

    lo, hi = -e, e   # lateral strain that makes the side faces traction-free, by bisection
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if lateral_stress(mid) > 0:
            hi = mid
        else:
            lo = mid
    t = 0.5 * (lo + hi)
    sigma = dpsi_dF_np(np.diag([1 + e, 1 + t, 1 + t]), mat.mu, mat.lam)[0, 0]
    assert sigma / e == pytest.approx(mat.youngs_modulus, rel=1e-4)
    assert -t / e == pytest.approx(nu, abs=1e-4)


@pytest.mark.parametrize("kwargs", [
    dict(youngs_modulus=-1.0, poisson_ratio=0.3), dict(youngs_modulus=1e4, poisson_ratio=0.5),
    dict(youngs_modulus=1e4, poisson_ratio=-1.0), dict(youngs_modulus=float("nan"), poisson_ratio=0.3),
    dict(youngs_modulus=1e4, poisson_ratio=0.3, density=0.0), dict(youngs_modulus="soft", poisson_ratio=0.3),
    dict(youngs_modulus=True, poisson_ratio=0.3), dict(youngs_modulus=1e4, poisson_ratio=False)])
def test_nonsense_material_parameters_are_refused(kwargs):
    with pytest.raises(solver.ConfigError, match="youngs_modulus|poisson_ratio|density"):
        solver.Material(**kwargs)
