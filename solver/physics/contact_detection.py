"""Finding the pairs of contact (issue 17): a hashed uniform grid built by Taichi kernels at each detection,
the exact distance of every candidate, per-vertex incidence lists and OGC's conservative bounds.

One detection is two kernel launches (their top-level loops run one after the other on the device):
  0. the bodies that can have no pair are left out (`active_bodies`): a body whose box, grown by q, meets
     no other body's box has no pair with another body, and one that has moved almost rigidly since rest
     has no self pair (below). Their primitives go into no grid and make no query;
  1. every triangle and edge of the other bodies gets its box, as a range of grid cells;
  2. the grid: count the entries of each hash bucket, prefix sum, scatter the items into their
     buckets, sort each bucket (so that everything after is deterministic), and copy each item's box
     next to its entries, so that a query reads the boxes of a bucket in a row;
  3. every surface vertex looks up the triangles in the cells within q (the query radius) of it, and
     every edge the edges of higher index in the cells of its box grown by q; an entry whose box
     meets the query's grown one is a candidate, reported once, in the lowest cell the two ranges share
     (first in each sorted bucket). A candidate that passes the filters below and lies closer than q is a pair: one
     pass notes each pair with its query and its rank there, a prefix sum of the counts per query places
     them in order of query and rank (the same order on every run, whatever the threads did). A query
     of a body that has no self pair to seek skips its own body's items in each bucket with one binary
     search, as they cannot be its partners (nor does a query of a body that seeks them whose own
     primitive cannot have one, below): where a body's triangles (or edges) are contiguous in the
     grid's numbering, as `merge_meshes` makes them, a sorted bucket holds them as one run
     (`own_item_ranges`; nothing is skipped where bodies interleave);
  4. per-vertex incidence lists (CSR: offsets, pair ids ascending), so that a vertex gathers its terms
     without atomics;
  5. the bound b_v = g min(q, distance of v's closest pair) of every vertex (g = bound_relaxation).

Filters: the primitives share no vertex; they belong to different bodies, or (with self_contact) to one
body and were not closer than q at rest; at least one of the four vertices is free.

Why a body that moved almost rigidly has no self pair: let (R, c) be a rotation and translation and
delta = max |x_v - c - R (X_v - C)| over its surface vertices v (X: rest positions, C: their mean). A
rigid motion keeps every distance, and moving each vertex by at most delta moves each point of a triangle
or edge (a convex combination of its vertices) by at most delta, so two primitives D apart at rest are
at least D - 2 delta apart now. The same-body pairs that are not excluded were D >= q apart at rest; if
the closest of them (D_min, listed once at rest, capped at REST_MARGIN q) has D_min - 2 delta > q, none is
within q. Any rotation R keeps this true; `best_rotation` takes one near the best fit. The same bound holds
per query (`may_have_self_pair`): a query primitive Q (a surface vertex, or an edge against those of
higher index) whose vertices lie within delta_Q of their rigid places is at least D - delta_Q - delta_P
from a same-body partner P that was D apart at rest, delta_P <= delta the largest deviation of P's
vertices. Its partners that are not excluded and were closer than REST_MARGIN q at rest are listed once,
by rest distance (the least is D_min(Q)); the others stay beyond q while delta_Q + delta < q. Where
none can come within q, its query skips its own body's items even though the body seeks self pairs. In
a settled pile of soft balls, where the bottom ones are squashed by millimetres, most queries are far
from where their body bends: of the 23,160 queries of 27 settled fine balls (`benchmarks/contact.py`),
3,440 seek self pairs, where the body's bound alone searched all of them. Buffers grow when a
detection needs more room (no pair is ever dropped: the launch is repeated); otherwise nothing is
allocated per detection.
"""
import numpy as np

from .._ti import initialised_arch, ti
from ..mesh.bodies import body_labels
from ..mesh.surface import surface_primitives
from .contact import Contact, PairKind, edge_edge, edge_edge_np, point_triangle, point_triangle_np

# Bits of the cell hash (Teschner et al. 2003's large primes); the bucket count is a power of two.
HASH_PRIMES = (73856093, 19349663, 83492791)
BUCKETS_PER_ITEM = 4
CELL_PER_EDGE = 1.25     # grid cell edge / (mean surface edge or 2 q, the larger): fastest of 0.75-2 measured
REST_MARGIN = 2.0        # the same-body pairs closer than this x q at rest are listed once, for D_min
POLAR_ITERATIONS = 8     # `best_rotation`: Newton steps towards the polar factor (any rotation is safe)
SEARCH_OTHERS, SEARCH_SELF = 1, 2    # `active_bodies` flags: a body may have pairs with others / with itself
RIGID_SLACK = 1e-3       # x q: round-off allowance when `active_bodies` compares 2 delta with D_min - q
# Below this many tets a CPU detection runs every loop on one thread, as the sweep does below
# vertex_solve.SERIAL_SWEEP_TETS: each parallel loop costs tens of us to start and end on the CPU backend,
# more than its work on a small mesh (2 shared cores: 0.75x the time of the parallel loops on a pile of one
# ball, 0.86x on 64 cubes, 5,376 tets; 0.93x on 64 balls, 9,600 tets, but 1.14x on 24,576 touching tets).
# All but the queries' loop, which holds most of a pile's work: it runs on one thread only below
# SERIAL_DETECT_QUERIES surface vertices and edges (`ContactDetector.detect` timed on the settled piles of
# benchmarks/contact.py, 2 shared cores, against every loop on one thread: 1.2x the time with 580 queries,
# 0.91x with 2,042, 0.66x with 8,256, 0.63x with 10,090).
SERIAL_DETECT_TETS = 6000
SERIAL_DETECT_QUERIES = 1000


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


