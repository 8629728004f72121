"""The shape of the solver: shared kernels and cached adjacency, live and read-only settings, the
divergence guard, backend warnings, and the translation correction that stops a dropped body drifting."""
import subprocess
import sys
import textwrap

import numpy as np
import pytest

import solver

pytestmark = pytest.mark.backend  # launches Taichi kernels: re-run on CUDA

H = 1 / 60


def cantilever(E=1e5, cells=(10, 2, 2), **kwargs):
    mesh = solver.box_mesh(size=(1.0, 0.1, 0.1), cells=cells)
    kwargs.setdefault("iterations", 20)
    kwargs.setdefault("dt", H)
    material = kwargs.pop("material", solver.Material(E, 0.3, 1000.0))
    return solver.Simulation(mesh, material, fixed=mesh.vertices[:, 0] < 1e-9, **kwargs)


def _compiled(kernel) -> int:
    """How many specialisations Taichi has compiled for a kernel in this process."""
    return len(kernel._primal.compiled_kernels)


def test_a_second_simulation_of_the_same_mesh_reuses_topology_and_kernels():
    from solver.vbd import implicit_euler, vertex_solve

    first = cantilever(cells=(12, 3, 3))
    first.step()
    kernels = (vertex_solve.vbd_iteration, implicit_euler.begin_step, implicit_euler.end_step)
    before = [_compiled(k) for k in kernels]
    second = cantilever(cells=(12, 3, 3))
    second.step()
    assert [_compiled(k) for k in kernels] == before        # nothing compiled for the second one
    assert second.topology is first.topology
    assert second.arrays.adj_f is first.arrays.adj_f        # device arrays shared too
    np.testing.assert_array_equal(second.positions, first.positions)


