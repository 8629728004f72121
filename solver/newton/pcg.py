"""Inexact Newton with preconditioned conjugate gradients, preconditioned by VBD's own blocks.

VBD is nonlinear block Gauss-Seidel: each vertex solves its 3x3 system H_i dx_i = f_i with its
neighbours frozen, so information crosses about one ring of tets per sweep. Here the same blocks
precondition conjugate gradients on the global Newton system H d = -g, which adds the global channel
VBD lacks (lecture notes, chapter 7):

- `Preconditioner.BLOCK_JACOBI`: z_i = H_i^-1 r_i with H_i the 3x3 diagonal block of vertex i
  (VBD's per-vertex Hessian, projected; VBD [Chen et al. 2024] Eq. 6 without the line search).
- `Preconditioner.COLOR_SWEEP`: one symmetric block Gauss-Seidel sweep, forward through the colours
  then backward (VBD's colour sweep on the linearised step, from zero). Symmetric positive definite,
  so CG stays valid. It reads the off-diagonal blocks H_ij from the assembled CSR Hessian of
  `solver.hessian` (about 60x fewer operations than recomputing them from the tets).

Hessian-vector products are matrix-free: per tet vol B^T A (B v) with the projected 9x9 stress
Hessians A of `solver.hessian`, computed once per Newton iteration. Each Newton iteration stops CG
at the forcing term ||r|| <= eta ||g||, eta = min(forcing, sqrt(||g|| / ||g_0||)) (an Eisenstat-Walker
style choice, tighter near the solution; forcing = 0.01 needed fewer Newton iterations and less time
to 1e-4 than 0.1 or 0.5 on the stiff bar). A CG that stalls (no convergence in
`max_cg_iterations`) warns and finishes the step with the direct solver of `solver.global_newton`.
"""
import warnings
from dataclasses import dataclass, field
from enum import Enum

import numpy as np

from .._ti import ti
from ..backend import RuntimeCache, ensure_taichi
from ..mesh.coloring import color_vertices
from ..errors import ConfigError, enum_value
from .damped_newton import REFERENCE_TOLERANCE, NewtonResult, damped_newton
from .direct import LinearSolver, global_newton
from ..physics.ground import ground_hessian_zz
from ..physics.inertia import inertia_block
from ..physics.material import deformation_gradient, vertex_gradients
from .hessian import StepKernels


class Preconditioner(Enum):
    """VBD's blocks as a CG preconditioner (see the module docstring)."""

    BLOCK_JACOBI = "block_jacobi"
    COLOR_SWEEP = "color_sweep"


@dataclass
class PCGResult(NewtonResult):
    """A `NewtonResult` plus cg_iterations: the CG iterations of each Newton iteration, and
    direct_iterations: how many Newton iterations fell back to the direct solver."""

    cg_iterations: list = field(default_factory=list)
    direct_iterations: int = 0


