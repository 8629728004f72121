"""Contact detection (solver/physics/contact_detection.py): the hashed grid finds exactly the pairs a
brute-force numpy search finds, with their incidence lists and bounds, deterministically."""
import numpy as np
import pytest

import solver
from solver._ti import ti
from solver.mesh.bodies import body_labels
from solver.mesh.surface import surface_primitives
from solver.physics.contact import PairKind, edge_edge_np, point_triangle_np
from solver.physics.contact_detection import ContactDetector

pytestmark = pytest.mark.backend   # compiles Taichi kernels: re-run on CUDA

VT, EE = int(PairKind.VERTEX_TRIANGLE), int(PairKind.EDGE_EDGE)


def brute_force_pairs(mesh, x, free, contact):
    """{(kind, primitive, primitive): distance} of every pair of the model, by trying all of them."""
    surface = surface_primitives(mesh.tets)
    body = body_labels(mesh.tets, mesh.n_vertices)
    q = contact.query_radius
    found = {}
    V, T = np.meshgrid(surface.vertices, np.arange(len(surface.triangles)), indexing="ij")
    V, T = V.ravel(), T.ravel()
    tri = surface.triangles[T]
    vt_sets = [(V, T, V[:, None], tri, lambda y: point_triangle_np(y[V], *(y[tri[:, k]] for k in range(3)))[0])]
    A, B = np.triu_indices(len(surface.edges), k=1)
    ea, eb = surface.edges[A], surface.edges[B]
    ee_sets = [(A, B, ea, eb, lambda y: edge_edge_np(y[ea[:, 0]], y[ea[:, 1]], y[eb[:, 0]], y[eb[:, 1]])[0])]
    for kind, (P0, P1, left, right, dist) in [(VT, vt_sets[0]), (EE, ee_sets[0])]:
        disjoint = ~(left[:, :, None] == right[:, None, :]).any(axis=(1, 2))
        same = body[left[:, 0]] == body[right[:, 0]]
        some_free = free[left].any(axis=1) | free[right].any(axis=1)
        keep = disjoint & some_free & (~same | (contact.self_contact & (dist(mesh.vertices) >= q)))
        d = dist(x)
        for i in np.flatnonzero(keep & (d < q)):
            found[(kind, int(P0[i]), int(P1[i]))] = d[i]
    return found


def _scene(rng, n_bodies=3):
    """Bodies of a few tets each, turned and placed at random in a small box, then shaken vertex by vertex."""
    mesh = solver.box_mesh(size=(0.2, 0.1, 0.1), cells=(2, 1, 1))
    placed = []
    for _ in range(n_bodies):
        Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        Q *= np.sign(np.linalg.det(Q))
        placed.append(solver.TetMesh((mesh.vertices - 0.05) @ Q.T + rng.uniform(0, 0.15, 3), mesh.tets))
    return solver.merge_meshes(placed)


def _positions(x):
    array = ti.Vector.ndarray(3, ti.f64, (1, len(x)))
    array.from_numpy(x[None])
    return array


@pytest.mark.parametrize("setting", ["default", "no_self", "fixed_body", "wide_query", "colliding_hash"])
def test_hash_grid_gives_the_brute_force_pairs_on_random_configurations(setting):
    solver.ensure_taichi()
    rng = np.random.default_rng(["default", "no_self", "fixed_body", "wide_query", "colliding_hash"].index(setting))
    mesh = _scene(rng)
    contact = solver.Contact(radius=0.01, query_radius=0.09 if setting == "wide_query" else 0.04,
                             self_contact=setting != "no_self")
    free = np.ones(mesh.n_vertices, dtype=bool)
    if setting == "fixed_body":
        free[body_labels(mesh.tets, mesh.n_vertices) == 1] = False
    detector = ContactDetector(mesh, free, contact)
    if setting == "colliding_hash":       # eight buckets: every bucket holds items of many cells
        detector._mask = 7
        detector._bucket_fill, detector._bucket_start = ti.ndarray(ti.i32, 8), ti.ndarray(ti.i32, 9)
        detector._bucket_fill.fill(0)
    if setting == "wide_query":
        assert sum(detector._n_excluded) > 0      # rest neighbours closer than q are excluded
    self_pairs = 0
    for _ in range(20):
        x = mesh.vertices + rng.normal(0, 0.015, mesh.vertices.shape)
        n = detector.detect(_positions(x))
        kind, vertices, primitives, distance = detector.pairs()
        got = {(int(k), int(a), int(b)): d for k, (a, b), d in zip(kind, primitives, distance)}
        want = brute_force_pairs(mesh, x, free, contact)
        assert len(got) == n                       # no pair twice
        assert got.keys() == want.keys()
        np.testing.assert_allclose([got[key] for key in want], list(want.values()), rtol=1e-10, atol=1e-14)
        body = detector.bodies
        self_pairs += int((body[vertices[:, 0]] == body[vertices[:, 3]]).sum())
        # incidence lists: vertex v lists exactly the pairs it belongs to, ascending; bounds from them
        offsets, ids = detector.vertex_pairs()
        bound = detector.bound.to_numpy()
        for v in range(mesh.n_vertices):
            mine = ids[offsets[v]:offsets[v + 1]]
            np.testing.assert_array_equal(mine, np.flatnonzero((vertices == v).any(axis=1)))
            nearest = min([contact.query_radius] + list(distance[mine]))
            assert bound[v] == pytest.approx(contact.bound_relaxation * nearest, rel=1e-12)
    if setting != "no_self":
        assert self_pairs > 0


