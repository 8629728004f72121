"""A global Newton solver for the same incremental potential G: the ground truth of every error.

    G(x) = sum_free m_i/(2h^2) |x_i - y_i|^2 + sum_tets vol Psi(F) + sum_free k_c/2 max(0, z0 - z_i)^2

Each iteration assembles the full sparse Hessian (every tet's 12x12 block, with the 9x9 stress
Hessian projected to be positive semi-definite), solves one large sparse linear system, and
backtracks along the direction until G decreases enough (Armijo; the loop of `damped_newton`, shared
with the fast Newton). This is the "black box" the lecture contrasts with VBD (lecture notes, chapter 2).
G, its gradient and Hessian are assembled here in pure numpy/scipy, independent of the Taichi kernels,
so agreement between the two is evidence for both.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from ..physics.ground import ground_energy_np, ground_gradient_np, ground_hessian_diag_np
from ..physics.material import d2psi_dF2_np, dpsi_dF_np, psi_np
from .damped_newton import REFERENCE_TOLERANCE, NewtonResult, damped_newton


@dataclass(frozen=True)
class StepProblem:
    """One implicit Euler step as a minimisation.

    tets (M, 4) int; grad_rows (M, 4, 3): m_k, so that F = sum_k x_k m_k^T; volumes (M,) m^3;
    masses (N,) kg; y (N, 3) inertial target; free (N,) bool, the unknowns;
    constrained_positions (N, 3): where the other (fixed, kinematic) vertices are during the step;
    h in s; mu, lam in Pa (Neo-Hookean); ground: a `solver.Ground` or None; contact: a `ContactTerm`
    (contact between bodies, `contact_term.py`) or None.
    """

    tets: np.ndarray
    grad_rows: np.ndarray
    volumes: np.ndarray
    masses: np.ndarray
    y: np.ndarray
    free: np.ndarray
    constrained_positions: np.ndarray
    h: float
    mu: float
    lam: float
    ground: object = None
    contact: object = None     # a `newton.contact_term.ContactTerm` (contact between bodies) or None

    def y_with_constraints(self) -> np.ndarray:
        """(N, 3): y at free vertices, the prescribed positions elsewhere (a natural start)."""
        return np.where(self.free[:, None], self.y, self.constrained_positions)

    def deformation_gradients(self, x: np.ndarray) -> np.ndarray:
        """(M, 3, 3) F of every tet at positions x (N, 3)."""
        return np.einsum("tka,tkb->tab", x[self.tets], self.grad_rows)

    def energy(self, x: np.ndarray) -> float:
        """G(x) in J."""
        d = (x - self.y)[self.free]
        inertia = 0.5 / self.h ** 2 * np.sum(self.masses[self.free] * np.sum(d * d, axis=1))
        elastic = np.sum(self.volumes * psi_np(self.deformation_gradients(x), self.mu, self.lam))
        contact = 0.0 if self.ground is None else ground_energy_np(self.ground, x, self.free)
        bodies = 0.0 if self.contact is None else self.contact.energy(x)
        return float(inertia + elastic + contact + bodies)

    def gradient(self, x: np.ndarray) -> np.ndarray:
        """(N, 3) dG/dx, zero at constrained vertices."""
        P = dpsi_dF_np(self.deformation_gradients(x), self.mu, self.lam)
        per_vertex = self.volumes[:, None, None] * np.einsum("tab,tkb->tka", P, self.grad_rows)
        g = np.zeros_like(x)
        np.add.at(g, self.tets.ravel(), per_vertex.reshape(-1, 3))
        g += self.masses[:, None] / self.h ** 2 * (x - self.y)
        if self.ground is not None:
            g += ground_gradient_np(self.ground, x, self.free)
        if self.contact is not None:
            g += self.contact.gradient(x)
        g[~self.free] = 0.0
        return g

    def hessian(self, x: np.ndarray, project: bool = True) -> sp.csr_matrix:
        """(3N, 3N) sparse d2G/dx2; with `project`, every tet's 9x9 stress Hessian dP/dF is
        projected to positive semi-definite (negative eigenvalues clamped to 0) first."""
        A = d2psi_dF2_np(self.deformation_gradients(x), self.mu, self.lam).reshape(-1, 9, 9)
        if project:
            lam_, Q = np.linalg.eigh(0.5 * (A + A.transpose(0, 2, 1)))
            A = np.einsum("tij,tj,tkj->tik", Q, np.maximum(lam_, 0.0), Q)
        # dF/dx as a (M, 9, 12) matrix: dF_ab / dx_kc = delta_ac m_kb, then blocks = vol B^T A B.
        B = np.zeros((len(A), 3, 3, 4, 3))
        for a in range(3):
            B[:, a, :, :, a] = self.grad_rows.transpose(0, 2, 1)
        B = B.reshape(-1, 9, 12)
        blocks = self.volumes[:, None, None] * (B.transpose(0, 2, 1) @ A @ B)
        dof = (3 * self.tets[:, :, None] + np.arange(3)).reshape(-1, 12)      # (M, 12)
        rows = np.broadcast_to(dof[:, :, None], blocks.shape).ravel()
        cols = np.broadcast_to(dof[:, None, :], blocks.shape).ravel()
        n = 3 * len(x)
        diag = np.repeat(self.masses / self.h ** 2, 3)
        if self.ground is not None:
            diag += ground_hessian_diag_np(self.ground, x, self.free)
        H = sp.coo_matrix((blocks.ravel(), (rows, cols)), shape=(n, n)).tocsr()
        H = H + sp.diags(diag)
        return H if self.contact is None else H + self.contact.hessian(x)


def newton_solve(problem: StepProblem, x0: np.ndarray, tolerance: float = REFERENCE_TOLERANCE, max_iterations: int = 50,
                 keep_iterates: bool = False) -> NewtonResult:
    """Minimise G from x0 (N, 3) with projected Newton and backtracking line search (`damped_newton`).

    The direction solves the full projected Hessian system assembled here in numpy with SuperLU.
    Converged when the Newton step is below `tolerance` times the body's size, or G's gradient is at
    round-off level.
    """
    free_dofs = np.flatnonzero(np.repeat(problem.free, 3))

    def energy_gradient(x, out):
        out[:] = problem.gradient(x)
        return problem.energy(x)

    def direction(x, g, iteration, trusted):
        H = problem.hessian(x)[free_dofs][:, free_dofs]
        d = np.zeros(x.size)
        d[free_dofs] = spla.spsolve(H.tocsc(), -g.ravel()[free_dofs], permc_spec="MMD_AT_PLUS_A")
        return d.reshape(-1, 3)

    step_cap = None if problem.contact is None else problem.contact.step_cap
    return damped_newton(problem, energy_gradient, direction, x0, tolerance, max_iterations, keep_iterates,
                         name="Newton reference", step_cap=step_cap)
