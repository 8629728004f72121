"""The VBD sweep with contact between bodies (issue 17): each vertex adds its pairs' barrier force and
block (and friction) to its f_i, H_i; partners may share a colour, so a vertex with pairs writes its new
position to a buffer first, applied once its colour is done (Jacobi inside a colour, VBD [Chen et al. 2024]
Sec. 3.9). A vertex without pairs is read by no other vertex of its colour and writes at once.

For the vertex i in colour slot k:

    f_i, H_i  = inertia + elasticity + damping + ground        (`vertex_solve.force_hessian`)
              + sum over i's pairs p: -b'(d_p) w_ip n_p,  J_ip b''(d_p) w_ip^2 n_p n_p^T   (`contact.py`)
              + lagged friction of each pair, its block times J_ip (`contact.contact_friction`)
    x_i      <- x_i + H_i^-1 f_i, then clamped to |x_i - x_det,i| <= b_i

J_ip = 2 where a vertex j across pair p has i's colour (solved in the same pass, from the old x_i), else 1.
Why: two partners solved at once each take the step that would close the pair's gap error if the other
stood still, so together they close it twice and land as far beyond as they started short: Jacobi's
zero-decrease mode, which leaves a pile that should rest jittering, its vertices hitting their bounds at
every iteration. A Jacobi pass over a colour lowers the quadratic model of G where 2 D - A is positive
definite (D: the blocks the sweep solves, A: the model's Hessian over the colour's vertices). The pair
puts b'' n n^T times [[w_i^2, w_i w_j], [w_i w_j, w_j^2]] into A and J_ip b'' w_i^2 n n^T, J_jp b'' w_j^2 n n^T
into D, so into 2 D - A b'' n n^T times [[(2J - 1) w_i^2, -w_i w_j], [-w_i w_j, (2J - 1) w_j^2]]: singular
for J = 1 (the mode that closes the gap from both sides), positive definite for J = 2. Only the step
changes, never f_i: a converged sweep is the same minimiser of G. The other vertices of i's own side
share an edge with i, so never its colour, and a fixed or kinematic vertex is solved by no pass (its
colour reads -1).

where x_det are the positions at which the bounds b were last set (`refresh_bounds`: OGC's conservative
bounds, g < 1/2, no two primitives can cross before the next refresh; `contact_state.py`). One launch per
iteration, and with Chebyshev acceleration one more (`chebyshev_contact_step`).

Arrays besides those of `vertex_solve` (P pairs, N vertices, S free vertices in colour order): kind (P,) int32
`PairKind`; pair (P,) 4-vectors of vertices; incidence_offsets (N + 1,) and incidence (4P,) the pairs of each
vertex; live_incidence (4P,) and live_end (N,): the live pairs of each vertex (those that may come within the
radius before the next refresh), near_incidence (4P,) and near_end (N,) the near ones among them
(`refresh_bounds`); the sweep walks only the near ones at a vertex i, and all its live ones where alert[i]
(N,) int32 holds this iteration's stamp: a vertex of one of i's live pairs has moved farther than the horizon
(m) since x_det (`raise_alerts`), so a pair of i that is not near may have come within the radius. Either way
in the order of the incidence lists, so that the sums are the same; distance (P,) m, each pair's distance at
x_det, or a lower bound of it where that changes no bound (`refresh_bounds`; a live pair whose vertices have
not moved far enough since is skipped too: `may_be_within`); x_det (N,) 3-vectors; moved (N,) m, each
vertex's move since x_det (`measure_moves`); bound (N,) m; color (N,) int32, each free vertex's colour, -1
at the others; target (N,) 3-vectors (scratch); touched (N,) int32, set to 1 at every vertex with a pair
closer than the radius; jacobi (S,) and jacobi_count (colours,): the vertices of colour c that have pairs
are jacobi[color_starts[c]:color_starts[c] + jacobi_count[c]] (`list_jacobi_vertices`). k_c N/m, r m, mu,
friction_speed m/s: the `Contact`.
serial: run the colours, and the writes after each, on one CPU thread (`vertex_solve.serial_sweep`); in
the other kernels, every loop on one thread, for the same small meshes.
While no pair is listed the iteration is `vbd_bounded_iteration` instead: the plain sweep plus the clamp,
without the write loops (on the CPU a parallel loop costs tens of us even when empty) and with ten arrays to
pass instead of 25 (each adds to the cost of a launch).
"""
from .._ti import ti

from ..physics.contact import (PairKind, barrier, barrier_derivatives, contact_force_hessian, contact_friction,
                               pair_geometry)
