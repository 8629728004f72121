"""The contact term E_c of G for the Newton reference (issue 17), in numpy: the pairs are found again
at every x by the numpy twin of the detector (`contact_detection.find_pairs_np`), independent of the
Taichi kernels, and every Newton step is capped by the same conservative bounds as the VBD sweep, so
that the line search never carries a surface through another (where G has a lower, wrong minimum).
"""
import numpy as np

from ..mesh.bodies import body_labels
from ..mesh.surface import surface_primitives
from ..physics.contact import (Contact, contact_energy_np, contact_gradient_np, contact_hessian_np)
from ..physics.contact_detection import find_pairs_np, rest_exclusions_np, vertex_bounds_np


class ContactTerm:
    """E_c of the mesh with (M, 4) tets, rest positions rest (N, 3) and free vertices free (N,) bool
    under `contact` (frictionless: friction is not a potential and the reference refuses it)."""

    def __init__(self, contact: Contact, tets: np.ndarray, rest: np.ndarray, free: np.ndarray):
        self.contact = contact
        self.tets, self.rest = np.asarray(tets), np.asarray(rest, dtype=np.float64)     # for the Taichi twin
        self.surface = surface_primitives(tets)
        self.bodies = body_labels(tets, len(rest))
        self.free = np.asarray(free, dtype=bool)
        empty = np.zeros(0, dtype=np.int64)
        self.excluded = (rest_exclusions_np(rest, self.surface, self.bodies, contact) if contact.self_contact
                         else (empty, empty))
        self._cache = (None, None)

    def pairs(self, x: np.ndarray):
        """(kind (P,), vertices (P, 4), distance (P,)) of the pairs at x (N, 3); the last x is cached."""
        if self._cache[0] is None or not np.array_equal(self._cache[0], x):
            kind, vertices, _, distance = find_pairs_np(x, self.surface, self.bodies, self.free, self.contact,
                                                        self.excluded)
            self._cache = (x.copy(), (kind, vertices, distance))
        return self._cache[1]

    def energy(self, x: np.ndarray) -> float:
        """E_c(x) in J."""
        kind, vertices, _ = self.pairs(x)
        return contact_energy_np(x, kind, vertices, self.contact)

    def gradient(self, x: np.ndarray) -> np.ndarray:
        """(N, 3) dE_c/dx."""
        kind, vertices, _ = self.pairs(x)
        return contact_gradient_np(x, kind, vertices, self.contact)

    def hessian(self, x: np.ndarray):
        """(3N, 3N) sparse d2E_c/dx2 with every pair's Hessian PSD (n held fixed)."""
        kind, vertices, _ = self.pairs(x)
        return contact_hessian_np(x, kind, vertices, self.contact)

    def step_cap(self, x: np.ndarray, d: np.ndarray) -> float:
        """The largest alpha in (0, 1] with |alpha d_v| <= b_v at every vertex, b the bounds at x (N, 3) and
        d (N, 3) the Newton direction."""
        _, vertices, distance = self.pairs(x)
        bound = vertex_bounds_np(len(x), vertices, distance, self.contact)
        length = np.linalg.norm(d, axis=1)
        moving = length > 0
        return float(min(1.0, np.min(bound[moving] / length[moving], initial=1.0)))
