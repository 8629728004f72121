"""Greedy graph colouring of the mesh vertices (lecture: "Greedy Graph Coloring").

Two vertices that share a tet get different colours, so all vertices of one colour can be solved
in parallel without touching each other's tets (VBD [Chen et al. 2024] Sec. 3.5). Colourings are
cached per mesh connectivity and per source of the colouring code (`_greedy`): in memory, and on
disk under `$VBD_CACHE_DIR` (default `~/.cache/vbd-taichi`; set it to an empty string to switch the
disk cache off). Keying on the source means a cache written by other code (the reference solution,
an earlier version of a homework `_greedy`) is never read.
"""
import hashlib
import inspect
import os
import tempfile
import time
from dataclasses import dataclass
from enum import Enum

import numpy as np
from .._ti import ti

from ..backend import ensure_taichi
from ..errors import ConfigError, MeshError, enum_value
from ..todo import require_implemented
from .tetmesh import tet_indices
from .topology import vertex_neighbours

MAX_COLORS = 64


class VertexOrder(Enum):
    """The order in which greedy colouring visits vertices."""

    NATURAL = "natural"           # index order 0, 1, 2, ...
    LARGEST_FIRST = "largest_first"  # most neighbours first (ties by index)


@dataclass(frozen=True)
class Coloring:
    """colors: (N,) int32 colour of every vertex; n_colors; sizes: (n_colors,) vertices per colour;
    seconds: time spent colouring (0 when it came from a cache); cached: whether it came from one."""

    colors: np.ndarray
    n_colors: int
    sizes: np.ndarray
    seconds: float
    cached: bool


@ti.kernel
def _greedy(offsets: ti.types.ndarray(), neighbours: ti.types.ndarray(), order: ti.types.ndarray(),
            colors: ti.types.ndarray()) -> ti.i32:
    """Visit vertices in `order`; give each the smallest colour no coloured neighbour has.

    colors must start at -1. Returns the number of colours; more than 64 means the colouring failed.
    """
    n_colors = 0
    ti.loop_config(serialize=True)
    for k in range(order.shape[0]):
        # BEGIN SOLUTION task=coloring
        v = order[k]
        used = ti.u64(0)
        for e in range(offsets[v], offsets[v + 1]):
            c = colors[neighbours[e]]
            if 0 <= c < MAX_COLORS:
                used |= ti.u64(1) << ti.u64(c)
        c = 0
        while c < MAX_COLORS and (used >> ti.u64(c)) & ti.u64(1) == 1:
            c += 1
        colors[v] = c
        n_colors = ti.max(n_colors, c + 1)
        # END SOLUTION
    return n_colors


_memory_cache = {}
_code_digest = {}


def _greedy_digest() -> str:
    """12 hex digits of a hash of `_greedy`'s source: part of every cache key."""
    if "greedy" not in _code_digest:
        try:
            source = inspect.getsource(_greedy)
        except (OSError, TypeError):
            source = ""
        _code_digest["greedy"] = hashlib.sha256(source.encode("utf-8")).hexdigest()[:12]
    return _code_digest["greedy"]


def _cache_file(key: str):
    folder = os.environ.get("VBD_CACHE_DIR", os.path.join(os.path.expanduser("~"), ".cache", "vbd-taichi"))
    return os.path.join(folder, f"colors-{key}.npy") if folder else None


def color_vertices(tets: np.ndarray, n_vertices: int, order: VertexOrder = VertexOrder.NATURAL,
                   key: str = None) -> Coloring:
    """Greedy colouring of the vertex graph of `tets` (M, 4); deterministic for a given order.

    order: a `VertexOrder` or its value ("natural", "largest_first"). key: a hash of the connectivity
    (`TetMesh.topology_key()`); when given, results are cached (keyed on it, the order and the source of
    `_greedy`). Tets and vertex count are checked as `TetMesh` checks them (a one-line `MeshError`).
    """
    require_implemented(_greedy)
    order = enum_value(VertexOrder, order, "order (solver.VertexOrder)")
    tets = tet_indices(tets, n_vertices)
    cache_key = f"{key}-{order.value}-{_greedy_digest()}" if key else None
    if cache_key in _memory_cache:
        return _memory_cache[cache_key]
    path = _cache_file(cache_key) if cache_key else None
    colors = _read_cache(path) if path else None
    if colors is not None and colors.shape == (n_vertices,) and is_valid_coloring(tets, colors):
        return _remember(cache_key, colors, 0.0, True)
    ensure_taichi()
    start = time.perf_counter()
    offsets, neighbours = vertex_neighbours(tets, n_vertices)
    if order is VertexOrder.NATURAL:
        visit = np.arange(n_vertices, dtype=np.int32)
    else:
        visit = np.argsort(-np.diff(offsets), kind="stable").astype(np.int32)
    colors = np.full(n_vertices, -1, dtype=np.int32)
    n_colors = _greedy(offsets, neighbours, visit, colors)
    if n_colors > MAX_COLORS:
        raise MeshError(f"the mesh needs more than {MAX_COLORS} colours (a vertex has too many "
                        "neighbours); remesh with better-shaped tets")
    seconds = time.perf_counter() - start
    if path:
        _write_cache(path, colors)
    return _remember(cache_key, colors, seconds, False)


def _read_cache(path: str):
    """The colours cached at path, or None when there are none or the file cannot be read."""
    try:
        return np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError):
        return None


def _write_cache(path: str, colors: np.ndarray) -> None:
    """Cache colours at path: written to a file of its own first and then renamed, so that processes
    colouring the same mesh at once (parallel test workers, renders) never read a half-written file. The
    disk cache is an optimisation only: when writing fails (a full disk), nothing is left behind."""
    part = None
    try:
        os.makedirs(os.path.dirname(path), exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=os.path.dirname(path), suffix=".part", delete=False) as file:
            part = file.name
            np.save(file, colors)
        os.replace(part, path)
    except OSError:
        if part is not None and os.path.exists(part):
            os.unlink(part)


def _remember(cache_key, colors, seconds, cached) -> Coloring:
    n_colors = int(colors.max()) + 1
    result = Coloring(colors, n_colors, np.bincount(colors, minlength=n_colors), seconds, cached)
    if cache_key:
        _memory_cache[cache_key] = Coloring(colors, n_colors, result.sizes, 0.0, True)
    return result


def is_valid_coloring(tets: np.ndarray, colors: np.ndarray) -> bool:
    """True when every vertex has a colour >= 0 and the 4 vertices of every tet differ; tets (M, 4), colors
    (N,) int, one per vertex (fewer than the tets use is a `ConfigError`)."""
    tets, colors = np.asarray(tets), np.asarray(colors)
    if tets.size and (colors.ndim != 1 or len(colors) <= tets.max()):
        raise ConfigError(f"colors must hold one colour per vertex, at least {tets.max() + 1} for these tets, "
                          f"got shape {colors.shape}")
    if (colors < 0).any():
        return False
    c = np.sort(colors[tets], axis=1)
    return bool((c[:, 1:] != c[:, :-1]).all())
