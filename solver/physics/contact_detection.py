"""Finding the pairs of contact (issue 17): a hashed uniform grid built by Taichi kernels at each detection,
the exact distance of every candidate, per-vertex incidence lists and OGC's conservative bounds.

One detection, all in kernels on the device:
  1. every triangle and edge gets its box grown by the query radius q, as a range of grid cells;
  2. the grid: count the entries of each hash bucket, prefix sum, scatter the items into their
     buckets, sort each bucket (so that everything after is deterministic);
  3. every surface vertex looks up the triangles in its cell (first in each sorted bucket), and every
     edge the edges of higher index in the cells of its box, each unordered edge pair once (reported
     in the lowest cell the two ranges share); a candidate whose box meets the query's, that passes
     the filters below and lies closer than q is a pair. One pass counts the
     pairs of each query, a prefix sum places them, a second pass writes them in order;
  4. per-vertex incidence lists (CSR: offsets, pair ids ascending), so that a vertex gathers its terms
     without atomics;
  5. the bound b_v = g min(q, distance of v's closest pair) of every vertex (g = bound_relaxation).

Filters: the primitives share no vertex; they belong to different bodies, or (with self_contact) to one
body and were not closer than q at rest; at least one of the four vertices is free. Buffers grow when a
detection needs more room (no pair is ever dropped); otherwise nothing is allocated per detection.
"""
import numpy as np

from .._ti import ti
from ..mesh.bodies import body_labels
from ..mesh.surface import surface_primitives
from .contact import Contact, PairKind, edge_edge, edge_edge_np, point_triangle, point_triangle_np

# Bits of the cell hash (Teschner et al. 2003's large primes); the bucket count is a power of two.
HASH_PRIMES = (73856093, 19349663, 83492791)
BUCKETS_PER_ITEM = 4


@ti.func
def cell_of(p, cell):
    """Integer grid cell (3,) of the point p for cells of edge `cell` m."""
    return ti.cast(ti.floor(p / cell), ti.i32)


@ti.func
def cell_hash(c, mask):
    """Bucket of cell c: the spatial hash of its coordinates, masked to the power-of-two bucket count."""
    return ((c[0] * HASH_PRIMES[0]) ^ (c[1] * HASH_PRIMES[1]) ^ (c[2] * HASH_PRIMES[2])) & mask


@ti.func
def item_box(positions: ti.template(), row, triangles: ti.template(), edges: ti.template(), item,
             dtype: ti.template()):
    """(lower, upper) corners of grid item `item`: triangle `item` if below T, else edge `item - T`."""
    lower = ti.Vector.zero(dtype, 3)
    upper = ti.Vector.zero(dtype, 3)
    if item < triangles.shape[0]:
        t = triangles[item]
        a, b, c = positions[row, t[0]], positions[row, t[1]], positions[row, t[2]]
        lower = ti.min(ti.min(a, b), c)
        upper = ti.max(ti.max(a, b), c)
    else:
        e = edges[item - triangles.shape[0]]
        a, b = positions[row, e[0]], positions[row, e[1]]
        lower = ti.min(a, b)
        upper = ti.max(a, b)
    return lower, upper


@ti.kernel
def cell_ranges(positions: ti.types.ndarray(), row: ti.i32, triangles: ti.types.ndarray(),
                edges: ti.types.ndarray(), q: ti.f64, cell: ti.f64, box_lo: ti.types.ndarray(),
                box_hi: ti.types.ndarray(), lo: ti.types.ndarray(), hi: ti.types.ndarray(),
                fill: ti.types.ndarray(), mask: ti.i32, dtype: ti.template()):
    """box_lo/box_hi (T + E,) corners of every item's box grown by q, lo/hi their cell ranges, and
    fill (B,) the bucket counts."""
    for h in range(fill.shape[0]):
        fill[h] = 0
    for item in range(lo.shape[0]):
        lower, upper = item_box(positions, row, triangles, edges, item, dtype)
        box_lo[item] = ti.cast(lower - q, dtype)
        box_hi[item] = ti.cast(upper + q, dtype)
        lo[item] = cell_of(box_lo[item], cell)
        hi[item] = cell_of(box_hi[item], cell)
        for i, j, k in ti.ndrange((lo[item][0], hi[item][0] + 1), (lo[item][1], hi[item][1] + 1),
                                  (lo[item][2], hi[item][2] + 1)):
            ti.atomic_add(fill[cell_hash(ti.Vector([i, j, k]), mask)], 1)


