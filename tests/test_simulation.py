"""The VBD time step: per-vertex derivatives, monotone sweeps, agreement with Newton, the stiffness
failure the lecture shows, and every optional feature (guesses, Chebyshev, damping, ground,
kinematic vertices, stopping tolerance, float32)."""
import subprocess
import sys

import numpy as np
import pytest

import solver

pytestmark = pytest.mark.backend  # launches Taichi kernels: re-run on CUDA

H = 1 / 60


def bar(cells=(10, 2, 2)):
    return solver.box_mesh(size=(1.0, 0.1, 0.1), cells=cells)


def cantilever(E, cells=(10, 2, 2), **kwargs):
    mesh = bar(cells)
    kwargs.setdefault("iterations", 20)
    return solver.Simulation(mesh, solver.Material(E, 0.3, 1000.0), dt=H, fixed=mesh.vertices[:, 0] < 1e-9, **kwargs)


def deformed(sim, seed=0, scale=0.02):
    rng = np.random.default_rng(seed)
    x = sim.mesh.vertices + scale * rng.standard_normal(sim.mesh.vertices.shape)
    x[sim.fixed_mask] = sim.mesh.vertices[sim.fixed_mask]
    return x


def test_residual_is_minus_the_gradient_of_G_and_H_its_derivative():
    sim = cantilever(1e5, initial_guess=solver.InitialGuess.PREVIOUS)
    sim.set_velocities(0.1 * np.ones((sim.mesh.n_vertices, 3)))
    sim.begin_step()
    sim.set_positions(deformed(sim))
    f, Hs = sim.local_systems()
    x0 = sim.positions
    eps = 1e-6
    for i in np.flatnonzero(~sim.fixed_mask)[::7]:
        for a in range(3):
            xp, xm = x0.copy(), x0.copy()
            xp[i, a] += eps
            xm[i, a] -= eps
            sim.set_positions(xp)
            Gp, fp = sim.energy(), sim.residual()[i]
            sim.set_positions(xm)
            Gm, fm = sim.energy(), sim.residual()[i]
            assert -(Gp - Gm) / (2 * eps) == pytest.approx(f[i, a], rel=1e-6, abs=1e-6)
            np.testing.assert_allclose(-(fp - fm) / (2 * eps), Hs[i][:, a], rtol=1e-5, atol=1e-5)
        assert np.linalg.eigvalsh(Hs[i]).min() > 0, "H_i is SPD"
    assert (f[sim.fixed_mask] == 0).all()


def test_local_energy_is_exactly_quadratic_so_one_solve_minimises_it():
    sim = cantilever(1e5, initial_guess=solver.InitialGuess.PREVIOUS)
    sim.begin_step()
    x = deformed(sim, seed=1, scale=0.01)
    sim.set_positions(x)
    f, Hs = sim.local_systems()
    i = int(np.flatnonzero(~sim.fixed_mask)[5])
    G0 = sim.energy()
    for dx in (np.array([0.05, -0.02, 0.03]), np.array([-0.2, 0.1, 0.0])):
        xd = x.copy()
        xd[i] += dx
        sim.set_positions(xd)
        assert sim.energy() - G0 == pytest.approx(-f[i] @ dx + 0.5 * dx @ Hs[i] @ dx, rel=1e-9)
    xd = x.copy()
    xd[i] += np.linalg.solve(Hs[i], f[i])
    sim.set_positions(xd)
    assert np.linalg.norm(sim.residual()[i]) < 1e-9 * np.linalg.norm(f[i])


def test_zero_force_at_rest_and_under_rigid_motion():
    sim = cantilever(1e6, gravity=(0, 0, 0), initial_guess=solver.InitialGuess.PREVIOUS)
    c, s = np.cos(0.7), np.sin(0.7)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]) @ np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    for x in (sim.mesh.vertices, sim.mesh.vertices @ R.T + [0.3, -1.0, 2.0]):
        sim.reset()
        sim.set_positions(x)
        sim.begin_step()
        scale = sim.material.youngs_modulus * 0.1 ** 2
        assert sim.max_residual() < 1e-9 * scale
        sim.end_step()


def test_G_never_increases_after_a_color_sweep():
    sim = cantilever(1e5, cells=(12, 3, 3), initial_guess=solver.InitialGuess.PREVIOUS)
    sim.set_velocities(np.random.default_rng(2).standard_normal((sim.mesh.n_vertices, 3)))
    sim.begin_step()
    G = sim.energy()
    for _ in range(15):
        for c in range(sim.n_colors):
            sim.solve_color(c)
            G_new = sim.energy()
            assert G_new <= G + 1e-12 * abs(G)
            G = G_new
    sim.end_step()


