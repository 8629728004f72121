"""Contact between bodies: the two-stage barrier of Offset Geometric Contact (OGC, Chen et al. 2025) on
the exact distance of vertex-triangle and edge-edge pairs, with lagged smoothed Coulomb friction.

A pair is four vertices x_0..x_3 with weights w (4,): the vector between its closest points is
D = sum_j w_j x_j and its distance d = |D|, n = D / d. For a vertex p against a triangle (a, b, c),
w = (1, -alpha, -beta, -gamma) with (alpha, beta, gamma) the barycentrics of the closest point; for
edges (a0, a1) and (b0, b1) with closest points a0 + s (a1 - a0) and b0 + t (b1 - b0),
w = (1 - s, s, -(1 - t), -t). Since the closest point is optimal, dd/dx_j = w_j n. The energy is

    b(d) = k/2 (r - d)^2               for tau <= d < r,     tau = r / 2
    b(d) = k tau^2 (1/2 - ln(d/tau))   for d < tau
    b(d) = 0                           for d >= r,

C2 at tau and infinite at d = 0. Vertex j of a pair gets the force -b'(d) w_j n and the block
b''(d) w_j^2 n n^T (n held fixed, VBD Sec. 3.5); the pair's 12x12 Hessian is the same product over
all four vertices, b''(d) (w (x) n)(w (x) n)^T, positive semi-definite because b'' > 0.

The exact pair Hessian adds b'(d) d2d/dx2 (indefinite, b' < 0), the curvature of the distance: with
u the closest-point parameters that are free (strictly inside their range: 0, 1 or 2 of alpha,
beta, gamma, s, t) and phi(x, u) = |sum_j w_j(u) x_j|, d(x) = phi(x, u*(x)), so by the implicit
function theorem d2d/dx2 = phi_xx - phi_xu phi_uu^-1 phi_ux. With W = (w_j I)_j (3x12), P = I - n n^T
and A = dD/du (3 x m): phi_xx = W^T P W / d, phi_uu = A^T P A / d, phi_xu = (dW/du)^T n + W^T P A / d.
Near parallel edges phi_uu is nearly singular and d bends sharply; there the exact Hessian lets the
Newton reference step onto the bend instead of stalling in front of it.

Written once: the `ti.func`s serve the sweep, energy() and the Taichi Newton; the numpy twins
(`*_np`, vectorised over pairs) serve the Newton reference and the tests.
"""
import numbers
from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from .._ti import ti
from ..errors import ConfigError
from .ground import friction_scale


@dataclass(frozen=True)
class Contact:
    """Contact between bodies (and within one, `self_contact`), OGC's two-stage barrier.

    stiffness: k in N/m. radius: r in m, the distance below which the barrier acts. query_radius: m,
    the distance within which pairs are collected (> radius; None: 3 radius). friction: Coulomb mu,
    dimensionless. friction_speed: m/s, below which friction is smoothed. self_contact: pairs within a
    body too, between primitives that share no vertex and were farther apart than query_radius at rest
    (closer ones, such as the turns of a body modelled tightly coiled, are never paired).
    detection_interval: iterations between checks of whether a pair the last detection missed
    may have come within the radius, and if so a new detection (>= 1). bound_relaxation: g in (0, 1/2), a
    vertex moves at most g times its distance to its closest pair between refreshes of the bounds.
    """

    stiffness: float = 1e5
    radius: float = 2e-3
    query_radius: float = None
    friction: float = 0.0
    friction_speed: float = 1e-3
    self_contact: bool = True
    detection_interval: int = 5
    bound_relaxation: float = 0.45

    def __post_init__(self):
        for name in ("stiffness", "radius", "query_radius", "friction", "friction_speed", "bound_relaxation"):
            value = getattr(self, name)
            if not (name == "query_radius" and value is None):
                object.__setattr__(self, name, _finite_number(name, value))
        if self.query_radius is None:
            if not np.isfinite(3 * self.radius):
                raise ConfigError(f"contact radius must be a finite number of metres whose 3 x (the default "
                                  f"query_radius) is finite too, got {self.radius!r}")
            object.__setattr__(self, "query_radius", 3 * self.radius)
        if self.stiffness <= 0:
            raise ConfigError(f"contact stiffness must be > 0 N/m, got {self.stiffness}")
        if self.radius <= 0:
            raise ConfigError(f"contact radius must be > 0 m, got {self.radius}")
        if self.query_radius <= self.radius:
            raise ConfigError(f"contact query_radius must exceed radius {self.radius} m, got {self.query_radius}; "
                              "leave it None for 3 radius")
        if self.friction < 0:
            raise ConfigError(f"contact friction must be >= 0, got {self.friction}")
        if self.friction_speed <= 0:
            raise ConfigError(f"contact friction_speed must be > 0 m/s, got {self.friction_speed}")
        if not isinstance(self.self_contact, (bool, np.bool_)):
            raise ConfigError(f"contact self_contact must be True or False, got {self.self_contact!r}")
        if (isinstance(self.detection_interval, (bool, np.bool_))
                or not isinstance(self.detection_interval, numbers.Integral) or self.detection_interval < 1):
            raise ConfigError(f"contact detection_interval must be an integer >= 1 (iterations), "
                              f"got {self.detection_interval!r}")
        if not 0 < self.bound_relaxation < 0.5:
            raise ConfigError(f"contact bound_relaxation must be in (0, 1/2) so that bounds prevent crossing, "
                              f"got {self.bound_relaxation}")


