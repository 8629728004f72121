"""The rigid-translation correction: the coarsest global channel, one translation per free body.

Unconverged VBD leaves a residual f_i at every vertex, and the residuals do not sum to zero: each
step then adds a spurious momentum h sum_i f_i, and a ball dropped straight down drifts sideways
(the `drop` scene); a block sliding on a fixed slab lags behind g (sin - mu cos). Elastic
forces are invariant under a translation of a whole body (every tet lies in one body), so the Newton
step restricted to the translation modes of the bodies, x_i <- x_i + d_b for every vertex i of body b,
costs one force evaluation per step. Bodies are the mesh's vertex-connected components
(`mesh.bodies.body_labels`); a body with a fixed or kinematic vertex gets no correction (its elastic
energy is not translation invariant), every other body b solves its own 3x3 system

    d_b = A_b^-1 F_b,   F_b = sum_{i in b} f_i + sum_{pairs p of b} f_p,b
                        A_b = sum_{i in b} (m_i/h^2 I + ground block) + sum_{pairs p of b} b''(d_p) n_p n_p^T

where the pairs are b's contact pairs with other bodies closer than the radius. A pair's weights on
one side sum to 1 (a vertex: 1; an edge: 1 - s + s) and on the other to -1, so a translated body acts
on the pair like one vertex of weight s_b = +-1: its force f_p,b and block come from the same
`contact.contact_force_hessian` (and `contact_friction`) as a vertex's. Pairs within one body are left
out: their forces sum to zero over the body and its translation does not change them. Friction is
not a potential and stays out of A_b (its lagged stiffness would block the correction on the ground
and on a slab); its force is part of F_b. A single body touching no other body has a diagonal A_b,
solved componentwise: the correction of a free body on its own is exactly the one for the whole mesh.

Why each body may solve alone. The exact Galerkin system couples two free bodies a, b through each
of their pairs: its quadratic model Q(d) = 1/2 d^T A d - F^T d has the pair term
b''/2 (n . (d_a - d_b))^2, and A_a counts the pair in full as if b stood still. This is block Jacobi
over the bodies, and it cannot increase Q: with D the block diagonal of the A_b,
d^T (2 D - A) d = sum_b d_b^T (masses and ground) d_b + sum_pairs b'' (n . (d_a + d_b))^2 >= 0, so for
any scale alpha_b in [0, 1] per body, Q(alpha d) <= sum_b (alpha_b^2 - alpha_b) F_b^T A_b^-1 F_b <= 0.
Two bodies pressed together may overshoot their relative correction, but by less than twice.

With contact, every vertex must stay within its bound |x_i - x_det,i| <= b_i (OGC's conservative
bounds, `contact_state.py`), or two surfaces could cross. A body whose step would take a vertex past
its bound has its step scaled down, d_b <- alpha_b d_b with alpha_b the largest scale in [0, 1] that
keeps all its vertices inside: the bound above still holds, and the body keeps as much of its
correction as the bounds allow (skipping it instead would drop the correction whenever one vertex of
a body in contact sits near its bound, which is where bodies lag). Q is only a model of G: a pair
that comes within the radius during the correction, or a gap closing into the barrier's log stage,
can make G rise where Q falls. With contact the steps of all bodies are therefore scaled together by
the largest of 1, 1/2, 1/4, 1/8 for which G does not rise, or dropped (`energy_changes` evaluates the
four in one launch: inertia, ground and the pairs between bodies; the elastic energy does not change).
Friction is not part of G, so with friction this line search may shorten a step that friction asks for.

A body touching another whose d_b is shorter than friction_speed h (the slip under which the friction
law holds a contact almost as if it stuck) is left alone. A resting body's correction answers only what
the sweeps left unconverged, and applied at every step it makes stacked bodies rock (chapter 8).

Block Jacobi keeps each body's forces in balance, not the whole mesh's: the contact blocks a body
counts in A_b push the two bodies of a pair by different amounts, so the forces of all bodies no longer
sum to zero, and a mesh of free bodies would gain momentum h sum_i f_i. Where every vertex is free,
one translation of the whole mesh follows (the same correction with one body: pairs and elastic
forces do not change under it, so it zeroes sum_i f_i exactly and G falls).

Arrays (N vertices, B bodies): body (N,) int32; corrected (B,) int32, 1 for a body without fixed or
kinematic vertices; F (B,) 3-vectors in N, D (B,) 3-vectors in N/m (the diagonal of the inertia and
ground blocks), K (B,) 3x3 in N/m (the contact blocks), touching (B,) int32 (pairs with other bodies),
d (B,) 3-vectors in m, alpha (B,); all per-body sums in float64.
"""
import numpy as np