from .chebyshev import chebyshev_update
from .layout import KEEP_ORIENTATION, TIME_STEP, X, X_N, X_PREV
from .vertex_solve import force_hessian, newton_step, step_limit

SAFETY = 0.999      # `guess_within_bounds`: the fraction of the least bound a refresh at x_n would set
MEASURE_ROUNDOFF = 1e-6     # x query radius: `refresh_bounds` measures the pairs whose lower bound is this close
FAR = 1e30                  # m: `refresh_bounds`' start for the least distance at a vertex (any float type holds it)


@ti.func
def pair_reach(kind, s):
    """How much closer a pair can come when its four vertices move by at most s (4,) m (since x_det, or until
    the next refresh: their bounds): the largest move on each side, as the closest points are convex
    combinations of their vertices."""
    reach = s[0] + ti.max(s[1], s[2], s[3])                     # vertex | triangle
    if kind == int(PairKind.EDGE_EDGE):
        reach = ti.max(s[0], s[1]) + ti.max(s[2], s[3])         # edge | edge
    return reach


@ti.func
def may_be_within(distance: ti.template(), kind, p, s, r, slack):
    """Whether pair p may be closer than r + slack at the current x: it was at least distance[p] apart at
    x_det, and its vertices have moved s (4,) m since, so it has come at most `pair_reach` closer. No
    distance needed."""
    return distance[p] - pair_reach(kind, s) < r + slack


@ti.func
def moves_since(state: ti.template(), x_det: ti.template(), v):
    """|x_j - x_det,j| (4,) in m of the vertices v of a pair, from eight reads (the sweep keeps them per
    vertex instead: `measure_moves`)."""
    return ti.Vector([(state[X, v[j]] - x_det[v[j]]).norm() for j in ti.static(range(4))])


@ti.func
def raise_alerts(i, alert: ti.template(), stamp, pair: ti.template(), incidence_offsets: ti.template(),
                 live_incidence: ti.template(), live_end: ti.template()):
    """alert[v] = stamp at the four vertices v of each live pair of vertex i: i has moved farther than the
    horizon since x_det, so these pairs may come within the radius without being near, and each of their
    vertices walks all its live pairs in this iteration (module docstring). Every writer writes the same
    value, so the order of the writes does not matter."""
    for s in range(incidence_offsets[i], live_end[i]):
        v = pair[live_incidence[s]]
        for j in ti.static(range(4)):
            alert[v[j]] = stamp


@ti.func
def measure_moves(state: ti.template(), x_det: ti.template(), moved: ti.template(), horizon, alert: ti.template(),
                  stamp, pair: ti.template(), incidence_offsets: ti.template(), live_incidence: ti.template(),
                  live_end: ti.template(), alerts: ti.template(), serial: ti.template(), dtype: ti.template()):
    """moved[i] = |x_i - x_det,i| in m for every vertex, so that the sweep reads a pair's `moves_since` as four
    numbers, and with alerts, `raise_alerts` around every vertex that has moved farther than the horizon (m)
    (both kept up to date by `apply_buffered`)."""
    ti.loop_config(serialize=serial)
    for i in range(moved.shape[0]):
        moved[i] = ti.cast((state[X, i] - x_det[i]).norm(), dtype)
        if ti.static(alerts):
            if moved[i] > horizon:
                raise_alerts(i, alert, stamp, pair, incidence_offsets, live_incidence, live_end)


@ti.func
def pair_slip(state: ti.template(), v, w, dtype: ti.template()):
    """u = sum_j w_j (x_j - x_n,j) (3,): the pair's relative displacement this step, which its lagged
    friction opposes (`contact.contact_friction`); v the pair's vertices, w their weights."""
    u = ti.Vector.zero(dtype, 3)
    for j in ti.static(range(4)):
        u += w[j] * (state[X, v[j]] - state[X_N, v[j]])
    return u


@ti.func
def partner_in_pass(color: ti.template(), v, i):
    """Whether a vertex of the pair v (4,) other than i has i's colour (module docstring: J_ip = 2)."""
    same = False
    for j in ti.static(range(4)):
        if v[j] != i and color[v[j]] == color[i]:
            same = True
    return same


