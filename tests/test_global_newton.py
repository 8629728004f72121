"""The Taichi Newton against the numpy oracle: G, gradient, projected Hessian and the converged step."""
import sys
import warnings

import numpy as np
import pytest
import scipy.sparse as sp

import solver
from solver.newton.direct import DirectSolver, GlobalNewton, LinearSolver, fast_newton_solve, global_newton
from solver.newton.hessian import HessianPattern, StepKernels

pytestmark = pytest.mark.backend  # launches Taichi kernels: re-run on CUDA


def _bar_with_ground():
    """A pinned bar pushed into the ground: contact active in the solution."""
    mesh = solver.box_mesh(size=(1.0, 0.1, 0.1), cells=(8, 2, 2))
    sim = solver.Simulation(mesh, solver.Material(1e5, 0.3, 1000.0), dt=1 / 60,
                            fixed=mesh.vertices[:, 0] < 1e-9, iterations=1,
                            ground=solver.Ground(height=-0.01, stiffness=1e4))
    sim.set_velocities(np.tile([0.0, 0.3, -1.0], (mesh.n_vertices, 1)))
    return sim.step_problem()


def _kinematic_block():
    """A stiff block whose left face is pulled along x by a script and whose right face is fixed."""
    mesh = solver.box_mesh(size=(0.3, 0.2, 0.1), cells=(3, 2, 2))
    X = mesh.vertices
    sim = solver.Simulation(mesh, solver.Material(1e6, 0.4, 1000.0), dt=1 / 60,
                            fixed=X[:, 0] > 0.3 - 1e-9, kinematic=X[:, 0] < 1e-9,
                            kinematic_motion=lambda t, rest: rest + np.array([-2.0 * t, 0.0, 0.5 * t]),
                            iterations=1)
    return sim.step_problem()


def _falling_cube():
    """A free cube falling onto the ground with a spin: no fixed vertex."""
    mesh = solver.box_mesh(size=(0.1, 0.1, 0.1), cells=(2, 2, 2), origin=(0.0, 0.0, 0.001))
    sim = solver.Simulation(mesh, solver.Material(1e4, 0.3, 1000.0), dt=1 / 30, iterations=1,
                            ground=solver.Ground(height=0.0, stiffness=1e5))
    omega = np.array([0.0, 3.0, 1.0])
    sim.set_velocities(np.cross(omega, mesh.vertices - 0.05) + [0.0, 0.0, -1.0])
    return sim.step_problem()


PROBLEMS = {"bar_with_ground": _bar_with_ground, "kinematic_block": _kinematic_block,
            "falling_cube": _falling_cube}


@pytest.fixture(scope="module", params=sorted(PROBLEMS))
def problem(request):
    return PROBLEMS[request.param]()


def _perturbed(p, scale, seed):
    rng = np.random.default_rng(seed)
    return np.ascontiguousarray(p.y_with_constraints() + scale * rng.standard_normal(p.y.shape) * p.free[:, None])


def test_energy_gradient_and_projected_hessian_match_the_oracle(problem):
    p = problem
    kernels = StepKernels(HessianPattern(p.tets, p.free), p)
    x = _perturbed(p, 0.01, 0)
    assert kernels.energy(x) == pytest.approx(p.energy(x), rel=1e-12)
    g = p.gradient(x)
    np.testing.assert_allclose(kernels.gradient(x), g, rtol=0, atol=1e-10 * np.abs(g).max())
    free = np.flatnonzero(np.repeat(p.free, 3))
    H_ref = p.hessian(x)[free][:, free]
    H = kernels.hessian(x)
    assert H.shape == H_ref.shape
    assert abs(H - H_ref).max() <= 1e-9 * abs(H_ref).max()
    # the projection is active here, so this compares the projections and not just the Hessians
    H_exact = p.hessian(x, project=False)[free][:, free]
    assert abs(H_exact - H_ref).max() > 1e-3 * abs(H_ref).max()
    assert abs(kernels.hessian(x, project=False) - H_exact).max() <= 1e-9 * abs(H_exact).max()
    H = kernels.hessian(x)
    pattern = kernels.pattern
    upper = sp.csc_matrix((pattern.upper, pattern.upper_indices, pattern.upper_indptr), shape=H.shape)
    assert abs(upper - sp.triu(H)).max() <= 1e-14 * abs(H).max()     # what the Cholesky solvers factorise
    from_full = pattern.upper.copy()
    pattern.upper[:] = 0.0
    assert kernels.hessian(x, full=False) is None      # only the upper triangle, straight from the blocks
    np.testing.assert_array_equal(pattern.upper, from_full)