@ti.func
def best_rotation(A):
    """An orthogonal 3x3 matrix near the rotation part of A (3x3, the cross-covariance of current and rest
    positions): a few Newton steps R <- (R + R^-T) / 2 towards A's polar factor, then Gram-Schmidt, so that
    R is orthogonal whatever A was (the identity if A is singular). Only orthogonality matters for
    `active_bodies`' bound; a better fit only leaves out more bodies."""
    R = A / (A.norm() + 1e-300)
    for _ in range(POLAR_ITERATIONS):
        if ti.abs(R.determinant()) > 1e-12:
            R = 0.5 * (R + R.inverse().transpose())
    c0 = ti.Vector([R[0, 0], R[1, 0], R[2, 0]])
    c1 = ti.Vector([R[0, 1], R[1, 1], R[2, 1]])
    c2 = ti.Vector([R[0, 2], R[1, 2], R[2, 2]])
    c0 = c0 / (c0.norm() + 1e-300)
    c1 = c1 - c0.dot(c1) * c0
    c1 = c1 / (c1.norm() + 1e-300)
    c2 = c2 - c0.dot(c2) * c0 - c1.dot(c2) * c1
    c2 = c2 / (c2.norm() + 1e-300)
    Q = ti.Matrix.cols([c0, c1, c2])
    if (Q.transpose() @ Q - ti.Matrix.identity(ti.f64, 3)).norm() > 1e-9:
        Q = ti.Matrix.identity(ti.f64, 3)
    return Q


@ti.kernel
def active_bodies(positions: ti.types.ndarray(), row: ti.i32, vertices: ti.types.ndarray(),
                  body: ti.types.ndarray(), rest: ti.types.ndarray(), rest_centroid: ti.types.ndarray(),
                  count: ti.types.ndarray(), has_free: ti.types.ndarray(), margin: ti.types.ndarray(),
                  lo: ti.types.ndarray(), hi: ti.types.ndarray(), centroid: ti.types.ndarray(),
                  rotation: ti.types.ndarray(), deviation: ti.types.ndarray(), vertex_deviation: ti.types.ndarray(),
                  active: ti.types.ndarray(), q: ti.f64, self_contact: ti.i32, serial: ti.template()) -> ti.i32:
    """Step 0 of the module docstring: active[b] = the pairs body b may have at x = positions[row], as flags
    SEARCH_OTHERS (its box grown by q meets another body's; one of them has a free vertex) and SEARCH_SELF
    (with self contact: it has a free vertex and moved too far from rigid); returns how many bodies have
    any. vertices (V,) the surface vertices, rest (V,) their rest positions, and per body (B,):
    rest_centroid C, count its surface vertices, has_free whether it has a free vertex, margin D_min - q
    in m; lo/hi (the boxes), centroid and rotation (3x3) are scratch; on return deviation (B,) holds each
    body's delta and vertex_deviation (N,) each surface vertex's distance from its rigid place, in m (read
    by `detect_pairs`). In float64 whatever the positions' type."""
    n_bodies = active.shape[0]
    ti.loop_config(serialize=serial)
    for b in range(n_bodies):
        lo[b] = ti.Vector([1e300, 1e300, 1e300])
        hi[b] = ti.Vector([-1e300, -1e300, -1e300])
        centroid[b] = ti.Vector.zero(ti.f64, 3)
        rotation[b] = ti.Matrix.zero(ti.f64, 3, 3)
        deviation[b] = 0.0
    ti.loop_config(serialize=serial)
    for k in range(vertices.shape[0]):
        b = body[vertices[k]]
        p = ti.cast(positions[row, vertices[k]], ti.f64)
        for j in ti.static(range(3)):
            ti.atomic_min(lo[b][j], p[j])
            ti.atomic_max(hi[b][j], p[j])
            ti.atomic_add(centroid[b][j], p[j] / count[b])
        rotation[b] += p.outer_product(rest[k] - rest_centroid[b])   # sum of x (X - C)^T: c drops out
    ti.loop_config(serialize=serial)
    for b in range(n_bodies):
        rotation[b] = best_rotation(rotation[b])
    ti.loop_config(serialize=serial)
    for k in range(vertices.shape[0]):
        b = body[vertices[k]]
        p = ti.cast(positions[row, vertices[k]], ti.f64)
        off = (p - centroid[b] - rotation[b] @ (rest[k] - rest_centroid[b])).norm()
        vertex_deviation[vertices[k]] = off
        ti.atomic_max(deviation[b], off)
    n_active = 0
    ti.loop_config(serialize=serial)
    for b in range(n_bodies):
        rigid = 2 * deviation[b] < margin[b] - RIGID_SLACK * q       # false for NaN: then b is searched
        search = 0
        if self_contact != 0 and has_free[b] != 0 and not rigid:
            search = SEARCH_SELF
        for c in range(n_bodies):
            if c != b and (has_free[b] != 0 or has_free[c] != 0):
                if (lo[b] - q <= hi[c]).all() and (lo[c] <= hi[b] + q).all():
                    search |= SEARCH_OTHERS
        active[b] = search
        if search != 0:
            n_active += 1
    return n_active


