"""Tetrahedral meshes: the `TetMesh` container, validation, generators, file input and output.

Everything here is one-off preprocessing in vectorised numpy; nothing runs inside the time step.
"""
from __future__ import annotations

import contextlib
import hashlib
import io
import math
import numbers
import os
import warnings
from dataclasses import dataclass, field

import numpy as np

from .cells import (CORNERS, is_lower_dimensional, is_surface_cell, kuhn_tets, linear_cell, oriented_tets,
                    signed_volumes, split_cells)
from ..errors import ConfigError, MeshError, MeshQualityWarning, MeshWarning, enum_value
from .quality import SLIVER_RADIUS_RATIO, MeshQuality, degenerate_mask, mesh_quality, sliver_mask
from .tetrahedralize import Mesher, tetwild_tets
from .voxelize import tetrahedralize_surface

SURFACE_SUFFIXES = (".obj", ".stl", ".ply", ".off", ".glb", ".gltf")

# Outward faces of a positively oriented tet (v0, v1, v2, v3), det[v1-v0, v2-v0, v3-v0] > 0,
# listed as local vertex triples in counter-clockwise order seen from outside.
TET_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]], dtype=np.int64)


def boundary_faces(tets) -> np.ndarray:
    """(F, 3) int32 tet faces used by exactly one tet of `tets`: a `TetMesh`, or (M, 4) positively
    oriented vertex indices."""
    tets = tets.tets if isinstance(tets, TetMesh) else np.asarray(tets)
    if tets.ndim != 2 or tets.shape[1] != 4 or not np.issubdtype(tets.dtype, np.integer):
        raise MeshError(f"boundary_faces needs a TetMesh or an (M, 4) integer array of tets, got shape "
                        f"{tets.shape} {tets.dtype}; pass mesh or mesh.tets")
    faces = tets[:, TET_FACES].reshape(-1, 3)
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

    def quality(self, sliver_radius_ratio: float = SLIVER_RADIUS_RATIO) -> MeshQuality:
        """Shape statistics of the rest mesh: dihedral angles, radius ratios, slivers (`solver.quality`)."""
        return mesh_quality(self.vertices, self.tets, sliver_radius_ratio)

    def without_slivers(self, sliver_radius_ratio: float = SLIVER_RADIUS_RATIO) -> "TetMesh":
        """A copy without the sliver tets (radius ratio below the threshold) that can go.

        Slivers are nearly flat, so dropping them changes the volume very little; an interior sliver
        leaves a thin crack. A sliver whose removal would cut a piece off the mesh (its face-connected
        pieces would multiply) stays. Vertices left unused are dropped; `original_index` still maps
        to the input's numbering.
        """
        sliver = sliver_mask(self.vertices, self.tets, sliver_radius_ratio)
        n_pieces = int(face_components(self.tets).max()) + 1
        faces = np.sort(self.tets[:, TET_FACES].reshape(-1, 3), axis=1)
        face_id = np.unique(faces, axis=0, return_inverse=True)[1].reshape(-1, 4)
        keep = ~sliver
        while keep.any():
            labels = np.full(self.n_tets, -1)
            labels[keep] = face_components(self.tets[keep])
            stray = labels >= n_pieces
            if not stray.any():
                break
            # put back the slivers that glue a stray piece to the rest
            glue = ~keep & np.isin(face_id, face_id[stray]).any(axis=1)
            if not glue.any():
                keep &= ~stray
                break
            keep |= glue
        if not keep.any():
            raise MeshError(f"all {self.n_tets} tets are slivers (radius ratio < {sliver_radius_ratio:g}); "
                            "remesh it with .remeshed() instead (needs pytetwild)")
        return TetMesh(self.vertices, self.tets[keep], self.original_index)

    def remeshed(self, edge_length: float = None) -> "TetMesh":
        """New well-shaped tets filling this mesh's boundary surface, made by fTetWild (optional
        pytetwild, `solver.tetrahedralize`); edge_length in metres, default 1/20 of the diagonal.
        The vertices are new: `original_index` numbers them 0..N-1."""
        used = np.unique(self.boundary_faces())
        remap = np.full(self.n_vertices, -1)
        remap[used] = np.arange(len(used))
        vertices, tets = tetwild_tets(self.vertices[used], remap[self.boundary_faces()], edge_length,
                                      name="the mesh's boundary")
        return TetMesh(vertices, without_degenerate(vertices, tets))

    def topology_key(self) -> str:
        """A hash of the connectivity (not the positions): the key of the colouring cache."""
        digest = hashlib.sha1(np.ascontiguousarray(self.tets, dtype=np.int32).tobytes())
        digest.update(str(self.n_vertices).encode())
        return digest.hexdigest()


