"""Turn a ``Scene`` into running simulations and, frame by frame, into what should be drawn."""
import dataclasses
import enum
import time
import warnings
from dataclasses import dataclass

import numpy as np

import solver
from solver.method import multilevel_cycles

from . import colors
from .errors import DemoError
from .scenes import PROBE_MOVED, Advance, ColorBy, Sweep

# The one Newton policy of the demo, that of Simulation(method="newton"), which advances the trajectory
# ghost: stop once the step is below 1e-8 of the body size, at most 50 iterations (`newton_cap`: twice as
# many with contact). x*, the reference of one VBD step, is solved with the same numbers from a warm start
# (the VBD result or y).
NEWTON_TOLERANCE = 1e-8
NEWTON_ITERATIONS = 50
DRIFT_SHOWN = 0.01      # m: a sideways drift of the centre of mass below this is not labelled
PROBE_RGB = (0.95, 0.10, 0.85)
UNSOLVED_RGB = (0.82, 0.82, 0.84)   # vertices the current iteration has not reached yet (Advance.COLOURS)


class GhostMode(enum.Enum):
    """What the translucent ghost of a panel shows."""

    TRAJECTORY = "trajectory"   # the converged implicit-Euler trajectory, advanced by Newton every step
    STEP = "step"               # x*, the converged Newton solution of the step VBD is taking now


