"""Turn a ``Scene`` into running simulations and, frame by frame, into what should be drawn."""
import dataclasses
import time
import warnings
from dataclasses import dataclass

import numpy as np

import solver
from solver.method import multilevel_cycles

from . import colors
from .errors import DemoError
from .scenes import Advance, ColorBy

# Newton stops once its step is below 1e-6 of the body size (a micrometre on a 1 m bar): far below
# what a frame shows, and a warm start from the VBD result gets there in two to four iterations
NEWTON_TOLERANCE = 1e-6
DRIFT_SHOWN = 0.01      # m: a sideways drift of the centre of mass below this is not labelled


class GhostMode:
    """What the translucent ghost of a panel shows."""

    TRAJECTORY = "trajectory"   # the converged implicit-Euler trajectory, advanced by Newton every step
    STEP = "step"               # x*, the converged Newton solution of the step VBD is taking now


@dataclass
class PanelState:
    """One panel after a frame: what to draw and what the label says."""

    positions: np.ndarray
    faces: np.ndarray
    rgb: np.ndarray
    ghost: np.ndarray       # reference positions, or None
    lines: list             # label lines
    error: float            # relative error of this step against its Newton solution x*, or None
    trajectory_gap: float = None    # m: max_i |x_i - ghost_i| against the converged trajectory, or None


@dataclass(frozen=True)
class PanelSettings:
    """What the interactive window changes in one panel while it runs."""

    youngs_modulus: float   # E, Pa
    iterations: int         # VBD iterations per time step
    dt: float               # time step, s
    chebyshev_rho: float    # Chebyshev spectral radius estimate; 0 switches the acceleration off

    def describe(self):
        """One line naming every setting, e.g. "E = 2.5e5 Pa, 20 it., dt = 1/60 s, Chebyshev rho 0.9"."""
        mantissa, exponent = f"{self.youngs_modulus:.1e}".split("e")
        e = f"{mantissa.removesuffix('.0')}e{int(exponent)}"
        rho = f", Chebyshev rho {self.chebyshev_rho:.3g}" if self.chebyshev_rho > 0 else ""
        return f"E = {e} Pa, {self.iterations} it., dt = {_fraction(self.dt)} s{rho}"