def _validated(vertices, tets, original_index):
    """Check a raw (vertices, tets) pair; return cleaned copies or raise `MeshError`.

    Vertices no tet uses are dropped before any check (a NaN there does no harm); every negatively
    ordered tet is reordered on its own; only a mesh that still overlaps itself is rejected.
    """
    try:
        vertices = np.asarray(vertices)
    except ValueError:                  # ragged rows
        raise MeshError("vertices must be an (N, 3) array, but its rows differ in length; pass 3D points") from None
    if vertices.ndim != 2 or vertices.shape[1] != 3 or vertices.shape[0] == 0:
        raise MeshError(f"vertices must be an (N, 3) array, got shape {vertices.shape}; pass 3D points")
    if not (np.issubdtype(vertices.dtype, np.integer) or np.issubdtype(vertices.dtype, np.floating)):
        raise MeshError(f"vertices must be real numbers (m), got an array of {vertices.dtype}")
    vertices = np.array(vertices, dtype=np.float64)
    n = vertices.shape[0]
    tets = tet_indices(tets, n)
    original = np.arange(n) if original_index is None else np.asarray(original_index, dtype=np.int64)
    if original.shape != (n,):
        raise MeshError(f"original_index must hold one index per vertex, ({n},), got shape {original.shape}")
    used = np.zeros(n, dtype=bool)
    used[tets.ravel()] = True
    if not used.all():
        tets = (np.cumsum(used) - 1)[tets]
        vertices = vertices[used]
        original = original[used]
    n_used = len(vertices)
    bad = ~np.isfinite(vertices).all(axis=1)
    if bad.any():
        raise MeshError(f"{bad.sum()} vertices used by tets have NaN or infinite coordinates (first: vertex "
                        f"{original[np.flatnonzero(bad)[0]]}); fix or remove them in the mesh file")
    srt = np.sort(tets, axis=1)
    repeated = (srt[:, 1:] == srt[:, :-1]).any(axis=1)
    if repeated.any():
        t = np.flatnonzero(repeated)[0]
        raise MeshError(f"{repeated.sum()} tets use one vertex twice (first: tet {t}); remove these "
                        "degenerate tets, or load with repair=True")
    _, first, counts = _unique_rows(srt, n_used, return_index=True, return_counts=True)
    if (counts > 1).any():
        t = first[counts > 1][0]
        raise MeshError(f"{(counts - 1).sum()} duplicate tets (first: tet {t}); remove the repeated elements")
    flat = degenerate_mask(vertices, tets)
    if flat.any():
        t = np.flatnonzero(flat)[0]
        raise MeshError(f"{flat.sum()} tets have zero volume (first: tet {t}); remove these flat tets, "
                        "or load with repair=True to drop them")
    tets = oriented_tets(vertices, tets)
    folded = _folded_tets(tets, n_used)
    if folded.any():
        t = np.flatnonzero(folded)[0]
        raise MeshError(f"{folded.sum()} tets overlap their neighbours (first: tet {t}): the mesh folds over "
                        "itself, so reordering tets cannot fix it; remesh it, e.g. from its boundary surface")
    return vertices, np.ascontiguousarray(tets, dtype=np.int32), original