@ti.func
def contact_force_hessian_at(state: ti.template(), i, kind: ti.template(), pair: ti.template(),
                             incidence_offsets: ti.template(), live_incidence: ti.template(), live_end: ti.template(),
                             near_incidence: ti.template(), near_end: ti.template(), every, moved: ti.template(),
                             distance: ti.template(), color: ti.template(), k_c, r, mu, eps_u, jacobi: ti.template(),
                             dtype: ti.template()):
    """(f (3,), H (3x3), number of pairs closer than r) of vertex i from its near live pairs, or with every
    from all its live pairs (`refresh_bounds`), at the current x; a pair that cannot be within r
    (`may_be_within`, from the moves `moved` (N,) since x_det) is skipped before its distance is computed.
    jacobi: count the blocks of pairs with a partner in i's colour (`color` (N,)) twice, as the sweep solves
    them (module docstring); else each block once, G's."""
    f = ti.Vector.zero(dtype, 3)
    H = ti.Matrix.zero(dtype, 3, 3)
    active = 0
    for s in range(incidence_offsets[i], live_end[i] if every else near_end[i]):
        p = live_incidence[s] if every else near_incidence[s]
        v = pair[p]
        if not may_be_within(distance, kind[p], p, ti.Vector([moved[v[j]] for j in ti.static(range(4))]), r, 0):
            continue
        d, w, n = pair_geometry(kind[p], state[X, v[0]], state[X, v[1]], state[X, v[2]], state[X, v[3]], dtype)
        if d < r:
            w_i = ti.cast(0, dtype)
            for j in ti.static(range(4)):
                if v[j] == i:
                    w_i = w[j]
            f_c, H_c = contact_force_hessian(d, w_i, n, k_c, r)
            if mu > 0:
                db, d2b = barrier_derivatives(d, k_c, r)
                f_f, H_f = contact_friction(pair_slip(state, v, w, dtype), n, w_i, -db, mu, eps_u, dtype)
                f_c += f_f
                H_c += H_f
            if ti.static(jacobi):
                if partner_in_pass(color, v, i):
                    H_c *= 2
            f += ti.cast(f_c, dtype)
            H += ti.cast(H_c, dtype)
            active += 1
    return f, H, active


@ti.func
def solve_contact_vertex(state: ti.template(), mass: ti.template(), color_order: ti.template(),
                         offsets: ti.template(), others: ti.template(), adj_f: ti.template(), params: ti.template(),
                         kind: ti.template(), pair: ti.template(), distance: ti.template(),
                         incidence_offsets: ti.template(), live_incidence: ti.template(), live_end: ti.template(),
                         near_incidence: ti.template(), near_end: ti.template(), x_det: ti.template(),
                         moved: ti.template(), alert: ti.template(), stamp, bound: ti.template(),
                         color: ti.template(), target: ti.template(), touched: ti.template(), k, kc, rr, mu_c,
                         friction_speed, dtype: ti.template()):
    """Solve the vertex in colour slot k (module docstring): its new position goes to x_i, or to target[i]
    when i has pairs; returns whether it hit its bound. moved (N,), alert (N,): `measure_moves`."""
    i = color_order[k]
    f, H = force_hessian(state, mass, color_order, offsets, others, adj_f, params, k, dtype)
    eps_u = ti.cast(friction_speed * params[TIME_STEP], dtype)
    f_c, H_c, active = contact_force_hessian_at(state, i, kind, pair, incidence_offsets, live_incidence, live_end,
                                                near_incidence, near_end, alert[i] == stamp, moved, distance, color,
                                                kc, rr, mu_c, eps_u, True, dtype)
    f += f_c
    H += H_c
    if active > 0:
        touched[i] = 1
    x_new, hit = bounded_step(state, offsets, others, adj_f, params, x_det, bound, i, k, f, H, dtype)
    if incidence_offsets[i + 1] > incidence_offsets[i]:
        target[i] = x_new           # a partner in this colour may still read x_i
    else:
        state[X, i] = x_new
    return hit


@ti.func
def bounded_step(state: ti.template(), offsets: ti.template(), others: ti.template(), adj_f: ti.template(),
                 params: ti.template(), x_det: ti.template(), bound: ti.template(), i, k, f, H, dtype: ti.template()):
    """(x_new (3,), whether it hit the bound): the vertex i in colour slot k after its Newton step for f_i, H_i
    (shortened by `step_limit` when the simulation keeps tets from inverting), clamped to
    |x_new - x_det,i| <= b_i."""
    dx = newton_step(f, H, dtype)
    if params[KEEP_ORIENTATION] > 0:
        dx *= ti.cast(step_limit(state, others, adj_f, offsets, i, k, dx), dtype)
    x_new = state[X, i] + dx
    offset = x_new - x_det[i]
    length = offset.norm()
    hit = False
    if length > bound[i]:
        x_new = x_det[i] + offset * ti.cast(bound[i] / length, dtype)
        hit = True
    return x_new, hit