class PanelSim:
    """The simulation of one panel, plus its boundary surface for drawing.

    With ``ghost_enabled``, every step is measured against x*, the converged Newton solution of the
    same step from the same state (started at the VBD result or at y, whichever is lower in G, so it
    usually costs a few Newton iterations): ``error`` = ||x - x*|| / ||x* - x_n||. In ``GhostMode.TRAJECTORY`` (time-step
    scenes) the ghost is a second simulation with identical settings that is advanced every step
    by a converged Newton solve of its own step: what implicit Euler would do with an exact solver.
    In ``GhostMode.STEP`` (iteration-by-iteration scenes and the interactive window) the ghost is x*.
    """

    def __init__(self, scene, panel, arch="cpu", ghost_mode=None):
        self.scene, self.panel = scene, panel
        mesh = panel.mesh.build()
        self.faces = np.ascontiguousarray(mesh.boundary_faces(), dtype=np.int32)
        self.tets = np.asarray(mesh.tets)
        self.ghost_enabled = panel.newton_ghost
        if ghost_mode is None:
            ghost_mode = GhostMode.STEP if scene.advance is Advance.ITERATIONS else GhostMode.TRAJECTORY
        self.ghost_mode = ghost_mode
        fixed = _mask(panel.fixed, mesh.vertices)
        kinematic = _mask(panel.kinematic, mesh.vertices)
        self._settings = dict(
            mesh=mesh, material=panel.material, dt=scene.dt, gravity=scene.gravity,
            fixed=fixed if fixed.any() else None, iterations=panel.iterations,
            initial_guess=panel.initial_guess, chebyshev_rho=panel.chebyshev_rho,
            damping=scene.damping, ground=scene.ground,
            kinematic=kinematic if kinematic.any() else None,
            kinematic_motion=panel.motion if kinematic.any() else None, keep_orientation=panel.keep_orientation,
            method=panel.method, arch=arch)
        self.sim = solver.Simulation(**self._settings)
        self.scene_settings = self.settings
        self.rest = mesh.vertices
        self.tip = mesh.vertices[:, 0] >= mesh.vertices[:, 0].max() - 1e-9     # the far end face
        self.length = float(np.ptp(mesh.vertices, axis=0).max())               # m, the body's longest side
        self.rest_tip_height = float(mesh.vertices[self.tip, 2].mean())
        self.reference = None       # the trajectory ghost's simulation, built on first use
        self.reference_source = None    # an earlier panel whose trajectory ghost is this one's too
        self.reset()

    def reset(self):
        self.sim.reset()
        if self.reference is not None:
            self.reference.reset()
        self.reference_synced = self.reference is not None
        self.start = self.sim.positions     # x_n, the positions at the start of the current step
        self.ghost = None
        self.error = None
        self.error_converged = True
        self.iteration = 0
        self.in_step = False
        self.failure = None         # why this panel stopped (it diverged), or None while it runs
        self.step_seconds = []      # wall time of every solver step since the reset (s)

    @property
    def settings(self):
        """The ``PanelSettings`` this panel simulates now."""
        sim = self.sim
        return PanelSettings(youngs_modulus=sim.material.youngs_modulus, iterations=sim.iterations, dt=sim.dt,
                             chebyshev_rho=sim.chebyshev_rho or 0.0)

    @property
    def label(self):
        """The scene's label while the panel runs the scene's settings, else a description of its settings."""
        settings = self.settings
        return self.panel.label if settings == self.scene_settings else f"changed: {settings.describe()}"

    def apply(self, settings):
        """Simulate with ``settings`` from the current state on: the one place a panel's settings change.

        An open iteration-by-iteration step is closed first; every setting is assigned to the running
        simulation (they are all live settings of `solver.Simulation`); one the panel's method refuses
        stops the panel with the solver's message, as a divergence does.
        """
        if settings == self.settings:
            return
        self.finish_step()
        material = dataclasses.replace(self.sim.material, youngs_modulus=settings.youngs_modulus)
        rho = settings.chebyshev_rho or None
        self._settings.update(material=material, iterations=settings.iterations, dt=settings.dt, chebyshev_rho=rho)
        self.sim.material = material
        self._guarded(lambda: setattr(self.sim, "settings", dataclasses.replace(
            self.sim.settings, chebyshev_rho=rho, iterations=settings.iterations, dt=settings.dt)))
        self.reference = None       # the trajectory ghost restarts with the new settings on first use
        self.reference_synced = False

    def step(self):
        """One full time step, measured against the Newton solution of the same step when enabled."""
        if self.failure is not None:
            return
        self.finish_step()
        self.start = self.sim.positions
        problem = self.sim.step_problem() if self.ghost_enabled else None
        if self.ghost_enabled and self.ghost_mode == GhostMode.TRAJECTORY and not self._shares_reference_next():
            self._sync_reference()
        started = time.perf_counter()
        if not self._guarded(self.sim.step):
            self.ghost, self.error = None, None
            return
        self.step_seconds.append(time.perf_counter() - started)
        self.iteration = self.sim.iterations
        if problem is None:
            self.ghost, self.error = None, None
            # a step without the reference breaks its trajectory: when the ghost is switched back on,
            # the reference restarts from the body's state then (so its first ghost is x* of that step)
            self.reference_synced = False
            return
        x_star, self.error_converged = _newton(problem, self.sim.positions)
        self.error = solver.relative_error(self.sim.positions, x_star, self.start)
        if self.ghost_mode != GhostMode.TRAJECTORY:
            self.ghost = x_star
        elif self._shares_reference():
            self.ghost = self.reference_source.ghost
        else:
            self.ghost = self._advance_reference()

    def _timed_step(self):
        """Wall time (s) of one time step of this panel's solver from its current state, to which the
        simulation returns afterwards."""
        saved = self.sim.save_state()
        started = time.perf_counter()
        self.sim.step()
        seconds = time.perf_counter() - started
        self.sim.restore_state(saved)
        return seconds

    def relative_step_time(self, other, rounds=7):
        """This panel's wall time per step over ``other``'s (a PanelSim): the median of ``rounds`` ratios,
        each of one step of each timed back to back, so that the load of a shared machine weighs on both
        alike; after an untimed step of each (compiling kernels, building the solvers' caches)."""
        self._timed_step()
        other._timed_step()
        return float(np.median([self._timed_step() / other._timed_step() for _ in range(rounds)]))

    def match_wall_time(self, other):
        """Give this panel as many iterations per step as fit in ``other``'s wall time per step. A step
        costs a + b x iterations: measured (relative to ``other``) at the panel's iterations n1 and at
        n2 = n1 / ratio(n1), then solved for a + b n = 1 (n2 if the measurements give no positive slope)."""
        n1 = self.sim.iterations
        r1 = self.relative_step_time(other)
        n2 = max(1, int(round(n1 / r1)))
        self.sim.iterations = n2
        r2 = self.relative_step_time(other)
        if n2 != n1 and (r2 - r1) / (n2 - n1) > 0:
            b = (r2 - r1) / (n2 - n1)
            self.sim.iterations = max(1, int(round(n2 + (1.0 - r2) / b)))
        self.scene_settings = self.settings

    def budget_line(self):
        """What the solver of a step does, e.g. "plain VBD, 140 iterations" or "two-level VBD, 5 cycles",
        with the median measured wall time per step when the panel shows it."""
        sim = self.sim
        if sim.method is solver.Method.MULTILEVEL:
            what = f"two-level VBD, {multilevel_cycles(sim.iterations)} cycles"
        elif sim.method is solver.Method.PCG:
            what = "Newton-PCG to convergence"
        elif sim.method is solver.Method.NEWTON:
            what = "Newton to convergence"
        elif self.panel.show_step_time:
            what = f"plain VBD, {sim.iterations} iterations"
        else:
            what = f"{sim.iterations} iterations"
        if self.panel.show_step_time and self.step_seconds:
            what += f" = {1e3 * float(np.median(self.step_seconds)):.0f} ms/step"
        return what

    def _guarded(self, advance):
        """Run ``advance()``; a diverging body stops this panel with a message (``failure``, shown in its
        label) instead of ending the program. Returns True while the panel runs."""
        try:
            advance()
        except solver.VBDError as e:      # the solver's divergence guard says what diverged and what to change
            self.failure = f"stopped at t = {self.sim.time:.2f} s: {e} Reset to run again."
        return self.failure is None

    def _shares_reference_next(self):
        src = self.reference_source
        return src is not None and src.ghost_enabled and src.ghost_mode == GhostMode.TRAJECTORY

    def _shares_reference(self):
        """True when an earlier panel with the same body, material and time step already advanced the
        converged trajectory this frame (the iteration budget does not change a converged solve)."""
        src = self.reference_source
        return (src is not None and src.ghost_enabled and src.ghost_mode == GhostMode.TRAJECTORY
                and src.ghost is not None and src.sim.frame == self.sim.frame and src.sim.dt == self.sim.dt
                and src.sim.material == self.sim.material)

    def _sync_reference(self):
        """Start the reference trajectory from the current state (first use, or after a reset)."""
        if self.reference is None:
            self.reference = solver.Simulation(**self._settings)
        if not self.reference_synced:
            self.reference.reset()
            self.reference.set_positions(self.sim.positions)
            self.reference.set_velocities(self.sim.velocities)
            self.reference.time, self.reference.frame = self.sim.time, self.sim.frame
            self.reference_synced = True

    def _advance_reference(self):
        """One converged implicit-Euler step of the reference from its own state."""
        self._sync_reference()      # a no-op unless the reference has never run (or was reset)
        ref = self.reference
        problem = ref.step_problem()
        x_n = ref.positions
        x, _ = _newton(problem, self.sim.positions)
        ref.set_positions(x)
        ref.set_velocities((x - x_n) / ref.dt)
        ref.time += ref.dt
        ref.frame += 1
        return x

    def iterate(self, count=1):
        """``count`` more iterations of the current time step (opening one if needed)."""
        if self.failure is not None:
            return
        if not self.in_step:
            self.start = self.sim.positions
            self.ghost = None
            if self.ghost_enabled:
                problem = self.sim.step_problem()
                self.ghost = solver.fast_newton_solve(problem, problem.y_with_constraints(),
                                                      tolerance=NEWTON_TOLERANCE).x
            self.sim.begin_step()
            self.iteration = 0
            self.in_step = True
        if count:
            if not self._guarded(lambda: self.sim.run_iterations(count)):
                self.error = None
                return
            self.iteration += count
        self._measure()

    def finish_step(self):
        """Close a time step opened by ``iterate``."""
        if self.in_step:
            self.sim.end_step()
            self.in_step = False
            # the reference trajectory no longer starts where the body is
            self.reference_synced = False

    def _measure(self):
        self.error = None
        if self.ghost is not None:
            self.error = solver.relative_error(self.sim.positions, self.ghost, self.start)

    def drift(self):
        """How far (m) the centre of mass has moved across gravity since the start."""
        masses = self.sim.masses / self.sim.masses.sum()
        moved = masses @ (self.sim.positions - self.rest)
        g = np.asarray(self.scene.gravity, float)
        if g.any():
            g = g / np.linalg.norm(g)
            moved = moved - (moved @ g) * g
        return float(np.linalg.norm(moved))

    def remarks(self):
        """Label lines about what went wrong: a measured sideways drift, a divergence."""
        lines = []
        if self.panel.show_drift:
            drift = self.drift()
            if drift >= DRIFT_SHOWN:
                lines.append(f"drifted {100 * drift:.0f} cm sideways: the unconverged steps do not conserve momentum")
        if self.failure is not None:
            lines.append(self.failure)
        return lines

    def state(self):
        x = self.sim.positions
        by, lo_hi = self.scene.color_by, self.scene.color_range
        lines = [self.label]
        if by is ColorBy.DISPLACEMENT:
            rgb = colors.sequential(colors.normalise(np.linalg.norm(x - self.start, axis=1), *lo_hi, log=True))
        elif by is ColorBy.RESIDUAL:
            rgb = colors.sequential(colors.normalise(np.linalg.norm(self.sim.residual(), axis=1), *lo_hi, log=True))
        elif by is ColorBy.COLOR_SETS:
            rgb = colors.categorical(self.sim.colors)
            lines.append(f"{self.sim.n_colors} colours for {len(x)} vertices")
        else:
            rgb = colors.uniform(len(x))
        if self.scene.advance is Advance.ITERATIONS:
            lines.append(f"iteration {self.iteration}")
        elif by is not ColorBy.COLOR_SETS:
            lines.append(f"{self.budget_line()}, dt = {_fraction(self.sim.dt)} s, t = {self.sim.time:.2f} s")
        gap = None
        if self.ghost is not None and self.ghost_mode == GhostMode.TRAJECTORY:
            tip = self.tip
            drop = lambda p: float(self.rest_tip_height - p[tip, 2].mean())
            lines.append(f"tip drop {_cm(drop(x))} cm (ghost {_cm(drop(self.ghost))} cm)")
            # the error that has built up over all steps so far: what the audience sees
            gap = float(np.linalg.norm(x - self.ghost, axis=1).max())
            lines.append(f"off the ghost by {_cm(gap)} cm = {gap / self.length:.0%} of its length")
        if self.error is not None:
            unsure = "" if self.error_converged else " (Newton not converged: approximate)"
            # three decimals read well down to 0.01; below, where only the remedies get, the exponent
            shown = f"{self.error:.3f}" if self.error >= 0.01 else f"{self.error:.1e}"
            lines.append(f"relative error {shown}{unsure}")
        if self.panel.show_inverted:
            lines.append(f"inverted tets: {self.sim.inverted_count()}")
        lines += self.remarks()
        return PanelState(x, self.faces, rgb, self.ghost, lines, self.error, gap)