@dataclass
class PanelState:
    """One panel after a frame: what to draw, what the label says, and the measured results as numbers
    (read these, never the label text)."""

    positions: np.ndarray   # (N, 3) m
    faces: np.ndarray       # (F, 3) boundary triangles
    rgb: np.ndarray         # (N, 3) vertex colours in [0, 1]
    ghost: np.ndarray       # (N, 3) reference positions, or None
    lines: list             # label lines
    error: float            # relative error of this step against its Newton solution x*, or None
    trajectory_gap: float = None    # m: max_i |x_i - ghost_i| against the converged trajectory, or None
    gap_fraction: float = None      # trajectory_gap over the body's longest side ("off the ghost ... %")
    budget: str = ""                # the solver of a step, e.g. "plain VBD, 140 iterations"
    step_ms: float = None           # median wall time of the panel's steps so far (ms), when it shows it
    newton_converged: bool = True   # False: a Newton solve behind the ghost or x* hit its iteration cap
    wave_cells: float = None        # N_c = h sqrt(E / rho) / dx of the panel's settings
    probe_moved_at: int = None      # the iteration at which the probe vertex first moved, or None


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
    same step from the same state (warm-started at the VBD result or at y, whichever is lower in G):
    ``error`` = ||x - x*|| / ||x* - x_n||. In ``GhostMode.TRAJECTORY`` (time-step scenes) the ghost is
    ``reference``, a ``solver.Simulation(method="newton")`` with the panel's settings stepped beside
    it: what implicit Euler does with an exact solver. In ``GhostMode.STEP`` (iteration-by-iteration
    scenes and the interactive window) the ghost is x*.
    """

    def __init__(self, scene, panel, arch="cpu", ghost_mode=None):
        self.scene, self.panel = scene, panel
        mesh = panel.mesh.build()
        self.faces = np.ascontiguousarray(mesh.boundary_faces(), dtype=np.int32)
        self.tets = np.asarray(mesh.tets)
        self.ghost_enabled = panel.newton_ghost
        if ghost_mode is None:
            ghost_mode = GhostMode.TRAJECTORY if scene.advance is Advance.TIME_STEPS else GhostMode.STEP
        self.ghost_mode = GhostMode(ghost_mode)
        fixed = _mask(panel.fixed, mesh.vertices)
        kinematic = _mask(panel.kinematic, mesh.vertices)
        self._settings = dict(
            mesh=mesh, material=panel.material, dt=scene.dt, gravity=scene.gravity,
            fixed=fixed if fixed.any() else None, iterations=panel.iterations,
            initial_guess=panel.initial_guess, chebyshev_rho=panel.chebyshev_rho,
            damping=scene.damping, ground=scene.ground,
            kinematic=kinematic if kinematic.any() else None,
            kinematic_motion=panel.motion if kinematic.any() else None, keep_orientation=panel.keep_orientation,
            method=panel.method, contact=panel.contact, arch=arch)
        self.sim = solver.Simulation(**self._settings)
        self.body_rgb = colors.per_body(self.sim.bodies, fixed | kinematic)
        self.scene_settings = self.settings
        self.rest = mesh.vertices
        self.tip = mesh.vertices[:, 0] >= mesh.vertices[:, 0].max() - 1e-9     # the far end face
        self.length = float(np.ptp(mesh.vertices, axis=0).max())               # m, the body's longest side
        self.rest_tip_height = float(mesh.vertices[self.tip, 2].mean())
        self.probe = _nearest_vertex(panel.probe, mesh.vertices, scene.camera.eye)
        self.matched_ratio = None   # same_wall_time_as: this panel's step time over the other's, timed at start
        self.reference = None       # the trajectory ghost's Simulation(method="newton"), built on first use
        self.reference_source = None    # an earlier panel whose trajectory ghost is this one's too
        self.reset()

    def reset(self):
        self.sim.reset()
        if self.panel.velocity is not None:
            self.sim.set_velocities(self.panel.velocity(self.sim.bodies))
        if self.reference is not None:
            self.reference.reset()
        self.reference_synced = self.reference is not None
        self.start = self.sim.positions     # x_n, the positions at the start of the current step
        self.ghost = None
        self.error = None
        self.error_converged = True
        self.ghost_converged = True
        self.iteration = 0
        self.colours_done = 0       # Advance.COLOURS: colour sets solved in the current iteration
        self.probe_moved_at = None
        self.in_step = False
        self.failure = None         # why this panel stopped (it diverged), or None while it runs
        self.step_seconds = []      # wall time of every solver step since the reset (s)

    @property
    def newton_iterations(self) -> int:
        """The cap of this panel's Newton solves (`newton_cap`)."""
        return newton_cap(self.panel.contact is not None)

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
        self.probe_moved_at = None
        problem = self.sim.step_problem() if self.ghost_enabled else None
        if self.ghost_enabled and self.ghost_mode is GhostMode.TRAJECTORY and not self._shares_reference_next():
            self._sync_reference()
        started = time.perf_counter()
        if not self._guarded(self._solve_step):
            self.ghost, self.error = None, None
            return
        self.step_seconds.append(time.perf_counter() - started)
        self.iteration = self.sim.iterations
        self._watch_probe()
        if problem is None:
            self.ghost, self.error = None, None
            # a step without the reference breaks its trajectory: when the ghost is switched back on,
            # the reference restarts from the body's state then (so its first ghost is x* of that step)
            self.reference_synced = False
            return
        x_star, self.error_converged = _newton(problem, self.sim.positions)
        self.error = solver.relative_error(self.sim.positions, x_star, self.start)
        if self.ghost_mode is not GhostMode.TRAJECTORY:
            self.ghost, self.ghost_converged = x_star, self.error_converged
        elif self._shares_reference():
            self.ghost, self.ghost_converged = self.reference_source.ghost, self.reference_source.ghost_converged
        else:
            self.ghost = self._advance_reference()

    def _solve_step(self):
        """One time step of the panel's solver; a Jacobi panel runs its own sweeps between the
        simulation's begin_step and end_step."""
        if self.panel.sweep is Sweep.GAUSS_SEIDEL or self.sim.method is not solver.Method.VBD:
            self.sim.step()
            return
        self.sim.begin_step()
        self._jacobi(self.sim.iterations)
        self.sim.end_step()

    def _jacobi(self, count):
        """``count`` Jacobi iterations: every free vertex solves its 3x3 system H_i dx_i = f_i at once,
        all from the positions of the previous iteration (VBD's vertex solve without the colouring)."""
        sim, free = self.sim, self.sim.free_mask
        for _ in range(count):
            f, H = sim.local_systems()
            x = sim.positions
            x[free] += np.linalg.solve(H[free], f[free][..., None])[..., 0]
            if not np.isfinite(x).all():    # end_step reports the divergence and returns to x_n
                break
            sim.set_positions(x)

    def _run_iterations(self, count):
        if self.panel.sweep is Sweep.JACOBI:
            self._jacobi(count)
        else:
            self.sim.run_iterations(count)

    def _timed_step(self):
        """Wall time (s) of one time step of this panel's solver from its current state, to which the
        simulation returns afterwards."""
        saved = self.sim.save_state()
        started = time.perf_counter()
        self._solve_step()
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
        n2 = n1 / ratio(n1), then solved for a + b n = 1 (n2 if the measurements give no positive slope);
        the ratio at the chosen budget is measured once more (``matched_ratio``)."""
        n1 = self.sim.iterations
        r1 = self.relative_step_time(other)
        n2 = max(1, int(round(n1 / r1)))
        self.sim.iterations = n2
        r2 = self.relative_step_time(other)
        if n2 != n1 and (r2 - r1) / (n2 - n1) > 0:
            b = (r2 - r1) / (n2 - n1)
            self.sim.iterations = max(1, int(round(n2 + (1.0 - r2) / b)))
        self.matched_ratio = self.relative_step_time(other)
        self.scene_settings = self.settings

    def budget_line(self):
        """What the solver of a step does, e.g. "plain VBD, 140 iterations" or "two-level VBD, 5 cycles"."""
        sim = self.sim
        if sim.method is solver.Method.MULTILEVEL:
            return f"two-level VBD, {multilevel_cycles(sim.iterations)} cycles"
        if sim.method is solver.Method.PCG:
            return "Newton-PCG to convergence"
        if sim.method is solver.Method.NEWTON:
            return "Newton to convergence"
        if self.panel.show_step_time:
            return f"plain VBD, {sim.iterations} iterations"
        return f"{sim.iterations} iterations"

    def step_ms(self):
        """Median measured wall time per step (ms) when the panel shows it, else None."""
        if self.panel.show_step_time and self.step_seconds:
            return 1e3 * float(np.median(self.step_seconds))
        return None

    def _guarded(self, advance):
        """Run ``advance()``; a diverging body stops this panel with a message (``failure``, shown in its
        label) instead of ending the program. Returns True while the panel runs."""
        try:
            advance()
        except solver.VBDError as e:      # the solver's divergence guard says what diverged and what to change
            self.failure = f"stopped at t = {self.sim.time:.2f} s: {e} Reset to run again."
            self.in_step = False
        return self.failure is None

    def _shares_reference_next(self):
        src = self.reference_source
        return src is not None and src.ghost_enabled and src.ghost_mode is GhostMode.TRAJECTORY

    def _shares_reference(self):
        """True when an earlier panel with the same body, material and time step already advanced the
        converged trajectory this frame (the iteration budget does not change a converged solve)."""
        src = self.reference_source
        return (src is not None and src.ghost_enabled and src.ghost_mode is GhostMode.TRAJECTORY
                and src.ghost is not None and src.sim.frame == self.sim.frame and src.sim.dt == self.sim.dt
                and src.sim.material == self.sim.material)

    def _sync_reference(self):
        """Start the reference trajectory from the current state (first use, or after a reset)."""
        if self.reference is None:
            self.reference = solver.Simulation(**{**self._settings, "method": solver.Method.NEWTON,
                                                  "iterations": self.newton_iterations})
        if not self.reference_synced:
            self.reference.reset()
            self.reference.set_positions(self.sim.positions)
            self.reference.set_velocities(self.sim.velocities)
            self.reference.time, self.reference.frame = self.sim.time, self.sim.frame
            self.reference_synced = True

    def _advance_reference(self):
        """One step of the reference (Newton to convergence) from its own state; returns its positions."""
        self._sync_reference()      # a no-op unless the reference has never run (or was reset)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)    # an unconverged solve is said in the label
            self.reference.step()
        self.ghost_converged = self.reference.last_iterations < self.newton_iterations
        return self.reference.positions

    def _open_step(self):
        """Begin an iteration-by-iteration time step, with x* as its ghost when enabled."""
        self.start = self.sim.positions
        self.ghost = None
        if self.ghost_enabled:
            problem = self.sim.step_problem()
            self.ghost, self.ghost_converged = _newton(problem, problem.y_with_constraints())
        self.sim.begin_step()
        self.iteration = 0
        self.colours_done = 0
        self.probe_moved_at = None
        self.in_step = True

    def iterate(self, count=1):
        """``count`` more iterations of the current time step (opening one if needed)."""
        if self.failure is not None:
            return
        if not self.in_step:
            self._open_step()
        if count:
            if not self._guarded(lambda: self._run_iterations(count)):
                self.error = None
                return
            self.iteration += count
        self._watch_probe()
        self._measure()

    def solve_next_colour(self):
        """Solve the next colour set of the current iteration (opening a time step if needed)."""
        if self.failure is not None:
            return
        if not self.in_step:
            self._open_step()
        if self.colours_done == self.sim.n_colors:
            self.colours_done = 0
        self.sim.solve_color(self.colours_done)
        self.colours_done += 1
        if self.colours_done == self.sim.n_colors:
            self.iteration += 1
        self._measure()

    def finish_step(self):
        """Close a time step opened by ``iterate``."""
        if self.in_step:
            self.in_step = False
            # the reference trajectory no longer starts where the body is
            self.reference_synced = False
            self._guarded(self.sim.end_step)

    def _measure(self):
        self.error = None
        if self.ghost is not None:
            self.error = solver.relative_error(self.sim.positions, self.ghost, self.start)
            self.error_converged = self.ghost_converged

    def _watch_probe(self):
        if self.probe is not None and self.probe_moved_at is None:
            if np.linalg.norm(self.sim.positions[self.probe] - self.start[self.probe]) > PROBE_MOVED:
                self.probe_moved_at = self.iteration

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

    def vertex_rgb(self, color_by):
        """(N, 3) vertex colours for ``color_by`` (a ``ColorBy``), the probe vertex highlighted: the one
        colour path of the headless frames and the window."""
        x = self.sim.positions
        lo_hi = self.scene.color_range
        if color_by is ColorBy.DISPLACEMENT:
            rgb = colors.sequential(colors.normalise(np.linalg.norm(x - self.start, axis=1), *lo_hi, log=True))
        elif color_by is ColorBy.RESIDUAL:
            rgb = colors.sequential(colors.normalise(np.linalg.norm(self.sim.residual(), axis=1), *lo_hi, log=True))
        elif color_by is ColorBy.COLOR_SETS:
            c = self.sim.colors
            rgb = colors.categorical(c)
            if self.scene.advance is Advance.COLOURS:
                rgb[c >= self.colours_done] = UNSOLVED_RGB
        else:
            rgb = self.body_rgb.copy()
        if self.probe is not None:
            rgb[self.probe] = PROBE_RGB
        return rgb

    def state(self, color_by=None):
        """This panel's ``PanelState``, coloured by ``color_by`` (default: the scene's)."""
        by = self.scene.color_by if color_by is None else color_by
        x = self.sim.positions
        rgb = self.vertex_rgb(by)
        lines = [self.label]
        wave_cells = self.sim.wave_cells
        n_c = f", N_c = {wave_cells:.0f}" if self.panel.show_wave_cells else ""
        if self.scene.advance is Advance.COLOURS:
            lines.append(self._colour_line() + n_c)
        elif self.scene.advance is Advance.ITERATIONS:
            lines.append(f"iteration {self.iteration}{n_c}")
        elif by is not ColorBy.COLOR_SETS:
            budget = self.budget_line()
            ms = self.step_ms()
            timed = f" = {ms:.0f} ms/step" if ms is not None else ""
            lines.append(f"{budget}{timed}{n_c}, dt = {_fraction(self.sim.dt)} s, t = {self.sim.time:.2f} s")
        if by is ColorBy.COLOR_SETS and self.scene.advance is not Advance.COLOURS:
            lines.append(f"{self.sim.n_colors} colours for {len(x)} vertices")
        if self.matched_ratio is not None:
            k = self.panel.same_wall_time_as
            lines.append(f"at the start its step timed {self.matched_ratio:.2f}x panel {k + 1}'s (median of 7 pairs)")
        gap = fraction = None
        if self.ghost is not None and self.ghost_mode is GhostMode.TRAJECTORY:
            tip = self.tip
            drop = lambda p: float(self.rest_tip_height - p[tip, 2].mean())
            if self.panel.contact is None:      # a bending bar's measure; bodies in contact have no tip
                lines.append(f"tip drop {_cm(drop(x))} cm (ghost {_cm(drop(self.ghost))} cm)")
            # the error that has built up over all steps so far: what the audience sees
            gap = float(np.linalg.norm(x - self.ghost, axis=1).max())
            fraction = gap / self.length
            lines.append(f"off the ghost by {_cm(gap)} cm = {fraction:.0%} of its length")
        if self.error is not None:
            unsure = ("" if self.error_converged
                      else f" (x* approximate: Newton stopped at its {self.newton_iterations}-iteration cap)")
            # three decimals read well down to 0.01; below, where only the remedies get, the exponent
            shown = f"{self.error:.3f}" if self.error >= 0.01 else f"{self.error:.1e}"
            lines.append(f"relative error {shown}{unsure}")
        if self.ghost is not None and self.ghost_mode is GhostMode.TRAJECTORY and not self.ghost_converged:
            lines.append(f"ghost approximate this step: Newton stopped at its {self.newton_iterations}-iteration cap")
        if self.probe is not None:
            lines.append(self._probe_line())
        if self.panel.show_inverted:
            lines.append(f"inverted tets: {self.sim.inverted_count()}")
        contact = [self._contact_line()] if self.panel.contact is not None else []
        if self.panel.show_momentum:     # on the contact line, which keeps the label within its rows
            p = self.sim.masses @ self.sim.velocities
            contact.append(f"momentum |sum m v| = {np.linalg.norm(p):.1e} kg m/s")
        if contact:
            lines.append("; ".join(contact))
        lines += self.remarks()
        converged = self.error_converged and (self.ghost is None or self.ghost_converged)
        return PanelState(x, self.faces, rgb, self.ghost, lines, self.error, gap, gap_fraction=fraction,
                          budget=self.budget_line(), step_ms=self.step_ms(), newton_converged=converged,
                          wave_cells=wave_cells, probe_moved_at=self.probe_moved_at)

    def _contact_line(self):
        """The contact pairs closer than the radius and the closest pair's distance (under the query radius)."""
        gap = self.sim.min_separation()
        shown = f"closest gap {1000 * gap:.2f} mm" if np.isfinite(gap) else "nothing within the query radius"
        return f"contacts: {self.sim.contact_count()}, {shown}"

    def _colour_line(self):
        n = self.sim.n_colors
        if not self.in_step or self.colours_done == 0:
            return f"iteration {self.iteration + 1}: no colour solved yet ({n} colours)"
        c = self.colours_done - 1
        count = int(np.count_nonzero(self.sim.colors == c))
        iteration = self.iteration + (self.colours_done < n)
        return f"iteration {iteration}: colour {c + 1} of {n} solved, {count} vertices at once"

    def _probe_line(self):
        moved = float(np.linalg.norm(self.sim.positions[self.probe] - self.start[self.probe]))
        if self.probe_moved_at is None:
            return f"probe (magenta): not moved yet (threshold {PROBE_MOVED:g} m)"
        return f"probe (magenta): first moved at iteration {self.probe_moved_at}; moved {1e3 * moved:.3g} mm now"


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

    def state(self, color_by=None):
        by = self.scene.color_by if color_by is None else color_by
        if by is ColorBy.COLOR_SETS:
            rgb = colors.categorical(self.colors)
            lines = [self.panel.label, f"{self.n_colors} colours for {len(self.start)} vertices"]
        else:
            rgb, lines = colors.uniform(len(self.start)), [self.panel.label]
        return PanelState(self.start, self.faces, rgb, None, lines, None)