def _finite_number(name: str, value) -> float:
    """value as a float, or a one-line `ConfigError` where it is not a finite real number (a bool, a
    string, NaN, an integer too large for a float)."""
    number = np.nan
    if isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_)):
        try:
            number = float(value)
        except OverflowError:
            number = np.inf
    if not np.isfinite(number):
        shown = repr(value)
        shown = shown if len(shown) <= 40 else shown[:36] + " ..."
        raise ConfigError(f"contact {name} must be a finite number, got {shown}")
    return number


class PairKind(IntEnum):
    """What the four vertices of a pair are: a vertex and a triangle (p, a, b, c), or two edges
    (a0, a1, b0, b1). Stored as this int in the pair arrays the kernels read."""

    VERTEX_TRIANGLE = 0
    EDGE_EDGE = 1


# Relative size of det(Gram) below which a triangle or an edge pair counts as degenerate (flat
# triangle, parallel edges): then the closest points lie on the primitives' boundaries.
DEGENERATE = 1e-12


# ---------------------------------------------------------------------------------------------
# Taichi functions.
# ---------------------------------------------------------------------------------------------
@ti.func
def point_segment(p, a, b, dtype: ti.template()):
    """Closest point a + t (b - a) of the segment to p: returns (t in [0, 1], squared distance)."""
    e = b - a
    ee = e.dot(e)
    t = ti.cast(0, dtype)
    if ee > 0:
        t = ti.min(ti.max((p - a).dot(e) / ee, 0), 1)
    D = p - a - t * e
    return t, D.dot(D)


@ti.func
def point_triangle(p, a, b, c, dtype: ti.template()):
    """Exact distance d from p to the triangle (a, b, c) and the weights w (4,) = (1, -alpha, -beta, -gamma)
    of its closest point; the interior if p projects inside, else the nearest of the three edges."""
    e1 = b - a
    e2 = c - a
    v = p - a
    A = e1.dot(e1)
    B = e1.dot(e2)
    C = e2.dot(e2)
    det = A * C - B * B
    w = ti.Vector.zero(dtype, 4)
    dd = ti.cast(0, dtype)
    inside = False
    if det > DEGENERATE * A * C:
        beta = (C * v.dot(e1) - B * v.dot(e2)) / det
        gamma = (A * v.dot(e2) - B * v.dot(e1)) / det
        if beta >= 0 and gamma >= 0 and beta + gamma <= 1:
            inside = True
            w = ti.Vector([1, -(1 - beta - gamma), -beta, -gamma], dt=dtype)
            D = v - beta * e1 - gamma * e2
            dd = D.dot(D)
    if not inside:
        t, dd = point_segment(p, a, b, dtype)
        w = ti.Vector([1, -(1 - t), -t, 0], dt=dtype)
        t2, dd2 = point_segment(p, b, c, dtype)
        if dd2 < dd:
            dd = dd2
            w = ti.Vector([1, 0, -(1 - t2), -t2], dt=dtype)
        t3, dd3 = point_segment(p, c, a, dtype)
        if dd3 < dd:
            dd = dd3
            w = ti.Vector([1, -t3, 0, -(1 - t3)], dt=dtype)
    return ti.sqrt(dd), w


