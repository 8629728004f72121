"""Projected Newton on G with Taichi assembly and a sparse direct solve: the fast twin of `newton_solve`.

Same loop, line search and convergence test as the numpy oracle `solver.newton.newton_solve`
(`damped_newton`, lecture notes, chapter 2), so the two agree to round-off; what changes is the cost. G, its gradient
and the projected Hessian come from the kernels in `solver.hessian`, into a CSR pattern built once
per mesh and free mask, and the linear system is solved by a sparse factorisation of that pattern:

- `LinearSolver.CHOLMOD`: CHOLMOD's supernodal Cholesky through `cvxopt`, with the fill-reducing
  ordering and symbolic analysis once per pattern; each iteration only refactorises the numbers. Fastest
  measured at every size here (benchmarks/newton_speed.py), but GPL-3, so an optional extra
  (`pip install -r requirements-cholmod.txt`; README, "Licence").
- `LinearSolver.QDLDL`: LDL^T (pip package `qdldl`, Apache-2.0) with AMD ordering and symbolic analysis
  once per pattern; each iteration only refactorises the numbers. Not supernodal: slower than SuperLU
  above ~10^4 unknowns.
- `LinearSolver.CHOLESPY`: CHOLMOD's Cholesky through `cholespy` (a BSD-3 wrapper, but its wheel links
  CHOLMOD's GPL Supernodal module statically, so also in requirements-cholmod.txt), analysed with every
  factorisation; never the fastest here.
- `LinearSolver.SUPERLU`: scipy's SuperLU with the MMD ordering of H^T + H, always available; the
  fallback when an asked-for optional package is missing (one warning per process).
- `LinearSolver.AUTO` (default): CHOLMOD when cvxopt is installed; otherwise, quietly, the faster
  permissive solver for the size: QDLDL up to AUTO_QDLDL_MAX_UNKNOWNS unknowns, SUPERLU above.

Build the solver once per mesh (`GlobalNewton(tets, free)`, or the cached `global_newton(...)`), then
call `.solve(problem, x0)` for every step. `fast_newton_solve(problem, x0)` is the drop-in for
`newton_solve`.

With contact (`problem.contact`, issue 17) G gains E_c from the kernels of `contact_pairs.py`, its pairs
found again at every iterate, and the line search starts from the step cap of the conservative bounds.
The Hessian's pattern is the tets' joined by the pairs closer than the radius (`HessianPattern`'s
couplings): built anew when those pairs change, and analysed anew (ordering, symbolic factorisation)
only when the coupled vertex pairs change; chord steps only while the pairs are those of the last
factorisation. Without contact nothing of this runs.
"""
import hashlib
import warnings
from collections import OrderedDict
from enum import Enum

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.sparse.csgraph import reverse_cuthill_mckee

from ..backend import RuntimeCache, ensure_taichi
from ..errors import ConfigError, enum_value
from .contact_pairs import ContactPairs
from .hessian import HessianPattern, StepKernels
from .damped_newton import REFERENCE_TOLERANCE, NewtonResult, damped_newton

_WARNED = set()


def warn_once(key: str, message: str) -> None:
    """Warn with `message` the first time `key` is seen in this process."""
    if key not in _WARNED:
        _WARNED.add(key)
        warnings.warn(message, stacklevel=3)


class LinearSolver(Enum):
    """How the Newton system H d = -g is solved (see the module docstring)."""

    AUTO = "auto"
    CHOLMOD = "cholmod"
    QDLDL = "qdldl"
    CHOLESPY = "cholespy"
    SUPERLU = "superlu"


# Without cvxopt, AUTO's switch from QDLDL to SuperLU (benchmarks/results/newton_speed: QDLDL is the
# faster on the 1,920-tet bar, SuperLU on the 30,720-tet one).
AUTO_QDLDL_MAX_UNKNOWNS = 10_000


def as_linear_solver(value) -> LinearSolver:
    """Accept a `LinearSolver` or its name."""
    return enum_value(LinearSolver, value, "linear solver")


