"""The GGUI window, driven off screen (show_window=False) where Vulkan exists."""
import numpy as np
import pytest

from demo import scenes
from demo.errors import DemoError


@pytest.fixture(scope="module")
def app():
    from demo.interactive import InteractiveApp

    try:
        return InteractiveApp("stiffness_sweep", size=(320, 180), show_window=False)
    except DemoError as e:
        pytest.skip(f"no GGUI window here: {e}")


def test_loop_runs_and_draws(app):
    app.toggle_play()
    app.run(max_frames=3)
    assert app.frames_drawn == 3
    assert all(p.sim.frame == 3 for p in app.panels)
    image = app.image()
    assert image.shape[:2] == (320, 180)
    assert image[..., :3].std() > 0.01            # not a blank canvas


def test_help_line_and_frames_do_not_pile_up(app):
    from demo.interactive import HELP

    for key in ("space", "n step", "i one iteration", "r reset", "left-drag", "Esc"):
        assert key in HELP
    # off screen each frame is read back, which clears GGUI's draw list: a paused scene gives the
    # same picture twice instead of accumulating copies (mouse dragging needs a real window: untested)
    app.playing = False
    app.run(max_frames=app.frames_drawn + 1)
    first = app.image().copy()
    app.run(max_frames=app.frames_drawn + 1)
    np.testing.assert_allclose(app.image(), first, atol=1e-6)


@pytest.mark.slow
def test_controls(app):
    app.playing = False
    app.reset()
    assert all(p.sim.frame == 0 for p in app.panels)
    app.single_iteration()
    assert all(p.iteration == 1 for p in app.panels)
    app.set_youngs_modulus(5.0)
    assert all(p.sim.material.youngs_modulus == pytest.approx(1e5) for p in app.panels)
    app.set_iterations(7)
    app.set_dt(1 / 120)
    app.single_step()
    assert all(p.sim.iterations == 7 and p.sim.dt == pytest.approx(1 / 120) for p in app.panels)
    app.set_chebyshev_rho(0.9)
    assert all(p.sim.chebyshev_rho == 0.9 for p in app.panels)
    app.set_colour_by(scenes.ColourBy.RESIDUAL)
    app.set_ghost(True)
    app.single_step()
    assert all(p.ghost is not None and np.isfinite(p.error) for p in app.panels)
    app.run(max_frames=app.frames_drawn + 1)
    app.load("twist")
    app.run(max_frames=app.frames_drawn + 1)
    assert app.scene.name == "twist"
