"""G's energy, gradient and positive semi-definite projected Hessian, assembled by Taichi kernels.

    G(x) = sum_free m_i/(2h^2) |x_i - y_i|^2 + sum_tets vol Psi(F) + sum_free k_c/2 max(0, z0 - z_i)^2

The same G as `solver.newton.StepProblem` (the numpy oracle), evaluated in parallel kernels. The
Hessian of each tet is vol B^T A B, where B = dF/dx (9 x 12) and A is the 9x9 stress Hessian dP/dF
of the stable Neo-Hookean energy (solver/material.py) projected to positive semi-definite: its
negative eigenvalues clamped to 0, as the oracle does with a dense eigendecomposition.

Closed-form eigensystem of A (derived as in Smith et al. 2019, "Analytic eigensystems for isotropic
distortion energies"). With F = U diag(s) V^T (U, V rotations, s_2 possibly negative),
J = s0 s1 s2 and cof(F) = U diag(s1 s2, s0 s2, s0 s1) V^T,

    A = mu I + lam vec(cof F) vec(cof F)^T + lam (J - alpha) d2J/dF2.

For every pair (i, j) with third index k, the "twist" and "flip" matrices
U (e_i e_j^T -+ e_j e_i^T) V^T / sqrt 2 are eigenvectors with eigenvalues mu +- lam (J - alpha) s_k;
the remaining three eigenvectors U diag(e) V^T come from the 3x3 "scaling" block
mu I + lam c c^T + lam (J - alpha) K, with c = (s1 s2, s0 s2, s0 s1) and K_ij = s_k off the diagonal.
The projected A is A plus (-lambda) q q^T for each negative eigenpair (lambda, q).

The sparsity pattern over the free vertices (`HessianPattern`) is computed once per mesh and free
mask; every Newton iteration writes into the same CSR arrays.
"""

import math

import numpy as np
import scipy.sparse as sp

from ._ti import ti
from .material import cofactor, dpsi_dF, psi

_SQRT_HALF = 1.0 / math.sqrt(2.0)
_PAIRS = ((1, 2, 0), (0, 2, 1), (0, 1, 2))    # (i, j, k): the pair and the third index


@ti.func
def _vec3(a: ti.template(), i):
    """Row i of an (n, 3) ndarray as a vector."""
    return ti.Vector([a[i, 0], a[i, 1], a[i, 2]], dt=ti.f64)


@ti.func
def _grad_row(grad_rows: ti.template(), t, k):
    return ti.Vector([grad_rows[t, k, 0], grad_rows[t, k, 1], grad_rows[t, k, 2]], dt=ti.f64)


@ti.func
def _deformation_gradient(x: ti.template(), tets: ti.template(), grad_rows: ti.template(), t):
    """F = sum_k x_k m_k^T of tet t."""
    F = ti.Matrix.zero(ti.f64, 3, 3)
    for k in ti.static(range(4)):
        F += _vec3(x, tets[t, k]).outer_product(_grad_row(grad_rows, t, k))
    return F


@ti.func
def _sym_eig3(A):
    """Eigenvalues (3-vector) and eigenvectors (columns) of a symmetric 3x3 matrix by cyclic Jacobi
    rotations, until the off-diagonal part is at round-off (at most 10 sweeps)."""
    V = ti.Matrix.identity(ti.f64, 3)
    tiny = 1e-30 * (A[0, 0] ** 2 + A[1, 1] ** 2 + A[2, 2] ** 2)
    for sweep in range(30):
        if A[0, 1] ** 2 + A[0, 2] ** 2 + A[1, 2] ** 2 <= tiny:
            break
        pair = sweep % 3
        p = 0 if pair < 2 else 1
        q = 1 if pair == 0 else 2
        apq = A[p, q]
        if ti.abs(apq) > 1e-300:
            theta = (A[q, q] - A[p, p]) / (2.0 * apq)
            t = 1.0 / (ti.abs(theta) + ti.sqrt(theta * theta + 1.0))
            if theta < 0.0:
                t = -t
            c = 1.0 / ti.sqrt(t * t + 1.0)
            s = t * c
            for r in range(3):         # A G and V G with the rotation G in the (p, q) plane
                arp, arq = A[r, p], A[r, q]
                A[r, p], A[r, q] = c * arp - s * arq, s * arp + c * arq
                vrp, vrq = V[r, p], V[r, q]
                V[r, p], V[r, q] = c * vrp - s * vrq, s * vrp + c * vrq
            for r in range(3):         # G^T (A G)
                apr, aqr = A[p, r], A[q, r]
                A[p, r], A[q, r] = c * apr - s * aqr, s * apr + c * aqr
    return ti.Vector([A[0, 0], A[1, 1], A[2, 2]]), V