class DirectSolver:
    """Factorise and solve the pattern's current matrix; the symbolic work is done once."""

    _MODULES = {LinearSolver.CHOLMOD: "cvxopt", LinearSolver.QDLDL: "qdldl", LinearSolver.CHOLESPY: "cholespy"}

    def __init__(self, pattern: HessianPattern, kind: LinearSolver):
        self.pattern = pattern
        if kind is LinearSolver.AUTO:
            kind = self._auto(pattern.n_dofs)
        self.kind = self._available(kind)
        self._factor = None
        self.factorised = False     # whether back_solve can use a factorisation of the last matrix

    @classmethod
    def _auto(cls, n_dofs):
        if cls.installed(LinearSolver.CHOLMOD):
            return LinearSolver.CHOLMOD
        return LinearSolver.QDLDL if n_dofs <= AUTO_QDLDL_MAX_UNKNOWNS else LinearSolver.SUPERLU

    @staticmethod
    def _importable(module):
        try:
            __import__(module)
        except ImportError:
            return False
        return True

    @classmethod
    def installed(cls, kind: LinearSolver) -> bool:
        """Whether `kind` can run here: its optional package imports (SuperLU, in scipy, always can)."""
        module = cls._MODULES.get(kind)
        return module is None or cls._importable(module)

    @classmethod
    def _available(cls, kind):
        if cls.installed(kind):
            return kind
        module = cls._MODULES[kind]
        install = "requirements.txt" if module == "qdldl" else "requirements-cholmod.txt"
        warn_once(f"missing-{module}", f"the optional sparse solver {module!r} is not installed "
                  f"(pip install -r {install}); using scipy's SuperLU instead")
        return LinearSolver.SUPERLU

    def _numeric(self):
        from cvxopt import cholmod

        cholmod.numeric(self._matrix, self._factor)
        self.factorised = True

    def _cholmod_factor(self):
        """CHOLMOD's factor of the current matrix with the better of two fill-reducing orderings:
        CHOLMOD's own AMD and reverse Cuthill-McKee of the vertex graph (a band ordering, which
        measured up to 25 % faster on long bars). Better means fewer flops, sum_j |L_j|^2 over the
        columns of L, so the choice is deterministic; it is made once per pattern."""
        from cvxopt import cholmod, matrix, spmatrix

        p = self.pattern
        columns = np.repeat(np.arange(p.n_dofs), np.diff(p.upper_indptr))
        self._matrix = spmatrix(matrix(p.upper), matrix(p.upper_indices.astype(np.int64)), matrix(columns),
                                (p.n_dofs, p.n_dofs))
        vertices = reverse_cuthill_mckee(p.vertex_graph, symmetric_mode=True).astype(np.int64)
        band = matrix((3 * vertices[:, None] + np.arange(3)).ravel())

        def analyse(ordering):
            if ordering is None:
                return cholmod.symbolic(self._matrix, uplo="U")
            return cholmod.symbolic(self._matrix, uplo="U", p=ordering)

        def flops(ordering):
            trial = analyse(ordering)
            cholmod.numeric(self._matrix, trial)
            return float(np.sum(np.diff(np.asarray(cholmod.getfactor(trial).CCS[0]).ravel()) ** 2.0))

        # getfactor turns a factor simplicial (slow to refactorise), so the chosen one is analysed anew.
        self._factor = analyse(band if flops(band) < flops(None) else None)
        self._numeric()
        return self._factor

    def back_solve(self, rhs: np.ndarray) -> np.ndarray:
        """d (3F,) with H d = rhs for the last factorised H."""
        if self.kind is LinearSolver.CHOLMOD:
            from cvxopt import cholmod, matrix

            out = matrix(rhs)
            cholmod.solve(self._factor, out)
            return np.array(out).ravel()
        if self.kind is LinearSolver.CHOLESPY:
            out = np.zeros_like(rhs)
            self._factor.solve(np.ascontiguousarray(rhs), out)
            return out
        return self._factor.solve(rhs)

    def _upper(self):
        """The current upper triangle as a scipy CSC matrix."""
        p = self.pattern
        return sp.csc_matrix((p.upper, p.upper_indices, p.upper_indptr), shape=(p.n_dofs, p.n_dofs))

    def solve(self, rhs: np.ndarray, require_definite: bool = False) -> np.ndarray:
        """d (3F,) with H d = rhs for the pattern's current values H (and `pattern.upper`).
        Raises ArithmeticError or RuntimeError when the factorisation finds H not positive definite: CHOLMOD
        and cholespy always; QDLDL (an LDL^T of any quasi-definite H) only with require_definite, from the
        signs of D, which cost a third of a factorisation to read; SuperLU never."""
        p = self.pattern
        self.factorised = False
        if self.kind is LinearSolver.CHOLMOD:
            from cvxopt import matrix

            if self._factor is None:
                self._factor = self._cholmod_factor()
            else:
                self._matrix.V = matrix(p.upper)
                self._numeric()
            return self.back_solve(rhs)
        if self.kind is LinearSolver.QDLDL:
            import qdldl

            if self._factor is None:
                self._factor = qdldl.Solver(self._upper(), upper=True)
            else:
                self._factor.update(self._upper(), upper=True)
            if require_definite and not (self._factor.factors()[1] > 0).all():     # H = L D L^T > 0 iff D > 0
                raise ArithmeticError("the Hessian is not positive definite")
        elif self.kind is LinearSolver.CHOLESPY:
            from cholespy import CholeskySolverD, MatrixType

            try:
                self._factor = CholeskySolverD(p.n_dofs, p.indptr, p.indices, p.data, MatrixType.CSR)
            except ValueError as error:         # cholespy's "Matrix is not positive definite!"
                raise ArithmeticError(str(error)) from None
        else:
            self._factor = spla.splu(p.matrix().tocsc(), permc_spec="MMD_AT_PLUS_A")
        self.factorised = True
        return self.back_solve(rhs)