def test_detection_is_deterministic_and_buffers_grow_without_dropping_pairs():
    solver.ensure_taichi()
    rng = np.random.default_rng(9)
    mesh = _scene(rng, n_bodies=4)
    contact = solver.Contact(radius=0.01, query_radius=0.05)
    detector = ContactDetector(mesh, np.ones(mesh.n_vertices, dtype=bool), contact)
    detector._allocate_pairs(1)                 # far too small: the detection must grow them
    detector._entries = ti.ndarray(ti.i32, 1)
    x = _positions(mesh.vertices + rng.normal(0, 0.01, mesh.vertices.shape))
    n = detector.detect(x)
    assert n > 1 and detector._capacity >= n and detector._entries.shape[0] > 1
    first = [a.copy() for a in detector.pairs()] + [a.copy() for a in detector.vertex_pairs()]
    capacity, entries = detector._capacity, detector._entries
    for _ in range(3):
        assert detector.detect(x) == n
        again = list(detector.pairs()) + list(detector.vertex_pairs())
        for a, b in zip(first, again):
            np.testing.assert_array_equal(a, b)
    assert detector._capacity == capacity and detector._entries is entries   # nothing allocated when nothing grows


def test_pairs_of_fixed_vertices_only_are_skipped():
    solver.ensure_taichi()
    a = solver.box_mesh(size=(0.1, 0.1, 0.1), cells=(1, 1, 1))
    mesh = solver.merge_meshes([a, solver.TetMesh(a.vertices + [0, 0, 0.11], a.tets)])
    contact = solver.Contact(radius=0.01, query_radius=0.03)
    x = _positions(mesh.vertices)
    assert ContactDetector(mesh, np.ones(mesh.n_vertices, bool), contact).detect(x) > 0
    assert ContactDetector(mesh, np.zeros(mesh.n_vertices, bool), contact).detect(x) == 0


