"""Contact in a VBD simulation (issue 17): the detector, the positions its bounds start from, when to
detect again, the contact term of G and the measurements the scripts read.

A full detection at x_full lists L, every admissible pair closer than the query radius q there, and
gives each vertex its bound. A refresh at later positions x keeps L and sets new bounds (a Verlet-list
argument), far cheaper than a detection:

    Delta = max_i |x_i - x_full,i|     (every vertex, fixed and kinematic ones included)
    b_v   = g min(q - 2 Delta, distance at x of each pair of v in L),   x_det = x

A pair not in L was at least q apart at x_full; each of its points has moved at most Delta since, so it
is at least q - 2 Delta apart at x. Every pair is thus at least b_v / g apart at x for each of its
vertices v, and as each vertex then moves at most b_v from x_det = x, with g < 1/2 no two primitives
can meet: two that were d apart close by at most 2 g d < d. No crossing by construction (OGC [Chen et
al. 2025]), whatever the refreshes. The pairs of L are the only ones that can be closer than the radius
r while 2 Delta < q - r; past that L may miss an active pair, and a full detection replaces the refresh.

Only the pairs that can set a bound need measuring: a pair whose vertices have moved s since x_det has
come at most `pair_reach`(s) closer, so a measured pair is at most its distance there plus that apart,
and every pair at least its distance there less that. A pair whose lower bound is at least the cap
q - 2 Delta, or at least that upper bound of the closest measured pair of each of its vertices, sets no
b_v. The refresh keeps that lower bound as the pair's distance instead (`refresh_bounds`): the bounds are
the same, and in a resting pile few pairs besides the closest one of each vertex are measured (and, where
the refresh lists the pairs the sweep walks, those whose lower bound is within r + 2 horizon, below: a
near pair is then one that is, not one that may be, and the sweep walks no pair that only a loose lower
bound made near).

The same bounds tell which pairs can matter before the next refresh: a pair d_p apart at x_det whose
vertices' bounds are at most b stays farther than d_p - 2 b, so with d_p >= r + 2 b its barrier stays
zero and the sweep skips it (`live`; in a resting pile most pairs of L are such).

The sweep walks only the live pairs closer than r + 2 horizon (near; horizon = NEAR_HORIZON r) while no
vertex of them has moved farther than the horizon since x_det: until then the others are at least r
apart. A vertex that moves farther alerts the vertices of its live pairs, which then walk all their live
pairs in that iteration (`contact_sweep.raise_alerts`); the rest of the pile keeps its near lists. In a
resting pile the vertices move microns per step, and most live pairs are not near.

When: a full detection whenever positions move outside that margin (checked at every refresh, and every
`Contact.detection_interval` iterations otherwise); a refresh at the start of every step (at x_n; the
initial guess is then clamped to the bounds), again before its first iteration (at the clamped guess),
and before any iteration that follows one in which a vertex hit its bound (bounds may cost refreshes,
never progress). The refresh at x_n only sets bounds: the one at the guess lists the live pairs. Where
the first would change nothing it is left out: the second sets the same bounds whether the last refresh
was at x_n or earlier (it measures every pair that may be a vertex's closest), and the forces do not
depend on the lower bounds it keeps for the others.
"""
import numpy as np

from .._ti import ti
from ..backend import running_on_cpu
from ..errors import ConfigError
from ..physics.contact import Contact
from ..physics.contact_detection import ContactDetector
from . import contact_sweep, implicit_euler
from .layout import STATE_ROWS, X, X_N
from .vertex_solve import serial_sweep, unrolled_colors

COPLANAR_ROUNDOFF = 1e-10   # `surface_crossing`: signed volumes below this x (the pair's longest edge)^3 are coplanar
NEAR_HORIZON = 0.02         # x radius: the sweep's horizon (module docstring); measured 0.01-0.2 in a resting pile
KINEMATIC_STALL = 1e-3      # `move_kinematic`: a move gaining less than this x the distance left is blocked