def test_simulations_built_after_ti_init_again_do_not_reuse_freed_arrays():
    """ti.init frees every array made before it. The device adjacency and the Newton solvers are cached
    per Taichi runtime, so a simulation built afterwards of the same mesh gets fresh ones and steps as
    before; one built before refuses in one line instead of reading freed memory."""
    code = textwrap.dedent("""
        import numpy as np, solver
        from solver._ti import ti
        mesh = solver.box_mesh(size=(1.0, 0.1, 0.1), cells=(6, 2, 2))
        def build(method):
            return solver.Simulation(mesh, solver.Material(1e5, 0.3, 1000.0), method=method, iterations=10,
                                     fixed=mesh.vertices[:, 0] < 1e-9)
        before = {}
        for method in ("vbd", "newton"):
            sim = build(method)
            sim.step(2)
            before[method] = (sim, sim.positions)
        ti.init(arch=ti.cpu, default_fp=ti.f64, log_level=ti.WARN)
        for method, (old, x) in before.items():
            sim = build(method)
            sim.step(2)
            print(method, np.abs(sim.positions - x).max())
            try:
                old.step()
            except solver.ConfigError as e:
                print(method, "old:", e)
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=180)
    assert out.returncode == 0, out.stderr[-2000:]
    lines = [line for line in out.stdout.splitlines() if line.startswith(("vbd", "newton"))]
    assert [line.split()[0] for line in lines] == ["vbd", "vbd", "newton", "newton"], out.stdout
    for method in ("vbd", "newton"):
        gap, old = [line.split(maxsplit=1)[1] for line in lines if line.startswith(method)]
        assert float(gap) == 0.0
        assert old.startswith("old: Taichi was initialised again (ti.init) after this Simulation was built")


def test_topology_is_read_only_and_consistent():
    sim = cantilever()
    top = sim.topology
    with pytest.raises(ValueError):
        top.q[0, 0] = 1.0
    assert top.n_slots == int(sim.free_mask.sum())
    assert sorted(top.color_order.tolist()) == np.flatnonzero(sim.free_mask).tolist()
    for c, (start, end) in enumerate(top.color_ranges):
        assert (sim.colors[top.color_order[start:end]] == c).all()
    # every (free vertex, tet) pair appears once
    degree = np.bincount(sim.mesh.tets.ravel(), minlength=sim.mesh.n_vertices)
    assert top.n_entries == int(degree[sim.free_mask].sum())


@pytest.mark.parametrize("name,value", [("mesh", None), ("fixed_mask", None), ("precision", "float32"),
                                        ("topology", None), ("kinematic_mask", None)])
def test_settings_fixed_at_construction_refuse_assignment(name, value):
    sim = cantilever()
    with pytest.raises(solver.ConfigError, match="fixed at construction"):
        setattr(sim, name, value)


def test_masks_cannot_be_changed_in_place():
    sim = cantilever()
    with pytest.raises(ValueError):
        sim.fixed_mask[5] = True


def _run(sim, steps=3):
    sim.step(steps)
    return sim.positions


@pytest.mark.parametrize("name,value", [
    ("damping", 0.05), ("chebyshev_rho", 0.8), ("dt", 1 / 120), ("iterations", 7),
    ("ground", solver.Ground(height=0.02, stiffness=2e4, friction=0.3)),
    ("material", solver.Material(3e5, 0.35, 800.0)), ("initial_guess", solver.InitialGuess.INERTIA),
])
def test_live_settings_act_like_constructor_arguments(name, value):
    changed = cantilever()
    _run(changed, 1)
    setattr(changed, name, value)
    after = _run(changed, 3)
    reference = cantilever(**{name: value})
    baseline = cantilever()
    _run(baseline, 1)
    reference.restore_state(baseline.save_state())
    np.testing.assert_allclose(after, _run(reference, 3), rtol=0, atol=1e-12)
    assert np.abs(after - _run(cantilever(), 4)).max() > 1e-6, "the setting had no effect"


@pytest.mark.parametrize("kwargs", [dict(gravity="down"), dict(chebyshev_rho="a"), dict(damping="a"),
                                    dict(dt=float("nan")), dict(chebyshev_rho=1.0), dict(iterations=0),
                                    dict(translation_correction="yes")])
def test_nonsense_parameters_raise_config_error(kwargs):
    with pytest.raises(solver.ConfigError):
        cantilever(**kwargs)


def test_newton_reference_rejects_a_negative_tolerance():
    with pytest.raises(solver.ConfigError):
        cantilever().newton_reference(tolerance=-1)


def test_kinematic_nan_says_what_is_wrong():
    mesh = solver.box_mesh(size=(1.0, 0.1, 0.1), cells=(4, 1, 1))
    end = mesh.vertices[:, 0] > 1 - 1e-9
    sim = solver.Simulation(mesh, solver.Material(1e4, 0.3), kinematic=end,
                            kinematic_motion=lambda t, rest: rest * np.nan)
    with pytest.raises(solver.ConfigError, match="NaN"):
        sim.step()


def test_a_kinematic_motion_of_the_wrong_signature_is_named():
    """A motion taking one argument was reported as returning a bad array."""
    mesh = solver.box_mesh(size=(1.0, 0.1, 0.1), cells=(4, 1, 1))
    end = mesh.vertices[:, 0] > 1 - 1e-9
    sim = solver.Simulation(mesh, solver.Material(1e4, 0.3), kinematic=end, kinematic_motion=lambda t: t)
    with pytest.raises(solver.ConfigError, match=r"kinematic_motion\(t, rest\) raised TypeError .*it must take the "
                                                 r"time t in s and the rest positions \(4, 3\)"):
        sim.step()


def test_a_diverging_step_raises_and_keeps_the_start_of_the_step():
    mesh = solver.box_mesh(size=(1.0, 0.1, 0.1), cells=(40, 4, 4))
    sim = solver.Simulation(mesh, solver.Material(1e6, 0.3, 1000.0), fixed=mesh.vertices[:, 0] < 1e-9,
                            iterations=100, chebyshev_rho=0.99)
    with pytest.raises(solver.VBDError, match="diverged.*chebyshev_rho"):
        for _ in range(10):
            before = sim.positions
            sim.step()
    assert np.isfinite(sim.positions).all()
    np.testing.assert_array_equal(sim.positions, before)
    with pytest.raises(solver.ConfigError, match="needs begin_step"):
        sim.end_step()                                      # the failed step is closed


def test_inverted_count():
    sim = cantilever(cells=(2, 1, 1))
    assert sim.inverted_count() == 0
    x = sim.mesh.vertices.copy()
    x[:, 2] *= -1.0                                # mirror: every tet inverted
    sim.set_positions(x)
    assert sim.inverted_count() == sim.mesh.n_tets


def _drop(friction, correction):
    sphere = solver.load_mesh("assets/sphere.obj", resolution=6)
    mesh = solver.TetMesh(sphere.vertices + [0.0, 0.0, 0.15], sphere.tets)
    sim = solver.Simulation(mesh, solver.Material(1e5, 0.3, 1000.0), iterations=10,
                            ground=solver.Ground(0.0, 1e5, friction), translation_correction=correction)
    sim.step(45)
    c = sim.positions.mean(axis=0) - mesh.vertices.mean(axis=0)
    assert sim.positions[:, 2].min() > -0.02, "the ball went through the ground"
    return float(np.hypot(c[0], c[1]))


@pytest.mark.parametrize("friction", [0.0, 0.5])
def test_a_symmetric_body_dropped_straight_stays_on_its_axis(friction):
    assert _drop(friction, True) < 0.01


def test_without_the_translation_correction_the_dropped_body_drifts():
    assert _drop(0.0, False) > 0.02     # the failure the correction removes (so the test above can fail)


def test_translation_correction_makes_the_residuals_sum_to_zero_for_a_free_body():
    sphere = solver.load_mesh("assets/sphere.obj", resolution=6)
    sim = solver.Simulation(sphere, solver.Material(1e5, 0.3), iterations=3)
    sim.set_velocities(np.random.default_rng(0).normal(size=(sphere.n_vertices, 3)))
    sim.begin_step()
    sim.run_iterations(3)
    assert np.abs(sim.residual().sum(axis=0)).max() > 1e-3
    sim.end_step()
    total = np.abs(sim.residual().sum(axis=0)).max()     # y and x_n are still those of the step
    weight = sim.masses.sum() * 9.81
    assert total < 1e-9 * weight


def test_asking_for_another_backend_warns_once():
    code = textwrap.dedent("""
        import warnings, solver
        solver.ensure_taichi("cpu")
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            solver.ensure_taichi("gpu")
            solver.ensure_taichi("gpu")
        print(len([w for w in caught if "already runs on the CPU" in str(w.message)]))
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.stdout.strip().splitlines()[-1] == "1", out.stderr


def test_the_serial_sweep_of_small_meshes_gives_the_same_iterate():
    """Small meshes on the CPU run each colour on one thread (no barrier per colour); the vertices of a
    colour are independent, so one iteration gives bit for bit what the parallel sweep gives."""
    from solver.vbd import vertex_solve

    sim = cantilever(E=1e6, cells=(8, 2, 2), iterations=1)
    assert sim._serial_sweep == vertex_solve.serial_sweep(sim.mesh.n_tets, solver.backend.running_on_cpu())
    sim.step()
    sim.begin_step()
    saved = sim.state.to_numpy()
    results = []
    for serial in (False, True):
        sim.state.from_numpy(saved)
        a = sim.arrays
        for _ in range(3):
            vertex_solve.vbd_iteration(a.state, a.mass, a.color_order, a.offsets, a.others, a.adj_f,
                                       a.color_starts, a.params, sim.n_colors, sim.dtype, serial)
        results.append(sim.positions)
    assert not np.allclose(results[0], sim.mesh.vertices)          # the iterations moved the bar
    np.testing.assert_array_equal(results[0], results[1])


def test_one_cpu_thread_sweeps_serially_at_any_size_and_more_threads_up_to_a_size_that_shrinks(monkeypatch):
    """`vertex_solve.serial_sweep`: one thread gains nothing from the parallel loops' barriers, whatever the
    mesh; two threads run serially below SERIAL_SWEEP_TETS, T threads below SERIAL_SWEEP_TETS (1/2) / (1 - 1/T)
    (8 threads: 22,857 tets); a GPU never."""
    from types import SimpleNamespace

    from solver.vbd import vertex_solve

    def serial(n_tets, threads, on_cpu=True):
        monkeypatch.setattr(vertex_solve, "running_config", lambda: SimpleNamespace(cpu_max_num_threads=threads))
        return vertex_solve.serial_sweep(n_tets, on_cpu)

    limit = vertex_solve.SERIAL_SWEEP_TETS
    assert serial(10 ** 7, 1)
    assert serial(limit - 1, 2) and not serial(limit, 2)
    assert serial(22_856, 8) and not serial(22_858, 8)
    assert not serial(100, 2, on_cpu=False)


def test_the_steps_of_a_small_mesh_on_one_thread_are_those_of_the_parallel_loops():
    """On the CPU a small mesh runs every loop of its step on one thread (`vertex_solve.serial_sweep`): the
    guess, the Chebyshev steps, the stop test, the velocity update and the reads and writes of positions
    and velocities (a parallel loop costs tens of microseconds to start and end there). Each vertex's
    update is its own, so the steps are those of the parallel loops to round-off (not bit for bit: LLVM
    compiles the two forms of a loop apart, and Taichi's fast math lets it fuse a multiply and an add in one
    and not the other; measured: 2e-16 m)."""
    runs = []
    for serial in (False, True):
        sim = cantilever(E=1e6, cells=(8, 2, 2), iterations=4, chebyshev_rho=0.8)
        assert sim._serial_sweep == solver.backend.running_on_cpu()
        sim._serial_sweep = serial and sim._serial_sweep
        v = np.zeros((sim.mesh.n_vertices, 3))
        v[:, 2] = np.linspace(0.0, -0.5, sim.mesh.n_vertices)
        sim.set_velocities(v)
        sim.step(3)
        runs.append((sim.positions, sim.velocities))
    assert not np.allclose(runs[0][0], sim.mesh.vertices)
    for parallel, one_thread in zip(*runs):
        np.testing.assert_allclose(one_thread, parallel, rtol=0, atol=1e-13)
