"""Simulation(method=...): the global solvers and two-level VBD behind the same step(), and AUTO."""
import numpy as np
import pytest

import solver

pytestmark = pytest.mark.backend  # launches Taichi kernels: re-run on CUDA

MESH = solver.box_mesh(size=(0.5, 0.1, 0.1), cells=(10, 2, 2))
FIXED = MESH.vertices[:, 0] < 1e-9


def _error_after_one_step(method, E=1e6, iterations=20):
    sim = solver.Simulation(MESH, solver.Material(E, 0.3, 1000.0), fixed=FIXED, iterations=iterations, method=method)
    x_n = sim.positions
    x_star = solver.newton_solve(sim.step_problem(), sim.step_problem().y_with_constraints()).x
    sim.step()
    return solver.relative_error(sim.positions, x_star, x_n), sim


@pytest.mark.parametrize("method", ["newton", "pcg"])
def test_global_methods_solve_the_step(method):
    error, sim = _error_after_one_step(method)
    assert error < 1e-6
    assert sim.method is solver.Method(method)


def test_two_level_vbd_beats_plain_vbd_on_a_stiff_bar():
    plain, _ = _error_after_one_step("vbd", iterations=40)
    two_level, _ = _error_after_one_step("multilevel", iterations=40)
    assert two_level < 0.2 * plain, (two_level, plain)


def test_auto_keeps_vbd_for_soft_bodies_and_adds_a_coarse_channel_for_stiff_ones():
    soft = solver.Simulation(MESH, solver.Material(1e4, 0.3, 1000.0), fixed=FIXED, method="auto")
    stiff = solver.Simulation(MESH, solver.Material(1e6, 0.3, 1000.0), fixed=FIXED, method="auto")
    assert soft.method is solver.Method.VBD and "N_c" in soft.method_reason
    assert stiff.method is solver.Method.MULTILEVEL and "N_c" in stiff.method_reason
    assert stiff.wave_cells == pytest.approx(10 * soft.wave_cells)


@pytest.mark.parametrize("kwargs", [dict(damping=0.1), dict(ground=solver.Ground(friction=0.5))])
def test_global_methods_refuse_forces_that_are_not_potentials(kwargs):
    with pytest.raises(solver.ConfigError, match="damping"):
        solver.Simulation(MESH, solver.Material(1e6, 0.3), fixed=FIXED, method="newton", **kwargs)


def test_global_methods_refuse_damping_assigned_later():
    sim = solver.Simulation(MESH, solver.Material(1e6, 0.3), fixed=FIXED, method="newton")
    with pytest.raises(solver.ConfigError, match="damping"):
        sim.damping = 0.1
    with pytest.raises(solver.ConfigError, match="friction"):
        sim.ground = solver.Ground(friction=0.5)
    assert sim.damping == 0.0 and sim.ground is None


def test_wave_cells_follow_the_live_material():
    sim = solver.Simulation(MESH, solver.Material(1e4, 0.3, 1000.0), fixed=FIXED)
    soft = sim.wave_cells
    sim.material = solver.Material(1e6, 0.3, 1000.0)
    assert sim.wave_cells == pytest.approx(10 * soft)


def test_unknown_method_is_a_config_error():
    with pytest.raises(solver.ConfigError, match="unknown method"):
        solver.Simulation(MESH, solver.Material(1e6, 0.3), fixed=FIXED, method="jacobi")


def test_method_is_fixed_at_construction():
    sim = solver.Simulation(MESH, solver.Material(1e6, 0.3), fixed=FIXED)
    with pytest.raises(solver.ConfigError, match="fixed at construction"):
        sim.method = solver.Method.NEWTON


def test_newton_reference_agrees_with_the_numpy_oracle():
    sim = solver.Simulation(MESH, solver.Material(1e6, 0.3), fixed=FIXED, ground=solver.Ground(height=0.02))
    sim.step(3)
    problem = sim.step_problem()
    oracle = solver.newton_solve(problem, problem.y_with_constraints()).x
    np.testing.assert_allclose(sim.newton_reference(), oracle, rtol=0, atol=1e-9)
