"""The interactive classroom window (Taichi GGUI, which needs Vulkan).

Controls are methods of ``InteractiveApp`` so that the window's buttons, the keyboard and the
tests all drive the same code. ``InteractiveApp(..., show_window=False)`` runs off screen.

Every panel keeps its own settings (``runner.PanelSettings``): the sliders change the panel chosen
under "edit" (or every panel, each keeping its other settings), always through ``PanelSim.apply``,
and each panel's line along the bottom names its current settings once they differ from the scene's.
"""
import argparse
import dataclasses
import math
import os
import sys
import textwrap
from pathlib import Path

import numpy as np

from solver._ti import ti

from . import scenes
from .cli import image_size, python_command, start_taichi
from .errors import DemoError
from .render import GHOST_RGB
from .runner import GhostMode, SceneRunner

HELP = ("space play/pause | n step | i one iteration | r reset | left-drag a vertex | "
        "right-drag + WASDQE camera | Esc quit")


COLOUR_OPTIONS = (scenes.ColorBy.BODY, scenes.ColorBy.COLOR_SETS, scenes.ColorBy.RESIDUAL)
CONTROLS_WIDTH = 0.3        # of the window width
CHAR_WIDTH = 8.6            # pixels per character of GGUI's built-in font
LINE_HEIGHT = 18            # pixels per line of text
TITLE_HEIGHT = 50           # pixels of a sub-window's title bar and margins
STATUS_BAND = 0.5           # the most of the window height the status band along the bottom takes
MIN_STATUS_CHARS = 30       # the status band wraps the panel lines to no fewer characters than this
# the smallest window (width, height) whose status band shows its title, the help line and one panel line
# of MIN_STATUS_CHARS characters
MIN_SIZE = (math.ceil((MIN_STATUS_CHARS + 2) * CHAR_WIDTH), math.ceil((TITLE_HEIGHT + 2 * LINE_HEIGHT) / STATUS_BAND))
OPAQUE = 1.0                # alpha of the per-vertex colours (GGUI takes RGBA)


def check_display():
    """A one-line DemoError when no display can show the window (GLFW would end the process instead)."""
    if not sys.platform.startswith("linux") or os.environ.get("WAYLAND_DISPLAY"):
        return
    display = os.environ.get("DISPLAY", "")
    local = display.startswith(":") and display[1:].split(".")[0].isdigit()
    socket = Path("/tmp/.X11-unix") / f"X{display[1:].split('.')[0]}" if local else None
    if not display or (socket is not None and not socket.exists()):
        found = f"DISPLAY={display} has no X server" if display else "DISPLAY is not set"
        demo = f"{python_command()} -m demo"
        raise DemoError(f"the interactive window needs a display ({found}): run it on a desktop or under a "
                        f"virtual one (xvfb-run {demo} interactive); headless rendering works anywhere: {demo} render")