class RestPanel:
    """A panel of an ``Advance.REST`` scene: the body at rest, coloured by its colour sets.

    Builds no ``solver.Simulation``, only the mesh and its colouring, so that a homework starter can
    draw its colouring before the solver tasks are done.
    """

    def __init__(self, scene, panel):
        self.scene, self.panel = scene, panel
        mesh = panel.mesh.build()
        self.faces = np.ascontiguousarray(mesh.boundary_faces(), dtype=np.int32)
        self.tets = np.asarray(mesh.tets)
        self.start = np.asarray(mesh.vertices, dtype=np.float64)
        coloring = solver.color_vertices(mesh.tets, mesh.n_vertices, key=mesh.topology_key())
        pinned = _mask(panel.fixed, mesh.vertices) | _mask(panel.kinematic, mesh.vertices)
        self.colors = np.where(pinned, -1, coloring.colors).astype(np.int32)
        self.n_colors = len(np.unique(self.colors[self.colors >= 0]))

    def state(self):
        if self.scene.color_by is ColorBy.COLOR_SETS:
            rgb = colors.categorical(self.colors)
            lines = [self.panel.label, f"{self.n_colors} colours for {len(self.start)} vertices"]
        else:
            rgb, lines = colors.uniform(len(self.start)), [self.panel.label]
        return PanelState(self.start, self.faces, rgb, None, lines, None)