@ti.func
def _unit_orthogonal(u):
    """A unit vector orthogonal to the unit vector u."""
    axis = ti.Vector([1.0, 0.0, 0.0])
    if ti.abs(u[0]) > 0.5:
        axis = ti.Vector([0.0, 1.0, 0.0])
    w = u.cross(axis)
    return w / w.norm()


@ti.func
def _svd3(F):
    """F = U diag(s) V^T with U, V rotations, s0 >= s1 >= |s2| (s2 < 0 for an inverted F), from the
    Jacobi eigendecomposition of F^T F: V and s0, s1 from it, U's columns F v_i / s_i and u0 x u1.
    (Taichi's own ti.svd reconstructs F only to ~1e-10 in float64 and is slow to compile.)"""
    evals, V = _sym_eig3(F.transpose() @ F)
    for _ in range(2):                           # sort the eigenpairs by decreasing eigenvalue
        for a in range(2):
            if evals[a] < evals[a + 1]:
                evals[a], evals[a + 1] = evals[a + 1], evals[a]
                for r in range(3):
                    V[r, a], V[r, a + 1] = V[r, a + 1], V[r, a]
    if V.determinant() < 0.0:
        for r in range(3):
            V[r, 2] = -V[r, 2]
    v0 = ti.Vector([V[0, 0], V[1, 0], V[2, 0]])
    v1 = ti.Vector([V[0, 1], V[1, 1], V[2, 1]])
    v2 = ti.Vector([V[0, 2], V[1, 2], V[2, 2]])
    u0 = F @ v0
    if u0.norm() > 1e-150:
        u0 /= u0.norm()
    else:
        u0 = ti.Vector([1.0, 0.0, 0.0])
    u1 = F @ v1
    u1 -= u1.dot(u0) * u0
    if u1.norm() > 1e-12 * ti.sqrt(ti.max(evals[0], 0.0)) and u1.norm() > 1e-150:
        u1 /= u1.norm()
    else:
        u1 = _unit_orthogonal(u0)
    u2 = u0.cross(u1)
    U = ti.Matrix.cols([u0, u1, u2])
    s = ti.Vector([u0.dot(F @ v0), u1.dot(F @ v1), u2.dot(F @ v2)])
    return U, s, V


@ti.func
def _levi_civita(i, j, k):
    return (i - j) * (j - k) * (k - i) // 2


