"""The interactive classroom window (Taichi GGUI, which needs Vulkan).

Controls are methods of ``InteractiveApp`` so that the window's buttons, the keyboard and the
tests all drive the same code. ``InteractiveApp(..., show_window=False)`` runs off screen.
"""
import dataclasses
import math

import numpy as np

import solver
from solver._ti import ti

from . import colours, scenes
from .errors import DemoError
from .render import GHOST_COLOUR
from .runner import GhostMode, PanelSim
from .scenes import Advance

HELP = ("space play/pause | n step | i one iteration | r reset | left-drag a vertex | "
        "right-drag + WASDQE camera | Esc quit")


COLOUR_OPTIONS = (scenes.ColourBy.BODY, scenes.ColourBy.COLOUR_SETS, scenes.ColourBy.RESIDUAL)


class InteractiveApp:
    """One window showing one scene's panels side by side in 3D, with controls."""

    def __init__(self, scene_name=scenes.DEFAULT_SCENE, arch="cpu", size=(1280, 720), show_window=True):
        if not hasattr(ti, "ui"):
            raise DemoError(f"the interactive window needs Taichi's GGUI, which {ti.__name__} lacks; "
                            "pip install taichi==1.7.4 (CPython 3.10-3.13). Headless rendering still works: "
                            "python -m demo render")
        solver.ensure_taichi(arch=arch)
        self.arch = arch
        try:
            self.window = ti.ui.Window("VBD classroom", tuple(size), vsync=True, show_window=show_window)
        except Exception as e:  # GGUI reports a missing Vulkan loader or driver in several ways
            first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise DemoError("the interactive window needs Vulkan (apt-get install mesa-vulkan-drivers libvulkan1); "
                            f"Taichi said: {first}. Headless rendering still works: python -m demo render") from None
        self.show_window = show_window
        self.canvas = self.window.get_canvas()
        self.scene3d = self.window.get_scene()
        self.camera = ti.ui.Camera()
        self.playing = False
        self.show_ghost = False
        self.colour_by = scenes.ColourBy.BODY
        self.drag = None          # (panel index, vertex index, view depth) while dragging
        self.frames_drawn = 0
        self.load(scene_name)

    # ---------------------------------------------------------------------------------------
    # Scene set-up
    # ---------------------------------------------------------------------------------------
    def load(self, scene_name):
        """Switch to a scene: new simulations, new GPU buffers (allocated here, not per frame)."""
        self.scene = scenes.get(scene_name)
        self.panels = [PanelSim(self.scene, p, self.arch, ghost_mode=GhostMode.STEP) for p in self.scene.panels]
        self.show_ghost = False
        for p in self.panels:
            p.ghost_enabled = False
        extent = np.ptp(self.panels[0].sim.positions[:, 0]) if self.panels else 1.0
        self.offsets = [np.array([1.4 * extent * i, 0.0, 0.0]) for i in range(len(self.panels))]
        self.vertex_fields, self.colour_fields, self.ghost_fields, self.index_fields = [], [], [], []
        for p in self.panels:
            n = p.sim.positions.shape[0]
            self.vertex_fields.append(ti.Vector.field(3, ti.f32, n))
            self.colour_fields.append(ti.Vector.field(3, ti.f32, n))
            self.ghost_fields.append(ti.Vector.field(3, ti.f32, n))
            indices = ti.field(ti.i32, p.faces.size)
            indices.from_numpy(p.faces.ravel().astype(np.int32))
            self.index_fields.append(indices)
        first = self.panels[0]
        material = first.panel.material
        self.log_e = math.log10(material.youngs_modulus)
        self.iterations = first.sim.iterations
        self.dt = first.sim.dt
        self.rho = first.panel.chebyshev_rho or 0.0
        cam = self.scene.camera
        # look a little to the left of the bodies so they sit right of the controls panel
        centre = np.mean([o for o in self.offsets], axis=0) - np.array([0.25 * max(extent, 0.5), 0.0, 0.0])
        self.camera.position(*(np.asarray(cam.eye) + centre))
        self.camera.lookat(*(np.asarray(cam.target) + centre))
        self.camera.up(*cam.up)
        self.camera.fov(cam.fov_degrees)

    # ---------------------------------------------------------------------------------------
    # Controls (used by the window widgets, the keyboard and the tests)
    # ---------------------------------------------------------------------------------------
    def toggle_play(self):
        self.playing = not self.playing

    def single_step(self):
        for p in self.panels:
            if self.scene.advance is Advance.ITERATIONS:
                p.iterate(1)
            else:
                p.step()
            self._hold_dragged(p)

    def single_iteration(self):
        for p in self.panels:
            p.iterate(1)
            self._hold_dragged(p)

    def reset(self):
        for p in self.panels:
            p.reset()
        self.drag = None

    def set_youngs_modulus(self, log10_e):
        self.log_e = float(log10_e)
        for p in self.panels:
            p.sim.set_material(dataclasses.replace(p.sim.material, youngs_modulus=10.0 ** self.log_e))

    def set_iterations(self, n):
        self.iterations = int(n)
        for p in self.panels:
            p.sim.iterations = self.iterations

    def set_dt(self, dt):
        self.dt = float(dt)
        for p in self.panels:
            p.finish_step()
            p.sim.dt = self.dt

    def set_chebyshev_rho(self, rho):
        """rho = 0 switches Chebyshev acceleration off. Turning it on or off rebuilds the simulations."""
        rho = float(rho)
        if (rho > 0) != (self.rho > 0):
            self.panels = [PanelSim(self.scene, dataclasses.replace(p.panel, chebyshev_rho=rho if rho > 0 else None,
                                                                    iterations=self.iterations), self.arch,
                                    ghost_mode=GhostMode.STEP)
                           for p in self.panels]
            for p in self.panels:
                p.ghost_enabled = self.show_ghost
                p.sim.dt = self.dt
                p.sim.set_material(dataclasses.replace(p.sim.material, youngs_modulus=10.0 ** self.log_e))
        elif rho > 0:
            for p in self.panels:
                p.sim.chebyshev_rho = rho
        self.rho = rho

    def set_ghost(self, on):
        self.show_ghost = bool(on)
        for p in self.panels:
            p.ghost_enabled = self.show_ghost

    def set_colour_by(self, colour_by):
        self.colour_by = colour_by

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
        with gui.sub_window("help", 0.0, 0.91, 1.0, 0.09) as w:
            w.text(HELP)
        with gui.sub_window("VBD", 0.01, 0.01, 0.27, 0.88) as w:
            w.text(f"scene: {self.scene.name}")
            if w.button("pause" if self.playing else "play"):
                self.toggle_play()
            if w.button("single step"):
                self.single_step()
            if w.button("single iteration"):
                self.single_iteration()
            if w.button("reset"):
                self.reset()
            log_e = w.slider_float("log10 E (Pa)", self.log_e, 3.0, 8.0)
            if log_e != self.log_e:
                self.set_youngs_modulus(log_e)
            iterations = w.slider_int("iterations", self.iterations, 1, 200)
            if iterations != self.iterations:
                self.set_iterations(iterations)
            dt = w.slider_float("dt (s)", self.dt, 1.0 / 480.0, 1.0 / 30.0)
            if dt != self.dt:
                self.set_dt(dt)
            rho = w.slider_float("Chebyshev rho (0 = off)", self.rho, 0.0, 0.99)
            if rho != self.rho:
                self.set_chebyshev_rho(rho)
            for option in COLOUR_OPTIONS:
                if w.checkbox(f"colour: {option.value}", self.colour_by is option) and self.colour_by is not option:
                    self.set_colour_by(option)
            ghost = w.checkbox("Newton ghost (slow: one Newton solve per step)", self.show_ghost)
            if ghost != self.show_ghost:
                self.set_ghost(ghost)
            w.text("scenes:")
            for name in scenes.SCENES:
                if w.button(name):
                    self.load(name)
                    return
            for p in self.panels:
                error = f", error {p.error:.3f}" if p.error is not None and self.show_ghost else ""
                w.text(f"{p.panel.label}: t = {p.sim.time:.2f} s{error}")
            w.text(HELP)

    def _upload(self):
        for i, p in enumerate(self.panels):
            x = p.sim.positions
            self.vertex_fields[i].from_numpy((x + self.offsets[i]).astype(np.float32))
            if self.colour_by is scenes.ColourBy.COLOUR_SETS:
                rgb = colours.categorical(p.sim.colors)
            elif self.colour_by is scenes.ColourBy.RESIDUAL:
                r = np.linalg.norm(p.sim.residual(), axis=1)
                rgb = colours.sequential(colours.normalise(r, 1e-6, max(float(r.max()), 1e-5), log=True))
            else:
                rgb = colours.uniform(len(x))
            self.colour_fields[i].from_numpy(rgb.astype(np.float32))
            if self.show_ghost and p.ghost is not None:
                self.ghost_fields[i].from_numpy((p.ghost + self.offsets[i]).astype(np.float32))

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
            self.scene3d.mesh(self.vertex_fields[i], indices=self.index_fields[i],
                              per_vertex_color=self.colour_fields[i], two_sided=True)
            if self.show_ghost and p.ghost is not None:
                self.scene3d.mesh(self.ghost_fields[i], indices=self.index_fields[i], color=GHOST_COLOUR,
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


def run(scene_name, arch="cpu", size=(1280, 720)):
    """Open the window on a scene (``python -m demo interactive SCENE``)."""
    scenes.get(scene_name)
    InteractiveApp(scene_name, arch=arch, size=size).run()