@ti.func
def apply_buffered(state: ti.template(), color_starts: ti.template(), jacobi: ti.template(),
                   jacobi_count: ti.template(), target: ti.template(), x_det: ti.template(), moved: ti.template(),
                   horizon, alert: ti.template(), stamp, pair: ti.template(), incidence_offsets: ti.template(),
                   live_incidence: ti.template(), live_end: ti.template(), c, serial: ti.template(),
                   dtype: ti.template()):
    """x_i = target[i] for the vertices of colour c that have pairs (Jacobi inside a colour), their
    moved[i] = |x_i - x_det,i| (only vertices with pairs are read there), and `raise_alerts` around each one
    that has now moved farther than the horizon (m) (where it had already, it raised them at the iteration's
    start). serial: in one loop on one thread."""
    ti.loop_config(serialize=serial)
    for j in range(color_starts[c], color_starts[c] + jacobi_count[c]):
        i = jacobi[j]
        state[X, i] = target[i]
        was = moved[i]
        moved[i] = ti.cast((target[i] - x_det[i]).norm(), dtype)
        if moved[i] > horizon and was <= horizon:
            raise_alerts(i, alert, stamp, pair, incidence_offsets, live_incidence, live_end)


@ti.kernel
def vbd_contact_iteration(state: ti.types.ndarray(), mass: ti.types.ndarray(), color_order: ti.types.ndarray(),
                          offsets: ti.types.ndarray(), others: ti.types.ndarray(), adj_f: ti.types.ndarray(),
                          color_starts: ti.types.ndarray(), params: ti.types.ndarray(), kind: ti.types.ndarray(),
                          pair: ti.types.ndarray(), distance: ti.types.ndarray(),
                          incidence_offsets: ti.types.ndarray(), live_incidence: ti.types.ndarray(),
                          live_end: ti.types.ndarray(), near_incidence: ti.types.ndarray(),
                          near_end: ti.types.ndarray(), x_det: ti.types.ndarray(), moved: ti.types.ndarray(),
                          horizon: ti.f64, alert: ti.types.ndarray(), stamp: ti.i32,
                          bound: ti.types.ndarray(), color: ti.types.ndarray(), target: ti.types.ndarray(),
                          touched: ti.types.ndarray(), jacobi: ti.types.ndarray(), jacobi_count: ti.types.ndarray(),
                          k_c: ti.f64, r: ti.f64, mu: ti.f64, friction_speed: ti.f64, n_colors: ti.template(),
                          dtype: ti.template(), serial: ti.template(), cpu: ti.template()) -> ti.i32:
    """One VBD iteration with contact (module docstring); returns how many vertices hit their bound.
    serial: one loop over the colours on one CPU thread (one copy of the vertex solve to compile);
    else each colour is a parallel loop, followed by its writes, on one thread on the CPU (cpu), where
    starting a parallel loop costs more than the writes of a colour's vertices with pairs (30 against
    9 us in a settled pile of 64 balls). n_colors: `vertex_solve.unrolled_colors`."""
    hits = 0
    kc, rr, mu_c = ti.cast(k_c, dtype), ti.cast(r, dtype), ti.cast(mu, dtype)
    measure_moves(state, x_det, moved, horizon, alert, stamp, pair, incidence_offsets, live_incidence, live_end, True,
                  serial, dtype)
    if ti.static(serial):
        ti.loop_config(serialize=True)
        for c in range(color_starts.shape[0] - 1):
            for k in range(color_starts[c], color_starts[c + 1]):
                if solve_contact_vertex(state, mass, color_order, offsets, others, adj_f, params, kind, pair, distance,
                                        incidence_offsets, live_incidence, live_end, near_incidence, near_end, x_det,
                                        moved, alert, stamp, bound, color, target, touched, k, kc, rr, mu_c,
                                        friction_speed, dtype):
                    hits += 1
            apply_buffered(state, color_starts, jacobi, jacobi_count, target, x_det, moved, horizon, alert, stamp, pair,
                           incidence_offsets, live_incidence, live_end, c, True, dtype)
    else:
        for c in ti.static(range(n_colors)):
            for k in range(color_starts[c], color_starts[c + 1]):
                if solve_contact_vertex(state, mass, color_order, offsets, others, adj_f, params, kind, pair, distance,
                                        incidence_offsets, live_incidence, live_end, near_incidence, near_end, x_det,
                                        moved, alert, stamp, bound, color, target, touched, k, kc, rr, mu_c,
                                        friction_speed, dtype):
                    ti.atomic_add(hits, 1)
            apply_buffered(state, color_starts, jacobi, jacobi_count, target, x_det, moved, horizon, alert, stamp, pair,
                           incidence_offsets, live_incidence, live_end, c, cpu, dtype)
    return hits


