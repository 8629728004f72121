"""Refreshed contact bounds (solver/vbd/contact_state.py): between full detections a bound hit sets new
bounds from the pairs L of the last detection instead of detecting again. Judged in numpy at every
iteration of two cubes driven into each other: the bounds follow the refresh's formula, the pairs of L
closer than the radius are exactly those a fresh detection finds, the pairs the sweep skips are beyond
the radius (each vertex walks exactly its live pairs, or only the near ones while no vertex of them has
moved past the horizon), and no bound lets two primitives meet. The sweep's
cheaper skip, by how far the vertices moved since the refresh (`contact_sweep.may_be_within`), is checked
against exact distances."""
import numpy as np
import pytest

import solver
from solver._ti import ti
from solver.physics.contact import PairKind, pair_geometry_np
from solver.physics.contact_detection import find_pairs_np, rest_exclusions_np
from solver.vbd import contact_state, contact_sweep
from solver.vbd.contact_sweep import may_be_within, moves_since
from solver.vbd.layout import STATE_ROWS, X

pytestmark = pytest.mark.backend

SOFT = solver.Material(youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0)


def _active(kind, primitives, distance, radius):
    """The set of (kind, primitive, primitive) of the pairs closer than radius."""
    return {(int(k), int(p), int(q)) for k, (p, q), d in zip(kind, primitives, distance) if d < radius}


def _reach(kind, vertices, bound):
    """(P,) the farthest the two primitives of each pair may move towards each other: the largest bound
    among the vertices of each side (vertex | triangle, or edge | edge), summed."""
    vt = kind == PairKind.VERTEX_TRIANGLE
    b = bound[vertices]
    side_a = np.where(vt, b[:, 0], b[:, :2].max(axis=1))
    side_b = np.where(vt, b[:, 1:].max(axis=1), b[:, 2:].max(axis=1))
    return side_a + side_b


