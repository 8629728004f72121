"""Regenerate every mesh in assets/ from the project's own generators (no third-party mesh data).

    python -m assets.make_assets
"""
import os

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
    for name in sorted(os.listdir(HERE)):
        if not name.endswith(".py"):
            print(f"{name}: {os.path.getsize(os.path.join(HERE, name)) / 1024:.0f} KiB")


if __name__ == "__main__":
    main()
