"""Regenerate every mesh in assets/ from the project's own generators and the public surfaces here.

    python -m assets.make_assets

The tet meshes of real shapes (bunny, spot) need the optional mesher (`pip install -r
requirements-mesh.txt`); without it they are kept as committed and the rest is regenerated. Sources
and licences: assets/README.md.
"""
import os

import numpy as np
import trimesh

import solver

HERE = os.path.dirname(os.path.abspath(__file__))


def main():
    for cells in ((40, 4, 4), (80, 8, 8), (10, 2, 2)):
        name = "bar_{}x{}x{}.msh".format(*cells)
        solver.save_mesh(solver.box_mesh(size=(1.0, 0.1, 0.1), cells=cells), os.path.join(HERE, name))
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    sphere.export(os.path.join(HERE, "sphere.obj"))
    solver.save_mesh(solver.load_mesh(os.path.join(HERE, "sphere.obj"), resolution=12),
                     os.path.join(HERE, "sphere_r12.vtu"))
    torus = trimesh.creation.torus(major_radius=0.1, minor_radius=0.04, major_sections=48, minor_sections=24)
    torus.export(os.path.join(HERE, "torus.stl"))
    if solver.tetrahedralize.tetwild_available():
        make_real_shapes()
    else:
        print("pytetwild not installed: bunny/spot tet meshes left as committed "
              "(pip install -r requirements-mesh.txt to regenerate them)")
    for name in sorted(os.listdir(HERE)):
        if not name.endswith(".py"):
            print(f"{name}: {os.path.getsize(os.path.join(HERE, name)) / 1024:.0f} KiB")


# Real shapes: (surface file, tet mesh file, rotation from the file's y-up frame to z-up, target edge
# length in metres, optimise the shapes?). Each is scaled so that its longest side is SHAPE_SIZE.
SHAPE_SIZE = 0.2
Y_UP_TO_Z_UP = ((1, 0, 0), (0, 0, -1), (0, 1, 0))            # (x, y, z) -> (x, -z, y)
Y_UP_TO_Z_UP_SIDEWAYS = ((0, 0, 1), (1, 0, 0), (0, 1, 0))     # (x, y, z) -> (z, x, y): the cow's side faces -y
REAL_SHAPES = (
    ("bunny.off", "bunny.vtu", Y_UP_TO_Z_UP, 0.022, True),
    ("spot.off", "spot.vtu", Y_UP_TO_Z_UP_SIDEWAYS, 0.02, True),
    # the same bunny without fTetWild's shape optimisation: thousands of slivers, for tests and
    # benchmarks/inversion.py
    ("bunny.off", "bunny_slivers.vtu", Y_UP_TO_Z_UP, 0.022, False),
)


def make_real_shapes():
    for surface_name, name, rotation, edge_length, optimize in REAL_SHAPES:
        surface = trimesh.load(os.path.join(HERE, surface_name), force="mesh", process=True)
        x = np.asarray(surface.vertices, dtype=np.float64) @ np.asarray(rotation, dtype=np.float64).T
        x = (x - x.min(axis=0)) * (SHAPE_SIZE / np.ptp(x, axis=0).max())
        x[:, :2] -= 0.5 * (x[:, :2].max(axis=0))                      # centred in x, y; resting on z = 0
        vertices, tets = solver.tetrahedralize.tetwild_tets(x, surface.faces, edge_length, optimize=optimize,
                                                            name=surface_name)
        tets = solver.mesh.without_degenerate(vertices, tets)
        mesh = solver.TetMesh(vertices, tets)
        solver.save_mesh(mesh, os.path.join(HERE, name))
        print(f"{name}: {mesh.n_tets} tets, {mesh.n_vertices} vertices; {mesh.quality().summary()}")


if __name__ == "__main__":
    main()
