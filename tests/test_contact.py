"""Contact between bodies, the term of G (solver/physics/contact.py): settings, exact distances, the
two-stage barrier against finite differences, the ti.funcs against their numpy twins, friction."""
from fractions import Fraction

import numpy as np
import pytest

import solver
from solver._ti import ti
from solver.physics import contact as C
from solver.physics.contact import PairKind

pytestmark = pytest.mark.backend   # compiles Taichi kernels: re-run on CUDA

VT, EE = int(PairKind.VERTEX_TRIANGLE), int(PairKind.EDGE_EDGE)
CONTACT = solver.Contact(stiffness=1e5, radius=0.1)


# ---------------------------------------------------------------------------------------------
# Settings
# ---------------------------------------------------------------------------------------------
def test_defaults_and_query_radius():
    c = solver.Contact()
    assert c.query_radius == pytest.approx(3 * c.radius)
    assert solver.Contact(radius=1e-3, query_radius=5e-3).query_radius == 5e-3
    with pytest.raises(Exception):
        c.radius = 1.0


@pytest.mark.parametrize("kwargs,match", [
    ({"stiffness": 0}, "stiffness"), ({"stiffness": -1.0}, "stiffness"), ({"stiffness": "1e5"}, "stiffness"),
    ({"stiffness": True}, "stiffness"), ({"radius": 0.0}, "radius"), ({"radius": -1e-3}, "radius"),
    ({"query_radius": 2e-3}, "query_radius"), ({"query_radius": 1e-3}, "query_radius"),
    ({"friction": -0.1}, "friction"), ({"friction_speed": 0.0}, "friction_speed"),
    ({"detection_interval": 0}, "detection_interval"), ({"detection_interval": 2.5}, "detection_interval"),
    ({"detection_interval": True}, "detection_interval"), ({"bound_relaxation": 0.5}, "bound_relaxation"),
    ({"bound_relaxation": 0.0}, "bound_relaxation"), ({"self_contact": 1}, "self_contact"),
    ({"stiffness": float("nan")}, "stiffness"), ({"stiffness": 10 ** 400}, "stiffness must be a finite number"),
    ({"radius": 1e308}, "radius must be a finite number of metres whose 3 x"),
])
def test_bad_settings_are_one_line_config_errors(kwargs, match):
    with pytest.raises(solver.ConfigError, match=match) as err:
        solver.Contact(**kwargs)
    assert "\n" not in str(err.value) and len(str(err.value)) < 200


def test_numbers_of_any_real_type_are_stored_as_floats():
    """A Fraction, an int or a numpy scalar is a number of N/m or m like any other (a Fraction raised
    numpy's TypeError from isfinite)."""
    c = solver.Contact(stiffness=Fraction(1, 2), radius=np.float32(0.25), friction=1)
    assert (c.stiffness, c.radius, c.query_radius, c.friction) == (0.5, 0.25, 0.75, 1.0)
    assert all(type(v) is float for v in (c.stiffness, c.radius, c.query_radius, c.friction))


# ---------------------------------------------------------------------------------------------
# Configurations: (kind, X (4, 3)) with the distance they must have
# ---------------------------------------------------------------------------------------------
TRI = np.array([[0.0, 0.0, 0.0], [0.3, 0.0, 0.0], [0.0, 0.3, 0.0]])


def _cases(d):
    """Pairs at distance d: closest point inside the triangle, on an edge, at a vertex; skew edges
    crossing inside, edge ending against the other's interior, endpoints nearest."""
    s = np.sqrt(0.5)
    return {
        "vt_face": (VT, np.vstack([[0.1, 0.05, d], TRI])),
        "vt_edge": (VT, np.vstack([[0.1, -d * 0.6, d * 0.8], TRI])),
        "vt_vertex": (VT, np.vstack([[-d * s, -d * s, 0.0], TRI])),
        "ee_cross": (EE, np.array([[-0.1, 0.02, 0.0], [0.2, 0.05, 0.0], [0.03, -0.1, d], [0.06, 0.2, d]])),
        "ee_end": (EE, np.array([[0.0, 0.0, 0.0], [0.3, 0.0, 0.0], [0.1, -0.2, d], [0.12, 0.0, d]])),
        "ee_corner": (EE, np.array([[0.0, 0.0, 0.0], [0.3, 0.0, 0.0], [0.3 + d * s, d * s, 0.0],
                                    [0.5, 0.2, 0.05]])),
    }


