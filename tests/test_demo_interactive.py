"""The GGUI window, driven off screen (show_window=False) where Vulkan exists; the panel logic it
drives (per-panel settings, divergence) runs without Vulkan."""
import dataclasses
import os
import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pytest

import solver
from demo import scenes
from demo.errors import DemoError
from demo.runner import PanelSettings, PanelSim

pytestmark = pytest.mark.backend  # launches Taichi kernels: re-run on CUDA

REPO = Path(__file__).resolve().parent.parent


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
    # same picture again and again instead of accumulating copies (mouse dragging needs a real window:
    # untested). The read-back of a new window's first two frames is not yet the whole picture (Mesa's
    # software Vulkan), so the frames compared start at the third, whichever test drew before.
    app.playing = False
    app.run(max_frames=app.frames_drawn + 3)
    first = app.image().copy()
    for _ in range(2):
        app.run(max_frames=app.frames_drawn + 1)
        np.testing.assert_allclose(app.image(), first, atol=1e-6)


def test_controls(app):
    app.playing = False
    app.reset()
    assert all(p.sim.frame == 0 for p in app.panels)
    app.single_iteration()
    assert all(p.iteration == 1 for p in app.panels)
    app.select_panel(None)
    app.set_youngs_modulus(5.0)
    assert all(p.sim.material.youngs_modulus == pytest.approx(1e5) for p in app.panels)
    app.set_iterations(7)
    app.set_dt(1 / 120)
    app.single_step()
    assert all(p.sim.iterations == 7 and p.sim.dt == pytest.approx(1 / 120) for p in app.panels)
    app.set_chebyshev_rho(0.9)
    assert all(p.sim.chebyshev_rho == 0.9 for p in app.panels)
    app.set_color_by(scenes.ColorBy.RESIDUAL)
    app.set_ghost(True)
    app.single_step()
    assert all(p.ghost is not None and np.isfinite(p.error) for p in app.panels)
    app.run(max_frames=app.frames_drawn + 1)
    app.load("twist")
    app.run(max_frames=app.frames_drawn + 1)
    assert app.scene.name == "twist"


def test_every_panel_keeps_its_own_settings_and_label(app):
    """Switching Chebyshev on used to rebuild every panel with the first panel's E and iterations."""
    app.load("iteration_sweep")
    scene_labels = [p.label for p in scenes.get("iteration_sweep").panels]
    assert [p.label for p in app.panels] == scene_labels
    app.select_panel(None)
    app.set_chebyshev_rho(0.5)
    assert [p.sim.iterations for p in app.panels] == [5, 20, 100]
    assert all(p.sim.material.youngs_modulus == 1e6 and p.sim.chebyshev_rho == 0.5 for p in app.panels)
    assert [p.label for p in app.panels] == [f"changed: E = 1e6 Pa, {n} it., dt = 1/60 s, Chebyshev rho 0.5"
                                              for n in (5, 20, 100)]
    app.select_panel(1)
    app.set_iterations(40)
    app.set_youngs_modulus(5.0)
    assert [p.sim.iterations for p in app.panels] == [5, 40, 100]
    assert [p.sim.material.youngs_modulus for p in app.panels] == pytest.approx([1e6, 1e5, 1e6])
    assert "E = 1e5 Pa, 40 it." in app.panel_lines(1)[0]
    app.select_panel(None)
    app.set_chebyshev_rho(0.0)
    assert all(p.sim.chebyshev_rho is None for p in app.panels)
    assert app.panels[0].label == scene_labels[0] and app.panels[2].label == scene_labels[2]
    with pytest.raises(DemoError, match="panel 3 does not exist"):
        app.select_panel(3)


def test_status_lines_fit_the_controls(app):
    app.load("stiffness_sweep")
    app.panels[1].apply(dataclasses.replace(app.panels[1].settings, chebyshev_rho=0.75, dt=1 / 120))
    lines = app.panel_lines(1, width=30)
    assert all(len(line) <= 30 for line in lines)
    assert "dt = 1/120 s" in lines[1]           # broken after a comma, not inside "dt = 1/120 s"
    assert " ".join(lines).split() == f"panel 2: {app.panels[1].label}, t = 0.00 s".split()


