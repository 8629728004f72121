"""Vertex Block Descent for elastic tetrahedral meshes, in Taichi.

Importing this package does not initialise Taichi; `Simulation` does that on first use.

    import solver
    mesh = solver.box_mesh(size=(1, .1, .1), cells=(40, 4, 4))
    sim = solver.Simulation(mesh, solver.Material(youngs_modulus=1e6, poisson_ratio=0.3, density=1000.0),
                            dt=1/60, fixed=mesh.vertices[:, 0] < 1e-9, iterations=100)
    sim.step()
"""
from .backend import Precision, ensure_taichi
from .mesh.bodies import merge_meshes
from .mesh.coloring import Coloring, VertexOrder, color_vertices, is_valid_coloring
from .physics.contact import Contact
from .physics.ground import Ground
from .errors import ConfigError, MeshError, MeshQualityWarning, MeshWarning, VBDError
from .newton.direct import LinearSolver, fast_newton_solve
from .physics.material import Material
from .mesh.tetmesh import TetMesh, box_mesh, boundary_faces, load_mesh, save_mesh, sliver_box_mesh
from .method import Method
from .metrics import relative_energy_gap, relative_error
from .newton.damped_newton import NewtonResult
from .newton.oracle import StepProblem, newton_solve
from .newton.pcg import Preconditioner, newton_pcg
from .mesh.quality import MeshQuality, det_F, inverted_count
from .vbd.simulation import InitialGuess, IterationRecord, Settings, Simulation
from .mesh.tetrahedralize import Mesher
from .mesh.topology import Topology

__all__ = [
    "Coloring", "ConfigError", "Contact", "Ground", "InitialGuess", "IterationRecord", "LinearSolver", "Material",
    "MeshError", "MeshQuality", "MeshQualityWarning", "MeshWarning", "Mesher", "Method", "NewtonResult",
    "Precision", "Preconditioner", "Settings", "Simulation", "StepProblem", "TetMesh", "Topology", "VBDError",
    "VertexOrder", "boundary_faces", "box_mesh", "color_vertices", "det_F", "ensure_taichi",
    "fast_newton_solve", "inverted_count", "is_valid_coloring", "load_mesh", "merge_meshes", "newton_pcg",
    "newton_solve",
    "relative_energy_gap", "relative_error", "save_mesh", "sliver_box_mesh",
]
