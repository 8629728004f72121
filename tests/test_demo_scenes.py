"""Every scene builds and steps; the stiffness sweep measures the propagation failure."""
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from demo import scenes
from demo.errors import DemoError
from demo.runner import SceneRunner

REPO = Path(__file__).resolve().parent.parent


def test_importing_demo_has_no_side_effects():
    code = ("import demo, demo.scenes, demo.render, demo.runner, demo.compose, demo.video, demo.export, "
            "demo.interactive\nimport taichi.lang.impl as impl\nassert impl.get_runtime().prog is None, 'ti.init ran'")
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr


def test_scenes_are_frozen_data():
    scene = scenes.get("stiffness_sweep")
    with pytest.raises(AttributeError):
        scene.dt = 0.1
    assert scenes.DEFAULT_SCENE == "stiffness_sweep"
    assert {"stiffness_sweep", "resolution_sweep", "iteration_sweep", "propagation", "colouring", "drop",
            "twist"} <= set(scenes.SCENES)


def test_unknown_scene_is_a_demo_error():
    with pytest.raises(DemoError, match="unknown scene 'nope'; known scenes: stiffness_sweep"):
        scenes.get("nope")


@pytest.mark.parametrize("name", sorted(scenes.SCENES))
def test_every_scene_builds_and_steps(name):
    runner = SceneRunner(scenes.get(name))
    for p in runner.panels:
        p.ghost_enabled = False     # Newton references are tested once below; they are the slow part
    rest = [p.sim.positions for p in runner.panels]
    for _ in range(2):
        states = runner.advance()
    assert len(states) == len(scenes.get(name).panels)
    for state, x0 in zip(states, rest):
        assert np.isfinite(state.positions).all()
        assert state.colours.shape == state.positions.shape
        assert state.lines and state.lines[0]
    scene = scenes.get(name)
    moves = scene.gravity != (0.0, 0.0, 0.0) or any(p.kinematic for p in scene.panels)
    if moves:
        assert max(np.abs(s.positions - x0).max() for s, x0 in zip(states, rest)) > 1e-6


def test_scene_builds_only_what_it_asks_for():
    sweep = SceneRunner(scenes.get("stiffness_sweep"))
    sim = sweep.panels[0].sim
    assert sim.ground is None and sim.damping == 0.0 and sim.chebyshev_rho is None
    assert SceneRunner(scenes.get("drop")).panels[0].sim.ground is not None


def test_stiffness_sweep_shows_the_stiff_bar_failing():
    """The lecture's point, measured: with the same 20 iterations the stiff bar is far from Newton."""
    runner = SceneRunner(scenes.get("stiffness_sweep"))
    for _ in range(3):
        soft, stiff = runner.advance()
    assert soft.ghost is not None and stiff.ghost is not None
    assert soft.error < 0.05
    assert stiff.error > 0.1
    assert stiff.lines[-1] == f"relative error {stiff.error:.3f}"


def test_propagation_front_moves_with_iterations():
    """The moved region grows by about one ring of elements per iteration (the first Gauss-Seidel sweep
    reaches a few rings, as colours are solved in order), so six iterations leave most of the bar untouched."""
    runner = SceneRunner(scenes.get("propagation"))
    runner.advance()                       # frame 0: the step is open, nothing solved yet
    cell = 1.0 / 40
    reach = []
    for _ in range(6):
        (state,) = runner.advance()
        moved = np.linalg.norm(state.positions - runner.panels[0].start, axis=1) > 1e-9
        reach.append(1.0 - state.positions[moved & (state.positions[:, 0] < 0.999), 0].min())
    assert all(b >= a for a, b in zip(reach, reach[1:]))
    assert reach[0] <= 4.5 * cell
    assert reach[-1] - reach[0] <= 5 * 2 * cell
    assert reach[-1] < 0.5
