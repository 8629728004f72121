"""Tetrahedral meshes: the `TetMesh` container, validation, generators, file input and output.

Everything here is one-off preprocessing in vectorised numpy; nothing runs inside the time step.
"""
from __future__ import annotations

import contextlib
import hashlib
import io
import os
from dataclasses import dataclass, field

import numpy as np

from .errors import MeshError

SURFACE_SUFFIXES = (".obj", ".stl", ".ply", ".off", ".glb", ".gltf")

# Outward faces of a positively oriented tet (v0, v1, v2, v3), det[v1-v0, v2-v0, v3-v0] > 0,
# listed as local vertex triples in counter-clockwise order seen from outside.
TET_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]], dtype=np.int64)


def signed_volumes(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Signed tet volumes `det[x1-x0, x2-x0, x3-x0] / 6`; vertices (N,3), tets (M,4) -> (M,)."""
    x = vertices[tets]
    return np.linalg.det(np.stack([x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]], axis=-1)) / 6.0


def boundary_faces(tets: np.ndarray) -> np.ndarray:
    """(F, 3) int32 tet faces used by exactly one tet of (M, 4) positively oriented `tets`."""
    faces = np.asarray(tets)[:, TET_FACES].reshape(-1, 3)
    key = np.sort(faces, axis=1)
    _, first, counts = np.unique(key, axis=0, return_index=True, return_counts=True)
    return faces[np.sort(first[counts == 1])].astype(np.int32)


@dataclass(frozen=True, eq=False)
class TetMesh:
    """A validated tetrahedral mesh.

    vertices: (N, 3) float64 rest positions in metres.
    tets: (M, 4) int32 vertex indices, every tet positively oriented (volume > 0).
    original_index: (N,) int64, index of each vertex in the input it was built from (unreferenced
        input vertices are dropped, so this maps back to the file's numbering).
    """

    vertices: np.ndarray
    tets: np.ndarray
    original_index: np.ndarray = field(default=None)

    def __post_init__(self):
        vertices, tets, original = _validated(self.vertices, self.tets, self.original_index)
        object.__setattr__(self, "vertices", vertices)
        object.__setattr__(self, "tets", tets)
        object.__setattr__(self, "original_index", original)

    @property
    def n_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def n_tets(self) -> int:
        return int(self.tets.shape[0])

    def rest_volumes(self) -> np.ndarray:
        """(M,) rest volume of each tet in m^3."""
        return signed_volumes(self.vertices, self.tets)

    def boundary_faces(self) -> np.ndarray:
        """(F, 3) int32 triangles of the boundary surface, counter-clockwise seen from outside."""
        return boundary_faces(self.tets)

    def topology_key(self) -> str:
        """A hash of the connectivity (not the positions): the key of the colouring cache."""
        digest = hashlib.sha1(np.ascontiguousarray(self.tets, dtype=np.int32).tobytes())
        digest.update(str(self.n_vertices).encode())
        return digest.hexdigest()


def _validated(vertices, tets, original_index):
    """Check a raw (vertices, tets) pair; return cleaned copies or raise `MeshError`."""
    vertices = np.asarray(vertices)
    tets = np.asarray(tets)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or vertices.shape[0] == 0:
        raise MeshError(f"vertices must be an (N, 3) array, got shape {vertices.shape}; pass 3D points")
    if tets.ndim != 2 or tets.shape[1] != 4 or tets.shape[0] == 0:
        raise MeshError(f"the mesh has no tetrahedra (tets shape {tets.shape}); pass a volume mesh, "
                        "or a closed surface to tetrahedralise with load_mesh")
    if not np.issubdtype(tets.dtype, np.integer):
        raise MeshError(f"tet indices must be integers, got {tets.dtype}; cast them with astype(int)")
    vertices = np.array(vertices, dtype=np.float64)
    tets = np.array(tets, dtype=np.int64)
    n = vertices.shape[0]
    bad = ~np.isfinite(vertices).all(axis=1)
    if bad.any():
        raise MeshError(f"{bad.sum()} vertices have NaN or infinite coordinates (first: vertex "
                        f"{np.flatnonzero(bad)[0]}); fix or remove them in the mesh file")
    if tets.min() < 0 or tets.max() >= n:
        t = np.flatnonzero((tets < 0).any(axis=1) | (tets >= n).any(axis=1))[0]
        raise MeshError(f"tet {t} has vertex index out of range {tets[t].tolist()} with {n} vertices; "
                        "indices must be 0-based and below the vertex count")
    srt = np.sort(tets, axis=1)
    repeated = (srt[:, 1:] == srt[:, :-1]).any(axis=1)
    if repeated.any():
        t = np.flatnonzero(repeated)[0]
        raise MeshError(f"{repeated.sum()} tets use one vertex twice (first: tet {t} = {tets[t].tolist()}); "
                        "remove these degenerate tets")
    _, first, counts = np.unique(srt, axis=0, return_index=True, return_counts=True)
    if (counts > 1).any():
        t = first[counts > 1][0]
        raise MeshError(f"{(counts - 1).sum()} duplicate tets (first: tet {t} = {tets[t].tolist()}); "
                        "remove the repeated elements")
    vol = signed_volumes(vertices, tets)
    x = vertices[tets]
    edges = x[:, [1, 2, 3, 2, 3, 3]] - x[:, [0, 0, 0, 1, 1, 2]]
    longest = np.linalg.norm(edges, axis=2).max(axis=1)
    flat = np.abs(vol) <= 1e-9 * longest ** 3
    if flat.any():
        t = np.flatnonzero(flat)[0]
        raise MeshError(f"{flat.sum()} tets have zero volume (first: tet {t}); remove these flat "
                        "slivers or remesh")
    negative = vol < 0
    if negative.all():
        tets = tets[:, [0, 1, 3, 2]]
    elif negative.any():
        t = np.flatnonzero(negative)[0]
        raise MeshError(f"{negative.sum()} of {len(tets)} tets are inverted (first: tet {t}) while the "
                        "rest are positive; the mesh folds over itself, fix it in the mesher")
    used = np.zeros(n, dtype=bool)
    used[tets.ravel()] = True
    original = np.arange(n) if original_index is None else np.asarray(original_index, dtype=np.int64)
    if not used.all():
        remap = np.cumsum(used) - 1
        tets = remap[tets]
        vertices = vertices[used]
        original = original[used]
    return vertices, np.ascontiguousarray(tets, dtype=np.int32), original


def kuhn_tets(cells: np.ndarray, node_dims) -> np.ndarray:
    """Split hexahedral lattice cells into 6 tets each (Kuhn/Freudenthal split along the main diagonal).

    cells: (C, 3) integer cell coordinates (i, j, k); node_dims: (nx+1, ny+1, nz+1) lattice nodes.
    Every cell is cut the same way, so neighbouring cells share faces exactly (a conforming mesh).
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
    nodes = cells[:, None, None, :] + offsets[None]            # (C, 6, 4, 3)
    index = (nodes[..., 0] * ny1 + nodes[..., 1]) * nz1 + nodes[..., 2]
    return index.reshape(-1, 4)


def box_mesh(size=(1.0, 0.1, 0.1), cells=(40, 4, 4), origin=(0.0, 0.0, 0.0)) -> TetMesh:
    """A box of `size` metres starting at `origin`, with `cells` hexahedra per axis, 6 tets each."""
    size = np.asarray(size, dtype=np.float64)
    cells = np.asarray(cells)
    if size.shape != (3,) or not np.isfinite(size).all() or (size <= 0).any():
        raise MeshError(f"box size must be three positive lengths, got {size.tolist()}")
    if cells.shape != (3,) or not np.issubdtype(cells.dtype, np.integer) or (cells < 1).any():
        raise MeshError(f"box cells must be three integers >= 1, got {cells.tolist()}")
    axes = [np.linspace(0.0, size[a], cells[a] + 1) + origin[a] for a in range(3)]
    vertices = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    cell_ijk = np.stack(np.meshgrid(*[np.arange(c) for c in cells], indexing="ij"), axis=-1).reshape(-1, 3)
    tets = kuhn_tets(cell_ijk, cells + 1)
    return TetMesh(vertices, oriented_tets(vertices, tets))


def oriented_tets(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Swap two vertices of every negatively oriented tet (used by generators, whose tets are valid)."""
    tets = tets.copy()
    neg = signed_volumes(vertices, tets) < 0
    tets[neg] = tets[neg][:, [0, 1, 3, 2]]
    return tets


def load_mesh(path, resolution: int = 16) -> TetMesh:
    """Read a tet mesh, or tetrahedralise a closed surface.

    Volume formats: anything meshio reads (.msh, .vtk, .vtu, .mesh, TetGen .node/.ele, ...).
    Surface formats (.obj, .stl, .ply, .off, ...): read with trimesh and filled with voxels, `resolution`
    cells along the longest side of the bounding box, then split into tets.
    """
    path = os.fspath(path)
    if not os.path.exists(path):
        raise MeshError(f"{path}: file not found; check the path")
    if os.path.isdir(path):
        raise MeshError(f"{path}: is a folder, not a mesh file; give the file's path")
    if path.lower().endswith(SURFACE_SUFFIXES):
        from .voxelize import tetrahedralize_surface

        vertices, faces = _read_surface(path)
        vertices, tets = tetrahedralize_surface(vertices, faces, resolution, name=path)
        return TetMesh(vertices, tets)
    import meshio

    try:
        with contextlib.redirect_stderr(io.StringIO()), contextlib.redirect_stdout(io.StringIO()):
            raw = meshio.read(path)
    except (Exception, SystemExit) as err:  # meshio raises many types, even SystemExit, on bad input
        reason = str(err).splitlines()[0] if str(err) and not isinstance(err, SystemExit) else "unknown format"
        raise MeshError(f"{path}: cannot read this file ({reason}); use a format meshio reads, "
                        "e.g. .msh, .vtu, .vtk, .mesh or TetGen .node/.ele") from None
    blocks = [c.data for c in raw.cells if c.type in ("tetra", "tetra10")]
    if not blocks:
        kinds = sorted({c.type for c in raw.cells}) or ["none"]
        raise MeshError(f"{path}: contains no tetrahedra (cell types: {', '.join(kinds)}); "
                        "a surface-only mesh must be tetrahedralised first, e.g. save it as .obj/.stl "
                        "and load that")
    tets = np.concatenate([b[:, :4] for b in blocks])
    try:
        return TetMesh(raw.points, tets)
    except MeshError as err:
        raise MeshError(f"{path}: {err}") from None


def _read_surface(path):
    import trimesh

    try:
        surface = trimesh.load(path, force="mesh", process=True)
    except Exception as err:
        reason = str(err).splitlines()[0] if str(err) else type(err).__name__
        raise MeshError(f"{path}: cannot read this surface ({reason}); check the file") from None
    if len(surface.faces) == 0:
        raise MeshError(f"{path}: has no triangles; give a closed triangle surface")
    if not np.isfinite(surface.vertices).all():
        raise MeshError(f"{path}: has NaN or infinite coordinates; fix the file")
    if not surface.is_watertight:
        raise MeshError(f"{path}: the surface is not closed (watertight), so its inside is undefined; "
                        "repair its holes (e.g. in Blender or MeshLab) first")
    return np.asarray(surface.vertices, dtype=np.float64), np.asarray(surface.faces, dtype=np.int64)


def save_mesh(mesh, path, point_data: dict | None = None) -> None:
    """Write a mesh (a `TetMesh` or a `(vertices, tets)` pair) with meshio.

    Volume formats get the tets; surface formats (.obj, .ply, .stl, .off) get the boundary triangles.
    point_data: optional {name: (N,) or (N, k) array} written where the format supports it.
    """
    import meshio

    vertices, tets = (mesh.vertices, mesh.tets) if isinstance(mesh, TetMesh) else mesh
    path = os.fspath(path)
    if path.lower().endswith(SURFACE_SUFFIXES):
        cells = [("triangle", boundary_faces(tets))]
    else:
        cells = [("tetra", np.asarray(tets))]
    try:
        meshio.write(path, meshio.Mesh(np.asarray(vertices, dtype=np.float64), cells,
                                       point_data=point_data or {}))
    except OSError as err:
        raise MeshError(f"{path}: cannot write ({err.strerror}); check that the folder exists and is "
                        "writable") from None
    except (meshio.ReadError, meshio.WriteError) as err:   # meshio reports an unknown suffix as ReadError
        raise MeshError(f"{path}: cannot write this format ({err}); use a suffix meshio writes, "
                        "e.g. .vtu, .msh, .ply or .obj") from None