def test_each_query_looks_up_exactly_its_own_exclusions():
    """The rest exclusions a query searches (excluded_range) are all the keys of its own primitive: a
    vertex v's vertex-triangle keys v T + t, an edge a's edge-edge keys a E + b."""
    solver.ensure_taichi()
    rng = np.random.default_rng(22)
    mesh = _scene(rng, n_bodies=3)
    detector = ContactDetector(mesh, np.ones(mesh.n_vertices, bool), solver.Contact(radius=0.01, query_radius=0.08))
    surface = detector.surface
    V, T, E = len(surface.vertices), len(surface.triangles), len(surface.edges)
    n_vt, n_ee = detector._n_excluded
    assert n_vt > 0 and n_ee > 0
    ranges = detector._excluded_range.to_numpy()
    for keys, queries, owner, size in ((detector._excluded_vt.to_numpy()[:n_vt], ranges[:V], surface.vertices, T),
                                       (detector._excluded_ee.to_numpy()[:n_ee], ranges[V:], np.arange(E), E)):
        assert (queries[:, 1] - queries[:, 0]).sum() == len(keys)     # every key in one query's range
        for (begin, end), own in zip(queries, owner):
            assert (keys[begin:end] // size == own).all()


def test_numpy_twin_finds_the_same_pairs_and_exclusions():
    from solver.physics.contact_detection import find_pairs_np, rest_exclusions_np, vertex_bounds_np

    solver.ensure_taichi()
    rng = np.random.default_rng(21)
    mesh = _scene(rng, n_bodies=4)
    contact = solver.Contact(radius=0.01, query_radius=0.08)
    free = rng.uniform(size=mesh.n_vertices) < 0.7
    detector = ContactDetector(mesh, free, contact)
    excluded = rest_exclusions_np(mesh.vertices, detector.surface, detector.bodies, contact)
    n_vt, n_ee = detector._n_excluded
    np.testing.assert_array_equal(excluded[0], detector._excluded_vt.to_numpy()[:n_vt])
    np.testing.assert_array_equal(excluded[1], detector._excluded_ee.to_numpy()[:n_ee])
    for _ in range(10):
        x = mesh.vertices + rng.normal(0, 0.015, mesh.vertices.shape)
        detector.detect(_positions(x))
        kind, vertices, primitives, distance = find_pairs_np(x, detector.surface, detector.bodies, free, contact,
                                                             excluded)
        kind_t, _, primitives_t, distance_t = detector.pairs()
        got = {(int(k), int(a), int(b)): d for k, (a, b), d in zip(kind_t, primitives_t, distance_t)}
        want = {(int(k), int(a), int(b)): d for k, (a, b), d in zip(kind, primitives, distance)}
        assert got.keys() == want.keys() and len(want) == len(kind) > 0
        np.testing.assert_allclose(vertex_bounds_np(mesh.n_vertices, vertices, distance, contact),
                                   detector.bound.to_numpy(), rtol=1e-10)
        np.testing.assert_allclose([got[key] for key in want], list(want.values()), rtol=1e-10, atol=1e-14)


def _turned(x, rng):
    """x (N, 3) turned by a random rotation about its centroid: a rigid motion."""
    Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    Q *= np.sign(np.linalg.det(Q))
    c = x.mean(axis=0)
    return (x - c) @ Q.T + c


def _bent(x, angle):
    """The bar x (N, 3) along x from 0 bent about the z axis into an arc of `angle` rad (its two ends meet
    near 2 pi): its own surfaces come close, and it is far from rigid."""
    L = x[:, 0].max()
    R = L / angle
    s, y = x[:, 0], x[:, 1]
    return np.stack([(R - y) * np.sin(s / R), R - (R - y) * np.cos(s / R), x[:, 2]], axis=1)


def test_bodies_that_cannot_have_pairs_are_left_out_and_the_pairs_stay_exact():
    """A body far from the others that moved almost rigidly is not searched (`active_bodies`); the pairs
    are still exactly the brute-force ones whether bodies are turned, shaken, brought together or bent."""
    from solver.physics.contact_detection import SEARCH_OTHERS, SEARCH_SELF

    solver.ensure_taichi()
    rng = np.random.default_rng(5)
    bar = solver.box_mesh(size=(0.3, 0.03, 0.03), cells=(10, 1, 1))
    cube = solver.box_mesh(size=(0.06, 0.06, 0.06), cells=(2, 2, 2), origin=(0.5, 0.0, 0.0))
    mesh = solver.merge_meshes([bar, cube])
    n_bar = bar.n_vertices
    contact = solver.Contact(radius=0.004, query_radius=0.015)
    free = np.ones(mesh.n_vertices, dtype=bool)
    detector = ContactDetector(mesh, free, contact)
    seen = set()
    for case in range(40):
        x = mesh.vertices.copy()
        x[:n_bar] = _turned(x[:n_bar], rng)
        x[n_bar:] = _turned(x[n_bar:], rng)
        if case % 4 == 1:                              # the cube beside the bar, within q of it
            x = mesh.vertices + np.where(np.arange(mesh.n_vertices)[:, None] < n_bar, 0.0,
                                         [-0.38, 0.03 + rng.uniform(0.004, 0.012), -0.015])
            x = _turned(x, rng)
        if case % 4 == 2:                              # shaken, by up to a few mm
            x += rng.normal(0, 10 ** rng.uniform(-4.5, -2.5), x.shape)
        if case % 4 == 3:                              # bent until its ends come near each other
            x[:n_bar] = _bent(mesh.vertices[:n_bar], rng.uniform(5.2, 5.9))
        n = detector.detect(_positions(x))
        flags = detector.active.to_numpy()
        kind, vertices, primitives, distance = detector.pairs()
        got = {(int(k), int(a), int(b)) for k, (a, b) in zip(kind, primitives)}
        want = brute_force_pairs(mesh, x, free, contact)
        assert got == want.keys() and n == len(want)
        self_pairs = any(detector.bodies[v[0]] == detector.bodies[v[3]] for v in vertices)
        if self_pairs:
            assert flags[detector.bodies[vertices[0, 0]]] & SEARCH_SELF
        near = any(detector.bodies[v[0]] != detector.bodies[v[3]] for v in vertices)
        assert bool(flags[0] & SEARCH_OTHERS) == bool(flags[1] & SEARCH_OTHERS)
        if near:
            assert flags[0] & SEARCH_OTHERS
        if case % 4 == 0:                              # turned only: nothing searched, every bound g q
            assert detector.active_count == 0 and n == 0
            np.testing.assert_allclose(detector.bound.to_numpy(), contact.bound_relaxation * contact.query_radius)
            np.testing.assert_array_equal(detector.vertex_pairs()[0], 0)
        seen.add((case % 4, bool(flags[0] & SEARCH_SELF), self_pairs, near))
    assert (3, True, True, False) in seen             # the bent bar was searched, and had self pairs
    assert any(case == 2 and not searched for case, searched, _, _ in seen)   # small shakes stay rigid
    assert any(case == 2 and searched for case, searched, _, _ in seen)       # larger ones do not
    assert any(case == 1 and near for case, _, _, near in seen)


def test_a_query_far_from_where_its_body_bends_skips_its_own_body():
    """A body that seeks self pairs (not rigid) still leaves them out at each query whose own primitive
    cannot have one (`may_have_self_pair`): from its vertices' deviation from the rigid fit, the body's
    largest, and its partners listed at rest with their own deviations (the lists, whose first entry is
    D_min(Q), and the body's D_min checked here against all same-body pairs). A bar squashed towards one end, by more or less, and a bar with
    one vertex or one triangle pushed by a few mm: the pairs are the brute-force ones, and only some
    queries seek self pairs."""
    from solver.physics.contact_detection import REST_MARGIN, SEARCH_SELF

    solver.ensure_taichi()
    rng = np.random.default_rng(3)
    bar = solver.box_mesh(size=(0.3, 0.03, 0.03), cells=(10, 1, 1))
    contact = solver.Contact(radius=0.004, query_radius=0.015)
    free = np.ones(bar.n_vertices, dtype=bool)
    detector = ContactDetector(bar, free, contact)
    surface, q, X = detector.surface, contact.query_radius, bar.vertices
    n_queries, n_triangles = len(surface.vertices) + len(surface.edges), len(surface.triangles)
    V, T = np.meshgrid(np.arange(len(surface.vertices)), np.arange(n_triangles), indexing="ij")
    v, t = surface.vertices[V.ravel()], surface.triangles[T.ravel()]
    d_vt = point_triangle_np(X[v], X[t[:, 0]], X[t[:, 1]], X[t[:, 2]])[0]
    A, B = np.triu_indices(len(surface.edges), k=1)
    ea, eb = surface.edges[A], surface.edges[B]
    d_ee = edge_edge_np(X[ea[:, 0]], X[ea[:, 1]], X[eb[:, 0]], X[eb[:, 1]])[0]
    d_min = np.full(n_queries, REST_MARGIN * q)    # one body: every pair is a same-body one
    want = set()
    for query, item, d, disjoint in (
            (V.ravel(), T.ravel(), d_vt, ~(t == v[:, None]).any(axis=1)),
            (len(surface.vertices) + A, n_triangles + B, d_ee, ~(ea[:, :, None] == eb[:, None, :]).any(axis=(1, 2)))):
        keep = disjoint & (d >= q)                      # closer at rest: excluded
        np.minimum.at(d_min, query[keep], d[keep])
        listed = keep & (d < REST_MARGIN * q)
        want |= {(int(a), int(b), round(float(c), 12)) for a, b, c in zip(query[listed], item[listed], d[listed])}
    np.testing.assert_allclose(detector._margin.to_numpy(), d_min.min() - q, rtol=0, atol=1e-12)   # the body's
    start, items = detector._partner_start.to_numpy(), detector._partner_item.to_numpy()
    distances = detector._partner_distance.to_numpy()
    assert np.all(np.diff(start) >= 0) and start[-1] == len(want)
    got = set()
    for query in range(n_queries):
        rows = slice(start[query], start[query + 1])
        assert np.all(np.diff(distances[rows]) >= 0)    # ascending, so that the walk may stop early
        if rows.stop > rows.start:                      # the first is D_min(Q)
            assert distances[rows.start] == pytest.approx(d_min[query], abs=1e-12)
        else:
            assert d_min[query] == REST_MARGIN * q
        got |= {(query, int(b), round(float(c), 12)) for b, c in zip(items[rows], distances[rows])}
    assert got == want
    seen = []
    for case in range(60):
        x = bar.vertices.copy()
        if case < 12:                                   # squashed across, towards one end
            squash = rng.uniform(0.2, 0.7) * np.clip((x[:, 0] - 0.2) / 0.1, 0, 1) ** 2
            x[:, 1:] = 0.015 + (x[:, 1:] - 0.015) * (1 - squash)[:, None]
            x += rng.normal(0, 1e-4, x.shape)
        else:                                           # one vertex, or one triangle, pushed
            pushed = [rng.integers(bar.n_vertices)] if case % 2 else surface.triangles[rng.integers(n_triangles)]
            x[pushed] += rng.normal(size=3) / np.sqrt(3) * rng.uniform(0.002, 0.008)
        n = detector.detect(_positions(x))
        kind, vertices, primitives, distance = detector.pairs()
        assert {(int(k), int(a), int(b)) for k, (a, b) in zip(kind, primitives)} == brute_force_pairs(
            bar, x, free, contact).keys()
        searched = bool(detector.active.to_numpy()[0] & SEARCH_SELF)
        assert searched or case >= 12                   # a squashed bar is not rigid
        seen.append((case < 12, n, detector.self_queries() if searched else None))
    assert all(0 < queries < n_queries for squashed, _, queries in seen if squashed)   # some queries, not all
    assert sum(n > 0 for squashed, n, _ in seen if squashed) >= 6        # and they found self pairs
    pushed = [(n, queries) for squashed, n, queries in seen if not squashed and queries is not None]
    assert len(pushed) >= 30 and all(queries < n_queries for _, queries in pushed)
    assert sum(n > 0 for n, _ in pushed) >= 10


def test_queries_skip_only_their_own_bodys_items():
    """A query of a body that seeks no self pair skips its own body's run of items in each bucket: the
    ranges cover exactly each body's triangles and edges where they are contiguous, none where bodies
    interleave in the numbering, and in both cases the pairs are the brute-force ones."""
    from solver.physics.contact_detection import SEARCH_SELF, own_item_ranges

    solver.ensure_taichi()
    rng = np.random.default_rng(11)
    mesh = _scene(rng, n_bodies=3)
    surface = surface_primitives(mesh.tets)
    body = body_labels(mesh.tets, mesh.n_vertices)
    ranges = own_item_ranges(body, surface)
    T = len(surface.triangles)
    for b in range(3):
        np.testing.assert_array_equal(np.arange(*ranges[b, :2]), np.flatnonzero(body[surface.triangles[:, 0]] == b))
        np.testing.assert_array_equal(np.arange(*ranges[b, 2:]) - T, np.flatnonzero(body[surface.edges[:, 0]] == b))
    # the same bodies with their vertices and tets dealt out in turn: every body's items interleave, and
    # nothing is skipped
    order = np.argsort(np.arange(mesh.n_vertices) % 5, kind="stable")
    label = np.empty_like(order)
    label[order] = np.arange(mesh.n_vertices)
    tets = label[mesh.tets][np.argsort(np.arange(mesh.n_tets) % 5, kind="stable")]
    dealt = solver.TetMesh(mesh.vertices[order], tets)
    dealt_surface = surface_primitives(dealt.tets)
    np.testing.assert_array_equal(own_item_ranges(body_labels(dealt.tets, dealt.n_vertices), dealt_surface), 0)
    contact = solver.Contact(radius=0.01, query_radius=0.04)
    for case_mesh in (mesh, dealt):
        free = np.ones(case_mesh.n_vertices, dtype=bool)
        detector = ContactDetector(case_mesh, free, contact)
        skipped = 0
        for _ in range(12):
            x = case_mesh.vertices.copy()
            for b in range(3):                       # each body turned about its centroid: rigid
                x[detector.bodies == b] = _turned(x[detector.bodies == b], rng)
            n = detector.detect(_positions(x))
            kind, _, primitives, _ = detector.pairs()
            got = {(int(k), int(a), int(c)) for k, (a, c) in zip(kind, primitives)}
            assert got == brute_force_pairs(case_mesh, x, free, contact).keys() and n == len(got)
            skipped += int(((detector.active.to_numpy() & SEARCH_SELF) == 0).sum())
        assert skipped > 0                           # rigid bodies: their queries did skip their own items


@pytest.mark.parametrize("serial", [False, True])
@pytest.mark.parametrize("n,chunk", [(0, 64), (1, 64), (63, 64), (64, 64), (1000, 64), (4097, 100)])
def test_exclusive_scan_is_the_cumulative_sum(n, chunk, serial):
    from solver.physics.contact_detection import exclusive_scan

    solver.ensure_taichi()
    counts = np.random.default_rng(n).integers(0, 9, max(n, 1)).astype(np.int32)
    device_counts = ti.ndarray(ti.i32, len(counts))
    device_counts.from_numpy(counts)
    starts = ti.ndarray(ti.i32, len(counts) + 1)
    partial = ti.ndarray(ti.i32, len(counts) // chunk + 1)
    total = exclusive_scan(device_counts, starts, n, chunk, partial, serial)
    want = np.concatenate([[0], np.cumsum(counts[:n])])
    assert total == want[-1]
    np.testing.assert_array_equal(starts.to_numpy()[:n + 1], want)


def test_float32_positions_give_the_same_pairs():
    solver.ensure_taichi()
    rng = np.random.default_rng(4)
    mesh = _scene(rng)
    contact = solver.Contact(radius=0.01, query_radius=0.04)
    x = mesh.vertices + rng.normal(0, 0.015, mesh.vertices.shape)
    found = {}
    for dtype, np_type in ((ti.f64, np.float64), (ti.f32, np.float32)):
        detector = ContactDetector(mesh, np.ones(mesh.n_vertices, bool), contact, dtype=dtype)
        positions = ti.Vector.ndarray(3, dtype, (1, len(x)))
        positions.from_numpy(x[None].astype(np_type))
        detector.detect(positions)
        kind, _, primitives, distance = detector.pairs()
        found[dtype] = {(int(k), int(a), int(b)): d for k, (a, b), d in zip(kind, primitives, distance)}
    borderline = {key for key, d in found[ti.f64].items() if abs(d - contact.query_radius) < 1e-5}
    assert found[ti.f64].keys() - borderline == found[ti.f32].keys() - borderline
    for key in found[ti.f32].keys() - borderline:
        assert found[ti.f32][key] == pytest.approx(found[ti.f64][key], rel=1e-4, abs=1e-6)


def test_one_thread_and_parallel_loops_find_the_same_pairs():
    """A small mesh on the CPU detects on one thread (SERIAL_DETECT_TETS, SERIAL_DETECT_QUERIES), a larger
    one with its queries in a parallel loop, a large one in parallel loops: the pairs, their order, the
    incidence lists and the bounds are the same either way."""
    solver.ensure_taichi()
    rng = np.random.default_rng(23)
    mesh = _scene(rng, n_bodies=4)
    contact = solver.Contact(radius=0.01, query_radius=0.08)
    free = np.ones(mesh.n_vertices, bool)
    detectors = [ContactDetector(mesh, free, contact) for _ in range(3)]
    for detector, (one_thread, serial_queries) in zip(detectors, ((True, True), (True, False), (False, False))):
        detector._one_thread, detector._serial_queries = one_thread, serial_queries
    one = detectors[0]
    for _ in range(3):
        x = _positions(mesh.vertices + rng.normal(0, 0.015, mesh.vertices.shape))
        n = one.detect(x)
        assert n > 0
        for many in detectors[1:]:
            assert many.detect(x) == n
            for a, b in zip(one.pairs() + one.vertex_pairs(), many.pairs() + many.vertex_pairs()):
                np.testing.assert_array_equal(a, b)
            np.testing.assert_array_equal(one.bound.to_numpy(), many.bound.to_numpy())