@ti.func
def _eigensystem(F, mu, lam, t, eigenvalues: ti.template(), eigenvectors: ti.template()):
    """The 9 eigenpairs of tet t's dP/dF: eigenvalues[t, q] and eigenvectors[t, q] (3x3, unit
    Frobenius norm), q < 6 twist/flip of the pairs, q >= 6 scaling."""
    alpha = 1.0 + mu / lam
    scale = lam * (F.determinant() - alpha)
    U, s, V = _svd3(F)
    for q in range(6):                 # twist (even q) and flip (odd q) of the pair (i, j)
        k = q // 2
        i = 1 if k == 0 else 0
        j = 1 if k == 2 else 2
        sign = 1.0 - 2.0 * (q % 2)
        eigenvalues[t, q] = mu + sign * scale * s[k]
        for a, b in ti.ndrange(3, 3):
            eigenvectors[t, q, a, b] = _SQRT_HALF * (U[a, i] * V[b, j] - sign * U[a, j] * V[b, i])
    cof_s = ti.Vector([s[1] * s[2], s[0] * s[2], s[0] * s[1]])
    B = mu * ti.Matrix.identity(ti.f64, 3) + lam * cof_s.outer_product(cof_s)
    for i, j, k in ti.static(_PAIRS):
        B[i, j] += scale * s[k]
        B[j, i] += scale * s[k]
    evals, evecs = _sym_eig3(B)
    for n in range(3):
        eigenvalues[t, 6 + n] = evals[n]
        for a, b in ti.ndrange(3, 3):
            value = 0.0
            for i in range(3):
                value += evecs[i, n] * U[a, i] * V[b, i]
            eigenvectors[t, 6 + n, a, b] = value


@ti.kernel
def eigensystem_kernel(x: ti.types.ndarray(), tets: ti.types.ndarray(), grad_rows: ti.types.ndarray(),
                       mu: ti.f64, lam: ti.f64, eigenvalues: ti.types.ndarray(), eigenvectors: ti.types.ndarray()):
    """eigenvalues (M, 9), eigenvectors (M, 9, 3, 3): the closed-form eigensystem of every tet's dP/dF."""
    for t in range(tets.shape[0]):
        _eigensystem(_deformation_gradient(x, tets, grad_rows, t), mu, lam, t, eigenvalues, eigenvectors)


@ti.kernel
def stress_hessian_kernel(x: ti.types.ndarray(), tets: ti.types.ndarray(), grad_rows: ti.types.ndarray(),
                          mu: ti.f64, lam: ti.f64, eigenvalues: ti.types.ndarray(),
                          eigenvectors: ti.types.ndarray(), A9: ti.types.ndarray()):
    """A9 (M, 9, 9): every tet's dP/dF at x (N, 3), projected to positive semi-definite by adding
    -lambda q q^T for each negative eigenpair from `eigensystem_kernel`; index 3a + b for F_ab."""
    for t in range(tets.shape[0]):
        F = _deformation_gradient(x, tets, grad_rows, t)
        alpha = 1.0 + mu / lam
        scale = lam * (F.determinant() - alpha)
        C = cofactor(F)
        negative = ti.Vector.zero(ti.i32, 9)
        n_negative = 0
        for q in range(9):
            if eigenvalues[t, q] < 0.0:
                negative[n_negative] = q
                n_negative += 1
        # mu I + lam vec(C) vec(C)^T + lam (J - alpha) eps_ace eps_bdf F_ef
        for r, c in ti.ndrange(9, 9):
            a, b, cc, d = r // 3, r % 3, c // 3, c % 3
            value = lam * C[a, b] * C[cc, d]
            if r == c:
                value += mu
            if a != cc and b != d:
                e, f = 3 - a - cc, 3 - b - d
                value += scale * _levi_civita(a, cc, e) * _levi_civita(b, d, f) * F[e, f]
            for n in range(n_negative):
                q = negative[n]
                value -= eigenvalues[t, q] * eigenvectors[t, q, a, b] * eigenvectors[t, q, cc, d]
            A9[t, r, c] = value


@ti.func
def _ground_depth(z, free_flag, has_ground, ground_height):
    depth = 0.0
    if has_ground != 0 and free_flag != 0:
        depth = ti.max(ground_height - z, 0.0)
    return depth


