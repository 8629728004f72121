"""Contact in a VBD simulation (issue 17): the detector, the positions of the last detection and when
to detect again, the contact term of G and the measurements the scripts read.

Detections happen before any iteration that follows one in which a vertex hit its bound (bounds may
cost detections, never progress), and at the start of a step (at x_n; the initial guess is then clamped
to the bounds) and every `Contact.detection_interval` iterations unless no pair can have come closer
than the radius since the last one: a pair it did not find was at least query_radius q apart, and
moves closer by at most twice the largest displacement delta since then, so while
2 delta < q - radius the pairs and bounds of the last detection are still complete and valid (the
bounds limit the displacement from x_det, wherever the step started).
"""
import numpy as np
from scipy.spatial import cKDTree

from .._ti import ti
from ..errors import ConfigError
from ..physics.contact import Contact
from ..physics.contact_detection import ContactDetector
from . import contact_sweep
from .layout import X, X_N


class ContactStage:
    """The contact of one simulation under one `Contact`.

    mesh: the `TetMesh` (every body); free: (N,) bool, the vertices VBD moves; dtype: float type of the
    state. `bound_hits` counts the vertices clamped to their bound since construction, `detections` the
    detections.
    """

    def __init__(self, mesh, free: np.ndarray, contact: Contact, dtype):
        self.contact = contact
        self.dtype = dtype
        self.free = np.asarray(free, dtype=bool)
        self.detector = ContactDetector(mesh, free, contact, dtype)
        self.bodies = self.detector.bodies
        n = mesh.n_vertices
        self.x_det = ti.Vector.ndarray(3, dtype, n)
        self._target = ti.Vector.ndarray(3, dtype, n)
        self.touched = ti.ndarray(ti.i32, n)
        self._since_detection = 0
        self._due = False
        self.bound_hits = 0
        self.detections = 0

    def detect(self, state, row: int = X) -> int:
        """Find the pairs at state[row], make those positions x_det; returns the number of pairs."""
        n_pairs = self.detector.detect(state, row)
        contact_sweep.copy_row(state, row, self.x_det)
        self._since_detection = 0
        self._due = False
        self.detections += 1
        return n_pairs

    def _stale(self, state, row: int) -> bool:
        """Whether at state[row] a pair the last detection missed may have come closer than the radius
        (module docstring)."""
        c = self.contact
        return 2 * contact_sweep.largest_move(state, row, self.x_det) >= c.query_radius - c.radius

    def begin_step(self, state, color_order) -> None:
        """Detect at x_n when due and clamp the initial guess to the bounds; no vertex has touched yet.
        Called after the guess is set, so the row X_N holds x_n and X the guess."""
        contact_sweep.clear(self.touched)
        if self._due or self._stale(state, X_N):
            self.detect(state, X_N)
        hits = contact_sweep.clamp_to_bounds(state, color_order, self.x_det, self.detector.bound, self.dtype)
        self.bound_hits += hits
        self._due = hits > 0

    def iterate(self, state, mass, adjacency, params, n_colors: int, dtype, omega=None) -> int:
        """One VBD iteration with contact (`contact_sweep.vbd_contact_iteration`), detecting first when
        due, then the Chebyshev step of weight omega (None: none) for the vertices that have not touched this
        step; returns the number of bound hits."""
        if self._since_detection >= self.contact.detection_interval and not self._due:
            self._due = self._stale(state, X)
            self._since_detection = 0
        if self._due:
            self.detect(state, X)
        d, c = self.detector, self.contact
        hits = contact_sweep.vbd_contact_iteration(state, mass, *adjacency, params, d.kind, d.pair,
                                                   d.incidence_offsets, d.incidence, self.x_det, d.bound,
                                                   self._target, self.touched, c.stiffness, c.radius, c.friction,
                                                   c.friction_speed, n_colors, dtype)
        if omega is not None:
            hits += contact_sweep.chebyshev_contact_step(state, adjacency[0], self.touched, self.x_det, d.bound,
                                                         omega, dtype)
        self._since_detection += 1
        self._due = hits > 0
        self.bound_hits += hits
        return hits

    def energy(self, state, dtype) -> float:
        """E_c in J at the current positions (detected there)."""
        self.detect(state, X)
        d = self.detector
        return float(contact_sweep.contact_energy(state, d.kind, d.pair, d.n_pairs, self.contact.stiffness,
                                                  self.contact.radius, dtype))

    def add_local_systems(self, state, color_order, params, f, H, dtype) -> float:
        """Add the contact terms to the per-vertex f (N,) and H (N,) 3x3 at the current positions (detected
        there); returns max_i |f_i| in N."""
        self.detect(state, X)
        d, c = self.detector, self.contact
        return float(contact_sweep.add_contact_local_systems(state, color_order, d.kind, d.pair, d.incidence_offsets,
                                                             d.incidence, params, f, H, c.stiffness, c.radius,
                                                             c.friction, c.friction_speed, dtype))

    def distances(self, state) -> np.ndarray:
        """(P,) distances in m of the pairs under query_radius at the current positions."""
        self.detect(state, X)
        return self.detector.pairs()[3].astype(np.float64)

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
            raise ConfigError(f"bodies {a} and {b} intersect (a surface edge passes through a triangle, distance 0 m); "
                              "move them apart before simulating")
        self.detect(state, X)
        _, vertices, _, distance = self.detector.pairs()
        touching = distance <= 0
        if touching.any():
            p = int(np.flatnonzero(touching)[0])
            a, b = sorted((int(self.bodies[vertices[p, 0]]), int(self.bodies[vertices[p, 3]])))
            raise ConfigError(f"bodies {a} and {b} touch (distance {distance[p]:.3g} m); "
                              "leave a gap between them before simulating")


