"""The per-body translation correction (`solver/vbd/translation.py`, issue 17): two free bodies beside a fixed
one each get their own translation, which zeroes the sum of their residuals (with and without contact),
never moves the fixed body, equals the whole-mesh correction for a single free body, does not increase G,
and with contact keeps every vertex within its bound (so the pairs it skips stay beyond the radius); a
resting pile comes to rest with it."""
import numpy as np
import pytest

import solver
from solver.physics.contact import pair_geometry_np
from solver.vbd.translation import BodyTranslation

pytestmark = pytest.mark.backend

SOFT = solver.Material(youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0)


def _cube(origin, size=0.1, cells=1):
    return solver.box_mesh(size=(size, size, size), cells=(cells, cells, cells), origin=origin)


def _two_cubes_on_a_slab(gap, **kwargs):
    """A fixed slab (body 0) with its top at z = 0 and two cubes (bodies 1, 2) `gap` above it, apart; the
    cubes' corners and edges lie off the slab's grid lines (closest points inside triangles and edges)."""
    slab = solver.box_mesh(size=(0.5, 0.3, 0.05), cells=(5, 3, 1), origin=(-0.1, -0.1, -0.05))
    mesh = solver.merge_meshes([slab, _cube((0.013, 0.027, gap)), _cube((0.263, 0.077, gap))])
    fixed = np.arange(slab.n_vertices)
    return solver.Simulation(mesh, SOFT, dt=1 / 60, fixed=fixed, **kwargs), slab.n_vertices


def _body_sums(sim):
    """(B, 3) sum of the residuals f_i over each body's vertices."""
    sums = np.zeros((sim.bodies.max() + 1, 3))
    np.add.at(sums, sim.bodies, sim.residual())
    return sums


@pytest.mark.parametrize("contact", [None, solver.Contact(stiffness=1e3, radius=0.005)])
def test_each_free_body_ends_with_residuals_summing_to_zero_and_the_fixed_body_stays(contact):
    """With contact the cubes rest in the barrier's quadratic stage (r/2 < d < r), where a pair's force is
    affine in a translation: the correction then zeroes the sums exactly, the pairs with the slab included."""
    gap = 0.02 if contact is None else 0.0035
    sim, n_slab = _two_cubes_on_a_slab(gap, iterations=3, contact=contact)
    assert sim._body_translation.corrected.tolist() == [False, True, True]
    v = 0.01 * np.random.default_rng(1).normal(size=(sim.mesh.n_vertices, 3))
    sim.set_velocities(v * sim.free_mask[:, None])
    weight = sim.masses[n_slab:].sum() * 9.81
    for _ in range(3):
        sim.begin_step()
        sim.run_iterations(3)
        before = np.abs(_body_sums(sim)[1:]).max()
        assert before > 1e-3 * weight                    # the correction has work to do
        sim.end_step()
        after = np.abs(_body_sums(sim)[1:]).max()        # y and x_n are still those of the step
        assert after < 1e-9 * weight
        if contact is not None:
            assert sim.contact_count() > 0
    np.testing.assert_array_equal(sim.positions[:n_slab], sim.mesh.vertices[:n_slab])


def test_a_single_free_body_gets_the_whole_mesh_correction():
    """d = sum_i f_i / sum_i (m_i/h^2 + ground k_c for penetrating vertices), componentwise: the correction
    before bodies had their own."""
    sphere = solver.load_mesh("assets/sphere.obj", resolution=6)
    ground = solver.Ground(height=float(sphere.vertices[:, 2].min()) + 0.02, stiffness=1e4)
    sim = solver.Simulation(sphere, SOFT, iterations=3, ground=ground)
    sim.set_velocities(np.random.default_rng(0).normal(size=(sphere.n_vertices, 3)))
    sim.begin_step()
    sim.run_iterations(3)
    x = sim.positions
    f = sim.residual()
    diagonal = np.full(3, sim.masses.sum() / sim.dt ** 2)
    diagonal[2] += ground.stiffness * np.count_nonzero(x[:, 2] < ground.height)
    d = f.sum(axis=0) / diagonal
    sim.end_step()
    assert np.abs(d).max() > 1e-6
    np.testing.assert_allclose(sim._body_translation.steps()[0], d, rtol=1e-12)
    np.testing.assert_allclose(sim.positions - x, np.broadcast_to(d, x.shape), rtol=0, atol=1e-9 * np.abs(d).max())


def test_bodies_with_a_fixed_or_kinematic_vertex_get_no_correction():
    bodies = np.array([0, 0, 1, 1, 2, 2, 3])
    free = np.array([True, False, True, True, True, True, True])
    free_but_kinematic = free.copy()
    free_but_kinematic[5] = False
    assert BodyTranslation(bodies, free).corrected.tolist() == [False, True, True, True]
    assert BodyTranslation(bodies, free_but_kinematic).corrected.tolist() == [False, True, False, True]