def test_vbd_converges_to_the_newton_solution_at_1e4_pa():
    sim = cantilever(1e4, cells=(40, 4, 4), iterations=300, initial_guess=solver.InitialGuess.INERTIAL)
    x_star = sim.newton_reference()
    x_n = sim.positions
    sim.step()
    err = solver.relative_error(sim.positions, x_star, x_n)
    print(f"E = 1e4 Pa, 3840 tets, 300 iterations: relative error {err:.2e}")
    assert err < 1e-6


def test_stiff_bar_is_far_from_newton_where_the_soft_bar_is_close():
    """The lecture's point: the same settings that work at 1e4 Pa fail at 1e6 Pa."""
    errors = {}
    for E in (1e4, 1e6):
        sim = cantilever(E, cells=(40, 4, 4), iterations=20, initial_guess=solver.InitialGuess.INERTIAL)
        x_star = sim.newton_reference()
        x_n = sim.positions
        sim.step()
        errors[E] = solver.relative_error(sim.positions, x_star, x_n)
    print(f"20 iterations, 3840 tets: relative error {errors[1e4]:.2e} at 1e4 Pa, {errors[1e6]:.2e} at 1e6 Pa")
    assert errors[1e4] < 1e-2
    assert errors[1e6] > 0.2
    assert errors[1e6] > 30 * errors[1e4]


def test_more_iterations_reduce_the_error_monotonically():
    sim = cantilever(1e6, iterations=1, initial_guess=solver.InitialGuess.INERTIAL)
    x_star = sim.newton_reference()
    x_n = sim.positions
    sim.begin_step()
    errors = []
    for _ in range(6):
        sim.run_iterations(10)
        errors.append(solver.relative_error(sim.positions, x_star, x_n))
    assert all(b < a for a, b in zip(errors, errors[1:]))


def test_fixed_vertices_are_held_and_velocity_is_the_position_change():
    sim = cantilever(1e4, iterations=5)
    x0 = sim.positions
    sim.step(3)
    x3 = sim.positions
    np.testing.assert_array_equal(x3[sim.fixed_mask], x0[sim.fixed_mask])
    sim.begin_step()
    sim.run_iterations(5)
    sim.end_step()
    np.testing.assert_allclose(sim.velocities, (sim.positions - x3) / H, rtol=1e-12, atol=1e-14)
    assert sim.frame == 4 and sim.time == pytest.approx(4 * H)
    assert sim.positions[~sim.fixed_mask, 2].mean() < x0[~sim.fixed_mask, 2].mean(), "the bar sags"


def test_initial_guesses():
    results = {}
    for guess in solver.InitialGuess:
        sim = cantilever(1e4, iterations=1, initial_guess=guess, gravity=(0, 0, -9.81))
        sim.set_velocities(np.tile([0.0, 0.0, 0.5], (sim.mesh.n_vertices, 1)))
        sim.begin_step()
        results[guess] = sim.positions - sim.x_n
    free = ~sim.fixed_mask
    np.testing.assert_allclose(results[solver.InitialGuess.PREVIOUS][free], 0.0)
    expected = np.zeros((free.sum(), 3))
    expected[:, 2] = 0.5 * H
    np.testing.assert_allclose(results[solver.InitialGuess.INERTIA][free], expected)
    expected[:, 2] -= 9.81 * H * H
    np.testing.assert_allclose(results[solver.InitialGuess.INERTIAL][free], expected)
    # Without history the adaptive guess assumes free fall, i.e. it equals y.
    np.testing.assert_allclose(results[solver.InitialGuess.ADAPTIVE], results[solver.InitialGuess.INERTIAL])


def test_adaptive_guess_scales_gravity_by_the_measured_acceleration():
    """a~ = clamp(a_n . g / |g|^2, 0, 1) with a_n = (v_n - v_{n-1}) / h (VBD Sec. 3.7)."""
    g = np.array([0.0, 0.0, -9.81])
    sim = cantilever(1e4, iterations=1, initial_guess=solver.InitialGuess.ADAPTIVE, gravity=g)
    n = sim.mesh.n_vertices
    free = ~sim.fixed_mask
    v = np.tile([0.2, 0.0, -0.1], (n, 1))
    for a_n, a_tilde in ((g, 1.0), (0.5 * g, 0.5), (-g, 0.0), (np.zeros(3), 0.0), (3 * g, 1.0)):
        sim.reset()
        sim.set_velocities(v, previous=v - H * a_n)
        sim.begin_step()
        expected = sim.mesh.vertices + H * v + H * H * a_tilde * g
        np.testing.assert_allclose(sim.positions[free], expected[free], rtol=1e-12, atol=1e-15)
        sim.end_step()