from .._ti import ti
from ..backend import running_on_cpu

from ..physics.contact import barrier, barrier_derivatives, contact_force_hessian, contact_friction, pair_geometry
from ..physics.ground import ground_energy, ground_hessian_zz
from ..physics.inertia import inertia_block, inertia_energy
from .layout import GROUND, GROUND_HEIGHT, GROUND_STIFFNESS, TIME_STEP, X, Y
from .contact_sweep import may_be_within, moves_since, pair_slip
from .vertex_solve import force_hessian

TRIALS = 4   # with contact, the scales 1, 1/2, 1/4, 1/8 of the step are tried (`energy_changes`)


@ti.kernel
def body_sums(state: ti.types.ndarray(), mass: ti.types.ndarray(), color_order: ti.types.ndarray(),
              offsets: ti.types.ndarray(), others: ti.types.ndarray(), adj_f: ti.types.ndarray(),
              params: ti.types.ndarray(), body: ti.types.ndarray(), corrected: ti.types.ndarray(),
              members: ti.types.ndarray(), member_starts: ti.types.ndarray(), f_i: ti.types.ndarray(),
              diagonal_i: ti.types.ndarray(), F: ti.types.ndarray(), D: ti.types.ndarray(), K: ti.types.ndarray(),
              touching: ti.types.ndarray(), ordered: ti.template(), dtype: ti.template(), serial: ti.template()):
    """F_b = sum_i f_i and D_b = the diagonal of sum_i m_i/h^2 I + ground block over the vertices of each
    corrected body b; K_b and touching_b cleared. ordered: each vertex's terms go to f_i (N,) and
    diagonal_i (N,) first, then each body sums its own in the order of `members` (its vertices are
    members[member_starts[b]:member_starts[b + 1]]), the same sums on every run; else (on a GPU, where one
    thread per body would be slow) they are added at once, in whatever order the threads come. serial: every
    loop on one thread (small meshes on the CPU, as their sweep: `vertex_solve.serial_sweep`)."""
    ti.loop_config(serialize=serial)
    for b in range(F.shape[0]):
        F[b] = ti.Vector.zero(ti.f64, 3)
        D[b] = ti.Vector.zero(ti.f64, 3)
        K[b] = ti.Matrix.zero(ti.f64, 3, 3)
        touching[b] = 0
    inv_h2 = 1 / params[TIME_STEP] ** 2
    ti.loop_config(serialize=serial)
    for k in range(color_order.shape[0]):
        i = color_order[k]
        b = body[i]
        if corrected[b]:
            f, H = force_hessian(state, mass, color_order, offsets, others, adj_f, params, k, dtype)
            M = inertia_block(ti.cast(inv_h2 * mass[i], dtype))
            diagonal = ti.Vector([M[0, 0], M[1, 1], M[2, 2]])
            if params[GROUND] > 0:
                diagonal[2] += ground_hessian_zz(state[X, i][2], params[GROUND_HEIGHT], params[GROUND_STIFFNESS])
            if ti.static(ordered):
                f_i[i] = ti.cast(f, ti.f64)
                diagonal_i[i] = ti.cast(diagonal, ti.f64)
            else:
                F[b] += ti.cast(f, ti.f64)
                D[b] += ti.cast(diagonal, ti.f64)
    if ti.static(ordered):
        ti.loop_config(serialize=serial)
        for b in range(F.shape[0]):
            if corrected[b]:
                for s in range(member_starts[b], member_starts[b + 1]):
                    F[b] += f_i[members[s]]
                    D[b] += diagonal_i[members[s]]