class InteractiveApp:
    """One window showing one scene's panels side by side in 3D, with controls."""

    def __init__(self, scene_name=scenes.DEFAULT_SCENE, arch="cpu", size=(1280, 720), show_window=True):
        if problem := too_small(size):
            raise DemoError(problem)
        if not hasattr(ti, "ui"):
            raise DemoError(f"the interactive window needs Taichi's GGUI, which {ti.__name__} lacks; "
                            "pip install taichi==1.7.4 (CPython 3.10-3.13). Headless rendering still works: "
                            f"{python_command()} -m demo render")
        if show_window:
            check_display()
        start_taichi(arch)
        self.arch = None        # what runs now
        try:
            self.window = ti.ui.Window("VBD classroom", tuple(size), vsync=True, show_window=show_window)
        except Exception as e:  # GGUI reports a missing Vulkan loader or driver in several ways
            first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise DemoError("the interactive window needs Vulkan (apt-get install mesa-vulkan-drivers libvulkan1); "
                            f"Taichi said: {first}. Headless rendering still works: "
                            f"{python_command()} -m demo render") from None
        self.show_window = show_window
        self.canvas = self.window.get_canvas()
        self.scene3d = self.window.get_scene()
        self.camera = ti.ui.Camera()
        self.playing = False
        self.show_ghost = False
        self.color_by = scenes.ColorBy.BODY
        self.drag = None          # (panel index, vertex index, view depth) while dragging
        self.frames_drawn = 0
        self.load(scene_name)

    # ---------------------------------------------------------------------------------------
    # Scene set-up
    # ---------------------------------------------------------------------------------------
    def load(self, scene_name):
        """Switch to a scene: new simulations, new GPU buffers (allocated here, not per frame)."""
        self.scene = scenes.get(scene_name)
        self.runner = SceneRunner(self.scene, self.arch, ghost_mode=GhostMode.STEP, live=True)
        self.runner.color_by = self.color_by
        self.panels = self.runner.panels
        self.show_ghost = False
        for p in self.panels:
            p.ghost_enabled = False
        extent = np.ptp(self.panels[0].sim.positions[:, 0]) if self.panels else 1.0
        self.offsets = [np.array([1.4 * extent * i, 0.0, 0.0]) for i in range(len(self.panels))]
        self.selected = None        # the panel index the sliders change; None: every panel
        # our own normals and RGBA colours: GGUI's kernels for the defaults assign float64 literals
        # to float32 fields (a page of precision warnings at start)
        self.vertex_fields, self.rgba_fields, self.ghost_fields, self.index_fields = [], [], [], []
        self.normal_fields, self.ghost_normal_fields = [], []
        for p in self.panels:
            n = p.sim.positions.shape[0]
            self.vertex_fields.append(ti.Vector.field(3, ti.f32, n))
            self.rgba_fields.append(ti.Vector.field(4, ti.f32, n))
            self.ghost_fields.append(ti.Vector.field(3, ti.f32, n))
            self.normal_fields.append(ti.Vector.field(3, ti.f32, n))
            self.ghost_normal_fields.append(ti.Vector.field(3, ti.f32, n))
            indices = ti.field(ti.i32, p.faces.size)
            indices.from_numpy(p.faces.ravel().astype(np.int32))
            self.index_fields.append(indices)
        self._aim_camera(extent)

    def _aim_camera(self, extent):
        """The scene's camera, moved back until every panel fits beside the controls and shifted so that
        the bodies sit right of them."""
        cam = self.scene.camera
        eye, target = np.asarray(cam.eye, float), np.asarray(cam.target, float)
        right, _, forward = cam.basis()
        width, height = self.window.get_window_shape()
        # the view's width (m) at the target per metre of distance
        view_width = 2.0 * math.tan(math.radians(cam.fov_degrees) / 2.0) * width / height
        span = 1.4 * extent * (len(self.panels) - 1) + extent
        free = 1.0 - CONTROLS_WIDTH - 0.05
        distance = max(float(np.linalg.norm(target - eye)), 1.1 * span / (free * view_width))
        centre = np.mean(self.offsets, axis=0) - right * (CONTROLS_WIDTH / 2.0) * distance * view_width
        self.camera.position(*(target + centre - forward * distance))
        self.camera.lookat(*(target + centre))
        self.camera.up(*cam.up)
        self.camera.fov(cam.fov_degrees)

    # ---------------------------------------------------------------------------------------
    # Controls (used by the window widgets, the keyboard and the tests)
    # ---------------------------------------------------------------------------------------
    def toggle_play(self):
        self.playing = not self.playing

    def single_step(self):
        self.runner.step()
        for p in self.panels:
            self._hold_dragged(p)

    def single_iteration(self):
        self.runner.iterate(1)
        for p in self.panels:
            self._hold_dragged(p)

    def reset(self):
        self.runner.reset()
        self.drag = None

    def select_panel(self, index):
        """Let the sliders change panel ``index`` (0 = leftmost) only, or every panel with None."""
        if index is not None and not 0 <= index < len(self.panels):
            raise DemoError(f"panel {index} does not exist; this scene has {len(self.panels)}")
        self.selected = index

    @property
    def shown_settings(self):
        """The settings the sliders show: the selected panel's, or the first panel's when editing all."""
        return self.panels[self.selected or 0].settings

    def _change(self, **fields):
        """Change ``fields`` of the edited panels' settings; every other setting of each panel stays."""
        targets = self.panels if self.selected is None else [self.panels[self.selected]]
        for p in targets:
            p.apply(dataclasses.replace(p.settings, **fields))

    def set_youngs_modulus(self, log10_e):
        self._change(youngs_modulus=10.0 ** float(log10_e))

    def set_iterations(self, n):
        self._change(iterations=int(n))

    def set_dt(self, dt):
        self._change(dt=float(dt))

    def set_chebyshev_rho(self, rho):
        """rho = 0 switches Chebyshev acceleration off (the slider stops at the scene's stable limit)."""
        self._change(chebyshev_rho=float(rho))

    def set_ghost(self, on):
        self.show_ghost = bool(on)
        for p in self.panels:
            p.ghost_enabled = self.show_ghost

    def set_color_by(self, color_by):
        self.color_by = self.runner.color_by = color_by

    # ---------------------------------------------------------------------------------------
    # Mouse dragging: pick the vertex nearest the cursor, then keep it under the cursor
    # ---------------------------------------------------------------------------------------
    def _view_projection(self):
        width, height = self.window.get_window_shape()
        view = self.camera.get_view_matrix().T   # GGUI returns row-vector matrices
        proj = self.camera.get_projection_matrix(width / height).T
        return proj @ view

    def _to_screen(self, points):
        clip = np.c_[points, np.ones(len(points))] @ self._view_projection().T
        return clip[:, :2] / clip[:, 3:4] * 0.5 + 0.5, clip[:, 3]

    def pick(self, cursor, radius=0.03):
        """Start dragging the vertex nearest the cursor (window coordinates in [0, 1]), if close."""
        best = None
        for i, p in enumerate(self.panels):
            screen, depth = self._to_screen(p.sim.positions + self.offsets[i])
            d = np.linalg.norm(screen - np.asarray(cursor), axis=1)
            j = int(np.argmin(d))
            if d[j] < radius and (best is None or d[j] < best[0]):
                best = (d[j], i, j, depth[j])
        self.drag = best[1:] if best else None

    def drag_to(self, cursor):
        """Move the dragged vertex under the cursor at its original view depth."""
        if self.drag is None:
            return
        i, j, w = self.drag
        ndc = (np.asarray(cursor) * 2 - 1) * w
        inverse = np.linalg.inv(self._view_projection())
        # solve for the point whose clip coordinates are (ndc x, ndc y, z, w) with z from the current vertex
        current = np.r_[self.panels[i].sim.positions[j] + self.offsets[i], 1.0] @ self._view_projection().T
        world = inverse @ np.array([ndc[0], ndc[1], current[2], w])
        target = world[:3] / world[3] - self.offsets[i]
        x = self.panels[i].sim.positions
        x[j] = target
        self.panels[i].sim.set_positions(x)

    def _hold_dragged(self, p):
        if self.show_window and self.drag is not None and self.panels[self.drag[0]] is p:
            self.drag_to(self.window.get_cursor_pos())

    # ---------------------------------------------------------------------------------------
    # The frame
    # ---------------------------------------------------------------------------------------
    def _handle_input(self):
        for e in self.window.get_events(ti.ui.PRESS):
            if e.key == ti.ui.SPACE:
                self.toggle_play()
            elif e.key == "n":
                self.single_step()
            elif e.key == "i":
                self.single_iteration()
            elif e.key == "r":
                self.reset()
            elif e.key == ti.ui.ESCAPE:
                self.window.running = False
            elif e.key == ti.ui.LMB:
                self.pick(self.window.get_cursor_pos())
        if self.drag is not None:
            if self.window.is_pressed(ti.ui.LMB):
                self.drag_to(self.window.get_cursor_pos())
            else:
                self.drag = None
        self.camera.track_user_inputs(self.window, movement_speed=0.02, hold_key=ti.ui.RMB)

    def _controls(self):
        gui = self.window.get_gui()
        window_width, window_height = self.window.get_window_shape()
        status = [f"scene {self.scene.name} | {HELP}"] + [line for i in range(len(self.panels))
                           for line in self.panel_lines(i, status_width(window_width))]
        band = min(STATUS_BAND, (LINE_HEIGHT * len(status) + TITLE_HEIGHT) / window_height)
        with gui.sub_window("help and panels", 0.0, 1.0 - band, 1.0, band) as w:
            for line in status:
                w.text(line)
        with gui.sub_window("VBD", 0.01, 0.01, CONTROLS_WIDTH, 0.98 - band) as w:
            if w.button("pause" if self.playing else "play"):
                self.toggle_play()
            if w.button("single step"):
                self.single_step()
            if w.button("single iteration"):
                self.single_iteration()
            if w.button("reset"):
                self.reset()
            if len(self.panels) > 1:
                for index, name in [(None, "edit: every panel")] + [(i, f"edit: panel {i + 1}")
                                                                     for i in range(len(self.panels))]:
                    if w.checkbox(name, self.selected == index) and self.selected != index:
                        self.select_panel(index)
            shown = self.shown_settings
            log_e = w.slider_float("log10 E (Pa)", math.log10(shown.youngs_modulus), 3.0, 8.0)
            if _moved(log_e, math.log10(shown.youngs_modulus)):
                self.set_youngs_modulus(log_e)
            iterations = w.slider_int("iterations", shown.iterations, 1, 200)
            if iterations != shown.iterations:
                self.set_iterations(iterations)
            dt = w.slider_float("dt (s)", shown.dt, 1.0 / 480.0, 1.0 / 30.0)
            if _moved(dt, shown.dt):
                self.set_dt(dt)
            w.text(f"Chebyshev rho (0 = off; stable to {self.scene.max_chebyshev_rho}):")
            rho = w.slider_float("rho", shown.chebyshev_rho, 0.0, self.scene.max_chebyshev_rho)
            if _moved(rho, shown.chebyshev_rho):
                self.set_chebyshev_rho(rho)
            for option in COLOUR_OPTIONS:
                if w.checkbox(f"colour: {option.value}", self.color_by is option) and self.color_by is not option:
                    self.set_color_by(option)
            ghost = w.checkbox("Newton ghost (slow)", self.show_ghost)
            if ghost != self.show_ghost:
                self.set_ghost(ghost)
            for name in scenes.SCENES:
                if w.button(f"load {name}"):
                    self.load(name)
                    return

    def panel_lines(self, index, width=40):
        """What the controls say about panel ``index``: what it simulates, its clock and error (or why it
        stopped), wrapped to ``width`` characters."""
        p = self.panels[index]
        line = f"panel {index + 1}: {p.label}, t = {p.sim.time:.2f} s"
        if p.error is not None and self.show_ghost:
            line += f", error {p.error:.3f}"
        lines = [line] + p.remarks()
        return [packed for i, line in enumerate(lines) for packed in _wrap(line, width, first_indent=i > 0)]

    def _upload(self):
        """The runner's panel states (positions, colours, ghosts) into the GPU buffers."""
        for i, (p, state) in enumerate(zip(self.panels, self.runner.states())):
            if p.failure is not None:       # not drawn
                continue
            x = state.positions
            self.vertex_fields[i].from_numpy((x + self.offsets[i]).astype(np.float32))
            self.normal_fields[i].from_numpy(vertex_normals(x, p.faces).astype(np.float32))
            self.rgba_fields[i].from_numpy(np.c_[state.rgb, np.full(len(x), OPAQUE)].astype(np.float32))
            if self.show_ghost and state.ghost is not None:
                self.ghost_fields[i].from_numpy((state.ghost + self.offsets[i]).astype(np.float32))
                self.ghost_normal_fields[i].from_numpy(vertex_normals(state.ghost, p.faces).astype(np.float32))

    def frame(self):
        """Handle input, advance if playing, draw. One call per displayed frame."""
        if self.show_window:    # off screen there are no input events
            self._handle_input()
        self._controls()
        if self.playing:
            self.single_step()
        self._upload()
        self.scene3d.set_camera(self.camera)
        self.scene3d.ambient_light((0.35, 0.35, 0.35))
        self.scene3d.point_light(pos=tuple(np.asarray(self.scene.camera.eye) + (0.0, 0.0, 3.0)), color=(0.9, 0.9, 0.9))
        for i, p in enumerate(self.panels):
            if p.failure is not None:       # a diverged body is far away (or not finite): its label explains
                continue
            self.scene3d.mesh(self.vertex_fields[i], indices=self.index_fields[i], normals=self.normal_fields[i],
                              per_vertex_color=self.rgba_fields[i], two_sided=True)
            if self.show_ghost and p.ghost is not None:
                self.scene3d.mesh(self.ghost_fields[i], indices=self.index_fields[i],
                                  normals=self.ghost_normal_fields[i], color=GHOST_RGB,
                                  show_wireframe=True, two_sided=True)
        self.canvas.set_background_color((0.9, 0.91, 0.93))
        self.canvas.scene(self.scene3d)
        self.frames_drawn += 1

    def run(self, max_frames=None):
        """The window loop; ``max_frames`` stops it early (used by tests)."""
        while self.window.running and (max_frames is None or self.frames_drawn < max_frames):
            self.frame()
            if self.show_window:
                self.window.show()
            else:
                # off screen, reading the image back is what finishes the frame (and clears the
                # scene's draw list for the next one); without it every frame is drawn on top
                self._last_image = self.window.get_image_buffer_as_numpy()

    def image(self):
        """The last drawn frame as a float RGBA array (width, height, 4), as GGUI returns it."""
        if not self.show_window and getattr(self, "_last_image", None) is not None:
            return self._last_image
        return self.window.get_image_buffer_as_numpy()


