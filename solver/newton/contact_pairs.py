"""The contact term E_c of G for the Taichi Newton (issue 17): the fast twin of `contact_term.ContactTerm`.

The pairs come from the hashed-grid `ContactDetector` that the VBD sweep uses, found again at every Newton
iterate x, where the step cap and the Hessian need the pairs and bounds at x itself. A line-search trial
only needs E_c and its gradient, and those take the pairs of the last detection, their distances
recomputed, while no vertex has moved by half of (query_radius - radius) since: a pair that detection
missed was at least query_radius apart and has come closer by at most twice that, so it is still
beyond the radius, where b = 0 (the rule of `vbd.contact_state`); further trials detect again. E_c is
then exactly that of the pairs found at the trial, as in the oracle.

Every pair's energy b(d), gradient b'(d) (w (x) n) and Hessian come from `physics.contact`
(`pair_energy_gradient`, `pair_curvature` and `pair_hessian_block`), evaluated in the kernels below: the PSD
b''(d) (w (x) n)(w (x) n)^T (n held fixed: VBD [Chen et al. 2024] Sec. 3.5, OGC [Chen et al. 2025]) in projected
steps, and the exact one, with the curvature b'(d) d2d/dx2 of the distance, where the Newton tries its exact
Hessian. The numpy `ContactTerm` of the oracle finds its pairs with its own k-d tree (`find_pairs_np`) and sums
its own terms: each checks the other.

- `energy_gradient(x, g)`: E_c(x), with dE_c/dx added to g at the free vertices: every pair writes its
  gradient to a buffer, then every vertex sums those of its pairs (the detector's incidence lists), so the
  sum has no atomics and a fixed order;
- `step_cap(x, d)`: the largest alpha in (0, 1] with |alpha d_v| <= b_v, b the detector's conservative
  bounds at x (as `ContactTerm.step_cap`): no line-search trial carries a surface through another;
- `couplings(x)`: the pairs closer than the radius (the others have no Hessian), whose four vertices a
  `HessianPattern` couples beside the tets';
- `write_blocks(x, pattern, full, exact)`: the 16 3x3 blocks of each of those pairs' Hessians into that
  pattern's slots (rows M.. of its slot_of), before `StepKernels.hessian` sums every block's slots.
"""
import numpy as np

from .._ti import ti
from ..mesh.tetmesh import TetMesh
from ..physics.contact import pair_curvature, pair_energy_gradient, pair_hessian_block, row3
from ..physics.contact_detection import ContactDetector


@ti.kernel
def contact_energy_gradient_kernel(x: ti.types.ndarray(), kind: ti.types.ndarray(), pair: ti.types.ndarray(),
                                   n_pairs: ti.i32, k: ti.f64, r: ti.f64, offsets: ti.types.ndarray(),
                                   incidence: ti.types.ndarray(), free: ti.types.ndarray(),
                                   pair_gradient: ti.types.ndarray(), g: ti.types.ndarray()) -> ti.f64:
    """E_c in J of the first n_pairs pairs (kind, pair: the detector's arrays) at x (N, 3), and g (N, 3) +=
    dE_c/dx at the free vertices (free (N,) int32). pair_gradient (>= n_pairs, 12): each pair's gradient;
    vertex v gathers those of its pairs incidence[offsets[v]:offsets[v + 1]]."""
    total = 0.0
    for p in range(n_pairs):
        v = pair[p]
        b, grad = pair_energy_gradient(kind[p], row3(x, v[0]), row3(x, v[1]), row3(x, v[2]), row3(x, v[3]), k, r,
                                       ti.f64)
        total += b
        for a in ti.static(range(12)):
            pair_gradient[p, a] = grad[a]
    for i in range(g.shape[0]):
        if free[i] != 0:
            gi = ti.Vector.zero(ti.f64, 3)
            for s in range(offsets[i], offsets[i + 1]):
                p = incidence[s]
                for j in ti.static(range(4)):
                    if pair[p][j] == i:
                        for a in ti.static(range(3)):
                            gi[a] += pair_gradient[p, 3 * j + a]
            for a in ti.static(range(3)):
                g[i, a] += gi[a]
    return total


