"""G's energy, gradient and positive semi-definite projected Hessian, assembled by Taichi kernels.

    G(x) = sum_free m_i/(2h^2) |x_i - y_i|^2 + sum_tets vol Psi(F) + sum_free k_c/2 max(0, z0 - z_i)^2

The same G as `solver.newton.StepProblem` (the numpy oracle), evaluated in parallel kernels. The
Hessian of each tet is vol B^T A B, where B = dF/dx (9 x 12) and A is the 9x9 stress Hessian dP/dF
of the stable Neo-Hookean energy (solver/physics/material.py) projected to positive semi-definite: its
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

Assembly without the 9x9 A: block (k, l) of vol B^T A B is vol sum_bd A[(a, b), (c, d)] m_kb m_ld, which
for the three terms of A and the rank-one corrections of the projection reduces to 3-vectors per
vertex (`_tet_blocks`), so an unprojected block costs a few dozen flops. The sparsity pattern over
the free vertices (`HessianPattern`) is computed once per mesh and free mask with a slot per (tet,
vertex pair): each tet writes its blocks to their slots, and each 3x3 block of the global matrix
sums its slots, read contiguously, without atomics (`hessian_kernel`). The Cholesky solvers read only
the upper triangle (`pattern.upper`, half the work); the full CSR arrays are filled on request.
"""

import math

import numpy as np
import scipy.sparse as sp

from .._ti import ti
from ..mesh.topology import vertex_tet_adjacency
from ..physics.ground import ground_energy, ground_gradient_z, ground_hessian_zz
from ..physics.inertia import inertia_block, inertia_energy, inertia_gradient
from ..physics.material import (cofactor, d2psi_dF2_entry, deformation_gradient, dpsi_dF, psi, tet_hessian_block,
                                vertex_gradients)

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
def _Dm_inv(grad_rows: ti.template(), t):
    """Dm^-1 of tet t: rows 1-3 of its gradient rows."""
    return ti.Matrix.rows([_grad_row(grad_rows, t, 1), _grad_row(grad_rows, t, 2), _grad_row(grad_rows, t, 3)])


@ti.func
def _deformation_gradient(x: ti.template(), tets: ti.template(), grad_rows: ti.template(), t):
    """F of tet t at x (N, 3), by `physics.material.deformation_gradient`."""
    return deformation_gradient(_vec3(x, tets[t, 0]), _vec3(x, tets[t, 1]), _vec3(x, tets[t, 2]),
                                _vec3(x, tets[t, 3]), _Dm_inv(grad_rows, t))


@ti.func
def _jacobi_rotation(A, V):
    """(G^T A G, V G) for the rotation G in the (0, 1) plane that zeroes A[0, 1]."""
    G = ti.Matrix.identity(ti.f64, 3)
    if A[0, 1] != 0.0:
        theta = (A[1, 1] - A[0, 0]) / (2.0 * A[0, 1])
        t = 1.0 / (ti.abs(theta) + ti.sqrt(theta * theta + 1.0))
        if theta < 0.0:
            t = -t
        c = 1.0 / ti.sqrt(t * t + 1.0)
        G[0, 0], G[1, 1], G[0, 1], G[1, 0] = c, c, t * c, -t * c
    return G.transpose() @ A @ G, V @ G