@ti.func
def edge_edge(a0, a1, b0, b1, dtype: ti.template()):
    """Exact distance d between the segments (a0, a1) and (b0, b1) and the weights
    w (4,) = (1 - s, s, -(1 - t), -t) of their closest points; the interior solution if both lie
    inside, else the nearest endpoint-to-segment pair (which covers parallel edges)."""
    e1 = a1 - a0
    e2 = b1 - b0
    r = a0 - b0
    A = e1.dot(e1)
    B = e1.dot(e2)
    C = e2.dot(e2)
    det = A * C - B * B
    w = ti.Vector.zero(dtype, 4)
    dd = ti.cast(0, dtype)
    inside = False
    if det > DEGENERATE * A * C:
        s = (B * e2.dot(r) - C * e1.dot(r)) / det
        t = (A * e2.dot(r) - B * e1.dot(r)) / det
        if 0 <= s <= 1 and 0 <= t <= 1:
            inside = True
            w = ti.Vector([1 - s, s, -(1 - t), -t], dt=dtype)
            D = r + s * e1 - t * e2
            dd = D.dot(D)
    if not inside:
        t0, dd = point_segment(a0, b0, b1, dtype)
        w = ti.Vector([1, 0, -(1 - t0), -t0], dt=dtype)
        t1, dd1 = point_segment(a1, b0, b1, dtype)
        if dd1 < dd:
            dd = dd1
            w = ti.Vector([0, 1, -(1 - t1), -t1], dt=dtype)
        s0, dd2 = point_segment(b0, a0, a1, dtype)
        if dd2 < dd:
            dd = dd2
            w = ti.Vector([1 - s0, s0, -1, 0], dt=dtype)
        s1, dd3 = point_segment(b1, a0, a1, dtype)
        if dd3 < dd:
            dd = dd3
            w = ti.Vector([1 - s1, s1, 0, -1], dt=dtype)
    return ti.sqrt(dd), w


@ti.func
def pair_geometry(kind, x0, x1, x2, x3, dtype: ti.template()):
    """Distance d, weights w (4,) and unit normal n = sum_j w_j x_j / d of a pair of `PairKind` kind."""
    d = ti.cast(0, dtype)
    w = ti.Vector.zero(dtype, 4)
    if kind == int(PairKind.VERTEX_TRIANGLE):
        d, w = point_triangle(x0, x1, x2, x3, dtype)
    else:
        d, w = edge_edge(x0, x1, x2, x3, dtype)
    n = (w[0] * x0 + w[1] * x1 + w[2] * x2 + w[3] * x3) / d
    return d, w, n


@ti.func
def barrier(d, k, r):
    """OGC's two-stage energy b(d) in J (module docstring); 0 for d >= r."""
    tau = r / 2
    b = d * 0
    if d < tau:
        b = k * tau * tau * (0.5 - ti.log(d / tau))
    elif d < r:
        b = k / 2 * (r - d) ** 2
    return b


@ti.func
def barrier_derivatives(d, k, r):
    """b'(d) in N and b''(d) in N/m; both 0 for d >= r. tau = r/2 is written out (r / 2 would be of
    Taichi's default float type, and float32 arguments would give float64 results)."""
    db = d * 0
    d2b = d * 0
    if 2 * d < r:                               # d < tau: -k tau^2 / d and k tau^2 / d^2
        db = -k * r * r / (4 * d)
        d2b = k * r * r / (4 * d * d)
    elif d < r:
        db = -k * (r - d)
        d2b = k + d * 0
    return db, d2b


