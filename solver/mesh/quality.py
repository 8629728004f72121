"""Tet shape quality: dihedral angles, radius ratio, slivers, and inverted elements (vectorised numpy).

A *sliver* here is any badly shaped tet: radius ratio below `SLIVER_RADIUS_RATIO`. The radius ratio
3 r_in / r_circ is 1 for the regular tet and 0 for a flat one, so it flags near-flat slivers, caps,
needles and wedges alike. Such tets have a huge stiffness in one direction and a tiny one in another,
and an unconverged solver can push a vertex through the opposite face in one step.

`det_F(rest, tets, x)` and `inverted_count(rest, tets, x)` measure inversion at deformed positions
x and are cheap enough to call once per time step.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .cells import signed_volumes

# Radius ratio below which a tet counts as a sliver. A cube's 6-tet (Kuhn) split has 0.72; a good
# fTetWild mesh has nearly all tets above 0.3.
SLIVER_RADIUS_RATIO = 0.1

# Local vertex pairs of the 6 edges and, for each edge, the two local vertices not on it.
_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
_OPPOSITE = np.array([[2, 3], [1, 3], [1, 2], [0, 3], [0, 2], [0, 1]])


def _edge_vectors(x: np.ndarray) -> np.ndarray:
    """(M, 3, 3) columns x1-x0, x2-x0, x3-x0 from (M, 4, 3) corner positions."""
    return np.stack([x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]], axis=-1)


def det_F(rest: np.ndarray, tets: np.ndarray, x: np.ndarray) -> np.ndarray:
    """(M,) det F = deformed volume / rest volume of every tet (signed; <= 0 means inverted).

    rest, x: (N, 3) rest and current positions; tets: (M, 4) positively oriented at rest.
    """
    return signed_volumes(x, tets) / signed_volumes(rest, tets)


def inverted_count(rest: np.ndarray, tets: np.ndarray, x: np.ndarray) -> int:
    """Number of tets with det F <= 0 at positions x (N, 3); rest (N, 3), tets (M, 4)."""
    return int(np.count_nonzero(det_F(rest, tets, x) <= 0.0))


def dihedral_angles(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(M, 6) interior dihedral angles in radians, one per edge (order of `_EDGES`).

    vertices: (N, 3); tets: (M, 4). Degenerate faces give NaN.
    """
    x = vertices[tets]                                            # (M, 4, 3)
    # Outward area normals of the faces opposite each vertex, any consistent orientation works for the
    # angle between two of them: the dihedral angle at an edge is pi minus the angle of the normals.
    normals = np.empty_like(x)
    for i, (a, b, c) in enumerate(((1, 2, 3), (0, 3, 2), (0, 1, 3), (0, 2, 1))):
        normals[:, i] = np.cross(x[:, b] - x[:, a], x[:, c] - x[:, a])
    sign = np.sign(signed_volumes(vertices, tets))[:, None]
    normals *= sign[..., None]
    n1, n2 = normals[:, _OPPOSITE[:, 0]], normals[:, _OPPOSITE[:, 1]]    # (M, 6, 3)
    with np.errstate(invalid="ignore", divide="ignore"):
        cos = (n1 * n2).sum(axis=2) / (np.linalg.norm(n1, axis=2) * np.linalg.norm(n2, axis=2))
    return np.pi - np.arccos(np.clip(cos, -1.0, 1.0))