def test_a_diverging_panel_stops_with_a_message_in_the_window(app):
    app.load("stiffness_sweep")
    app.select_panel(0)
    app.set_chebyshev_rho(0.999)            # above the slider's cap: the iteration grows without bound
    app.playing = True
    for _ in range(60):
        app.run(max_frames=app.frames_drawn + 1)
        if app.panels[0].failure:
            break
    assert "diverged" in app.panels[0].failure and "lower chebyshev_rho" in app.panels[0].failure
    assert app.panels[0].failure in " ".join(" ".join(app.panel_lines(0, 200)).split())
    stopped_at, other = app.panels[0].sim.frame, app.panels[1].sim.frame
    app.run(max_frames=app.frames_drawn + 1)
    assert app.panels[0].sim.frame == stopped_at and app.panels[1].sim.frame == other + 1
    assert app.panels[1].failure is None
    app.set_chebyshev_rho(0.0)
    app.reset()
    assert app.panels[0].failure is None


def test_vertex_normals_point_out_of_a_box():
    from demo.interactive import vertex_normals

    mesh = solver.box_mesh(size=(1.0, 0.2, 0.1), cells=(5, 2, 1))
    faces = mesh.boundary_faces()
    n = vertex_normals(mesh.vertices, faces)
    used = np.unique(faces)
    np.testing.assert_allclose(np.linalg.norm(n[used], axis=1), 1.0)
    assert np.all(np.einsum("ij,ij->i", n[used], mesh.vertices[used] - mesh.vertices.mean(axis=0)) > 0)
    corner = np.argmin(mesh.vertices.sum(axis=1))           # (0, 0, 0): the normal points along -(1, 1, 1)
    np.testing.assert_allclose(n[corner], -np.ones(3) / np.sqrt(3), atol=0.2)


def test_a_window_too_small_for_the_labels_is_refused(capsys):
    """The window's --size took any image size from 16x16, and a window under 26 pixels wide ended in
    textwrap's 'ValueError: invalid width 0': the status band wrapped the panel lines to 0 characters or
    fewer. Now a window under MIN_SIZE is a one-line error naming it (from --size, before any window opens,
    and from InteractiveApp), and at MIN_SIZE the panel lines wrap to MIN_STATUS_CHARS characters."""
    from demo.__main__ import main
    from demo.interactive import MIN_SIZE, MIN_STATUS_CHARS, InteractiveApp, _wrap, status_width, window_size

    width, height = MIN_SIZE
    for size in ("20x20", "25x720", f"{width - 1}x{height}", f"{width}x{height - 1}"):
        assert main(["interactive", "twist", "--size", size]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and f"needs at least {width}x{height} pixels" in err, err
    with pytest.raises(DemoError, match=f"needs at least {width}x{height} pixels"):
        InteractiveApp("twist", size=(20, 20), show_window=False)
    assert window_size(f"{width}x{height}") == (width, height)
    assert status_width(width) == MIN_STATUS_CHARS
    line = "panel 2: changed: E = 2.5e5 Pa, 200 it., dt = 1/120 s, Chebyshev rho 0.975, t = 12.34 s"
    pieces = _wrap(line, status_width(width), first_indent=False)
    assert all(0 < len(piece) <= MIN_STATUS_CHARS for piece in pieces), pieces
    assert any("dt = 1/120 s" in piece for piece in pieces), pieces


@pytest.mark.parametrize("display, match", [(None, "DISPLAY is not set"), (":987", "DISPLAY=:987 has no X server")])
def test_no_display_gives_a_hint_instead_of_ending_the_process(monkeypatch, display, match):
    from demo.interactive import check_display

    monkeypatch.setattr(sys, "platform", "linux")
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    if display is None:
        monkeypatch.delenv("DISPLAY", raising=False)
    else:
        monkeypatch.setenv("DISPLAY", display)
    with pytest.raises(DemoError, match=match) as e:
        check_display()
    assert "xvfb-run" in str(e.value) and "\n" not in str(e.value)


@pytest.mark.slow
def test_window_start_compiles_without_precision_warnings(app):
    """GGUI's default normals and RGB colours compile float64 literals into float32 fields."""
    code = ("from demo.interactive import InteractiveApp\n"
            "app = InteractiveApp('stiffness_sweep', size=(320, 180), show_window=False)\n"
            "app.set_ghost(True); app.toggle_play(); app.run(max_frames=2)\n"
            "app.set_color_by(app.color_by.__class__.RESIDUAL); app.run(max_frames=3)\n")
    run = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=300,
                         env={**os.environ, "TI_OFFLINE_CACHE": "0"})
    assert run.returncode == 0, run.stderr[-2000:]
    assert "precision" not in run.stdout + run.stderr


