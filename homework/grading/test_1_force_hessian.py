"""Task force_hessian: one tet's contribution to f_i and H_i (lecture notes, chapter 3)."""
import numpy as np
import pytest

from gradelib import random_rotation, require
from solver._ti import ti
from solver.physics.material import cofactor_np, dpsi_dF_np, psi_np, vertex_force_hessian

pytestmark = pytest.mark.task("force_hessian")

MU, LAM = 3.0e3, 9.0e3


@ti.kernel
def _evaluate(Fm: ti.types.ndarray(), J: ti.types.ndarray(), w: ti.types.ndarray(), m_sq: ti.types.ndarray(),
              vol: ti.types.ndarray(), mu: ti.f64, lam: ti.f64, f_out: ti.types.ndarray(),
              H_out: ti.types.ndarray()):
    for t in range(J.shape[0]):
        f, H = vertex_force_hessian(ti.Vector([Fm[t, 0], Fm[t, 1], Fm[t, 2]]), J[t],
                                    ti.Vector([w[t, 0], w[t, 1], w[t, 2]]), m_sq[t], vol[t], mu, lam)
        for a in ti.static(range(3)):
            f_out[t, a] = f[a]
            for b in ti.static(range(3)):
                H_out[t, a, b] = H[a, b]


def tets(count, seed, invert=False):
    """Random rest tets X (T, 4, 3) and deformed copies x; some inverted when `invert`."""
    rng = np.random.default_rng(seed)
    X = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]])[None] * 0.1 + rng.normal(scale=0.02, size=(count, 4, 3))
    flip = np.diag([1.0, 1.0, -1.0]) if invert else np.eye(3)
    A = np.stack([random_rotation(rng) @ (np.eye(3) + rng.normal(scale=0.3, size=(3, 3))) @ flip for _ in range(count)])
    x = np.einsum("tab,tkb->tka", A, X) + rng.normal(scale=0.01, size=(count, 4, 3))
    return X, x


def geometry(X, x):
    """Per tet: F, the gradient rows m (T, 4, 3) and the rest volume."""
    Dm = np.stack([X[:, k] - X[:, 0] for k in (1, 2, 3)], axis=-1)
    Ds = np.stack([x[:, k] - x[:, 0] for k in (1, 2, 3)], axis=-1)
    Dm_inv = np.linalg.inv(Dm)
    rows = np.concatenate([-Dm_inv.sum(axis=1, keepdims=True), Dm_inv], axis=1)
    return Ds @ Dm_inv, rows, np.abs(np.linalg.det(Dm)) / 6.0


def student(X, x, k):
    """f_i and H_i of local vertex k of every tet, from the student's vertex_force_hessian."""
    require("force_hessian")
    F, rows, vol = geometry(X, x)
    m = rows[:, k]
    Fm = np.einsum("tab,tb->ta", F, m)
    w = np.einsum("tab,tb->ta", cofactor_np(F), m)
    f = np.zeros((len(F), 3))
    H = np.zeros((len(F), 3, 3))
    _evaluate(Fm, np.linalg.det(F), w, (m * m).sum(axis=1), vol, MU, LAM, f, H)
    return f, H


def energy(X, x):
    F, _, vol = geometry(X, x)
    return vol * psi_np(F, MU, LAM)


def force(X, x, k):
    """-dE/dx_k from the (given) stress P(F): -vol P m_k."""
    F, rows, vol = geometry(X, x)
    return -vol[:, None] * np.einsum("tab,tb->ta", dpsi_dF_np(F, MU, LAM), rows[:, k])


@pytest.mark.parametrize("k", [0, 1, 2, 3])
def test_force_is_minus_the_energy_gradient(k):
    X, x = tets(16, seed=k)
    f, _ = student(X, x, k)
    eps = 1e-7
    numeric = np.zeros_like(f)
    for a in range(3):
        xp, xm = x.copy(), x.copy()
        xp[:, k, a] += eps
        xm[:, k, a] -= eps
        numeric[:, a] = -(energy(X, xp) - energy(X, xm)) / (2 * eps)
    scale = np.abs(numeric).max()
    assert np.abs(f - numeric).max() <= 1e-5 * scale, "f_i does not match -dE/dx_i (finite differences)"


@pytest.mark.parametrize("invert", [False, True])
def test_hessian_is_the_force_jacobian(invert):
    X, x = tets(16, seed=7, invert=invert)
    for k in range(4):
        _, H = student(X, x, k)
        eps = 1e-7
        numeric = np.zeros_like(H)
        for b in range(3):
            xp, xm = x.copy(), x.copy()
            xp[:, k, b] += eps
            xm[:, k, b] -= eps
            numeric[:, :, b] = -(force(X, xp, k) - force(X, xm, k)) / (2 * eps)
        scale = np.abs(numeric).max()
        assert np.abs(H - numeric).max() <= 1e-5 * scale, f"H_i of local vertex {k} is not d2E/dx_i2"


def test_hessian_is_symmetric_positive_definite_even_for_inverted_tets():
    X, x = tets(32, seed=3, invert=True)
    assert (np.linalg.det(geometry(X, x)[0]) < 0).sum() > 16
    for k in range(4):
        _, H = student(X, x, k)
        assert np.allclose(H, H.transpose(0, 2, 1), rtol=0, atol=1e-9 * np.abs(H).max())
        assert (np.linalg.eigvalsh(H) > 0).all()


def test_no_force_at_rest_and_force_scales_with_volume():
    X, _ = tets(8, seed=11)
    f, H = student(X, X.copy(), 2)
    assert np.abs(f).max() <= 1e-9, "the rest shape F = I must have no elastic force"
    f2, H2 = student(2 * X, 2 * X + 0.02, 2)        # twice the size: 8x volume, 1/2 the gradient rows
    f1, H1 = student(X, X + 0.01, 2)                 # same F and a translation: f = 0 for both
    assert np.abs(f1).max() <= 1e-9 and np.abs(f2).max() <= 1e-9
    assert np.allclose(H2, 2 * H1, rtol=1e-9)        # vol |m|^2 and vol w w^T both scale by 8 / 4