@ti.kernel
def energy_kernel(x: ti.types.ndarray(), y: ti.types.ndarray(), tets: ti.types.ndarray(),
                  grad_rows: ti.types.ndarray(), volumes: ti.types.ndarray(), masses: ti.types.ndarray(),
                  free: ti.types.ndarray(), h: ti.f64, mu: ti.f64, lam: ti.f64, has_ground: ti.i32,
                  ground_height: ti.f64, ground_stiffness: ti.f64) -> ti.f64:
    """G(x) in J. Arrays as in `StepProblem`; free is (N,) int32."""
    total = 0.0
    for t in range(tets.shape[0]):
        total += volumes[t] * psi(_deformation_gradient(x, tets, grad_rows, t), mu, lam)
    for i in range(x.shape[0]):
        if free[i] != 0:
            d = _vec3(x, i) - _vec3(y, i)
            depth = _ground_depth(x[i, 2], free[i], has_ground, ground_height)
            total += 0.5 * masses[i] / (h * h) * d.dot(d) + 0.5 * ground_stiffness * depth * depth
    return total


@ti.kernel
def gradient_kernel(x: ti.types.ndarray(), y: ti.types.ndarray(), tets: ti.types.ndarray(),
                    grad_rows: ti.types.ndarray(), volumes: ti.types.ndarray(), masses: ti.types.ndarray(),
                    free: ti.types.ndarray(), h: ti.f64, mu: ti.f64, lam: ti.f64, has_ground: ti.i32,
                    ground_height: ti.f64, ground_stiffness: ti.f64, g: ti.types.ndarray()):
    """g (N, 3) = dG/dx, zero at constrained vertices."""
    for i in range(x.shape[0]):
        for c in ti.static(range(3)):
            g[i, c] = 0.0
    for t in range(tets.shape[0]):
        F = _deformation_gradient(x, tets, grad_rows, t)
        P = dpsi_dF(F, mu, lam)
        for k in ti.static(range(4)):
            v = tets[t, k]
            if free[v] != 0:
                f = volumes[t] * (P @ _grad_row(grad_rows, t, k))
                for c in ti.static(range(3)):
                    g[v, c] += f[c]
    for i in range(x.shape[0]):
        if free[i] != 0:
            for c in ti.static(range(3)):
                g[i, c] += masses[i] / (h * h) * (x[i, c] - y[i, c])
            g[i, 2] -= ground_stiffness * _ground_depth(x[i, 2], free[i], has_ground, ground_height)


@ti.kernel
def assemble_kernel(A9: ti.types.ndarray(), tets: ti.types.ndarray(), grad_rows: ti.types.ndarray(),
                    volumes: ti.types.ndarray(), block_start: ti.types.ndarray(), row_length: ti.types.ndarray(),
                    x: ti.types.ndarray(), masses: ti.types.ndarray(), free_index: ti.types.ndarray(),
                    diag_start: ti.types.ndarray(), h: ti.f64, has_ground: ti.i32, ground_height: ti.f64,
                    ground_stiffness: ti.f64, data: ti.types.ndarray()):
    """CSR values `data` of the free-dof Hessian: tet blocks, then masses/h^2 and contact on the
    diagonal. block_start (M, 4, 4): CSR index of entry (3 f_k, 3 f_l), -1 when either vertex is
    constrained; row_length (M, 4): entries per scalar row of vertex k; diag_start (F, 3): CSR index
    of each diagonal entry."""
    for n in range(data.shape[0]):
        data[n] = 0.0
    for t in range(tets.shape[0]):
        A = ti.Matrix.zero(ti.f64, 9, 9)
        for r, c in ti.ndrange(9, 9):
            A[r, c] = volumes[t] * A9[t, r, c]
        m = ti.Matrix.zero(ti.f64, 4, 3)
        for k, b in ti.static(ti.ndrange(4, 3)):
            m[k, b] = grad_rows[t, k, b]
        for l in range(4):
            W = ti.Matrix.zero(ti.f64, 9, 3)        # W[(c, b), d] = sum_e A[(c, b), (d, e)] m_le
            for r, d in ti.ndrange(9, 3):
                W[r, d] = A[r, 3 * d] * m[l, 0] + A[r, 3 * d + 1] * m[l, 1] + A[r, 3 * d + 2] * m[l, 2]
            for k in range(l + 1):                 # block (k, l) of vol B^T A B, and its transpose (l, k)
                start = block_start[t, k, l]
                if start >= 0:
                    mirror = block_start[t, l, k]
                    for c, d in ti.ndrange(3, 3):
                        value = W[3 * c, d] * m[k, 0] + W[3 * c + 1, d] * m[k, 1] + W[3 * c + 2, d] * m[k, 2]
                        data[start + c * row_length[t, k] + d] += value
                        if k != l:
                            data[mirror + d * row_length[t, l] + c] += value
    for i in range(masses.shape[0]):
        f = free_index[i]
        if f >= 0:
            for c in ti.static(range(3)):
                data[diag_start[f, c]] += masses[i] / (h * h)
            if has_ground != 0 and x[i, 2] < ground_height:
                data[diag_start[f, 2]] += ground_stiffness