def test_projection_of_an_inverted_and_a_degenerate_tet():
    """Inverted (det F < 0), flattened and rest-state tets: the closed-form eigensystem gives the
    same projected dP/dF as a dense eigendecomposition."""
    from solver.physics.material import d2psi_dF2_np

    rng = np.random.default_rng(3)
    F = np.stack([np.eye(3), np.diag([1.0, 1.0, -0.5]), np.diag([1.0, 1.0, 1e-9]),
                  np.diag([0.7, 0.7, 0.7]), np.eye(3) + 0.4 * rng.standard_normal((3, 3))])
    # one tet per F: vertices 0..3 at the columns of F after a unit rest tet with m_k = e_k
    x = np.concatenate([np.zeros((len(F), 1, 3)), F.transpose(0, 2, 1)], axis=1).reshape(-1, 3)
    tets = np.arange(4 * len(F)).reshape(-1, 4)
    grad_rows = np.tile(np.array([[-1.0, -1.0, -1.0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]), (len(F), 1, 1))
    mu, lam = 3.0, 20.0
    p = solver.StepProblem(tets=tets, grad_rows=grad_rows, volumes=np.ones(len(F)), masses=np.ones(len(x)),
                           y=x, free=np.ones(len(x), bool), constrained_positions=x, h=1.0, mu=mu, lam=lam)
    kernels = StepKernels(HessianPattern(tets, p.free), p)
    A9 = kernels.stress_hessians(np.ascontiguousarray(x))
    A = d2psi_dF2_np(F, mu, lam).reshape(-1, 9, 9)
    w, Q = np.linalg.eigh(A)
    expected = np.einsum("tij,tj,tkj->tik", Q, np.maximum(w, 0.0), Q)
    np.testing.assert_allclose(A9, expected, rtol=0, atol=1e-9 * np.abs(expected).max())
    assert (w.min(axis=1)[1:] < -1e-6).all()      # every case but the rest state needs projecting


def test_fast_newton_agrees_with_newton_solve(problem):
    p = problem
    x0 = p.y_with_constraints()
    ref = solver.newton_solve(p, x0, tolerance=1e-12)
    fast = fast_newton_solve(p, x0, tolerance=1e-12)
    assert ref.converged and fast.converged
    step = np.abs(ref.x - x0).max()
    assert step > 1e-4
    assert np.abs(fast.x - ref.x).max() <= 1e-9 * step
    assert fast.iterations <= ref.iterations          # eigenvalue filtering: never slower than projected Newton
    energies = [r.energy for r in fast.history]
    assert all(b <= a + 1e-12 * abs(a) for a, b in zip(energies, energies[1:]))


def test_exact_hessian_near_the_solution_converges_in_fewer_iterations_than_projected_newton():
    """Eigenvalue filtering: where the projection is active at x*, projected Newton (the numpy oracle)
    converges linearly, the fast Newton quadratically: fewer iterations, the same x*, and the last
    iteration is a back substitution with the previous factorisation (one factorisation fewer)."""
    p = _bar_with_ground()
    x0 = p.y_with_constraints()
    ref = solver.newton_solve(p, x0, tolerance=1e-12)
    newton = GlobalNewton(p.tets, p.free)
    calls = []
    real_solve = newton.direct.solve
    newton.direct.solve = lambda rhs, **options: calls.append(1) or real_solve(rhs, **options)
    fast = newton.solve(p, x0, tolerance=1e-12)
    assert fast.converged and fast.iterations < ref.iterations
    assert np.abs(fast.x - ref.x).max() <= 1e-9 * np.abs(ref.x - x0).max()
    assert len(calls) < fast.iterations                # chord steps reuse the last factorisation
    gradients = [r.max_gradient for r in fast.history]
    assert gradients[2] < 1e-3 * gradients[1]          # quadratic, not linear, once close


def _squashed_cube():
    """(problem, x): the falling cube squashed to a third of its height, where G's exact Hessian (long time
    step) is not positive definite."""
    p = _falling_cube()
    x = p.y_with_constraints().copy()
    x[:, 2] = 0.001 + 0.3 * (x[:, 2] - x[:, 2].min())
    return p, np.ascontiguousarray(x)


def test_an_indefinite_exact_hessian_quietly_takes_the_projected_one():
    """A cube squashed to a third of its height with a long time step: the exact Hessian of G is not
    positive definite, so the direction is the projected Newton step, without a warning."""
    p, x = _squashed_cube()
    newton = GlobalNewton(p.tets, p.free)
    kernels = StepKernels(newton.pattern, p)
    assert np.linalg.eigvalsh(kernels.hessian(x, project=False).toarray()).min() < 0
    g = kernels.gradient(x)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        d = newton.newton_direction(kernels, x, g, project=False)
    projected = kernels.hessian(x).toarray()
    expected = np.linalg.solve(projected, -g[p.free].ravel())
    np.testing.assert_allclose(d[p.free].ravel(), expected, rtol=0, atol=1e-9 * np.abs(expected).max())


@pytest.mark.parametrize("kind", [LinearSolver.CHOLMOD, LinearSolver.CHOLESPY, LinearSolver.QDLDL])
def test_the_definiteness_test_of_each_linear_solver(kind):
    """The squashed cube's exact Hessian is indefinite: CHOLMOD and cholespy refuse it, QDLDL when asked
    (require_definite, as for exact contact pair blocks), always as ArithmeticError; the projected one
    passes every test and is solved."""
    module = {LinearSolver.CHOLMOD: "cvxopt", LinearSolver.CHOLESPY: "cholespy", LinearSolver.QDLDL: "qdldl"}[kind]
    pytest.importorskip(module, reason=f"the optional {module} is not installed")
    from solver.newton.direct import DirectSolver

    p, x = _squashed_cube()
    newton = GlobalNewton(p.tets, p.free)
    kernels = StepKernels(newton.pattern, p)
    direct = DirectSolver(newton.pattern, kind)
    rhs = -kernels.gradient(x)[p.free].ravel()
    exact = kernels.hessian(x, False, True, newton.pattern).toarray()
    assert np.linalg.eigvalsh(exact).min() < 0
    with pytest.raises(ArithmeticError):
        direct.solve(rhs, require_definite=True)
    assert not direct.factorised                    # no chord step from a refused factorisation
    if kind is LinearSolver.QDLDL:
        np.testing.assert_allclose(exact @ direct.solve(rhs), rhs, rtol=0, atol=1e-8 * np.abs(rhs).max())
    projected = kernels.hessian(x, True, True, newton.pattern).toarray()
    np.testing.assert_allclose(projected @ direct.solve(rhs, require_definite=True), rhs, rtol=0,
                               atol=1e-8 * np.abs(rhs).max())


@pytest.mark.parametrize("kind", list(LinearSolver))
def test_every_linear_solver_gives_the_same_step(kind):
    p = _bar_with_ground()
    if kind is LinearSolver.CHOLMOD:
        pytest.importorskip("cvxopt", reason="the optional CHOLMOD solver (requirements-cholmod.txt) is not installed")
    if kind is LinearSolver.CHOLESPY:
        pytest.importorskip("cholespy", reason="the optional cholespy (requirements-cholmod.txt) is not installed")
    if kind is LinearSolver.QDLDL:
        pytest.importorskip("qdldl", reason="optional sparse solver qdldl is not installed")
    x0 = p.y_with_constraints()
    ref = fast_newton_solve(p, x0, tolerance=1e-12, linear_solver=LinearSolver.SUPERLU)
    result = fast_newton_solve(p, x0, tolerance=1e-12, linear_solver=kind)
    assert result.converged
    assert np.abs(result.x - ref.x).max() <= 1e-9 * np.abs(ref.x - x0).max()


def test_solver_is_cached_per_connectivity_and_free_mask():
    p = _bar_with_ground()
    a = global_newton(p.tets, p.free)
    assert global_newton(p.tets.copy(), p.free.copy()) is a
    free = p.free.copy()
    free[np.flatnonzero(free)[0]] = False
    assert global_newton(p.tets, free) is not a
    with pytest.raises(solver.ConfigError, match="another mesh or free mask"):
        global_newton(p.tets, free).solve(p, p.y)


@pytest.mark.parametrize("module, asked, message", [
    ("qdldl", LinearSolver.QDLDL, "'qdldl' is not installed.*requirements.txt.*SuperLU"),
    ("cvxopt", LinearSolver.CHOLMOD, "'cvxopt' is not installed.*requirements-cholmod.txt.*SuperLU"),
])
def test_a_missing_sparse_solver_asked_for_falls_back_with_one_warning(monkeypatch, module, asked, message):
    p = _bar_with_ground()
    pattern = HessianPattern(p.tets, p.free)
    monkeypatch.setitem(sys.modules, module, None)      # makes `import <module>` fail
    monkeypatch.setattr("solver.newton.direct._WARNED", set())
    with pytest.warns(UserWarning, match=message):
        assert DirectSolver(pattern, asked).kind is LinearSolver.SUPERLU
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert DirectSolver(pattern, asked).kind is LinearSolver.SUPERLU


@pytest.mark.parametrize("limit_offset, used", [(0, LinearSolver.QDLDL), (-1, LinearSolver.SUPERLU)])
def test_auto_without_cvxopt_quietly_takes_qdldl_up_to_the_limit_and_superlu_above(monkeypatch, limit_offset, used):
    """cvxopt (GPL) is optional: its absence is the normal case, so AUTO does not warn."""
    p = _bar_with_ground()
    pattern = HessianPattern(p.tets, p.free)
    monkeypatch.setitem(sys.modules, "cvxopt", None)
    monkeypatch.setattr("solver.newton.direct._WARNED", set())
    monkeypatch.setattr("solver.newton.direct.AUTO_QDLDL_MAX_UNKNOWNS", pattern.n_dofs + limit_offset)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert DirectSolver(pattern, LinearSolver.AUTO).kind is used


def test_auto_with_cvxopt_takes_cholmod():
    pytest.importorskip("cvxopt", reason="the optional CHOLMOD solver (requirements-cholmod.txt) is not installed")
    p = _bar_with_ground()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert DirectSolver(HessianPattern(p.tets, p.free), LinearSolver.AUTO).kind is LinearSolver.CHOLMOD


@pytest.mark.parametrize("case", ["cholmod", "no cvxopt", "indefinite"])
def test_spd_solver_solves_with_cholmod_or_superlu(monkeypatch, case):
    """The two-level coarse solve: CHOLMOD, or SuperLU without cvxopt or for a matrix CHOLMOD rejects."""
    from solver.newton.direct import spd_solver

    rng = np.random.default_rng(1)
    A = sp.random(30, 30, density=0.2, random_state=2)
    H = (A @ A.T + sp.identity(30)).tocsr()
    if case == "indefinite":
        H = H - 3.0 * sp.identity(30)
        assert np.linalg.eigvalsh(H.toarray()).min() < 0
    if case == "cholmod":
        pytest.importorskip("cvxopt", reason="the optional CHOLMOD solver (requirements-cholmod.txt) is not installed")
    if case == "no cvxopt":
        monkeypatch.setitem(sys.modules, "cvxopt", None)
    b = rng.standard_normal(30)
    np.testing.assert_allclose(H @ spd_solver(H)(b), b, rtol=0, atol=1e-9)


def test_unknown_linear_solver_is_a_config_error():
    p = _bar_with_ground()
    with pytest.raises(solver.ConfigError, match="unknown linear solver 'mumps'"):
        global_newton(p.tets, p.free, linear_solver="mumps")


def test_a_solver_giving_no_descent_direction_warns_and_falls_back(monkeypatch):
    """If the factorisation returns a direction along which G increases (as for a Hessian that is
    not positive definite), the step warns, retries with SuperLU, and still converges to x*."""
    p = _bar_with_ground()
    x0 = p.y_with_constraints()
    ref = solver.newton_solve(p, x0, tolerance=1e-12)
    newton = GlobalNewton(p.tets, p.free, LinearSolver.QDLDL)
    monkeypatch.setattr(newton.direct, "solve", lambda rhs, **options: -rhs)      # an ascent direction: d = +g
    with pytest.warns(UserWarning, match="not positive definite.*retrying with SuperLU"):
        result = newton.solve(p, x0, tolerance=1e-12)
    assert result.converged
    assert np.abs(result.x - ref.x).max() <= 1e-9 * np.abs(ref.x - x0).max()


def test_time_budget_stops_quietly_after_the_iteration_that_exceeds_it():
    p = _bar_with_ground()
    x0 = p.y_with_constraints()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        result = global_newton(p.tets, p.free).solve(p, x0, tolerance=1e-12, keep_iterates=True, time_budget=0.0)
    assert result.iterations == 1 and not result.converged and len(result.iterates) == 1
    assert result.history[1].energy < result.history[0].energy


def test_a_failed_line_search_warns_and_keeps_the_last_iterate(monkeypatch):
    """When no step length decreases G (here: G reported as +inf away from x0), the solve stops with a
    warning naming the line search, and returns the last iterate, never NaN."""
    p = _bar_with_ground()
    x0 = p.y_with_constraints()
    start = np.ascontiguousarray(x0, dtype=np.float64)
    real = StepKernels.energy_gradient
    monkeypatch.setattr(StepKernels, "energy_gradient",
                        lambda self, x, g: real(self, x, g) if np.array_equal(x, start) else np.inf)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = global_newton(p.tets, p.free).solve(p, x0)
    messages = [str(w.message) for w in caught]
    assert any("line search could not decrease G" in m for m in messages), messages
    assert not result.converged and result.iterations == 0
    np.testing.assert_array_equal(result.x, start)
