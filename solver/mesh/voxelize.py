"""Tetrahedralise a closed triangle surface by filling it with voxels (vectorised numpy).

Inside test: a ray from each voxel centre along +z crosses the closed surface an odd number of times.
All rays of one (x, y) column are handled together: each triangle's hit with a column is binned to
the first voxel centre above it, and a cumulative sum along z counts crossings below every centre.

Voxels joined to the rest only along an edge or at a corner would hang on a single lattice edge or
node (a hinge no real body has), and islands would fall away, so only the largest face-connected
piece is kept (with a `MeshWarning` saying how many voxels went).
"""
import warnings

import numpy as np

from ..errors import MeshError, MeshWarning
from .cells import kuhn_tets, oriented_tets

RESOLUTION_RANGE = (2, 1000)
"""Voxels along a surface's longest side that `tetrahedralize_surface` accepts (least, most)."""


def inside_voxels(vertices: np.ndarray, faces: np.ndarray, origin: np.ndarray, pitch: float,
                  dims) -> np.ndarray:
    """Boolean (nx, ny, nz) grid: is the centre of voxel (i, j, k) inside the closed surface?

    vertices: (V, 3); faces: (F, 3); voxel (i, j, k) has centre origin + pitch * (i, j, k) + pitch / 2.
    """
    nx, ny, nz = dims
    tri = vertices[faces]                                     # (F, 3, 3)
    # Column coordinates of the triangle corners, in units of voxels, centres at integers.
    uv = (tri[:, :, :2] - origin[:2] - 0.5 * pitch) / pitch
    lo = np.clip(np.ceil(uv.min(axis=1)), 0, [nx, ny]).astype(np.int64)
    hi = np.clip(np.floor(uv.max(axis=1)), -1, [nx - 1, ny - 1]).astype(np.int64)
    span = np.maximum(hi - lo + 1, 0)
    count = span[:, 0] * span[:, 1]
    owner = np.repeat(np.arange(len(faces)), count)
    local = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    ci = lo[owner, 0] + local // np.maximum(span[owner, 1], 1)
    cj = lo[owner, 1] + local % np.maximum(span[owner, 1], 1)
    # Barycentric coordinates of the column centre in the projected triangle.
    a, b, c = uv[owner, 0], uv[owner, 1], uv[owner, 2]
    p = np.stack([ci, cj], axis=1).astype(np.float64)
    d = (b[:, 1] - c[:, 1]) * (a[:, 0] - c[:, 0]) + (c[:, 0] - b[:, 0]) * (a[:, 1] - c[:, 1])
    ok = np.abs(d) > 1e-14
    d = np.where(ok, d, 1.0)
    w0 = ((b[:, 1] - c[:, 1]) * (p[:, 0] - c[:, 0]) + (c[:, 0] - b[:, 0]) * (p[:, 1] - c[:, 1])) / d
    w1 = ((c[:, 1] - a[:, 1]) * (p[:, 0] - c[:, 0]) + (a[:, 0] - c[:, 0]) * (p[:, 1] - c[:, 1])) / d
    w2 = 1.0 - w0 - w1
    hit = ok & (w0 >= 0) & (w1 >= 0) & (w2 >= 0)
    z = (w0 * tri[owner, 0, 2] + w1 * tri[owner, 1, 2] + w2 * tri[owner, 2, 2])[hit]
    ci, cj = ci[hit], cj[hit]
    first_above = np.clip(np.ceil((z - origin[2]) / pitch - 0.5), 0, nz).astype(np.int64)
    crossings = np.zeros((nx, ny, nz + 1), dtype=np.int64)
    np.add.at(crossings, (ci, cj, first_above), 1)
    return (np.cumsum(crossings, axis=2)[:, :, :nz] % 2) == 1


def largest_face_connected(inside: np.ndarray) -> np.ndarray:
    """Boolean grid like `inside` (nx, ny, nz) holding only its largest face-connected piece (ties: the
    first in memory order): voxels joined to it along an edge or at a corner, and islands, go."""
    from scipy import ndimage

    labels, n = ndimage.label(inside, structure=ndimage.generate_binary_structure(3, 1))
    if n <= 1:
        return inside.copy()
    size = np.bincount(labels.ravel())
    size[0] = 0
    return labels == int(np.argmax(size))


def tetrahedralize_surface(vertices: np.ndarray, faces: np.ndarray, resolution: int, name: str = "surface"):
    """Fill a closed surface with voxels, `resolution` along its longest side, 6 tets per voxel.

    Returns (vertices (N, 3), tets (M, 4)) on a conforming lattice, every tet positively oriented.
    """
    lowest, highest = RESOLUTION_RANGE
    if not isinstance(resolution, (int, np.integer)) or not lowest <= resolution <= highest:
        raise MeshError(f"voxel resolution must be an integer from {lowest} to {highest}, got {resolution!r}")
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    pitch = float((hi - lo).max()) / resolution
    # A tiny irrational shift keeps rays off mesh vertices and edges of axis-aligned inputs.
    origin = lo + pitch * 1e-7 * np.array([np.sqrt(2), np.sqrt(3), 0.0])
    dims = np.maximum(np.ceil((hi - origin) / pitch - 1e-9).astype(np.int64), 1)
    inside = inside_voxels(vertices, faces, origin, pitch, dims)
    kept = largest_face_connected(inside)
    dropped = int(inside.sum() - kept.sum())
    if dropped:
        warnings.warn(f"{name}: dropped {dropped} of {int(inside.sum())} voxels that are not face-connected to the "
                      f"largest piece (they would hang on an edge or a corner, or float free); raise the "
                      f"resolution to keep them", MeshWarning, stacklevel=3)
    inside = kept
    cells = np.argwhere(inside)
    if len(cells) == 0:
        raise MeshError(f"{name}: no voxel centre lies inside the surface at resolution {resolution}; "
                        "raise the resolution")
    node_dims = dims + 1
    tets = kuhn_tets(cells, node_dims)
    grid = np.stack(np.meshgrid(*[np.arange(n) for n in node_dims], indexing="ij"), axis=-1).reshape(-1, 3)
    lattice = origin + pitch * grid
    used, tets = np.unique(tets, return_inverse=True)
    tets = tets.reshape(-1, 4)
    points = lattice[used]
    return points, oriented_tets(points, tets)