class HessianPattern:
    """The CSR sparsity pattern of G's Hessian over the free degrees of freedom, built once.

    tets (M, 4) int; free (N,) bool. Free vertex i has unknowns 3 free_index[i] + (0, 1, 2);
    free_index is -1 at constrained vertices. indptr (3F + 1,), indices (nnz,) int32: the scalar
    CSR pattern (columns sorted) of the 3x3 blocks of every pair of free vertices sharing a tet.
    """

    def __init__(self, tets: np.ndarray, free: np.ndarray):
        tets = np.ascontiguousarray(tets, dtype=np.int32)
        free = np.asarray(free, dtype=bool)
        self.tets, self.free = tets, free
        self.free_int = free.astype(np.int32)
        self.free_index = np.full(len(free), -1, dtype=np.int32)
        self.free_index[free] = np.arange(int(free.sum()), dtype=np.int32)
        self.n_free = int(free.sum())
        self.n_dofs = 3 * self.n_free
        fi = self.free_index[tets]                                        # (M, 4)
        rows = np.repeat(fi, 4, axis=1).ravel()
        cols = np.tile(fi, (1, 4)).ravel()
        keep = (rows >= 0) & (cols >= 0)
        diag = np.arange(self.n_free)
        adjacency = sp.csr_matrix((np.ones(keep.sum() + self.n_free),
                                   (np.concatenate([rows[keep], diag]), np.concatenate([cols[keep], diag]))),
                                  shape=(self.n_free, self.n_free))
        adjacency.sum_duplicates()
        adjacency.sort_indices()
        vptr = adjacency.indptr.astype(np.int64)
        vcols = adjacency.indices.astype(np.int64)
        n_neighbours = np.diff(vptr)
        keys = np.repeat(np.arange(self.n_free, dtype=np.int64), n_neighbours) * self.n_free + vcols

        def start_of(f, w):
            """CSR index of scalar entry (3f, 3w) for free vertices f, w (arrays)."""
            rank = np.searchsorted(keys, f.astype(np.int64) * self.n_free + w) - vptr[f]
            return 9 * vptr[f] + 3 * rank

        block_start = np.full((len(tets), 4, 4), -1, dtype=np.int64)
        fk = np.broadcast_to(fi[:, :, None], block_start.shape)
        fl = np.broadcast_to(fi[:, None, :], block_start.shape)
        both = (fk >= 0) & (fl >= 0)
        block_start[both] = start_of(fk[both], fl[both])
        self.block_start = block_start.astype(np.int32)
        self.row_length = np.where(fi >= 0, 3 * n_neighbours[np.maximum(fi, 0)], 0).astype(np.int32)
        diag_start = start_of(diag, diag)
        self.diag_start = (diag_start[:, None] + (3 * n_neighbours[:, None] + 1) * np.arange(3)).astype(np.int32)
        # Scalar pattern: entry (3f + c, 3w + d) sits at 9 vptr[f] + 3 nb_f c + 3 rank + d.
        self.nnz = int(9 * vptr[-1])
        if self.nnz >= 2 ** 31:
            raise MemoryError("Hessian pattern too large for 32-bit CSR indices")
        entry_f = np.repeat(np.arange(self.n_free), n_neighbours)
        entry_rank = np.arange(len(vcols)) - vptr[entry_f]
        c = np.arange(3)[None, :, None]
        d = np.arange(3)[None, None, :]
        where = (9 * vptr[entry_f])[:, None, None] + 3 * n_neighbours[entry_f][:, None, None] * c \
            + 3 * entry_rank[:, None, None] + d
        indices = np.empty(self.nnz, dtype=np.int32)
        indices[where.ravel()] = np.broadcast_to(3 * vcols[:, None, None] + d, where.shape).ravel()
        self.indices = indices
        self.indptr = np.concatenate([[0], np.cumsum(np.repeat(3 * n_neighbours, 3))]).astype(np.int32)
        self.data = np.zeros(self.nnz)
        self.A9 = np.zeros((len(tets), 9, 9))
        self.eigenvalues = np.zeros((len(tets), 9))
        self.eigenvectors = np.zeros((len(tets), 9, 3, 3))

    def matrix(self) -> sp.csr_matrix:
        """The current values as a (3F, 3F) scipy CSR matrix (shares `data`)."""
        return sp.csr_matrix((self.data, self.indices, self.indptr), shape=(self.n_dofs, self.n_dofs))