@ti.kernel
def vbd_bounded_iteration(state: ti.types.ndarray(), mass: ti.types.ndarray(), color_order: ti.types.ndarray(),
                          offsets: ti.types.ndarray(), others: ti.types.ndarray(), adj_f: ti.types.ndarray(),
                          color_starts: ti.types.ndarray(), params: ti.types.ndarray(), x_det: ti.types.ndarray(),
                          bound: ti.types.ndarray(), n_colors: ti.template(), dtype: ti.template(),
                          serial: ti.template()) -> ti.i32:
    """`vbd_contact_iteration` where no pair is listed (module docstring): the plain sweep, every step clamped
    to its bound (`bounded_step`); returns how many vertices hit their bound."""
    hits = 0
    if ti.static(serial):
        ti.loop_config(serialize=True)
        for k in range(color_starts[0], color_starts[color_starts.shape[0] - 1]):
            i = color_order[k]
            f, H = force_hessian(state, mass, color_order, offsets, others, adj_f, params, k, dtype)
            x_new, hit = bounded_step(state, offsets, others, adj_f, params, x_det, bound, i, k, f, H, dtype)
            state[X, i] = x_new
            if hit:
                hits += 1
    else:
        for c in ti.static(range(n_colors)):
            for k in range(color_starts[c], color_starts[c + 1]):
                i = color_order[k]
                f, H = force_hessian(state, mass, color_order, offsets, others, adj_f, params, k, dtype)
                x_new, hit = bounded_step(state, offsets, others, adj_f, params, x_det, bound, i, k, f, H, dtype)
                state[X, i] = x_new
                if hit:
                    ti.atomic_add(hits, 1)
    return hits


@ti.kernel
def list_jacobi_vertices(color_order: ti.types.ndarray(), color_starts: ti.types.ndarray(),
                         incidence_offsets: ti.types.ndarray(), jacobi: ti.types.ndarray(),
                         jacobi_count: ti.types.ndarray(), color: ti.types.ndarray(), serial: ti.template()):
    """jacobi[color_starts[c]:color_starts[c] + jacobi_count[c]]: the vertices of colour c that have a pair,
    in slot order, and color[i] = c for every vertex i of colour c (module docstring)."""
    ti.loop_config(serialize=serial)
    for c in range(jacobi_count.shape[0]):
        n = 0
        for k in range(color_starts[c], color_starts[c + 1]):
            i = color_order[k]
            color[i] = c
            if incidence_offsets[i + 1] > incidence_offsets[i]:
                jacobi[color_starts[c] + n] = i
                n += 1
        jacobi_count[c] = n


