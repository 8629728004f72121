"""Task vbd_sweep: assemble and solve each vertex's 3x3 system, one colour at a time (chapters 3-4)."""
import numpy as np
import pytest

import solver
from gradelib import (bar, elastic_gradient, elastic_hessian_blocks, reference, require, simulation,
                      student_local_systems)

pytestmark = pytest.mark.task("vbd_sweep")


# Each term of f_i = -dG/dx_i and H_i = d2G/dx_i2 on its own, against G built from the given stress P(F):
# G(x) = sum_i m_i/(2 h^2) |x_i - y_i|^2 + sum_t vol_t Psi(F_t).
def deformed(mesh, seed=0, scale=0.01):
    """The rest shape with every vertex moved by up to about `scale` metres (no tet inverted)."""
    return mesh.vertices + np.random.default_rng(seed).normal(scale=scale, size=mesh.vertices.shape)


def inertia_force(y, x, m, h):
    return (m / h ** 2)[:, None] * (y - x)


def test_inertia_term_of_the_force():
    require("vbd_sweep")
    mesh = bar(cells=(2, 1, 1))
    x = mesh.vertices.copy()                       # the rest shape: no elastic force, only inertia
    f, _, y, m, h, free, _ = student_local_systems(mesh, x)
    expected = inertia_force(y, x, m, h)
    assert np.allclose(f[free], expected[free], rtol=1e-9, atol=1e-12 * np.abs(expected).max()), \
        "the inertia term of f_i is wrong: at the rest shape (no elastic force) f_i must be m_i/h^2 (y_i - x_i)"


def test_inertia_term_of_the_hessian():
    require("vbd_sweep")
    mesh = bar(cells=(2, 1, 1))
    x = deformed(mesh)
    _, H1, _, m1, h, free, _ = student_local_systems(mesh, x, density=1000.0)
    _, H2, _, m2, _, _, _ = student_local_systems(mesh, x, density=2000.0)
    expected = ((m2 - m1) / h ** 2)[:, None, None] * np.eye(3)
    assert np.allclose((H2 - H1)[free], expected[free], rtol=1e-9, atol=1e-9 * np.abs(expected).max()), \
        "the inertia term of H_i is wrong: doubling the density (so m_i) must add m_i/h^2 I to H_i"


def test_elasticity_term_of_the_force():
    require("vbd_sweep")
    mesh = bar(cells=(2, 1, 1))
    x = deformed(mesh)
    f, _, y, m, h, free, material = student_local_systems(mesh, x)
    expected = -elastic_gradient(mesh.vertices, mesh.tets, x, material.mu, material.lam)
    elastic = f - inertia_force(y, x, m, h)
    assert np.abs(elastic - expected)[free].max() <= 1e-7 * np.abs(expected).max(), \
        "the elasticity term of f_i is wrong: f_i - m_i/h^2 (y_i - x_i) must be -dE/dx_i, summed over all tets around i"


def test_elasticity_term_of_the_hessian():
    require("vbd_sweep")
    mesh = bar(cells=(2, 1, 1))
    x = deformed(mesh)
    _, H, _, m, h, free, material = student_local_systems(mesh, x)
    expected = elastic_hessian_blocks(mesh.vertices, mesh.tets, x, material.mu, material.lam)
    elastic = H - (m / h ** 2)[:, None, None] * np.eye(3)
    assert np.abs(elastic - expected)[free].max() <= 1e-5 * np.abs(expected).max(), \
        "the elasticity term of H_i is wrong: H_i - m_i/h^2 I must be d2E/dx_i2, summed over all tets around i"


def test_every_iteration_lowers_the_incremental_potential():
    require("vbd_sweep")
    sim = simulation(bar(), youngs_modulus=1e5, iterations=15, record_history=True)
    sim.step()
    G = np.array([r.energy for r in sim.history])
    assert G[-1] < G[0]
    # each local energy is quadratic in x_i, so each 3x3 Newton step minimises it exactly
    assert (np.diff(G) <= 1e-10 * np.abs(G).max()).all(), "an iteration increased G"


def test_the_last_color_is_solved_exactly():
    require("vbd_sweep")
    sim = simulation(bar(), youngs_modulus=1e5)
    sim.begin_step()
    before = np.linalg.norm(sim.residual(), axis=1).max()
    sim.run_iterations(1)
    f = np.linalg.norm(sim.residual(), axis=1)
    last = sim.colors == sim.colors.max()
    assert f[last].max() <= 1e-9 * before, "after a sweep the vertices solved last must have f_i = 0"
    assert f.max() > 1e-6 * before        # ...while other vertices moved on without them
    sim.end_step()


def test_converges_to_the_newton_step():
    require("vbd_sweep")
    sim, x_star = reference("soft_bar", iterations=300)
    x_n = sim.positions
    sim.step()
    assert solver.relative_error(sim.positions, x_star, x_n) < 1e-6


def test_pinned_vertices_stay_and_the_bar_sags():
    require("vbd_sweep")
    sim = simulation(bar(), youngs_modulus=1e4, iterations=30)
    rest = sim.positions
    sim.step(3)
    x = sim.positions
    assert np.array_equal(x[sim.fixed_mask], rest[sim.fixed_mask])
    tip = rest[:, 0] > rest[:, 0].max() - 1e-9
    assert (x[tip, 2] < rest[tip, 2]).all(), "gravity points down (-z): the free end must sag"
    assert np.isfinite(x).all()


def test_inertia_alone_gives_free_fall():
    require("vbd_sweep")
    mesh = bar(cells=(2, 1, 1))
    sim = solver.Simulation(mesh, solver.Material(1e4, 0.3, 1000.0), dt=0.01, iterations=200,
                            initial_guess=solver.InitialGuess.PREVIOUS)
    sim.step()
    # a free body at rest: elastic forces stay zero, implicit Euler moves it by h^2 g in one step
    assert np.allclose(sim.positions - mesh.vertices, [0.0, 0.0, -9.81e-4], rtol=0, atol=1e-10)
