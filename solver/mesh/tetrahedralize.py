"""Closed triangle surface -> tets: fTetWild (through the optional `pytetwild` package) or voxels.

fTetWild [Hu et al. 2020, "Fast Tetrahedral Meshing in the Wild"] makes well-shaped tets that follow
the surface within a small envelope; it is an optional extra (`pip install -r requirements-mesh.txt`)
because it is a compiled package. Its results are cached per input (a hash of the surface and the
parameters) on disk under `$VBD_CACHE_DIR` (default `~/.cache/vbd-taichi`; an empty string switches
the disk cache off), the same folder as the colouring cache. Voxels (`solver.voxelize`) need nothing
extra and are the default.
"""
from __future__ import annotations

import contextlib
import enum
import hashlib
import numbers
import os
import tempfile

import numpy as np

from ..errors import ConfigError, MeshError

# fTetWild's envelope: the output surface stays within this fraction of the bounding-box diagonal
# of the input (fTetWild's default is 1e-3; 5e-3 keeps small assets at a few thousand tets).
ENVELOPE = 5e-3


class Mesher(enum.Enum):
    """How a closed surface is filled with tets."""

    VOXELS = "voxels"     # a voxel lattice, 6 tets per voxel: no dependency, staircase boundary
    TETWILD = "tetwild"   # fTetWild via pytetwild: smooth boundary, well-shaped tets, optional extra


def cache_folder():
    """The on-disk cache folder (shared with the colouring cache), or None when switched off."""
    return os.environ.get("VBD_CACHE_DIR", os.path.join(os.path.expanduser("~"), ".cache", "vbd-taichi")) or None


def tetwild_available() -> bool:
    """Whether the optional `pytetwild` package can be imported."""
    try:
        import pytetwild  # noqa: F401
    except ImportError:
        return False
    return True


def tetwild_tets(vertices: np.ndarray, faces: np.ndarray, edge_length: float = None,
                 envelope: float = ENVELOPE, optimize: bool = True, name: str = "surface"):
    """Tetrahedralise a closed surface with fTetWild; results are cached per input.

    vertices: (V, 3) in metres; faces: (F, 3); edge_length: target tet edge length in metres
    (default: 1/20 of the bounding-box diagonal); envelope: allowed surface deviation as a fraction of
    the bounding-box diagonal; optimize: False skips fTetWild's shape optimisation (faster, but
    leaves many slivers: useful only to make a bad mesh on purpose).
    Returns (vertices (N, 3) float64, tets (M, 4) int64), orientation not yet fixed.
    Raises ConfigError when pytetwild is not installed.
    """
    vertices = np.ascontiguousarray(vertices, dtype=np.float64)
    faces = np.ascontiguousarray(faces, dtype=np.int32)
    diagonal = float(np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0)))
    if edge_length is None:
        edge_length = diagonal / 20.0
    if not (isinstance(edge_length, numbers.Real) and not isinstance(edge_length, bool)
            and np.isfinite(edge_length) and edge_length > 0):
        raise ConfigError(f"edge_length must be a positive length in metres, got {edge_length!r}")
    if not (isinstance(envelope, numbers.Real) and 0 < envelope < 0.1):
        raise ConfigError(f"envelope must be a fraction of the bounding-box diagonal in (0, 0.1), got {envelope!r}")
    if edge_length > diagonal:
        raise ConfigError(f"edge_length {edge_length:g} m is longer than the whole surface ({diagonal:g} m "
                          "diagonal); choose a smaller one")
    try:
        import pytetwild
    except ImportError:
        raise ConfigError("the tetwild mesher needs the optional package pytetwild; install it with "
                          "`pip install -r requirements-mesh.txt`, or use mesher='voxels'") from None
    digest = hashlib.sha1(vertices.tobytes())
    digest.update(faces.tobytes())
    digest.update(f"{edge_length!r} {envelope!r} {optimize!r} {getattr(pytetwild, '__version__', '?')}".encode())
    folder = cache_folder()
    path = os.path.join(folder, f"tetwild-{digest.hexdigest()}.npz") if folder else None
    if path and os.path.exists(path):
        with np.load(path) as cached:
            return cached["vertices"], cached["tets"]
    # one thread: fTetWild's multi-threaded result depends on scheduling, a cached asset should not.
    # fTetWild writes a scratch file (__tracked_surface.stl) into the working directory: run it in a
    # temporary one so that nothing lands in the user's folder.
    with tempfile.TemporaryDirectory(prefix="vbd-tetwild-") as scratch, contextlib.chdir(scratch):
        points, tets = pytetwild.tetrahedralize(vertices, faces, edge_length_abs=float(edge_length),
                                                epsilon=float(envelope), optimize=bool(optimize),
                                                num_threads=1)
    if len(tets) == 0:
        raise MeshError(f"{name}: fTetWild produced no tets; check that the surface is closed and "
                        "not tiny compared with edge_length")
    points, tets = np.asarray(points, dtype=np.float64), np.asarray(tets, dtype=np.int64)
    if path:
        try:
            os.makedirs(folder, exist_ok=True)
            with open(path + ".part", "wb") as file:
                np.savez(file, vertices=points, tets=tets)
            os.replace(path + ".part", path)
        except OSError:
            pass  # the disk cache is an optimisation only
    return points, tets
