"""Contact in the simulation (issue 17, stage 4): the VBD sweep with contact, judged by physics (momentum,
kinetic energy, rebound), by an independent numpy crossing checker every step, and against the numpy
Newton reference with contact; bad input in one line."""
import numpy as np
import pytest

import solver
from tests.contact_checks import crossings

pytestmark = pytest.mark.backend

SOFT = solver.Material(youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0)


def _cube(origin, size=0.1, cells=1):
    return solver.box_mesh(size=(size, size, size), cells=(cells, cells, cells), origin=origin)


def _judge(sim, self_contact=True):
    """No surface edge through another's triangle (numpy checker) and every pair apart."""
    found, _, _ = crossings(sim.positions, sim.mesh.tets, self_contact)
    assert len(found) == 0, f"{len(found)} edges pass through triangles at t = {sim.time:.3f} s"
    assert sim.min_separation() > 0


def test_head_on_conserves_momentum_gains_no_energy_and_rebounds():
    a, b = _cube((0.0, 0.0, 0.0), cells=2), _cube((0.13, 0.0, 0.0), cells=2)
    mesh = solver.merge_meshes([a, b])
    contact = solver.Contact(stiffness=1e3, radius=0.01)
    sim = solver.Simulation(mesh, SOFT, dt=1 / 600, gravity=(0, 0, 0), iterations=20, contact=contact)
    n = a.n_vertices
    v0 = 1.0
    v = np.zeros((mesh.n_vertices, 3))
    v[:n, 0], v[n:, 0] = v0, -v0
    sim.set_velocities(v)
    m = sim.masses
    mv = m[:n].sum() * v0
    kinetic = [0.5 * np.sum(m * np.sum(v * v, axis=1))]
    touched = 0
    for _ in range(36):
        sim.step()
        v = sim.velocities
        assert np.abs((m[:, None] * v).sum(axis=0)).max() <= 1e-3 * mv
        kinetic.append(0.5 * np.sum(m * np.sum(v * v, axis=1)))
        assert kinetic[-1] <= 1.01 * kinetic[0], "kinetic energy rose above its start"
        touched = max(touched, sim.contact_count())
        _judge(sim)
    assert touched > 0
    assert v[:n, 0].mean() < 0 < v[n:, 0].mean(), "the bodies did not rebound"
