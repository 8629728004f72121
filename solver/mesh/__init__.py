"""Meshes: loading and validation (`tetmesh`), cell splitting (`cells`), quality (`quality`),
tetrahedralisation of surfaces (`tetrahedralize`, `voxelize`), graph colouring (`coloring`) and the
per-mesh derived data every solver reads (`topology`: incidence, Dm^-1, rest volumes); several bodies in
one mesh (`bodies`) and the surface primitives contact acts on (`surface`).

Lowest wing: it imports nothing from the other wings.
"""
from .bodies import body_labels, merge_meshes
from .coloring import Coloring, VertexOrder, color_vertices, is_valid_coloring
from .quality import MeshQuality, det_F, inverted_count
from .surface import SurfacePrimitives, surface_primitives
from .tetmesh import TetMesh, ball_mesh, boundary_faces, box_mesh, load_mesh, save_mesh, sliver_box_mesh
from .tetrahedralize import Mesher
from .topology import Topology