# Three kernels, not one: Taichi's optimisation of one kernel holding all of this (two 12x12 Hessians
# beside the forces) took 40-48 s to compile here, longer than the three apart.
@ti.kernel
def _vertex_terms(kind: ti.types.ndarray(), X: ti.types.ndarray(), X_n: ti.types.ndarray(), k: ti.f64,
                  r: ti.f64, mu: ti.f64, eps_u: ti.f64, d_out: ti.types.ndarray(), w_out: ti.types.ndarray(),
                  force: ti.types.ndarray(), block: ti.types.ndarray(), friction: ti.types.ndarray(),
                  friction_block: ti.types.ndarray()):
    for p in range(kind.shape[0]):
        d, w, n = C.pair_geometry(kind[p], X[p, 0], X[p, 1], X[p, 2], X[p, 3], ti.f64)
        d_out[p] = d
        db, _ = C.barrier_derivatives(d, k, r)
        u = ti.Vector.zero(ti.f64, 3)
        for j in ti.static(range(4)):
            u += w[j] * (X[p, j] - X_n[p, j])
        for j in ti.static(range(4)):
            w_out[p, j] = w[j]
            force[p, j], block[p, j] = C.contact_force_hessian(d, w[j], n, k, r)
            friction[p, j], friction_block[p, j] = C.contact_friction(u, n, w[j], ti.abs(db), mu, eps_u, ti.f64)


@ti.kernel
def _energy_gradient(kind: ti.types.ndarray(), X: ti.types.ndarray(), k: ti.f64, r: ti.f64,
                     energy: ti.types.ndarray(), gradient: ti.types.ndarray()):
    for p in range(kind.shape[0]):
        b, g = C.pair_energy_gradient(kind[p], X[p, 0], X[p, 1], X[p, 2], X[p, 3], k, r, ti.f64)
        energy[p] = b
        for a in ti.static(range(12)):
            gradient[p, a] = g[a]


@ti.kernel
def _hessian(kind: ti.types.ndarray(), X: ti.types.ndarray(), k: ti.f64, r: ti.f64, exact: ti.i32,
             hessian: ti.types.ndarray()):
    for p in range(kind.shape[0]):
        c = C.pair_curvature(kind[p], X[p, 0], X[p, 1], X[p, 2], X[p, 3], k, r, exact)
        for j, l in ti.ndrange(4, 4):
            block = C.pair_hessian_block(c, j, l)
            for a, b in ti.static(ti.ndrange(3, 3)):
                hessian[p, 3 * j + a, 3 * l + b] = block[a, b]


def taichi_twin(kind, X, X_n, contact, h):
    """Everything the ti.funcs give for pairs (kind (P,), X (P, 4, 3)), as numpy arrays."""
    solver.ensure_taichi()
    P = len(kind)
    vec = lambda shape: ti.Vector.ndarray(3, ti.f64, shape)
    mat = lambda shape: ti.Matrix.ndarray(3, 3, ti.f64, shape)
    args = dict(kind=ti.ndarray(ti.i32, P), X=vec((P, 4)), X_n=vec((P, 4)))
    args["kind"].from_numpy(np.asarray(kind, dtype=np.int32))
    args["X"].from_numpy(np.asarray(X, dtype=np.float64))
    args["X_n"].from_numpy(np.asarray(X_n, dtype=np.float64))
    out = dict(d_out=ti.ndarray(ti.f64, P), w_out=ti.ndarray(ti.f64, (P, 4)), energy=ti.ndarray(ti.f64, P),
               force=vec((P, 4)), block=mat((P, 4)), friction=vec((P, 4)), friction_block=mat((P, 4)),
               gradient=ti.ndarray(ti.f64, (P, 12)), hessian=ti.ndarray(ti.f64, (P, 12, 12)),
               exact_hessian=ti.ndarray(ti.f64, (P, 12, 12)))
    k, r = contact.stiffness, contact.radius
    _vertex_terms(args["kind"], args["X"], args["X_n"], k, r, contact.friction, contact.friction_speed * h,
                  out["d_out"], out["w_out"], out["force"], out["block"], out["friction"], out["friction_block"])
    _energy_gradient(args["kind"], args["X"], k, r, out["energy"], out["gradient"])
    _hessian(args["kind"], args["X"], k, r, 0, out["hessian"])
    _hessian(args["kind"], args["X"], k, r, 1, out["exact_hessian"])
    return {name: a.to_numpy() for name, a in out.items()}