def refuse_overrides(scene, live=False, youngs_modulus=None, iterations=None, dt=None):
    """A one-line `DemoError` where `scene` has nothing for one of these settings (None: not given) to
    change: a rest scene (unless live, simulated in the window), or iterations in a scene that shows one
    iteration or one colour per frame. Checked before anything is built or written."""
    if (youngs_modulus, iterations, dt) == (None, None, None):
        return
    if scene.advance is Advance.REST and not live:
        raise DemoError(f"scene {scene.name!r} shows the rest shape; it has no material, iterations or dt to change")
    if iterations is not None and scene.advance in (Advance.ITERATIONS, Advance.COLOURS):
        raise DemoError(f"scene {scene.name!r} shows one {scene.advance.value[:-1]} per frame, so --iterations has "
                        "nothing to change; pass --frames for more of them")


class SceneRunner:
    """All panels of a scene, the one frame loop of the headless frames and the interactive window:
    ``advance()`` produces the next frame's panel states; ``step``, ``iterate`` and ``states`` are its
    parts for a viewer that advances only while playing."""

    def __init__(self, scene, arch="cpu", ghost_mode=None, live=False):
        """live: simulate every panel even in an ``Advance.REST`` scene (the window lets it move)."""
        self.scene = scene
        self.color_by = scene.color_by
        self.frame = 0
        if scene.advance is Advance.REST and not live:
            solver.ensure_taichi(arch)
            self.panels = [RestPanel(scene, panel) for panel in scene.panels]
            return
        self.panels = [PanelSim(scene, panel, arch, ghost_mode) for panel in scene.panels]
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

    def override(self, youngs_modulus=None, iterations=None, dt=None):
        """Run every panel with these settings instead of the scene's (None keeps a setting); each
        panel's label then names its settings."""
        fields = {k: v for k, v in dict(youngs_modulus=youngs_modulus, iterations=iterations, dt=dt).items()
                  if v is not None}
        refuse_overrides(self.scene, live=all(isinstance(p, PanelSim) for p in self.panels), **fields)
        for p in self.panels if fields else ():
            p.apply(dataclasses.replace(p.settings, **fields))

    def step(self):
        """Every panel one frame further: a time step, an iteration or a colour set, as the scene advances."""
        for p in self.panels:
            if self.scene.advance is Advance.ITERATIONS:
                p.iterate(1)
            elif self.scene.advance is Advance.COLOURS:
                p.solve_next_colour()
            elif isinstance(p, PanelSim):       # time steps (the window also moves a rest scene's bodies)
                p.step()

    def iterate(self, count=1):
        """``count`` more iterations of every panel's current time step."""
        for p in self.panels:
            p.iterate(count)

    def reset(self):
        for p in self.panels:
            p.reset()
        self.frame = 0

    def states(self):
        """The panels' states now, coloured by ``color_by``."""
        return [p.state(self.color_by) for p in self.panels]

    def advance(self):
        """The next frame: the first one of a step-by-parts scene shows the opened step, nothing solved."""
        if self.frame == 0 and self.scene.advance in (Advance.ITERATIONS, Advance.COLOURS):
            for p in self.panels:
                p.iterate(0)
        else:
            self.step()
        self.frame += 1
        return self.states()


