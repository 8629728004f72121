"""Task analysis: derivations checked numerically, measurements checked against the solution's (chapters 3-6)."""
import numpy as np
import pytest

from gradelib import random_rotation, require, stored
from solver.physics.material import cofactor_np, dpsi_dF_np

pytestmark = pytest.mark.task("analysis")


def rest_and_deformed(seed, invert=False):
    """One random rest tet X (4, 3) and a deformed copy x (4, 3), inverted when `invert`."""
    rng = np.random.default_rng(seed)
    X = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]]) * 0.1 + rng.normal(scale=0.02, size=(4, 3))
    A = random_rotation(rng) @ (np.eye(3) + rng.normal(scale=0.3, size=(3, 3)))
    if invert:
        A = A @ np.diag([1.0, 1.0, -1.0])
    return X, X @ A.T


def deformation(X, x):
    Dm = np.stack([X[k] - X[0] for k in (1, 2, 3)], axis=-1)
    Ds = np.stack([x[k] - x[0] for k in (1, 2, 3)], axis=-1)
    Dm_inv = np.linalg.inv(Dm)
    rows = np.concatenate([-Dm_inv.sum(axis=0, keepdims=True), Dm_inv], axis=0)    # (4, 3)
    return Ds @ Dm_inv, rows, abs(np.linalg.det(Dm)) / 6.0


@pytest.mark.parametrize("k", [0, 3])
def test_dF_dx_is_the_constant_derivative_of_F(k):
    require("analysis")
    from exercises.analysis import dF_dx

    X, x = rest_and_deformed(seed=k)
    _, rows, _ = deformation(X, x)
    D = np.asarray(dF_dx(rows[k]), dtype=float)
    assert D.shape == (9, 3), f"dF_dx must return a (9, 3) matrix, got shape {D.shape}"
    for step in (1e-3, 0.5):                    # F is linear in x_i: the difference quotient is exact at any size
        numeric = np.zeros((9, 3))
        for c in range(3):
            moved = x.copy()
            moved[k, c] += step
            numeric[:, c] = ((deformation(X, moved)[0] - deformation(X, x)[0]) / step).reshape(9)
        assert np.allclose(D, numeric, rtol=1e-8, atol=1e-8 * np.abs(numeric).max()), \
            "dF_dx(m) is not d vec(F) / d x_i (vec(F) row by row)"


@pytest.mark.parametrize("invert", [False, True])
def test_hessian_eigenvalues_in_closed_form(invert):
    require("analysis")
    from exercises.analysis import hessian_eigenvalues

    mu, lam, k = 3.0e3, 9.0e3, 1
    X, x = rest_and_deformed(seed=5, invert=invert)
    F, rows, vol = deformation(X, x)
    m = rows[k]
    H = np.zeros((3, 3))                        # d2(vol Psi)/dx_k2 by central differences of the force
    for b in range(3):
        plus, minus = x.copy(), x.copy()
        plus[k, b] += 1e-7
        minus[k, b] -= 1e-7
        H[:, b] = vol * (dpsi_dF_np(deformation(X, plus)[0], mu, lam) - dpsi_dF_np(deformation(X, minus)[0], mu, lam)) @ m / 2e-7
    expected = np.linalg.eigvalsh(0.5 * (H + H.T))
    got = np.asarray(hessian_eigenvalues(float(m @ m), cofactor_np(F) @ m, vol, mu, lam), dtype=float)
    assert got.shape == (3,), f"hessian_eigenvalues must return 3 numbers, got shape {got.shape}"
    assert np.allclose(got, expected, rtol=1e-5), "the eigenvalues are not those of H_i (ascending)"


def test_iterations_against_the_stiffness():
    require("analysis")
    from exercises.analysis import YOUNGS_MODULI, iterations_needed

    expected = stored("iterations_needed")
    got = np.array([iterations_needed(E) for E in YOUNGS_MODULI])
    assert np.all(np.abs(got - expected) <= np.maximum(2, 0.1 * expected)), \
        f"iterations_needed gives {got.tolist()} for E = {list(YOUNGS_MODULI)} Pa; the solution measures {expected.tolist()}"


def test_choosing_rho():
    require("analysis")
    from exercises.analysis import RHO_GRID, best_rho, rho_residuals

    expected = stored("rho_residuals")
    residuals = rho_residuals()
    got = np.array([residuals[rho] for rho in RHO_GRID])
    finite = np.isfinite(expected)
    assert np.array_equal(np.isfinite(got), finite) and np.allclose(got[finite], expected[finite], rtol=0.05), \
        "rho_residuals differs from the solution's measurement by more than 5 %"
    rho = best_rho()
    assert rho in RHO_GRID and expected[RHO_GRID.index(rho)] <= 1.5 * expected[finite].min(), \
        f"rho = {rho} is not among the best of RHO_GRID"


def test_jacobi_against_the_coloured_sweep():
    require("analysis")
    from exercises.analysis import JACOBI_KEYS, jacobi_against_coloring

    expected = dict(zip(JACOBI_KEYS, stored("jacobi_against_coloring")))
    measured = jacobi_against_coloring()
    missing = [key for key in JACOBI_KEYS if key not in measured]
    assert not missing, f"jacobi_against_coloring must return the keys {list(JACOBI_KEYS)}; missing {missing}"
    got = {key: float(measured[key]) for key in JACOBI_KEYS}
    assert got["jacobi"] >= got["start"] or got["jacobi"] >= 10 * got["vbd"], \
        f"plain Jacobi: {got['jacobi']:.3g} N, below its start and near the coloured sweep; all vertices from the same x?"
    assert got["vbd"] < got["under_relaxed"] < got["start"], \
        (f"under-relaxed Jacobi: {got['under_relaxed']:.3g} N from {got['start']:.3g} N (coloured: {got['vbd']:.3g} N); "
         "it should converge, more slowly than the colouring")
    off = [key for key in JACOBI_KEYS if not np.isclose(got[key], expected[key], rtol=0.05)]
    assert not off, "jacobi_against_coloring: " + ", ".join(
        f"{key} {got[key]:.3g} N, the solution measures {expected[key]:.3g} N" for key in off)