@ti.func
def _sym_eig3(A):
    """Eigenvalues (3-vector) and eigenvectors (columns) of a symmetric 3x3 matrix by cyclic Jacobi
    sweeps, until the off-diagonal part is at round-off (at most 10 sweeps; about 4 are needed). Each
    sweep rotates in the (0, 1) plane and then renames the indices cyclically, three times: one rotation
    in the code, which keeps the kernels that inline this quick to compile."""
    V = ti.Matrix.identity(ti.f64, 3)
    tiny = 1e-30 * (A[0, 0] ** 2 + A[1, 1] ** 2 + A[2, 2] ** 2)
    for _ in range(10):
        if A[0, 1] ** 2 + A[0, 2] ** 2 + A[1, 2] ** 2 <= tiny:
            break
        for _r in range(3):
            A, V = _jacobi_rotation(A, V)
            A = ti.Matrix([[A[1, 1], A[1, 2], A[1, 0]], [A[2, 1], A[2, 2], A[2, 0]], [A[0, 1], A[0, 2], A[0, 0]]])
            V = ti.Matrix.cols([ti.Vector([V[0, 1], V[1, 1], V[2, 1]]), ti.Vector([V[0, 2], V[1, 2], V[2, 2]]),
                                ti.Vector([V[0, 0], V[1, 0], V[2, 0]])])
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
    for a in ti.static((0, 1, 0)):                # sort the eigenpairs by decreasing eigenvalue
        if evals[a] < evals[a + 1]:
            evals[a], evals[a + 1] = evals[a + 1], evals[a]
            for r in ti.static(range(3)):
                V[r, a], V[r, a + 1] = V[r, a + 1], V[r, a]
    if V.determinant() < 0.0:
        for r in ti.static(range(3)):
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
def _scaling_block(s, mu, lam, scale):
    """The 3x3 block mu I + lam c c^T + lam (J - alpha) K of dP/dF on the scalings U diag(e) V^T, with
    c = (s1 s2, s0 s2, s0 s1), K_ij = s_k off the diagonal, scale = lam (J - alpha)."""
    cof_s = ti.Vector([s[1] * s[2], s[0] * s[2], s[0] * s[1]])
    B = mu * ti.Matrix.identity(ti.f64, 3) + lam * cof_s.outer_product(cof_s)
    for i, j, k in ti.static(_PAIRS):
        B[i, j] += scale * s[k]
        B[j, i] += scale * s[k]
    return B


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
    evals, evecs = _sym_eig3(_scaling_block(s, mu, lam, scale))
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
        J = F.determinant()
        C = cofactor(F)
        negative = ti.Vector.zero(ti.i32, 9)
        n_negative = 0
        for q in range(9):
            if eigenvalues[t, q] < 0.0:
                negative[n_negative] = q
                n_negative += 1
        for r, c in ti.ndrange(9, 9):
            a, b, cc, d = r // 3, r % 3, c // 3, c % 3
            value = d2psi_dF2_entry(F, C, J, a, b, cc, d, mu, lam)
            for n in range(n_negative):
                q = negative[n]
                value -= eigenvalues[t, q] * eigenvectors[t, q, a, b] * eigenvectors[t, q, cc, d]
            A9[t, r, c] = value