def test_refreshes_keep_the_active_pairs_and_never_let_a_pair_touch(monkeypatch):
    a, b = (solver.box_mesh(size=(0.1,) * 3, cells=(2, 2, 2), origin=o) for o in ((0, 0, 0), (0.112, 0.02, 0.01)))
    mesh = solver.merge_meshes([a, b])
    contact = solver.Contact(stiffness=1e3, radius=0.004, detection_interval=3)
    horizon = 0.05      # x radius: wide enough that these fast cubes also have iterations that walk only the near pairs
    monkeypatch.setattr(contact_state, "NEAR_HORIZON", horizon)
    sim = solver.Simulation(mesh, SOFT, dt=1 / 240, gravity=(0, 0, 0), iterations=8, contact=contact)
    v = np.zeros((mesh.n_vertices, 3))
    v[:a.n_vertices, 0], v[a.n_vertices:, 0] = 1.5, -1.5
    sim.set_velocities(v)
    stage = sim._contact_stage
    surface, bodies = stage.detector.surface, stage.bodies
    free = np.ones(mesh.n_vertices, bool)
    excluded = rest_exclusions_np(mesh.vertices, surface, bodies, contact)
    none = np.zeros(0, np.int64)
    wide = solver.Contact(stiffness=1e3, radius=0.004, query_radius=0.05, self_contact=False)
    q, g = contact.query_radius, contact.bound_relaxation
    refreshes, detections, hits = stage.refreshes, stage.detections, stage.bound_hits
    active_seen = lower_bounds_seen = near_only_seen = far_walked_seen = 0
    steps = 5
    for _ in range(steps):
        sim.begin_step()
        for _ in range(8):
            sim.run_iterations(1)
            x, x_det, x_full = sim.positions, stage.x_det.to_numpy(), stage.x_full.to_numpy()
            bound = stage.bound.to_numpy()
            kind, vertices, primitives, _ = stage.detector.pairs()
            # the bounds of the last refresh: g min(q - 2 Delta, distance at x_det of each pair of L)
            delta = np.linalg.norm(x_det - x_full, axis=1).max()
            nearest = np.full(mesh.n_vertices, q - 2 * delta)
            np.minimum.at(nearest, vertices.ravel(), np.repeat(pair_geometry_np(kind, x_det[vertices])[0], 4))
            np.testing.assert_allclose(bound, g * nearest, rtol=1e-12, atol=0)
            # which needs exact distances only where they set a bound: distance holds a lower bound of each
            # pair's distance at x_det, the distance itself where flagged exact
            held, exact = stage.distance.to_numpy()[:len(kind)], pair_geometry_np(kind, x_det[vertices])[0]
            assert (held <= exact * (1 + 1e-12)).all()
            flagged = stage._exact.to_numpy()[:len(kind)] == 1
            np.testing.assert_allclose(held[flagged], exact[flagged], rtol=1e-12, atol=0)
            lower_bounds_seen += np.count_nonzero(held < exact * (1 - 1e-9))
            assert (np.linalg.norm(x - x_det, axis=1) <= bound * (1 + 1e-12)).all()
            # L's pairs closer than the radius at x are a fresh detection's
            fresh = find_pairs_np(x, surface, bodies, free, contact, excluded)
            d = pair_geometry_np(kind, x[vertices])[0]
            known = _active(kind, primitives, d, contact.radius)
            assert known == _active(fresh[0], fresh[2], fresh[3], contact.radius)
            # the pairs the sweep skips until the next refresh are beyond the radius
            live = stage.live.to_numpy()[:len(d)]
            assert (d[live == 0] >= contact.radius).all()
            # and it walks, per vertex, the live pairs of its incidence list in their order, or only those
            # closer than r + 2 horizon at x_det (near)
            offsets, incidence = stage.detector.vertex_pairs()
            live_incidence, live_end = stage.live_incidence.to_numpy(), stage.live_end.to_numpy()
            near_incidence, near_end = stage.near_incidence.to_numpy(), stage.near_end.to_numpy()
            near = held < contact.radius + 2 * horizon * contact.radius
            assert flagged[near].all()          # a near pair is measured: near, not only maybe near
            for i in range(mesh.n_vertices):
                listed = incidence[offsets[i]:offsets[i + 1]]
                np.testing.assert_array_equal(live_incidence[offsets[i]:live_end[i]], listed[live[listed] == 1])
                np.testing.assert_array_equal(near_incidence[offsets[i]:near_end[i]],
                                              listed[(live[listed] == 1) & near[listed]])
            # the moves since x_det it reads for those pairs' vertices are the moves to x (`measure_moves`,
            # then `apply_buffered` after each colour)
            paired = np.diff(offsets) > 0
            moves = np.linalg.norm(x - x_det, axis=1)[paired]
            np.testing.assert_allclose(stage._moved.to_numpy()[paired], moves, rtol=1e-12, atol=1e-18)
            # and a vertex walks only its near ones unless a vertex of one of its live pairs has moved past the
            # horizon (`raise_alerts`, this iteration's stamp): the live pairs it skips are beyond the radius
            alerted = stage._alert.to_numpy() == stage._stamp
            far = np.linalg.norm(x - x_det, axis=1) > horizon * contact.radius
            live_pairs = np.flatnonzero(live == 1)
            assert alerted[vertices[live_pairs[far[vertices[live_pairs]].any(axis=1)]]].all()
            near_only_seen += int((~alerted & (near_end < live_end)).any())
            far_walked_seen += int(alerted.any() and (near_end < live_end).any())
            active_seen = max(active_seen, len(known))
            # within their bounds no two primitives can meet: the pairs of L, and every pair between the
            # bodies up to 5 cm apart at x_det
            d_L = pair_geometry_np(kind, x_det[vertices])[0]
            assert (_reach(kind, vertices, bound) < d_L).all()
            w_kind, w_vertices, _, w_d = find_pairs_np(x_det, surface, bodies, free, wide, (none, none))
            assert (_reach(w_kind, w_vertices, bound) < w_d).all()
        sim.end_step()
    assert active_seen > 0 and lower_bounds_seen > 0 and near_only_seen > 0 and far_walked_seen > 0
    assert stage.bound_hits > hits and stage.refreshes - refreshes > steps     # refreshes after hits, not only at x_n
    assert stage.detections > detections


def test_the_serial_and_parallel_contact_sweeps_give_the_same_steps():
    """Small meshes sweep on one CPU thread (`vertex_solve.serial_sweep`). With contact the serial sweep is one
    loop over the colours, each followed by its buffered writes; vertices of a colour without pairs are read
    by no other vertex of it, so it gives bit for bit the parallel sweep's steps (friction, bound hits and
    refreshes included)."""
    a = solver.box_mesh(size=(0.1,) * 3, cells=(2, 2, 2), origin=(0, 0, 0))
    b = solver.box_mesh(size=(0.1,) * 3, cells=(2, 2, 2), origin=(0.03, 0.02, 0.105))
    mesh = solver.merge_meshes([a, b])
    contact = solver.Contact(stiffness=1e3, radius=0.004, friction=0.3)
    runs = []
    for serial in (False, True):
        sim = solver.Simulation(mesh, SOFT, dt=1 / 120, fixed=np.arange(a.n_vertices), iterations=6,
                                contact=contact)
        sim._contact_stage._serial = serial
        v = np.zeros((mesh.n_vertices, 3))
        v[a.n_vertices:, 2] = -1.0
        sim.set_velocities(v)
        sim.step(12)
        runs.append((sim.positions, sim.contact_count(), sim._contact_stage.bound_hits))
    (x_parallel, count, hits), (x_serial, _, _) = runs
    assert count > 0 and hits > 0 and not np.allclose(x_parallel[a.n_vertices:], mesh.vertices[a.n_vertices:])
    np.testing.assert_array_equal(x_parallel, x_serial)
    assert runs[0][1:] == runs[1][1:]