@ti.func
def scan(counts: ti.template(), starts: ti.template(), n, chunk, partial: ti.template(), serial: ti.template()):
    """starts[i] = counts[0] + ... + counts[i-1] for i <= n. serial: in one serial loop (on the CPU, where
    starting a parallel loop costs more than the sum). Else in three top-level loops of about sqrt(n) serial
    steps each: chunks of `chunk` counts summed in parallel, the chunk sums prefix-summed serially
    (partial (n / chunk + 1,) holds them), then every entry offset by its chunk's start."""
    if ti.static(serial):
        starts[0] = 0
        ti.loop_config(serialize=True)
        for i in range(n):
            starts[i + 1] = starts[i] + counts[i]
    else:
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


@ti.kernel
def exclusive_scan(counts: ti.types.ndarray(), starts: ti.types.ndarray(), n: ti.i32, chunk: ti.i32,
                   partial: ti.types.ndarray(), serial: ti.template()) -> ti.i32:
    """`scan` on its own; returns starts[n]."""
    scan(counts, starts, n, chunk, partial, serial)
    return starts[n]


@ti.func
def sort_segment(values: ti.template(), begin, end):
    """Insertion sort of values[begin:end] ascending: the scatters fill each segment from its front, in the
    order their loop ran, so that only what the threads interleaved is moved (filled from the back, a
    bucket of a few hundred items in a pile was sorted from descending order: 2.8x the time)."""
    for a in range(begin + 1, end):
        v = values[a]
        b = a
        while b > begin and values[b - 1] > v:
            values[b] = values[b - 1]
            b -= 1
        values[b] = v


@ti.func
def is_excluded(keys: ti.template(), begin, end, key):
    """Whether the int64 key is among the sorted keys[begin:end] (binary search)."""
    a = begin
    b = end
    while a < b:
        m = (a + b) // 2
        if keys[m] < key:
            a = m + 1
        else:
            b = m
    return a < end and keys[a] == key


@ti.func
def admissible(same_body, search, excluded: ti.template(), within, key, rest_mode):
    """Whether two primitives that share no vertex, not both still, make a pair (module docstring):
    same_body, search the pairs the query seeks (`active_bodies` flags, less SEARCH_SELF where its own
    primitive cannot have a self pair), `key` their entry in the sorted rest exclusions, looked up (only
    for a query that may have self pairs) in within = [begin, end) of
    `excluded`, the keys of the query's own primitive (a short run of the sorted keys, read in cache,
    where a search of all of them would miss it at each step). In rest mode: whether they lie in one
    body (to list the self-contact exclusions at rest)."""
    ok = same_body
    if rest_mode == 0:
        ok = True
        if same_body:
            ok = False
            if search & SEARCH_SELF:
                ok = not is_excluded(excluded, within[0], within[1], key)
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
def new_candidate(entries: ti.template(), entry_box: ti.template(), moving: ti.template(), begin, e, lower, upper,
                  c, cell, still):
    """Whether the item entries[e], in cell c's bucket (which starts at begin), is a candidate of the query
    whose box (grown by q) is [lower, upper], met for the first time: the two boxes overlap (entry_box[0, e]
    and entry_box[1, e], the item's box stored with the entry, read in bucket order), c is the lowest cell
    of both cell ranges (the cell of max(lower, item's lower corner): floor is monotonic) and the entry is
    the item's first in the bucket; for a still query, only items with a free vertex (moving). The box test
    first: most entries fail it."""
    new = False
    item_lo = entry_box[0, e]
    if (lower <= entry_box[1, e]).all() and (item_lo <= upper).all():
        if (cell_of(ti.max(lower, item_lo), cell) == c).all():
            if first_in_bucket(entries, begin, e):
                new = True
                if still:
                    new = moving[entries[e]] != 0
    return new


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


@ti.func
def record(counter: ti.template(), found: ti.template(), found_distance: ti.template(), query, rank, partner, d):
    """Note the pair (query, partner) at distance d, the rank-th of its query, in the next free row
    (counter[0], then one up) of found ((C,) 3-vectors: query, rank, partner) and found_distance (C,); rows past C
    are counted, not kept."""
    s = ti.atomic_add(counter[0], 1)
    if s < found.shape[0]:
        found[s] = ti.Vector([query, rank, partner])
        found_distance[s] = d


@ti.func
def may_have_self_pair(query, moved, spread, partner_start: ti.template(), partner_item: ti.template(),
                       partner_distance: ti.template(), triangles: ti.template(), edges: ti.template(),
                       vertex_deviation: ti.template(), q):
    """Whether query Q of a body that seeks self pairs may have one (module docstring): its vertices lie
    within moved (delta_Q, m) of their rigid places, the body's within spread (delta). None while
    delta_Q + delta < q (no partner farther than REST_MARGIN q at rest can come within q) and each partner
    listed at rest (partner_start (V + E + 1,), then partner_item the grid items and partner_distance their
    rest distances D, ascending per query) has D - delta_Q - delta_P > q, delta_P its own vertices' largest
    deviation; the ascending order ends the walk at the first partner even delta could not bring within q
    (at once where D_min(Q) - delta_Q - delta > q). True for NaN."""
    slack = RIGID_SLACK * q
    reach = moved + spread
    result = True
    if reach < (REST_MARGIN - 1) * q - slack:
        result = False
        s = partner_start[query]
        end = partner_start[query + 1]
        while s < end and partner_distance[s] - q - reach < slack:      # (a sentinel ends partner_distance)
            item = partner_item[s]
            partner_moved = ti.cast(0.0, ti.f64)
            if item < triangles.shape[0]:
                t = triangles[item]
                partner_moved = ti.max(vertex_deviation[t[0]], vertex_deviation[t[1]], vertex_deviation[t[2]])
            else:
                e = edges[item - triangles.shape[0]]
                partner_moved = ti.max(vertex_deviation[e[0]], vertex_deviation[e[1]])
            if not partner_distance[s] - q - moved - partner_moved >= slack:
                result = True
                break
            s += 1
    return result


