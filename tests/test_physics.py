"""The terms of G are written once, in solver/physics/: the source says so (greps), and each term's
`ti.func`s agree with their numpy twins and with finite differences of its energy."""
import re
from pathlib import Path

import numpy as np
import pytest
from solver._ti import ti

import solver
from solver.mesh.topology import grad_rows, rest_geometry
from solver.physics import ground as ground_terms
from solver.physics import inertia as inertia_terms
from solver.physics.material import (cofactor, d2psi_dF2_entry, d2psi_dF2_np, deformation_gradient,
                                     deformation_gradient_np, dpsi_dF, psi, psi_np, tet_gradients_np,
                                     tet_hessian_blocks_np, tet_hessian_block, vertex_force_hessian,
                                     vertex_gradients)

pytestmark = pytest.mark.backend   # compiles Taichi kernels: re-run on CUDA

SOLVER = Path(solver.__file__).resolve().parent
rng = np.random.default_rng(7)


def files_matching(patterns) -> set:
    """Paths (relative to solver/) of the solver's Python files with a line matching one of `patterns`."""
    found = set()
    for path in SOLVER.rglob("*.py"):
        for line in path.read_text().splitlines():
            if any(re.search(p, line.split("#", 1)[0]) for p in patterns):
                found.add(path.relative_to(SOLVER).as_posix())
    return found


# ---------------------------------------------------------------------------------------------
# One place per formula
# ---------------------------------------------------------------------------------------------
GROUND_TEST = [r"height\s*-", r"<=?\s*[\w.\[\], ]*height", r"height[\w.\[\], ]*\s*>=?", r"\[2\]\s*[<>]",
               r"\bz\w*\s*[<>]"]


def test_the_ground_test_is_only_in_the_physics():
    assert files_matching(GROUND_TEST) == {"physics/ground.py"}


def test_the_ground_patterns_find_the_forms_the_solvers_used_to_write():
    lines = ["if has_ground != 0 and x[i, 2] < ground_height:", "depth = height - x_i[2]",
             "diag[2::3] += k * (free & (x[:, 2] < problem.ground.height))",
             "if params[GROUND] > 0 and state[X, i][2] < params[GROUND_HEIGHT]:"]
    assert all(any(re.search(p, line) for p in GROUND_TEST) for line in lines)


def test_deformation_gradient_is_computed_in_one_place():
    """F = Ds Dm^-1 in physics/material.py; the numpy oracle keeps its own (it is the independent check)."""
    patterns = [r"@\s*Dm_inv\b", r"\bDs\s*@", r"tka,tkb->tab", r"outer_product\(_grad_row"]
    assert files_matching(patterns) == {"physics/material.py", "newton/oracle.py"}


def test_dm_inverse_and_rest_volumes_are_computed_in_one_place():
    assert files_matching([r"linalg\.inv\(Dm", r"Dm_inv\s*=\s*np\."]) == {"mesh/topology.py"}
    assert files_matching([r"det\(.*\)\)?\s*/\s*6", r"np\.cross\(.*\)\)\s*/\s*6"]) == {"mesh/cells.py"}


def test_rest_geometry_is_cached_read_only_and_right():
    mesh = solver.box_mesh(size=(0.3, 0.2, 0.1), cells=(3, 2, 1))
    rest = rest_geometry(mesh.vertices, mesh.tets)
    assert rest_geometry(mesh.vertices.copy(), mesh.tets.copy()) is rest
    assert grad_rows(mesh.vertices, mesh.tets) is rest.grad_rows
    with pytest.raises(ValueError):
        rest.volumes[0] = 1.0
    np.testing.assert_allclose(rest.volumes.sum(), 0.3 * 0.2 * 0.1, rtol=1e-12)
    F = deformation_gradient_np(mesh.vertices, mesh.tets, rest.Dm_inv)
    np.testing.assert_allclose(F, np.broadcast_to(np.eye(3), F.shape), atol=1e-12)
    np.testing.assert_allclose(rest.grad_rows.sum(axis=1), 0.0, atol=1e-9)