def newton_cap(contact: bool) -> int:
    """The demo Newton's iteration cap: NEWTON_ITERATIONS, twice that with contact, where a Newton step is
    cut short once one vertex would pass its bound (the head_on balls take 10-60 iterations a step, where
    a body without contact takes under 10)."""
    return 2 * NEWTON_ITERATIONS if contact else NEWTON_ITERATIONS


def _newton(problem, guess):
    """(x*, converged): the minimiser of the step's G by the demo's Newton policy, started from whichever
    of the inertial prediction y and ``guess`` (the VBD result) is lower in G: a VBD result that has
    converged (soft body) puts Newton next to the answer; one that has not (stiff body) can be a worse
    start than y. With contact always from ``guess``, whose bodies are apart (y may lie across a body,
    where G has a lower, wrong minimum)."""
    y = problem.y_with_constraints()
    guess = np.where(problem.free[:, None], guess, problem.constrained_positions)
    start = guess if problem.contact is not None or problem.energy(guess) < problem.energy(y) else y
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)    # reported in the label instead
        result = solver.fast_newton_solve(problem, start, tolerance=NEWTON_TOLERANCE,
                                          max_iterations=newton_cap(problem.contact is not None))
    return result.x, result.converged


def _nearest_vertex(selectors, vertices, point):
    """The selected vertex nearest ``point`` (the camera, so that it is in sight), or None without selectors."""
    if not selectors:
        return None
    chosen = np.flatnonzero(_mask(selectors, vertices))
    return int(chosen[np.argmin(np.linalg.norm(vertices[chosen] - np.asarray(point, float), axis=1))])


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