@ti.kernel
def detect_pairs(positions: ti.types.ndarray(), row: ti.i32, vertices: ti.types.ndarray(),
                 edges: ti.types.ndarray(), triangles: ti.types.ndarray(), body: ti.types.ndarray(),
                 active: ti.types.ndarray(), deviation: ti.types.ndarray(), vertex_deviation: ti.types.ndarray(),
                 partner_start: ti.types.ndarray(), partner_item: ti.types.ndarray(),
                 partner_distance: ti.types.ndarray(), own_items: ti.types.ndarray(), free: ti.types.ndarray(),
                 moving: ti.types.ndarray(), excluded_vt: ti.types.ndarray(), excluded_ee: ti.types.ndarray(),
                 excluded_range: ti.types.ndarray(),
                 box: ti.types.ndarray(), lo: ti.types.ndarray(), hi: ti.types.ndarray(),
                 bucket_fill: ti.types.ndarray(), bucket_start: ti.types.ndarray(), entries: ti.types.ndarray(),
                 entry_box: ti.types.ndarray(),
                 partial: ti.types.ndarray(), counter: ti.types.ndarray(), found: ti.types.ndarray(),
                 found_distance: ti.types.ndarray(), query_count: ti.types.ndarray(),
                 query_start: ti.types.ndarray(), vertex_fill: ti.types.ndarray(), kind: ti.types.ndarray(),
                 pair: ti.types.ndarray(), primitives: ti.types.ndarray(), distance: ti.types.ndarray(),
                 offsets: ti.types.ndarray(), incidence: ti.types.ndarray(), bound: ti.types.ndarray(),
                 q: ti.f64, g: ti.f64, cell: ti.f64, mask: ti.i32, chunk: ti.i32,
                 rest_mode: ti.i32, serial: ti.template(), one_thread: ti.template(), serial_queries: ti.template(),
                 dtype: ti.template()) -> ti.i32:
    """Steps 1-5 of the module docstring in one launch, for the bodies b with active[b] != 0 (step 0;
    every body in rest mode). own_items (B,) 4-vectors: [lo, hi) of each body's triangles, then of its
    edges, as items (`own_item_ranges`), which its queries skip unless it seeks self pairs and the query's
    own primitive may have one (`may_have_self_pair`: deviation (B,) and vertex_deviation (N,) from
    `active_bodies`, partner_start, partner_item, partner_distance; not read in rest mode). excluded_vt,
    excluded_ee: the sorted keys of the rest exclusions; excluded_range (V + E,) 2-vectors: [begin, end) of
    each query's own keys there (`admissible`).
    Grid: box (2, T + E) the items' boxes (triangles, then edges; lower corners in row 0, upper in row 1),
    lo/hi their cell ranges, bucket_fill (B,) zero on entry and exit, bucket_start (B + 1,) and entries the
    items of each bucket, ascending, with entry_box (2, len(entries)) their boxes in the same order (the
    narrow phase reads a bucket's boxes one after the other, not each item's from box); moving (T + E,)
    whether an item has a free vertex. Pairs: each query (the V surface vertices, then the E edges) notes
    its pairs with their rank in found (3-vectors: query, rank, partner) and found_distance (capacity C;
    counter (2,) counts them, and the queries that sought self pairs), then they are written to
    kind/pair/primitives/distance (C,) at query_start[query] + rank and listed per vertex in offsets
    (N + 1,)/incidence (4C,) (vertex_fill (N,) zero on entry and exit). serial: prefix sums in one serial
    loop (CPU); one_thread: every other loop on one thread (small meshes on the CPU, `SERIAL_DETECT_TETS`)
    and serial_queries the queries too (`SERIAL_DETECT_QUERIES`). Returns the number of pairs; if they exceed C,
    nothing past `found` is written; if the grid's entries exceed their buffer, -(entries needed) and
    no pair is sought."""
    n_vertices = vertices.shape[0]
    n_triangles = triangles.shape[0]
    n_edges = edges.shape[0]
    n_items = lo.shape[0]
    n_buckets = bucket_fill.shape[0]
    n = vertex_fill.shape[0]
    ti.loop_config(serialize=one_thread)
    for item in range(n_items):
        first = triangles[item][0] if item < n_triangles else edges[item - n_triangles][0]
        lo[item] = ti.Vector([0, 0, 0])
        hi[item] = ti.Vector([-1, -1, -1])        # no cell: an item of a body left out
        if rest_mode != 0 or active[body[first]] != 0:
            lower, upper = item_box(positions, row, triangles, edges, item, dtype)
            box[0, item] = lower
            box[1, item] = upper
            lo[item] = cell_of(lower, cell)
            hi[item] = cell_of(upper, cell)
        for i, j, k in ti.ndrange((lo[item][0], hi[item][0] + 1), (lo[item][1], hi[item][1] + 1),
                                  (lo[item][2], hi[item][2] + 1)):
            ti.atomic_add(bucket_fill[cell_hash(ti.Vector([i, j, k]), mask)], 1)
    scan(bucket_fill, bucket_start, n_buckets, chunk, partial, serial)
    n_entries = bucket_start[n_buckets]
    fits = n_entries <= entries.shape[0]
    counter[0] = 0
    counter[1] = 0
    ti.loop_config(serialize=one_thread)
    for item in range(n_items):                 # counts back down to zero, ready for the next detection
        for i, j, k in ti.ndrange((lo[item][0], hi[item][0] + 1), (lo[item][1], hi[item][1] + 1),
                                  (lo[item][2], hi[item][2] + 1)):
            h = cell_hash(ti.Vector([i, j, k]), mask)
            e = bucket_start[h + 1] - ti.atomic_sub(bucket_fill[h], 1)     # from the front: `sort_segment`
            if fits:
                entries[e] = item
    ti.loop_config(serialize=one_thread)
    for h in range(n_buckets if fits else 0):
        sort_segment(entries, bucket_start[h], bucket_start[h + 1])
    ti.loop_config(serialize=one_thread)
    for e in range(n_entries if fits else 0):
        entry_box[0, e] = box[0, entries[e]]
        entry_box[1, e] = box[1, entries[e]]
    ti.loop_config(serialize=serial_queries)
    for query in range(n_vertices + n_edges if fits else 0):
        rank = 0
        searched = True
        flags = 0                               # the pairs this query seeks (`active_bodies` flags)
        own = ti.Vector([0, 0, 0, 0])           # the item ranges this query skips: none
        if rest_mode == 0:
            first = vertices[query] if query < n_vertices else edges[query - n_vertices][0]
            flags = active[body[first]]
            if flags & SEARCH_SELF:             # its own primitive may be too far from any partner
                moved = vertex_deviation[first]
                if query >= n_vertices:
                    moved = ti.max(moved, vertex_deviation[edges[query - n_vertices][1]])
                if may_have_self_pair(query, moved, deviation[body[first]], partner_start, partner_item,
                                      partner_distance, triangles, edges, vertex_deviation, q):
                    ti.atomic_add(counter[1], 1)
                else:
                    flags -= SEARCH_SELF
            searched = flags != 0
            if not flags & SEARCH_SELF:
                own = own_items[body[first]]
        if searched and query < n_vertices:     # a surface vertex against the triangles
            v = vertices[query]
            still = free[v] == 0 and rest_mode == 0
            p = positions[row, v]
            p_lo = p - q
            p_hi = p + q
            lo_p = cell_of(p_lo, cell)
            hi_p = cell_of(p_hi, cell)
            for i, j, k in ti.ndrange((lo_p[0], hi_p[0] + 1), (lo_p[1], hi_p[1] + 1), (lo_p[2], hi_p[2] + 1)):
                c = ti.Vector([i, j, k])
                h = cell_hash(c, mask)
                begin, end = bucket_start[h], bucket_start[h + 1]
                e = begin
                while e < end:
                    item = entries[e]
                    if item >= n_triangles:     # the triangles come first in a bucket, then the edges
                        break
                    if own[0] <= item < own[1]:         # its own body's run: no partner there
                        e = first_above(entries, e, end, own[1] - 1)
                        continue
                    if new_candidate(entries, entry_box, moving, begin, e, p_lo, p_hi, c, cell, still):
                        t = triangles[item]
                        if v != t[0] and v != t[1] and v != t[2]:
                            key = ti.cast(v, ti.i64) * n_triangles + item
                            if admissible(body[v] == body[t[0]], flags, excluded_vt, excluded_range[query],
                                          key, rest_mode):
                                d, _ = point_triangle(p, positions[row, t[0]], positions[row, t[1]],
                                                      positions[row, t[2]], dtype)
                                if d < q:
                                    record(counter, found, found_distance,
                                           query, rank, item, d)
                                    rank += 1
                    e += 1
        elif searched:                          # an edge against the edges of higher index
            a = query - n_vertices
            ea = edges[a]
            still = moving[n_triangles + a] == 0 and rest_mode == 0
            pa0 = positions[row, ea[0]]
            pa1 = positions[row, ea[1]]
            lower = ti.min(pa0, pa1) - q
            upper = ti.max(pa0, pa1) + q
            lo_a = cell_of(lower, cell)
            hi_a = cell_of(upper, cell)
            for i, j, k in ti.ndrange((lo_a[0], hi_a[0] + 1), (lo_a[1], hi_a[1] + 1), (lo_a[2], hi_a[2] + 1)):
                c = ti.Vector([i, j, k])
                h = cell_hash(c, mask)
                begin, end = bucket_start[h], bucket_start[h + 1]
                for e in range(first_above(entries, begin, end, ti.max(n_triangles + a, own[3] - 1)), end):
                    item = entries[e]
                    b = item - n_triangles
                    if new_candidate(entries, entry_box, moving, begin, e, lower, upper, c, cell, still):
                        eb = edges[b]
                        if ea[0] != eb[0] and ea[0] != eb[1] and ea[1] != eb[0] and ea[1] != eb[1]:
                            key = ti.cast(a, ti.i64) * n_edges + b
                            if admissible(body[ea[0]] == body[eb[0]], flags, excluded_ee,
                                          excluded_range[query], key, rest_mode):
                                d, _ = edge_edge(pa0, pa1, positions[row, eb[0]], positions[row, eb[1]], dtype)
                                if d < q:
                                    record(counter, found, found_distance,
                                           query, rank, b, d)
                                    rank += 1
        query_count[query] = rank
    n_pairs = counter[0]
    placed = fits and n_pairs <= found.shape[0]
    scan(query_count, query_start, n_vertices + n_edges, chunk, partial, serial)
    ti.loop_config(serialize=one_thread)
    for s in range(n_pairs if placed else 0):
        query, rank, partner = found[s][0], found[s][1], found[s][2]
        slot = query_start[query] + rank
        if query < n_vertices:
            v = vertices[query]
            t = triangles[partner]
            kind[slot] = int(PairKind.VERTEX_TRIANGLE)
            pair[slot] = ti.Vector([v, t[0], t[1], t[2]])
            primitives[slot] = ti.Vector([v, partner])
        else:
            ea = edges[query - n_vertices]
            eb = edges[partner]
            kind[slot] = int(PairKind.EDGE_EDGE)
            pair[slot] = ti.Vector([ea[0], ea[1], eb[0], eb[1]])
            primitives[slot] = ti.Vector([query - n_vertices, partner])
        distance[slot] = found_distance[s]
        for j in ti.static(range(4)):
            ti.atomic_add(vertex_fill[pair[slot][j]], 1)
    scan(vertex_fill, offsets, n, chunk, partial, serial)
    ti.loop_config(serialize=one_thread)
    for p in range(n_pairs if placed else 0):   # counts back down to zero, ready for the next detection
        for j in ti.static(range(4)):
            v = pair[p][j]
            incidence[offsets[v + 1] - ti.atomic_sub(vertex_fill[v], 1)] = p   # from the front
    ti.loop_config(serialize=one_thread)
    for v in range(n):
        sort_segment(incidence, offsets[v], offsets[v + 1])
        nearest = q
        for s in range(offsets[v], offsets[v + 1]):
            nearest = ti.min(nearest, distance[incidence[s]])
        bound[v] = ti.cast(g * nearest, dtype)
    return n_pairs if fits else -n_entries