@ti.kernel
def refresh_bounds(state: ti.types.ndarray(), row: ti.i32, x_full: ti.types.ndarray(), kind: ti.types.ndarray(),
                   pair: ti.types.ndarray(), n_pairs: ti.i32, incidence_offsets: ti.types.ndarray(),
                   incidence: ti.types.ndarray(), q: ti.f64, r: ti.f64, g: ti.f64, distance: ti.types.ndarray(),
                   exact: ti.types.ndarray(), reach: ti.types.ndarray(), x_det: ti.types.ndarray(),
                   moved: ti.types.ndarray(), bound: ti.types.ndarray(), nearest: ti.types.ndarray(),
                   live: ti.types.ndarray(), live_incidence: ti.types.ndarray(), live_end: ti.types.ndarray(),
                   near_incidence: ti.types.ndarray(), near_end: ti.types.ndarray(), horizon: ti.f64,
                   free: ti.types.ndarray(), dtype: ti.template(), serial: ti.template(),
                   lists: ti.template()) -> ti.f64:
    """New bounds at x = state[row] from the first n_pairs pairs, found by the last full detection at
    x_full (N,) (`contact_state.py`); returns Delta in m. distance (P,) holds on entry a lower bound of each
    pair's distance at x_det, the distance itself where exact (P,) int32 is 1, and on return the same at x.
    In order:
      Delta = max_i |x_i - x_full,i| over every vertex (fixed and kinematic ones included), and
      moved[i] = |x_i - x_det,i| (scratch);
      for every pair, its vertices moved s (4,) since x_det, so it has come at most reach[p] = pair_reach(s)
      closer (scratch (P,)), and it is at least distance[p] - reach[p] and, where exact, at most
      distance[p] + reach[p] apart at x;
      U_i = min(q - 2 Delta, distance[p] + reach[p] of each exact pair p of i), at least the distance of
      i's closest pair at x (scratch, in bound; each pair writes its four vertices' minima, in the same
      loop, so that no vertex walks its incidence list);
      for every pair whose lower bound distance[p] - reach[p] is below (a round-off above) the U_i of one
      of its vertices, or with lists below r + 2 horizon, distance[p] = d_p, the exact distance at x;
      every other pair is farther than the closest pair of each of its vertices (or the cap), changes no
      bound and keeps the lower bound (not exact, unless nothing moved), and cannot be near (below);
      b_i = g min(q - 2 Delta, distance[p] of each pair p of i) and x_det,i = x_i, for every vertex: the
      bounds of the exact distances (nearest (N,) scratch: the minima, written pair by pair as U_i);
    and with lists (without, live and the lists stay as they were: for a refresh that another follows
    before the next iteration, `contact_state.ContactStage.begin_step`):
      live[p] = 1 unless distance[p] >= r + (largest b of its first primitive) + (largest b of its second),
      b counted 0 at the vertices the sweep does not move (free (N,) int32 is 0 there): until the next
      refresh such a pair stays beyond the radius, and the sweep skips it;
      live_incidence[incidence_offsets[i]:live_end[i]] = the live pairs of incidence[incidence_offsets[i]:
      incidence_offsets[i + 1]], in order, for every vertex (the sweep walks only those), and
      near_incidence[incidence_offsets[i]:near_end[i]] those of them closer than r + 2 horizon (near), in
      order (while no vertex has moved farther than the horizon since x_det, the others are beyond the
      radius: the sweep walks only the near ones until one has)."""
    delta = ti.cast(0.0, ti.f64)
    far = ti.cast(FAR, dtype)
    ti.loop_config(serialize=serial)
    for i in range(x_full.shape[0]):
        ti.atomic_max(delta, ti.cast((state[row, i] - x_full[i]).norm(), ti.f64))
        moved[i] = ti.cast((state[row, i] - x_det[i]).norm(), dtype)
        bound[i] = far
        nearest[i] = far
    cap = ti.cast(q - 2 * delta, dtype)
    ti.loop_config(serialize=serial)
    for p in range(n_pairs):
        v = pair[p]
        reach[p] = pair_reach(kind[p], ti.Vector([moved[v[j]] for j in ti.static(range(4))]))
        if exact[p]:
            for j in ti.static(range(4)):
                ti.atomic_min(bound[v[j]], distance[p] + reach[p])
    roundoff = ti.cast(MEASURE_ROUNDOFF * q, dtype)
    near = ti.cast(r + 2 * horizon, dtype) if ti.static(lists) else -far      # without lists: no pair for this
    ti.loop_config(serialize=serial)
    for p in range(n_pairs):
        v = pair[p]
        if reach[p] > 0 or not exact[p]:
            lower = distance[p] - reach[p]
            upper = ti.min(cap, ti.max(bound[v[0]], bound[v[1]], bound[v[2]], bound[v[3]]))
            if lower < ti.max(upper, near) + roundoff:
                d, w, n = pair_geometry(kind[p], state[row, v[0]], state[row, v[1]], state[row, v[2]],
                                        state[row, v[3]], dtype)
                distance[p] = d
                exact[p] = 1
            else:
                distance[p] = lower
                exact[p] = 0
        for j in ti.static(range(4)):
            ti.atomic_min(nearest[v[j]], distance[p])
    ti.loop_config(serialize=serial)
    for i in range(x_full.shape[0]):
        bound[i] = ti.cast(g * ti.min(cap, nearest[i]), dtype)
        x_det[i] = state[row, i]
    if ti.static(lists):
        ti.loop_config(serialize=serial)
        for p in range(n_pairs):
            v = pair[p]
            b = ti.Vector([bound[v[j]] * free[v[j]] for j in ti.static(range(4))])
            live[p] = ti.cast(distance[p] < r + pair_reach(kind[p], b), ti.i32)
        ti.loop_config(serialize=serial)
        for i in range(x_full.shape[0]):
            end = incidence_offsets[i]
            end_near = end
            for s in range(incidence_offsets[i], incidence_offsets[i + 1]):
                p = incidence[s]
                if live[p]:
                    live_incidence[end] = p
                    end += 1
                    if distance[p] < near:
                        near_incidence[end_near] = p
                        end_near += 1
            live_end[i] = end
            near_end[i] = end_near
    return delta


