"""Projected Newton on G with Taichi assembly and a sparse direct solve: the fast twin of `newton_solve`.

Same iteration, line search and convergence test as the numpy oracle `solver.newton.newton_solve`
(lecture notes, chapter 2), so the two agree to round-off; what changes is the cost. G, its gradient
and the projected Hessian come from the kernels in `solver.hessian`, into a CSR pattern built once
per mesh and free mask, and the linear system is solved by a sparse factorisation of that pattern:

- `LinearSolver.QDLDL`: LDL^T (pip package `qdldl`) with AMD ordering and symbolic analysis once per
  pattern; each iteration only refactorises the numbers. Fastest measured below ~10^4 unknowns.
- `LinearSolver.CHOLESPY`: CHOLMOD's Cholesky through `cholespy`, analysed with every factorisation.
- `LinearSolver.SUPERLU`: scipy's SuperLU with the MMD ordering of H^T + H, always available; the
  fallback when an optional package is missing (one warning per process). Fastest measured on the
  30,720-tet bar (less fill than qdldl's AMD; COLAMD was 3x slower there).
- `LinearSolver.AUTO` (default): QDLDL up to 10,000 unknowns, SUPERLU above.

Build the solver once per mesh (`GlobalNewton(tets, free)`, or the cached `global_newton(...)`), then
call `.solve(problem, x0)` for every step. `fast_newton_solve(problem, x0)` is the drop-in for
`newton_solve`.
"""
import hashlib
import time
import warnings
from collections import OrderedDict
from enum import Enum

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .backend import ensure_taichi
from .errors import ConfigError, enum_value
from .hessian import HessianPattern, StepKernels
from .newton import NewtonRecord, NewtonResult

_WARNED = set()


def warn_once(key: str, message: str) -> None:
    """Warn with `message` the first time `key` is seen in this process."""
    if key not in _WARNED:
        _WARNED.add(key)
        warnings.warn(message, stacklevel=3)


class LinearSolver(Enum):
    """How the Newton system H d = -g is solved (see the module docstring)."""

    AUTO = "auto"
    QDLDL = "qdldl"
    CHOLESPY = "cholespy"
    SUPERLU = "superlu"


AUTO_QDLDL_MAX_UNKNOWNS = 10_000


def as_linear_solver(value) -> LinearSolver:
    """Accept a `LinearSolver` or its name."""
    return enum_value(LinearSolver, value, "linear solver")


class DirectSolver:
    """Factorise and solve the pattern's current matrix; the symbolic work is done once."""

    def __init__(self, pattern: HessianPattern, kind: LinearSolver):
        self.pattern = pattern
        if kind is LinearSolver.AUTO:
            kind = LinearSolver.QDLDL if pattern.n_dofs <= AUTO_QDLDL_MAX_UNKNOWNS else LinearSolver.SUPERLU
        self.kind = self._available(kind)
        rows = np.repeat(np.arange(pattern.n_dofs, dtype=np.int32), np.diff(pattern.indptr))
        if self.kind is LinearSolver.QDLDL:
            # The upper triangle in CSC is the lower triangle in CSR (H is symmetric).
            self._lower = np.flatnonzero(pattern.indices <= rows)
            self._upper_indptr = np.concatenate([[0], np.cumsum(np.bincount(rows[self._lower],
                                                                             minlength=pattern.n_dofs))])
            self._upper_indices = pattern.indices[self._lower]
            self._qdldl = None
        elif self.kind is LinearSolver.CHOLESPY:
            self._rows = rows

    @staticmethod
    def _available(kind):
        module = {LinearSolver.QDLDL: "qdldl", LinearSolver.CHOLESPY: "cholespy"}.get(kind)
        if module is None:
            return kind
        try:
            __import__(module)
        except ImportError:
            warn_once(f"missing-{module}", f"the optional sparse solver {module!r} is not installed "
                      f"(pip install {module}); using scipy's SuperLU instead")
            return LinearSolver.SUPERLU
        return kind

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """d (3F,) with H d = rhs for the pattern's current values H."""
        p = self.pattern
        if self.kind is LinearSolver.QDLDL:
            import qdldl

            upper = sp.csc_matrix((p.data[self._lower], self._upper_indices, self._upper_indptr),
                                  shape=(p.n_dofs, p.n_dofs))
            if self._qdldl is None:
                self._qdldl = qdldl.Solver(upper, upper=True)
            else:
                self._qdldl.update(upper, upper=True)
            return self._qdldl.solve(rhs)
        if self.kind is LinearSolver.CHOLESPY:
            from cholespy import CholeskySolverD, MatrixType

            factor = CholeskySolverD(p.n_dofs, p.indptr, p.indices, p.data, MatrixType.CSR)
            out = np.zeros_like(rhs)
            factor.solve(np.ascontiguousarray(rhs), out)
            return out
        return superlu_solve(p.matrix(), rhs)