@ti.kernel
def no_pairs(offsets: ti.types.ndarray(), bound: ti.types.ndarray(), b: ti.f64, dtype: ti.template()):
    """The incidence lists (offsets (N + 1,)) and bounds (N,) of a detection without pairs: empty lists,
    and every bound b = g q in m."""
    for v in range(bound.shape[0]):
        offsets[v + 1] = 0
        bound[v] = ti.cast(b, dtype)
    offsets[0] = 0


class ContactDetector:
    """The pairs of one mesh under one `Contact`, found again by each `detect`.

    mesh: the `TetMesh` (every body; `merge_meshes`). free: (N,) bool, the vertices the solver moves
    (pairs of fixed and kinematic vertices only are skipped). dtype: the float type of the positions.
    The self-contact exclusions are listed once, from the rest positions `mesh.vertices`.

    After `detect`, the first `n_pairs` entries of these device arrays hold the pairs:
      kind (P,) int32 `PairKind`; pair (P,) 4-vectors of vertices (p, a, b, c or a0, a1, b0, b1);
      primitives (P,) 2-vectors (vertex, triangle or edge, edge); distance (P,) in m;
    and per vertex: incidence_offsets (N + 1,), incidence (4P,) pair ids, ascending per vertex;
    bound (N,) b_v = bound_relaxation min(query_radius, distance of v's closest pair) in m;
    and per body (B,): active, the `active_bodies` flags of the last detection (0: not searched), and
    active_count, the bodies searched.
    """

    def __init__(self, mesh, free: np.ndarray, contact: Contact, dtype=ti.f64):
        self.contact = contact
        self.dtype = dtype
        self.surface = surface_primitives(mesh.tets)
        self.bodies = body_labels(mesh.tets, mesh.n_vertices)
        n = mesh.n_vertices
        V, E, T = len(self.surface.vertices), len(self.surface.edges), len(self.surface.triangles)
        edge_lengths = np.linalg.norm(np.diff(mesh.vertices[self.surface.edges], axis=1)[:, 0], axis=1)
        self.cell = CELL_PER_EDGE * float(max(edge_lengths.mean(), 2 * contact.query_radius))  # m
        buckets = 1 << int(np.ceil(np.log2(BUCKETS_PER_ITEM * (T + E))))
        self._mask = buckets - 1
        self._vertices = _device(self.surface.vertices, ti.i32)
        self._edges = ti.Vector.ndarray(2, ti.i32, E)
        self._edges.from_numpy(self.surface.edges)
        self._triangles = ti.Vector.ndarray(3, ti.i32, T)
        self._triangles.from_numpy(self.surface.triangles)
        self._body = _device(self.bodies, ti.i32)
        own = own_item_ranges(self.bodies, self.surface)
        self._own_items = ti.Vector.ndarray(4, ti.i32, len(own))
        self._own_items.from_numpy(own)
        free = np.asarray(free, dtype=bool)
        self._free = _device(free.astype(np.int32), ti.i32)
        self._moving = _device(np.concatenate([free[self.surface.triangles].any(axis=1),
                                               free[self.surface.edges].any(axis=1)]).astype(np.int32), ti.i32)
        self._box = ti.Vector.ndarray(3, dtype, (2, T + E))
        self._lo = ti.Vector.ndarray(3, ti.i32, T + E)
        self._hi = ti.Vector.ndarray(3, ti.i32, T + E)
        self._bucket_fill = ti.ndarray(ti.i32, buckets)       # zero between detections
        self._bucket_fill.fill(0)
        self._bucket_start = ti.ndarray(ti.i32, buckets + 1)
        self._allocate_entries(4 * (T + E))
        self._counter = ti.ndarray(ti.i32, 2)
        self._query_count = ti.ndarray(ti.i32, V + E)
        self._query_start = ti.ndarray(ti.i32, V + E + 1)
        self._vertex_fill = ti.ndarray(ti.i32, n)             # zero between detections
        self._vertex_fill.fill(0)
        longest = max(buckets, V + E, n)
        self._chunk = max(64, int(np.sqrt(longest)))
        self._serial = initialised_arch() == ti.cpu
        self._one_thread = self._serial and mesh.n_tets < SERIAL_DETECT_TETS
        self._serial_queries = self._one_thread and V + E < SERIAL_DETECT_QUERIES
        self._partial = ti.ndarray(ti.i32, longest // self._chunk + 1)
        self.incidence_offsets = ti.ndarray(ti.i32, n + 1)
        self.bound = ti.ndarray(dtype, n)
        self._allocate_pairs(max(64, V))
        self.n_pairs = 0
        empty = np.zeros(1, dtype=np.int64)
        self._excluded_vt, self._excluded_ee = _device(empty, ti.i64), _device(empty, ti.i64)
        self._n_excluded = (0, 0)
        self._excluded_range = ti.Vector.ndarray(2, ti.i32, V + E)    # per query: none
        self._excluded_range.fill(0)
        B = int(self.bodies.max()) + 1
        self.active = ti.ndarray(ti.i32, B)
        self.active.fill(1)
        self.active_count = B
        self._deviation = ti.ndarray(ti.f64, B)
        self._vertex_deviation = _device(np.zeros(n), ti.f64)
        margin = np.full(B, (REST_MARGIN - 1) * contact.query_radius)       # D_min - q per body, m
        self._partner_start = _device(np.zeros(V + E + 1, dtype=np.int32), ti.i32)     # no partner listed
        self._partner_item = _device(np.zeros(1, dtype=np.int32), ti.i32)
        self._partner_distance = _device(np.zeros(1), ti.f64)
        if contact.self_contact:
            self_margin = self._rest_exclusions(mesh)
            np.minimum.at(margin, self.bodies[np.concatenate([self.surface.vertices, self.surface.edges[:, 0]])],
                          self_margin)
        self._init_bodies(mesh.vertices, free, margin)

    def _rest_exclusions(self, mesh) -> np.ndarray:
        """List the same-body pairs closer than q at rest (never pairs, sorted keys on the device), list
        the others closer than REST_MARGIN q as each query's partners (`may_have_self_pair`) and return
        D_min(Q) - q in m (V + E,) per query Q (its surface vertex, then its edge), (REST_MARGIN - 1) q for
        a query without partners."""
        q = self.contact.query_radius
        T, E = len(self.surface.triangles), len(self.surface.edges)
        rest = ti.Vector.ndarray(3, self.dtype, (1, mesh.n_vertices))
        rest.from_numpy(mesh.vertices[None].astype(np.float32 if self.dtype == ti.f32 else np.float64))
        self._detect(rest, 0, rest_mode=True, q=REST_MARGIN * q)
        kind, vertices, primitives, distance = self.pairs()
        close = distance < q
        keys = [np.unique(primitives[mine, 0].astype(np.int64) * size + primitives[mine, 1])
                for mine, size in ((close & (kind == PairKind.VERTEX_TRIANGLE), T),
                                   (close & (kind == PairKind.EDGE_EDGE), E))]
        empty = np.zeros(1, dtype=np.int64)
        self._excluded_vt, self._excluded_ee = (_device(np.concatenate([k, empty]), ti.i64) for k in keys)
        self._n_excluded = (len(keys[0]), len(keys[1]))
        first = (self.surface.vertices.astype(np.int64) * T, np.arange(E, dtype=np.int64) * E)   # each query's keys
        self._excluded_range.from_numpy(np.concatenate(
            [np.stack([np.searchsorted(k, lo), np.searchsorted(k, lo + size)], axis=1)
             for k, lo, size in zip(keys, first, (T, E))]).astype(np.int32))
        self.n_pairs = 0
        query = len(self.surface.vertices) + primitives[:, 0].astype(np.int64)      # an edge's query
        vt = kind == PairKind.VERTEX_TRIANGLE
        query[vt] = np.searchsorted(self.surface.vertices, primitives[vt, 0])       # a vertex's
        far = ~close
        self_margin = np.full(len(self.surface.vertices) + E, (REST_MARGIN - 1) * q)
        np.minimum.at(self_margin, query[far], distance[far].astype(np.float64) - q)
        order = np.lexsort((distance[far], query[far]))        # by query, then rest distance
        item = np.where(vt, primitives[:, 1], T + primitives[:, 1])[far][order]
        self._partner_start = _device(np.searchsorted(query[far][order], np.arange(len(self_margin) + 1))
                                      .astype(np.int32), ti.i32)
        self._partner_item = _device(np.append(item, 0).astype(np.int32), ti.i32)
        self._partner_distance = _device(np.append(distance[far][order], np.inf).astype(np.float64), ti.f64)
        return self_margin

    def _init_bodies(self, rest: np.ndarray, free: np.ndarray, margin: np.ndarray):
        """The per-body arrays of `active_bodies`: rest (N, 3) positions, free (N,) bool, margin (B,) m."""
        B = len(margin)
        surface_body = self.bodies[self.surface.vertices]
        X = rest[self.surface.vertices].astype(np.float64)
        count = np.bincount(surface_body, minlength=B)
        centroid = np.stack([np.bincount(surface_body, X[:, k], minlength=B) for k in range(3)], axis=1)
        centroid /= np.maximum(count, 1)[:, None]
        has_free = np.zeros(B, dtype=np.int32)
        np.maximum.at(has_free, self.bodies, free.astype(np.int32))
        self._rest_surface = ti.Vector.ndarray(3, ti.f64, len(X))
        self._rest_surface.from_numpy(X)
        self._rest_centroid = ti.Vector.ndarray(3, ti.f64, B)
        self._rest_centroid.from_numpy(centroid)
        self._surface_count = _device(count.astype(np.int32), ti.i32)
        self._has_free = _device(has_free, ti.i32)
        self._margin = _device(margin, ti.f64)
        self._body_lo = ti.Vector.ndarray(3, ti.f64, B)
        self._body_hi = ti.Vector.ndarray(3, ti.f64, B)
        self._body_centroid = ti.Vector.ndarray(3, ti.f64, B)
        self._rotation = ti.Matrix.ndarray(3, 3, ti.f64, B)

    def _allocate_entries(self, capacity: int):
        self._entries = ti.ndarray(ti.i32, capacity)
        self._entry_box = ti.Vector.ndarray(3, self.dtype, (2, capacity))

    def _allocate_pairs(self, capacity: int):
        self._capacity = capacity
        self._found = ti.Vector.ndarray(3, ti.i32, capacity)
        self._found_distance = ti.ndarray(self.dtype, capacity)
        self.kind = ti.ndarray(ti.i32, capacity)
        self.pair = ti.Vector.ndarray(4, ti.i32, capacity)
        self.primitives = ti.Vector.ndarray(2, ti.i32, capacity)
        self.distance = ti.ndarray(self.dtype, capacity)
        self.incidence = ti.ndarray(ti.i32, 4 * capacity)

    def _detect(self, positions, row: int, rest_mode: bool, q: float = None) -> int:
        """`active_bodies` (not in rest mode), then one launch of `detect_pairs`, again after growing a
        buffer that was too small. q: the query radius, m (None: the contact's)."""
        c = self.contact
        q = c.query_radius if q is None else q
        if not rest_mode:
            self.active_count = active_bodies(positions, row, self._vertices, self._body, self._rest_surface,
                                              self._rest_centroid, self._surface_count, self._has_free, self._margin,
                                              self._body_lo, self._body_hi, self._body_centroid, self._rotation,
                                              self._deviation, self._vertex_deviation, self.active, q,
                                              int(c.self_contact), self._serial)
            if self.active_count == 0:
                no_pairs(self.incidence_offsets, self.bound, c.bound_relaxation * q, self.dtype)
                self.n_pairs = 0
                return 0
        while True:
            found = detect_pairs(positions, row, self._vertices, self._edges, self._triangles, self._body,
                                 self.active, self._deviation, self._vertex_deviation, self._partner_start,
                                 self._partner_item, self._partner_distance, self._own_items, self._free,
                                 self._moving, self._excluded_vt,
                                 self._excluded_ee, self._excluded_range, self._box,
                                 self._lo, self._hi, self._bucket_fill, self._bucket_start, self._entries,
                                 self._entry_box, self._partial, self._counter, self._found, self._found_distance,
                                 self._query_count, self._query_start, self._vertex_fill,
                                 self.kind, self.pair, self.primitives, self.distance, self.incidence_offsets,
                                 self.incidence, self.bound, q, c.bound_relaxation, self.cell,
                                 self._mask, self._chunk, int(rest_mode), self._serial, self._one_thread,
                                 self._serial_queries, self.dtype)
            if found < 0:
                self._allocate_entries(-2 * found)
            elif found > self._capacity:
                self._allocate_pairs(2 * found)
            else:
                self.n_pairs = found
                return found

    def detect(self, positions, row: int = 0) -> int:
        """Find the pairs at x = positions[row] ((rows, N) ndarray of 3-vectors), their incidence lists
        and the bounds; returns the number of pairs."""
        return self._detect(positions, row, rest_mode=False)

    def pairs(self):
        """(kind (P,) int32, vertices (P, 4) int32, primitives (P, 2) int32, distance (P,)) of the last
        detection, as numpy arrays."""
        P = self.n_pairs
        return (self.kind.to_numpy()[:P], self.pair.to_numpy()[:P], self.primitives.to_numpy()[:P],
                self.distance.to_numpy()[:P])

    def self_queries(self) -> int:
        """How many queries of the last detection sought self pairs: those of the bodies searched for them
        (`active` has SEARCH_SELF) whose own primitive may have one (module docstring)."""
        return int(self._counter.to_numpy()[1]) if self.active_count else 0

    def vertex_pairs(self):
        """(offsets (N + 1,), pair ids (4P,)) of the last detection: vertex v's pairs are
        ids[offsets[v]:offsets[v + 1]]."""
        offsets = self.incidence_offsets.to_numpy()
        return offsets, self.incidence.to_numpy()[:offsets[-1]]


def own_item_ranges(bodies: np.ndarray, surface) -> np.ndarray:
    """(B, 4) int32: per body, the grid items (triangles 0..T-1, then edges T..T+E-1) of its triangles as
    [lo, hi) in columns 0-1 and of its edges in columns 2-3, where they are contiguous; (0, 0) where they
    are not (bodies interleaved in the numbering) or there are none, so that nothing is skipped."""
    B, T = int(bodies.max()) + 1, len(surface.triangles)
    ranges = np.zeros((B, 4), dtype=np.int32)
    for column, (primitives, base) in enumerate(((surface.triangles, 0), (surface.edges, T))):
        owner = bodies[primitives[:, 0]]
        index = np.arange(len(owner))
        count = np.bincount(owner, minlength=B)
        lo = np.full(B, len(owner))
        np.minimum.at(lo, owner, index)
        hi = np.zeros(B, dtype=np.int64)
        np.maximum.at(hi, owner, index + 1)
        contiguous = (count > 0) & (hi - lo == count)
        ranges[contiguous, 2 * column] = lo[contiguous] + base
        ranges[contiguous, 2 * column + 1] = hi[contiguous] + base
    return ranges


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
