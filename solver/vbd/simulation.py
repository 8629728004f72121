"""Vertex Block Descent time stepping for elastic tet meshes (VBD [Chen et al. 2024], Alg. 1).

One time step of implicit Euler minimises the incremental potential

    G(x) = sum_i m_i / (2 h^2) |x_i - y_i|^2 + sum_tets vol Psi(F),   y = x_n + h v_n + h^2 g,

one vertex at a time: all vertices of one colour are solved in parallel, each by one 3x3 Newton step
on its local energy (lecture notes, chapter 3). `Simulation` holds the state and drives the loop,
which reads like the lecture:

    step():  predict y, pick the initial guess                          (begin_step)
             for each iteration: for each colour: solve that colour      (run_iterations)
             v = (x - x_n) / h                                           (end_step)

The physics lives in free functions beside their numpy twins (`vertex_solve.py`, `physics/`,
`chebyshev.py`, `implicit_euler.py`, `energy.py`), the adjacency in `mesh/topology.py`. The plumbing
is elsewhere: the settings and what each method makes of them in `settings.py`, the device arrays in
`state.py`, the steps of the global methods in `global_methods.py`.
"""
from dataclasses import fields, replace
from difflib import get_close_matches
from typing import Callable, Optional

import numpy as np

from . import energy as energy_kernels
from . import global_methods, implicit_euler, orientation, vertex_solve
from ..backend import as_precision, ensure_taichi, running_on_cpu
from .chebyshev import chebyshev_omega, chebyshev_step, chebyshev_update
from .contact_state import as_contact
from ..errors import ConfigError, VBDError, enum_value
from .implicit_euler import InitialGuess
from ..method import Method, as_method, choose, wave_cells
from ..mesh.coloring import Coloring, VertexOrder, color_vertices
from ..mesh.tetmesh import TetMesh
from ..mesh.topology import Topology, build_topology
from ..physics.ground import Ground
from ..physics.material import Material, vertex_force_hessian
from .settings import Settings, check_method, count, positive
from .state import IterationRecord, SimulationState, SweepArrays
from ..todo import require_implemented

__all__ = ["Ground", "InitialGuess", "IterationRecord", "Settings", "Simulation", "SweepArrays"]

_READ_ONLY = {
    "mesh": "the mesh", "fixed_mask": "the fixed vertices", "kinematic_mask": "the kinematic vertices",
    "free_mask": "the free vertices", "precision": "the float type", "arch": "the backend",
    "coloring": "the colouring", "topology": "the adjacency", "method": "the solver",
    "method_reason": "why the solver was chosen",
}
_GUESS_REPAIR_PASSES = 10   # each pass puts the vertices of newly inverted tets back to x_n; then all


def _index_mask(value, n: int, name: str) -> np.ndarray:
    """A read-only boolean (n,) mask from None, a boolean mask or an index array."""
    mask = np.zeros(n, dtype=bool)
    if value is not None:
        arr = np.asarray(value)
        if arr.dtype == bool:
            if arr.shape != (n,):
                raise ConfigError(f"{name} mask has shape {arr.shape}, expected ({n},) for {n} vertices")
            mask = arr.copy()
        else:
            if arr.size and not np.issubdtype(arr.dtype, np.integer):
                raise ConfigError(f"{name} must be a boolean mask or integer vertex indices, got {arr.dtype}")
            if arr.ndim > 1:
                raise ConfigError(f"{name} vertex indices must be a flat list, got shape {arr.shape}")
            arr = arr.astype(np.int64).ravel()
            if arr.size and (arr.min() < 0 or arr.max() >= n):
                raise ConfigError(f"{name} has vertex indices outside 0..{n - 1}")
            mask[arr] = True
    return mask


def _read_only(mask: np.ndarray) -> np.ndarray:
    mask.flags.writeable = False
    return mask


