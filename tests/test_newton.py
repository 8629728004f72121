"""The global Newton reference: its G, gradient and Hessian, and its quadratic convergence."""
import numpy as np
import pytest

import solver

pytestmark = pytest.mark.backend  # launches Taichi kernels: re-run on CUDA


@pytest.fixture(scope="module")
def problem():
    mesh = solver.box_mesh(size=(1.0, 0.1, 0.1), cells=(8, 2, 2))
    sim = solver.Simulation(mesh, solver.Material(1e5, 0.3, 1000.0), dt=1 / 60,
                            fixed=mesh.vertices[:, 0] < 1e-9, iterations=1,
                            ground=solver.Ground(height=-0.01, stiffness=1e4))
    sim.set_velocities(np.tile([0.0, 0.3, -1.0], (mesh.n_vertices, 1)))
    return sim, sim.step_problem()


def test_step_problem_energy_matches_the_taichi_energy(problem):
    sim, p = problem
    x = p.y_with_constraints() + 0.003 * np.random.default_rng(0).standard_normal(p.y.shape) * p.free[:, None]
    sim.begin_step()
    sim.set_positions(x)
    assert p.energy(x) == pytest.approx(sim.energy(), rel=1e-12)
    np.testing.assert_allclose(-p.gradient(x), sim.residual(), rtol=1e-9, atol=1e-9)
    sim.end_step()
    sim.reset()
    sim.set_velocities(np.tile([0.0, 0.3, -1.0], (sim.mesh.n_vertices, 1)))


def test_gradient_and_hessian_by_finite_differences(problem):
    _, p = problem
    rng = np.random.default_rng(1)
    x = p.y_with_constraints() + 0.002 * rng.standard_normal(p.y.shape) * p.free[:, None]
    g = p.gradient(x)
    d = rng.standard_normal(x.shape) * p.free[:, None]
    eps = 1e-6
    fd = (p.energy(x + eps * d) - p.energy(x - eps * d)) / (2 * eps)
    assert fd == pytest.approx(np.sum(g * d), rel=1e-6)
    Hd = (p.hessian(x, project=False) @ d.ravel()).reshape(-1, 3)
    fd_H = (p.gradient(x + eps * d) - p.gradient(x - eps * d)) / (2 * eps)
    np.testing.assert_allclose(Hd[p.free], fd_H[p.free], rtol=1e-5, atol=1e-6 * np.abs(Hd).max())
    # The projected Hessian of the free block is positive definite (the mass term keeps it > 0).
    free = np.flatnonzero(np.repeat(p.free, 3))
    H = p.hessian(x)[free][:, free].toarray()
    assert np.linalg.eigvalsh(0.5 * (H + H.T)).min() > 0


def test_newton_converges_quadratically_to_a_tight_tolerance(problem):
    _, p = problem
    result = solver.newton_solve(p, p.y_with_constraints(), tolerance=1e-12, keep_iterates=True)
    assert result.converged and result.iterations <= 10
    gradients = [r.max_gradient for r in result.history]
    assert gradients[-1] < 1e-9 * gradients[0]
    energies = [r.energy for r in result.history]
    assert all(b <= a + 1e-12 * abs(a) for a, b in zip(energies, energies[1:]))
    assert len(result.iterates) == result.iterations
    # Superlinear: once close, one iteration takes the relative gradient from r to below r^1.5.
    rel = np.array(gradients) / gradients[0]
    assert any(b < a ** 1.5 for a, b in zip(rel, rel[1:]) if a < 1e-2)


def test_newton_refuses_damping_and_friction():
    mesh = solver.box_mesh(cells=(3, 1, 1))
    sim = solver.Simulation(mesh, solver.Material(1e4, 0.3, 1000.0), damping=0.1, iterations=1)
    with pytest.raises(solver.ConfigError, match="damping"):
        sim.newton_reference()