@ti.kernel
def pair_sums(state: ti.types.ndarray(), kind: ti.types.ndarray(), pair: ti.types.ndarray(), n_pairs: ti.i32,
              x_det: ti.types.ndarray(), distance: ti.types.ndarray(), live: ti.types.ndarray(),
              body: ti.types.ndarray(), corrected: ti.types.ndarray(), F: ti.types.ndarray(), K: ti.types.ndarray(),
              touching: ti.types.ndarray(), params: ti.types.ndarray(), k_c: ti.f64, r: ti.f64, mu: ti.f64,
              friction_speed: ti.f64, ordered: ti.template(), dtype: ti.template()):
    """Add to F_b and K_b of each corrected body its pairs with other bodies closer than r, the body acting
    on the pair as one vertex of weight s_b = sum of the pair's weights on its side (module docstring);
    pair (P,) 4-vectors of vertices and kind (P,) `PairKind` as the detector left them, distance (P,) in m
    at the positions x_det (N,) of the last refresh and live (P,) int32 its flags (pairs that cannot be
    within r are skipped: not live, or `contact_sweep.may_be_within`). ordered: on one thread, in the
    order of the pairs (the same sums on every run)."""
    kc, rr, mu_c = ti.cast(k_c, dtype), ti.cast(r, dtype), ti.cast(mu, dtype)
    eps_u = ti.cast(friction_speed * params[TIME_STEP], dtype)
    ti.loop_config(serialize=ordered)
    for p in range(n_pairs):
        if not live[p]:
            continue
        v = pair[p]
        ends = ti.Vector([body[v[0]], body[v[3]]])
        if ends[0] == ends[1] or not may_be_within(distance, kind[p], p, moves_since(state, x_det, v), rr, 0):
            continue
        d, w, n = pair_geometry(kind[p], state[X, v[0]], state[X, v[1]], state[X, v[2]], state[X, v[3]], dtype)
        if d < rr:
            s = ti.cast(0, dtype)
            for j in ti.static(range(4)):
                if body[v[j]] == ends[0]:
                    s += w[j]
            u = pair_slip(state, v, w, dtype)
            for side in ti.static(range(2)):
                c = ends[side]
                if corrected[c]:
                    s_c = (1 - 2 * side) * s
                    f, H = contact_force_hessian(d, s_c, n, kc, rr)
                    if mu_c > 0:
                        db, _ = barrier_derivatives(d, kc, rr)
                        f_f, _ = contact_friction(u, n, s_c, -db, mu_c, eps_u, dtype)
                        f += f_f
                    F[c] += ti.cast(f, ti.f64)
                    K[c] += ti.cast(H, ti.f64)
                    touching[c] += 1


@ti.kernel
def body_steps(corrected: ti.types.ndarray(), F: ti.types.ndarray(), D: ti.types.ndarray(), K: ti.types.ndarray(),
               touching: ti.types.ndarray(), d: ti.types.ndarray(), alpha: ti.types.ndarray(),
               params: ti.types.ndarray(), friction_speed: ti.f64, serial: ti.template()):
    """d_b = (diag(D_b) + K_b)^-1 F_b for each corrected body (F_b / D_b componentwise for one touching no
    other body), 0 for the others and for a body touching another whose d_b is shorter than
    friction_speed h in m (module docstring; 0 without contact); alpha_b = 1."""
    least = friction_speed * params[TIME_STEP]
    ti.loop_config(serialize=serial)
    for b in range(F.shape[0]):
        step = ti.Vector.zero(ti.f64, 3)
        if corrected[b]:
            if touching[b] == 0:
                step = F[b] / D[b]
            else:
                A = K[b]
                for a in ti.static(range(3)):
                    A[a, a] += D[b][a]
                step = A.inverse() @ F[b]
                if step.norm() < least:
                    step = ti.Vector.zero(ti.f64, 3)
        d[b] = step
        alpha[b] = 1.0