@ti.func
def contact_force_hessian(d, w_j, n, k, r):
    """Force -b'(d) w_j n (3,) and block b''(d) w_j^2 n n^T (3x3) of vertex j of a pair."""
    db, d2b = barrier_derivatives(d, k, r)
    return -db * w_j * n, d2b * w_j * w_j * n.outer_product(n)


@ti.func
def contact_friction(u, n, w_j, f_n, mu, eps_u, dtype: ti.template()):
    """Friction force (3,) and block (3x3) of vertex j of a pair: the ground's lagged smoothed Coulomb law
    on the pair's relative tangential displacement u_t = (I - n n^T) u this step, u = sum_j w_j (x_j - x_n,j),
    with normal force f_n = |b'(d)| and eps_u = friction_speed h: force -w_j k_f u_t, block
    w_j^2 k_f (I - n n^T), k_f = mu f_n f1(s)/s, s = |u_t|."""
    P = ti.Matrix.identity(dtype, 3) - n.outer_product(n)
    u_t = P @ u
    k_f = mu * f_n * ti.cast(friction_scale(u_t.norm(), eps_u), dtype)
    return -w_j * k_f * u_t, w_j * w_j * k_f * P


@ti.func
def distance_gradient(w, n, dtype: ti.template()):
    """dd/dx = w (x) n (12,) of a pair with weights w (4,) and normal n, coordinates vertex by vertex."""
    J = ti.Vector.zero(dtype, 12)
    for j in ti.static(range(4)):
        for a in ti.static(range(3)):
            J[3 * j + a] = w[j] * n[a]
    return J


@ti.func
def pair_energy_gradient(kind, x0, x1, x2, x3, k, r, dtype: ti.template()):
    """Energy b (J) and gradient g (12,) = b'(d) (w (x) n) of one pair, coordinates ordered vertex by
    vertex; for the Taichi Newton."""
    d, w, n = pair_geometry(kind, x0, x1, x2, x3, dtype)
    db, _ = barrier_derivatives(d, k, r)
    return barrier(d, k, r), db * distance_gradient(w, n, dtype)


@ti.func
def free_directions(kind, w, dtype: ti.template()):
    """The free closest-point parameters u of a pair with weights w (4,): dw/du_i (4,) for i = 0, 1 and
    their number m (0-2). On each primitive (vertex 0, or edge 0-1, against the rest) the vertices of
    nonzero weight span the feature the closest point lies inside; its parameters move weight from the
    first of them to each other one, dw/du = +-(e_j - e_first) (the sign does not matter below)."""
    second = 1 if kind == int(PairKind.VERTEX_TRIANGLE) else 2
    c0 = ti.Vector.zero(dtype, 4)
    c1 = ti.Vector.zero(dtype, 4)
    m = 0
    first = ti.Vector([-1, -1])                 # the first vertex of nonzero weight on each primitive
    for j in ti.static(range(4)):
        if w[j] != 0:
            side = 0 if j < second else 1
            if first[side] < 0:
                first[side] = j
            else:
                c = ti.Vector.zero(dtype, 4)
                c[j] = 1
                for i in ti.static(range(4)):
                    if i == first[side]:
                        c[i] = -1
                if m == 0:
                    c0 = c
                else:
                    c1 = c
                m += 1
    return c0, c1, m


# What the 3x3 blocks of one pair's 12x12 Hessian are made of (`pair_curvature`, `pair_hessian_block`): weights
# w (4,), normal n (3,), b''(d) in N/m, and b'(d) times the curvature of the distance d2d/dx2 = phi_xx - phi_xu
# phi_uu^-1 phi_ux (module docstring) by parts: s = b'(d) in N (0 for the PSD Hessian), P_d = P / d (3x3), the
# rows of phi_xu per vertex for the two free parameters, F0 and F1 (4x3), and phi_uu^-1 (2x2).
PairCurvature = ti.types.struct(w=ti.types.vector(4, ti.f64), n=ti.types.vector(3, ti.f64), d2b=ti.f64, s=ti.f64,
                                P_d=ti.types.matrix(3, 3, ti.f64), F0=ti.types.matrix(4, 3, ti.f64),
                                F1=ti.types.matrix(4, 3, ti.f64), inverse=ti.types.matrix(2, 2, ti.f64))