def _energy(kind, X, contact=CONTACT):
    return C.pair_energy_np(np.array([kind]), X[None], contact)[0]


STEPS = np.eye(12).reshape(12, 4, 3)        # one coordinate of one vertex moved, for each of the 12


def _fd_forces_all(kind, X, contact=CONTACT, eps=1e-8):
    """-dE/dX (P, 4, 3) of the pairs (kind (P,), X (P, 4, 3)) by central differences, all at once."""
    P = len(kind)
    kinds = np.repeat(kind, 12)
    plus = C.pair_energy_np(kinds, (X[:, None] + eps * STEPS).reshape(-1, 4, 3), contact).reshape(P, 12)
    minus = C.pair_energy_np(kinds, (X[:, None] - eps * STEPS).reshape(-1, 4, 3), contact).reshape(P, 12)
    return (-(plus - minus) / (2 * eps)).reshape(P, 4, 3)


def _fd_forces(kind, X, contact=CONTACT, eps=1e-8):
    """-dE/dX (4, 3) of one pair by central differences."""
    return _fd_forces_all(np.array([kind]), X[None], contact, eps)[0]


# ---------------------------------------------------------------------------------------------
# Distances, forces, blocks
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("d", [0.02, 0.07])   # below tau = r/2 (log stage), between tau and r (quadratic)
@pytest.mark.parametrize("case", list(_cases(0.05)))
def test_distance_and_forces_match_finite_differences_in_both_stages(case, d):
    kind, X = _cases(d)[case]
    dist, w, n = C.pair_geometry_np(np.array([kind]), X[None])
    assert dist[0] == pytest.approx(d, rel=1e-12)
    np.testing.assert_allclose(w[0].sum(), 0.0, atol=1e-14)       # closest points are affine combinations
    f = C.pair_forces_np(np.array([kind]), X[None], CONTACT)[0]
    fd = _fd_forces(kind, X)
    assert np.linalg.norm(f - fd) <= 1e-6 * np.linalg.norm(f)
    np.testing.assert_allclose(f.sum(axis=0), 0.0, atol=1e-9 * np.abs(f).max())   # a pair's forces cancel


def _random_pairs(rng, count):
    """Random vertex-triangle and edge-edge pairs in a box of the contact radius (some beyond it)."""
    kind = rng.integers(0, 2, count)
    X = rng.uniform(-0.08, 0.08, (count, 4, 3))
    return kind, X


def test_forces_match_finite_differences_on_random_pairs():
    rng = np.random.default_rng(3)
    kind, X = _random_pairs(rng, 300)
    d, _, _ = C.pair_geometry_np(kind, X)
    tau, r = CONTACT.radius / 2, CONTACT.radius
    keep = (d > 1e-3) & (np.abs(d - tau) > 1e-4) & (d < r - 1e-4)
    assert keep.sum() > 150
    forces = C.pair_forces_np(kind, X, CONTACT)
    fd = _fd_forces_all(kind[keep], X[keep])
    for p, fd_p in zip(np.flatnonzero(keep), fd):
        assert np.linalg.norm(forces[p] - fd_p) <= 1e-6 * np.linalg.norm(forces[p]), (p, kind[p])