# ---------------------------------------------------------------------------------------------
# Each term: ti.func against its numpy twin against finite differences
# ---------------------------------------------------------------------------------------------
def fd_gradient(energy, x, eps):
    """Central differences of energy(x) for x of any shape."""
    g = np.zeros_like(x)
    for idx in np.ndindex(x.shape):
        e = np.zeros_like(x)
        e[idx] = eps
        g[idx] = (energy(x + e) - energy(x - e)) / (2 * eps)
    return g


def fd_jacobian(gradient, x, eps):
    """(n, n) central differences of gradient(x) (same shape as x), n = x.size: column j is d gradient / d x_j."""
    columns = []
    for j in range(x.size):
        e = np.zeros(x.size)
        e[j] = eps
        e = e.reshape(x.shape)
        columns.append(((gradient(x + e) - gradient(x - e)) / (2 * eps)).ravel())
    return np.stack(columns, axis=1)


def test_inertia_matches_its_twin_and_finite_differences():
    n = 6
    x, y = rng.standard_normal((n, 3)), rng.standard_normal((n, 3))
    masses, h = rng.uniform(0.1, 2.0, n), 1 / 60
    free = np.array([True, True, False, True, True, False])
    out_E = ti.ndarray(ti.f64, n)
    out_g = ti.ndarray(ti.f64, (n, 3))
    out_H = ti.ndarray(ti.f64, (n, 3, 3))

    @ti.kernel
    def evaluate(x: ti.types.ndarray(), y: ti.types.ndarray(), m_h2: ti.types.ndarray(),
                 E: ti.types.ndarray(), g: ti.types.ndarray(), H: ti.types.ndarray()):
        for i in range(x.shape[0]):
            xi = ti.Vector([x[i, 0], x[i, 1], x[i, 2]])
            yi = ti.Vector([y[i, 0], y[i, 1], y[i, 2]])
            E[i] = inertia_terms.inertia_energy(m_h2[i], xi, yi)
            gi = inertia_terms.inertia_gradient(m_h2[i], xi, yi)
            Hi = inertia_terms.inertia_block(m_h2[i])
            for a in ti.static(range(3)):
                g[i, a] = gi[a]
                for b in ti.static(range(3)):
                    H[i, a, b] = Hi[a, b]

    evaluate(x, y, masses / h ** 2, out_E, out_g, out_H)
    E_np = inertia_terms.inertia_energy_np(masses, h, x, y, free)
    assert out_E.to_numpy()[free].sum() == pytest.approx(E_np, rel=1e-12)
    g_np = inertia_terms.inertia_gradient_np(masses, h, x, y, free)
    np.testing.assert_allclose(out_g.to_numpy()[free], g_np[free], rtol=1e-12)
    assert not g_np[~free].any()
    np.testing.assert_allclose(fd_gradient(lambda z: inertia_terms.inertia_energy_np(masses, h, z, y, free), x, 1e-6),
                               g_np, rtol=1e-6, atol=1e-6)
    diag = inertia_terms.inertia_hessian_diag_np(masses, h, free)
    blocks = out_H.to_numpy()
    np.testing.assert_allclose(np.einsum("iaa->ia", blocks)[free].ravel(), diag.reshape(-1, 3)[free].ravel())
    assert not (blocks - np.einsum("ia,ab->iab", np.einsum("iaa->ia", blocks), np.eye(3))).any()
    np.testing.assert_allclose(fd_jacobian(lambda z: inertia_terms.inertia_gradient_np(masses, h, z, y, free), x, 1e-6),
                               np.diag(diag), rtol=1e-6, atol=1e-6 * diag.max())