@ti.func
def pair_curvature(kind, x0, x1, x2, x3, k, r, exact):
    """`PairCurvature` of one pair (float64); with exact (int, nonzero) the curvature term b'(d) d2d/dx2
    (indefinite) is kept, else s = 0 and the blocks are those of the PSD b''(d) (w (x) n)(w (x) n)^T.
    The Hessian is never formed as one 12x12 matrix: Taichi took 10 s to compile one that was."""
    d, w, n = pair_geometry(kind, x0, x1, x2, x3, ti.f64)
    db, d2b = barrier_derivatives(d, k, r)
    c = PairCurvature(w=w, n=n, d2b=d2b, s=0.0, P_d=ti.Matrix.zero(ti.f64, 3, 3), F0=ti.Matrix.zero(ti.f64, 4, 3),
                      F1=ti.Matrix.zero(ti.f64, 4, 3), inverse=ti.Matrix.zero(ti.f64, 2, 2))
    if exact != 0 and db != 0:
        c0, c1, m = free_directions(kind, w, ti.f64)
        P = ti.Matrix.identity(ti.f64, 3) - n.outer_product(n)
        A0 = c0[0] * x0 + c0[1] * x1 + c0[2] * x2 + c0[3] * x3
        A1 = c1[0] * x0 + c1[1] * x1 + c1[2] * x2 + c1[3] * x3
        PA0, PA1 = P @ A0, P @ A1
        phi_uu = ti.Matrix([[A0.dot(PA0), A0.dot(PA1)], [A1.dot(PA0), A1.dot(PA1)]], dt=ti.f64) / d
        if m < 2:                                   # unused parameters: identity rows, zero couplings
            phi_uu[1, 1] = 1
        if m < 1:
            phi_uu[0, 0] = 1
        c.s = db
        c.P_d = P / d
        c.F0 = c0.outer_product(n) + w.outer_product(PA0) / d
        c.F1 = c1.outer_product(n) + w.outer_product(PA1) / d
        c.inverse = phi_uu.inverse()
    return c


@ti.func
def row3(M: ti.template(), j):
    """Row j (j may be runtime) of a (rows, 3) local matrix or ndarray as a float64 3-vector."""
    return ti.Vector([M[j, 0], M[j, 1], M[j, 2]], dt=ti.f64)


@ti.func
def pair_hessian_block(c: ti.template(), j, l):
    """The 3x3 block (vertex j, vertex l) of the pair Hessian described by c (`pair_curvature`):
    b'' w_j w_l n n^T + s (w_j w_l P / d - sum_uv phi_uu^-1[u, v] F_u[j] F_v[l]^T); j, l may be runtime."""
    wj, wl = c.w[j], c.w[l]
    F0j, F1j, F0l, F1l = row3(c.F0, j), row3(c.F1, j), row3(c.F0, l), row3(c.F1, l)
    G0 = c.inverse[0, 0] * F0l + c.inverse[0, 1] * F1l
    G1 = c.inverse[1, 0] * F0l + c.inverse[1, 1] * F1l
    curvature = wj * wl * c.P_d - F0j.outer_product(G0) - F1j.outer_product(G1)
    return c.d2b * wj * wl * c.n.outer_product(c.n) + c.s * curvature


# ---------------------------------------------------------------------------------------------
# Numpy twins, vectorised over P pairs.
# ---------------------------------------------------------------------------------------------
def _dot(u, v):
    return np.einsum("...i,...i->...", u, v)


def point_segment_np(p, a, b):
    """(t (P,), squared distance (P,)) of the closest points a + t (b - a) to p; p, a, b (P, 3)."""
    e = b - a
    ee = _dot(e, e)
    t = np.where(ee > 0, np.clip(_dot(p - a, e) / np.where(ee > 0, ee, 1.0), 0.0, 1.0), 0.0)
    D = p - a - t[:, None] * e
    return t, _dot(D, D)