def test_walking_only_the_near_pairs_and_leaving_out_refreshes_change_no_step(monkeypatch):
    """Two cubes 7 mm apart settling on a fixed slab. A vertex walks only its near live pairs (closer than
    r + 2 horizon) while no vertex of its live pairs has moved farther than the horizon, and a step leaves out
    the refresh at x_n where it would neither detect nor clamp the guess (`contact_sweep.guess_within_bounds`);
    the steps are bit for bit those of a sweep that walks every live pair (horizon 0: every move crosses it)
    and refreshes at every x_n (on the CPU; to round-off on CUDA)."""
    slab = solver.box_mesh(size=(0.3, 0.3, 0.05), cells=(3, 3, 1), origin=(-0.1, -0.1, -0.05))
    cubes = [solver.box_mesh(size=(0.1,) * 3, cells=(2, 2, 2), origin=(x, 0, 0.004)) for x in (0, 0.107)]
    mesh = solver.merge_meshes([slab, *cubes])
    contact = solver.Contact(stiffness=1e4, radius=0.005, friction=0.3)
    runs = []
    for shortcuts in (True, False):
        if not shortcuts:
            monkeypatch.setattr(contact_state, "NEAR_HORIZON", 0.0)
            monkeypatch.setattr(contact_sweep, "guess_within_bounds", lambda *args: 0)
        sim = solver.Simulation(mesh, SOFT, dt=1 / 60, fixed=np.arange(slab.n_vertices), iterations=10,
                                contact=contact)
        stage = sim._contact_stage
        near_only = 0
        for _ in range(40):
            sim.begin_step()
            for _ in range(10):
                sim.run_iterations(1)
                live_end, near_end = stage.live_end.to_numpy(), stage.near_end.to_numpy()
                alerted = stage._alert.to_numpy() == stage._stamp
                near_only += int((~alerted & (near_end < live_end)).any())
            sim.end_step()
        runs.append((sim.positions, near_only, stage.refreshes + stage.detections, sim.contact_count()))
    (x_short, near_only, refreshes, count), (x_every, none, every_refresh, _) = runs
    assert count > 0 and near_only > 0 and none == 0 and refreshes < every_refresh
    if solver.backend.running_on_cpu():
        np.testing.assert_array_equal(x_short, x_every)
    else:       # CUDA's per-body translation sums are atomic adds: 1e-14 m apart after 40 steps on an H200
        np.testing.assert_allclose(x_short, x_every, rtol=0, atol=1e-12)


@ti.kernel
def _may_be_within(state: ti.types.ndarray(), x_det: ti.types.ndarray(), distance: ti.types.ndarray(),
                   kind: ti.types.ndarray(), pair: ti.types.ndarray(), r: ti.f64, slack: ti.f64,
                   out: ti.types.ndarray()):
    for p in range(out.shape[0]):
        out[p] = ti.cast(may_be_within(distance, kind[p], p, moves_since(state, x_det, pair[p]), r, slack), ti.i32)


def test_a_pair_skipped_for_its_vertices_moves_is_beyond_the_radius():
    """Pairs 5 to 30 mm apart at x_det, each vertex then moved up to 6 mm (for half of the pairs straight
    towards the other primitive, where the bound is tight): wherever `may_be_within` says no, the exact
    distance at x is at least r + slack; it says no for many pairs, and yes for many that are within."""
    rng = np.random.default_rng(7)
    P, r, slack = 4000, 0.01, 0.002
    kind = np.where(np.arange(P) % 2 == 0, PairKind.VERTEX_TRIANGLE, PairKind.EDGE_EDGE).astype(np.int32)
    base = rng.normal(size=(P, 4, 3)) * 0.02
    d_det, _, n = pair_geometry_np(kind, base)
    gap = rng.uniform(0.005, 0.03, P)
    side_a = np.where(kind[:, None] == PairKind.VERTEX_TRIANGLE, [1, 0, 0, 0], [1, 1, 0, 0]).astype(bool)
    base += np.where(side_a[:, :, None], ((gap - d_det)[:, None] * n)[:, None], 0.0)          # d = gap at x_det
    d_det = pair_geometry_np(kind, base)[0]
    np.testing.assert_allclose(d_det, gap, rtol=1e-9)
    move = rng.normal(size=(P, 4, 3))
    towards = rng.random(P) < 0.5
    move[towards] = np.where(side_a[towards][:, :, None], -1.0, 1.0) * n[towards][:, None]
    move *= (rng.uniform(0, 0.006, (P, 4)) / np.linalg.norm(move, axis=2))[:, :, None]
    x = base + move
    state = ti.Vector.ndarray(3, ti.f64, (STATE_ROWS, 4 * P))
    rows = np.zeros((STATE_ROWS, 4 * P, 3))
    rows[X] = x.reshape(-1, 3)
    state.from_numpy(rows)
    x_det, distance, kinds, pairs, out = (ti.Vector.ndarray(3, ti.f64, 4 * P), ti.ndarray(ti.f64, P),
                                          ti.ndarray(ti.i32, P), ti.Vector.ndarray(4, ti.i32, P), ti.ndarray(ti.i32, P))
    x_det.from_numpy(base.reshape(-1, 3))
    distance.from_numpy(d_det)
    kinds.from_numpy(kind)
    pairs.from_numpy(np.arange(4 * P, dtype=np.int32).reshape(P, 4))
    _may_be_within(state, x_det, distance, kinds, pairs, r, slack, out)
    maybe = out.to_numpy().astype(bool)
    d = pair_geometry_np(kind, x)[0]
    assert (d[~maybe] >= r + slack).all()
    assert (~maybe).sum() > P // 4 and (maybe & (d < r + slack)).sum() > P // 4