@ti.func
def body_shift(i, body: ti.template(), corrected: ti.template(), d: ti.template(), alpha: ti.template(), scale):
    """The translation scale alpha_b d_b (float64 3-vector, m) of vertex i's body b, 0 if b gets none."""
    t = ti.Vector.zero(ti.f64, 3)
    b = body[i]
    if corrected[b]:
        t = scale * alpha[b] * d[b]
    return t


@ti.func
def pair_distance(kind, x0, x1, x2, x3):
    """The distance d in m of a pair (`contact.pair_geometry`) at float64 positions."""
    d, w, n = pair_geometry(kind, x0, x1, x2, x3, ti.f64)
    return d


@ti.kernel
def energy_changes(state: ti.types.ndarray(), mass: ti.types.ndarray(), color_order: ti.types.ndarray(),
                   params: ti.types.ndarray(), body: ti.types.ndarray(), corrected: ti.types.ndarray(),
                   d: ti.types.ndarray(), alpha: ti.types.ndarray(), kind: ti.types.ndarray(),
                   pair: ti.types.ndarray(), n_pairs: ti.i32, x_det: ti.types.ndarray(), distance: ti.types.ndarray(),
                   live: ti.types.ndarray(), k_c: ti.f64, r: ti.f64, change_i: ti.types.ndarray(),
                   change: ti.types.ndarray(), ordered: ti.template(), serial: ti.template()):
    """change[s] = G(x + t) - G(x) in J, in float64, for the translations t_b = 2^-s alpha_b d_b of the
    corrected bodies, s < TRIALS: their inertia and ground terms and their pairs with other bodies (the
    elastic energy and the pairs within a body do not change under a translation of the body). A pair whose
    two bodies both stay put does not change and is skipped, as is one that cannot come within r under the
    largest of the translations: not live (the translations keep every vertex within its bound,
    `limit_to_bounds`), or by `contact_sweep.may_be_within` (x_det, distance, live as for `pair_sums`).
    ordered: the vertices' changes go to change_i (N,) TRIALS-vectors first and are summed on one thread,
    as are the pairs' (the same sums on every run)."""
    for s in ti.static(range(TRIALS)):
        change[s] = 0.0
    inv_h2 = 1 / ti.cast(params[TIME_STEP], ti.f64) ** 2
    height, k_g = ti.cast(params[GROUND_HEIGHT], ti.f64), ti.cast(params[GROUND_STIFFNESS], ti.f64)
    ti.loop_config(serialize=serial)
    for k in range(color_order.shape[0]):
        i = color_order[k]
        delta = ti.Vector.zero(ti.f64, TRIALS)
        if corrected[body[i]]:
            x, y = ti.cast(state[X, i], ti.f64), ti.cast(state[Y, i], ti.f64)
            m_h2 = inv_h2 * ti.cast(mass[i], ti.f64)
            scale = ti.cast(1.0, ti.f64)
            for s in ti.static(range(TRIALS)):
                t = body_shift(i, body, corrected, d, alpha, scale)
                delta[s] = inertia_energy(m_h2, x + t, y) - inertia_energy(m_h2, x, y)
                if params[GROUND] > 0:
                    delta[s] += ground_energy(x[2] + t[2], height, k_g) - ground_energy(x[2], height, k_g)
                scale *= 0.5
        if ti.static(ordered):
            change_i[i] = delta
        else:
            for s in ti.static(range(TRIALS)):
                change[s] += delta[s]
    if ti.static(ordered):
        ti.loop_config(serialize=True)
        for k in range(color_order.shape[0]):
            for s in ti.static(range(TRIALS)):
                change[s] += change_i[color_order[k]][s]
    ti.loop_config(serialize=ordered)
    for p in range(n_pairs):
        if not live[p]:
            continue
        v = pair[p]
        a, b = body[v[0]], body[v[3]]
        if a == b or not (corrected[a] or corrected[b]):
            continue
        largest = (body_shift(v[0], body, corrected, d, alpha, 1.0).norm()          # the scale-1 translations
                   + body_shift(v[3], body, corrected, d, alpha, 1.0).norm())
        if largest == 0 or not may_be_within(distance, kind[p], p, moves_since(state, x_det, v), r, largest):
            continue
        x0, x1 = ti.cast(state[X, v[0]], ti.f64), ti.cast(state[X, v[1]], ti.f64)
        x2, x3 = ti.cast(state[X, v[2]], ti.f64), ti.cast(state[X, v[3]], ti.f64)
        before = barrier(pair_distance(kind[p], x0, x1, x2, x3), k_c, r)
        scale = ti.cast(1.0, ti.f64)
        for s in range(TRIALS):
            after = pair_distance(kind[p], x0 + body_shift(v[0], body, corrected, d, alpha, scale),
                                  x1 + body_shift(v[1], body, corrected, d, alpha, scale),
                                  x2 + body_shift(v[2], body, corrected, d, alpha, scale),
                                  x3 + body_shift(v[3], body, corrected, d, alpha, scale))
            change[s] += barrier(after, k_c, r) - before
            scale *= 0.5


