"""Several bodies in one mesh: `merge_meshes` puts meshes side by side, `body_labels` finds them again
as the mesh's vertex-connected components (issue 17)."""
import numpy as np

from ..errors import MeshError
from .tetmesh import TetMesh


def merge_meshes(meshes, *more) -> TetMesh:
    """One `TetMesh` holding every mesh of the list: the vertices of each in order, its tets renumbered
    by the vertices before it. The bodies stay where they are; place them apart first. (`more` only
    catches meshes passed one by one, merge_meshes(a, b), to say how to pass them.)"""
    if more:
        raise MeshError(f"merge_meshes takes one list of meshes, got {1 + len(more)} arguments; pass a list: "
                        "merge_meshes([a, b])")
    meshes = [] if isinstance(meshes, TetMesh) or not hasattr(meshes, "__iter__") else list(meshes)
    if not meshes:
        raise MeshError("merge_meshes needs a non-empty list of TetMesh, e.g. merge_meshes([mesh_a, mesh_b])")
    for k, mesh in enumerate(meshes):
        if not isinstance(mesh, TetMesh):
            raise MeshError(f"merge_meshes item {k} is a {type(mesh).__name__}, not a TetMesh; "
                            "build it with box_mesh or load_mesh")
    starts = np.cumsum([0] + [m.n_vertices for m in meshes[:-1]])
    vertices = np.concatenate([m.vertices for m in meshes])
    tets = np.concatenate([m.tets.astype(np.int64) + s for m, s in zip(meshes, starts)])
    return TetMesh(vertices, tets)


def body_labels(tets: np.ndarray, n_vertices: int) -> np.ndarray:
    """(N,) int32 body of each vertex: the vertex-connected components of the (M, 4) tets, numbered
    0, 1, ... in the order of their smallest vertex."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    tets = np.asarray(tets, dtype=np.int64)
    a = np.repeat(tets[:, :1], 3, axis=1).ravel()
    graph = coo_matrix((np.ones(len(a)), (a, tets[:, 1:].ravel())), shape=(n_vertices, n_vertices))
    count, label = connected_components(graph, directed=False)
    smallest = np.full(count, n_vertices)
    np.minimum.at(smallest, label, np.arange(n_vertices))
    rank = np.empty(count, dtype=np.int32)
    rank[np.argsort(smallest)] = np.arange(count)
    return rank[label]