def test_distance_is_the_least_over_sampled_points():
    """The exact distance is no more than the distance of any two sampled points of the primitives, and
    the closest points it reports are on them (weights in range) at that distance."""
    rng = np.random.default_rng(5)
    kind, X = _random_pairs(rng, 200)
    d, w, n = C.pair_geometry_np(kind, X)
    u = rng.uniform(0, 1, (4000, 2))
    tri = np.column_stack([1 - np.sqrt(u[:, 0]), np.sqrt(u[:, 0]) * (1 - u[:, 1]), np.sqrt(u[:, 0]) * u[:, 1]])
    seg = np.linspace(0, 1, 65)
    for p in range(len(kind)):
        if kind[p] == VT:
            sampled = np.linalg.norm(X[p, 0] - tri @ X[p, 1:], axis=1).min()
            assert w[p, 0] == 1 and (w[p, 1:] <= 0).all()
        else:
            A = X[p, 0] + seg[:, None] * (X[p, 1] - X[p, 0])
            B = X[p, 2] + seg[:, None] * (X[p, 3] - X[p, 2])
            sampled = np.linalg.norm(A[:, None] - B[None], axis=2).min()
            assert (w[p, :2] >= 0).all() and (w[p, 2:] <= 0).all()
        assert d[p] <= sampled + 1e-12
        assert np.linalg.norm(w[p] @ X[p]) == pytest.approx(d[p], rel=1e-12)
    assert np.allclose(np.linalg.norm(n, axis=1), 1.0)


def test_degenerate_pairs_parallel_edges_and_flat_triangle():
    d0 = 0.03
    parallel = np.array([[0.0, 0.0, 0.0], [0.3, 0.0, 0.0], [0.1, 0.0, d0], [0.5, 0.0, d0]])
    collinear_gap = np.array([[0.0, 0.0, 0.0], [0.3, 0.0, 0.0], [0.3 + d0, 0.0, 0.0], [0.5, 0.0, 0.0]])
    flat_triangle = np.array([[0.1, d0, 0.0], [0.0, 0.0, 0.0], [0.2, 0.0, 0.0], [0.4, 0.0, 0.0]])
    kind = np.array([EE, EE, VT])
    X = np.stack([parallel, collinear_gap, flat_triangle])
    d, w, n = C.pair_geometry_np(kind, X)
    np.testing.assert_allclose(d, d0, rtol=1e-12)
    forces = C.pair_forces_np(kind, X, CONTACT)
    assert np.isfinite(forces).all()
    np.testing.assert_allclose(forces.sum(axis=1), 0.0, atol=1e-9)
    # moving the first primitive as a whole along n changes the energy by -(its force) . step
    for p in range(3):
        first = [0] if kind[p] == VT else [0, 1]
        eps = 1e-8
        Xp, Xm = X[p].copy(), X[p].copy()
        Xp[first] += eps * n[p]
        Xm[first] -= eps * n[p]
        slope = (_energy(kind[p], Xp) - _energy(kind[p], Xm)) / (2 * eps)
        assert -slope == pytest.approx(forces[p, first].sum(axis=0) @ n[p], rel=1e-6)
    got = taichi_twin(kind, X, X, CONTACT, 1 / 60)
    np.testing.assert_allclose(got["d_out"], d, rtol=1e-12)
    np.testing.assert_allclose(got["force"], forces, rtol=1e-10, atol=1e-9)