def spd_solver(H: sp.spmatrix):
    """A function b (n,) -> H^-1 b for a symmetric positive definite scipy matrix H (n, n), from one
    factorisation: CHOLMOD through cvxopt (analysed anew: for matrices whose pattern is not a
    `HessianPattern`, such as the two-level coarse operator), or SuperLU when cvxopt is missing or
    finds H not positive definite."""
    if DirectSolver._importable("cvxopt"):
        from cvxopt import cholmod, matrix, spmatrix

        upper = sp.triu(H, format="coo")
        A = spmatrix(matrix(np.asarray(upper.data, dtype=np.float64)), matrix(upper.row.astype(np.int64)),
                     matrix(upper.col.astype(np.int64)), H.shape)
        factor = cholmod.symbolic(A, uplo="U")
        try:
            cholmod.numeric(A, factor)
        except ArithmeticError:
            factor = None
        if factor is not None:
            def solve(b):
                out = matrix(np.ascontiguousarray(b, dtype=np.float64))
                cholmod.solve(factor, out)
                return np.array(out).ravel()
            return solve
    return spla.splu(H.tocsc(), permc_spec="MMD_AT_PLUS_A").solve


def superlu_solve(H: sp.spmatrix, rhs: np.ndarray) -> np.ndarray:
    """SuperLU with the MMD ordering of H^T + H: no positive-definiteness needed."""
    return spla.spsolve(H.tocsc(), rhs, permc_spec="MMD_AT_PLUS_A")