def radius_ratio(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(M,) 3 r_in / r_circ of every tet: 1 for the regular tet, 0 for a flat one (sign of the volume).

    vertices: (N, 3); tets: (M, 4).
    """
    x = vertices[tets]
    e = _edge_vectors(x)                                          # columns a, b, c
    six_volume = 6.0 * signed_volumes(vertices, tets)
    a, b, c = e[..., 0], e[..., 1], e[..., 2]
    area = 0.5 * (np.linalg.norm(np.cross(a, b), axis=1) + np.linalg.norm(np.cross(b, c), axis=1)
                  + np.linalg.norm(np.cross(c, a), axis=1)
                  + np.linalg.norm(np.cross(b - a, c - a), axis=1))
    # circumradius: |a^2 (b x c) + b^2 (c x a) + c^2 (a x b)| / (2 * 6V)
    aa, bb, cc = (a * a).sum(1), (b * b).sum(1), (c * c).sum(1)
    circum = np.linalg.norm(aa[:, None] * np.cross(b, c) + bb[:, None] * np.cross(c, a)
                            + cc[:, None] * np.cross(a, b), axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        r_in = np.abs(six_volume) / (2.0 * area)                  # 3V / A
        r_circ = circum / (2.0 * np.abs(six_volume))
        ratio = np.sign(six_volume) * 3.0 * r_in / r_circ
    return np.nan_to_num(ratio, nan=0.0, posinf=0.0, neginf=0.0)


@dataclass(frozen=True)
class MeshQuality:
    """Shape statistics of a tet mesh at its rest positions.

    n_tets: number of tets. min/max_dihedral_degrees: extreme interior dihedral angles (degrees;
    70.5 for the regular tet). min/median_radius_ratio: 3 r_in / r_circ (1 regular, 0 flat).
    n_slivers: tets with radius ratio below `sliver_radius_ratio` (inverted and flat ones included).
    n_inverted: tets with negative volume. n_degenerate: tets with (numerically) zero volume.
    """

    n_tets: int
    min_dihedral_degrees: float
    max_dihedral_degrees: float
    min_radius_ratio: float
    median_radius_ratio: float
    n_slivers: int
    n_inverted: int
    n_degenerate: int
    sliver_radius_ratio: float = SLIVER_RADIUS_RATIO

    def summary(self) -> str:
        """One line for logs and warnings."""
        return (f"{self.n_slivers} of {self.n_tets} tets are slivers (radius ratio < {self.sliver_radius_ratio:g}; "
                f"min {self.min_radius_ratio:.3g}), dihedral angles {self.min_dihedral_degrees:.1f} to "
                f"{self.max_dihedral_degrees:.1f} degrees, {self.n_inverted} inverted, "
                f"{self.n_degenerate} flat")


def degenerate_mask(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(M,) True where a tet has (numerically) zero volume: |V| <= 1e-9 (longest edge)^3."""
    x = vertices[tets]
    edges = x[:, _EDGES[:, 1]] - x[:, _EDGES[:, 0]]
    longest = np.linalg.norm(edges, axis=2).max(axis=1)
    return np.abs(signed_volumes(vertices, tets)) <= 1e-9 * longest ** 3


def sliver_mask(vertices: np.ndarray, tets: np.ndarray, threshold: float = SLIVER_RADIUS_RATIO) -> np.ndarray:
    """(M,) True for tets whose radius ratio is below `threshold` (flat and inverted ones included)."""
    return radius_ratio(vertices, tets) < threshold


def mesh_quality(vertices: np.ndarray, tets: np.ndarray, threshold: float = SLIVER_RADIUS_RATIO) -> MeshQuality:
    """The `MeshQuality` of tets (M, 4) over vertices (N, 3)."""
    tets = np.asarray(tets)
    ratio = radius_ratio(vertices, tets)
    degenerate = degenerate_mask(vertices, tets)
    angles = np.degrees(dihedral_angles(vertices, tets[~degenerate]))
    finite = angles[np.isfinite(angles)]
    return MeshQuality(
        n_tets=len(tets),
        min_dihedral_degrees=float(finite.min()) if finite.size else 0.0,
        max_dihedral_degrees=float(finite.max()) if finite.size else 180.0,
        min_radius_ratio=float(ratio.min()),
        median_radius_ratio=float(np.median(ratio)),
        n_slivers=int(np.count_nonzero(ratio < threshold)),
        n_inverted=int(np.count_nonzero((ratio < 0) & ~degenerate)),
        n_degenerate=int(np.count_nonzero(degenerate)),
        sliver_radius_ratio=threshold,
    )