def tet_indices(tets, n_vertices) -> np.ndarray:
    """`tets` as an (M, 4) int64 copy, checked against `n_vertices`; a one-line `MeshError` for a vertex
    count that is not an integer >= 1, a shape other than (M, 4) with M >= 1, non-integer entries, or an
    index outside 0 .. n_vertices - 1."""
    if isinstance(n_vertices, bool) or not isinstance(n_vertices, numbers.Integral) or n_vertices < 1:
        raise MeshError(f"the vertex count must be an integer >= 1, got {n_vertices!r}; pass mesh.n_vertices")
    try:
        tets = np.asarray(tets)
    except ValueError:                          # rows of different lengths
        raise MeshError("tets must be rows of 4 vertex indices each, and some rows have another length") from None
    if tets.ndim != 2 or tets.shape[1] != 4 or tets.shape[0] == 0:
        raise MeshError(f"the mesh has no tetrahedra (tets shape {tets.shape}, not (M, 4)); pass a volume mesh, "
                        "or a closed surface to tetrahedralise with load_mesh")
    if not np.issubdtype(tets.dtype, np.integer):
        raise MeshError(f"tet indices must be integers, got {tets.dtype}; cast them with astype(int)")
    tets = np.array(tets, dtype=np.int64)
    if tets.min() < 0 or tets.max() >= n_vertices:
        t = np.flatnonzero((tets < 0).any(axis=1) | (tets >= n_vertices).any(axis=1))[0]
        raise MeshError(f"tet {t} has vertex index out of range {tets[t].tolist()} with {n_vertices} vertices; "
                        "indices must be 0-based and below the vertex count")
    return tets


def _unique_rows(rows: np.ndarray, n: int, **options):
    """`np.unique(rows, axis=0, **options)` for rows (R, k) of integers in 0 .. n-1, sorting numbers instead
    of rows: each row becomes one int64, ordered as the rows are (lexicographically), where n^k fits in one."""
    if n ** rows.shape[1] >= 2 ** 63:
        return np.unique(rows, axis=0, **options)
    keys = np.zeros(len(rows), dtype=np.int64)
    for column in rows.T:
        keys = keys * n + column
    return np.unique(keys, **options)