def test_chebyshev_acceleration_lowers_the_error_for_the_same_iterations():
    errors = {}
    for rho in (None, 0.9):
        sim = cantilever(1e5, cells=(20, 2, 2), iterations=60, chebyshev_rho=rho,
                         initial_guess=solver.InitialGuess.INERTIAL)
        x_star = sim.newton_reference()
        x_n = sim.positions
        sim.step()
        errors[rho] = solver.relative_error(sim.positions, x_star, x_n)
    print(f"60 iterations, 1e5 Pa: plain {errors[None]:.2e}, Chebyshev rho=0.9 {errors[0.9]:.2e}")
    assert errors[0.9] < 0.5 * errors[None]


def test_tolerance_stops_early_and_history_records_each_iteration():
    sim = cantilever(1e4, iterations=500, tolerance=1e-6, check_every=3, record_history=True,
                     initial_guess=solver.InitialGuess.INERTIAL)
    sim.begin_step()
    sim.run_iterations(sim.iterations)
    assert 1 < sim.last_iterations < 500 and sim.last_iterations % 3 == 0
    history = sim.history
    assert len(history) == sim.last_iterations + 1
    scale = max(history[0].max_residual, sim.masses.max() * 9.81)
    assert history[-1].max_residual <= 1e-6 * scale < history[-4].max_residual
    assert history[-1].energy < history[0].energy
    sim.end_step()


def test_a_step_that_starts_converged_stops_at_the_first_check():
    sim = cantilever(1e4, iterations=100, tolerance=1e-3, check_every=1, gravity=(0, 0, 0))
    sim.step()
    assert sim.last_iterations == 1


def test_damping_removes_energy_from_a_vibrating_bar():
    amplitude = {}
    for k_d in (0.0, 0.01):
        sim = cantilever(1e5, iterations=30, damping=k_d, gravity=(0, 0, 0))
        sim.set_velocities(np.tile([0.0, 0.0, 1.0], (sim.mesh.n_vertices, 1)) * (sim.mesh.vertices[:, :1] > 0))
        sim.step(30)
        amplitude[k_d] = np.abs(sim.velocities).max() + np.abs(sim.positions - sim.mesh.vertices).max() / H
    assert amplitude[0.01] < 0.7 * amplitude[0.0]


def test_a_dropped_box_rests_on_the_ground():
    mesh = solver.box_mesh(size=(0.2, 0.2, 0.2), cells=(3, 3, 3), origin=(0, 0, 0.05))
    ground = solver.Ground(height=0.0, stiffness=1e5, friction=0.5)
    sim = solver.Simulation(mesh, solver.Material(1e5, 0.3, 1000.0), dt=H, iterations=20, ground=ground)
    sim.step(60)
    z = sim.positions[:, 2]
    assert -0.01 < z.min() < 0.005, "resting on the plane, penetrating by less than 1 cm"
    assert np.abs(sim.velocities).max() < 0.1
    assert np.isfinite(sim.positions).all()


def test_kinematic_vertices_follow_their_script():
    mesh = bar()
    left = mesh.vertices[:, 0] < 1e-9
    right = mesh.vertices[:, 0] > 1.0 - 1e-9

    def pull(t, rest):
        return rest + [0.1 * t, 0.0, 0.0]

    sim = solver.Simulation(mesh, solver.Material(1e4, 0.3, 1000.0), dt=H, fixed=left, kinematic=right,
                            kinematic_motion=pull, iterations=30, gravity=(0, 0, 0))
    sim.step(6)
    np.testing.assert_allclose(sim.positions[right], mesh.vertices[right] + [0.1 * 6 * H, 0, 0], atol=1e-12)
    np.testing.assert_allclose(sim.velocities[right][:, 0], 0.1, rtol=1e-9)
    middle = np.abs(mesh.vertices[:, 0] - 0.5) < 1e-9
    assert 0 < (sim.positions[middle, 0] - 0.5).mean() < 0.1 * 6 * H, "the bar stretches in between"


def test_newton_reference_is_unchanged_by_kinematic_scripts_and_matches_vbd():
    mesh = bar((6, 2, 2))
    right = mesh.vertices[:, 0] > 1.0 - 1e-9
    sim = solver.Simulation(mesh, solver.Material(1e4, 0.3, 1000.0), dt=H, fixed=mesh.vertices[:, 0] < 1e-9,
                            kinematic=right, kinematic_motion=lambda t, rest: rest + [0, 0, t], iterations=400)
    x_star = sim.newton_reference()
    x_n = sim.positions
    sim.step()
    assert solver.relative_error(sim.positions, x_star, x_n) < 1e-6