def test_ground_matches_its_twin_and_finite_differences():
    ground = solver.Ground(height=0.1, stiffness=3e4, friction=0.0)
    x = np.column_stack([rng.standard_normal((8, 2)), [-0.2, 0.05, 0.099, 0.3, 0.1 + 1e-3, -1.0, 0.5, 0.0]])
    free = np.ones(len(x), bool)
    free[6] = False
    x[6, 2] = -0.5                                       # a constrained vertex below the ground: no term
    n = len(x)
    out = ti.ndarray(ti.f64, (n, 4))
    out_f = ti.ndarray(ti.f64, (n, 3))
    out_H = ti.ndarray(ti.f64, (n, 3, 3))

    @ti.kernel
    def evaluate(x: ti.types.ndarray(), height: ti.f64, k_c: ti.f64, out: ti.types.ndarray(),
                 f: ti.types.ndarray(), H: ti.types.ndarray()):
        for i in range(x.shape[0]):
            xi = ti.Vector([x[i, 0], x[i, 1], x[i, 2]])
            out[i, 0] = ground_terms.ground_depth(xi[2], height)
            out[i, 1] = ground_terms.ground_energy(xi[2], height, k_c)
            out[i, 2] = ground_terms.ground_gradient_z(xi[2], height, k_c)
            out[i, 3] = ground_terms.ground_hessian_zz(xi[2], height, k_c)
            fi, Hi = ground_terms.ground_force_hessian(xi, ti.Vector.zero(ti.f64, 3), 1 / 60, height, k_c, 0.0,
                                                       1e-3, ti.f64)
            for a in ti.static(range(3)):
                f[i, a] = fi[a]
                for b in ti.static(range(3)):
                    H[i, a, b] = Hi[a, b]

    evaluate(x, ground.height, ground.stiffness, out, out_f, out_H)
    r = out.to_numpy()
    np.testing.assert_allclose(r[free, 0], ground_terms.ground_depth_np(ground, x, free)[free], rtol=1e-14)
    assert r[free, 1].sum() == pytest.approx(ground_terms.ground_energy_np(ground, x, free), rel=1e-12)
    g_np = ground_terms.ground_gradient_np(ground, x, free)
    np.testing.assert_allclose(r[free, 2], g_np[free, 2], rtol=1e-12)
    assert not g_np[:, :2].any() and not g_np[~free].any()
    np.testing.assert_allclose(r[free, 3], ground_terms.ground_hessian_diag_np(ground, x, free)[2::3][free])
    assert (r[:, 3] > 0).tolist() == (x[:, 2] < ground.height).tolist()
    # the sweep's block without friction is -gradient and the Hessian
    np.testing.assert_allclose(out_f.to_numpy()[:, 2], -r[:, 2], rtol=1e-12)
    np.testing.assert_allclose(out_H.to_numpy()[:, 2, 2], r[:, 3])
    eps = 1e-7
    fd = fd_gradient(lambda z: ground_terms.ground_energy_np(ground, z, free), x, eps)
    np.testing.assert_allclose(fd, g_np, rtol=1e-6, atol=1e-6)
    away = np.repeat(np.abs(x[:, 2] - ground.height) > 10 * eps, 3)          # off the kink of max(0, d)
    fd_H = fd_jacobian(lambda z: ground_terms.ground_gradient_np(ground, z, free), x, eps)
    np.testing.assert_allclose(fd_H[np.ix_(away, away)],
                               np.diag(ground_terms.ground_hessian_diag_np(ground, x, free))[np.ix_(away, away)],
                               rtol=1e-6, atol=1e-6 * ground.stiffness)


def test_ground_friction_opposes_the_tangential_motion():
    ground = solver.Ground(height=0.0, stiffness=1e4, friction=0.5, friction_speed=1e-3)
    out = ti.ndarray(ti.f64, (2, 3))

    @ti.kernel
    def evaluate(u_x: ti.f64, out: ti.types.ndarray()):
        f, H = ground_terms.ground_force_hessian(ti.Vector([0.0, 0.0, -0.01]), ti.Vector([u_x, 0.0, 0.0]), 1 / 60,
                                                 0.0, 1e4, 0.5, 1e-3, ti.f64)
        for a in ti.static(range(3)):
            out[0, a] = f[a]
            out[1, a] = H[a, a]

    evaluate(1.0, out)
    f, H = out.to_numpy()
    assert f[0] == pytest.approx(-0.5 * 1e4 * 0.01, rel=1e-12)      # sliding: |f_t| = mu f_n
    assert f[2] == pytest.approx(1e4 * 0.01) and H[2] == pytest.approx(1e4)