def test_barrier_is_c2_at_half_radius_and_vanishes_beyond_radius():
    k, r = CONTACT.stiffness, CONTACT.radius
    tau = r / 2
    for x, orders in ((tau, 3), (r, 2)):     # b, b', b'' continuous at tau; b, b' at r (b'' drops k -> 0)
        lo, hi = x * (1 - 1e-9), x * (1 + 1e-9)
        for v_lo, v_hi in list(zip((C.barrier_np(lo, k, r), *C.barrier_derivatives_np(lo, k, r)),
                                   (C.barrier_np(hi, k, r), *C.barrier_derivatives_np(hi, k, r))))[:orders]:
            assert v_lo == pytest.approx(v_hi, rel=1e-6, abs=1e-3)
    assert C.barrier_np(1.2 * r, k, r) == 0 and C.barrier_derivatives_np(1.2 * r, k, r) == (0, 0)
    assert C.barrier_np(0.0, k, r) == np.inf
    d = np.linspace(0.01, 0.099, 50)
    db, d2b = C.barrier_derivatives_np(d, k, r)
    h = 1e-7
    np.testing.assert_allclose(db, (C.barrier_np(d + h, k, r) - C.barrier_np(d - h, k, r)) / (2 * h), rtol=1e-6)
    np.testing.assert_allclose(d2b, (C.barrier_derivatives_np(d + h, k, r)[0]
                                     - C.barrier_derivatives_np(d - h, k, r)[0]) / (2 * h), rtol=1e-6)


def _fd_hessians(kind, X, eps):
    """d2E/dX2 (P, 12, 12) of the pairs (kind (P,), X (P, 4, 3)) by central differences of the numpy forces,
    all at once."""
    P = len(kind)
    kinds = np.repeat(kind, 12)
    plus = C.pair_forces_np(kinds, (X[:, None] + eps * STEPS).reshape(-1, 4, 3), CONTACT).reshape(P, 12, 12)
    minus = C.pair_forces_np(kinds, (X[:, None] - eps * STEPS).reshape(-1, 4, 3), CONTACT).reshape(P, 12, 12)
    return (-(plus - minus) / (2 * eps)).transpose(0, 2, 1)     # column a: the forces' change along a


def _near_parallel_edges(degrees, d):
    """Overlapping edges d apart whose directions differ by `degrees`: the closest points inside both."""
    th = np.radians(degrees)
    return EE, np.array([[0.0, 0.0, 0.0], [0.3, 0.0, 0.0], [0.05, -0.1 * np.sin(th), d],
                         [0.05 + 0.2 * np.cos(th), 0.1 * np.sin(th), d]])


def test_exact_pair_hessian_matches_finite_differences():
    """b''(d) J J^T + b'(d) d2d/dx2 is the Hessian of the pair energy for 0, 1 and 2 free closest-point
    parameters (vertex, edge, face; endpoint, edge, both edges), in both stages, and for edges 1 and 0.1
    degrees from parallel, where the curvature term is thousands of times the PSD part."""
    rng = np.random.default_rng(5)
    kind, X = _random_pairs(rng, 300)
    d, w, _ = C.pair_geometry_np(kind, X)
    keep = (d > 1e-3) & (np.abs(d - CONTACT.radius / 2) > 1e-4) & (d < CONTACT.radius - 1e-4)
    kind, X = kind[keep], X[keep]
    _, m = C.free_directions_np(kind, C.pair_geometry_np(kind, X)[1])
    for k in (VT, EE):
        assert np.bincount(m[kind == k], minlength=3).min() >= 10       # every case of the formula is checked
    cases = [c for dist in (0.02, 0.07) for name, c in _cases(dist).items()
             if name != "ee_end"]       # ee_end's closest point sits exactly where t leaves (0, 1): a kink
    cases += [_near_parallel_edges(deg, dist) for deg in (1.0, 0.1) for dist in (0.03, 0.07)]
    kind = np.concatenate([kind, [c[0] for c in cases]])
    X = np.concatenate([X, np.stack([c[1] for c in cases])])
    H = C.pair_hessian_np(kind, X, CONTACT, exact=True)
    np.testing.assert_allclose(H, H.transpose(0, 2, 1), rtol=0, atol=1e-12 * np.abs(H).max())
    for p, fd in enumerate(_fd_hessians(kind, X, 1e-7)):
        assert np.linalg.norm(H[p] - fd) <= 1e-6 * np.linalg.norm(fd), (p, kind[p])
    psd = C.pair_hessian_np(kind, X, CONTACT)
    assert np.linalg.norm(H[-2]) > 1e3 * np.linalg.norm(psd[-2])      # 0.1 degrees, d = 0.03


