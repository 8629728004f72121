"""Per-frame mesh export through meshio: volume meshes (.vtu) for ParaView, surfaces (.ply, .obj)."""
import enum

import meshio
import numpy as np


class ExportFormat(enum.Enum):
    NONE = "none"
    VTU = "vtu"     # the tets, with per-vertex data
    PLY = "ply"     # the boundary triangles
    OBJ = "obj"     # the boundary triangles


def export_mesh(path, export_format, positions, tets, faces, point_data=None):
    """Write one frame's mesh to ``path`` in ``export_format``."""
    points = np.asarray(positions, dtype=np.float64)
    if export_format is ExportFormat.VTU:
        mesh = meshio.Mesh(points, [("tetra", np.asarray(tets, dtype=np.int64))], point_data=point_data or {})
    else:
        used = np.unique(faces)
        remap = np.full(len(points), -1, dtype=np.int32)     # PLY has no 64-bit integers
        remap[used] = np.arange(len(used))
        mesh = meshio.Mesh(points[used], [("triangle", remap[faces])])
    meshio.write(str(path), mesh, file_format={"vtu": "vtu", "ply": "ply", "obj": "obj"}[export_format.value])