class ContactStage:
    """The contact of one simulation under one `Contact`.

    mesh: the `TetMesh` (every body); free: (N,) bool, the vertices VBD moves; dtype: float type of the
    state. x_full (N,) holds the positions of the last full detection, x_det (N,) those of the last
    refresh, bound (N,) the bounds it set, in m, distance (P,) the pairs' distances there (lower bounds
    where the exact one changes no bound: module docstring), in m, and live (P,) int32 its pairs that may
    come within the radius before the next one (module docstring), listed per vertex in live_incidence
    (4P,) up to live_end (N,), the near ones among them in near_incidence (4P,) up to near_end (N,)
    (`contact_sweep.refresh_bounds`).
    `bound_hits` counts the vertices clamped to their bound since construction, `detections` the full
    detections, `refreshes` the refreshes.
    """

    def __init__(self, mesh, free: np.ndarray, contact: Contact, dtype):
        self.contact = contact
        self.dtype = dtype
        self.free = np.asarray(free, dtype=bool)
        self.detector = ContactDetector(mesh, free, contact, dtype)
        self.bodies = self.detector.bodies
        n = mesh.n_vertices
        self.x_full = ti.Vector.ndarray(3, dtype, n)
        self.x_det = ti.Vector.ndarray(3, dtype, n)
        self.bound = ti.ndarray(dtype, n)
        self._moved = ti.ndarray(dtype, n)
        self._nearest = ti.ndarray(dtype, n)         # scratch for `refresh_bounds`
        self.distance = ti.ndarray(dtype, 64)       # per pair, grown with the pair count
        self._exact = ti.ndarray(ti.i32, 64)        # whether distance holds the distance itself
        self._reach = ti.ndarray(dtype, 64)         # scratch for `refresh_bounds`
        self.live = ti.ndarray(ti.i32, 64)
        self.live_incidence = ti.ndarray(ti.i32, 4 * 64)
        self.live_end = ti.ndarray(ti.i32, n)
        self.near_incidence = ti.ndarray(ti.i32, 4 * 64)
        self.near_end = ti.ndarray(ti.i32, n)
        self._alert = ti.ndarray(ti.i32, n)            # `contact_sweep.raise_alerts`: stamps, 0 for none yet
        self._alert.fill(0)
        self._stamp = 0                                 # the iteration's stamp: one up per contact iteration
        self._free = ti.ndarray(ti.i32, n)
        self._free.from_numpy(self.free.astype(np.int32))
        self._color = ti.ndarray(ti.i32, n)             # each free vertex's colour (set with the jacobi lists)
        self._color.from_numpy(np.full(n, -1, dtype=np.int32))
        self._target = ti.Vector.ndarray(3, dtype, n)
        self.touched = ti.ndarray(ti.i32, n)
        self._cpu = running_on_cpu()
        self._serial = serial_sweep(mesh.n_tets, self._cpu)
        self._jacobi = None             # the vertices of each colour that have pairs (set at the first iteration)
        self._jacobi_count = None
        self._listed = False            # whether they are those of the last detection
        self._since_check = 0
        self._due = False
        self.bound_hits = 0
        self.detections = 0
        self.refreshes = 0

    def detect(self, state, row: int = X) -> int:
        """A full detection: find the pairs at state[row], whose positions become x_full and x_det, and
        set the bounds there; returns the number of pairs."""
        n_pairs = self.detector.detect(state, row)
        if n_pairs > self.live.shape[0]:
            self.distance = ti.ndarray(self.dtype, 2 * n_pairs)
            self._exact = ti.ndarray(ti.i32, 2 * n_pairs)
            self._reach = ti.ndarray(self.dtype, 2 * n_pairs)
            self.live = ti.ndarray(ti.i32, 2 * n_pairs)
            self.live_incidence = ti.ndarray(ti.i32, 8 * n_pairs)
            self.near_incidence = ti.ndarray(ti.i32, 8 * n_pairs)
        contact_sweep.copy_row(state, row, self.x_full, self._serial)
        contact_sweep.copy_row(state, row, self.x_det, self._serial)
        contact_sweep.copy_prefix(self.detector.distance, n_pairs, self.distance, self._serial)  # exact at x_det
        self._exact.fill(1)
        self._set_bounds(state, row)                # Delta = 0: b_v = g min(q, distance of v's closest pair)
        self._listed = False
        self.detections += 1
        return n_pairs

    def refresh(self, state, row: int = X, lists: bool = True) -> None:
        """New bounds at state[row] from the pairs of the last full detection, or a full detection there
        when a pair it missed may have come closer than the radius (module docstring). lists: also list
        the live pairs (not needed where another refresh follows before the next iteration)."""
        c = self.contact
        if 2 * self._set_bounds(state, row, lists) >= c.query_radius - c.radius:
            self.detect(state, row)
        else:
            self.refreshes += 1

    def _set_bounds(self, state, row: int, lists: bool = True) -> float:
        """x_det = state[row], the bounds there and (with lists) which pairs are live
        (`contact_sweep.refresh_bounds`); returns Delta in m."""
        d, c = self.detector, self.contact
        delta = contact_sweep.refresh_bounds(state, row, self.x_full, d.kind, d.pair, d.n_pairs, d.incidence_offsets,
                                             d.incidence, c.query_radius, c.radius, c.bound_relaxation,
                                             self.distance, self._exact, self._reach, self.x_det, self._moved,
                                             self.bound, self._nearest, self.live, self.live_incidence, self.live_end,
                                             self.near_incidence, self.near_end, NEAR_HORIZON * c.radius,
                                             self._free, self.dtype, self._serial, lists)
        self._since_check = 0
        self._due = False
        return delta

    def _stale(self, state, row: int) -> bool:
        """Whether at state[row] a pair the last full detection missed may have come closer than the radius
        (module docstring)."""
        c = self.contact
        return 2 * contact_sweep.largest_move(state, row, self.x_full, self._serial) >= c.query_radius - c.radius

    def begin_step(self, state, color_order, kinematic_ids, kinematic_targets, n_kinematic: int) -> None:
        """Refresh the bounds at x_n and clamp the initial guess to them, then move the kinematic vertices to
        their targets (K,) 3-vectors within the bounds (`move_kinematic`), and have the first iteration
        refresh at the clamped guess, where kinematic vertices sit at their targets (so the first refresh
        lists no live pairs); no vertex has touched yet. The refresh at x_n is left out where it would
        change nothing: no detection, and no bound it could set below the guess's move
        (`contact_sweep.guess_within_bounds`; the refresh at the guess then finds the same bounds and
        pairs, module docstring). Called after the guess is set, so the row X_N holds x_n and X the guess
        (the kinematic vertices at their targets)."""
        contact_sweep.clear(self.touched, self._serial)
        c = self.contact
        if n_kinematic:
            contact_sweep.hold_kinematic(state, kinematic_ids, n_kinematic, self._serial)
        if not contact_sweep.guess_within_bounds(state, color_order, self.x_det, self.x_full, self.bound,
                                                 c.bound_relaxation, c.query_radius - c.radius, self.dtype,
                                                 self._serial):
            self.refresh(state, X_N, lists=False)
            self.bound_hits += contact_sweep.clamp_to_bounds(state, color_order, self.x_det, self.bound, self.dtype,
                                                             self._serial)
        if n_kinematic:
            self.move_kinematic(state, kinematic_ids, kinematic_targets, n_kinematic)
        self._due = True

    def move_kinematic(self, state, kinematic_ids, kinematic_targets, n_kinematic: int) -> None:
        """Move the kinematic vertices from x_n to their targets in straight moves, each within the bounds,
        refreshing between them: a prescribed motion then never carries a surface through another, however
        far it goes in a step. Where the bodies in its way keep it from arriving (the gap ahead halves at
        every move while the free vertices wait for the iterations), raise a one-line `ConfigError` and put
        every vertex back at x_n. In free space every move is g q long, so a far target costs moves (and
        detections), never a refusal: only a move that gains less than KINEMATIC_STALL of the distance left
        (the gap ahead nearly closed) counts as blocked."""
        left = np.inf
        moves = 0
        while True:
            before = left
            left = contact_sweep.advance_kinematic(state, kinematic_ids, kinematic_targets, n_kinematic, self.x_det,
                                                   self.bound, self.dtype, self._serial)
            moves += 1
            if left == 0:
                return
            if before - left < KINEMATIC_STALL * left:
                break
            self.refresh(state, X, lists=False)
        x = state.to_numpy()[X][kinematic_ids.to_numpy()[:n_kinematic]]
        short = np.linalg.norm(kinematic_targets.to_numpy()[:n_kinematic] - x, axis=1)
        vertex = int(kinematic_ids.to_numpy()[int(np.argmax(short))])
        implicit_euler.return_to_start(state, self._serial)
        raise ConfigError(f"kinematic vertex {vertex} would touch or pass through a body this step: "
                          f"{short.max():.3g} m short of its target after {moves} moves within the contact bounds; "
                          "use a smaller dt or a slower kinematic_motion")

    def compile_kernels(self, mass, adjacency, params, n_colors: int, sweeps: bool) -> None:
        """Compile now the kernels a run may first launch long after its first step, so that the first
        contact does not stall the run while they compile (about 0.6 s with Taichi's offline cache, seconds
        without): the check for a move since the last detection (`_detect_here`), the copy of the pair
        distances that `contact_count` and `min_separation` read and, with sweeps (VBD), the contact
        iteration (once pairs appear), the bounded one (while none is listed), the refresh at x_n and the
        clamp of the guess. Each is launched on a one-vertex scratch problem with no colour to solve, with
        the argument types and compile-time constants of this simulation's launches: nothing of the
        simulation is read or written."""
        color_order, offsets, others, adj_f, color_starts = adjacency
        dtype, unrolled = self.dtype, unrolled_colors(n_colors, self._serial)
        state = ti.Vector.ndarray(3, dtype, (STATE_ROWS, 1))
        vector, number = ti.Vector.ndarray(3, dtype, 1), ti.ndarray(dtype, 1)
        flag, slots = ti.ndarray(ti.i32, 1), ti.ndarray(ti.i32, 2)
        no_colors = ti.ndarray(ti.i32, color_starts.shape[0])     # every colour empty
        no_jacobi = ti.ndarray(ti.i32, n_colors)
        pair = ti.Vector.ndarray(4, ti.i32, 1)
        for array in (state, vector, number, flag, slots, no_colors, no_jacobi, pair):
            array.from_numpy(np.zeros_like(array.to_numpy()))     # (fill(0) compiles a float64 fill and warns)
        contact_sweep.largest_move(state, X, vector, self._serial)
        contact_sweep.copy_prefix(number, 0, np.empty(1), self._serial)       # `distances`
        if not sweeps:
            return
        contact_sweep.vbd_contact_iteration(state, mass, color_order, offsets, others, adj_f, no_colors, params, flag,
                                            pair, number, slots, flag, flag, flag, flag, vector, number, 0.0, flag, 1,
                                            number, flag, vector, flag, flag, no_jacobi, 1.0, 1.0, 0.0, 1.0, unrolled,
                                            dtype, self._serial, self._cpu)
        contact_sweep.vbd_bounded_iteration(state, mass, color_order, offsets, others, adj_f, no_colors, params, vector,
                                            number, unrolled, dtype, self._serial)
        contact_sweep.refresh_bounds(state, X, vector, flag, pair, 0, slots, flag, 1.0, 0.5, 0.25, number, flag,
                                     number, vector, number, number, number, flag, flag, flag, flag, flag, 0.0, flag,
                                     dtype, self._serial, False)
        contact_sweep.clamp_to_bounds(state, flag, vector, number, dtype, self._serial)

    def iterate(self, state, mass, adjacency, params, n_colors: int, dtype, omega=None) -> int:
        """One VBD iteration with contact (`contact_sweep.vbd_contact_iteration`, or `vbd_bounded_iteration`
        while no pair is listed), refreshing first after a bound hit and detecting first when stale, then the
        Chebyshev step of weight omega (None: none) for the vertices that have not touched this step;
        returns the number of bound hits."""
        if self._due:
            self.refresh(state, X)
        elif self._since_check >= self.contact.detection_interval:
            if self._stale(state, X):
                self.detect(state, X)
            self._since_check = 0
        color_order, _, _, _, color_starts = adjacency
        d, c = self.detector, self.contact
        if not self._listed:
            if self._jacobi is None:
                self._jacobi = ti.ndarray(ti.i32, color_order.shape[0])
                self._jacobi_count = ti.ndarray(ti.i32, n_colors)
            contact_sweep.list_jacobi_vertices(color_order, color_starts, d.incidence_offsets, self._jacobi,
                                               self._jacobi_count, self._color, self._serial)
            self._listed = True
        if d.n_pairs == 0:
            hits = contact_sweep.vbd_bounded_iteration(state, mass, *adjacency, params, self.x_det, self.bound,
                                                       unrolled_colors(n_colors, self._serial), dtype, self._serial)
        else:
            self._stamp += 1
            hits = contact_sweep.vbd_contact_iteration(state, mass, *adjacency, params, d.kind, d.pair,
                                                       self.distance, d.incidence_offsets, self.live_incidence,
                                                       self.live_end, self.near_incidence, self.near_end, self.x_det,
                                                       self._moved, NEAR_HORIZON * c.radius, self._alert, self._stamp,
                                                       self.bound, self._color, self._target, self.touched,
                                                       self._jacobi, self._jacobi_count, c.stiffness, c.radius,
                                                       c.friction, c.friction_speed,
                                                       unrolled_colors(n_colors, self._serial), dtype, self._serial,
                                                       self._cpu)
        if omega is not None:
            hits += contact_sweep.chebyshev_contact_step(state, color_order, self.touched, self.x_det, self.bound,
                                                         omega, dtype, self._serial)
        self._since_check += 1
        self._due = hits > 0
        self.bound_hits += hits
        return hits

    def _detect_here(self, state) -> None:
        """Make the detector's pairs those at the current positions: a full detection there, unless the last
        one was made at exactly these positions (it would find the same pairs: detection is deterministic),
        so that asking for the contact count and then the closest gap detects once."""
        if contact_sweep.largest_move(state, X, self.x_full, self._serial) != 0:
            self.detect(state, X)

    def energy(self, state, dtype) -> float:
        """E_c in J at the current positions (detected there)."""
        self._detect_here(state)
        d = self.detector
        return float(contact_sweep.contact_energy(state, d.kind, d.pair, d.n_pairs, self.contact.stiffness,
                                                  self.contact.radius, dtype))

    def add_local_systems(self, state, color_order, params, f, H, dtype) -> float:
        """Add the contact terms to the per-vertex f (N,) and H (N,) 3x3 at the current positions (detected
        there); returns max_i |f_i| in N."""
        self.detect(state, X)
        d, c = self.detector, self.contact
        return float(contact_sweep.add_contact_local_systems(state, color_order, d.kind, d.pair, self.distance,
                                                             d.incidence_offsets, self.live_incidence, self.live_end,
                                                             self.near_incidence, self.near_end, self.x_det,
                                                             self._moved, self._alert, self._color, params, f, H,
                                                             c.stiffness, c.radius, c.friction, c.friction_speed,
                                                             dtype))

    def distances(self, state) -> np.ndarray:
        """(P,) distances in m of the pairs under query_radius at the current positions."""
        self._detect_here(state)
        out = np.empty(self.detector.n_pairs)
        contact_sweep.copy_prefix(self.detector.distance, len(out), out, self._serial)
        return out

    def count(self, state) -> int:
        """Pairs closer than the radius at the current positions."""
        return int(np.count_nonzero(self.distances(state) < self.contact.radius))

    def min_separation(self, state) -> float:
        """Least pair distance (m) under query_radius at the current positions, else inf."""
        d = self.distances(state)
        return float(d.min()) if len(d) else float("inf")

    def check_apart(self, state, x: np.ndarray) -> None:
        """Raise `ConfigError` if, at positions x (N, 3) (also in state's X row), two bodies (or two parts
        of one, with self contact) intersect or touch, naming both bodies and the distance."""
        crossing = surface_crossing(x, self.detector.surface, self.bodies, self.free, self.contact.self_contact)
        if crossing is not None:
            a, b = crossing
            if a == b:
                raise ConfigError(f"body {a} intersects itself (a surface edge passes through one of its triangles); "
                                  "untangle it before simulating, or use self_contact=False")
            raise ConfigError(f"bodies {a} and {b} intersect (a surface edge passes through a triangle, distance 0 m); "
                              "move them apart before simulating")
        self.detect(state, X)
        _, vertices, _, distance = self.detector.pairs()
        touching = distance <= 0
        if touching.any():
            p = int(np.flatnonzero(touching)[0])
            a, b = sorted((int(self.bodies[vertices[p, 0]]), int(self.bodies[vertices[p, 3]])))
            raise ConfigError(f"bodies {a} and {b} touch or overlap (distance {distance[p]:.3g} m); "
                              "leave a gap between them before simulating")
        inside = enclosed_body(x, self.detector.surface, self.bodies, self.free)
        if inside is not None:
            inner, outer = inside
            raise ConfigError(f"body {inner} lies inside body {outer} (their surfaces do not meet, one encloses "
                              "the other); move it out before simulating")