def _nearest(candidates):
    """Pick, per pair, the first candidate (squared distance (P,), weights (P, 4)) of least distance."""
    dd, w = candidates[0]
    dd, w = dd.copy(), w.copy()
    for dd_k, w_k in candidates[1:]:
        closer = dd_k < dd
        dd = np.where(closer, dd_k, dd)
        w = np.where(closer[:, None], w_k, w)
    return dd, w


def point_triangle_np(p, a, b, c):
    """(d (P,), w (P, 4)) of vertex p against triangle (a, b, c), all (P, 3); as `point_triangle`."""
    e1, e2, v = b - a, c - a, p - a
    A, B, C = _dot(e1, e1), _dot(e1, e2), _dot(e2, e2)
    det = A * C - B * B
    regular = det > DEGENERATE * A * C
    safe = np.where(regular, det, 1.0)
    beta = (C * _dot(v, e1) - B * _dot(v, e2)) / safe
    gamma = (A * _dot(v, e2) - B * _dot(v, e1)) / safe
    inside = regular & (beta >= 0) & (gamma >= 0) & (beta + gamma <= 1)
    one, zero = np.ones_like(A), np.zeros_like(A)
    t1, dd1 = point_segment_np(p, a, b)
    t2, dd2 = point_segment_np(p, b, c)
    t3, dd3 = point_segment_np(p, c, a)
    dd, w = _nearest([(dd1, np.stack([one, -(1 - t1), -t1, zero], 1)),
                      (dd2, np.stack([one, zero, -(1 - t2), -t2], 1)),
                      (dd3, np.stack([one, -t3, zero, -(1 - t3)], 1))])
    D = v - beta[:, None] * e1 - gamma[:, None] * e2
    dd = np.where(inside, _dot(D, D), dd)
    w = np.where(inside[:, None], np.stack([one, -(1 - beta - gamma), -beta, -gamma], 1), w)
    return np.sqrt(dd), w


def edge_edge_np(a0, a1, b0, b1):
    """(d (P,), w (P, 4)) of edges (a0, a1) and (b0, b1), all (P, 3); as `edge_edge`."""
    e1, e2, r = a1 - a0, b1 - b0, a0 - b0
    A, B, C = _dot(e1, e1), _dot(e1, e2), _dot(e2, e2)
    det = A * C - B * B
    regular = det > DEGENERATE * A * C
    safe = np.where(regular, det, 1.0)
    s = (B * _dot(e2, r) - C * _dot(e1, r)) / safe
    t = (A * _dot(e2, r) - B * _dot(e1, r)) / safe
    inside = regular & (s >= 0) & (s <= 1) & (t >= 0) & (t <= 1)
    one, zero = np.ones_like(A), np.zeros_like(A)
    t0, dd0 = point_segment_np(a0, b0, b1)
    t1, dd1 = point_segment_np(a1, b0, b1)
    s0, dd2 = point_segment_np(b0, a0, a1)
    s1, dd3 = point_segment_np(b1, a0, a1)
    dd, w = _nearest([(dd0, np.stack([one, zero, -(1 - t0), -t0], 1)),
                      (dd1, np.stack([zero, one, -(1 - t1), -t1], 1)),
                      (dd2, np.stack([1 - s0, s0, -one, zero], 1)),
                      (dd3, np.stack([1 - s1, s1, zero, -one], 1))])
    D = r + s[:, None] * e1 - t[:, None] * e2
    dd = np.where(inside, _dot(D, D), dd)
    w = np.where(inside[:, None], np.stack([1 - s, s, -(1 - t), -t], 1), w)
    return np.sqrt(dd), w


def pair_geometry_np(kind, X):
    """(d (P,), w (P, 4), n (P, 3)) of pairs with `PairKind` kind (P,) and vertex positions X (P, 4, 3)."""
    kind = np.asarray(kind)
    X = np.asarray(X, dtype=np.float64)
    d_vt, w_vt = point_triangle_np(X[:, 0], X[:, 1], X[:, 2], X[:, 3])
    d_ee, w_ee = edge_edge_np(X[:, 0], X[:, 1], X[:, 2], X[:, 3])
    vt = kind == PairKind.VERTEX_TRIANGLE
    d = np.where(vt, d_vt, d_ee)
    w = np.where(vt[:, None], w_vt, w_ee)
    n = np.einsum("pj,pja->pa", w, X) / d[:, None]
    return d, w, n