class SceneRunner:
    """All panels of a scene; ``advance()`` produces the next frame's panel states."""

    def __init__(self, scene, arch="cpu"):
        self.scene = scene
        if scene.advance is Advance.REST:
            solver.ensure_taichi(arch)
            self.panels = [RestPanel(scene, panel) for panel in scene.panels]
            self.frame = 0
            return
        self.panels = [PanelSim(scene, panel, arch) for panel in scene.panels]
        for p in self.panels:
            k = p.panel.same_wall_time_as
            if k is None:
                continue
            if not (isinstance(k, int) and 0 <= k < len(self.panels)) or self.panels[k] is p:
                raise DemoError(f"panel {p.panel.label!r}: same_wall_time_as={k!r} must be the index of another "
                                f"panel of scene {scene.name!r} (0..{len(self.panels) - 1})")
            p.match_wall_time(self.panels[k])
        for i, p in enumerate(self.panels):
            for q in self.panels[:i]:
                if q.reference_source is None and _same_body(p.panel, q.panel):
                    p.reference_source = q
                    break
        self.frame = 0

    def advance(self):
        for p in self.panels:
            if self.scene.advance is Advance.ITERATIONS:
                p.iterate(1 if self.frame > 0 else 0)
            elif self.scene.advance is Advance.TIME_STEPS:
                p.step()
        self.frame += 1
        return [p.state() for p in self.panels]