def random_tet():
    X = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.12, 0.0], [0.01, 0.02, 0.09]])
    tets = np.array([[0, 1, 2, 3]])
    x = X @ (np.eye(3) + 0.25 * rng.standard_normal((3, 3))).T + 0.01 * rng.standard_normal((4, 3))
    return X, tets, x


def test_elasticity_per_tet_matches_its_twin_and_finite_differences():
    """deformation_gradient, vertex_gradients and tet_hessian_block (Taichi) against the numpy twins, the
    twins against central differences of vol Psi(F(x)), and the sweep's per-vertex vertex_force_hessian
    against row k of the gradient and diagonal block (k, k)."""
    mat = solver.Material(2e5, 0.35, 1000.0)
    mu, lam = mat.mu, mat.lam
    X, tets, x = random_tet()
    rest = rest_geometry(X, tets)
    vol = rest.volumes
    out_F = ti.ndarray(ti.f64, (3, 3))
    out_E = ti.ndarray(ti.f64, 1)
    out_g = ti.ndarray(ti.f64, (4, 3))
    out_H = ti.ndarray(ti.f64, (4, 4, 3, 3))
    out_v = ti.ndarray(ti.f64, (4, 3))
    out_vH = ti.ndarray(ti.f64, (4, 3, 3))

    @ti.kernel
    def evaluate(x: ti.types.ndarray(), rows: ti.types.ndarray(), vol: ti.f64, mu: ti.f64, lam: ti.f64,
                 out_F: ti.types.ndarray(), out_E: ti.types.ndarray(), out_g: ti.types.ndarray(),
                 out_H: ti.types.ndarray(), out_v: ti.types.ndarray(), out_vH: ti.types.ndarray()):
        for _ in range(1):
            m = ti.Matrix.zero(ti.f64, 4, 3)
            p = ti.Matrix.zero(ti.f64, 4, 3)
            for k, c in ti.static(ti.ndrange(4, 3)):
                m[k, c] = rows[0, k, c]
                p[k, c] = x[k, c]
            Dm_inv = ti.Matrix.zero(ti.f64, 3, 3)
            for k, c in ti.static(ti.ndrange(3, 3)):
                Dm_inv[k, c] = m[k + 1, c]
            F = deformation_gradient(ti.Vector([p[0, 0], p[0, 1], p[0, 2]]), ti.Vector([p[1, 0], p[1, 1], p[1, 2]]),
                                     ti.Vector([p[2, 0], p[2, 1], p[2, 2]]), ti.Vector([p[3, 0], p[3, 1], p[3, 2]]),
                                     Dm_inv)
            J = F.determinant()
            C = cofactor(F)
            for a, b in ti.static(ti.ndrange(3, 3)):
                out_F[a, b] = F[a, b]
            out_E[0] = vol * psi(F, mu, lam)
            g = vol * vertex_gradients(dpsi_dF(F, mu, lam), Dm_inv)
            for k in range(4):                   # loops, not unrolled: quicker to compile
                m_k = ti.Vector([m[k, 0], m[k, 1], m[k, 2]])
                f_k, H_kk = vertex_force_hessian(F @ m_k, J, C @ m_k, m_k.dot(m_k), vol, mu, lam)
                for a in ti.static(range(3)):
                    out_g[k, a] = g[k, a]
                    out_v[k, a] = f_k[a]
                    for b in ti.static(range(3)):
                        out_vH[k, a, b] = H_kk[a, b]
                for l in range(4):
                    m_l = ti.Vector([m[l, 0], m[l, 1], m[l, 2]])
                    block = tet_hessian_block(F, J, C @ m_k, C @ m_l, m_k, m_l, vol, mu, lam)
                    for a, b in ti.static(ti.ndrange(3, 3)):
                        out_H[k, l, a, b] = block[a, b]

    evaluate(x, np.ascontiguousarray(rest.grad_rows), float(vol[0]), mu, lam, out_F, out_E, out_g, out_H, out_v,
             out_vH)
    F_np = deformation_gradient_np(x, tets, rest.Dm_inv)
    np.testing.assert_allclose(out_F.to_numpy(), F_np[0], rtol=1e-12, atol=1e-14)
    assert out_E.to_numpy()[0] == pytest.approx(vol[0] * psi_np(F_np[0], mu, lam), rel=1e-12)
    g_np = tet_gradients_np(F_np, rest.Dm_inv, vol, mu, lam)[0]
    H_np = tet_hessian_blocks_np(F_np, rest.Dm_inv, vol, mu, lam)[0]
    scale = np.abs(g_np).max()
    np.testing.assert_allclose(out_g.to_numpy(), g_np, rtol=1e-10, atol=1e-12 * scale)
    np.testing.assert_allclose(out_H.to_numpy(), H_np, rtol=1e-9, atol=1e-11 * np.abs(H_np).max())

    def energy(z):
        return float(vol[0] * psi_np(deformation_gradient_np(z, tets, rest.Dm_inv)[0], mu, lam))

    def gradient(z):
        return tet_gradients_np(deformation_gradient_np(z, tets, rest.Dm_inv), rest.Dm_inv, vol, mu, lam)[0]

    np.testing.assert_allclose(fd_gradient(energy, x, 1e-7), g_np, rtol=1e-5, atol=1e-6 * scale)
    fd_H = np.stack([fd_gradient(lambda z: gradient(z)[l // 3, l % 3], x, 1e-7) for l in range(12)])
    np.testing.assert_allclose(fd_H.reshape(4, 3, 4, 3).transpose(2, 0, 3, 1), H_np, rtol=1e-5,
                               atol=1e-6 * np.abs(H_np).max())
    # the sweep's per-vertex form: f_i = -row i of the gradient, H_i = diagonal block (i, i)
    np.testing.assert_allclose(out_v.to_numpy(), -g_np, rtol=1e-10, atol=1e-12 * scale)
    np.testing.assert_allclose(out_vH.to_numpy(), H_np[np.arange(4), np.arange(4)], rtol=1e-10,
                               atol=1e-12 * np.abs(H_np).max())
    # elastic forces of a tet sum to zero (translation invariance)
    np.testing.assert_allclose(g_np.sum(axis=0), 0.0, atol=1e-9 * scale)


def test_stress_hessian_entries_match_the_numpy_twin():
    """d2psi_dF2_entry (Taichi, read by the Newton Hessian and the PCG products) against d2psi_dF2_np,
    which tests/test_material.py checks against finite differences of the stress."""
    mat = solver.Material(1e5, 0.45, 1000.0)
    Fs = np.eye(3) + 0.4 * rng.standard_normal((6, 3, 3))
    Fs[0] = np.diag([1.2, 0.9, -0.3])                                  # an inverted F too
    out = ti.ndarray(ti.f64, (len(Fs), 3, 3, 3, 3))

    @ti.kernel
    def evaluate(Fs: ti.types.ndarray(), mu: ti.f64, lam: ti.f64, out: ti.types.ndarray()):
        for n in range(Fs.shape[0]):
            F = ti.Matrix.zero(ti.f64, 3, 3)
            for a, b in ti.static(ti.ndrange(3, 3)):
                F[a, b] = Fs[n, a, b]
            C, J = cofactor(F), F.determinant()
            for a, b, c, d in ti.ndrange(3, 3, 3, 3):
                out[n, a, b, c, d] = d2psi_dF2_entry(F, C, J, a, b, c, d, mu, lam)

    evaluate(Fs, mat.mu, mat.lam, out)
    expected = d2psi_dF2_np(Fs, mat.mu, mat.lam)
    np.testing.assert_allclose(out.to_numpy(), expected, rtol=1e-12, atol=1e-12 * np.abs(expected).max())