def _folded_tets(tets: np.ndarray, n: int) -> np.ndarray:
    """(M,) True for positively oriented tets that share a face with a tet on the same side of it, or a
    face with two other tets: in a mesh that does not overlap itself, two tets sharing a face list
    it in opposite orders. n: the vertex count."""
    faces = tets[:, TET_FACES].reshape(-1, 3)
    a, b, c = faces[:, 0], faces[:, 1], faces[:, 2]
    parity = ((a > b).astype(np.int64) + (a > c) + (b > c)) % 2
    _, inverse, counts = _unique_rows(np.sort(faces, axis=1), n, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    odd = np.bincount(inverse, weights=parity, minlength=len(counts))
    bad_face = (counts > 2) | ((counts == 2) & (odd != 1))
    return bad_face[inverse].reshape(-1, 4).any(axis=1)


def face_components(tets: np.ndarray) -> np.ndarray:
    """(M,) label of each tet's face-connected component (tets joined through a shared triangle;
    tets touching only along an edge or at a vertex are in different components), largest first."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    tets = np.asarray(tets)
    faces = np.sort(tets[:, TET_FACES].reshape(-1, 3), axis=1)
    _, inverse = np.unique(faces, axis=0, return_inverse=True)
    owner = np.repeat(np.arange(len(tets)), 4)
    incidence = coo_matrix((np.ones(len(owner)), (owner, inverse.ravel())))
    _, labels = connected_components(incidence @ incidence.T, directed=False)
    order = np.argsort(-np.bincount(labels), kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return rank[labels]


def _point(value, what: str) -> np.ndarray:
    """value as a (3,) float64 point in m, or a one-line MeshError naming `what` and the value given."""
    try:
        point = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        point = None
    if point is None or point.shape != (3,) or not np.isfinite(point).all():
        raise MeshError(f"{what} must be three finite coordinates in m, got {value!r}")
    return point


MAX_BOX_CELLS = 10 ** 7     # `box_mesh`: 60 million tets, a few GB of arrays, already past what a step can take here


def _box_dimensions(size, cells):
    """(size (3,) float64 m, cells (3,) int) of a box, checked: three positive lengths, three integers >= 1
    and at most MAX_BOX_CELLS cells in all; else a one-line `MeshError`."""
    try:
        size = np.asarray(size, dtype=np.float64)
    except (TypeError, ValueError):
        raise MeshError(f"box size must be three positive lengths in m, got {size!r}") from None
    cells = np.asarray(cells)
    if size.shape != (3,) or not np.isfinite(size).all() or (size <= 0).any():
        raise MeshError(f"box size must be three positive lengths, got {size.tolist()}")
    if cells.shape != (3,) or not np.issubdtype(cells.dtype, np.integer) or (cells < 1).any():
        raise MeshError(f"box cells must be three integers >= 1, got {cells.tolist()}")
    total = int(np.prod(cells.astype(np.float64)))
    if total > MAX_BOX_CELLS:
        raise MeshError(f"box cells {cells.tolist()} make {total:,} cells (x 6 tets), more than {MAX_BOX_CELLS:,}; "
                        "use fewer cells")
    return size, cells


def box_mesh(size=(1.0, 0.1, 0.1), cells=(40, 4, 4), origin=(0.0, 0.0, 0.0)) -> TetMesh:
    """A box of `size` metres starting at `origin`, with `cells` hexahedra per axis, 6 tets each."""
    origin = _point(origin, "box origin")
    size, cells = _box_dimensions(size, cells)
    axes = [np.linspace(0.0, size[a], cells[a] + 1) + origin[a] for a in range(3)]
    vertices = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    cell_ijk = np.stack(np.meshgrid(*[np.arange(c) for c in cells], indexing="ij"), axis=-1).reshape(-1, 3)
    tets = kuhn_tets(cell_ijk, cells + 1)
    return TetMesh(vertices, oriented_tets(vertices, tets))


def ball_mesh(radius: float = 0.1, cells: int = 4, center=(0.0, 0.0, 0.0)) -> TetMesh:
    """A ball of `radius` metres around `center`: the cube [-1, 1]^3 split into `cells` (even) hexahedra per
    axis, 6 tets each, its splits reflected in the lower half along each axis so that every diagonal points
    away from the centre, then mapped onto the ball shell by shell: a node at max-norm s goes to s times
    the point of the unit sphere over its place on the cube (the cube-to-sphere map that spreads each face
    evenly). Its surface is a quad sphere, (cells + 1)^3 nodes and 6 cells^3 tets, none a sliver: at
    cells = 4, 384 tets, the least radius ratio 0.75 and dihedral angles 32-103 degrees.
    """
    if isinstance(radius, bool) or not isinstance(radius, numbers.Real) or not (math.isfinite(radius) and radius > 0):
        raise MeshError(f"ball radius must be a positive length in m, got {radius!r}")
    if isinstance(cells, bool) or not isinstance(cells, numbers.Integral) or cells < 2 or cells % 2:
        raise MeshError(f"ball cells must be an even integer >= 2 (cells per diameter), got {cells!r}")
    point = _point(center, "ball center")
    axis = np.linspace(-1.0, 1.0, cells + 1)
    p = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1).reshape(-1, 3)
    cell_ijk = np.stack(np.meshgrid(*[np.arange(cells)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    tets = kuhn_tets(cell_ijk, (cells + 1,) * 3, mirror=cell_ijk < cells // 2)
    shell = np.abs(p).max(axis=1, keepdims=True)                       # (V, 1) max-norm, 0 at the centre
    c = np.divide(p, shell, out=np.zeros_like(p), where=shell > 0)     # on the cube's surface
    c2 = c * c
    sphere = c * np.sqrt(1 - (np.roll(c2, 1, axis=1) + np.roll(c2, 2, axis=1)) / 2
                         + np.roll(c2, 1, axis=1) * np.roll(c2, 2, axis=1) / 3)
    vertices = point + float(radius) * shell * sphere
    return TetMesh(vertices, oriented_tets(vertices, tets))


def sliver_box_mesh(size=(0.2, 0.2, 0.2), cells=(4, 4, 4), jitter: float = 0.001, seed: int = 0) -> TetMesh:
    """A box meshed badly on purpose, full of slivers: the Delaunay tets of a lattice whose interior
    nodes are moved at random by up to `jitter` cells (nearly co-spherical points make flat tets).

    size: metres; cells: lattice cells per axis. The defaults give 444 tets, 64 of them slivers.
    Hung from its highest 5 % of vertices (E = 1e5 Pa, dt = 1/60 s, 50 VBD iterations per step),
    VBD turns one of them inside out from the 4th step on while converged Newton inverts none:
    a small test case for `benchmarks/inversion.py` and the solver tests.
    """
    from scipy.spatial import Delaunay

    size, cells = _box_dimensions(size, cells)
    if isinstance(jitter, bool) or not isinstance(jitter, numbers.Real) or not 0 <= jitter < 0.5:
        raise MeshError(f"sliver jitter must be a number of cells in [0, 0.5) (nodes stay inside their cell), "
                        f"got {jitter!r}")
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or seed < 0:
        raise MeshError(f"sliver seed must be a whole number >= 0, got {seed!r}")
    axes = [np.linspace(0.0, size[a], cells[a] + 1) for a in range(3)]
    points = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    interior = (points > 1e-9 * size) & (points < size * (1 - 1e-9))
    shift = np.random.default_rng(seed).uniform(-1.0, 1.0, points.shape) * jitter * size / cells
    points = points + np.where(interior, shift, 0.0)
    tets = Delaunay(points).simplices
    return TetMesh(points, without_degenerate(points, tets))


def load_mesh(path, resolution: int = 16, *, scale: float = None, fit: float = None, repair: bool = False,
              mesher=Mesher.VOXELS, edge_length: float = None) -> TetMesh:
    """Read a volume mesh, or tetrahedralise a closed surface; path: a str, bytes or os.PathLike.

    Volume formats: anything meshio reads (.msh, .vtk, .vtu, .mesh, TetGen .node/.ele, ...), with
    tets, hexahedra, wedges and pyramids (split conformingly into tets, `solver.cells`) and their
    higher-order versions (corner nodes kept, with a `MeshWarning`). Lower-dimensional cells of any
    order in a volume file (boundary triangles, edges, points: gmsh writes them) are ignored.
    Surface formats (.obj, .stl, .ply, .off, ...): read with trimesh and filled by `mesher`:
    `Mesher.VOXELS` (default, `resolution` cells along the longest side) or `Mesher.TETWILD`
    (optional pytetwild; `edge_length` in metres after scaling, default 1/20 of the diagonal).

    scale: multiply every coordinate by this factor (e.g. 0.001 for a file in millimetres).
    fit: scale uniformly so that the longest side of the bounding box is `fit` metres.
    repair: drop zero-volume tets and slivers (`TetMesh.without_slivers`) instead of failing or warning.
    A mesh that keeps slivers gets a one-line `MeshQualityWarning`.
    """
    path = _file_path(path)
    factor_of = _scale_rule(scale, fit)
    if not isinstance(repair, bool):
        raise ConfigError(f"repair must be True or False, got {repair!r}")
    mesher = enum_value(Mesher, mesher, "mesher")
    if edge_length is not None and mesher is not Mesher.TETWILD:
        raise ConfigError("edge_length only applies to mesher='tetwild'; use resolution for voxels")
    if not os.path.exists(path):
        raise MeshError(f"{path}: file not found; check the path")
    if os.path.isdir(path):
        raise MeshError(f"{path}: is a folder, not a mesh file; give the file's path")
    if path.lower().endswith(SURFACE_SUFFIXES):
        vertices, faces = _read_surface(path)
        vertices = vertices * factor_of(vertices)
        if mesher is Mesher.TETWILD:
            vertices, tets = tetwild_tets(vertices, faces, edge_length, name=path)
        else:
            vertices, tets = tetrahedralize_surface(vertices, faces, resolution, name=path)
        factor = 1.0
    else:
        vertices, tets = _read_volume(path)
        used = np.unique(tets)
        factor = factor_of(vertices[used]) if np.isfinite(vertices[used]).all() else 1.0
    if repair:
        tets = without_degenerate(vertices, tets)
    try:
        mesh = TetMesh(vertices * factor, tets)
    except MeshError as err:
        raise MeshError(f"{path}: {err}") from None
    if repair:
        mesh = mesh.without_slivers()
    quality = mesh.quality()
    if quality.n_slivers:
        fix = ("they hold the mesh together, so repair kept them; remesh it with .remeshed() (needs pytetwild)"
               if repair else "load it with repair=True to drop them, or remesh it with .remeshed() "
               "(needs pytetwild)")
        warnings.warn(f"{path}: {quality.summary()}; slivers can invert under load: simulate it with "
                      f"Simulation(..., keep_orientation=True), or {fix}",
                      MeshQualityWarning, stacklevel=2)
    return mesh


def _file_path(path) -> str:
    """`path` (a str, bytes or os.PathLike) as a str, or a one-line `ConfigError`."""
    try:
        return os.fsdecode(path)
    except TypeError:
        raise ConfigError(f"a mesh file path must be a str, bytes or pathlib.Path, got {type(path).__name__} "
                          f"{path!r}; pass the file's name, e.g. 'bar.msh'") from None


def _scale_rule(scale, fit):
    """Check the `scale` / `fit` arguments; return a function (N, 3) points -> scale factor."""
    for name, value in (("scale", scale), ("fit", fit)):
        if value is not None and not (isinstance(value, numbers.Real) and not isinstance(value, bool)
                                      and np.isfinite(value) and value > 0):
            raise ConfigError(f"{name} must be a positive number, got {value!r}")
    if scale is not None and fit is not None:
        raise ConfigError("give scale or fit, not both: scale multiplies coordinates, fit sets the "
                          "longest bounding-box side in metres")
    if fit is None:
        return lambda points: float(scale) if scale is not None else 1.0
    return lambda points: float(fit) / float(np.ptp(points, axis=0).max())


def without_degenerate(vertices, tets):
    """Tets (M', 4) without those using a vertex twice or of zero volume (for `repair=True`)."""
    srt = np.sort(tets, axis=1)
    tets = tets[(srt[:, 1:] != srt[:, :-1]).all(axis=1)]
    ok = np.isfinite(vertices[tets]).all(axis=(1, 2))
    ok[ok] = ~degenerate_mask(vertices, tets[ok])
    return tets[ok]


def _read_volume(path):
    """(points (N, 3), tets (M, 4)) of a volume file, every cell split into tets."""
    import meshio

    log = io.StringIO()
    try:
        with contextlib.redirect_stderr(log), contextlib.redirect_stdout(log):
            raw = meshio.read(path)
    except meshio.ReadError as err:        # raised by meshio.read itself: no reader for this suffix
        raise MeshError(f"{path}: cannot read this file ({err}); use a format meshio reads, "
                        "e.g. .msh, .vtu, .vtk, .mesh or TetGen .node/.ele") from None
    except ModuleNotFoundError as err:      # meshio's HDF5-based formats (.xdmf, .med, .h5m) need h5py
        raise MeshError(f"{path}: reading this format needs the Python package {err.name}; "
                        f"pip install {err.name}, or convert the file to .vtu or .msh") from None
    except (Exception, SystemExit) as err:  # the suffix's reader failed: it raised, or printed why and exited
        if isinstance(err, SystemExit):
            said = [line.removeprefix("Error: ") for line in log.getvalue().splitlines() if line.strip()]
        else:
            said = str(err).splitlines()[:1] or [type(err).__name__]
        reason = "; ".join(said) or "no reason given"
        raise MeshError(f"{path}: cannot read this file, it is damaged, truncated or not in the format its "
                        f"suffix names (meshio: {reason}); export it again") from None
    kinds = sorted({c.type for c in raw.cells})
    unknown = [k for k in kinds if linear_cell(k) is None and not is_lower_dimensional(k)]
    if unknown:
        raise MeshError(f"{path}: has cells of type {', '.join(unknown)} that cannot be split into tets; "
                        "convert them to tetrahedra, hexahedra, wedges or pyramids")
    blocks = [(c.type, c.data) for c in raw.cells if linear_cell(c.type) is not None and len(c.data)]
    if not blocks:
        if any(is_surface_cell(k) for k in kinds):
            raise MeshError(f"{path}: contains only surface cells ({', '.join(kinds)}), no volume; "
                            "a surface mesh must be tetrahedralised first: save it as .obj/.stl/.off and load that")
        raise MeshError(f"{path}: contains no volume cells (cell types: {', '.join(kinds) or 'none'}); "
                        "give a mesh of tetrahedra, hexahedra, wedges or pyramids")
    n_points = len(raw.points)
    for kind, data in blocks:
        missing = (data < 0) | (data >= n_points)
        if missing.any():
            cell, node = np.argwhere(missing)[0]
            raise MeshError(f"{path}: {kind} cell {cell} names point {data[cell, node]}, but the file has "
                            f"{n_points} points (0 to {n_points - 1}); the file is damaged: export it again")
    higher = sorted({k for k, _ in blocks if k not in CORNERS})
    if higher:
        count = sum(len(d) for k, d in blocks if k not in CORNERS)
        warnings.warn(f"{path}: kept only the corner nodes of {count} higher-order cells ({', '.join(higher)}); "
                      "the simulation uses linear tets", MeshWarning, stacklevel=3)
    tets = [split_cells(linear_cell(k), d[:, :CORNERS[linear_cell(k)]]) for k, d in blocks]
    return np.asarray(raw.points, dtype=np.float64), np.concatenate(tets)


def _read_surface(path):
    import trimesh

    try:
        surface = trimesh.load(path, force="mesh", process=False)
        used = np.unique(surface.faces)
        bad = used[~np.isfinite(surface.vertices[used]).all(axis=1)]
        bad_points = surface.vertices[bad]
        surface.process()        # what trimesh.load does by default, but it drops NaN vertices without a word
    except Exception as err:
        reason = str(err).splitlines()[0] if str(err) else type(err).__name__
        raise MeshError(f"{path}: cannot read this surface ({reason}); check the file") from None
    if len(bad):
        raise MeshError(f"{path}: {len(bad)} vertices used by triangles have NaN or infinite coordinates (first: "
                        f"vertex {bad[0]} counting from 0, at {bad_points[0].tolist()}); fix or remove them in the "
                        "file")
    if len(surface.faces) == 0:
        raise MeshError(f"{path}: has no triangles; give a closed triangle surface")
    if not surface.is_watertight:
        raise MeshError(f"{path}: the surface is not closed (watertight), so its inside is undefined; "
                        "repair its holes (e.g. in Blender or MeshLab) first")
    return np.asarray(surface.vertices, dtype=np.float64), np.asarray(surface.faces, dtype=np.int64)


def _mesh_arrays(mesh):
    """(vertices (N, 3) float64, tets (M, 4) int64) of a `TetMesh` or a `(vertices, tets)` pair, else a
    one-line `MeshError` naming what is wrong."""
    if isinstance(mesh, TetMesh):
        return mesh.vertices.astype(np.float64), mesh.tets.astype(np.int64)
    if not (isinstance(mesh, (tuple, list)) and len(mesh) == 2):
        raise MeshError(f"save_mesh needs a TetMesh or a (vertices, tets) pair, got {type(mesh).__name__}")
    try:
        vertices = np.asarray(mesh[0], dtype=np.float64)
        tets = np.asarray(mesh[1])
    except (TypeError, ValueError):
        raise MeshError("save_mesh: vertices must be an (N, 3) array of numbers and tets an (M, 4) array of "
                        "vertex indices") from None
    if vertices.ndim != 2 or vertices.shape[1] != 3 or not np.isfinite(vertices).all():
        raise MeshError(f"save_mesh: vertices must be an (N, 3) array of finite numbers, got shape {vertices.shape}")
    if (tets.ndim != 2 or tets.shape[1] != 4 or not np.issubdtype(tets.dtype, np.integer)
            or (tets.size and (tets.min() < 0 or tets.max() >= len(vertices)))):
        raise MeshError(f"save_mesh: tets must be an (M, 4) array of indices below {len(vertices)} (the vertex "
                        f"count), got shape {tets.shape} of {tets.dtype}")
    return vertices, tets.astype(np.int64)


def _point_data(point_data, n: int) -> dict:
    """`point_data` as {name: (n,) or (n, k) float array}, else a one-line `MeshError`."""
    if point_data is None:
        return {}
    if not isinstance(point_data, dict):
        raise MeshError(f"save_mesh: point_data must be a dict of per-vertex arrays, got {type(point_data).__name__}")
    checked = {}
    for name, values in point_data.items():
        try:
            values = np.asarray(values, dtype=np.float64)
        except (TypeError, ValueError):
            raise MeshError(f"save_mesh: point_data[{name!r}] must be an array of numbers") from None
        if values.ndim not in (1, 2) or len(values) != n:
            raise MeshError(f"save_mesh: point_data[{name!r}] has shape {values.shape}; it needs one row per "
                            f"vertex, ({n},) or ({n}, k)")
        checked[str(name)] = values
    return checked


def save_mesh(mesh, path, point_data: dict | None = None) -> None:
    """Write a mesh (a `TetMesh` or a `(vertices, tets)` pair) with meshio.

    Volume formats get the tets; surface formats (.obj, .ply, .stl, .off) get the boundary triangles.
    point_data: optional {name: (N,) or (N, k) array} written where the format supports it.
    """
    import meshio

    vertices, tets = _mesh_arrays(mesh)
    path = _file_path(path)
    point_data = _point_data(point_data, len(vertices))
    if path.lower().endswith(SURFACE_SUFFIXES):
        cells = [("triangle", boundary_faces(tets))]
    else:
        cells = [("tetra", tets)]
    try:
        meshio.write(path, meshio.Mesh(vertices, cells, point_data=point_data))
    except ModuleNotFoundError as err:      # meshio's HDF5-based formats (.xdmf, .med, .h5m) need h5py
        raise MeshError(f"{path}: writing this format needs the Python package {err.name}; "
                        f"pip install {err.name}, or use .vtu or .msh") from None
    except OSError as err:
        raise MeshError(f"{path}: cannot write ({err.strerror}); check that the folder exists and is "
                        "writable") from None
    except (meshio.ReadError, meshio.WriteError) as err:   # meshio reports an unknown suffix as ReadError
        raise MeshError(f"{path}: cannot write this format ({err}); use a suffix meshio writes, "
                        "e.g. .vtu, .msh, .ply or .obj") from None