@ti.kernel
def chebyshev_contact_step(state: ti.types.ndarray(), color_order: ti.types.ndarray(), touched: ti.types.ndarray(),
                           x_det: ti.types.ndarray(), bound: ti.types.ndarray(), omega: ti.f64,
                           dtype: ti.template(), serial: ti.template()) -> ti.i32:
    """The Chebyshev step (`chebyshev.py`) for the free vertices that have not touched this step (VBD
    Sec. 3.8: off for the others, whose history only shifts), each clamped to its bound after; returns how
    many were clamped."""
    hits = 0
    ti.loop_config(serialize=serial)
    for k in range(color_order.shape[0]):
        i = color_order[k]
        if touched[i]:
            chebyshev_update(state, i, ti.cast(1.0, dtype))     # omega = 1: x stays, the history shifts
        else:
            chebyshev_update(state, i, ti.cast(omega, dtype))
            moved = state[X, i] - x_det[i]
            length = moved.norm()
            if length > bound[i]:
                state[X, i] = x_det[i] + moved * ti.cast(bound[i] / length, dtype)
                state[X_PREV, i] = state[X, i]
                ti.atomic_add(hits, 1)
    return hits


@ti.kernel
def clamp_to_bounds(state: ti.types.ndarray(), color_order: ti.types.ndarray(), x_det: ti.types.ndarray(),
                    bound: ti.types.ndarray(), dtype: ti.template(), serial: ti.template()) -> ti.i32:
    """Clamp every free vertex (slot of `color_order`) to |x_i - x_det,i| <= b_i (the initial guess);
    returns how many were clamped."""
    hits = 0
    ti.loop_config(serialize=serial)
    for k in range(color_order.shape[0]):
        i = color_order[k]
        moved = state[X, i] - x_det[i]
        length = moved.norm()
        if length > bound[i]:
            state[X, i] = x_det[i] + moved * ti.cast(bound[i] / length, dtype)
            ti.atomic_add(hits, 1)
    return hits


@ti.kernel
def hold_kinematic(state: ti.types.ndarray(), kinematic_ids: ti.types.ndarray(), n_kinematic: ti.i32,
                   serial: ti.template()):
    """x_i = x_n,i for the first n_kinematic kinematic vertices (`advance_kinematic` moves them on)."""
    ti.loop_config(serialize=serial)
    for k in range(n_kinematic):
        state[X, kinematic_ids[k]] = state[X_N, kinematic_ids[k]]


@ti.kernel
def advance_kinematic(state: ti.types.ndarray(), kinematic_ids: ti.types.ndarray(),
                      kinematic_targets: ti.types.ndarray(), n_kinematic: ti.i32, x_det: ti.types.ndarray(),
                      bound: ti.types.ndarray(), dtype: ti.template(), serial: ti.template()) -> ti.f64:
    """Move each of the first n_kinematic kinematic vertices straight towards its target (K,) 3-vectors,
    as far as |x_i - x_det,i| <= b_i allows (the ball every vertex keeps to between refreshes, so no surface
    passes through another); returns the largest distance in m still left to a target."""
    left = ti.cast(0.0, ti.f64)
    ti.loop_config(serialize=serial)
    for k in range(n_kinematic):
        i = kinematic_ids[k]
        offset = kinematic_targets[k] - x_det[i]
        length = offset.norm()
        x = kinematic_targets[k]
        if length > bound[i]:
            x = x_det[i] + offset * ti.cast(bound[i] / length, dtype)
        state[X, i] = x
        ti.atomic_max(left, ti.cast((kinematic_targets[k] - x).norm(), ti.f64))
    return left


@ti.kernel
def guess_within_bounds(state: ti.types.ndarray(), color_order: ti.types.ndarray(), x_det: ti.types.ndarray(),
                        x_full: ti.types.ndarray(), bound: ti.types.ndarray(), g: ti.f64, margin: ti.f64,
                        dtype: ti.template(), serial: ti.template()) -> ti.i32:
    """Whether refreshing at x_n (row X_N) would neither detect nor clamp the initial guess (row X), without
    measuring a pair: with M = max_j |x_n,j - x_det,j| each pair has come at most 2 M closer since x_det and
    the cap q - 2 Delta has fallen by at most 2 M, so the bounds a refresh at x_n would set are at least
    b_i - 2 g M; 1 if every free vertex's guess lies within SAFETY of that of x_n,i and 2 max_j
    |x_n,j - x_full,j| is below margin (q - r) in m, else 0."""
    M = ti.cast(0.0, ti.f64)
    delta = ti.cast(0.0, ti.f64)
    ti.loop_config(serialize=serial)
    for i in range(x_det.shape[0]):
        ti.atomic_max(M, ti.cast((state[X_N, i] - x_det[i]).norm(), ti.f64))
        ti.atomic_max(delta, ti.cast((state[X_N, i] - x_full[i]).norm(), ti.f64))
    outside = 0
    ti.loop_config(serialize=serial)
    for k in range(color_order.shape[0]):
        i = color_order[k]
        if (state[X, i] - state[X_N, i]).norm() > ti.cast(SAFETY * (bound[i] - 2 * g * M), dtype):
            ti.atomic_add(outside, 1)
    return ti.cast(outside == 0 and 2 * delta < margin, ti.i32)


