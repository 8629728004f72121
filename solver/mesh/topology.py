"""Derived mesh data, built once per mesh with numpy and cached: the rest geometry (Dm^-1 and rest
volumes, `rest_geometry`), connectivity in compressed sparse row (CSR) form (`vertex_tet_adjacency`,
`vertex_neighbours`), and the slot-major adjacency layout the VBD sweep reads (`build_topology`).
Every solver reads Dm^-1 and the rest volumes from here."""
import hashlib
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from .cells import signed_volumes


def vertex_tet_adjacency(tets: np.ndarray, n_vertices: int):
    """Tets around each vertex.

    tets: (M, 4). Returns (offsets (N+1,), tet (4M,), local (4M,)) int32: the tets around vertex i are
    `tet[offsets[i]:offsets[i+1]]`, and i is local vertex `local[...]` (0..3) of each.
    """
    flat = np.asarray(tets).ravel()
    order = np.argsort(flat, kind="stable")
    counts = np.bincount(flat, minlength=n_vertices)
    offsets = np.concatenate([[0], np.cumsum(counts)])
    return (offsets.astype(np.int32), (order // 4).astype(np.int32), (order % 4).astype(np.int32))


def vertex_neighbours(tets: np.ndarray, n_vertices: int):
    """Vertices that share a tet with each vertex, as CSR (offsets (N+1,), neighbours (E,)) int32."""
    tets = np.asarray(tets, dtype=np.int64)
    a = np.repeat(tets, 4, axis=1).ravel()
    b = np.tile(tets, (1, 4)).ravel()
    keep = a != b
    pairs = np.unique(a[keep] * n_vertices + b[keep])
    src, dst = pairs // n_vertices, pairs % n_vertices
    offsets = np.concatenate([[0], np.cumsum(np.bincount(src, minlength=n_vertices))])
    return offsets.astype(np.int32), dst.astype(np.int32)


@dataclass(frozen=True, eq=False)
class Topology:
    """The slot-major adjacency one VBD sweep streams through (lecture notes, chapter 3,
    "Computing f_i fast"); read-only, built once per mesh and constraint set and cached.

    The free vertices are listed colour by colour: slot k holds vertex `color_order[k]`, and colour c
    owns the slots `color_ranges[c][0] <= k < color_ranges[c][1]`. The tets around the vertex in slot
    k are the entries `offsets[k] <= e < offsets[k + 1]`, stored in slot order so that one colour
    reads one sequential stream. For each entry, with d_j = x_j - x_i for the other three vertices:

      others (E, 3) int32: the other vertices j of the tet;
      q      (E, 3):       q_j = m_j . m_i, so that F m_i = sum_j q_j d_j;
      c      (E,):         1 / det[d_1 d_2 d_3] at rest, so that det F = c det[d_1 d_2 d_3];
      m_sq   (E,):         |m_i|^2;
      volume (E,):         the tet's rest volume in m^3;

    where m_k is the row of Dm^-1 that belongs to local vertex k (m_0 = -(m_1 + m_2 + m_3)).
    color_order (S,) int32; offsets (S + 1,) int32; color_ranges: one (start, end) per colour.
    """

    color_order: np.ndarray
    color_ranges: tuple
    offsets: np.ndarray
    others: np.ndarray
    q: np.ndarray
    c: np.ndarray
    m_sq: np.ndarray
    volume: np.ndarray

    def __post_init__(self):
        for name in ("color_order", "offsets", "others", "q", "c", "m_sq", "volume"):
            getattr(self, name).flags.writeable = False

    @property
    def n_colors(self) -> int:
        return len(self.color_ranges)

    @property
    def n_slots(self) -> int:
        """Number of free vertices."""
        return int(self.color_order.shape[0])

    @property
    def n_entries(self) -> int:
        """Number of (free vertex, tet) pairs."""
        return int(self.others.shape[0])


_topology_cache: "OrderedDict[str, Topology]" = OrderedDict()
_TOPOLOGY_CACHE_SIZE = 8


@dataclass(frozen=True, eq=False)
class RestGeometry:
    """The rest shape of every tet, read-only.

    grad_rows (M, 4, 3): rows m_k per local vertex k, so that F = sum_k x_k m_k^T; rows 1-3 are
    Dm^-1 (`Dm_inv`, (M, 3, 3)) and m_0 = -(m_1 + m_2 + m_3). volumes (M,): rest volumes in m^3.
    """

    grad_rows: np.ndarray
    volumes: np.ndarray

    def __post_init__(self):
        self.grad_rows.flags.writeable = False
        self.volumes.flags.writeable = False

    @property
    def Dm_inv(self) -> np.ndarray:
        """(M, 3, 3) inverse rest edge matrices Dm^-1, Dm = [X_1 - X_0, X_2 - X_0, X_3 - X_0]."""
        return self.grad_rows[:, 1:]


_rest_cache: "OrderedDict[str, RestGeometry]" = OrderedDict()


def _digest(*arrays) -> str:
    digest = hashlib.sha1()
    for a in arrays:
        digest.update(a.dtype.str.encode())
        digest.update(np.ascontiguousarray(a).tobytes())
    return digest.hexdigest()


def rest_geometry(vertices: np.ndarray, tets: np.ndarray) -> RestGeometry:
    """The `RestGeometry` of rest positions vertices (N, 3) and positively oriented tets (M, 4): the
    one place Dm^-1 and the rest volumes are computed. Cached in memory by the bytes of both arrays."""
    X = np.asarray(vertices, dtype=np.float64)
    T = np.asarray(tets, dtype=np.int64)
    key = _digest(X, T)
    if key in _rest_cache:
        _rest_cache.move_to_end(key)
        return _rest_cache[key]
    d1, d2, d3 = (X[T[:, k]] - X[T[:, 0]] for k in (1, 2, 3))      # the columns of Dm
    volumes = signed_volumes(X, T)
    # Dm^-1 by cofactors, not LAPACK per 3x3: its rows are d2 x d3, d3 x d1, d1 x d2 over det Dm = 6 vol
    Dm_inv = np.stack([np.cross(d2, d3), np.cross(d3, d1), np.cross(d1, d2)], axis=1) / (6.0 * volumes)[:, None, None]
    rest = RestGeometry(grad_rows=np.concatenate([-Dm_inv.sum(axis=1, keepdims=True), Dm_inv], axis=1),
                        volumes=volumes)
    _rest_cache[key] = rest
    if len(_rest_cache) > _TOPOLOGY_CACHE_SIZE:
        _rest_cache.popitem(last=False)
    return rest


def grad_rows(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(M, 4, 3) rows m_k of Dm^-1 per local vertex k, so that F = sum_k x_k m_k^T (`rest_geometry`)."""
    return rest_geometry(vertices, tets).grad_rows


def build_topology(vertices: np.ndarray, tets: np.ndarray, colors: np.ndarray) -> Topology:
    """The `Topology` of a mesh whose free vertices have colours `colors` (N,) (-1 for fixed and
    kinematic vertices). vertices (N, 3) rest positions, tets (M, 4) positively oriented.

    Cached in memory by the bytes of all three arrays, so that a second simulation of the same mesh
    and constraints builds nothing.
    """
    digest = hashlib.sha1()
    for a in (np.ascontiguousarray(vertices, dtype=np.float64), np.ascontiguousarray(tets, dtype=np.int32),
              np.ascontiguousarray(colors, dtype=np.int32)):
        digest.update(a.tobytes())
    key = digest.hexdigest()
    if key in _topology_cache:
        _topology_cache.move_to_end(key)
        return _topology_cache[key]
    topology = _build(np.asarray(vertices, dtype=np.float64), np.asarray(tets), np.asarray(colors))
    _topology_cache[key] = topology
    if len(_topology_cache) > _TOPOLOGY_CACHE_SIZE:
        _topology_cache.popitem(last=False)
    return topology


def _build(X: np.ndarray, T: np.ndarray, colors: np.ndarray) -> Topology:
    order = np.argsort(colors, kind="stable")
    order = order[colors[order] >= 0].astype(np.int32)
    counts = np.bincount(colors[order])
    counts = counts[counts > 0]
    ends = np.cumsum(counts)
    color_ranges = tuple((int(e - n), int(e)) for n, e in zip(counts, ends))

    rest = rest_geometry(X, T)
    rows, vol = rest.grad_rows, rest.volumes
    offsets, adj_tet, adj_local = vertex_tet_adjacency(T, len(X))
    degree = np.diff(offsets)[order]
    slot_offsets = np.concatenate([[0], np.cumsum(degree)])
    entry = np.repeat(offsets[order] - slot_offsets[:-1], degree) + np.arange(slot_offsets[-1])
    adj_tet, adj_local = adj_tet[entry], adj_local[entry]
    others = (adj_local[:, None] + np.arange(1, 4)[None, :]) % 4                  # (E, 3) local ids
    m_i = rows[adj_tet, adj_local]                                                  # (E, 3)
    m_j = np.take_along_axis(rows[adj_tet], others[:, :, None], axis=1)             # (E, 3, 3)
    j = np.take_along_axis(T[adj_tet], others, axis=1)
    Ds = (X[j] - X[T[adj_tet, adj_local]][:, None, :]).transpose(0, 2, 1)
    return Topology(color_order=order, color_ranges=color_ranges,
                    offsets=slot_offsets.astype(np.int32), others=j.astype(np.int32),
                    q=np.einsum("ejk,ek->ej", m_j, m_i), c=1.0 / np.linalg.det(Ds),
                    m_sq=np.einsum("ek,ek->e", m_i, m_i), volume=vol[adj_tet])