@ti.kernel
def limit_to_bounds(state: ti.types.ndarray(), color_order: ti.types.ndarray(), body: ti.types.ndarray(),
                    corrected: ti.types.ndarray(), d: ti.types.ndarray(), alpha: ti.types.ndarray(),
                    x_det: ti.types.ndarray(), bound: ti.types.ndarray(), serial: ti.template()):
    """alpha_b = the largest scale in [0, 1] for which x_i + alpha_b d_b stays within |. - x_det,i| <= b_i
    for every vertex i of body b: the larger root of |m + alpha d|^2 = b_i^2, m = x_i - x_det,i (0 for a
    vertex outside its ball that the step does not bring back); x_det (N,) 3-vectors, bound (N,) in m."""
    ti.loop_config(serialize=serial)
    for k in range(color_order.shape[0]):
        i = color_order[k]
        b = body[i]
        step = d[b]
        a2 = step.dot(step)
        if corrected[b] and a2 > 0:
            m = ti.cast(state[X, i] - x_det[i], ti.f64)
            md = m.dot(step)
            q = ti.cast(bound[i], ti.f64)
            discriminant = md * md - a2 * (m.dot(m) - q * q)
            reach = ti.cast(0.0, ti.f64)
            if discriminant > 0:
                reach = ti.max((-md + ti.sqrt(discriminant)) / a2, 0.0)
            ti.atomic_min(alpha[b], reach)


@ti.kernel
def translate(state: ti.types.ndarray(), color_order: ti.types.ndarray(), body: ti.types.ndarray(),
              corrected: ti.types.ndarray(), d: ti.types.ndarray(), alpha: ti.types.ndarray(), scale: ti.f64,
              dtype: ti.template(), serial: ti.template()):
    """x_i += scale alpha_b d_b for every vertex i of a corrected body b."""
    ti.loop_config(serialize=serial)
    for k in range(color_order.shape[0]):
        i = color_order[k]
        b = body[i]
        if corrected[b]:
            state[X, i] += ti.cast(scale * alpha[b] * d[b], dtype)