class GlobalNewton:
    """Projected Newton with Armijo backtracking for `StepProblem`s on one mesh and free mask.

    tets (M, 4) int; free (N,) bool: which vertices are unknowns. Builds the Hessian pattern and the
    solver's symbolic analysis once; `solve` can be called for any problem with these tets and free
    mask (other positions, masses, material, time step, ground, contact). With contact, `contact` is the
    `ContactPairs` of the last problem, and `analyses` counts the patterns with pairs analysed.
    exact_pairs: whether `newton_direction` tries the contact pairs' exact Hessians before their PSD parts
    (False only to measure what they buy: benchmarks/newton_contact.py).
    """

    def __init__(self, tets: np.ndarray, free: np.ndarray, linear_solver=LinearSolver.AUTO, exact_pairs: bool = True):
        ensure_taichi()
        self.pattern = HessianPattern(tets, free)
        self.linear_solver = as_linear_solver(linear_solver)
        self.exact_pairs = bool(exact_pairs)
        self.direct = DirectSolver(self.pattern, self.linear_solver)
        self.contact = None
        self._coupled = None        # (couplings (P, 4), pattern, DirectSolver) of the last Hessian with contact
        self.analyses = 0

    def check(self, problem) -> None:
        """Raise ConfigError unless `problem` has this solver's tets and free mask."""
        p = self.pattern
        if problem.tets.shape != p.tets.shape or not np.array_equal(problem.free, p.free) \
                or not np.array_equal(problem.tets, p.tets):
            raise ConfigError("this GlobalNewton was built for another mesh or free mask; "
                              "use solver.global_newton.global_newton(problem.tets, problem.free) for this problem")

    def contact_pairs(self, term) -> ContactPairs:
        """The Taichi twin of a problem's `ContactTerm`, kept while the problems have its Contact and rest
        positions (built again otherwise)."""
        if self.contact is None or not self.contact.serves(term):
            self.contact = ContactPairs(term)
            self._coupled = None
        return self.contact

    def coupled_system(self, contact: ContactPairs, x: np.ndarray):
        """(pattern, DirectSolver) of the Hessian at x (N, 3) with contact: the tets' pattern joined by the
        pairs closer than the radius. Kept while those pairs stay; when they change, a new pattern, which
        keeps the last symbolic analysis if its vertex graph is the same and is analysed anew otherwise."""
        _, couplings = contact.couplings(x)
        if self._coupled is not None and np.array_equal(self._coupled[0], couplings):
            return self._coupled[1], self._coupled[2]
        pattern = HessianPattern(self.pattern.tets, self.pattern.free, couplings)
        direct = None if self._coupled is None else self._coupled[2]
        if direct is not None and _same_graph(direct.pattern, pattern):
            direct.pattern = pattern
        else:
            direct = DirectSolver(pattern, self.linear_solver)
            self.analyses += 1
        self._coupled = (couplings, pattern, direct)
        return pattern, direct

    def _assemble(self, kernels: StepKernels, contact, pattern: HessianPattern, x: np.ndarray, project: bool,
                  full: bool, exact_pairs: bool = False):
        """The Hessian at x into `pattern` (`StepKernels.hessian`), elastic blocks projected or not, with the
        contact pairs' blocks, exact or their PSD parts."""
        if contact is not None:
            contact.write_blocks(x, pattern, full, exact_pairs)
        return kernels.hessian(x, project, full, pattern)

    def newton_direction(self, kernels: StepKernels, x: np.ndarray, g: np.ndarray, project: bool = True,
                         contact: ContactPairs = None) -> np.ndarray:
        """d (N, 3) solving H d = -g on the free vertices (0 elsewhere), H with the pairs' blocks of
        `contact` (a `ContactPairs` or None). The Hessians tried, the first that is positive definite and
        gives a descent direction taken:

        1. (project=False only) the exact Hessian: unprojected elastic blocks, exact pair blocks;
        2. (with contact) projected elastic blocks, exact pair blocks: the curvature of the distance where
           closest points slide (near-parallel edges), which the PSD blocks miss;
        3. projected elastic blocks, PSD pair blocks (n held fixed), positive definite by construction;

        then SuperLU, then a mass-scaled gradient step, with a warning. With exact pair blocks a descent
        direction of an indefinite Hessian may lead to a saddle of G, so those Hessians must pass a test of
        definiteness (`DirectSolver.solve`'s require_definite); SuperLU has none, so with it the pair blocks
        are always the PSD ones. The exact elastic Hessian alone is taken on descent, as it always was."""
        p, direct = (self.pattern, self.direct) if contact is None else self.coupled_system(contact, x)
        full = direct.kind in (LinearSolver.SUPERLU, LinearSolver.CHOLESPY)
        exact_pairs = self.exact_pairs and contact is not None and direct.kind is not LinearSolver.SUPERLU
        attempts = [(False, exact_pairs)] if not project else []
        if exact_pairs:
            attempts.append((True, True))
        attempts.append((True, False))
        rhs = -g[p.free].ravel()
        d = np.zeros_like(x)
        for project_elastic, exact in attempts:
            self._assemble(kernels, contact, p, x, project_elastic, full, exact)
            try:
                d[p.free] = direct.solve(rhs, require_definite=exact).reshape(-1, 3)
            except (ArithmeticError, RuntimeError):     # cholmod, qdldl: not positive definite
                continue
            if np.isfinite(d).all() and np.vdot(g, d) < 0:
                return d
        warnings.warn("the projected Hessian is not positive definite (no descent direction); "
                      "retrying with SuperLU", stacklevel=3)
        d[p.free] = superlu_solve(self._assemble(kernels, contact, p, x, True, True), rhs).reshape(-1, 3)
        if np.isfinite(d).all() and np.vdot(g, d) < 0:
            return d
        warnings.warn("SuperLU gave no descent direction either; taking a mass-scaled gradient step",
                      stacklevel=3)
        inverse_stiffness = np.divide(kernels.h ** 2, kernels.masses, out=np.zeros_like(kernels.masses),
                                      where=kernels.masses > 0)
        return -g * inverse_stiffness[:, None]

    def solve(self, problem, x0: np.ndarray, tolerance: float = REFERENCE_TOLERANCE, max_iterations: int = 50,
              keep_iterates: bool = False, time_budget: float = None,
              force_tolerance: float = None, warn_at_cap: bool = True) -> NewtonResult:
        """Minimise G from x0 (N, 3); the loop, convergence test and warnings of `newton_solve`
        (`damped_newton`: tolerance is its step_tolerance; force_tolerance, time_budget and warn_at_cap as
        there).

        Eigenvalue filtering (after Chen et al. 2024, "Trust-region eigenvalue filtering for projected
        Newton"): the projection that keeps far-away steps safe also slows Newton to linear convergence
        near x*, where the exact Hessian is positive definite. So the first iteration, and any after a
        step whose quadratic model mispredicted the decrease of G, use the projected Hessian; the
        others use the exact one (if it is positive definite), which converges quadratically.

        With contact (`problem.contact`, a `ContactTerm`): G + E_c by `contact_pairs`, the pairs found
        again at every iterate, steps capped by the bounds (start where no surface crosses: x_n, or
        `Simulation.begin_step`'s guess clamped to the bounds; never y, which may lie across a body)."""
        self.check(problem)
        kernels = StepKernels(self.pattern, problem)
        contact = None if problem.contact is None else self.contact_pairs(problem.contact)
        energy_gradient = kernels.energy_gradient if contact is None else _with_contact(kernels, contact)
        return damped_newton(problem, energy_gradient,
                             lambda x, g, it, trusted: self.newton_direction(kernels, x, g, not trusted, contact),
                             x0, tolerance, max_iterations, keep_iterates, time_budget,
                             lambda x, g: self.chord_direction(x, g, contact), force_tolerance,
                             step_cap=None if contact is None else contact.step_cap, warn_at_cap=warn_at_cap)

    def chord_direction(self, x: np.ndarray, g: np.ndarray, contact: ContactPairs = None):
        """d (N, 3) solving H_last d = -g with the last factorised Hessian (a back substitution, no new
        Hessian), or None when there is none, or (with `contact`) when the pairs at x (N, 3) are not those
        of that Hessian."""
        p, direct = self.pattern, self.direct
        if contact is not None:
            if self._coupled is None or not np.array_equal(contact.couplings(x)[1], self._coupled[0]):
                return None
            _, p, direct = self._coupled
        if not direct.factorised:
            return None
        d = np.zeros_like(g)
        d[p.free] = direct.back_solve(-g[p.free].ravel()).reshape(-1, 3)
        return d