class Simulation(SimulationState):
    """A VBD simulation of one elastic body.

    mesh: the `TetMesh`; material: its `Material`; fixed: vertices held at their rest position
    (boolean (N,) mask or index array); kinematic: vertices whose positions `kinematic_motion(t, rest)`
    scripts, rest being their (K, 3) rest positions and the result their (K, 3) positions at time t;
    precision: "float64" or "float32"; arch: "cpu", "gpu" or None (the backend Taichi already runs on,
    else the CPU; `sim.arch` then says which of "cpu" and "gpu" runs, after any fallback);
    coloring_order: a `VertexOrder` or its name;
    method: the solver of each step, a `Method` or its name: "vbd" (default), "newton" (projected
    Newton, sparse direct solve), "pcg" (Newton-PCG with VBD's colour sweep as preconditioner),
    "multilevel" (two-level VBD: cycles of 2 sweeps + coarse correction + 2 sweeps), "auto" (chosen
    from N_c, see `method_reason`). The other arguments are the fields of `Settings` (dt in s, gravity
    in m/s^2, iterations, tolerance, check_every, initial_guess, chebyshev_rho, damping in s, ground,
    translation_correction, keep_orientation, kinematic_motion, record_history), where what each one
    means for each method is written down; a setting a method cannot honour raises `ConfigError`;
    contact: a `Contact` between the mesh's bodies (`bodies`, `merge_meshes`) and within one, or None
    (`contact_state.py`; methods "vbd", where Chebyshev skips the vertices that touched this step and
    the translation correction of each free body counts its pairs with other bodies and keeps to the
    bounds, and "newton", frictionless, `settings.py`).

    Live settings, used from the next iteration or step on: every field of `Settings` (`sim.dt = ...`
    or, several at once, `sim.settings = dataclasses.replace(sim.settings, ...)`) and `material` (or
    `set_material`), `contact`. Fixed at construction (assigning raises `ConfigError`): `mesh`, `fixed_mask`,
    `kinematic_mask`, `free_mask`, `precision`, `arch`, `coloring`, `topology`, `method`.

    During a step, `stop_below` is the max_i |f_i| in N at which it stops (None without a tolerance);
    after it, `last_iterations` counts its iterations and `history` holds its `IterationRecord`s.

    Every kernel is shared by all simulations in the process: a second `Simulation` of the same
    mesh compiles nothing and reuses the colouring and the adjacency (`topology`). Initialising Taichi
    again (`ti.init`) frees every array made before: a simulation built before then refuses to step
    (`ConfigError`); build a new one.
    """

    def __init__(self, mesh: TetMesh, material: Material, dt: float = 1 / 60, gravity=(0.0, 0.0, -9.81),
                 fixed=None, iterations: int = 100, initial_guess: InitialGuess = InitialGuess.ADAPTIVE,
                 chebyshev_rho: Optional[float] = None, damping: float = 0.0, ground: Optional[Ground] = None,
                 tolerance: Optional[float] = None, check_every: Optional[int] = None, kinematic=None,
                 kinematic_motion: Optional[Callable] = None, precision="float64", arch: Optional[str] = None,
                 coloring_order: VertexOrder = VertexOrder.NATURAL,
                 translation_correction: bool = True, keep_orientation: bool = False,
                 method=Method.VBD, record_history: bool = False, contact=None):
        if not isinstance(mesh, TetMesh):
            raise ConfigError(f"mesh must be a solver.TetMesh, got {type(mesh).__name__}; "
                              "use solver.load_mesh or solver.box_mesh")
        coloring_order = enum_value(VertexOrder, coloring_order, "coloring_order (solver.VertexOrder)")
        n = mesh.n_vertices
        self.mesh = mesh
        self.precision = as_precision(precision)
        fixed_mask = _index_mask(fixed, n, "fixed")
        kinematic_mask = _index_mask(kinematic, n, "kinematic")
        self.kinematic_mask = _read_only(kinematic_mask)
        self.fixed_mask = _read_only(fixed_mask & ~kinematic_mask)
        self.free_mask = _read_only(~(fixed_mask | kinematic_mask))
        if not self.free_mask.any():
            raise ConfigError("every vertex is fixed or kinematic; nothing is left to simulate")
        settings = Settings(dt=dt, gravity=gravity, iterations=iterations, tolerance=tolerance,
                            check_every=check_every, initial_guess=initial_guess, chebyshev_rho=chebyshev_rho,
                            damping=damping, ground=ground, translation_correction=translation_correction,
                            keep_orientation=keep_orientation, kinematic_motion=kinematic_motion,
                            record_history=record_history)
        if not isinstance(material, Material):
            raise ConfigError(f"material must be a solver.Material, got {type(material).__name__}")
        method = as_method(method)
        self.method_reason = f"method={method.value} was asked for"
        if method is Method.AUTO:
            method, self.method_reason = choose(wave_cells(mesh, material, settings.dt))
            if as_contact(contact) is not None and method is not Method.VBD:
                method, self.method_reason = Method.VBD, f"{self.method_reason}; but 'multilevel' has no contact"
        if method is not Method.VBD:
            global_methods.require_global_solvers()
        self.method = method
        self._check(settings)

        ensure_taichi(arch)
        self.arch = "cpu" if running_on_cpu() else "gpu"
        self._serial_sweep = vertex_solve.serial_sweep(mesh.n_tets, running_on_cpu())
        require_implemented(vertex_force_hessian, vertex_solve.force_hessian, vertex_solve.newton_step)
        self.coloring: Coloring = color_vertices(mesh.tets, n, coloring_order, key=mesh.topology_key())
        self.topology: Topology = build_topology(mesh.vertices, mesh.tets,
                                                 np.where(self.free_mask, self.coloring.colors, -1))
        self._allocate()
        self._material = material
        self.settings = settings
        self.set_material(material)
        self._two_level = None          # the two-level cycle of method="multilevel", built at the first step
        self.history: list[IterationRecord] = []
        self.last_iterations = 0
        self.stop_below: Optional[float] = None
        self.reset()
        self._contact_stage = None
        self.contact = contact
        self._constructed = True

    # -----------------------------------------------------------------------------------------
    # The time step
    # -----------------------------------------------------------------------------------------
    def step(self, n: int = 1) -> None:
        """Advance `n` time steps with the simulation's `method`."""
        self._require_live()
        for _ in range(count(n, "n")):
            if self.method is Method.VBD:
                self.begin_step()
                self.run_iterations(self.iterations)
                self.end_step()
            else:
                global_methods.step(self)

    def begin_step(self) -> None:
        """Save x_n, move kinematic vertices to their targets at t + h, predict y, set the guess, and
        set `stop_below`, the max_i |f_i| in N at which this step stops (None without a tolerance)."""
        self._require_live()
        if self._in_step:
            raise ConfigError("begin_step() called twice; call end_step() first")
        s = self._settings
        if self._n_kinematic:
            self._kin_targets.from_numpy(self._kinematic_targets(self.time + s.dt).astype(self._np_dtype))
        implicit_euler.begin_step(self.state, self._free, self._kin_ids, self._kin_targets, self._n_kinematic,
                                  self._params, s.initial_guess.code, self.dtype, self._serial_sweep)
        if s.keep_orientation:
            for _ in range(_GUESS_REPAIR_PASSES):
                if orientation.undo_inverting_guess(self.state, self._tets, self._free) == 0:
                    break
            else:
                implicit_euler.return_to_start(self.state, self._serial_sweep)     # x_n: upright wherever it was
        if self._contact_stage is not None:                     # bounds at x_n, the guess clamped to them
            self._contact_stage.begin_step(self.state, self._adjacency[0], self._kin_ids, self._kin_targets,
                                           self._n_kinematic)
        self._in_step = True
        self._iteration = 0
        self._omega = 1.0
        self.last_iterations = 0
        self.history = []
        self.stop_below = None
        if s.tolerance is not None:
            weight = self._max_mass * float(np.linalg.norm(self._gravity))
            eps = np.finfo(self._np_dtype).eps
            roundoff = 100 * eps * self._material.mu * float(np.mean(self._rest_vol)) ** (2 / 3)
            self.stop_below = max(s.tolerance * max(self.max_residual(), weight), roundoff)
        if s.record_history:
            self.history.append(IterationRecord(0, self.energy(), self.max_residual()))

    def run_iterations(self, k: int) -> int:
        """Run up to `k` VBD iterations of the current step; returns how many ran. With method="vbd", stop
        once max_i |f_i| <= `stop_below`, checked every `check_every` iterations."""
        self._require_live()
        if not self._in_step:
            raise ConfigError("run_iterations() needs begin_step() first")
        s = self._settings
        color_order, offsets, others, adj_f, color_starts = self._adjacency
        check = self.stop_below is not None and self.method is Method.VBD
        ran = 0
        for _ in range(count(k, "k")):
            self._iteration += 1
            if s.chebyshev_rho is not None:
                self._omega = chebyshev_omega(self._iteration, s.chebyshev_rho, self._omega)
            if self._contact_stage is not None:      # Jacobi contact inside a colour; no Chebyshev where touched
                self._contact_stage.iterate(self.state, self._mass, self._adjacency, self._params, self.n_colors,
                                            self.dtype, None if s.chebyshev_rho is None else self._omega)
            else:
                n_colors = vertex_solve.unrolled_colors(self.n_colors, self._serial_sweep)
                vertex_solve.vbd_iteration(self.state, self._mass, color_order, offsets, others, adj_f, color_starts,
                                           self._params, n_colors, self.dtype, self._serial_sweep)
                if s.chebyshev_rho is not None:
                    chebyshev_step(self.state, color_order, self._omega, self.dtype, self._serial_sweep)
            ran += 1
            if s.record_history:
                self.history.append(IterationRecord(self._iteration, self.energy(), self.max_residual()))
            if check and self._iteration % s.vbd_check_every == 0 and self.max_residual() <= self.stop_below:
                break
        self.last_iterations = self._iteration
        return ran

    def end_step(self) -> None:
        """The translation correction (each body without fixed or kinematic vertices, `translation.py`),
        v = (x - x_n) / h, advance the clock. A step that diverged raises `VBDError` and leaves the
        simulation at x_n, as before the step."""
        if not self._in_step:
            raise ConfigError("end_step() needs begin_step() first")
        if self._settings.translation_correction and self._body_translation.any:
            self._body_translation.apply(self.state, self._mass, self._adjacency, self._params, self._contact_stage,
                                         self.dtype)
            if self._mesh_translation is not None:      # the bodies' forces sum to zero again: momentum kept
                self._mesh_translation.apply(self.state, self._mass, self._adjacency, self._params, None, self.dtype)
        moved = implicit_euler.largest_displacement(self.state, self._serial_sweep)
        size = self._size
        if not moved <= 10 * size:
            implicit_euler.return_to_start(self.state, self._serial_sweep)
            self._in_step = False
            what = "non-finite positions" if not np.isfinite(moved) else f"a vertex moved {moved:.3g} m in one step"
            hint = ("lower chebyshev_rho (or switch it off)" if self.chebyshev_rho is not None
                    else "use a smaller dt, more iterations, or a softer material")
            if self._contact_stage is not None:
                hint += (f" (with contact: a smaller radius or stiffness; surfaces that start within the radius, "
                         f"{self._contact_stage.contact.radius:g} m, are pushed apart at once)")
            raise VBDError(f"the step diverged ({what}, body size {size:.3g} m); {hint}. "
                           "The simulation is back at the start of the step.")
        implicit_euler.end_step(self.state, self._params, self._serial_sweep)
        self._in_step = False
        self.time += self._settings.dt
        self.frame += 1

    def solve_color(self, c: int) -> None:
        """Solve the vertices of colour c once (part of an iteration; for plots of one colour sweep)."""
        if not self._in_step:
            raise ConfigError("solve_color() needs begin_step() first")
        if self._contact_stage is not None:
            raise ConfigError("solve_color() runs the sweep without contact; use run_iterations() with contact")
        if isinstance(c, bool) or not isinstance(c, (int, np.integer)) or not 0 <= c < self.n_colors:
            raise ConfigError(f"colour must be an integer in 0..{self.n_colors - 1}, got {c!r}")
        color_order, offsets, others, adj_f, _ = self._adjacency
        start, end = self.topology.color_ranges[c]
        vertex_solve.vbd_color(self.state, self._mass, color_order, offsets, others, adj_f, self._params,
                               start, end, self.dtype, self._serial_sweep)

    def _kinematic_targets(self, t: float) -> np.ndarray:
        shape = self._kinematic_rest.shape
        try:
            moved = self.kinematic_motion(t, self._kinematic_rest.copy())
        except TypeError as err:        # its own errors of other kinds are the caller's to read
            raise ConfigError(f"kinematic_motion(t, rest) raised TypeError ({err}); it must take the time t in s "
                              f"and the rest positions {shape} and return the targets") from err
        try:
            target = np.asarray(moved, dtype=np.float64)
        except (TypeError, ValueError):
            raise ConfigError(f"kinematic_motion must return an array of numbers of shape {shape}") from None
        if target.shape != shape:
            raise ConfigError(f"kinematic_motion must return positions of shape {shape}, got {target.shape}")
        if not np.isfinite(target).all():
            raise ConfigError(f"kinematic_motion returned NaN or infinite positions at t = {t:.4g} s; "
                              "it must return finite positions")
        return target

    # -----------------------------------------------------------------------------------------
    # Measurements
    # -----------------------------------------------------------------------------------------
    def energy(self) -> float:
        """Incremental potential G(x) in J at the current positions, for the current step's y.

        Damping and friction are not potentials and are not included.
        """
        G = float(energy_kernels.incremental_potential(self.state, self._mass, self._free, self._tets,
                                                       self._Dm_inv, self._volume, self._params, self._serial_sweep))
        if self._contact_stage is not None:
            G += self._contact_stage.energy(self.state, self.dtype)     # + E_c
        return G

    def _local_systems(self) -> float:
        color_order, offsets, others, adj_f, _ = self._adjacency
        largest = float(vertex_solve.local_systems(self.state, self._mass, color_order, offsets, others, adj_f,
                                                   self._params, self._f, self._H, self.dtype, self._serial_sweep))
        if self._contact_stage is not None:                      # + the contact pairs' terms
            largest = self._contact_stage.add_local_systems(self.state, color_order, self._params, self._f,
                                                            self._H, self.dtype)
        return largest

    def residual(self) -> np.ndarray:
        """(N, 3) float64 per-vertex force residual f_i = -dG/dx_i (0 at fixed/kinematic vertices)."""
        self._local_systems()
        return self._f.to_numpy().astype(np.float64)

    def local_systems(self):
        """Per-vertex f_i (N, 3) and H_i (N, 3, 3) at the current positions (zero at constrained
        vertices): the 3x3 system each vertex solves, for plots and tests."""
        self._local_systems()
        return self._f.to_numpy().astype(np.float64), self._H.to_numpy().astype(np.float64)

    def max_residual(self) -> float:
        """max_i |f_i| in newtons."""
        return self._local_systems()

    def inverted_count(self) -> int:
        """Number of tets with det F <= 0 (inverted or flat) at the current positions."""
        return int(orientation.count_inverted(self.state, self._tets))

    def inertial_target(self) -> np.ndarray:
        """(N, 3) y = x_n + h v_n + h^2 g for a step taken from the current state."""
        return self.positions + self.dt * self.velocities + self.dt ** 2 * self._gravity

    def step_problem(self):
        """The minimisation the next `step()` solves, as a `StepProblem` for the Newton reference."""
        global_methods.require_global_solvers()
        from ..newton.oracle import StepProblem

        if self._in_step:
            raise ConfigError("step_problem() is defined between steps; call end_step() first")
        x = self.positions
        targets = x.copy()
        if self.kinematic_mask.any():
            targets[self.kinematic_mask] = self._kinematic_targets(self.time + self.dt)
        if self.damping > 0 or (self.ground is not None and self.ground.friction > 0):
            raise ConfigError("the Newton reference minimises G, which has no damping or friction; "
                              "set damping=0 and ground friction=0 to compare against it")
        return StepProblem(tets=self.mesh.tets, grad_rows=self._grad_rows, volumes=self._rest_vol,
                           masses=self.masses, y=self.inertial_target(), free=self.free_mask.copy(),
                           constrained_positions=targets, h=self.dt, mu=self._material.mu,
                           lam=self._material.lam, ground=self.ground, contact=self._contact_term())

    def newton_reference(self, tolerance: float = 1e-10, max_iterations: int = 50, x0=None) -> np.ndarray:
        """(N, 3) converged global Newton solution x* of the next step, from the current state.

        x0: (N, 3) start of the Newton iterations (default y; x_n with contact, since y may lie across a
        body, solved by the numpy `newton_solve`: the reference that method="newton", its Taichi twin, is
        checked against); the simulation itself is not changed.
        To measure a VBD step cheaply, build `problem = sim.step_problem()` before `sim.step()` and
        warm-start `solver.fast_newton_solve(problem, sim.positions)` after it. Solved by the Taichi
        Newton (`global_newton`); `solver.newton_solve` is its independent numpy twin.
        """
        from ..newton.direct import fast_newton_solve
        from ..newton.oracle import newton_solve

        tolerance = positive(tolerance, "tolerance", "(relative)")
        max_iterations = count(max_iterations, "max_iterations")
        problem = self.step_problem()
        if problem.contact is not None:
            start = problem.constrained_positions if x0 is None else self._checked_state(x0, "x0")
            return newton_solve(problem, start, tolerance, max_iterations).x
        start = problem.y_with_constraints() if x0 is None else self._checked_state(x0, "x0")
        return fast_newton_solve(problem, start, tolerance, max_iterations).x

    # -----------------------------------------------------------------------------------------
    # Settings: every live setting goes through `settings` (validated by `Settings`, checked
    # against the method by `check_method`)
    # -----------------------------------------------------------------------------------------
    @property
    def settings(self) -> Settings:
        """The live `Settings`; assign a new one (e.g. `dataclasses.replace(sim.settings, ...)`)."""
        return self._settings

    @settings.setter
    def settings(self, settings: Settings):
        if not isinstance(settings, Settings):
            raise ConfigError(f"settings must be a solver.Settings, got {type(settings).__name__}")
        self._check(settings)
        self._settings = settings
        self._gravity = np.array(settings.gravity)
        self._gravity.flags.writeable = False
        self._upload_params(settings, self._material)

    def _check(self, settings: Settings) -> None:
        check_method(settings, self.method)
        if settings.kinematic_motion is None and self.kinematic_mask.any():
            raise ConfigError("kinematic vertices need kinematic_motion(t, rest) -> (K, 3) positions")
        if settings.chebyshev_rho is not None:
            require_implemented(chebyshev_omega, chebyshev_update)

    @property
    def gravity(self) -> np.ndarray:
        """(3,) gravitational acceleration g in m/s^2 (read-only array; assign a new one)."""
        return self._gravity

    @gravity.setter
    def gravity(self, value):
        self.settings = replace(self._settings, gravity=value)

    @property
    def material(self) -> Material:
        """The body's `Material`; assigning one changes E, nu and density without rebuilding anything."""
        return self._material

    @material.setter
    def material(self, material):
        self.set_material(material)

    def set_material(self, material: Material) -> None:
        """Change E, nu and density without rebuilding anything."""
        if not isinstance(material, Material):
            raise ConfigError(f"material must be a solver.Material, got {type(material).__name__}")
        self._material = material
        self._upload_masses(material.density)
        self._upload_params(self._settings, material)

    @property
    def wave_cells(self) -> float:
        """N_c = h sqrt(E / rho) / dx: cells an elastic wave crosses in one step (`method.wave_cells`)."""
        return wave_cells(self.mesh, self._material, self.dt)

    def __setattr__(self, name, value):
        if getattr(self, "_constructed", False):
            if name in _READ_ONLY:
                raise ConfigError(f"Simulation.{name} ({_READ_ONLY[name]}) is fixed at construction; "
                                  f"build a new Simulation with the {name} you want")
            if not name.startswith("_") and name not in self.__dict__ and not hasattr(type(self), name):
                close = get_close_matches(name, [n for n in dir(self) if not n.startswith("_")], n=1)
                hint = f"did you mean {close[0]!r}?" if close else "its live settings are the fields of solver.Settings"
                raise ConfigError(f"Simulation has no setting {name!r}; {hint}")
        super().__setattr__(name, value)


def _live(name: str) -> property:
    def get(self):
        return getattr(self._settings, name)

    def set(self, value):
        self.settings = replace(self._settings, **{name: value})

    return property(get, set, doc=f"The live setting `Settings.{name}` (its meaning per method: `vbd/settings.py`); "
                                  "assigning it replaces `settings`, validated and checked against the method.")


for _field in fields(Settings):      # sim.dt, sim.iterations, ...: one property per field of Settings
    if _field.name != "gravity":
        setattr(Simulation, _field.name, _live(_field.name))
