"""The Taichi Newton with contact (issue 17, acceptance 7): against the numpy Newton oracle, against converged
VBD, its pair blocks against the numpy twin, its pattern analysed again only when the coupled vertex pairs
change, the same answer from every linear solver, and head-on Newton steps that conserve momentum."""
import numpy as np
import pytest

import solver
from solver.newton.direct import GlobalNewton, LinearSolver, fast_newton_solve
from solver.newton.hessian import StepKernels
from solver.newton.oracle import newton_solve
from solver.physics.contact import contact_hessian_np, pair_hessian_np
from tests.contact_checks import crossings

pytestmark = pytest.mark.backend

SOFT = solver.Material(youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0)
CONTACT = solver.Contact(stiffness=1e4, radius=0.005)


def _cube(origin, axis, angle=0.3):
    """A 0.1 m cube at `origin` turned by `angle` rad about its centre's `axis` (0, 1, 2), so that none of
    its edges lies parallel to another body's: the exact distance of parallel edges has a kink there, where
    Newton (the oracle as much as the Taichi one) only creeps towards x*."""
    cube = solver.box_mesh(size=(0.1, 0.1, 0.1), cells=(1, 1, 1))
    c, s = np.cos(angle), np.sin(angle)
    i, j = [a for a in range(3) if a != axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    centre = np.full(3, 0.05)
    return solver.TetMesh((cube.vertices - centre) @ R.T + centre + origin, cube.tets)


def _landing(method="newton", iterations=50, height=0.004):
    """A free cube, turned about z, `height` m above a fixed slab, inside the barrier's radius: it lands."""
    slab = solver.box_mesh(size=(0.3, 0.3, 0.05), cells=(3, 3, 1), origin=(-0.1, -0.1, -0.05))
    mesh = solver.merge_meshes([slab, _cube((0.0, 0.0, height), axis=2)])
    return solver.Simulation(mesh, SOFT, dt=1 / 60, fixed=np.arange(slab.n_vertices), iterations=iterations,
                             contact=CONTACT, method=method)


def _head_on(gap=0.004):
    """Two free cubes `gap` m apart along x (no gravity), the second turned about x, moving towards each
    other at 0.5 m/s each."""
    a = _cube((0.0, 0.0, 0.0), axis=0, angle=0.0)
    mesh = solver.merge_meshes([a, _cube((0.1 + gap, 0.0, 0.0), axis=0)])
    sim = solver.Simulation(mesh, SOFT, dt=1 / 600, gravity=(0, 0, 0), iterations=50, contact=CONTACT,
                            method="newton")
    v = np.zeros((mesh.n_vertices, 3))
    v[:a.n_vertices, 0], v[a.n_vertices:, 0] = 0.5, -0.5
    sim.set_velocities(v)
    return sim, a.n_vertices


def test_fast_newton_equals_the_numpy_oracle_with_contact():
    sim = _landing()
    for _ in range(2):
        problem, x_n = sim.step_problem(), sim.positions
        reference = newton_solve(problem, x_n)
        fast = fast_newton_solve(problem, x_n)
        assert reference.converged and fast.converged
        assert solver.relative_error(fast.x, reference.x, x_n) <= 1e-8
        sim.step()
        assert sim.contact_count() > 0


def test_newton_simulation_agrees_with_the_reference_and_with_converged_vbd():
    newton, vbd = _landing(), _landing(method="vbd", iterations=400)
    x_n = newton.positions
    x_star = newton.newton_reference()
    newton.step()
    vbd.step()
    assert newton.contact_count() > 0
    assert solver.relative_error(newton.positions, x_star, x_n) <= 1e-6
    assert solver.relative_error(vbd.positions, newton.positions, x_n) <= 1e-3
    x_n = newton.positions                  # a second step, from the landed state
    x_star = newton.newton_reference()
    newton.step()
    assert solver.relative_error(newton.positions, x_star, x_n) <= 1e-6
    assert newton.contact_count() > 0


def test_pair_blocks_and_gradient_match_the_numpy_twins():
    sim = _landing(height=0.002)
    problem = sim.step_problem()
    x = np.ascontiguousarray(sim.positions + 5e-4 * np.random.default_rng(3).standard_normal(sim.positions.shape)
                             * sim.free_mask[:, None])
    newton = GlobalNewton(problem.tets, problem.free, LinearSolver.SUPERLU)
    contact = newton.contact_pairs(problem.contact)
    kernels = StepKernels(newton.pattern, problem)
    # E_c and its gradient: the numpy term's, and the central differences of the Taichi energy
    g = np.zeros_like(x)
    E = contact.energy_gradient(x, g)
    assert E > 0 and E == pytest.approx(problem.contact.energy(x), rel=1e-12)
    g_np = problem.contact.gradient(x) * sim.free_mask[:, None]
    np.testing.assert_allclose(g, g_np, rtol=0, atol=1e-10 * np.abs(g_np).max())
    eps = 1e-8
    for i in np.flatnonzero(np.abs(g).sum(axis=1) > 0):
        for a in range(3):
            xp, xm = x.copy(), x.copy()
            xp[i, a] += eps
            xm[i, a] -= eps
            scratch = np.zeros_like(x)
            fd = (contact.energy_gradient(xp, scratch) - contact.energy_gradient(xm, scratch)) / (2 * eps)
            assert fd == pytest.approx(g[i, a], rel=1e-5, abs=1e-6 * np.abs(g).max())
    # the Hessian with the pair blocks: the oracle's (PSD Gauss-Newton pair blocks, n held fixed), free dofs
    free_dofs = np.flatnonzero(np.repeat(problem.free, 3))
    pattern, _ = newton.coupled_system(contact, x)
    contact.write_blocks(x, pattern, True, False)
    H = kernels.hessian(x, True, True, pattern).toarray()
    H_np = problem.hessian(x)[free_dofs][:, free_dofs].toarray()
    np.testing.assert_allclose(H, H_np, rtol=0, atol=1e-9 * np.abs(H_np).max())
    blocks = H - kernels.hessian(x, True, True).toarray()
    kind, vertices, _ = problem.contact.pairs(x)
    blocks_np = contact_hessian_np(x, kind, vertices, CONTACT)[free_dofs][:, free_dofs].toarray()
    assert np.abs(blocks_np).max() > 0
    np.testing.assert_allclose(blocks, blocks_np, rtol=0, atol=1e-9 * np.abs(blocks_np).max())
    # exact pair blocks (the Newton's trusted steps): the numpy twin's curvature b'(d) d2d/dx2 on top
    contact.write_blocks(x, pattern, True, True)
    curvature = kernels.hessian(x, True, True, pattern).toarray() - H
    near = problem.contact.pairs(x)[2] < CONTACT.radius
    extra = pair_hessian_np(kind[near], x[vertices[near]], CONTACT, exact=True) - pair_hessian_np(
        kind[near], x[vertices[near]], CONTACT)
    dof = (3 * vertices[near][:, :, None] + np.arange(3)).reshape(-1, 12)
    full = np.zeros((3 * len(x), 3 * len(x)))
    np.add.at(full, (dof[:, :, None], dof[:, None, :]), extra)
    expected = full[free_dofs][:, free_dofs]
    assert np.abs(expected).max() > 1e-3 * np.abs(blocks_np).max()
    np.testing.assert_allclose(curvature, expected, rtol=0, atol=1e-9 * np.abs(expected).max())


def test_pattern_is_analysed_again_only_when_the_coupled_vertices_change():
    # a cube on a fixed slab couples no two free vertices the tets do not: pairs change, no new analysis
    sim = _landing()
    problem = sim.step_problem()
    newton = GlobalNewton(problem.tets, problem.free, LinearSolver.QDLDL)
    contact = newton.contact_pairs(problem.contact)
    x = sim.positions
    touching, direct = newton.coupled_system(contact, x)
    assert len(contact.couplings(x)[1]) > 0 and newton.analyses == 1
    assert newton.coupled_system(contact, x.copy()) == (touching, direct)
    lifted = x + [0.0, 0.0, 0.01] * sim.free_mask[:, None]
    apart, same_direct = newton.coupled_system(contact, lifted)
    assert len(contact.couplings(lifted)[1]) == 0 and apart is not touching
    assert same_direct is direct and newton.analyses == 1
    result = newton.solve(problem, x)
    assert result.converged and newton.analyses == 1
    # two free cubes: their pairs couple vertices of both bodies, which only contact joins
    sim, n = _head_on()
    problem = sim.step_problem()
    newton = GlobalNewton(problem.tets, problem.free, LinearSolver.QDLDL)
    contact = newton.contact_pairs(problem.contact)
    x = sim.positions
    _, first = newton.coupled_system(contact, x)
    assert newton.analyses == 1
    separated = x.copy()
    separated[:n, 0] -= 0.005
    separated[n:, 0] += 0.005
    _, second = newton.coupled_system(contact, separated)
    assert newton.analyses == 2 and second is not first
    newton.coupled_system(contact, x)
    assert newton.analyses == 3


@pytest.mark.parametrize("linear_solver", [LinearSolver.QDLDL, LinearSolver.SUPERLU, LinearSolver.AUTO])
def test_every_linear_solver_gives_the_oracle_answer(linear_solver):
    sim, _ = _head_on()
    problem, x_n = sim.step_problem(), sim.positions
    reference = newton_solve(problem, x_n)
    fast = fast_newton_solve(problem, x_n, linear_solver=linear_solver)
    assert fast.converged
    assert solver.relative_error(fast.x, reference.x, x_n) <= 1e-8


def test_head_on_newton_steps_conserve_momentum_and_never_cross():
    sim, n = _head_on()
    m = sim.masses
    p0 = 0.5 * m[:n].sum()
    touched = 0
    for _ in range(30):
        sim.step()
        v = sim.velocities
        assert np.abs(m @ v).max() <= 1e-6 * p0
        assert len(crossings(sim.positions, sim.mesh.tets, True)[0]) == 0 and sim.min_separation() > 0
        touched = max(touched, sim.contact_count())
    assert touched > 0
    assert v[:n, 0].mean() < 0 < v[n:, 0].mean(), "the cubes did not rebound"