@ti.kernel
def exclusive_scan(counts: ti.types.ndarray(), starts: ti.types.ndarray(), n: ti.i32, chunk: ti.i32,
                   partial: ti.types.ndarray()) -> ti.i32:
    """starts[i] = counts[0] + ... + counts[i-1] for i <= n; returns starts[n]. In three passes of about
    sqrt(n) serial steps each: chunks of `chunk` counts summed in parallel, the chunk sums prefix-summed
    serially (partial (n / chunk + 1,) holds them), then every entry offset by its chunk's start."""
    n_chunks = (n + chunk - 1) // chunk
    for c in range(n_chunks):
        total = 0
        for i in range(c * chunk, ti.min((c + 1) * chunk, n)):
            total += counts[i]
            starts[i + 1] = total
        partial[c] = total
    running = 0
    ti.loop_config(serialize=True)
    for c in range(n_chunks):
        total = partial[c]
        partial[c] = running
        running += total
    for i in range(n):
        starts[i + 1] += partial[i // chunk]
    starts[0] = 0
    return running


@ti.func
def sort_segment(values: ti.template(), begin, end):
    """Insertion sort of values[begin:end] ascending (segments are short)."""
    for a in range(begin + 1, end):
        v = values[a]
        b = a
        while b > begin and values[b - 1] > v:
            values[b] = values[b - 1]
            b -= 1
        values[b] = v


@ti.kernel
def scatter_items(lo: ti.types.ndarray(), hi: ti.types.ndarray(), starts: ti.types.ndarray(),
                  fill: ti.types.ndarray(), entries: ti.types.ndarray(), mask: ti.i32):
    """entries[starts[h]:starts[h + 1]]: the items whose range covers a cell of bucket h, ascending."""
    for h in range(fill.shape[0]):
        fill[h] = 0
    for item in range(lo.shape[0]):
        for i, j, k in ti.ndrange((lo[item][0], hi[item][0] + 1), (lo[item][1], hi[item][1] + 1),
                                  (lo[item][2], hi[item][2] + 1)):
            h = cell_hash(ti.Vector([i, j, k]), mask)
            entries[starts[h] + ti.atomic_add(fill[h], 1)] = item
    for h in range(fill.shape[0]):
        sort_segment(entries, starts[h], starts[h + 1])


@ti.func
def is_excluded(keys: ti.template(), n_keys, key):
    """Whether the int64 key is among the sorted keys[:n_keys] (binary search)."""
    a = 0
    b = n_keys
    while a < b:
        m = (a + b) // 2
        if keys[m] < key:
            a = m + 1
        else:
            b = m
    return a < n_keys and keys[a] == key


@ti.func
def admissible(same_body, n_free, excluded: ti.template(), n_excluded, key, self_contact, rest_mode):
    """Whether two primitives that share no vertex make a pair (module docstring): same_body, n_free of
    their four vertices free, `key` their entry in the sorted rest exclusions. In rest mode: whether
    they lie in one body (to list the self-contact exclusions at rest)."""
    ok = same_body
    if rest_mode == 0:
        ok = n_free > 0
        if same_body:
            ok = ok and self_contact != 0
            if ok:
                ok = not is_excluded(excluded, n_excluded, key)
    return ok


@ti.func
def first_in_bucket(entries: ti.template(), begin, e):
    """Whether entries[e] differs from the entry before it in its (sorted) bucket, which starts at begin:
    an item whose range covers two cells of one bucket is listed twice there."""
    first = True
    if e > begin:
        first = entries[e - 1] != entries[e]
    return first


@ti.func
def first_above(entries: ti.template(), begin, end, item):
    """The first e in [begin, end) with entries[e] > item in a sorted bucket (binary search); end if none."""
    a = begin
    b = end
    while a < b:
        m = (a + b) // 2
        if entries[m] <= item:
            a = m + 1
        else:
            b = m
    return a


@ti.kernel
def find_pairs(positions: ti.types.ndarray(), row: ti.i32, vertices: ti.types.ndarray(),
               edges: ti.types.ndarray(), triangles: ti.types.ndarray(), body: ti.types.ndarray(),
               free: ti.types.ndarray(), box_lo: ti.types.ndarray(), box_hi: ti.types.ndarray(),
               lo: ti.types.ndarray(), hi: ti.types.ndarray(), starts: ti.types.ndarray(),
               entries: ti.types.ndarray(), excluded_vt: ti.types.ndarray(), n_excluded_vt: ti.i32,
               excluded_ee: ti.types.ndarray(), n_excluded_ee: ti.i32,
               query_count: ti.types.ndarray(), query_start: ti.types.ndarray(), kind: ti.types.ndarray(),
               pair: ti.types.ndarray(), primitives: ti.types.ndarray(), distance: ti.types.ndarray(),
               q: ti.f64, cell: ti.f64, mask: ti.i32, self_contact: ti.i32, rest_mode: ti.i32,
               write: ti.template(), dtype: ti.template()):
    """Queries 0..V-1 are the surface vertices (against the triangles in their cell whose grown box holds
    them), V..V+E-1 the edges (against the edges of higher index whose grown box meets theirs, in the
    lowest cell the two ranges share).
    Without `write`: query_count[query] = its number of pairs. With `write`: its pairs go to
    kind/pair/primitives (vertex, triangle or edge, edge)/distance from query_start[query] on."""
    n_vertices = vertices.shape[0]
    n_triangles = triangles.shape[0]
    n_edges = edges.shape[0]
    for query in range(n_vertices):
        found = 0
        slot = 0
        if ti.static(write):
            slot = query_start[query]
        v = vertices[query]
        p = positions[row, v]
        c = cell_of(p, cell)
        h = cell_hash(c, mask)
        for e in range(starts[h], starts[h + 1]):
            item = entries[e]
            if item >= n_triangles:         # the triangles come first in a bucket, then the edges
                break
            if first_in_bucket(entries, starts[h], e):
                t = triangles[item]
                inside = (box_lo[item] <= p).all() and (p <= box_hi[item]).all()
                if inside and v != t[0] and v != t[1] and v != t[2]:
                    n_free = free[v] + free[t[0]] + free[t[1]] + free[t[2]]
                    key = ti.cast(v, ti.i64) * n_triangles + item
                    if admissible(body[v] == body[t[0]], n_free, excluded_vt, n_excluded_vt, key,
                                  self_contact, rest_mode):
                        d, _ = point_triangle(p, positions[row, t[0]], positions[row, t[1]],
                                              positions[row, t[2]], dtype)
                        if d < q:
                            if ti.static(write):
                                kind[slot + found] = int(PairKind.VERTEX_TRIANGLE)
                                pair[slot + found] = ti.Vector([v, t[0], t[1], t[2]])
                                primitives[slot + found] = ti.Vector([v, item])
                                distance[slot + found] = d
                            found += 1
        if ti.static(not write):
            query_count[query] = found
    for a in range(n_edges):
        query = n_vertices + a
        found = 0
        slot = 0
        if ti.static(write):
            slot = query_start[query]
        ea = edges[a]
        pa0 = positions[row, ea[0]]
        pa1 = positions[row, ea[1]]
        lower = ti.min(pa0, pa1)
        upper = ti.max(pa0, pa1)
        lo_a = cell_of(lower, cell)
        hi_a = cell_of(upper, cell)
        for i, j, k in ti.ndrange((lo_a[0], hi_a[0] + 1), (lo_a[1], hi_a[1] + 1), (lo_a[2], hi_a[2] + 1)):
            c = ti.Vector([i, j, k])
            h = cell_hash(c, mask)
            for e in range(first_above(entries, starts[h], starts[h + 1], n_triangles + a), starts[h + 1]):
                item = entries[e]
                b = item - n_triangles
                if first_in_bucket(entries, starts[h], e):
                    lowest = ti.max(lo_a, lo[item])
                    eb = edges[b]
                    overlap = (lower <= box_hi[item]).all() and (box_lo[item] <= upper).all()
                    disjoint = ea[0] != eb[0] and ea[0] != eb[1] and ea[1] != eb[0] and ea[1] != eb[1]
                    if overlap and (lowest == c).all() and disjoint:
                        n_free = free[ea[0]] + free[ea[1]] + free[eb[0]] + free[eb[1]]
                        key = ti.cast(a, ti.i64) * n_edges + b
                        if admissible(body[ea[0]] == body[eb[0]], n_free, excluded_ee, n_excluded_ee, key,
                                      self_contact, rest_mode):
                            d, _ = edge_edge(pa0, pa1, positions[row, eb[0]], positions[row, eb[1]], dtype)
                            if d < q:
                                if ti.static(write):
                                    kind[slot + found] = int(PairKind.EDGE_EDGE)
                                    pair[slot + found] = ti.Vector([ea[0], ea[1], eb[0], eb[1]])
                                    primitives[slot + found] = ti.Vector([a, b])
                                    distance[slot + found] = d
                                found += 1
        if ti.static(not write):
            query_count[query] = found


@ti.kernel
def count_incidence(pair: ti.types.ndarray(), n_pairs: ti.i32, fill: ti.types.ndarray()):
    """fill[v] = number of pairs among the first n_pairs that vertex v belongs to."""
    for v in range(fill.shape[0]):
        fill[v] = 0
    for p in range(n_pairs):
        for j in ti.static(range(4)):
            ti.atomic_add(fill[pair[p][j]], 1)


@ti.kernel
def scatter_incidence(pair: ti.types.ndarray(), n_pairs: ti.i32, offsets: ti.types.ndarray(),
                      fill: ti.types.ndarray(), incidence: ti.types.ndarray(), distance: ti.types.ndarray(),
                      q: ti.f64, g: ti.f64, bound: ti.types.ndarray(), dtype: ti.template()):
    """incidence[offsets[v]:offsets[v + 1]]: the pairs of vertex v, ascending; bound[v] = g min(q, their
    least distance)."""
    for v in range(fill.shape[0]):
        fill[v] = 0
    for p in range(n_pairs):
        for j in ti.static(range(4)):
            v = pair[p][j]
            incidence[offsets[v] + ti.atomic_add(fill[v], 1)] = p
    for v in range(fill.shape[0]):
        sort_segment(incidence, offsets[v], offsets[v + 1])
        nearest = q
        for s in range(offsets[v], offsets[v + 1]):
            nearest = ti.min(nearest, distance[incidence[s]])
        bound[v] = ti.cast(g * nearest, dtype)


class ContactDetector:
    """The pairs of one mesh under one `Contact`, found again by each `detect`.

    mesh: the `TetMesh` (every body; `merge_meshes`). free: (N,) bool, the vertices the solver moves
    (pairs of fixed and kinematic vertices only are skipped). dtype: the float type of the positions.
    The self-contact exclusions are listed once, from the rest positions `mesh.vertices`.

    After `detect`, the first `n_pairs` entries of these device arrays hold the pairs:
      kind (P,) int32 `PairKind`; pair (P,) 4-vectors of vertices (p, a, b, c or a0, a1, b0, b1);
      primitives (P,) 2-vectors (vertex, triangle or edge, edge); distance (P,) in m;
    and per vertex: incidence_offsets (N + 1,), incidence (4P,) pair ids, ascending per vertex;
    bound (N,) b_v = bound_relaxation min(query_radius, distance of v's closest pair) in m.
    """

    def __init__(self, mesh, free: np.ndarray, contact: Contact, dtype=ti.f64):
        self.contact = contact
        self.dtype = dtype
        self.surface = surface_primitives(mesh.tets)
        self.bodies = body_labels(mesh.tets, mesh.n_vertices)
        n = mesh.n_vertices
        V, E, T = len(self.surface.vertices), len(self.surface.edges), len(self.surface.triangles)
        edge_lengths = np.linalg.norm(np.diff(mesh.vertices[self.surface.edges], axis=1)[:, 0], axis=1)
        self.cell = float(max(edge_lengths.mean(), 2 * contact.query_radius))   # grid cell edge in m
        buckets = 1 << int(np.ceil(np.log2(BUCKETS_PER_ITEM * (T + E))))
        self._mask = buckets - 1
        self._vertices = _device(self.surface.vertices, ti.i32)
        self._edges = ti.Vector.ndarray(2, ti.i32, E)
        self._edges.from_numpy(self.surface.edges)
        self._triangles = ti.Vector.ndarray(3, ti.i32, T)
        self._triangles.from_numpy(self.surface.triangles)
        self._body = _device(self.bodies, ti.i32)
        self._free = _device(np.asarray(free, dtype=np.int32), ti.i32)
        self._box_lo = ti.Vector.ndarray(3, dtype, T + E)
        self._box_hi = ti.Vector.ndarray(3, dtype, T + E)
        self._lo = ti.Vector.ndarray(3, ti.i32, T + E)
        self._hi = ti.Vector.ndarray(3, ti.i32, T + E)
        self._bucket_fill = ti.ndarray(ti.i32, buckets)
        self._bucket_start = ti.ndarray(ti.i32, buckets + 1)
        self._entries = ti.ndarray(ti.i32, 8 * (T + E))
        self._query_count = ti.ndarray(ti.i32, V + E)
        self._query_start = ti.ndarray(ti.i32, V + E + 1)
        self._vertex_fill = ti.ndarray(ti.i32, n)
        longest = max(buckets, V + E, n)
        self._chunk = max(64, int(np.sqrt(longest)))
        self._partial = ti.ndarray(ti.i32, longest // self._chunk + 1)
        self.incidence_offsets = ti.ndarray(ti.i32, n + 1)
        self.bound = ti.ndarray(dtype, n)
        self._allocate_pairs(max(64, V))
        self.n_pairs = 0
        empty = np.zeros(1, dtype=np.int64)
        self._excluded_vt, self._excluded_ee = _device(empty, ti.i64), _device(empty, ti.i64)
        self._n_excluded = (0, 0)
        if contact.self_contact:
            rest = ti.Vector.ndarray(3, dtype, (1, n))
            rest.from_numpy(mesh.vertices[None].astype(np.float32 if dtype == ti.f32 else np.float64))
            self._find(rest, 0, rest_mode=True)
            kind, _, primitives, _ = self.pairs()
            keys = [np.unique(primitives[kind == k, 0].astype(np.int64) * size + primitives[kind == k, 1])
                    for k, size in ((PairKind.VERTEX_TRIANGLE, T), (PairKind.EDGE_EDGE, E))]
            self._excluded_vt, self._excluded_ee = (_device(np.concatenate([k, empty]), ti.i64) for k in keys)
            self._n_excluded = (len(keys[0]), len(keys[1]))
            self.n_pairs = 0

    def _allocate_pairs(self, capacity: int):
        self._capacity = capacity
        self.kind = ti.ndarray(ti.i32, capacity)
        self.pair = ti.Vector.ndarray(4, ti.i32, capacity)
        self.primitives = ti.Vector.ndarray(2, ti.i32, capacity)
        self.distance = ti.ndarray(self.dtype, capacity)
        self.incidence = ti.ndarray(ti.i32, 4 * capacity)

    def _find(self, positions, row: int, rest_mode: bool):
        """Steps 1-3 of the module docstring: the grid, then the pairs, counted and then written."""
        q, V, E = self.contact.query_radius, len(self.surface.vertices), len(self.surface.edges)
        cell_ranges(positions, row, self._triangles, self._edges, q, self.cell, self._box_lo, self._box_hi,
                    self._lo, self._hi, self._bucket_fill, self._mask, self.dtype)
        n_entries = self._scan(self._bucket_fill, self._bucket_start, self._mask + 1)
        if n_entries > self._entries.shape[0]:
            self._entries = ti.ndarray(ti.i32, 2 * n_entries)
        scatter_items(self._lo, self._hi, self._bucket_start, self._bucket_fill, self._entries, self._mask)
        args = (self._vertices, self._edges, self._triangles, self._body, self._free, self._box_lo,
                self._box_hi, self._lo, self._hi, self._bucket_start, self._entries, self._excluded_vt,
                self._n_excluded[0], self._excluded_ee, self._n_excluded[1], self._query_count, self._query_start)
        flags = (q, self.cell, self._mask, int(self.contact.self_contact), int(rest_mode))
        find_pairs(positions, row, *args, self.kind, self.pair, self.primitives, self.distance, *flags, False,
                   self.dtype)
        self.n_pairs = self._scan(self._query_count, self._query_start, V + E)
        if self.n_pairs > self._capacity:
            self._allocate_pairs(2 * self.n_pairs)
        find_pairs(positions, row, *args, self.kind, self.pair, self.primitives, self.distance, *flags, True,
                   self.dtype)

    def _scan(self, counts, starts, n: int) -> int:
        return exclusive_scan(counts, starts, n, self._chunk, self._partial)

    def detect(self, positions, row: int = 0) -> int:
        """Find the pairs at x = positions[row] ((rows, N) ndarray of 3-vectors), their incidence lists
        and the bounds; returns the number of pairs."""
        self._find(positions, row, rest_mode=False)
        n = self.bodies.shape[0]
        count_incidence(self.pair, self.n_pairs, self._vertex_fill)
        self._scan(self._vertex_fill, self.incidence_offsets, n)
        scatter_incidence(self.pair, self.n_pairs, self.incidence_offsets, self._vertex_fill, self.incidence,
                          self.distance, self.contact.query_radius, self.contact.bound_relaxation, self.bound,
                          self.dtype)
        return self.n_pairs

    def pairs(self):
        """(kind (P,) int32, vertices (P, 4) int32, primitives (P, 2) int32, distance (P,)) of the last
        detection, as numpy arrays."""
        P = self.n_pairs
        return (self.kind.to_numpy()[:P], self.pair.to_numpy()[:P], self.primitives.to_numpy()[:P],
                self.distance.to_numpy()[:P])

    def vertex_pairs(self):
        """(offsets (N + 1,), pair ids (4P,)) of the last detection: vertex v's pairs are
        ids[offsets[v]:offsets[v + 1]]."""
        offsets = self.incidence_offsets.to_numpy()
        return offsets, self.incidence.to_numpy()[:offsets[-1]]


def _device(values: np.ndarray, dtype):
    """A 1-D ti.ndarray holding `values`."""
    array = ti.ndarray(dtype, len(values))
    array.from_numpy(np.ascontiguousarray(values))
    return array


# ---------------------------------------------------------------------------------------------
# Numpy twin, for the Newton reference: the same pairs, found with scipy's k-d tree instead of the grid.
# ---------------------------------------------------------------------------------------------
def find_pairs_np(x: np.ndarray, surface, bodies: np.ndarray, free: np.ndarray, contact: Contact,
                  excluded, rest_mode: bool = False):
    """The pairs at x (N, 3) as (kind (P,) int32, vertices (P, 4) int32, primitives (P, 2) int32,
    distance (P,)), the same set as `ContactDetector` finds, ordered by query, then partner.

    surface: `SurfacePrimitives`; bodies (N,) int; free (N,) bool; excluded: the (vertex-triangle keys,
    edge-edge keys) of `rest_exclusions_np`. rest_mode: list the same-body pairs only, free or not,
    ignoring `excluded` (how those keys are made).
    """
    from scipy.spatial import cKDTree

    q = contact.query_radius
    V, E, T = surface.vertices, surface.edges, surface.triangles
    found = []
    # vertex-triangle: triangles whose centroid is within q + (largest centroid-to-corner distance)
    centroid = x[T].mean(axis=1)
    reach = np.linalg.norm(x[T] - centroid[:, None], axis=2).max()
    near = cKDTree(centroid).query_ball_point(x[V], q + reach)
    query = np.repeat(np.arange(len(V)), [len(n) for n in near])
    tri = np.concatenate([np.asarray(n, dtype=np.int64) for n in near] + [np.zeros(0, np.int64)])
    left, right = V[query][:, None], T[tri]
    keys = V[query].astype(np.int64) * len(T) + tri
    found.append((PairKind.VERTEX_TRIANGLE, query, np.stack([V[query], tri], 1), left, right, keys,
                  lambda y: point_triangle_np(y[left[:, 0]], y[right[:, 0]], y[right[:, 1]], y[right[:, 2]])[0]))
    # edge-edge: midpoints within q + (longest edge)
    mid = x[E].mean(axis=1)
    longest = np.linalg.norm(x[E[:, 1]] - x[E[:, 0]], axis=1).max()
    ab = cKDTree(mid).query_pairs(q + longest, output_type="ndarray").astype(np.int64).reshape(-1, 2)
    ab = np.sort(ab, axis=1)
    ea, eb = E[ab[:, 0]], E[ab[:, 1]]
    found.append((PairKind.EDGE_EDGE, len(V) + ab[:, 0], ab, ea, eb, ab[:, 0] * len(E) + ab[:, 1],
                  lambda y: edge_edge_np(y[ea[:, 0]], y[ea[:, 1]], y[eb[:, 0]], y[eb[:, 1]])[0]))
    parts = []
    for k, (kind, query, primitives, left, right, keys, dist) in enumerate(found):
        disjoint = ~(left[:, :, None] == right[:, None, :]).any(axis=(1, 2))
        same = bodies[left[:, 0]] == bodies[right[:, 0]]
        if rest_mode:
            keep = disjoint & same
        else:
            allowed = ~same | (contact.self_contact & ~np.isin(keys, excluded[k]))
            keep = disjoint & allowed & (free[left].any(axis=1) | free[right].any(axis=1))
        d = dist(x)
        keep &= d < q
        vertices = np.concatenate([left, right], axis=1)
        order = np.lexsort((primitives[keep, 1], query[keep]))
        parts.append((np.full(keep.sum(), int(kind), np.int32), vertices[keep][order].astype(np.int32),
                      primitives[keep][order].astype(np.int32), d[keep][order]))
    return tuple(np.concatenate(arrays) for arrays in zip(*parts))


def rest_exclusions_np(rest: np.ndarray, surface, bodies: np.ndarray, contact: Contact):
    """(vertex-triangle keys, edge-edge keys), sorted int64: the same-body pairs closer than query_radius
    at the rest positions rest (N, 3), keyed vertex * T + triangle and edge_a * E + edge_b."""
    kind, _, primitives, _ = find_pairs_np(rest, surface, bodies, np.ones(len(rest), bool), contact, None,
                                           rest_mode=True)
    sizes = (len(surface.triangles), len(surface.edges))
    return tuple(np.unique(primitives[kind == k, 0].astype(np.int64) * size + primitives[kind == k, 1])
                 for k, size in zip(PairKind, sizes))


def vertex_bounds_np(n_vertices: int, vertices: np.ndarray, distance: np.ndarray, contact: Contact) -> np.ndarray:
    """(N,) b_v = bound_relaxation min(query_radius, distance of v's closest pair) in m, from the pairs'
    vertices (P, 4) and distances (P,): how far each vertex may move before the next detection."""
    nearest = np.full(n_vertices, contact.query_radius)
    np.minimum.at(nearest, np.asarray(vertices).ravel(), np.repeat(distance, 4))
    return contact.bound_relaxation * nearest