PAIR_CHUNK = 1 << 20        # `overlapping_boxes`: candidate pairs handled at a time (bounds the memory)
LARGE_BOXES = 64            # `overlapping_boxes`: the largest boxes, compared with every box of the other side


def overlapping_boxes(lo_a: np.ndarray, hi_a: np.ndarray, lo_b: np.ndarray, hi_b: np.ndarray):
    """Yield, in chunks, the index pairs (i, j) (two (P,) int64 arrays) of boxes [lo_a[i], hi_a[i]] and
    [lo_b[j], hi_b[j]] (each (N, 3)) that overlap, every such pair exactly once, chunks in increasing
    i * len(lo_b) + j. The LARGE_BOXES largest boxes (a slab's triangles under small bodies) are compared
    with every box of the other side; the others go into a uniform grid whose cell is twice the median box
    size, or a quarter of the largest of them, so that each covers at most 5 x 5 x 5 cells: each is
    entered into the cells it covers, pairs sharing a cell are candidates, and their boxes are compared
    exactly."""
    lower, upper = np.minimum(lo_a.min(0), lo_b.min(0)), np.maximum(hi_a.max(0), hi_b.max(0))
    size_a, size_b = (hi_a - lo_a).max(axis=1), (hi_b - lo_b).max(axis=1)
    size = np.sort(np.concatenate([size_a, size_b]))
    largest_small = size[-LARGE_BOXES - 1] if len(size) > LARGE_BOXES else size[-1]
    cell = max(2 * float(np.median(size)), float(largest_small) / 4, float((upper - lower).max()) / 2 ** 20, 1e-300)
    dims = np.floor((upper - lower) / cell).astype(np.int64) + 1       # keys below 2^63

    def entries(lo, hi, small):
        """(cell key, box index) of every cell each small box covers, sorted by key."""
        c0 = np.floor((lo[small] - lower) / cell).astype(np.int64)
        extent = np.floor((hi[small] - lower) / cell).astype(np.int64) - c0 + 1
        counts = extent.prod(axis=1)
        index = np.flatnonzero(small)
        box = np.repeat(np.arange(len(index)), counts)
        k = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
        ny, nz = extent[box, 1], extent[box, 2]
        c = c0[box] + np.stack([k // (ny * nz), (k // nz) % ny, k % nz], axis=1)
        key = (c[:, 0] * dims[1] + c[:, 1]) * dims[2] + c[:, 2]
        order = np.argsort(key, kind="stable")
        return key[order], index[box[order]]

    def overlap(i, j):
        keep = ((lo_a[i] <= hi_b[j]) & (lo_b[j] <= hi_a[i])).all(axis=1)
        return np.unique(i[keep] * len(lo_b) + j[keep])

    small_a, small_b = size_a <= largest_small, size_b <= largest_small
    found = [overlap(np.repeat(i, len(lo_b)), np.arange(len(lo_b))) for i in np.flatnonzero(~small_a)]
    found += [overlap(np.flatnonzero(small_a), np.full(small_a.sum(), j)) for j in np.flatnonzero(~small_b)]
    key_a, box_a = entries(lo_a, hi_a, small_a)
    key_b, box_b = entries(lo_b, hi_b, small_b)
    first, last = np.searchsorted(key_b, key_a, "left"), np.searchsorted(key_b, key_a, "right")
    counts = last - first
    ends = np.cumsum(counts)
    start = 0
    while start < len(key_a):
        stop = max(int(np.searchsorted(ends, ends[start] - counts[start] + PAIR_CHUNK, "right")), start + 1)
        n = counts[start:stop]
        i = np.repeat(box_a[start:stop], n)
        found.append(overlap(i, box_b[np.repeat(first[start:stop], n) + np.arange(n.sum())
                                      - np.repeat(np.cumsum(n) - n, n)]))
        start = stop
    pairs = np.unique(np.concatenate(found + [np.zeros(0, np.int64)]))
    for chunk in range(0, len(pairs), PAIR_CHUNK):
        part = pairs[chunk:chunk + PAIR_CHUNK]
        yield part // len(lo_b), part % len(lo_b)


def surface_crossing(x: np.ndarray, surface, bodies: np.ndarray, free: np.ndarray, self_contact: bool):
    """(body a, body b) of the first surface edge that passes through a surface triangle sharing none of
    its vertices (of another body, or of its own with self_contact; not both fixed or kinematic, as the
    pairs), else None; x (N, 3), free (N,) bool. Candidates are the edges and triangles whose boxes
    overlap (`overlapping_boxes`); a crossing is decided by signed volumes: the edge's ends lie strictly
    (beyond COPLANAR_ROUNDOFF) on either side of the triangle's plane and the edge's line passes inside
    the triangle."""
    triangles, edges = surface.triangles, surface.edges

    def six_volume(a, b, c, d):
        return np.einsum("ka,ka->k", np.cross(b - a, c - a), d - a)

    for e, t in overlapping_boxes(x[edges].min(axis=1), x[edges].max(axis=1),
                                  x[triangles].min(axis=1), x[triangles].max(axis=1)):
        shares = (edges[e][:, :, None] == triangles[t][:, None, :]).any(axis=(1, 2))
        same = bodies[edges[e, 0]] == bodies[triangles[t, 0]]
        moves = free[edges[e]].any(axis=1) | free[triangles[t]].any(axis=1)
        keep = ~shares & (~same | self_contact) & moves
        e, t = e[keep], t[keep]
        p, q = x[edges[e, 0]], x[edges[e, 1]]
        a, b, c = (x[triangles[t, k]] for k in range(3))
        vp, vq = six_volume(a, b, c, p), six_volume(a, b, c, q)
        scale = np.max([np.linalg.norm(u - v, axis=1) for u, v in ((p, q), (a, b), (b, c), (c, a))], axis=0)
        floor = COPLANAR_ROUNDOFF * scale ** 3      # coplanar up to round-off (one flat face): not a crossing
        sides = (vp * vq < 0) & (np.abs(vp) > floor) & (np.abs(vq) > floor)
        around = np.stack([six_volume(p, q, a, b), six_volume(p, q, b, c), six_volume(p, q, c, a)], axis=1)
        hit = np.flatnonzero(sides & ((around >= 0).all(axis=1) | (around <= 0).all(axis=1)))
        if len(hit):
            return tuple(sorted((int(bodies[edges[e[hit[0]], 0]]), int(bodies[triangles[t[hit[0]], 0]]))))
    return None


def enclosed_body(x: np.ndarray, surface, bodies: np.ndarray, free: np.ndarray):
    """(inner, outer) of a body that lies inside another body's closed surface, else None; x (N, 3),
    bodies (N,), free (N,) bool; pairs of bodies without a free vertex are skipped, as the pairs. For
    surfaces that neither cross nor touch (`surface_crossing`, then the pairs' distances), one body is
    inside another exactly when any one of its vertices is: decided for its first vertex by the winding
    number of the other's surface around it, the sum of its triangles' solid angles over 4 pi (1 inside,
    0 outside; Van Oosterom and Strackee's formula for each angle)."""
    triangles = surface.triangles
    n_bodies = int(bodies.max()) + 1
    lower = np.full((n_bodies, 3), np.inf)
    upper = np.full((n_bodies, 3), -np.inf)
    np.minimum.at(lower, bodies, x)
    np.maximum.at(upper, bodies, x)
    moving = np.zeros(n_bodies, dtype=bool)
    moving[bodies[free]] = True
    first = np.unique(bodies, return_index=True)[1]
    tri_body = bodies[triangles[:, 0]]
    inner, outer = _boxes_within(lower, upper, moving)
    inside = np.zeros(len(inner), dtype=bool)
    by_outer = np.argsort(outer, kind="stable")
    groups = np.split(by_outer, np.flatnonzero(np.diff(outer[by_outer])) + 1) if len(inner) else []
    for rows in groups:                  # every body nested in the box of one outer body, in chunks
        corners = x[triangles[tri_body == outer[rows[0]]]]                  # (T, 3, 3)
        step = max(1, PAIR_CHUNK // len(corners))
        for chunk in range(0, len(rows), step):
            r = rows[chunk:chunk + step]
            a, b, c = (corners[None, :, k] - x[first[inner[r]]][:, None] for k in range(3))    # (n, T, 3)
            la, lb, lc = (np.linalg.norm(v, axis=2) for v in (a, b, c))
            volume = np.einsum("nta,nta->nt", a, np.cross(b, c))
            den = la * lb * lc + np.einsum("nta,nta->nt", a, b) * lc + np.einsum("nta,nta->nt", b, c) * la \
                + np.einsum("nta,nta->nt", c, a) * lb
            inside[r] = np.abs(np.arctan2(volume, den).sum(axis=1) / (2 * np.pi)) > 0.5
    hit = np.flatnonzero(inside)
    return (int(inner[hit[0]]), int(outer[hit[0]])) if len(hit) else None


def _boxes_within(lower: np.ndarray, upper: np.ndarray, moving: np.ndarray, rows: int = 1024):
    """(inner, outer): index arrays of the boxes [lower, upper] ((B, 3) each) that lie within another one,
    at least one of the two moving ((B,) bool); compared `rows` inner boxes at a time (B x B may not fit)."""
    found = [(np.zeros(0, np.int64), np.zeros(0, np.int64))]
    for start in range(0, len(lower), rows):
        inner = slice(start, start + rows)
        within = (lower[inner, None] >= lower[None]).all(axis=2) & (upper[inner, None] <= upper[None]).all(axis=2)
        within &= moving[inner, None] | moving[None]
        i, j = np.nonzero(within)
        i = i + start
        found.append((i[i != j], j[i != j]))
    return tuple(np.concatenate(k) for k in zip(*found))


def as_contact(value):
    """value if it is a `Contact` or None, else a one-line `ConfigError`."""
    if value is not None and not isinstance(value, Contact):
        raise ConfigError(f"contact must be a solver.Contact or None, got {type(value).__name__}")
    return value