def _newton(problem, guess):
    """x*, the converged minimiser of the step's G, started from whichever of the inertial prediction y
    and ``guess`` (the VBD result) is lower in G: a VBD result that has converged (soft body) puts
    Newton next to the answer; one that has not (stiff body) can be a worse start than y."""
    y = problem.y_with_constraints()
    guess = np.where(problem.free[:, None], guess, problem.constrained_positions)
    start = guess if problem.energy(guess) < problem.energy(y) else y
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)    # reported in the label instead
        result = solver.fast_newton_solve(problem, start, tolerance=NEWTON_TOLERANCE)
    return result.x, result.converged


def _same_body(a, b):
    """Panels whose converged trajectories are identical: only the VBD settings differ."""
    return (a.mesh, a.material, a.fixed, a.kinematic, a.motion) == (b.mesh, b.material, b.fixed, b.kinematic, b.motion)


def _mask(selectors, vertices):
    mask = np.zeros(len(vertices), bool)
    for selector in selectors:
        mask |= selector.select(vertices)
    return mask


def _cm(metres):
    """Whole centimetres, never "-0"."""
    text = f"{100 * metres:.0f}"
    return "0" if text == "-0" else text


def _fraction(dt):
    """1/60 rather than 0.016666."""
    inverse = 1.0 / dt
    return f"1/{inverse:.0f}" if abs(inverse - round(inverse)) < 1e-9 else f"{dt:g}"
