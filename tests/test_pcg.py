"""Newton-PCG: matrix-free Hessian-vector products, VBD-block preconditioners, and convergence to x*."""
import numpy as np
import pytest

import solver
from solver.newton.hessian import StepKernels
from solver.newton.pcg import NewtonPCG, Preconditioner, inverse_diagonal_blocks_kernel

pytestmark = pytest.mark.backend  # launches Taichi kernels: re-run on CUDA


@pytest.fixture(scope="module")
def problem():
    """A pinned stiff bar pushed into the ground (contact active)."""
    mesh = solver.box_mesh(size=(0.6, 0.1, 0.1), cells=(6, 2, 2))
    sim = solver.Simulation(mesh, solver.Material(1e6, 0.3, 1000.0), dt=1 / 60,
                            fixed=mesh.vertices[:, 0] < 1e-9, iterations=1,
                            ground=solver.Ground(height=-0.005, stiffness=1e5))
    sim.set_velocities(np.tile([0.0, 0.2, -1.0], (mesh.n_vertices, 1)))
    return sim.step_problem()


@pytest.fixture(scope="module")
def state(problem):
    """(solver, kernels, x): stress Hessians, assembled Hessian and diagonal blocks at a perturbed x."""
    p = problem
    pcg = NewtonPCG(p.tets, p.free, Preconditioner.COLOR_SWEEP)
    kernels = StepKernels(pcg.pattern, p)
    rng = np.random.default_rng(0)
    x = np.ascontiguousarray(p.y_with_constraints() + 0.01 * rng.standard_normal(p.y.shape) * p.free[:, None])
    kernels.stress_hessians(x)
    kernels.hessian(x)
    inverse_diagonal_blocks_kernel(pcg.pattern.A9, p.tets.astype(np.int32), kernels.grad_rows, kernels.volumes,
                                   kernels.masses, pcg.pattern.free_int, x, kernels.h, *kernels.ground, pcg.D_inv)
    return pcg, kernels, x


def _free_hessian(p, x):
    free = np.flatnonzero(np.repeat(p.free, 3))
    return p.hessian(x)[free][:, free].toarray()


def test_hessian_vector_product_matches_the_oracle(problem, state):
    pcg, kernels, x = state
    p = problem
    assert (x[p.free, 2] < p.ground.height).any()      # contact contributes
    v = np.random.default_rng(1).standard_normal(x.shape) * p.free[:, None]
    Hv = pcg.hessian_vector(kernels, x, v, np.zeros_like(x))
    expected = (_free_hessian(p, x) @ v[p.free].ravel()).reshape(-1, 3)
    np.testing.assert_allclose(Hv[p.free], expected, rtol=0, atol=1e-10 * np.abs(expected).max())
    assert np.all(Hv[~p.free] == 0.0)


def test_diagonal_blocks_are_the_vertex_hessians(problem, state):
    pcg, _, x = state
    p = problem
    H = _free_hessian(p, x)
    n = int(p.free.sum())
    blocks = np.stack([H[3 * i:3 * i + 3, 3 * i:3 * i + 3] for i in range(n)])
    np.testing.assert_allclose(np.linalg.inv(pcg.D_inv[p.free]), blocks, rtol=0, atol=1e-10 * np.abs(blocks).max())


def test_color_sweep_is_symmetric_gauss_seidel(problem, state):
    """M^-1 r equals (D + U)^-1 D (D + L)^-1 r with the vertices in colour order, and is symmetric."""
    pcg, kernels, x = state
    p = problem
    H = _free_hessian(p, x)
    rank = np.full(len(p.free), -1)
    rank[p.free] = np.arange(int(p.free.sum()))
    perm = (3 * rank[pcg.color_order][:, None] + np.arange(3)).ravel()
    Hp = H[np.ix_(perm, perm)]
    block = np.kron(np.eye(len(pcg.color_order)), np.ones((3, 3))) > 0
    D = np.where(block, Hp, 0.0)
    lower = np.tril(Hp, -1) * ~block + D
    upper = np.triu(Hp, 1) * ~block + D
    rng = np.random.default_rng(2)
    r = rng.standard_normal(x.shape) * p.free[:, None]
    z = pcg.precondition(kernels, r, np.zeros_like(x))
    expected = np.linalg.solve(upper, D @ np.linalg.solve(lower, r[pcg.color_order].ravel()))
    np.testing.assert_allclose(z[pcg.color_order].ravel(), expected, rtol=1e-9, atol=1e-12 * np.abs(expected).max())
    s = rng.standard_normal(x.shape) * p.free[:, None]
    zs = pcg.precondition(kernels, s, np.zeros_like(x))
    assert np.vdot(s, z) == pytest.approx(np.vdot(r, zs), rel=1e-10)


@pytest.mark.parametrize("preconditioner", list(Preconditioner))
def test_newton_pcg_converges_to_the_newton_solution(problem, preconditioner):
    p = problem
    x0 = p.y_with_constraints()
    ref = solver.newton_solve(p, x0, tolerance=1e-12)
    result = NewtonPCG(p.tets, p.free, preconditioner).solve(p, x0, tolerance=1e-12)
    assert result.converged and result.direct_iterations == 0
    assert len(result.cg_iterations) == result.iterations and min(result.cg_iterations) >= 1
    assert np.abs(result.x - ref.x).max() <= 1e-9 * np.abs(ref.x - x0).max()


def test_stalled_pcg_finishes_with_the_direct_solver(problem):
    p = problem
    x0 = p.y_with_constraints()
    ref = solver.newton_solve(p, x0, tolerance=1e-12)
    pcg = NewtonPCG(p.tets, p.free, Preconditioner.BLOCK_JACOBI, forcing=1e-3, max_cg_iterations=2)
    with pytest.warns(UserWarning, match=r"PCG stalled at .* after 2 iterations; finishing with the direct solver"):
        result = pcg.solve(p, x0, tolerance=1e-12)
    assert result.converged and result.direct_iterations == result.iterations
    assert np.abs(result.x - ref.x).max() <= 1e-9 * np.abs(ref.x - x0).max()


def test_bad_settings_are_config_errors(problem):
    p = problem
    with pytest.raises(solver.ConfigError, match="unknown preconditioner 'ilu'"):
        NewtonPCG(p.tets, p.free, "ilu")
    with pytest.raises(solver.ConfigError, match="forcing"):
        NewtonPCG(p.tets, p.free, forcing=1.5)