@ti.func
def _stress_times(A9: ti.template(), t, dF):
    """dP = A dF for tet t's 9x9 A (index 3a + b)."""
    dP = ti.Matrix.zero(ti.f64, 3, 3)
    for r in ti.static(range(9)):
        value = 0.0
        for c in ti.static(range(9)):
            value += A9[t, r, c] * dF[c // 3, c % 3]
        dP[r // 3, r % 3] = value
    return dP


@ti.func
def _row(a: ti.template(), i):
    return ti.Vector([a[i, 0], a[i, 1], a[i, 2]], dt=ti.f64)


@ti.func
def _matrix_row(M, k: ti.template()):
    return ti.Vector([M[k, 0], M[k, 1], M[k, 2]])


@ti.func
def _diagonal_term(masses: ti.template(), x: ti.template(), i, h, has_ground, ground_height, ground_stiffness):
    """The vertex's inertia block m_i/h^2 I plus its ground block (penalty stiffness on z)."""
    D = inertia_block(masses[i] / (h * h))
    if has_ground != 0:
        D[2, 2] += ground_hessian_zz(x[i, 2], ground_height, ground_stiffness)
    return D


@ti.kernel
def hessian_vector_kernel(A9: ti.types.ndarray(), tets: ti.types.ndarray(), grad_rows: ti.types.ndarray(),
                          volumes: ti.types.ndarray(), masses: ti.types.ndarray(), free: ti.types.ndarray(),
                          x: ti.types.ndarray(), h: ti.f64, has_ground: ti.i32, ground_height: ti.f64,
                          ground_stiffness: ti.f64, v: ti.types.ndarray(), out: ti.types.ndarray()):
    """out (N, 3) = H v on the free vertices (0 elsewhere), v (N, 3) read at free vertices only."""
    for i in range(out.shape[0]):
        w = ti.Vector.zero(ti.f64, 3)
        if free[i] != 0:
            w = _diagonal_term(masses, x, i, h, has_ground, ground_height, ground_stiffness) @ _row(v, i)
        for c in ti.static(range(3)):
            out[i, c] = w[c]
    for t in range(tets.shape[0]):
        v_t = ti.Matrix.zero(ti.f64, 4, 3)                 # row k: v at local vertex k, 0 if constrained
        for k in ti.static(range(4)):
            if free[tets[t, k]] != 0:
                for c in ti.static(range(3)):
                    v_t[k, c] = v[tets[t, k], c]
        Dm_inv = ti.Matrix.zero(ti.f64, 3, 3)              # rows 1-3 of the gradient rows
        for k, c in ti.static(ti.ndrange(3, 3)):
            Dm_inv[k, c] = grad_rows[t, k + 1, c]
        dF = deformation_gradient(_matrix_row(v_t, 0), _matrix_row(v_t, 1), _matrix_row(v_t, 2),
                                  _matrix_row(v_t, 3), Dm_inv)
        rows = volumes[t] * vertex_gradients(_stress_times(A9, t, dF), Dm_inv)
        for k in ti.static(range(4)):
            vk = tets[t, k]
            if free[vk] != 0:
                for c in ti.static(range(3)):
                    out[vk, c] += rows[k, c]


@ti.kernel
def inverse_diagonal_blocks_kernel(A9: ti.types.ndarray(), tets: ti.types.ndarray(), grad_rows: ti.types.ndarray(),
                                   volumes: ti.types.ndarray(), masses: ti.types.ndarray(),
                                   free: ti.types.ndarray(), x: ti.types.ndarray(), h: ti.f64, has_ground: ti.i32,
                                   ground_height: ti.f64, ground_stiffness: ti.f64, D_inv: ti.types.ndarray()):
    """D_inv (N, 3, 3): the inverse of every free vertex's 3x3 diagonal block H_i (identity elsewhere)."""
    for i, a, b in ti.ndrange(masses.shape[0], 3, 3):
        D_inv[i, a, b] = 0.0
    for t, k in ti.ndrange(tets.shape[0], 4):
        vk = tets[t, k]
        if free[vk] != 0:
            for c, d in ti.ndrange(3, 3):
                value = 0.0
                for b, e in ti.ndrange(3, 3):
                    value += grad_rows[t, k, b] * A9[t, 3 * c + b, 3 * d + e] * grad_rows[t, k, e]
                D_inv[vk, c, d] += volumes[t] * value
    for i in range(masses.shape[0]):
        D = ti.Matrix.identity(ti.f64, 3)
        if free[i] != 0:
            D = _diagonal_term(masses, x, i, h, has_ground, ground_height, ground_stiffness)
            for a, b in ti.static(ti.ndrange(3, 3)):
                D[a, b] += D_inv[i, a, b]
        D = D.inverse()
        for a, b in ti.static(ti.ndrange(3, 3)):
            D_inv[i, a, b] = D[a, b]


@ti.kernel
def block_jacobi_kernel(D_inv: ti.types.ndarray(), r: ti.types.ndarray(), z: ti.types.ndarray()):
    """z_i = D_inv_i r_i for every vertex."""
    for i in range(r.shape[0]):
        for a in ti.static(range(3)):
            z[i, a] = D_inv[i, a, 0] * r[i, 0] + D_inv[i, a, 1] * r[i, 1] + D_inv[i, a, 2] * r[i, 2]


@ti.kernel
def color_sweep_kernel(order: ti.types.ndarray(), count: ti.i32, backward: ti.i32, free_index: ti.types.ndarray(),
                       free_vertices: ti.types.ndarray(), indptr: ti.types.ndarray(), indices: ti.types.ndarray(),
                       data: ti.types.ndarray(), D_inv: ti.types.ndarray(), r: ti.types.ndarray(),
                       z: ti.types.ndarray()):
    """Block Gauss-Seidel on H z = r over the vertices order[:count] (sorted by colour), forward or
    backward: z_i = H_i^-1 (r_i - sum_{j != i} H_ij z_j), with H the assembled free-dof CSR matrix.
    Vertices of one colour share no tet, so this equals the colour-parallel sweep; it runs serially in
    one launch (cheaper than a launch per colour on a CPU with few cores)."""
    ti.loop_config(serialize=True)
    for m in range(count):
        n = count - 1 - m if backward != 0 else m
        i = order[n]
        f = free_index[i]
        s = _row(r, i)
        for c in ti.static(range(3)):
            row = 3 * f + c
            for e in range(indptr[row], indptr[row + 1]):
                j = indices[e] // 3
                if j != f:
                    s[c] -= data[e] * z[free_vertices[j], indices[e] % 3]
        for a in ti.static(range(3)):
            z[i, a] = D_inv[i, a, 0] * s[0] + D_inv[i, a, 1] * s[1] + D_inv[i, a, 2] * s[2]


class NewtonPCG:
    """Inexact projected Newton for `StepProblem`s on one mesh and free mask, with PCG inner solves.

    tets (M, 4) int; free (N,) bool; preconditioner: a `Preconditioner` or its name; forcing: the
    largest CG tolerance eta (relative to ||g||); max_cg_iterations: CG iterations per Newton
    iteration before the direct solver (`linear_solver`) takes over for the rest of the solve.
    """

    def __init__(self, tets: np.ndarray, free: np.ndarray, preconditioner=Preconditioner.COLOR_SWEEP,
                 forcing: float = 0.01, max_cg_iterations: int = 500, linear_solver=LinearSolver.AUTO):
        ensure_taichi()
        self.preconditioner = enum_value(Preconditioner, preconditioner, "preconditioner")
        if not 0.0 < forcing < 1.0:
            raise ConfigError(f"forcing must be in (0, 1), got {forcing}")
        if max_cg_iterations < 1:
            raise ConfigError(f"max_cg_iterations must be >= 1, got {max_cg_iterations}")
        self.forcing, self.max_cg_iterations, self.linear_solver = forcing, int(max_cg_iterations), linear_solver
        self.direct = global_newton(tets, free, linear_solver)
        self.pattern = self.direct.pattern          # shared, so that the direct fallback sees the same arrays
        tets = self.pattern.tets
        n = len(free)
        colors = color_vertices(tets, n).colors
        free_vertices = np.flatnonzero(free)
        self.free_vertices = free_vertices.astype(np.int32)
        by_color = free_vertices[np.argsort(colors[free_vertices], kind="stable")]
        self.color_order = by_color.astype(np.int32)
        counts = np.bincount(colors[free_vertices])
        self.color_offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        self.D_inv = np.zeros((n, 3, 3))
        self._r = np.zeros((n, 3))
        self._z = np.zeros((n, 3))
        self._Hp = np.zeros((n, 3))

    def hessian_vector(self, kernels: StepKernels, x: np.ndarray, v: np.ndarray, out: np.ndarray) -> np.ndarray:
        """out (N, 3) = H v with the stress Hessians last computed by `kernels.stress_hessians`."""
        p = self.pattern
        hessian_vector_kernel(p.A9, p.tets, kernels.grad_rows, kernels.volumes, kernels.masses, p.free_int, x,
                              kernels.h, *kernels.ground, v, out)
        return out

    def precondition(self, kernels: StepKernels, r: np.ndarray, z: np.ndarray) -> np.ndarray:
        """z (N, 3) = M^-1 r for the chosen preconditioner."""
        if self.preconditioner is Preconditioner.BLOCK_JACOBI:
            block_jacobi_kernel(self.D_inv, r, z)
            return z
        p = self.pattern
        z.fill(0.0)
        n = len(self.color_order)
        last = int(self.color_offsets[-2])        # the backward sweep skips the last colour: unchanged
        for count, backward in ((n, 0), (last, 1)):
            color_sweep_kernel(self.color_order, count, backward, p.free_index, self.free_vertices, p.indptr,
                               p.indices, p.data, self.D_inv, r, z)
        return z

    def cg(self, kernels: StepKernels, x: np.ndarray, b: np.ndarray, tolerance: float):
        """Solve H d = b (N, 3) by PCG to ||r|| <= tolerance ||b||; returns (d, iterations, relative residual)."""
        d = np.zeros_like(b)
        r = self._r
        r[:] = b
        z = self.precondition(kernels, r, self._z)
        p = z.copy()
        rz = float(np.vdot(r, z))
        b_norm = float(np.linalg.norm(b))
        relative = 1.0
        for k in range(1, self.max_cg_iterations + 1):
            Hp = self.hessian_vector(kernels, x, p, self._Hp)
            pHp = float(np.vdot(p, Hp))
            if not pHp > 0.0:
                warnings.warn("PCG met a direction of non-positive curvature (the projected Hessian is not "
                              "positive definite); using the CG iterate so far", stacklevel=4)
                return d, k, relative
            a = rz / pHp
            d += a * p
            r -= a * Hp
            relative = float(np.linalg.norm(r)) / b_norm if b_norm > 0 else 0.0
            if relative <= tolerance:
                return d, k, relative
            z = self.precondition(kernels, r, z)
            rz_new = float(np.vdot(r, z))
            p *= rz_new / rz
            p += z
            rz = rz_new
        return d, self.max_cg_iterations, relative

    def solve(self, problem, x0: np.ndarray, tolerance: float = REFERENCE_TOLERANCE, max_iterations: int = 50,
              keep_iterates: bool = False, time_budget: float = None, force_tolerance: float = None,
              warn_at_cap: bool = True) -> PCGResult:
        """Minimise G from x0 (N, 3); the loop and convergence test of `newton_solve` (`damped_newton`:
        tolerance is its step_tolerance; force_tolerance, time_budget and warn_at_cap as there)."""
        p = self.pattern
        if problem.tets.shape != p.tets.shape or not np.array_equal(problem.free, p.free) \
                or not np.array_equal(problem.tets, p.tets):
            raise ConfigError("this NewtonPCG was built for another mesh or free mask; "
                              "use solver.pcg.newton_pcg(problem.tets, problem.free) for this problem")
        if problem.contact is not None:
            raise ConfigError("Newton-PCG has no contact term; solve a problem with contact by "
                              "solver.fast_newton_solve (or solver.newton_solve)")
        kernels = StepKernels(p, problem)
        state = dict(g0=None, direct=False, direct_iterations=0)
        cg_counts = []

        def direction(x, g, iteration, trusted):
            g_norm = float(np.linalg.norm(g))
            if state["g0"] is None:
                state["g0"] = g_norm
            if state["direct"]:
                cg_counts.append(0)
                state["direct_iterations"] += 1
                return self.direct.newton_direction(kernels, x, g)
            eta = min(self.forcing, np.sqrt(g_norm / state["g0"])) if state["g0"] > 0 else self.forcing
            kernels.stress_hessians(x)
            if self.preconditioner is Preconditioner.COLOR_SWEEP:
                kernels.hessian(x)                      # the sweep reads the assembled off-diagonal blocks
            inverse_diagonal_blocks_kernel(p.A9, p.tets, kernels.grad_rows, kernels.volumes, kernels.masses,
                                           p.free_int, x, kernels.h, *kernels.ground, self.D_inv)
            d, count, relative = self.cg(kernels, x, -g, eta)
            cg_counts.append(count)
            if relative <= eta and np.vdot(g, d) < 0:
                return d
            warnings.warn(f"PCG stalled at {relative:.0e} after {count} iterations; finishing with the direct "
                          "solver", stacklevel=4)
            state["direct"] = True
            state["direct_iterations"] += 1
            return self.direct.newton_direction(kernels, x, g)

        base = damped_newton(problem, kernels.energy_gradient, direction, x0, tolerance, max_iterations,
                             keep_iterates, time_budget, force_tolerance=force_tolerance, warn_at_cap=warn_at_cap)
        result = PCGResult(base.x, base.iterations, base.converged, base.history, base.iterates)
        result.cg_iterations = cg_counts
        result.direct_iterations = state["direct_iterations"]
        return result


_CACHE = RuntimeCache()


def newton_pcg(tets: np.ndarray, free: np.ndarray, preconditioner=Preconditioner.COLOR_SWEEP,
               forcing: float = 0.01, max_cg_iterations: int = 500) -> NewtonPCG:
    """The `NewtonPCG` of this connectivity, free mask and settings, built on first use and cached
    (for the running Taichi, whose arrays `ti.init` frees)."""
    from .direct import connectivity_key

    key = connectivity_key(tets, free) + (str(getattr(preconditioner, "value", preconditioner)), float(forcing),
                                          int(max_cg_iterations))
    ensure_taichi()
    cache = _CACHE.get()
    if key not in cache:
        if len(cache) >= 8:
            cache.pop(next(iter(cache)))
        cache[key] = NewtonPCG(tets, free, preconditioner, forcing, max_cg_iterations)
    return cache[key]