@pytest.mark.parametrize("serial", [True, False])
def test_with_no_pair_the_contact_sweep_is_the_plain_sweep_within_the_bounds(serial):
    """Two cubes 20 cm apart drifting towards each other at 1 mm per step, no gravity: no pair under the
    query radius, so each iteration is the plain sweep with every step clamped to its bound. The clamps never
    bind at this speed, so the steps are contact=None's (to round-off: the translation correction sums its
    bodies in another order with contact); at 1 m per step they bind (and only slow the cubes down)."""
    a = solver.box_mesh(size=(0.1,) * 3, cells=(2, 2, 2))
    mesh = solver.merge_meshes([a, solver.TetMesh(a.vertices + (0.3, 0.0, 0.0), a.tets)])
    x = {}
    for speed in (0.06, 60.0):
        for contact in (None, solver.Contact(stiffness=1e3, radius=0.004)):
            sim = solver.Simulation(mesh, SOFT, dt=1 / 60, gravity=(0, 0, 0), iterations=5, contact=contact)
            if contact is not None:
                sim._contact_stage._serial = serial
            v = np.zeros((mesh.n_vertices, 3))
            v[:a.n_vertices, 0] = speed
            sim.set_velocities(v)
            sim.step(4)
            x[speed, contact is None] = sim.positions
            if contact is not None:
                assert sim.contact_count() == 0 and sim._contact_stage.detector.n_pairs == 0
                hits = sim._contact_stage.bound_hits
        assert (hits > 0) == (speed > 1)
    np.testing.assert_allclose(x[0.06, False], x[0.06, True], rtol=0, atol=1e-14)
    assert np.abs(x[60.0, False] - x[60.0, True]).max() > 1e-3
    assert x[60.0, False][:a.n_vertices, 0].mean() < x[60.0, True][:a.n_vertices, 0].mean()


def test_the_contact_count_and_closest_gap_at_one_set_of_positions_detect_once():
    """contact_count(), min_separation() and energy() at the positions of the last full detection reuse its
    pairs (detection is deterministic); once the positions move they detect again. Both numbers are judged
    against the numpy twin's pairs (scipy's k-d tree) at the positions of the moment."""
    a, b = (solver.box_mesh(size=(0.1,) * 3, cells=(2, 2, 2), origin=o) for o in ((0, 0, 0), (0.103, 0.01, 0.0)))
    mesh = solver.merge_meshes([a, b])
    contact = solver.Contact(stiffness=1e4, radius=0.004)
    sim = solver.Simulation(mesh, SOFT, dt=1 / 60, gravity=(0, 0, 0), iterations=5, contact=contact)
    v = np.zeros((mesh.n_vertices, 3))
    v[:a.n_vertices, 0] = 0.06
    sim.set_velocities(v)
    stage = sim._contact_stage
    surface, bodies = stage.detector.surface, stage.bodies
    excluded = rest_exclusions_np(mesh.vertices, surface, bodies, contact)
    free = np.ones(mesh.n_vertices, bool)
    counts = []
    for step in range(3):
        detections = stage.detections
        count, gap, energy = sim.contact_count(), sim.min_separation(), sim.energy()
        assert stage.detections == detections + (step > 0)    # construction detected at the start positions
        _, _, _, distance = find_pairs_np(sim.positions, surface, bodies, free, contact, excluded)
        assert count == np.count_nonzero(distance < contact.radius)
        assert gap == pytest.approx(distance.min(), rel=1e-12)
        assert sim.energy() == energy and stage.detections == detections + (step > 0)
        counts.append(count)
        sim.step()
    assert counts[0] > 0 and len(set(counts)) > 1, counts