def test_float32_agrees_with_float64():
    x = {}
    for precision in ("float64", "float32"):
        sim = cantilever(1e4, iterations=50, precision=precision, damping=0.01,
                         ground=solver.Ground(-0.003, friction=0.3))          # the tip rests on it
        sim.step(5)
        x[precision] = sim.positions
    assert x["float64"][:, 2].min() < -0.003 + 1e-4
    disp = np.abs(x["float64"] - bar().vertices).max()
    error = np.abs(x["float32"] - x["float64"]).max()
    assert 0 < error < 1e-3 * disp                                            # float32 really ran


def test_set_material_and_dt_take_effect_without_rebuilding():
    sim = cantilever(1e4, iterations=100, initial_guess=solver.InitialGuess.INERTIAL)
    sim.set_material(solver.Material(1e5, 0.3, 500.0))
    sim.dt = 1 / 120
    assert sim.masses.sum() == pytest.approx(500.0 * 0.1 * 0.1 * 1.0)
    x_star = sim.newton_reference()
    x_n = sim.positions
    sim.step()
    assert solver.relative_error(sim.positions, x_star, x_n) < 1e-3


@pytest.mark.parametrize("kwargs, match", [
    (dict(dt=0.0), "dt"), (dict(dt=float("nan")), "dt"), (dict(iterations=0), "iterations"),
    (dict(iterations=2.5), "iterations"), (dict(gravity=(0, 0)), "gravity"),
    (dict(chebyshev_rho=1.5), "chebyshev_rho"), (dict(damping=-1.0), "damping"),
    (dict(fixed=np.ones(3, dtype=bool)), "mask"), (dict(fixed=[0, 10**6]), "outside"),
    (dict(fixed=np.ones(99, dtype=bool)), "nothing is left"), (dict(kinematic=[5]), "kinematic_motion"),
    (dict(initial_guess="y"), "InitialGuess"), (dict(precision="float16"), "precision"),
    (dict(tolerance=-1.0), "tolerance"), (dict(arch="tpu"), "arch"), (dict(ground="floor"), "Ground"),
])
def test_nonsense_parameters_raise_config_error(kwargs, match):
    mesh = bar((10, 2, 2))
    with pytest.raises(solver.ConfigError, match=match):
        solver.Simulation(mesh, solver.Material(1e4, 0.3, 1000.0), **kwargs)


def test_bad_states_and_call_order_raise_config_error():
    sim = cantilever(1e4)
    with pytest.raises(solver.ConfigError, match="shape"):
        sim.set_positions(np.zeros((3, 3)))
    with pytest.raises(solver.ConfigError, match="NaN"):
        sim.set_velocities(np.full((sim.mesh.n_vertices, 3), np.nan))
    with pytest.raises(solver.ConfigError, match="begin_step"):
        sim.run_iterations(1)
    with pytest.raises(solver.ConfigError):
        solver.Ground(stiffness=-1.0)
    saved = sim.save_state()
    wrong_shape = dict(saved, state=saved["state"][:, :3])
    for bad in (None, {}, {"state": saved["state"]}, wrong_shape, dict(saved, time="noon"), [saved]):
        with pytest.raises(solver.ConfigError, match="takes what save_state") as err:
            sim.restore_state(bad)
        assert "\n" not in str(err.value)
    sim.step()
    sim.restore_state(saved)
    assert np.array_equal(sim.positions, sim.mesh.vertices) and sim.time == 0.0


def test_importing_does_not_initialise_taichi_and_gpu_falls_back_with_one_warning():
    code = (
        "import warnings, solver\n"
        "from taichi.lang.impl import get_runtime\n"
        "assert get_runtime().prog is None, 'import initialised taichi'\n"
        "mesh = solver.box_mesh(cells=(2, 1, 1))\n"
        "with warnings.catch_warnings(record=True) as w:\n"
        "    warnings.simplefilter('always')\n"
        "    sim = solver.Simulation(mesh, solver.Material(1e4, 0.3, 1000.0), arch='gpu', iterations=2)\n"
        "sim.step()\n"
        "import taichi as ti\n"
        "assert sim.arch == ('gpu' if get_runtime().prog.config().arch == ti.cuda else 'cpu'), sim.arch\n"
        "print(len(w), get_runtime().prog.config().arch, w[0].message if w else '')\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    last = out.stdout.strip().splitlines()[-1]
    if "cuda" not in last:
        assert last.startswith("1 ") and "running on the CPU" in last
