"""Turn a ``Scene`` into running simulations and, frame by frame, into what should be drawn."""
from dataclasses import dataclass

import numpy as np

import solver

from . import colours
from .scenes import Advance, ColourBy

# Newton steps below 1e-7 of the body size: x* to about a micrometre, far below what a frame shows
NEWTON_TOLERANCE = 1e-7


@dataclass
class PanelState:
    """One panel after a frame: what to draw and what the label says."""

    positions: np.ndarray
    faces: np.ndarray
    colours: np.ndarray
    ghost: np.ndarray       # Newton reference positions, or None
    lines: list             # label lines
    error: float            # relative error against the Newton reference, or None


class PanelSim:
    """The simulation of one panel, plus its boundary surface for drawing."""

    def __init__(self, scene, panel, arch="cpu"):
        self.scene, self.panel = scene, panel
        mesh = panel.mesh.build()
        self.faces = np.ascontiguousarray(mesh.boundary_faces(), dtype=np.int32)
        self.tets = np.asarray(mesh.tets)
        self.ghost_enabled = panel.newton_ghost
        fixed = _mask(panel.fixed, mesh.vertices)
        kinematic = _mask(panel.kinematic, mesh.vertices)
        self.sim = solver.Simulation(
            mesh, panel.material, dt=scene.dt, gravity=scene.gravity,
            fixed=fixed if fixed.any() else None, iterations=panel.iterations,
            initial_guess=panel.initial_guess, chebyshev_rho=panel.chebyshev_rho,
            damping=scene.damping, ground=scene.ground,
            kinematic=kinematic if kinematic.any() else None,
            kinematic_motion=panel.motion if kinematic.any() else None, arch=arch)
        self.reset()

    def reset(self):
        self.sim.reset()
        self.start = self.sim.positions     # x_n, the positions at the start of the current step
        self.ghost = None
        self.error = None
        self.iteration = 0
        self.in_step = False

    def step(self):
        """One full time step, measured against the Newton reference when the panel shows one."""
        self.finish_step()
        self.start = self.sim.positions
        self.ghost = self.sim.newton_reference(tolerance=NEWTON_TOLERANCE) if self.ghost_enabled else None
        self.sim.step()
        self.iteration = self.sim.iterations
        self._measure()

    def iterate(self, count=1):
        """``count`` more iterations of the current time step (opening one if needed)."""
        if not self.in_step:
            self.start = self.sim.positions
            self.ghost = self.sim.newton_reference(tolerance=NEWTON_TOLERANCE) if self.ghost_enabled else None
            self.sim.begin_step()
            self.iteration = 0
            self.in_step = True
        if count:
            self.sim.run_iterations(count)
            self.iteration += count
        self._measure()

    def finish_step(self):
        """Close a time step opened by ``iterate``."""
        if self.in_step:
            self.sim.end_step()
            self.in_step = False

    def _measure(self):
        if self.ghost is not None:
            self.error = solver.relative_error(self.sim.positions, self.ghost, self.start)

    def state(self):
        x = self.sim.positions
        by, lo_hi = self.scene.colour_by, self.scene.colour_range
        lines = [self.panel.label]
        if by is ColourBy.DISPLACEMENT:
            rgb = colours.sequential(colours.normalise(np.linalg.norm(x - self.start, axis=1), *lo_hi, log=True))
        elif by is ColourBy.RESIDUAL:
            rgb = colours.sequential(colours.normalise(np.linalg.norm(self.sim.residual(), axis=1), *lo_hi, log=True))
        elif by is ColourBy.COLOUR_SETS:
            rgb = colours.categorical(self.sim.colors)
            lines.append(f"{self.sim.n_colors} colours for {len(x)} vertices")
        else:
            rgb = colours.uniform(len(x))
        if self.scene.advance is Advance.ITERATIONS:
            lines.append(f"iteration {self.iteration}")
        elif by is not ColourBy.COLOUR_SETS:
            lines.append(f"{self.panel.iterations} iterations, dt = {_fraction(self.scene.dt)} s, t = {self.sim.time:.2f} s")
        if self.error is not None:
            lines.append(f"relative error {self.error:.3f}")
        return PanelState(x, self.faces, rgb, self.ghost, lines, self.error)


class SceneRunner:
    """All panels of a scene; ``advance()`` produces the next frame's panel states."""

    def __init__(self, scene, arch="cpu"):
        self.scene = scene
        self.panels = [PanelSim(scene, panel, arch) for panel in scene.panels]
        self.frame = 0

    def advance(self):
        for p in self.panels:
            if self.scene.advance is Advance.ITERATIONS:
                p.iterate(1 if self.frame > 0 else 0)
            else:
                p.step()
        self.frame += 1
        return [p.state() for p in self.panels]


def _mask(selectors, vertices):
    mask = np.zeros(len(vertices), bool)
    for selector in selectors:
        mask |= selector.select(vertices)
    return mask


def _fraction(dt):
    """1/60 rather than 0.016666."""
    inverse = 1.0 / dt
    return f"1/{inverse:.0f}" if abs(inverse - round(inverse)) < 1e-9 else f"{dt:g}"