def test_blocks_and_pair_hessian_are_psd_and_consistent():
    rng = np.random.default_rng(7)
    kind, X = _random_pairs(rng, 200)
    blocks = C.pair_blocks_np(kind, X, CONTACT)
    H = C.pair_hessian_np(kind, X, CONTACT)
    assert np.linalg.eigvalsh(blocks).min() >= -1e-9 * np.abs(blocks).max()
    assert np.linalg.eigvalsh(H).min() >= -1e-9 * np.abs(H).max()
    for j in range(4):                  # the per-vertex blocks are the diagonal blocks of the pair Hessian
        np.testing.assert_allclose(H[:, 3 * j:3 * j + 3, 3 * j:3 * j + 3], blocks[:, j], rtol=1e-12, atol=1e-12)
    # moving the first primitive rigidly along n moves d one for one: there H is the exact b''(d)
    d, w, n = C.pair_geometry_np(kind, X)
    for p in np.flatnonzero((d > 0.01) & (d < 0.09) & (np.abs(d - 0.05) > 1e-3))[:20]:
        first = [0] if kind[p] == VT else [0, 1]
        dirn = np.zeros((4, 3))
        dirn[first] = n[p]
        e = 1e-5
        second = (_energy(kind[p], X[p] + e * dirn) - 2 * _energy(kind[p], X[p])
                  + _energy(kind[p], X[p] - e * dirn)) / e ** 2
        assert dirn.ravel() @ H[p] @ dirn.ravel() == pytest.approx(second, rel=1e-4)


