"""Vertex Block Descent for elastic tetrahedral meshes, in Taichi.

Importing this package does not initialise Taichi; `Simulation` does that on first use. The global
solvers (the `solver.newton` wing) load on first use of one of their names, so a copy without that
wing (the homework starter) still imports.

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
from .physics.material import Material
from .mesh.tetmesh import TetMesh, ball_mesh, box_mesh, boundary_faces, load_mesh, save_mesh, sliver_box_mesh
from .method import Method
from .metrics import relative_energy_gap, relative_error
from .mesh.quality import MeshQuality, det_F, inverted_count
from .vbd.simulation import InitialGuess, IterationRecord, Settings, Simulation
from .mesh.tetrahedralize import Mesher
from .mesh.topology import Topology
from .vbd.global_methods import HAS_GLOBAL_SOLVERS as _HAS_GLOBAL_SOLVERS, require_global_solvers as _require_global_solvers

_NEWTON_NAMES = {"LinearSolver": "direct", "fast_newton_solve": "direct", "NewtonResult": "damped_newton",
                 "StepProblem": "oracle", "newton_solve": "oracle", "Preconditioner": "pcg", "newton_pcg": "pcg"}


def __getattr__(name):
    """The newton wing's public names, imported on first use (PEP 562); ConfigError without the wing."""
    if name not in _NEWTON_NAMES:
        raise AttributeError(f"module 'solver' has no attribute {name!r}")
    from importlib import import_module

    _require_global_solvers()
    return getattr(import_module(f".newton.{_NEWTON_NAMES[name]}", __name__), name)


__all__ = [
    "Coloring", "ConfigError", "Contact", "Ground", "InitialGuess", "IterationRecord", "Material", "MeshError",
    "MeshQuality", "MeshQualityWarning", "MeshWarning", "Mesher", "Method", "Precision", "Settings", "Simulation",
    "TetMesh", "Topology", "VBDError", "VertexOrder", "ball_mesh", "boundary_faces", "box_mesh", "color_vertices", "det_F",
    "ensure_taichi", "inverted_count", "is_valid_coloring", "load_mesh", "merge_meshes", "relative_energy_gap",
    "relative_error", "save_mesh", "sliver_box_mesh",
]
if _HAS_GLOBAL_SOLVERS:
    __all__ += sorted(_NEWTON_NAMES)