def barrier_np(d, k: float, r: float):
    """b(d) (J) for an array of distances d (m)."""
    d = np.asarray(d, dtype=np.float64)
    tau = r / 2
    with np.errstate(divide="ignore"):
        inner = k * tau * tau * (0.5 - np.log(np.where(d < tau, d, tau) / tau))
    return np.where(d < tau, inner, np.where(d < r, 0.5 * k * (r - d) ** 2, 0.0))


def barrier_derivatives_np(d, k: float, r: float):
    """(b'(d) in N, b''(d) in N/m) for an array of distances d (m)."""
    d = np.asarray(d, dtype=np.float64)
    tau = r / 2
    safe = np.where(d < tau, d, tau)
    db = np.where(d < tau, -k * tau * tau / safe, np.where(d < r, -k * (r - d), 0.0))
    d2b = np.where(d < tau, k * tau * tau / safe ** 2, np.where(d < r, k, 0.0))
    return db, d2b


def pair_energy_np(kind, X, contact: Contact):
    """(P,) energy b(d) in J of each pair; kind (P,), X (P, 4, 3)."""
    d, _, _ = pair_geometry_np(kind, X)
    return barrier_np(d, contact.stiffness, contact.radius)


def pair_forces_np(kind, X, contact: Contact):
    """(P, 4, 3) force -b'(d) w_j n on each vertex j of each pair; they sum to zero over j."""
    d, w, n = pair_geometry_np(kind, X)
    db, _ = barrier_derivatives_np(d, contact.stiffness, contact.radius)
    return -db[:, None, None] * w[:, :, None] * n[:, None, :]


def pair_blocks_np(kind, X, contact: Contact):
    """(P, 4, 3, 3) per-vertex block b''(d) w_j^2 n n^T of each vertex j of each pair."""
    d, w, n = pair_geometry_np(kind, X)
    _, d2b = barrier_derivatives_np(d, contact.stiffness, contact.radius)
    return (d2b[:, None] * w ** 2)[:, :, None, None] * np.einsum("pa,pb->pab", n, n)[:, None]


def free_directions_np(kind, w):
    """(dw/du (P, 2, 4), m (P,)): the free closest-point parameters of pairs with weights w (P, 4), as
    `free_directions` (unused rows zero)."""
    kind, w = np.asarray(kind), np.asarray(w)
    rows = np.arange(len(w))
    second = np.where(kind == PairKind.VERTEX_TRIANGLE, 1, 2)
    c = np.zeros((len(w), 2, 4))
    m = np.zeros(len(w), dtype=np.int64)
    first = np.full((len(w), 2), -1)
    for j in range(4):
        side = (j >= second).astype(np.int64)
        anchor = first[rows, side]
        active = w[:, j] != 0
        new = active & (anchor < 0)
        first[rows[new], side[new]] = j
        free = rows[active & (anchor >= 0)]
        c[free, m[free], j] = 1
        c[free, m[free], anchor[free]] = -1
        m[free] += 1
    return c, m


def distance_hessian_np(kind, X):
    """(P, 12, 12) d2d/dx2 of pairs with `PairKind` kind (P,) and positions X (P, 4, 3), d > 0; as
    `pair_curvature`."""
    X = np.asarray(X, dtype=np.float64)
    d, w, n = pair_geometry_np(kind, X)
    c, m = free_directions_np(kind, w)
    A = np.einsum("pij,pja->pia", c, X)                                   # (P, 2, 3)
    PA = A - np.einsum("pia,pa->pi", A, n)[:, :, None] * n[:, None, :]
    phi_uu = np.einsum("pia,pla->pil", A, PA) / d[:, None, None]
    phi_uu[m < 2, 1, 1] = 1
    phi_uu[m < 1, 0, 0] = 1
    F = (c[:, :, :, None] * n[:, None, None, :]
         + w[:, None, :, None] * PA[:, :, None, :] / d[:, None, None, None]).reshape(-1, 2, 12)
    P = np.eye(3) - np.einsum("pa,pb->pab", n, n)
    H = np.einsum("pj,pk,pab->pjakb", w, w, P).reshape(-1, 12, 12) / d[:, None, None]
    return H - np.einsum("pia,pil,plb->pab", F, np.linalg.inv(phi_uu), F)