def superlu_solve(H: sp.spmatrix, rhs: np.ndarray) -> np.ndarray:
    """SuperLU with the MMD ordering of H^T + H: no positive-definiteness needed."""
    return spla.spsolve(H.tocsc(), rhs, permc_spec="MMD_AT_PLUS_A")


class GlobalNewton:
    """Projected Newton with Armijo backtracking for `StepProblem`s on one mesh and free mask.

    tets (M, 4) int; free (N,) bool: which vertices are unknowns. Builds the Hessian pattern and the
    solver's symbolic analysis once; `solve` can be called for any problem with these tets and free
    mask (other positions, masses, material, time step, ground).
    """

    def __init__(self, tets: np.ndarray, free: np.ndarray, linear_solver=LinearSolver.AUTO):
        ensure_taichi()
        self.pattern = HessianPattern(tets, free)
        self.linear_solver = as_linear_solver(linear_solver)
        self.direct = DirectSolver(self.pattern, self.linear_solver)

    def check(self, problem) -> None:
        """Raise ConfigError unless `problem` has this solver's tets and free mask."""
        p = self.pattern
        if problem.tets.shape != p.tets.shape or not np.array_equal(problem.free, p.free) \
                or not np.array_equal(problem.tets, p.tets):
            raise ConfigError("this GlobalNewton was built for another mesh or free mask; "
                              "use solver.global_newton.global_newton(problem.tets, problem.free) for this problem")

    def newton_direction(self, kernels: StepKernels, x: np.ndarray, g: np.ndarray) -> np.ndarray:
        """d (N, 3) solving H d = -g on the free vertices (0 elsewhere); falls back to SuperLU, then
        to a mass-scaled gradient step, with a warning, when H is not positive definite."""
        p = self.pattern
        kernels.hessian(x)
        rhs = -g[p.free].ravel()
        d = np.zeros_like(x)
        try:
            d[p.free] = self.direct.solve(rhs).reshape(-1, 3)
        except RuntimeError:            # qdldl: "not quasi-definite"
            d[:] = np.nan
        if np.isfinite(d).all() and np.vdot(g, d) < 0:
            return d
        warnings.warn("the projected Hessian is not positive definite (no descent direction); "
                      "retrying with SuperLU", stacklevel=3)
        d[p.free] = superlu_solve(p.matrix(), rhs).reshape(-1, 3)
        if np.isfinite(d).all() and np.vdot(g, d) < 0:
            return d
        warnings.warn("SuperLU gave no descent direction either; taking a mass-scaled gradient step",
                      stacklevel=3)
        inverse_stiffness = np.divide(kernels.h ** 2, kernels.masses, out=np.zeros_like(kernels.masses),
                                      where=kernels.masses > 0)
        return -g * inverse_stiffness[:, None]

    def solve(self, problem, x0: np.ndarray, tolerance: float = 1e-10, max_iterations: int = 50,
              keep_iterates: bool = False, time_budget: float = None) -> NewtonResult:
        """Minimise G from x0 (N, 3); same result, convergence test and warnings as `newton_solve`.
        time_budget: stop (quietly, not converged) after the iteration that exceeds these seconds."""
        self.check(problem)
        kernels = StepKernels(self.pattern, problem)
        return newton_iterations(problem, kernels, x0, tolerance, max_iterations, keep_iterates,
                                 lambda x, g, it: self.newton_direction(kernels, x, g), time_budget)


