"""Split the cells of a mixed volume mesh (hexahedra, wedges, pyramids, higher-order cells) into tets.

A linear cell is cut by coning from its vertex with the smallest global index, v0, to every face that
does not contain v0; a quadrilateral face is cut along its diagonal through its own smallest-index
vertex. Faces that contain v0 are then cut along the diagonal through v0, which is again their
smallest-index vertex, so two cells sharing a quadrilateral always cut it the same way: the result is
conforming, and it fills each (convex) cell exactly. Hexahedra give 6 tets, wedges 3, pyramids 2.
The same rule reproduces `kuhn_tets` on a lattice numbered lexicographically.

Higher-order cells (tetra10, hexahedron27, ...) keep their corner nodes only: meshio and VTK list the
corners first.
"""
from __future__ import annotations

import numpy as np

# Faces of each linear cell in meshio/VTK local numbering (any orientation; the tets are oriented later).
CELL_FACES = {
    "hexahedron": [(0, 1, 2, 3), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7)],
    "wedge": [(0, 1, 2), (3, 4, 5), (0, 1, 4, 3), (1, 2, 5, 4), (2, 0, 3, 5)],
    "pyramid": [(0, 1, 2, 3), (0, 1, 4), (1, 2, 4), (2, 3, 4), (3, 0, 4)],
}
CORNERS = {"tetra": 4, "hexahedron": 8, "wedge": 6, "pyramid": 5}

# Cells of lower dimension than a volume, of any order (meshio's "triangle15", "quad9", "line3", ...,
# and VTK's arbitrary-order Lagrange cells), by name without the node count. A volume file's boundary and
# edge markers: ignored beside volume cells. Surface cells bound a volume but hold none: a file with only
# these is a surface mesh.
SURFACE_CELLS = ("triangle", "quad", "polygon", "VTK_LAGRANGE_TRIANGLE", "VTK_LAGRANGE_QUADRILATERAL")
CURVE_CELLS = ("vertex", "line", "VTK_LAGRANGE_CURVE")


def split_cells(kind: str, cells: np.ndarray) -> np.ndarray:
    """Tets (K*C, 4) filling cells (C, n) of a linear meshio cell type `kind`, not yet oriented.

    kind: "tetra", "hexahedron", "wedge" or "pyramid"; cells: global vertex indices, corners only.
    """
    cells = np.asarray(cells, dtype=np.int64)
    if kind == "tetra":
        return cells
    n_cells = len(cells)
    apex_local = np.argmin(cells, axis=1)                                  # (C,)
    apex = cells[np.arange(n_cells), apex_local]
    tets = []
    for face in CELL_FACES[kind]:
        face = np.asarray(face)
        keep = (face[None, :] != apex_local[:, None]).all(axis=1)          # face does not contain v0
        if len(face) == 3:
            triangles = [cells[:, face]]
        else:
            quad = cells[:, face]                                          # (C, 4), rolled to its min
            roll = np.argmin(quad, axis=1)
            quad = quad[np.arange(n_cells)[:, None], (roll[:, None] + np.arange(4)) % 4]
            triangles = [quad[:, [0, 1, 2]], quad[:, [0, 2, 3]]]
        for tri in triangles:
            tets.append(np.column_stack([apex, tri])[keep])
    return np.concatenate(tets)


def is_surface_cell(cell_type: str) -> bool:
    """True for a meshio surface cell type of any order ("triangle", "triangle15", "quad9", ...)."""
    return cell_type.rstrip("0123456789") in SURFACE_CELLS


def is_lower_dimensional(cell_type: str) -> bool:
    """True for a meshio cell type of dimension 0, 1 or 2, of any order ("vertex", "line3", "triangle15")."""
    return is_surface_cell(cell_type) or cell_type.rstrip("0123456789") in CURVE_CELLS


def linear_cell(cell_type: str):
    """The linear cell ("tetra", "hexahedron", "wedge", "pyramid") of a meshio volume cell type such as
    "tetra10" or "hexahedron27"; None for any other type."""
    base = cell_type.rstrip("0123456789")
    return base if base in CORNERS else None


def signed_volumes(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Signed tet volumes `det[x1-x0, x2-x0, x3-x0] / 6`; vertices (N,3), tets (M,4) -> (M,). The determinant
    as the triple product (x1-x0) . ((x2-x0) x (x3-x0)), not by LAPACK's LU of each 3x3 matrix."""
    x = vertices[tets]
    x0 = x[:, 0]
    return np.einsum("mk,mk->m", x[:, 1] - x0, np.cross(x[:, 2] - x0, x[:, 3] - x0)) / 6.0


def kuhn_tets(cells: np.ndarray, node_dims, mirror: np.ndarray = None) -> np.ndarray:
    """Split hexahedral lattice cells into 6 tets each (Kuhn/Freudenthal split along the main diagonal).

    cells: (C, 3) integer cell coordinates (i, j, k); node_dims: (nx+1, ny+1, nz+1) lattice nodes.
    Every cell is cut the same way, so neighbouring cells share faces exactly (a conforming mesh).
    mirror: (C, 3) bool, the axes along which a cell's split is reflected (default none). The mesh stays
    conforming where two cells that share a face reflect alike along the face's two axes (`ball_mesh`
    reflects along each axis in the lower half of the lattice).
    Returns (6C, 4) node indices `(i * ny1 + j) * nz1 + k`, not yet oriented.
    """
    _, ny1, nz1 = node_dims
    paths = []
    for axes in ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)):
        corner = np.zeros(3, dtype=np.int64)
        path = [corner.copy()]
        for a in axes:
            corner[a] += 1
            path.append(corner.copy())
        paths.append(path)
    offsets = np.array(paths)                                  # (6, 4, 3)
    if mirror is None:
        nodes = cells[:, None, None, :] + offsets[None]        # (C, 6, 4, 3)
    else:
        nodes = cells[:, None, None, :] + np.where(mirror[:, None, None, :], 1 - offsets[None], offsets[None])
    index = (nodes[..., 0] * ny1 + nodes[..., 1]) * nz1 + nodes[..., 2]
    return index.reshape(-1, 4)


def oriented_tets(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Swap two vertices of every negatively oriented tet (used by generators, whose tets are valid)."""
    tets = tets.copy()
    neg = signed_volumes(vertices, tets) < 0
    tets[neg] = tets[neg][:, [0, 1, 3, 2]]
    return tets
