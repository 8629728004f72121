"""Settings x methods: every live setting changes the step of every method, or that method refuses it
with a one-line ConfigError saying what to use instead (issue 16, part 3)."""
import dataclasses
import warnings

import numpy as np
import pytest

import solver

pytestmark = pytest.mark.backend   # compiles Taichi kernels: re-run on CUDA

MESH = solver.box_mesh(size=(0.5, 0.1, 0.1), cells=(10, 2, 2))
FIXED = MESH.vertices[:, 0] < 1e-9
TIP = MESH.vertices[:, 0] > 0.5 - 1e-9
MATERIAL = solver.Material(1e6, 0.3, 1000.0)      # N_c >= 6: "auto" chooses two-level VBD
GLOBAL = {solver.Method.NEWTON, solver.Method.PCG, solver.Method.MULTILEVEL}
GROUND = solver.Ground(height=0.05)


def _squash(sim):
    """Throw the tip at the fixed end: an initial guess that inverts tets."""
    v = np.zeros((MESH.n_vertices, 3))
    v[TIP, 0] = -40.0
    sim.set_velocities(v)


def _shear(sim):
    """A free body set spinning and stretching: the rigid-translation correction has work to do."""
    x = MESH.vertices
    sim.set_velocities(np.column_stack([4 * (x[:, 2] - 0.05), 3 * x[:, 0] ** 2, -2 * (x[:, 1] - 0.05)]))


def _shifted(t, rest):
    return rest + np.array([0.0, 0.0, 0.3 * t])


# setting: (constructor arguments of both runs, the live assignment, methods that refuse it, set-up);
# every field of solver.Settings has a row, and the material
CASES = {
    "dt": (dict(iterations=4), dict(dt=1 / 30), set(), None),
    "gravity": (dict(iterations=4), dict(gravity=(0.0, -9.81, 0.0)), set(), None),
    "iterations": (dict(iterations=1), dict(iterations=20), set(), None),
    "iterations below a cycle": (dict(iterations=4), dict(iterations=2), {solver.Method.MULTILEVEL}, None),
    "tolerance": (dict(iterations=40), dict(tolerance=0.3), set(), None),
    "check_every": (dict(iterations=40, tolerance=0.3), dict(check_every=7), GLOBAL, None),
    "initial_guess": (dict(iterations=1, initial_guess="inertial"), dict(initial_guess="previous"), set(), None),
    "chebyshev_rho": (dict(iterations=10), dict(chebyshev_rho=0.5), GLOBAL, None),
    "damping": (dict(iterations=4), dict(damping=0.01), GLOBAL, None),
    "ground": (dict(iterations=4), dict(ground=GROUND), set(), None),
    "ground friction": (dict(iterations=4, ground=GROUND), dict(ground=solver.Ground(height=0.05, friction=0.5)),
                        GLOBAL, None),
    "keep_orientation": (dict(iterations=2, dt=1 / 30), dict(keep_orientation=True), GLOBAL, _squash),
    "translation_correction": (dict(iterations=1, fixed=None), dict(translation_correction=False), set(), _shear),
    "kinematic_motion": (dict(iterations=4, fixed=None, kinematic=FIXED, kinematic_motion=lambda t, rest: rest),
                         dict(kinematic_motion=_shifted), set(), None),
    "record_history": (dict(iterations=4), dict(record_history=True), set(), None),
    "material": (dict(iterations=4), dict(material=solver.Material(3e5, 0.3, 1000.0)), set(), None),
}
METHODS = ["vbd", "newton", "pcg", "multilevel", "auto"]
CYCLE = solver.method.MULTILEVEL_CYCLE_SWEEPS
TWO_LEVEL = {"multilevel", "auto"}    # "auto" chooses two-level VBD for MATERIAL


def test_the_table_covers_every_setting():
    names = {name for change in (case[1] for case in CASES.values()) for name in change}
    assert names == {field.name for field in dataclasses.fields(solver.Settings)} | {"material"}


def _simulation(method, kwargs):
    kwargs = dict(dict(fixed=FIXED), **kwargs)
    return solver.Simulation(MESH, MATERIAL, method=method, **kwargs)


def _step(sim, set_up):
    if set_up is not None:
        set_up(sim)
    sim.step()
    return sim.positions, len(sim.history)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("setting", list(CASES))
def test_every_method_honours_or_refuses_every_setting(setting, method):
    common, change, refused_by, set_up = CASES[setting]
    if method in TWO_LEVEL:         # whole cycles of CYCLE sweeps: a row's smaller budget is one cycle
        common = dict(common, iterations=max(common["iterations"], CYCLE))
    sim = _simulation(method, common)
    if sim.method in refused_by:
        name, value = next(iter(change.items()))
        old = getattr(sim, name)
        with pytest.raises(solver.ConfigError, match="use method='vbd'") as live:
            setattr(sim, name, value)
        assert "\n" not in str(live.value)
        assert getattr(sim, name) == old
        with pytest.raises(solver.ConfigError, match="use method='vbd'"):
            _simulation(method, dict(common, **change))
        return
    before, before_history = _step(sim, set_up)
    changed = _simulation(method, common)
    for name, value in change.items():
        setattr(changed, name, value)
    after, after_history = _step(changed, set_up)
    if setting == "record_history":
        assert before_history == 0 and after_history >= 2
    elif setting == "translation_correction" and sim.method is solver.Method.NEWTON:
        # Applied, and a no-op: an exact Newton step leaves no net force on a free body (the elastic
        # forces sum to zero, inertia is linear), so the best rigid translation is zero.
        assert np.abs(after - before).max() < 1e-12
    else:
        assert np.abs(after - before).max() > 1e-10, f"{setting} did not change a step of method={method}"