@ti.kernel
def pair_blocks_kernel(x: ti.types.ndarray(), kind: ti.types.ndarray(), vertices: ti.types.ndarray(), k: ti.f64,
                       r: ti.f64, first: ti.i32, full: ti.i32, exact: ti.i32, slot_of: ti.types.ndarray(),
                       slots: ti.types.ndarray()):
    """Pair p's (kind (P,), vertices (P, 4)) Hessian at x (N, 3), exact or PSD (`pair_curvature`): its block
    of the ordered vertex pair (k, l) into slots[slot_of[first + p, 4 k + l]] (-1: a constrained vertex;
    -2 - slot: above the diagonal, only written when full), as a tet's in `hessian._tet_blocks`. The 16
    blocks are a loop, not unrolled: 1.5 s to compile instead of 10."""
    for p in range(kind.shape[0]):
        c = pair_curvature(kind[p], row3(x, vertices[p, 0]), row3(x, vertices[p, 1]), row3(x, vertices[p, 2]),
                           row3(x, vertices[p, 3]), k, r, exact)
        for kl in range(16):
            n = slot_of[first + p, kl]
            if n <= -2 and full != 0:
                n = -2 - n
            if n >= 0:
                block = pair_hessian_block(c, kl // 4, kl % 4)
                for a, b in ti.static(ti.ndrange(3, 3)):
                    slots[n, a, b] = block[a, b]


class ContactPairs:
    """E_c of G for the Taichi Newton, built from the oracle's `ContactTerm` `term` (its Contact, tets,
    rest positions and free mask; none of its pairs). `detections` counts the detections."""

    def __init__(self, term):
        self.term = term
        self.contact = term.contact
        self.rest = term.rest
        n = len(term.rest)
        self.free = np.ascontiguousarray(term.free, dtype=np.int32)
        self.detector = ContactDetector(TetMesh(term.rest, term.tets), term.free, term.contact, ti.f64)
        self._positions = ti.Vector.ndarray(3, ti.f64, (1, n))
        self._at = np.full((n, 3), np.nan)           # x of the last detection
        self._pair_gradient = np.zeros((64, 12))
        self._couplings = None
        self.detections = 0
        self._compile_blocks()

    def _compile_blocks(self) -> None:
        """Compile `pair_blocks_kernel` now, on one scratch pair whose blocks all go nowhere (slot -1), so
        that the first pair closer than the radius does not stall the solve that meets it (0.3 s with
        Taichi's offline cache, more without)."""
        pair_blocks_kernel(np.zeros((1, 3)), np.zeros(1, dtype=np.int32), np.zeros((1, 4), dtype=np.int32),
                           self.contact.stiffness, self.contact.radius, 0, 0, 1, np.full((1, 16), -1, dtype=np.int32),
                           np.zeros((1, 3, 3)))

    def serves(self, term) -> bool:
        """Whether this is the Taichi twin of `term` (same Contact and rest positions)."""
        return term is self.term or (term.contact == self.contact and np.array_equal(term.rest, self.rest))

    def detect(self, x: np.ndarray) -> None:
        """Find the pairs at x (N, 3) unless they were found there last."""
        if np.array_equal(self._at, x):
            return
        self._detect(x)

    def _detect(self, x: np.ndarray) -> None:
        """Find the pairs, their incidence lists and the bounds at x (N, 3)."""
        self._positions.from_numpy(x[None])
        self.detector.detect(self._positions, 0)
        self._at[:] = x
        self._couplings = None
        self.detections += 1

    def energy_gradient(self, x: np.ndarray, g: np.ndarray) -> float:
        """E_c(x) in J; adds dE_c/dx (N, 3) to g at the free vertices. x (N, 3) float64 C-contiguous.
        Detects again only when a pair the last detection missed may have come closer than the radius."""
        c = self.contact
        if not 2 * np.linalg.norm(x - self._at, axis=1).max() < c.query_radius - c.radius:
            self._detect(x)
        d = self.detector
        if d.n_pairs > len(self._pair_gradient):
            self._pair_gradient = np.zeros((2 * d.n_pairs, 12))
        return float(contact_energy_gradient_kernel(x, d.kind, d.pair, d.n_pairs, c.stiffness, c.radius,
                                                    d.incidence_offsets, d.incidence, self.free,
                                                    self._pair_gradient, g))

    def step_cap(self, x: np.ndarray, d: np.ndarray) -> float:
        """The largest alpha in (0, 1] with |alpha d_v| <= b_v at every vertex, b the bounds at x (N, 3) and
        d (N, 3) the Newton direction."""
        self.detect(x)
        bound = self.detector.bound.to_numpy()
        length = np.linalg.norm(d, axis=1)
        moving = length > 0
        return float(min(1.0, np.min(bound[moving] / length[moving], initial=1.0)))

    def couplings(self, x: np.ndarray):
        """(kind (P,) int32, vertices (P, 4) int32): the pairs closer than the radius at x (N, 3)."""
        self.detect(x)
        if self._couplings is None:
            kind, vertices, _, distance = self.detector.pairs()
            near = distance < self.contact.radius
            self._couplings = (np.ascontiguousarray(kind[near]), np.ascontiguousarray(vertices[near]))
        return self._couplings

    def write_blocks(self, x: np.ndarray, pattern, full: bool, exact: bool) -> None:
        """The Hessian blocks of `couplings(x)` into the slots of `pattern`, a `HessianPattern` of the tets
        with those couplings (full as in `StepKernels.hessian`); exact: the pairs' exact Hessians, else their
        PSD parts."""
        kind, vertices = self.couplings(x)
        if len(kind):
            pair_blocks_kernel(x, kind, vertices, self.contact.stiffness, self.contact.radius, len(pattern.tets),
                               int(full), int(exact), pattern.slot_of, pattern.slots)