def _bar_panel(rho, iterations=20):
    scene = scenes.get("stiffness_sweep")
    return PanelSim(scene, dataclasses.replace(scene.panels[1], chebyshev_rho=rho, iterations=iterations,
                                               newton_ghost=False))


def test_panel_settings_apply_and_describe():
    p = _bar_panel(None)
    assert p.settings == PanelSettings(1e6, 20, 1 / 60, 0.0) and p.label == "E = 1e6 Pa (stiff)"
    p.step()
    p.apply(PanelSettings(2.5e5, 7, 1 / 120, 0.6))        # Chebyshev switched on: the motion carries over
    assert p.sim.frame == 1 and p.sim.chebyshev_rho == 0.6 and p.sim.iterations == 7
    assert p.sim.material.youngs_modulus == 2.5e5 and p.sim.dt == 1 / 120
    assert p.label == "changed: E = 2.5e5 Pa, 7 it., dt = 1/120 s, Chebyshev rho 0.6"
    moved = p.sim.positions
    p.apply(PanelSettings(1e6, 20, 1 / 60, 0.0))
    np.testing.assert_array_equal(p.sim.positions, moved)
    assert p.label == "E = 1e6 Pa (stiff)" and p.sim.chebyshev_rho is None


def test_the_chebyshev_cap_is_stable_where_rho_near_one_diverges():
    """The 0.5 m stiff bar: at the window's cap it sags like the plain solve; at 0.999 it flies off."""
    scene = scenes.get("stiffness_sweep")
    capped, over = _bar_panel(scene.max_chebyshev_rho, iterations=5), _bar_panel(0.999, iterations=5)
    for _ in range(30):
        capped.step()
        over.step()
    assert capped.failure is None and np.abs(capped.sim.positions - capped.rest).max() < 1.5
    assert over.failure is not None and "diverged" in over.failure
    frame = over.sim.frame
    over.step()
    assert over.sim.frame == frame          # a stopped panel stays stopped until reset
    assert over.failure in over.state().lines


def test_drop_scene_labels_its_sideways_drift():
    scene = scenes.get("drop")
    assert any("drift" in note for note in scene.notes)
    p = PanelSim(scene, scene.panels[0])
    assert p.drift() == 0.0 and not any("drifted" in line for line in p.state().lines)
    x = p.sim.positions
    p.sim.set_positions(x + (0.03, 0.04, -0.2))             # 5 cm sideways, 20 cm down
    assert p.drift() == pytest.approx(0.05)
    assert any(line.startswith("drifted 5 cm sideways") for line in p.state().lines)


class _StubCamera:
    """What InteractiveApp asks of a GGUI camera while it aims it."""

    def __getattr__(self, name):
        return lambda *args, **kwargs: None


def test_the_window_views_the_scene_runner_without_vulkan():
    """The window's controls and GPU upload, with a stub in place of the GGUI window (the tests above need
    Vulkan): one SceneRunner advances the panels, and the uploaded colours are the runner's states'."""
    from demo.interactive import InteractiveApp
    from demo.runner import GhostMode, SceneRunner

    app = InteractiveApp.__new__(InteractiveApp)
    app.arch, app.show_window, app.drag, app.playing, app.show_ghost = None, False, None, False, False
    app.color_by = scenes.ColorBy.BODY
    app.window = types.SimpleNamespace(get_window_shape=lambda: (320, 180))
    app.camera = _StubCamera()
    app.load("sweep_by_colour")
    assert isinstance(app.runner, SceneRunner) and app.panels is app.runner.panels
    assert all(p.ghost_mode is GhostMode.STEP for p in app.panels)
    app.set_color_by(scenes.ColorBy.COLOR_SETS)
    app.single_step()                       # this scene's frame: one colour set
    (panel,) = app.panels
    assert panel.colours_done == 1
    app._upload()
    rgba = app.rgba_fields[0].to_numpy()
    (state,) = app.runner.states()
    np.testing.assert_allclose(rgba[:, :3], state.rgb, atol=1e-6)
    app.load("stiffness_sweep")
    app.set_ghost(True)
    app.single_step()
    assert all(p.sim.frame == 1 and p.ghost is not None and np.isfinite(p.error) for p in app.panels)
    app.single_iteration()
    assert all(p.iteration == 1 and p.in_step for p in app.panels)
    app.reset()
    assert all(p.sim.frame == 0 and p.failure is None for p in app.panels) and app.runner.frame == 0