def newton_iterations(problem, kernels, x0, tolerance, max_iterations, keep_iterates, direction, time_budget=None):
    """The loop of `newton_solve` with G and dG/dx from `kernels` and the step from
    direction(x, g, iteration) -> d (N, 3). Shared by the direct and the PCG Newton."""
    free = problem.free
    x = np.ascontiguousarray(np.where(free[:, None], x0, problem.constrained_positions), dtype=np.float64)
    size = float(np.ptp(x, axis=0).max()) or 1.0
    force_scale = float(np.max(problem.masses) / problem.h ** 2 * size)
    start = time.perf_counter()
    G = kernels.energy(x)
    g = kernels.gradient(x)
    result = NewtonResult(x, 0, False)
    result.history.append(NewtonRecord(0, G, float(np.abs(g).max()), 0.0))
    x_new = np.empty_like(x)
    for it in range(1, max_iterations + 1):
        d = direction(x, g, it)
        if not np.isfinite(d).all():
            warnings.warn(f"Newton direction is not finite at iteration {it}; stopping at the last iterate",
                          stacklevel=3)
            break
        slope = float(np.vdot(g, d))
        alpha = 1.0
        while alpha >= 1e-10:
            np.multiply(d, alpha, out=x_new)
            x_new += x
            G_new = kernels.energy(x_new)
            if np.isfinite(G_new) and G_new <= G + 1e-4 * alpha * slope + 1e-15 * abs(G):
                break
            alpha *= 0.5
        else:
            if np.abs(g).max() > 1e-10 * force_scale:
                warnings.warn(f"the line search could not decrease G at iteration {it} (max |dG/dx| = "
                              f"{np.abs(g).max():.2e} N); stopping at the last iterate", stacklevel=3)
            break
        x, x_new = x_new, x
        G = G_new
        g = kernels.gradient(x)
        result.history.append(NewtonRecord(it, G, float(np.abs(g).max()), time.perf_counter() - start))
        if keep_iterates:
            result.iterates.append(x.copy())
        result.iterations = it
        if alpha * np.abs(d).max() <= tolerance * size or np.abs(g).max() <= 1e-13 * force_scale:
            result.converged = True
            break
        if time_budget is not None and result.history[-1].seconds > time_budget:
            break
    result.x = x.copy()
    if not result.converged and (time_budget is None or result.history[-1].seconds <= time_budget):
        warnings.warn(f"Newton did not converge ({result.iterations} iterations)", stacklevel=3)
    return result


_CACHE = OrderedDict()
_CACHE_SIZE = 8


def connectivity_key(tets: np.ndarray, free: np.ndarray) -> tuple:
    """A hashable key of a mesh's connectivity and free mask."""
    tets = np.ascontiguousarray(tets, dtype=np.int64)
    free = np.ascontiguousarray(free, dtype=bool)
    digest = hashlib.sha1(tets.tobytes())
    digest.update(free.tobytes())
    return tets.shape, free.shape, digest.hexdigest()


def global_newton(tets: np.ndarray, free: np.ndarray, linear_solver=LinearSolver.AUTO) -> GlobalNewton:
    """The `GlobalNewton` of this connectivity and free mask, built on first use and cached (the last
    8 meshes) so that every step and every Simulation on the same mesh reuses it."""
    key = connectivity_key(tets, free) + (as_linear_solver(linear_solver),)
    if key in _CACHE:
        _CACHE.move_to_end(key)
        return _CACHE[key]
    solver = GlobalNewton(tets, free, linear_solver)
    _CACHE[key] = solver
    while len(_CACHE) > _CACHE_SIZE:
        _CACHE.popitem(last=False)
    return solver


def fast_newton_solve(problem, x0: np.ndarray, tolerance: float = 1e-10, max_iterations: int = 50,
                      keep_iterates: bool = False, linear_solver=LinearSolver.AUTO) -> NewtonResult:
    """Drop-in for `solver.newton_solve`: the same minimisation by the cached `GlobalNewton`."""
    return global_newton(problem.tets, problem.free, linear_solver).solve(problem, x0, tolerance, max_iterations,
                                                                         keep_iterates)