def status_width(window_width):
    """Characters per line of the status band of a window ``window_width`` pixels wide, less a margin of two."""
    return int(window_width / CHAR_WIDTH) - 2


def too_small(size):
    """Why a window of ``size`` (width, height) cannot show the status band's labels, or None when it can."""
    width, height = size
    if width >= MIN_SIZE[0] and height >= MIN_SIZE[1]:
        return None
    return (f"a {width}x{height} window is too small to show the labels: the interactive window needs at least "
            f"{MIN_SIZE[0]}x{MIN_SIZE[1]} pixels")


def window_size(text):
    """The window's --size: WIDTHxHEIGHT as `cli.image_size` takes it, at least MIN_SIZE."""
    size = image_size(text)
    if problem := too_small(size):
        raise argparse.ArgumentTypeError(problem)
    return size


def vertex_normals(x, faces):
    """Unit normals (N, 3) at the vertices x (N, 3) of the triangles ``faces`` (F, 3): the normalised
    sum of the unit normals of the triangles around each vertex."""
    n = np.cross(x[faces[:, 1]] - x[faces[:, 0]], x[faces[:, 2]] - x[faces[:, 0]])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    summed = np.stack([sum(np.bincount(faces[:, k], n[:, d], minlength=len(x)) for k in range(3))
                       for d in range(3)], axis=1)
    return summed / np.maximum(np.linalg.norm(summed, axis=1, keepdims=True), 1e-300)


def _wrap(line, width, first_indent):
    """``line`` in lines of at most ``width`` characters, broken after commas where possible (so that
    "dt = 1/60 s" stays together), continuation lines indented."""
    indent = "   "
    out, current = [], indent if first_indent else ""
    for part in line.split(", "):
        joined = f"{current}, {part}" if current.strip() else current + part
        if len(joined) <= width or not current.strip():
            current = joined
        else:
            out.append(current + ",")
            current = indent + part
    out.append(current)
    return [piece for text in out for piece in textwrap.wrap(text, width, subsequent_indent=indent,
                                                             drop_whitespace=False) or [text]]


def _moved(value, shown):
    """True when a slider moved: GGUI hands back float32, so an untouched slider differs by round-off."""
    return not math.isclose(value, shown, rel_tol=1e-6, abs_tol=1e-9)


def run(scene_name, arch="cpu", size=(1280, 720)):
    """Open the window on a scene (``python -m demo interactive SCENE``)."""
    scenes.get(scene_name)
    InteractiveApp(scene_name, arch=arch, size=size).run()
