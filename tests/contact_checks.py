"""A numpy judge of contact scenes, independent of the solver's detector: which surface edges pass
through a surface triangle of another body (or, for self contact, of their own body, sharing no vertex).

Used by the contact tests to judge every step of a scene; found by a k-d tree over triangle centroids
and decided exactly by signed volumes.
"""
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

import solver


ROUNDOFF = 1e-10     # signed volumes below this x (longest edge)^3 are coplanar up to round-off


def _volume(a, b, c, d):
    """(K,) six times the signed volume of the tets (a, b, c, d), all (K, 3)."""
    return np.einsum("ka,ka->k", np.cross(b - a, c - a), d - a)


def crossings(x: np.ndarray, tets: np.ndarray, self_contact: bool = True) -> np.ndarray:
    """(found (K, 2), edges (E, 2), triangles (T, 3)): the surface edges and triangles of the (M, 4) tets,
    and each (edge row, triangle row) where, at positions x (N, 3), the edge's segment passes through the
    triangle (interior or boundary) with its endpoints strictly on either side; between different
    bodies, and with self_contact also within one body when edge and triangle share no vertex.
    "Strictly": each endpoint's signed volume with the triangle exceeds ROUNDOFF times the longest
    edge cubed, so that an edge and a triangle of one flat face, coplanar up to round-off, never count."""
    n = len(x)
    _, body = connected_components(coo_matrix((np.ones(3 * len(tets)), (np.repeat(tets[:, 0], 3),
                                                                          tets[:, 1:].ravel())), shape=(n, n)),
                                   directed=False)
    triangles = solver.boundary_faces(tets)
    edges = np.unique(np.sort(triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1), axis=0)
    centroid = x[triangles].mean(axis=1)
    reach = np.linalg.norm(x[triangles] - centroid[:, None], axis=2).max()
    half = np.linalg.norm(x[edges[:, 1]] - x[edges[:, 0]], axis=1).max() / 2
    near = cKDTree(centroid).query_ball_point(x[edges].mean(axis=1), reach + half)
    e = np.repeat(np.arange(len(edges)), [len(k) for k in near])
    t = np.concatenate([np.asarray(k, dtype=np.int64) for k in near] + [np.zeros(0, np.int64)])
    shares = (edges[e][:, :, None] == triangles[t][:, None, :]).any(axis=(1, 2))
    same = body[edges[e, 0]] == body[triangles[t, 0]]
    keep = ~shares & (~same | self_contact)
    e, t = e[keep], t[keep]
    p, q = x[edges[e, 0]], x[edges[e, 1]]
    a, b, c = (x[triangles[t, k]] for k in range(3))
    floor = ROUNDOFF * (2 * half) ** 3
    vp, vq = _volume(a, b, c, p), _volume(a, b, c, q)
    sides = (vp * vq < 0) & (np.abs(vp) > floor) & (np.abs(vq) > floor)     # endpoints on opposite sides
    around = np.stack([_volume(p, q, a, b), _volume(p, q, b, c), _volume(p, q, c, a)], axis=1)
    through = (around >= 0).all(axis=1) | (around <= 0).all(axis=1)
    hit = sides & through
    return np.stack([e[hit], t[hit]], axis=1), edges, triangles