@pytest.mark.parametrize("method", ["newton", "pcg"])
def test_newton_iterations_and_tolerance_are_the_cap_and_the_relative_stopping_test(method):
    capped = _simulation(method, dict(iterations=1))
    with warnings.catch_warnings():
        warnings.simplefilter("error")           # the cap is the user's budget: reaching it is no warning
        capped.step()
    assert capped.last_iterations == 1
    problem = capped.step_problem()             # a direct call's cap is a safety limit: still warned about
    with pytest.warns(UserWarning, match="did not converge"):
        if method == "newton":
            solver.fast_newton_solve(problem, problem.y_with_constraints(), max_iterations=1)
        else:
            solver.newton_pcg(problem.tets, problem.free).solve(problem, problem.y_with_constraints(),
                                                                 max_iterations=1)
    loose = _simulation(method, dict(tolerance=0.5, record_history=True))
    loose.step()
    history = loose.history
    assert history[-1].max_residual <= loose.stop_below < history[-2].max_residual
    assert loose.stop_below == pytest.approx(0.5 * max(history[0].max_residual,
                                                        loose.masses.max() * 9.81), rel=1e-9)


def test_multilevel_stops_at_the_first_cycle_below_the_tolerance():
    sim = _simulation("multilevel", dict(iterations=200, tolerance=1e-3))
    sim.step()
    ml = sim._two_level
    residuals = [record.max_residual for record in ml.history]
    assert residuals[-1] <= sim.stop_below < min(residuals[:-1])
    assert len(ml.history) - 1 < solver.method.multilevel_cycles(200)


def test_enum_settings_accept_their_names_and_list_the_choices():
    sim = _simulation("vbd", dict(initial_guess="inertia", coloring_order="natural"))
    assert sim.initial_guess is solver.InitialGuess.INERTIA
    sim.initial_guess = "previous"
    assert sim.initial_guess is solver.InitialGuess.PREVIOUS
    with pytest.raises(solver.ConfigError, match="'previous', 'inertia', 'inertial', 'adaptive'"):
        sim.initial_guess = "y"
    assert sim.initial_guess is solver.InitialGuess.PREVIOUS


@pytest.mark.parametrize("dt, method", [(1e300, "newton"), (1e4, "vbd"), (1e-300, "multilevel"), (1e-10, "vbd")])
def test_a_time_step_outside_the_physical_range_is_refused_in_one_line(dt, method):
    low, high = solver.vbd.settings.DT_RANGE
    with pytest.raises(solver.ConfigError, match=f"dt must be between {low:g} and {high:g} seconds") as err:
        _simulation(method, dict(dt=dt))
    assert "\n" not in str(err.value)
    sim = _simulation(method, dict(dt=high))
    sim.dt = low
    with pytest.raises(solver.ConfigError, match="dt must be between"):
        sim.dt = dt
    assert sim.dt == low


@pytest.mark.parametrize("kwargs, match", [
    (dict(tolerance=-1.0), r"tolerance must be a positive number of the initial residual \(a fraction, e.g. 1e-4\)"),
    (dict(fixed=[[0, 1], [2, 3]]), r"fixed vertex indices must be a flat list, got shape \(2, 2\)"),
])
def test_a_nonsense_setting_is_named_in_one_line(kwargs, match):
    with pytest.raises(solver.ConfigError, match=match):
        solver.Simulation(MESH, MATERIAL, **kwargs)


def test_live_assignment_goes_through_settings():
    sim = _simulation("vbd", dict(iterations=3))
    sim.settings = dataclasses.replace(sim.settings, dt=0.01, iterations=7)
    assert (sim.dt, sim.iterations) == (0.01, 7)
    with pytest.raises(solver.ConfigError, match="dt"):
        sim.dt = -1.0
    with pytest.raises(TypeError):
        solver.Settings(0.01)                    # keyword-only
    with pytest.raises(dataclasses.FrozenInstanceError):
        sim.settings.dt = 0.02
    assert sim.settings == solver.Settings(dt=0.01, iterations=7)


def test_a_misspelt_live_setting_is_refused_with_the_close_name():
    """`sim.itterations = 5` used to make a new attribute and leave the iterations as they were."""
    sim = _simulation("vbd", dict(iterations=3))
    with pytest.raises(solver.ConfigError, match="no setting 'itterations'; did you mean 'iterations'") as err:
        sim.itterations = 5
    assert "\n" not in str(err.value)
    with pytest.raises(solver.ConfigError, match="no setting 'speed'"):
        sim.speed = 2
    assert sim.iterations == 3 and not hasattr(sim, "itterations")
    sim.iterations = 5
    assert sim.iterations == 5