class BodyTranslation:
    """The per-body translation correction of one simulation (module docstring).

    bodies: (N,) int body of each vertex (`mesh.bodies.body_labels`); free: (N,) bool, the vertices VBD
    moves; serial: every loop on one thread (small meshes on the CPU). `corrected` (B,) bool marks the
    bodies without fixed or kinematic vertices, `any` whether there is one; after `apply`, `scale` is the
    line search's factor (1 without contact, 0 for a dropped step) and `steps()` each body's translation
    scale alpha_b d_b.
    """

    def __init__(self, bodies: np.ndarray, free: np.ndarray, serial: bool = False):
        bodies = np.asarray(bodies, dtype=np.int32)
        n_bodies = int(bodies.max()) + 1
        self.corrected = np.bincount(bodies, weights=(~np.asarray(free, dtype=bool)).astype(float),
                                      minlength=n_bodies) == 0
        self.any = bool(self.corrected.any())
        self.body = ti.ndarray(ti.i32, len(bodies))
        self.body.from_numpy(bodies)
        self._corrected = ti.ndarray(ti.i32, n_bodies)
        self._corrected.from_numpy(self.corrected.astype(np.int32))
        self.F = ti.Vector.ndarray(3, ti.f64, n_bodies)
        self.D = ti.Vector.ndarray(3, ti.f64, n_bodies)
        self.K = ti.Matrix.ndarray(3, 3, ti.f64, n_bodies)
        self.touching = ti.ndarray(ti.i32, n_bodies)
        self.d = ti.Vector.ndarray(3, ti.f64, n_bodies)
        self.alpha = ti.ndarray(ti.f64, n_bodies)
        self._changes = np.zeros(TRIALS)      # written by `energy_changes` (a numpy array: read without a copy)
        self.scale = 1.0
        members = np.argsort(bodies, kind="stable").astype(np.int32)     # each body's vertices, ascending
        self._members = ti.ndarray(ti.i32, len(bodies))
        self._members.from_numpy(members)
        self._member_starts = ti.ndarray(ti.i32, n_bodies + 1)
        self._member_starts.from_numpy(np.searchsorted(bodies[members], np.arange(n_bodies + 1)).astype(np.int32))
        self._f_i = ti.Vector.ndarray(3, ti.f64, len(bodies))
        self._diagonal_i = ti.Vector.ndarray(3, ti.f64, len(bodies))
        self._change_i = ti.Vector.ndarray(TRIALS, ti.f64, len(bodies))
        self._ordered = running_on_cpu()    # sums in a fixed order: the same steps on every run
        self._serial = serial

    def apply(self, state, mass, adjacency, params, contact_stage, dtype) -> None:
        """Translate every corrected body by its alpha_b d_b at the current positions; contact_stage: the
        simulation's `ContactStage` (its pairs, x_det and bounds), or None."""
        color_order, offsets, others, adj_f, _ = adjacency
        body, corrected = self.body, self._corrected
        body_sums(state, mass, color_order, offsets, others, adj_f, params, body, corrected, self._members,
                  self._member_starts, self._f_i, self._diagonal_i, self.F, self.D, self.K, self.touching,
                  self._ordered, dtype, self._serial)
        if contact_stage is not None:
            det, c = contact_stage.detector, contact_stage.contact
            pair_sums(state, det.kind, det.pair, det.n_pairs, contact_stage.x_det, contact_stage.distance,
                      contact_stage.live, body, corrected, self.F, self.K, self.touching, params, c.stiffness,
                      c.radius, c.friction, c.friction_speed, self._ordered, dtype)
        body_steps(corrected, self.F, self.D, self.K, self.touching, self.d, self.alpha, params,
                   0.0 if contact_stage is None else contact_stage.contact.friction_speed, self._serial)
        self.scale = 1.0
        if contact_stage is not None:
            limit_to_bounds(state, color_order, body, corrected, self.d, self.alpha, contact_stage.x_det,
                            contact_stage.bound, self._serial)
            energy_changes(state, mass, color_order, params, body, corrected, self.d, self.alpha, det.kind, det.pair,
                           det.n_pairs, contact_stage.x_det, contact_stage.distance, contact_stage.live,
                           c.stiffness, c.radius, self._change_i, self._changes, self._ordered, self._serial)
            descending = np.flatnonzero(self._changes <= 0)
            self.scale = 0.5 ** int(descending[0]) if len(descending) else 0.0
        translate(state, color_order, body, corrected, self.d, self.alpha, self.scale, dtype, self._serial)

    def steps(self) -> np.ndarray:
        """(B,) 3-vectors: the translation scale alpha_b d_b in m of each body at the last `apply` (0 for
        bodies without a correction)."""
        return self.scale * self.alpha.to_numpy()[:, None] * self.d.to_numpy()