def test_taichi_funcs_agree_with_numpy_twins():
    rng = np.random.default_rng(11)
    kind, X = _random_pairs(rng, 400)
    cases = [_cases(d)[c] for d in (0.02, 0.07) for c in _cases(d)]
    kind = np.concatenate([kind, [c[0] for c in cases]])
    X = np.concatenate([X, np.stack([c[1] for c in cases])])
    X_n = X + rng.normal(0, 0.003, X.shape)
    contact = solver.Contact(stiffness=1e5, radius=0.1, friction=0.4, friction_speed=0.1)
    h = 1 / 60
    got = taichi_twin(kind, X, X_n, contact, h)
    d, w, _ = C.pair_geometry_np(kind, X)
    np.testing.assert_allclose(got["d_out"], d, rtol=1e-12)
    np.testing.assert_allclose(got["w_out"], w, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(got["energy"], C.pair_energy_np(kind, X, contact), rtol=1e-12)
    forces = C.pair_forces_np(kind, X, contact)
    np.testing.assert_allclose(got["force"], forces, rtol=1e-10, atol=1e-9)
    np.testing.assert_allclose(got["gradient"], -forces.reshape(-1, 12), rtol=1e-10, atol=1e-9)
    np.testing.assert_allclose(got["block"], C.pair_blocks_np(kind, X, contact), rtol=1e-10, atol=1e-6)
    np.testing.assert_allclose(got["hessian"], C.pair_hessian_np(kind, X, contact), rtol=1e-10, atol=1e-6)
    exact = C.pair_hessian_np(kind, X, contact, exact=True)
    scale = np.abs(exact).max(axis=(1, 2), keepdims=True)          # per pair: the curvature term spans decades
    assert (np.abs(got["exact_hessian"] - exact) <= 1e-10 * scale + 1e-9).all()
    f_fric, H_fric = C.pair_friction_np(kind, X, X_n, contact, h)
    np.testing.assert_allclose(got["friction"], f_fric, rtol=1e-10, atol=1e-9)
    np.testing.assert_allclose(got["friction_block"], H_fric, rtol=1e-10, atol=1e-6)


def test_friction_opposes_relative_sliding_and_saturates_at_coulomb():
    """Sliding the vertex over the triangle: friction on it opposes the slide, has no normal part, cancels
    over the pair, and equals mu |b'| once the slide exceeds friction_speed h (less below)."""
    contact = solver.Contact(stiffness=1e5, radius=0.1, friction=0.3, friction_speed=0.01)
    h = 0.1
    kind, X = _cases(0.04)["vt_face"]
    db, _ = C.barrier_derivatives_np(np.array([0.04]), contact.stiffness, contact.radius)
    for slide, full in ((0.01, True), (0.0005, False)):
        X_n = X.copy()
        X_n[0, 0] -= slide                  # the vertex moved +x by `slide` this step
        f, H = C.pair_friction_np(np.array([kind]), X[None], X_n[None], contact, h)
        f = f[0]
        assert f[0, 0] < 0 and abs(f[0, 2]) < 1e-12 and abs(f[0, 1]) < 1e-12
        np.testing.assert_allclose(f.sum(axis=0), 0.0, atol=1e-9)
        coulomb = contact.friction * abs(db[0])
        if full:
            assert -f[0, 0] == pytest.approx(coulomb, rel=1e-12)
        else:
            assert 0 < -f[0, 0] < coulomb
        assert np.linalg.eigvalsh(H[0]).min() >= -1e-9


def test_sums_over_pairs_for_the_newton_reference():
    """contact_energy_np/gradient_np/hessian_np on a mesh of shaken bodies: the gradient is the finite
    difference of the energy, the Hessian is symmetric PSD and assembled at the pairs' vertices."""
    from solver.physics.contact_detection import find_pairs_np, rest_exclusions_np
    from solver.mesh.bodies import body_labels
    from solver.mesh.surface import surface_primitives

    rng = np.random.default_rng(2)
    cube = solver.box_mesh(size=(0.1, 0.1, 0.1), cells=(1, 1, 1))
    mesh = solver.merge_meshes([cube, solver.TetMesh(cube.vertices + [0.02, 0.03, 0.11], cube.tets)])
    contact = solver.Contact(stiffness=1e4, radius=0.03)
    surface, bodies = surface_primitives(mesh.tets), body_labels(mesh.tets, mesh.n_vertices)
    free = np.ones(mesh.n_vertices, bool)
    excluded = rest_exclusions_np(mesh.vertices, surface, bodies, contact)
    x = mesh.vertices + rng.normal(0, 0.002, mesh.vertices.shape)
    kind, vertices, _, distance = find_pairs_np(x, surface, bodies, free, contact, excluded)
    assert (distance < contact.radius).sum() > 4
    E = C.contact_energy_np(x, kind, vertices, contact)
    assert E == pytest.approx(C.pair_energy_np(kind, x[vertices], contact).sum()) and E > 0
    g = C.contact_gradient_np(x, kind, vertices, contact)
    eps = 1e-8
    fd = np.zeros_like(x)
    for i in np.unique(vertices):
        for a in range(3):
            xp, xm = x.copy(), x.copy()
            xp[i, a] += eps
            xm[i, a] -= eps
            fd[i, a] = (C.contact_energy_np(xp, kind, vertices, contact)
                        - C.contact_energy_np(xm, kind, vertices, contact)) / (2 * eps)
    assert np.linalg.norm(g - fd) <= 1e-6 * np.linalg.norm(g)
    np.testing.assert_allclose(g.sum(axis=0), 0.0, atol=1e-9 * np.abs(g).max())
    H = C.contact_hessian_np(x, kind, vertices, contact).toarray()
    np.testing.assert_allclose(H, H.T, atol=1e-9 * np.abs(H).max())
    assert np.linalg.eigvalsh(H).min() >= -1e-9 * np.abs(H).max()
    # assembled at the right places: u^T H u = sum over pairs of b''(d) (sum_j w_j n . u_j)^2
    d, w, n = C.pair_geometry_np(kind, x[vertices])
    _, d2b = C.barrier_derivatives_np(d, contact.stiffness, contact.radius)
    u = rng.normal(size=x.shape)
    along = np.einsum("pj,pa,pja->p", w, n, u[vertices])
    assert u.ravel() @ H @ u.ravel() == pytest.approx(np.sum(d2b * along ** 2), rel=1e-12)