def pair_hessian_np(kind, X, contact: Contact, exact: bool = False):
    """(P, 12, 12) pair Hessian, coordinates ordered vertex by vertex: the PSD b''(d) (w (x) n)(w (x) n)^T,
    plus b'(d) d2d/dx2 when exact (the exact Hessian of b(d(x)), indefinite); as `pair_curvature` and
    `pair_hessian_block`."""
    d, w, n = pair_geometry_np(kind, X)
    db, d2b = barrier_derivatives_np(d, contact.stiffness, contact.radius)
    J = (w[:, :, None] * n[:, None, :]).reshape(-1, 12)
    H = d2b[:, None, None] * np.einsum("pa,pb->pab", J, J)
    if exact:
        near = db != 0
        H[near] += db[near, None, None] * distance_hessian_np(np.asarray(kind)[near], np.asarray(X)[near])
    return H


def friction_scale_np(s, eps_u: float):
    """f1(s)/s in 1/m of the ground's smoothed Coulomb law (`ground.friction_scale`), for an array s."""
    s = np.asarray(s, dtype=np.float64)
    return np.where(s < eps_u, (2 - s / eps_u) / eps_u, 1 / np.where(s < eps_u, 1.0, s))


def pair_friction_np(kind, X, X_n, contact: Contact, h: float):
    """(forces (P, 4, 3), blocks (P, 4, 3, 3)) of lagged friction on each vertex of each pair, X the
    current and X_n the step-start positions (P, 4, 3), h the time step in s; as `contact_friction`."""
    d, w, n = pair_geometry_np(kind, X)
    db, _ = barrier_derivatives_np(d, contact.stiffness, contact.radius)
    u = np.einsum("pj,pja->pa", w, np.asarray(X) - np.asarray(X_n))
    P = np.eye(3) - np.einsum("pa,pb->pab", n, n)
    u_t = np.einsum("pab,pb->pa", P, u)
    k_f = contact.friction * np.abs(db) * friction_scale_np(np.linalg.norm(u_t, axis=1),
                                                            contact.friction_speed * h)
    forces = -(k_f[:, None] * w)[:, :, None] * u_t[:, None, :]
    blocks = (k_f[:, None] * w ** 2)[:, :, None, None] * P[:, None]
    return forces, blocks


# ---------------------------------------------------------------------------------------------
# Sums over the pairs, for the Newton reference (newton.StepProblem).
# ---------------------------------------------------------------------------------------------
def contact_energy_np(x, kind, vertices, contact: Contact) -> float:
    """E_c = sum of b(d) over the pairs in J; x (N, 3), kind (P,) `PairKind`, vertices (P, 4)."""
    return float(pair_energy_np(kind, x[vertices], contact).sum())


def contact_gradient_np(x, kind, vertices, contact: Contact) -> np.ndarray:
    """(N, 3) dE_c/dx: minus the pair forces, gathered at their vertices."""
    g = np.zeros_like(x, dtype=np.float64)
    np.add.at(g, np.asarray(vertices).ravel(), -pair_forces_np(kind, x[vertices], contact).reshape(-1, 3))
    return g


def contact_hessian_np(x, kind, vertices, contact: Contact):
    """(3N, 3N) scipy.sparse csr sum of the PSD pair Hessians b''(d) (w (x) n)(w (x) n)^T."""
    import scipy.sparse as sp

    blocks = pair_hessian_np(kind, x[vertices], contact)
    dof = (3 * np.asarray(vertices)[:, :, None] + np.arange(3)).reshape(-1, 12)
    rows = np.broadcast_to(dof[:, :, None], blocks.shape).ravel()
    cols = np.broadcast_to(dof[:, None, :], blocks.shape).ravel()
    n = 3 * len(x)
    return sp.coo_matrix((blocks.ravel(), (rows, cols)), shape=(n, n)).tocsr()