def _with_contact(kernels: StepKernels, contact: ContactPairs):
    """(x, g) -> G(x) + E_c(x), with g (N, 3) = their gradient: the energy_gradient of `damped_newton`."""
    def energy_gradient(x, g):
        G = kernels.energy_gradient(x, g)           # writes g
        return G + contact.energy_gradient(x, g)    # adds dE_c/dx
    return energy_gradient


def _same_graph(a: HessianPattern, b: HessianPattern) -> bool:
    """Whether two patterns couple the same free vertices (and so have the same scalar pattern)."""
    return (np.array_equal(a.vertex_graph.indptr, b.vertex_graph.indptr)
            and np.array_equal(a.vertex_graph.indices, b.vertex_graph.indices))


_CACHE = RuntimeCache(OrderedDict)
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
    8 meshes of the running Taichi, whose arrays `ti.init` frees) so that every step and every
    Simulation on the same mesh reuses it."""
    key = connectivity_key(tets, free) + (as_linear_solver(linear_solver),)
    ensure_taichi()
    cache = _CACHE.get()
    if key in cache:
        cache.move_to_end(key)
        return cache[key]
    solver = GlobalNewton(tets, free, linear_solver)
    cache[key] = solver
    while len(cache) > _CACHE_SIZE:
        cache.popitem(last=False)
    return solver


def fast_newton_solve(problem, x0: np.ndarray, tolerance: float = REFERENCE_TOLERANCE, max_iterations: int = 50,
                      keep_iterates: bool = False, linear_solver=LinearSolver.AUTO,
                      force_tolerance: float = None, warn_at_cap: bool = True) -> NewtonResult:
    """Drop-in for `solver.newton_solve`: the same minimisation by the cached `GlobalNewton`
    (force_tolerance in N: also stop once max_i |dG/dx_i| is below it; warn_at_cap as in `damped_newton`),
    contact included."""
    return global_newton(problem.tets, problem.free, linear_solver).solve(
        problem, x0, tolerance, max_iterations, keep_iterates, force_tolerance=force_tolerance,
        warn_at_cap=warn_at_cap)
