"""Two-level VBD: a coarse correction carries the long waves, VBD sweeps smooth the short ones.

VBD is nonlinear block Gauss-Seidel: one sweep moves information about one ring of elements, so a
stiff step, whose deformation spans N_c = h sqrt(E/rho)/dx rings, needs many sweeps (lecture notes,
chapters 5 and 7). A two-level cycle adds a global channel without changing the sweeps:

    pre-smooth:  k1 VBD iterations of the Simulation (the method the lecture teaches)
    coarse:      at the iterate x, g = dG/dx; solve H_c u = -P^T g on a coarse cage, d = P u;
                 a line search on G along d (never accepts an increase of G); x <- x + alpha d
    post-smooth: k2 VBD iterations

P (N_f, N_c) interpolates the coarse cage's nodes to the fine vertices (`solver.prolongation`). The
coarse Hessian H_c is either Galerkin, P^T H P with the fine projected Hessian (exact, but it costs a
fine assembly), or rediscretised: the cage's own projected elastic Hessian at the restricted
positions, weighted by how much of each cage tet the body fills, plus the exact Galerkin inertia
P^T (M/h^2) P and a penalty that holds the cage at the fine constrained vertices.

    sim = solver.Simulation(mesh, material, fixed=..., iterations=1)
    ml = TwoLevelVBD(sim, cage_cells=(10, 2, 2))      # from solver.multilevel import TwoLevelVBD
    ml.step()                       # one time step of `cycles` cycles
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from enum import Enum
from typing import Optional

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from ..errors import ConfigError
from ..mesh.topology import rest_geometry
from ..physics.ground import ground_hessian_diag_np
from ..physics.inertia import inertia_hessian_diag_np
from .direct import spd_solver
from .hessian import HessianPattern, StepKernels
from .oracle import StepProblem
from .prolongation import Prolongation, cage_cells_for, cage_fill, cage_prolongation


# With `CoarseRefresh.KEEP`, a cycle that reduces max_i |f_i| by less than this factor refactorises H_c.
# Measured over 30 steps of the swinging 30,720-tet bar at 1e6 Pa with a fresh H_c every step: factor
# 0.28 per cycle (median), 0.52 (90th percentile); with 0.5, KEEP refactorised in 24 of the 30 steps
# and took 10 to 13 cycles per step like STEP; with 0.7, 21 steps, but up to 24 cycles in stale ones.
SLOW_CYCLE = 0.5


class CoarseOperator(Enum):
    """How the coarse Hessian H_c is built."""

    GALERKIN = "galerkin"              # P^T H P from the fine projected Hessian (numpy assembly)
    REDISCRETIZED = "rediscretized"    # the cage's own elastic Hessian + Galerkin inertia


class CoarseRefresh(Enum):
    """When H_c is assembled and factorised again."""

    CYCLE = "cycle"    # before every coarse correction
    STEP = "step"      # once per time step (and again whenever the line search fails)
    KEEP = "keep"      # kept across time steps until a cycle is slow (see SLOW_CYCLE) or a line search fails


@dataclass(frozen=True)
class CycleRecord:
    """After cycle `cycle` of the current step: fine VBD sweeps so far, G in J, max_i |f_i| in N,
    the accepted coarse step length alpha (0 when rejected) and the wall time of the step so far (s)."""

    cycle: int
    sweeps: int
    energy: float
    max_residual: float
    alpha: float
    seconds: float


class TwoLevelVBD:
    """Two-level cycles around a `Simulation`'s VBD sweeps.

    sim: the Simulation (damping 0, no ground friction, no Chebyshev: the coarse step minimises G; its
    `iterations` are not used, the cycle runs its own sweeps); cage_cells: (3,)
    cells of the coarse cage (default: `coarsening` times the fine edge length per axis);
    operator: a `CoarseOperator`; refresh: a `CoarseRefresh`; pre_sweeps, post_sweeps: VBD iterations
    before and after each coarse correction; cycles: cycles per `step()`; tolerance: stop a step early
    once max_i |f_i| falls below this fraction of its value at the initial guess (None: the Simulation's
    own tolerance test, `Simulation.stop_below`, checked after every cycle).
    """

    def __init__(self, sim, cage_cells=None, coarsening: int = 2,
                 operator: CoarseOperator = CoarseOperator.REDISCRETIZED,
                 refresh: CoarseRefresh = CoarseRefresh.STEP, pre_sweeps: int = 2, post_sweeps: int = 2,
                 cycles: int = 10, tolerance: Optional[float] = None):
        if not isinstance(operator, CoarseOperator):
            raise ConfigError(f"operator must be a solver.multilevel.CoarseOperator, got {operator!r}")
        if not isinstance(refresh, CoarseRefresh):
            raise ConfigError(f"refresh must be a solver.multilevel.CoarseRefresh, got {refresh!r}")
        for name, value in (("pre_sweeps", pre_sweeps), ("post_sweeps", post_sweeps)):
            if int(value) != value or value < 0:
                raise ConfigError(f"{name} must be an integer >= 0, got {value!r}")
        if int(cycles) != cycles or cycles < 1:
            raise ConfigError(f"cycles must be an integer >= 1, got {cycles!r}")
        if tolerance is not None and not (np.isfinite(tolerance) and tolerance > 0):
            raise ConfigError(f"tolerance must be a positive fraction or None, got {tolerance!r}")
        self.sim = sim
        self.operator = operator
        self.refresh = refresh
        self.pre_sweeps, self.post_sweeps, self.cycles = int(pre_sweeps), int(post_sweeps), int(cycles)
        self.tolerance = tolerance
        mesh = sim.mesh
        free = ~(sim.fixed_mask | sim.kinematic_mask)
        cells = cage_cells_for(mesh, coarsening) if cage_cells is None else cage_cells
        self.prolongation: Prolongation = cage_prolongation(mesh, cells, free)
        self._free = free
        self._setup_rediscretized(mesh)
        self.history: list[CycleRecord] = []
        self._problem: Optional[StepProblem] = None
        self._solve = None

    # -----------------------------------------------------------------------------------------
    # One-off set-up of the rediscretised operator (vectorised numpy)
    # -----------------------------------------------------------------------------------------
    def _setup_rediscretized(self, mesh):
        pro = self.prolongation
        cage = pro.cage
        fill = cage_fill(mesh, pro)
        used = fill > 0
        T = cage.tets[used]
        rest = rest_geometry(cage.vertices, T)
        self._cage_tets = T
        self._cage_grad_rows = rest.grad_rows
        self._cage_volumes = rest.volumes * fill[used]
        kept = np.zeros(cage.n_vertices, dtype=bool)
        kept[pro.kept] = True
        self._cage_pattern = HessianPattern(T, kept)
        W = pro.weights
        WtW = (W.T @ W).tocsc()
        eps = 1e-8 * float(WtW.diagonal().mean())
        self._restrict_lu = spla.splu((WtW + eps * sp.identity(cage.n_vertices, format="csc")).tocsc())
        self._restrict_eps = eps
        # fine constrained vertices pull the cage with the stiffness of the fine elements there
        fine_volumes = rest_geometry(mesh.vertices, mesh.tets).volumes
        vertex_volume = np.bincount(mesh.tets.ravel(), weights=np.repeat(fine_volumes / 4, 4),
                                    minlength=mesh.n_vertices)
        constrained = np.flatnonzero(~self._free)
        Wc = W[constrained][:, pro.kept]
        self._pin_weights, self._pin_lengths = Wc, vertex_volume[constrained] ** (1 / 3)

    def restrict_positions(self, x: np.ndarray) -> np.ndarray:
        """(N_cage, 3) cage node positions whose interpolation best fits x (N_f, 3) (least squares,
        regularised towards the rest cage): exact for affine deformations."""
        W = self.prolongation.weights
        rhs = W.T @ x + self._restrict_eps * self.prolongation.cage.vertices
        return self._restrict_lu.solve(rhs)

    # -----------------------------------------------------------------------------------------
    # The coarse Hessian
    # -----------------------------------------------------------------------------------------
    def coarse_hessian(self, problem: StepProblem, x: np.ndarray) -> sp.csr_matrix:
        """(3 N_c, 3 N_c) H_c at the fine positions x (N_f, 3), xyz-interleaved per coarse node."""
        P3 = self.prolongation.P3
        if self.operator is CoarseOperator.GALERKIN:
            return (P3.T @ problem.hessian(x) @ P3).tocsr()
        diag = inertia_hessian_diag_np(problem.masses, problem.h, problem.free)
        if problem.ground is not None:
            diag += ground_hessian_diag_np(problem.ground, x, problem.free)
        inertia = P3.T @ sp.diags(diag) @ P3
        n_cage = self.prolongation.cage.n_vertices
        cage_problem = StepProblem(tets=self._cage_tets, grad_rows=self._cage_grad_rows,
                                   volumes=self._cage_volumes, masses=np.zeros(n_cage),
                                   y=np.zeros((n_cage, 3)), free=np.ones(n_cage, bool),
                                   constrained_positions=np.zeros((n_cage, 3)), h=problem.h,
                                   mu=problem.mu, lam=problem.lam)
        # the cage's projected elastic Hessian over its kept nodes, by the Taichi kernels of solver.hessian
        elastic = StepKernels(self._cage_pattern, cage_problem).hessian(
            np.ascontiguousarray(self.restrict_positions(x), dtype=np.float64))
        Wc = self._pin_weights
        stiffness = (problem.lam + 2 * problem.mu) * self._pin_lengths      # N/m, about E dx
        penalty = sp.kron(Wc.T @ sp.diags(stiffness) @ Wc, sp.identity(3))
        return (inertia + elastic + penalty).tocsr()

    def _factorize(self, x):
        self._solve = spd_solver(self.coarse_hessian(self._problem, x))

    # -----------------------------------------------------------------------------------------
    # The cycle
    # -----------------------------------------------------------------------------------------
    def coarse_correction(self) -> float:
        """One coarse step at the Simulation's current iterate; returns the accepted alpha (0: none).

        d = P u with H_c u = -P^T g; the step length starts at the secant estimate of the minimiser
        of G along d (one extra gradient), then halves until G decreases (Armijo). G never increases
        (below G's round-off, a directional-derivative test stands in for the Armijo test).
        Gradient and G come from the Simulation's own kernels (`residual()` = -g, `energy()`).
        """
        sim = self.sim
        x = sim.positions
        g = -sim.residual()
        if self._solve is None or self.refresh is CoarseRefresh.CYCLE:
            self._factorize(x)
        alpha = self._line_search(x, g)
        if alpha == 0.0 and self.refresh is not CoarseRefresh.CYCLE:
            self._factorize(x)
            alpha = self._line_search(x, g)
        return alpha

    def _line_search(self, x, g):
        sim, P3 = self.sim, self.prolongation.P3
        d = (P3 @ self._solve(-(P3.T @ g.ravel()))).reshape(-1, 3)
        slope = float(g.ravel() @ d.ravel())
        if not np.isfinite(slope) or slope >= 0:
            return 0.0
        G0 = sim.energy()
        sim.set_positions(x + d)
        curvature = float((-sim.residual() - g).ravel() @ d.ravel())
        alpha = -slope / curvature if curvature > 0 else 1.0
        for _ in range(30):
            sim.set_positions(x + alpha * d)
            if -alpha * slope < 1e-11 * abs(G0):
                # G's round-off hides the decrease: accept only a step that stops short of the
                # minimum along d (phi'(alpha) <= |phi'(0)| / 2), which lowers G on a convex line
                if float(-sim.residual().ravel() @ d.ravel()) <= -0.5 * slope:
                    return alpha
            else:
                G_new = sim.energy()
                if np.isfinite(G_new) and G_new <= G0 + 1e-4 * alpha * slope:
                    return alpha
            alpha *= 0.5
        sim.set_positions(x)
        return 0.0

    def begin_step(self) -> None:
        """Start a time step: the Simulation's begin_step (initial guess); the coarse Hessian is
        assembled at the first coarse correction (`CoarseRefresh.STEP`, `CYCLE`) or kept from the
        previous step (`KEEP`)."""
        if self.sim.chebyshev_rho is not None:
            raise ConfigError("two-level VBD needs chebyshev_rho=None on the Simulation: Chebyshev's "
                              "extrapolation from earlier iterates would undo the coarse step")
        self._problem = self.sim.step_problem()
        self.sim.begin_step()
        if self.refresh is not CoarseRefresh.KEEP:
            self._solve = None
        self._sweeps = 0
        self._cycle = 0
        self._start = time.perf_counter()
        r = self.sim.max_residual()
        self._stop_below = self.sim.stop_below if self.tolerance is None else self.tolerance * r
        self.history = [CycleRecord(0, 0, self.sim.energy(), r, 0.0, 0.0)]

    def run_cycles(self, n: int) -> int:
        """Run up to n cycles (pre-smooth, coarse correction, post-smooth); returns how many ran."""
        if self._problem is None:
            raise ConfigError("run_cycles() needs begin_step() first")
        sim = self.sim
        ran = 0
        for _ in range(int(n)):
            self._sweeps += sim.run_iterations(self.pre_sweeps) if self.pre_sweeps else 0
            alpha = self.coarse_correction()
            self._sweeps += sim.run_iterations(self.post_sweeps) if self.post_sweeps else 0
            self._cycle += 1
            ran += 1
            r = sim.max_residual()
            self.history.append(CycleRecord(self._cycle, self._sweeps, sim.energy(), r, alpha,
                                            time.perf_counter() - self._start))
            if self.refresh is CoarseRefresh.KEEP and r > SLOW_CYCLE * self.history[-2].max_residual:
                self._solve = None          # the kept H_c has gone stale: refactorise at the next cycle
            if self._stop_below is not None and r <= self._stop_below:
                break
        return ran

    def end_step(self) -> None:
        """Finish the time step (velocities from the positions, advance the clock)."""
        self.sim.end_step()
        self._problem = None

    def step(self, n: int = 1) -> None:
        """Advance n time steps of `cycles` cycles each."""
        for _ in range(int(n)):
            self.begin_step()
            self.run_cycles(self.cycles)
            self.end_step()
