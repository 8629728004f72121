"""Mesh connectivity in compressed sparse row (CSR) form, built once per mesh with numpy."""
import numpy as np


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