def ground_arguments(ground):
    """(has_ground, height in m, stiffness in N/m) for the kernels."""
    if ground is None:
        return 0, 0.0, 0.0
    return 1, float(ground.height), float(ground.stiffness)


class StepKernels:
    """G, dG/dx and the projected Hessian of one `StepProblem` on a `HessianPattern`, by the kernels
    above. Arrays are converted once in the constructor; after the first call (which compiles the
    kernels once per process) no call compiles or allocates Taichi memory."""

    def __init__(self, pattern: HessianPattern, problem):
        self.pattern = pattern
        self.problem = problem
        self.tets = pattern.tets
        self.grad_rows = np.ascontiguousarray(problem.grad_rows, dtype=np.float64)
        self.volumes = np.ascontiguousarray(problem.volumes, dtype=np.float64)
        self.masses = np.ascontiguousarray(problem.masses, dtype=np.float64)
        self.y = np.ascontiguousarray(problem.y, dtype=np.float64)
        self.h, self.mu, self.lam = float(problem.h), float(problem.mu), float(problem.lam)
        self.ground = ground_arguments(problem.ground)

    def energy(self, x: np.ndarray) -> float:
        """G(x) in J for x (N, 3) float64 C-contiguous."""
        return float(energy_kernel(x, self.y, self.tets, self.grad_rows, self.volumes, self.masses,
                                   self.pattern.free_int, self.h, self.mu, self.lam, *self.ground))

    def gradient(self, x: np.ndarray, out: np.ndarray = None) -> np.ndarray:
        """(N, 3) dG/dx, zero at constrained vertices."""
        out = np.empty_like(x) if out is None else out
        gradient_kernel(x, self.y, self.tets, self.grad_rows, self.volumes, self.masses, self.pattern.free_int,
                        self.h, self.mu, self.lam, *self.ground, out)
        return out

    def stress_hessians(self, x: np.ndarray) -> np.ndarray:
        """Fill and return pattern.A9 (M, 9, 9), the projected dP/dF of every tet at x."""
        p = self.pattern
        eigensystem_kernel(x, self.tets, self.grad_rows, self.mu, self.lam, p.eigenvalues, p.eigenvectors)
        stress_hessian_kernel(x, self.tets, self.grad_rows, self.mu, self.lam, p.eigenvalues, p.eigenvectors, p.A9)
        return self.pattern.A9

    def hessian(self, x: np.ndarray) -> sp.csr_matrix:
        """(3F, 3F) projected Hessian over the free unknowns at x, in the pattern's CSR arrays."""
        p = self.pattern
        self.stress_hessians(x)
        assemble_kernel(p.A9, self.tets, self.grad_rows, self.volumes, p.block_start, p.row_length, x,
                        self.masses, p.free_index, p.diag_start, self.h, *self.ground, p.data)
        return p.matrix()
