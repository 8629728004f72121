"""The surface primitives that contact acts on (issue 17): the boundary triangles of a tet mesh, their
edges and their vertices, built once per mesh with numpy."""
from dataclasses import dataclass

import numpy as np

from .tetmesh import boundary_faces


@dataclass(frozen=True, eq=False)
class SurfacePrimitives:
    """vertices (V,) int32: the mesh vertices on the boundary, ascending. edges (E, 2) int32: the edges of
    the boundary triangles, each once, lower vertex first, sorted. triangles (T, 3) int32: the boundary
    triangles, counter-clockwise seen from outside (`boundary_faces`). All index the mesh's vertices."""

    vertices: np.ndarray
    edges: np.ndarray
    triangles: np.ndarray


def surface_primitives(tets: np.ndarray) -> SurfacePrimitives:
    """The `SurfacePrimitives` of the (M, 4) positively oriented `tets` (every body of a merged mesh)."""
    triangles = boundary_faces(tets)
    edges = np.sort(triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    edges = np.unique(edges, axis=0).astype(np.int32)
    vertices = np.unique(triangles).astype(np.int32)
    for a in (vertices, edges, triangles):
        a.setflags(write=False)
    return SurfacePrimitives(vertices, edges, triangles)