@pytest.mark.parametrize("down, sideways, what", [(3.0, 0.0, "halved"), (0.5, 2.0, "scaled")])
def test_the_correction_never_increases_G_and_keeps_every_vertex_within_its_bound(down, sideways, what):
    """Two cubes stacked on a fixed slab, thrown at it with one iteration per step: G after the correction
    is at most G before it, and no vertex leaves |x_i - x_det,i| <= b_i. Thrown straight down, the
    quadratic model overshoots (pairs come within the radius) and the line search halves a step; thrown
    sideways, some body's step is scaled down to its bounds."""
    slab = solver.box_mesh(size=(0.3, 0.3, 0.05), cells=(3, 3, 1), origin=(-0.1, -0.1, -0.05))
    mesh = solver.merge_meshes([slab, _cube((0.0, 0.0, 0.006)), _cube((0.02, 0.01, 0.112))])
    n = slab.n_vertices
    sim = solver.Simulation(mesh, SOFT, dt=1 / 60, fixed=np.arange(n), iterations=1,
                            contact=solver.Contact(stiffness=1e4, radius=0.005))
    v = np.zeros((mesh.n_vertices, 3))
    v[n:] = (sideways, 0.0, -down)
    sim.set_velocities(v)
    stage, correction = sim._contact_stage, sim._body_translation
    seen = {"decreased": 0, "halved": 0, "scaled": 0}
    for _ in range(20):
        sim.begin_step()
        sim.run_iterations(1)
        G_before = sim.energy()                        # detects at the iterate: x_det and bounds there
        sim.end_step()
        moved = np.linalg.norm(sim.positions - stage.x_det.to_numpy(), axis=1)
        assert (moved <= stage.bound.to_numpy() * (1 + 1e-9) + 1e-15).all()
        kind, vertices, _, _ = stage.detector.pairs()       # the pairs the correction skips stay beyond r
        skipped = stage.live.to_numpy()[:len(kind)] == 0
        assert (pair_geometry_np(kind[skipped], sim.positions[vertices[skipped]])[0] >= 0.005).all()
        G_after = sim.energy()
        assert G_after <= G_before + 1e-12 * abs(G_before)
        seen["decreased"] += G_after < G_before - 1e-9 * abs(G_before)
        seen["halved"] += correction.scale < 1
        seen["scaled"] += (correction.alpha.to_numpy()[1:] < 1).any()
    assert seen["decreased"] > 0 and seen[what] > 0, seen
    assert sim.contact_count() > 0


def test_the_sums_are_taken_in_a_fixed_order_so_that_runs_repeat_bit_for_bit():
    """On every backend F_b and D_b are the sums of the vertices' terms. On the CPU each body's F_b and D_b
    are summed from its vertices' terms kept per vertex, one body on one thread, whatever order the threads
    computed the terms in; two runs of a small pile with contact then give the same positions bit for bit
    (atomic float adds made long piles differ between runs; CUDA keeps them, for speed)."""
    sim, _ = _two_cubes_on_a_slab(0.002, contact=solver.Contact(stiffness=1e3, radius=0.005))
    sim.set_positions(sim.positions + np.random.default_rng(3).normal(0, 1e-4, sim.positions.shape)
                      * sim.free_mask[:, None])
    sim.begin_step()
    translation = sim._body_translation
    assert translation._ordered == solver.backend.running_on_cpu()    # CUDA sums with atomic adds
    translation.apply(sim.state, sim._mass, sim._adjacency, sim._params, None, sim.dtype)
    f_i, diagonal_i, F, D = (a.to_numpy() for a in (translation._f_i, translation._diagonal_i, translation.F,
                                                     translation.D))
    for b in np.flatnonzero(translation.corrected):
        members = np.flatnonzero(sim.bodies == b)
        scale = np.abs(f_i[members]).sum(axis=0)
        np.testing.assert_allclose(F[b], f_i[members].sum(axis=0), rtol=0, atol=1e-12 * scale.max())
        np.testing.assert_allclose(D[b], diagonal_i[members].sum(axis=0), rtol=1e-12)
    if not translation._ordered:
        pytest.skip("on CUDA the per-body sums are atomic adds: runs repeat to round-off, not bit for bit")
    runs = []
    for _ in range(2):
        sim, _ = _two_cubes_on_a_slab(0.002, contact=solver.Contact(stiffness=1e3, radius=0.005, friction=0.3))
        sim.step(15)
        runs.append(sim.positions)
    np.testing.assert_array_equal(runs[0], runs[1])


def test_a_resting_pile_comes_to_rest_with_the_correction():
    """Eight cubes in two layers in a fixed box (benchmarks/contact.py's pile), friction 0.3, 20 iterations:
    after 8 s every cube's mean velocity is below 0.5 mm/s. A correction applied at every step, however
    short, answers only what the sweeps left unconverged and keeps the upper cubes rocking at 2-4 mm/s; a
    body touching another is left alone where its correction is shorter than friction_speed h."""
    from benchmarks.contact import pile_scene
    mesh, n_walls = pile_scene(solver, 2, apart=False)
    sim = solver.Simulation(mesh, SOFT, dt=1 / 60, fixed=np.arange(n_walls), iterations=20,
                            contact=solver.Contact(stiffness=1e4, radius=0.005, friction=0.3))
    sim.step(484)
    bodies, v = sim.bodies[n_walls:], sim.velocities[n_walls:]
    speeds = [np.linalg.norm(v[bodies == b].mean(axis=0)) for b in np.unique(bodies)]
    assert max(speeds) < 5e-4, speeds