@ti.kernel
def energy_gradient_kernel(x: ti.types.ndarray(), y: ti.types.ndarray(), tets: ti.types.ndarray(),
                           grad_rows: ti.types.ndarray(), volumes: ti.types.ndarray(), masses: ti.types.ndarray(),
                           free: ti.types.ndarray(), h: ti.f64, mu: ti.f64, lam: ti.f64, has_ground: ti.i32,
                           ground_height: ti.f64, ground_stiffness: ti.f64, incidence_start: ti.types.ndarray(),
                           incidence: ti.types.ndarray(), tet_forces: ti.types.ndarray(), g: ti.types.ndarray()) -> ti.f64:
    """G(x) in J, and g (N, 3) = dG/dx, zero at constrained vertices. Arrays as in `StepProblem`;
    free is (N,) int32. Each tet writes vol P m_k for its 4 vertices to tet_forces (M, 4, 3), and each
    vertex i sums its entries incidence[incidence_start[i]:incidence_start[i + 1]] (4 t + k): no atomics."""
    total = 0.0
    for t in range(tets.shape[0]):
        F = _deformation_gradient(x, tets, grad_rows, t)
        total += volumes[t] * psi(F, mu, lam)
        rows = volumes[t] * vertex_gradients(dpsi_dF(F, mu, lam), _Dm_inv(grad_rows, t))
        for k, c in ti.static(ti.ndrange(4, 3)):
            tet_forces[t, k, c] = rows[k, c]
    for i in range(x.shape[0]):
        gi = ti.Vector.zero(ti.f64, 3)
        if free[i] != 0:
            for n in range(incidence_start[i], incidence_start[i + 1]):
                code = incidence[n]
                for c in ti.static(range(3)):
                    gi[c] += tet_forces[code // 4, code % 4, c]
            m_h2 = masses[i] / (h * h)
            total += inertia_energy(m_h2, _vec3(x, i), _vec3(y, i))
            gi += inertia_gradient(m_h2, _vec3(x, i), _vec3(y, i))
            if has_ground != 0:
                total += ground_energy(x[i, 2], ground_height, ground_stiffness)
                gi[2] += ground_gradient_z(x[i, 2], ground_height, ground_stiffness)
        for c in ti.static(range(3)):
            g[i, c] = gi[c]
    return total


@ti.func
def _eigen_rows(q, U, A, evecs, k):
    """Q_q m_k (3-vector) for eigenpair q of dP/dF (q < 6: twist (even q) and flip (odd q) of the pair
    (i, j), Q = U (e_i e_j^T -+ e_j e_i^T) V^T / sqrt 2; q >= 6: scaling, Q = U diag(evecs[:, q - 6]) V^T),
    with a_k = V^T m_k in row k of A (4x3)."""
    r = ti.Vector.zero(ti.f64, 3)
    if q < 6:
        k3 = q // 2
        i = 1 if k3 == 0 else 0
        j = 1 if k3 == 2 else 2
        sign = 1.0 - 2.0 * (q % 2)
        for a in ti.static(range(3)):
            r[a] = _SQRT_HALF * (U[a, i] * A[k, j] - sign * U[a, j] * A[k, i])
    else:
        for a in ti.static(range(3)):
            r[a] = U[a, 0] * evecs[0, q - 6] * A[k, 0] + U[a, 1] * evecs[1, q - 6] * A[k, 1] \
                + U[a, 2] * evecs[2, q - 6] * A[k, 2]
    return r


@ti.func
def _tet_blocks(x: ti.template(), tets: ti.template(), grad_rows: ti.template(), volumes: ti.template(), mu, lam,
                project, full, t, slot_of: ti.template(), slots: ti.template()):
    """Tet t's projected Hessian vol B^T A B at x (N, 3), block by block, into its slots (see
    `hessian_kernel`), without assembling A. With m_k the gradient rows, block (k, l) is

        vol (mu (m_k . m_l) I + lam (C m_k)(C m_l)^T + lam (J - alpha) eps_ace (F (m_k x m_l))_e)
        - sum over negative eigenpairs (lambda, Q) of A of vol lambda (Q m_k)(Q m_l)^T,

    because B^T vec(M) = (M m_k)_k for any 3x3 M; Q m_k only needs a_k = V^T m_k (module docstring).
    project = 0 leaves the blocks unprojected (the exact Hessian) and skips the eigensystem. The scaling
    eigenpairs are computed only when the scaling block is not positive definite (Sylvester's criterion).
    Loops rather than unrolled code over the blocks and eigenpairs keep the kernel quick to compile."""
    F = _deformation_gradient(x, tets, grad_rows, t)
    vol = volumes[t]
    alpha = 1.0 + mu / lam
    J = F.determinant()
    scale = lam * (J - alpha)
    m = ti.Matrix.zero(ti.f64, 4, 3)
    for k, b in ti.static(ti.ndrange(4, 3)):
        m[k, b] = grad_rows[t, k, b]
    Cm = m @ cofactor(F).transpose()                      # row k: C m_k = dJ/dx_k
    weights = ti.Vector.zero(ti.f64, 9)                   # vol lambda_q for the negative eigenpairs, else 0
    R = ti.Matrix.zero(ti.f64, 36, 3)                     # row 4 q + k: Q_q m_k, for the negative eigenpairs q
    if project != 0:
        U, s, V = _svd3(F)
        A = m @ V                                         # row k: a_k = V^T m_k
        evals, evecs = ti.Vector([1.0, 1.0, 1.0]), ti.Matrix.identity(ti.f64, 3)
        B = _scaling_block(s, mu, lam, scale)
        if B[0, 0] <= 0.0 or B[0, 0] * B[1, 1] - B[0, 1] ** 2 <= 0.0 or B.determinant() <= 0.0:
            evals, evecs = _sym_eig3(B)
        for q in range(9):
            eigenvalue = evals[q - 6] if q >= 6 else mu + (1.0 - 2.0 * (q % 2)) * scale * s[q // 2]
            if eigenvalue < 0.0:
                weights[q] = vol * eigenvalue
                for k in range(4):
                    r = _eigen_rows(q, U, A, evecs, k)
                    for a in ti.static(range(3)):
                        R[4 * q + k, a] = r[a]
    for kl in range(16):                                   # the ordered vertex pair (k, l)
        n = slot_of[t, kl]
        if n <= -2 and full != 0:
            n = -2 - n
        if n >= 0:
            k, l = kl // 4, kl % 4
            block = tet_hessian_block(F, J, ti.Vector([Cm[k, 0], Cm[k, 1], Cm[k, 2]]),
                                      ti.Vector([Cm[l, 0], Cm[l, 1], Cm[l, 2]]),
                                      ti.Vector([m[k, 0], m[k, 1], m[k, 2]]), ti.Vector([m[l, 0], m[l, 1], m[l, 2]]),
                                      vol, mu, lam)
            for q in range(9):
                if weights[q] != 0.0:
                    rk = ti.Vector([R[4 * q + k, 0], R[4 * q + k, 1], R[4 * q + k, 2]])
                    rl = ti.Vector([R[4 * q + l, 0], R[4 * q + l, 1], R[4 * q + l, 2]])
                    block -= weights[q] * rk.outer_product(rl)
            for a, c in ti.static(ti.ndrange(3, 3)):
                slots[n, a, c] = block[a, c]


@ti.kernel
def hessian_kernel(x: ti.types.ndarray(), tets: ti.types.ndarray(), grad_rows: ti.types.ndarray(),
                   volumes: ti.types.ndarray(), masses: ti.types.ndarray(), h: ti.f64, mu: ti.f64, lam: ti.f64,
                   has_ground: ti.i32, ground_height: ti.f64, ground_stiffness: ti.f64, project: ti.i32,
                   full: ti.i32, slot_of: ti.types.ndarray(), slots: ti.types.ndarray(),
                   contribution_start: ti.types.ndarray(), block_entry: ti.types.ndarray(),
                   block_row_length: ti.types.ndarray(), block_vertex: ti.types.ndarray(),
                   lower_blocks: ti.types.ndarray(), data: ti.types.ndarray(), upper_entry: ti.types.ndarray(),
                   upper: ti.types.ndarray()):
    """The free-dof Hessian at x (N, 3): the tet blocks of `_tet_blocks`, then one 3x3 block of a
    vertex pair per thread and no atomics: the sum of its tet blocks, masses/h^2 and contact on the
    diagonal blocks. full = 1: every block into the CSR values `data`, then `upper` = data[upper_entry];
    full = 0: only the blocks on and below the diagonal (`lower_blocks`), straight into `upper`, the upper
    triangle in CSC order that the Cholesky solvers read (half the work; `data` is left as it was).
    Each tet writes its block of every ordered vertex pair (k, l) to slots[slot_of[t, 4 k + l]] (-1: a
    constrained vertex; -2 - slot: a block above the diagonal, only written when full),
    so that slots[contribution_start[b]:contribution_start[b + 1]]
    are the tet blocks of block b, read contiguously; block_entry (B,): index of the block's entry
    (0, 0) in `data`; block_row_length (B,):
    entries per scalar row; block_vertex (B,): the vertex of a diagonal block, -1 off the diagonal;
    lower_blocks (L, 3): block index, index of its entry (0, 0) in `upper`, length of its first row there."""
    for t in range(tets.shape[0]):
        _tet_blocks(x, tets, grad_rows, volumes, mu, lam, project, full, t, slot_of, slots)
    for j in range(block_entry.shape[0] if full != 0 else lower_blocks.shape[0]):
        b = j if full != 0 else lower_blocks[j, 0]
        H = ti.Matrix.zero(ti.f64, 3, 3)
        for n in range(contribution_start[b], contribution_start[b + 1]):
            for a, c in ti.static(ti.ndrange(3, 3)):
                H[a, c] += slots[n, a, c]
        i = block_vertex[b]
        if i >= 0:
            H += inertia_block(masses[i] / (h * h))
            if has_ground != 0:
                H[2, 2] += ground_hessian_zz(x[i, 2], ground_height, ground_stiffness)
        if full != 0:
            for a, c in ti.static(ti.ndrange(3, 3)):
                data[block_entry[b] + a * block_row_length[b] + c] = H[a, c]
        else:                       # row a of the block starts at entry + a L0 + a (a - 1) / 2 in `upper`
            for a, c in ti.static(ti.ndrange(3, 3)):
                if ti.static(c <= a) or i < 0:
                    upper[lower_blocks[j, 1] + a * lower_blocks[j, 2] + a * (a - 1) // 2 + c] = H[a, c]
    for n in range(upper_entry.shape[0] if full != 0 else 0):
        upper[n] = data[upper_entry[n]]


class HessianPattern:
    """The CSR sparsity pattern of G's Hessian over the free degrees of freedom, built once.

    tets (M, 4) int; free (N,) bool; couplings (P, 4) int or None: further groups of four vertices whose
    blocks join the pattern like a tet's (the contact pairs of the Taichi Newton, `contact_pairs.py`);
    their slots are rows M.. of slot_of. Free vertex i has unknowns 3 free_index[i] + (0, 1, 2);
    free_index is -1 at constrained vertices; vertex_graph (F, F) CSR: which free vertices share a tet
    (or a coupling). indptr (3F + 1,), indices (nnz,) int32: the scalar CSR pattern (columns sorted) of
    the 3x3 blocks of every pair of free vertices sharing a tet or a coupling; upper_indptr,
    upper_indices: its upper triangle in CSC.
    """

    def __init__(self, tets: np.ndarray, free: np.ndarray, couplings: np.ndarray = None):
        tets = np.ascontiguousarray(tets, dtype=np.int32)
        free = np.asarray(free, dtype=bool)
        self.tets, self.free = tets, free
        self.free_int = free.astype(np.int32)
        self.free_index = np.full(len(free), -1, dtype=np.int32)
        self.free_index[free] = np.arange(int(free.sum()), dtype=np.int32)
        self.n_free = int(free.sum())
        self.n_dofs = 3 * self.n_free
        groups = tets if couplings is None else np.concatenate([tets, np.asarray(couplings, np.int32).reshape(-1, 4)])
        fi = self.free_index[groups]                                      # (M + P, 4)
        rows = np.repeat(fi, 4, axis=1).ravel()
        cols = np.tile(fi, (1, 4)).ravel()
        keep = (rows >= 0) & (cols >= 0)
        diag = np.arange(self.n_free)
        adjacency = sp.csr_matrix((np.ones(keep.sum() + self.n_free),
                                   (np.concatenate([rows[keep], diag]), np.concatenate([cols[keep], diag]))),
                                  shape=(self.n_free, self.n_free))
        adjacency.sum_duplicates()
        adjacency.sort_indices()
        self.vertex_graph = adjacency
        vptr = adjacency.indptr.astype(np.int64)
        vcols = adjacency.indices.astype(np.int64)
        n_neighbours = np.diff(vptr)
        keys = np.repeat(np.arange(self.n_free, dtype=np.int64), n_neighbours) * self.n_free + vcols

        def block_of(f, w):
            """Index of the 3x3 block of free vertices (f, w) (arrays) among all blocks, row by row."""
            return np.searchsorted(keys, f.astype(np.int64) * self.n_free + w)

        self.nnz = int(9 * vptr[-1])
        if self.nnz >= 2 ** 31 or 16 * len(groups) >= 2 ** 31:
            raise MemoryError("Hessian pattern too large for 32-bit CSR indices")
        entry_f = np.repeat(np.arange(self.n_free), n_neighbours)
        entry_rank = np.arange(len(vcols)) - vptr[entry_f]
        # Scalar pattern: entry (3f + c, 3w + d) sits at 9 vptr[f] + 3 nb_f c + 3 rank + d.
        self.block_entry = (9 * vptr[entry_f] + 3 * entry_rank).astype(np.int32)
        self.block_row_length = (3 * n_neighbours[entry_f]).astype(np.int32)
        self.block_vertex = np.where(vcols == entry_f, np.flatnonzero(free)[entry_f], -1).astype(np.int32)
        k, l = np.divmod(np.arange(16), 4)
        fk, fl = fi[:, k], fi[:, l]                                       # (M, 16): ordered pairs (k, l)
        both = (fk >= 0) & (fl >= 0)
        block = block_of(fk[both], fl[both])
        order = np.argsort(block, kind="stable")
        slot = np.empty(len(block), dtype=np.int64)
        slot[order] = np.arange(len(block))
        self.slot_of = np.full((len(groups), 16), -1, dtype=np.int32)
        self.slot_of[both] = np.where(fl[both] <= fk[both], slot, -2 - slot)   # above the diagonal: -2 - slot
        self.slots = np.zeros((len(block), 3, 3))
        self.contribution_start = np.concatenate([[0], np.cumsum(np.bincount(block, minlength=len(vcols)))]) \
            .astype(np.int32)
        c = np.arange(3)[None, :, None]
        d = np.arange(3)[None, None, :]
        where = self.block_entry[:, None, None] + self.block_row_length[:, None, None] * c + d
        indices = np.empty(self.nnz, dtype=np.int32)
        indices[where.ravel()] = np.broadcast_to(3 * vcols[:, None, None] + d, where.shape).ravel()
        self.indices = indices
        self.indptr = np.concatenate([[0], np.cumsum(np.repeat(3 * n_neighbours, 3))]).astype(np.int32)
        # The upper triangle in CSC order is the lower triangle in CSR order (H is symmetric).
        rows = np.repeat(np.arange(self.n_dofs, dtype=np.int32), np.diff(self.indptr))
        self.upper_entry = np.flatnonzero(self.indices <= rows).astype(np.int32)
        self.upper_indices = self.indices[self.upper_entry]
        self.upper_indptr = np.concatenate([[0], np.cumsum(np.bincount(rows[self.upper_entry],
                                                                       minlength=self.n_dofs))]).astype(np.int32)
        self.upper = np.zeros(len(self.upper_entry))
        # Blocks (f, w) with w <= f hold the upper triangle in CSC order: row 3f + a there has the
        # 3 n_lower(f) entries of f's lower neighbours w < f, then a + 1 of the diagonal block.
        lower = np.flatnonzero(vcols <= entry_f)
        n_lower = np.bincount(entry_f[vcols < entry_f], minlength=self.n_free)
        self.lower_blocks = np.stack([lower, self.upper_indptr[3 * entry_f[lower]] + 3 * entry_rank[lower],
                                      3 * n_lower[entry_f[lower]] + 1], axis=1).astype(np.int32)
        self.incidence_start, incident_tet, incident_local = vertex_tet_adjacency(tets, len(free))
        self.incidence = 4 * incident_tet + incident_local                               # 4 t + k, by vertex
        self.tet_forces = np.zeros((len(tets), 4, 3))
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

    def energy_gradient(self, x: np.ndarray, g: np.ndarray) -> float:
        """G(x) in J for x (N, 3) float64 C-contiguous; fills g (N, 3) with dG/dx (zero at constrained
        vertices). One pass over the tets for both."""
        p = self.pattern
        return float(energy_gradient_kernel(x, self.y, self.tets, self.grad_rows, self.volumes, self.masses,
                                            p.free_int, self.h, self.mu, self.lam, *self.ground, p.incidence_start,
                                            p.incidence, p.tet_forces, g))

    def energy(self, x: np.ndarray) -> float:
        """G(x) in J."""
        return self.energy_gradient(x, np.empty_like(x))

    def gradient(self, x: np.ndarray, out: np.ndarray = None) -> np.ndarray:
        """(N, 3) dG/dx, zero at constrained vertices."""
        out = np.empty_like(x) if out is None else out
        self.energy_gradient(x, out)
        return out

    def stress_hessians(self, x: np.ndarray) -> np.ndarray:
        """Fill and return pattern.A9 (M, 9, 9), the projected dP/dF of every tet at x."""
        p = self.pattern
        eigensystem_kernel(x, self.tets, self.grad_rows, self.mu, self.lam, p.eigenvalues, p.eigenvectors)
        stress_hessian_kernel(x, self.tets, self.grad_rows, self.mu, self.lam, p.eigenvalues, p.eigenvectors, p.A9)
        return self.pattern.A9

    def hessian(self, x: np.ndarray, project: bool = True, full: bool = True, pattern: HessianPattern = None):
        """(3F, 3F) Hessian over the free unknowns at x, projected per tet unless project=False: its upper
        triangle in `pattern.upper`, and with full=True the whole matrix in the pattern's CSR arrays,
        returned as a scipy CSR matrix (full=False returns None). pattern: another pattern of these tets
        (default this one's), e.g. one with contact couplings, whose coupling slots are already written."""
        p = self.pattern if pattern is None else pattern
        hessian_kernel(x, self.tets, self.grad_rows, self.volumes, self.masses, self.h, self.mu, self.lam,
                       *self.ground, int(project), int(full), p.slot_of, p.slots, p.contribution_start,
                       p.block_entry, p.block_row_length, p.block_vertex, p.lower_blocks, p.data, p.upper_entry,
                       p.upper)
        if not full:
            return None
        return p.matrix()