def surface_crossing(x: np.ndarray, surface, bodies: np.ndarray, free: np.ndarray, self_contact: bool):
    """(body a, body b) of the first surface edge that passes through a surface triangle sharing none of
    its vertices (of another body, or of its own with self_contact; not both fixed or kinematic, as the
    pairs), else None; x (N, 3), free (N,) bool. Decided by
    signed volumes: the edge's ends lie strictly on either side of the triangle's plane and the edge's
    line passes inside the triangle."""
    triangles, edges = surface.triangles, surface.edges
    centroid = x[triangles].mean(axis=1)
    reach = np.linalg.norm(x[triangles] - centroid[:, None], axis=2).max()
    half = np.linalg.norm(x[edges[:, 1]] - x[edges[:, 0]], axis=1).max() / 2
    near = cKDTree(centroid).query_ball_point(x[edges].mean(axis=1), reach + half)
    e = np.repeat(np.arange(len(edges)), [len(k) for k in near])
    t = np.concatenate([np.asarray(k, dtype=np.int64) for k in near] + [np.zeros(0, np.int64)])
    shares = (edges[e][:, :, None] == triangles[t][:, None, :]).any(axis=(1, 2))
    same = bodies[edges[e, 0]] == bodies[triangles[t, 0]]
    moves = free[edges[e]].any(axis=1) | free[triangles[t]].any(axis=1)
    keep = ~shares & (~same | self_contact) & moves
    e, t = e[keep], t[keep]

    def six_volume(a, b, c, d):
        return np.einsum("ka,ka->k", np.cross(b - a, c - a), d - a)

    p, q = x[edges[e, 0]], x[edges[e, 1]]
    a, b, c = (x[triangles[t, k]] for k in range(3))
    sides = six_volume(a, b, c, p) * six_volume(a, b, c, q) < 0
    around = np.stack([six_volume(p, q, a, b), six_volume(p, q, b, c), six_volume(p, q, c, a)], axis=1)
    hit = np.flatnonzero(sides & ((around >= 0).all(axis=1) | (around <= 0).all(axis=1)))
    if len(hit) == 0:
        return None
    return tuple(sorted((int(bodies[edges[e[hit[0]], 0]]), int(bodies[triangles[t[hit[0]], 0]]))))


def as_contact(value):
    """value if it is a `Contact` or None, else a one-line `ConfigError`."""
    if value is not None and not isinstance(value, Contact):
        raise ConfigError(f"contact must be a solver.Contact or None, got {type(value).__name__}")
    return value