@ti.kernel
def largest_move(state: ti.types.ndarray(), row: ti.i32, x_full: ti.types.ndarray(),
                 serial: ti.template()) -> ti.f64:
    """max_i |state[row, i] - x_full,i| in m over all vertices (fixed and kinematic ones included)."""
    result = ti.cast(0.0, ti.f64)
    ti.loop_config(serialize=serial)
    for i in range(x_full.shape[0]):
        ti.atomic_max(result, ti.cast((state[row, i] - x_full[i]).norm(), ti.f64))
    return result


@ti.kernel
def copy_row(state: ti.types.ndarray(), row: ti.i32, out: ti.types.ndarray(), serial: ti.template()):
    """out[i] = state[row, i]."""
    ti.loop_config(serialize=serial)
    for i in range(out.shape[0]):
        out[i] = state[row, i]


@ti.kernel
def copy_prefix(source: ti.types.ndarray(), n: ti.i32, out: ti.types.ndarray(), serial: ti.template()):
    """out[k] = source[k] for k < n."""
    ti.loop_config(serialize=serial)
    for k in range(n):
        out[k] = source[k]


@ti.kernel
def clear(flags: ti.types.ndarray(), serial: ti.template()):
    """flags[i] = 0."""
    ti.loop_config(serialize=serial)
    for i in range(flags.shape[0]):
        flags[i] = 0


@ti.kernel
def contact_energy(state: ti.types.ndarray(), kind: ti.types.ndarray(), pair: ti.types.ndarray(), n_pairs: ti.i32,
                   k_c: ti.f64, r: ti.f64, dtype: ti.template()) -> ti.f64:
    """E_c = sum of b(d) over the first n_pairs pairs at the current x, in J."""
    E = ti.cast(0.0, ti.f64)
    for p in range(n_pairs):
        v = pair[p]
        d, w, n = pair_geometry(kind[p], state[X, v[0]], state[X, v[1]], state[X, v[2]], state[X, v[3]], dtype)
        E += barrier(ti.cast(d, ti.f64), k_c, r)
    return E


@ti.kernel
def add_contact_local_systems(state: ti.types.ndarray(), color_order: ti.types.ndarray(), kind: ti.types.ndarray(),
                              pair: ti.types.ndarray(), distance: ti.types.ndarray(),
                              incidence_offsets: ti.types.ndarray(), live_incidence: ti.types.ndarray(),
                              live_end: ti.types.ndarray(), near_incidence: ti.types.ndarray(),
                              near_end: ti.types.ndarray(), x_det: ti.types.ndarray(), moved: ti.types.ndarray(),
                              alert: ti.types.ndarray(), color: ti.types.ndarray(), params: ti.types.ndarray(),
                              f_out: ti.types.ndarray(), H_out: ti.types.ndarray(), k_c: ti.f64, r: ti.f64, mu: ti.f64,
                              friction_speed: ti.f64, dtype: ti.template()) -> ti.f64:
    """Add every free vertex's contact force and block to f_out (N,) and H_out (N,) 3x3 (as
    `vertex_solve.local_systems` filled them), the bounds, live lists and distances set at the current x
    (x_det = x); return max_i |f_i| in N. moved (N,): scratch for `measure_moves`; alert (N,) goes unread:
    every live pair is walked. The blocks are G's, each pair's once: the sweep's Jacobi factor (module docstring) is
    not part of G, and color (N,) goes unread."""
    result = ti.cast(0.0, ti.f64)
    measure_moves(state, x_det, moved, 0.0, alert, 0, pair, incidence_offsets, live_incidence, live_end, False, False,
                  dtype)
    for k in range(color_order.shape[0]):
        i = color_order[k]
        eps_u = ti.cast(friction_speed * params[TIME_STEP], dtype)
        f_c, H_c, active = contact_force_hessian_at(state, i, kind, pair, incidence_offsets, live_incidence,
                                                    live_end, near_incidence, near_end, True, moved, distance, color,
                                                    ti.cast(k_c, dtype), ti.cast(r, dtype), ti.cast(mu, dtype), eps_u,
                                                    False, dtype)
        f_out[i] += f_c
        H_out[i] += H_c
        ti.atomic_max(result, ti.cast(f_out[i].norm(), ti.f64))
    return result
