"""The shipped real-shape assets: they load cleanly, match their surfaces, hang and drop sensibly."""
import os
import warnings

import numpy as np
import pytest
import trimesh

import solver

ASSETS = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "assets")
MATERIAL = solver.Material(youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0)


def _load(name):
    return solver.load_mesh(os.path.join(ASSETS, name))


@pytest.mark.parametrize("tets,surface", [("bunny.vtu", "bunny.off"), ("spot.vtu", "spot.off")])
def test_real_shapes_load_without_warnings_and_fill_their_surface(tets, surface):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        mesh = _load(tets)
    quality = mesh.quality()
    assert quality.n_slivers == 0 and quality.min_dihedral_degrees > 5
    assert np.ptp(mesh.vertices, axis=0).max() == pytest.approx(0.2, rel=0.01)     # within the envelope
    assert mesh.vertices[:, 2].min() == pytest.approx(0.0, abs=2e-3)
    # the tets fill the surface they were made from (same y-up -> z-up turn and scale as make_assets)
    closed = trimesh.load(os.path.join(ASSETS, surface), force="mesh")
    scale = 0.2 / np.ptp(closed.vertices, axis=0).max()
    assert mesh.rest_volumes().sum() == pytest.approx(closed.volume * scale ** 3, rel=0.03)
    # one face-connected body, boundary closed
    assert (solver.mesh.tetmesh.face_components(mesh.tets) == 0).all()
    assert trimesh.Trimesh(mesh.vertices, mesh.boundary_faces(), process=False).is_watertight


def test_the_sliver_bunny_warns_and_names_the_fix():
    with pytest.warns(solver.MeshQualityWarning, match=r"4166 of 10484 tets are slivers.*repair=True"):
        mesh = _load("bunny_slivers.vtu")
    assert mesh.quality().min_dihedral_degrees < 0.1


@pytest.mark.backend
def test_a_hung_bunny_stays_finite_and_uninverted():
    mesh = _load("bunny.vtu")
    top = mesh.vertices[:, 2] >= np.quantile(mesh.vertices[:, 2], 0.95)
    sim = solver.Simulation(mesh, MATERIAL, dt=1 / 60, fixed=top, iterations=50)
    for _ in range(4):
        sim.step()
    x = sim.positions
    assert np.isfinite(x).all()
    np.testing.assert_array_equal(x[top], mesh.vertices[top])
    assert x[~top, 2].mean() < mesh.vertices[~top, 2].mean()          # it sags under gravity
    assert solver.inverted_count(mesh.vertices, mesh.tets, x) == 0


@pytest.mark.backend
def test_a_dropped_cow_lands_on_the_ground():
    mesh = _load("spot.vtu")
    lifted = solver.TetMesh(mesh.vertices + [0.0, 0.0, 0.03], mesh.tets)
    sim = solver.Simulation(lifted, MATERIAL, dt=1 / 60, iterations=30,
                            ground=solver.Ground(height=0.0, stiffness=1e5, friction=0.5))
    lowest = []
    for _ in range(10):                      # free fall of 3 cm takes about 5 steps
        sim.step()
        lowest.append(sim.positions[:, 2].min())
    assert np.isfinite(sim.positions).all()
    assert min(lowest) < 0.005                 # it reached the ground ...
    assert min(lowest) > -0.01                 # ... and did not sink through it (penalty contact)
    assert sim.positions[:, 2].max() > 0.1     # a soft cow slumps on its legs but is not flattened


@pytest.mark.backend
def test_newton_converges_on_a_real_mesh_and_vbd_approaches_it():
    mesh = _load("bunny.vtu")
    top = mesh.vertices[:, 2] >= np.quantile(mesh.vertices[:, 2], 0.95)
    sim = solver.Simulation(mesh, MATERIAL, dt=1 / 60, fixed=top, iterations=50)
    problem, x_n = sim.step_problem(), sim.positions
    newton = solver.newton_solve(problem, problem.y_with_constraints(), tolerance=1e-8)
    assert newton.converged and newton.iterations <= 15
    errors = []
    for iterations in (50, 200):
        sim.reset()
        sim.iterations = iterations
        sim.step()
        errors.append(solver.relative_error(sim.positions, newton.x, x_n))
    assert errors[1] < errors[0] < 0.5          # VBD heads for the converged step, slowly
