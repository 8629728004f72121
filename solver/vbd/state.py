"""The device arrays of a `Simulation` and the plumbing around them: allocation and upload (once, at
construction), the parameters array, reading and writing positions and velocities, saving and
restoring a state. `SimulationState` is the base class of `Simulation`, which holds the time step.
"""
from dataclasses import dataclass
from typing import NamedTuple
from weakref import WeakKeyDictionary, ref

import numpy as np
from .. import _ti
from .._ti import ti

from . import layout as L
from ..backend import RuntimeCache
from ..errors import ConfigError
from ..mesh.bodies import body_labels
from ..mesh.topology import Topology, grad_rows
from ..method import Method
from .contact_state import ContactStage, as_contact
from .translation import BodyTranslation

_DEVICE_TOPOLOGY = RuntimeCache(WeakKeyDictionary)      # {Topology: {dtype: arrays}} per Taichi runtime


class SweepArrays(NamedTuple):
    """`Simulation.arrays`: the ti.ndarrays of one simulation's state and settings (`layout.py`) and of
    its `Topology` (color_order (S,), offsets (S + 1,), others (E, 3), adj_f (E, ADJ_FLOATS),
    color_starts (C + 1,))."""

    state: object
    mass: object
    params: object
    color_order: object
    offsets: object
    others: object
    adj_f: object
    color_starts: object


@dataclass(frozen=True)
class IterationRecord:
    """One entry of `Simulation.history`: G in J and the largest |f_i| in N after `iteration` iterations
    (VBD iterations; Newton iterations for method="newton" and "pcg")."""

    iteration: int
    energy: float
    max_residual: float


class SimulationState:
    """Device arrays of one simulation: state (STATE_ROWS, N) 3-vectors (rows: `layout.X`, X_N, ...),
    masses (N,), params (PARAM_COUNT,), per-vertex f_i (N, 3) and H_i (N, 3, 3), and the mesh's tets
    (M, 4), Dm^-1 (M, 3, 3), rest volumes (M,) and `Topology` on the device."""

    def _allocate(self):
        mesh = self.mesh
        dtype = self.dtype = self.precision.ti_dtype
        self._np_dtype = np.float64 if dtype == ti.f64 else np.float32
        n, m = mesh.n_vertices, mesh.n_tets
        self.state = ti.Vector.ndarray(3, dtype, (L.STATE_ROWS, n))
        self._mass = ti.ndarray(dtype, n)
        self._params = ti.ndarray(dtype, L.PARAM_COUNT)
        self._f = ti.Vector.ndarray(3, dtype, n)
        self._H = ti.Matrix.ndarray(3, 3, dtype, n)
        self._free = ti.ndarray(ti.i32, n)
        self._free.from_numpy(self.free_mask.astype(np.int32))
        bodies = body_labels(mesh.tets, n)
        self._body_translation = BodyTranslation(bodies, self.free_mask, self._serial_sweep)
        # every vertex free and several bodies: the whole mesh's translation after the bodies' (`translation.py`)
        self._mesh_translation = (BodyTranslation(np.zeros(n, np.int32), self.free_mask, self._serial_sweep)
                                  if self.free_mask.all() and bodies.max() > 0 else None)

        X, T = mesh.vertices, mesh.tets
        self._grad_rows = grad_rows(X, T)                  # (M, 4, 3): rows 1-3 are Dm^-1
        self._rest_vol = mesh.rest_volumes()
        self._size = float(np.ptp(X, axis=0).max())      # m, the body's largest extent
        self._tets = ti.Vector.ndarray(4, ti.i32, m)
        self._Dm_inv = ti.Matrix.ndarray(3, 3, dtype, m)
        self._volume = ti.ndarray(dtype, m)
        self._tets.from_numpy(T.astype(np.int32))
        self._Dm_inv.from_numpy(self._grad_rows[:, 1:].astype(self._np_dtype))
        self._volume.from_numpy(self._rest_vol.astype(self._np_dtype))
        self._adjacency = self._device_topology()
        self._runtime = ref(_ti.runtime())              # the Taichi these arrays belong to

        kin = np.flatnonzero(self.kinematic_mask).astype(np.int32)
        self._kinematic_rest = X[kin]
        self._n_kinematic = len(kin)
        self._kin_ids = ti.ndarray(ti.i32, max(len(kin), 1))
        self._kin_targets = ti.Vector.ndarray(3, dtype, max(len(kin), 1))
        self._kin_ids.from_numpy(np.resize(kin, max(len(kin), 1)))

    def _device_topology(self):
        """The topology's arrays on the device, shared by simulations of the same mesh and precision
        (and of the same Taichi runtime: `ti.init` frees them)."""
        top = self.topology
        per_dtype = _DEVICE_TOPOLOGY.get().setdefault(top, {})
        if self.dtype not in per_dtype:
            color_order = ti.ndarray(ti.i32, top.n_slots)
            offsets = ti.ndarray(ti.i32, top.n_slots + 1)
            others = ti.Vector.ndarray(3, ti.i32, top.n_entries)
            adj_f = ti.Vector.ndarray(L.ADJ_FLOATS, self.dtype, top.n_entries)
            color_starts = ti.ndarray(ti.i32, top.n_colors + 1)
            color_order.from_numpy(top.color_order)
            offsets.from_numpy(top.offsets)
            others.from_numpy(top.others)
            adj_f.from_numpy(np.column_stack([top.q, top.c, top.m_sq, top.volume]).astype(self._np_dtype))
            color_starts.from_numpy(np.array([s for s, _ in top.color_ranges] + [top.n_slots], dtype=np.int32))
            per_dtype[self.dtype] = (color_order, offsets, others, adj_f, color_starts)
        return per_dtype[self.dtype]

    def _upload_params(self, settings, material):
        """Write the scalar settings and the material into `params` (`layout.py`)."""
        p = np.zeros(L.PARAM_COUNT)
        p[L.TIME_STEP] = settings.dt
        p[L.MU], p[L.LAM] = material.mu, material.lam
        p[L.DAMPING] = settings.damping
        ground = settings.ground
        if ground is not None:
            p[L.GROUND] = 1.0
            p[L.GROUND_HEIGHT] = ground.height
            p[L.GROUND_STIFFNESS] = ground.stiffness
            p[L.FRICTION] = ground.friction
            p[L.FRICTION_SPEED] = ground.friction_speed
        p[L.GRAVITY_X:L.GRAVITY_X + 3] = settings.gravity
        p[L.KEEP_ORIENTATION] = float(settings.keep_orientation)
        self._params.from_numpy(p.astype(self._np_dtype))

    def _upload_masses(self, density: float) -> None:
        """Lumped masses m_i = density x (a quarter of the volume of every tet at i), in kg."""
        mass = np.zeros(self.mesh.n_vertices)
        np.add.at(mass, self.mesh.tets.ravel(), np.repeat(density * self._rest_vol / 4.0, 4))
        self._mass.from_numpy(mass.astype(self._np_dtype))
        self._max_mass = float(mass.max())

    @property
    def positions(self) -> np.ndarray:
        """(N, 3) float64 copy of the current positions x."""
        return self._row(L.X)

    @property
    def velocities(self) -> np.ndarray:
        """(N, 3) float64 copy of the velocities v."""
        return self._row(L.V)

    @property
    def x_n(self) -> np.ndarray:
        """(N, 3) float64 copy of the positions x_n at the start of the current (or last) step."""
        return self._row(L.X_N)

    @property
    def y(self) -> np.ndarray:
        """(N, 3) float64 copy of the current (or last) step's inertial target y = x_n + h v_n + h^2 g."""
        return self._row(L.Y)

    def _require_live(self) -> None:
        """Refuse to touch the arrays once `ti.init` has freed them (Taichi initialised again after
        this simulation was built), where Taichi would crash or read freed memory."""
        if self._runtime() is not _ti.runtime():
            raise ConfigError("Taichi was initialised again (ti.init) after this Simulation was built, which "
                              "freed its arrays; build a new Simulation after ti.init")

    def _row(self, row: int) -> np.ndarray:
        self._require_live()
        out = np.empty((self.mesh.n_vertices, 3))
        L.read_row(self.state, row, out, self._serial_sweep)
        return out

    @property
    def arrays(self) -> SweepArrays:
        """The device arrays the kernels of `vertex_solve` take, for code that launches its own sweeps
        (baselines, probes): state (STATE_ROWS, N), mass (N,), params, and the `Topology` on the device.
        Shared, not copied: writing into them changes the simulation."""
        return SweepArrays(self.state, self._mass, self._params, *self._adjacency)

    @property
    def colors(self) -> np.ndarray:
        """(N,) int32 colour of every vertex, -1 for fixed and kinematic vertices."""
        return np.where(self.free_mask, self.coloring.colors, -1).astype(np.int32)

    @property
    def n_colors(self) -> int:
        return self.topology.n_colors

    @property
    def masses(self) -> np.ndarray:
        """(N,) lumped vertex masses in kg."""
        return self._mass.to_numpy().astype(np.float64)

    def set_positions(self, x: np.ndarray) -> None:
        """Overwrite the positions (N, 3) in metres, e.g. to start from a deformed state (with contact:
        bodies that intersect or touch there raise `ConfigError`)."""
        x = self._checked_state(x, "positions")
        before = self.positions
        self._set_rows({L.X: x})
        if self._contact_stage is not None:
            try:
                self._contact_stage.check_apart(self.state, x)
            except ConfigError:                 # refused: the simulation keeps the positions it had
                self._set_rows({L.X: before})
                self._contact_stage.detect(self.state, L.X)
                raise

    # -----------------------------------------------------------------------------------------
    # Contact between bodies (`contact_state.ContactStage`, issue 17)
    # -----------------------------------------------------------------------------------------
    @property
    def contact(self):
        """Contact between bodies and within one (a `Contact`), or None; live."""
        return self._contact

    @contact.setter
    def contact(self, value):
        value = as_contact(value)
        if value is not None and self.method not in (Method.VBD, Method.NEWTON):
            raise ConfigError(f"method={self.method.value!r} has no contact term; use method='vbd' or 'newton' "
                              "with contact (sim.newton_reference() solves the same step with contact)")
        if value is not None and self.method is Method.NEWTON and value.friction > 0:
            raise ConfigError("method='newton' minimises G, which has no friction; set contact friction=0, "
                              "or use method='vbd'")
        stage = None if value is None else ContactStage(self.mesh, self.free_mask, value, self.dtype)
        if stage is not None:
            stage.check_apart(self.state, self.positions)
            stage.compile_kernels(self._mass, self._adjacency, self._params, self.n_colors,
                                  sweeps=self.method is Method.VBD)
        self._contact, self._contact_stage = value, stage
        self._newton_contact = None         # the contact term of the StepProblems, built on first use

    @property
    def bodies(self) -> np.ndarray:
        """(N,) int32 body of each vertex, bodies numbered by their smallest vertex."""
        if self._contact_stage is not None:
            return self._contact_stage.bodies.copy()
        return body_labels(self.mesh.tets, self.mesh.n_vertices)

    def contact_count(self) -> int:
        """Contact pairs closer than the radius at the current positions (0 without contact)."""
        return 0 if self._contact_stage is None else self._contact_stage.count(self.state)

    def min_separation(self) -> float:
        """Least contact pair distance in m under query_radius at the current positions, else inf."""
        return float("inf") if self._contact_stage is None else self._contact_stage.min_separation(self.state)

    def _contact_term(self):
        """The numpy contact term of the Newton reference (`newton.contact_term`), or None; one per
        `contact`, shared by the step problems (method="newton" builds its Taichi twin from it)."""
        if self._contact is None:
            return None
        if self._contact.friction > 0:
            raise ConfigError("the Newton reference minimises G, which has no friction; "
                              "set contact friction=0 to compare against it")
        if self._newton_contact is None:
            from ..newton.contact_term import ContactTerm

            self._newton_contact = ContactTerm(self._contact, self.mesh.tets, self.mesh.vertices, self.free_mask)
        return self._newton_contact

    def set_velocities(self, v: np.ndarray, previous=None) -> None:
        """Overwrite the velocities v_n (N, 3) in m/s. previous: the velocities v_{n-1} (N, 3) of the
        step before, which the adaptive initial guess reads; by default v - h g, i.e. free fall, so the
        adaptive guess of the next step is y = x_n + h v_n + h^2 g. To resume bodies at rest or in
        contact, pass the velocities of the step before, or use `save_state` / `restore_state`, which
        resume a run exactly."""
        v = self._checked_state(v, "velocities")
        v_prev = v - self.dt * self.gravity if previous is None else self._checked_state(previous, "previous")
        self._set_rows({L.V: v, L.V_PREV: v_prev})

    def _set_rows(self, rows: dict) -> None:
        self._require_live()
        for row, value in rows.items():
            L.write_row(self.state, row, np.ascontiguousarray(value, dtype=np.float64), self.dtype,
                        self._serial_sweep)

    def _checked_state(self, a, name):
        try:
            a = np.asarray(a, dtype=np.float64)
        except (TypeError, ValueError):
            raise ConfigError(f"{name} must be an array of numbers of shape ({self.mesh.n_vertices}, 3)") from None
        if a.shape != (self.mesh.n_vertices, 3):
            raise ConfigError(f"{name} must have shape ({self.mesh.n_vertices}, 3), got {a.shape}")
        if not np.isfinite(a).all():
            raise ConfigError(f"{name} contain NaN or infinite values; pass finite numbers")
        return a

    def save_state(self) -> dict:
        """A copy of everything a step reads (positions, velocities, clock), for `restore_state`."""
        if self._in_step:
            raise ConfigError("save_state() is defined between steps; call end_step() first")
        return {"state": self.state.to_numpy(), "time": self.time, "frame": self.frame}

    def restore_state(self, saved: dict) -> None:
        """Go back to a state returned by `save_state` of this simulation."""
        shape = tuple(self.state.shape) + (3,)
        try:
            state, time, frame = np.asarray(saved["state"]), float(saved["time"]), int(saved["frame"])
        except (TypeError, KeyError, ValueError, IndexError):
            state = None
        if state is None or state.shape != shape or not np.isfinite(state).all():
            raise ConfigError("restore_state() takes what save_state() of this simulation returned "
                              f"(a dict with 'state' of shape {shape}, 'time' and 'frame')")
        self.state.from_numpy(state.astype(self._np_dtype))
        self.time, self.frame = time, frame
        self._in_step = False

    def reset(self) -> None:
        """Back to the rest shape at rest, time 0."""
        zero = np.zeros_like(self.mesh.vertices)
        self._set_rows({L.X: self.mesh.vertices, L.X_N: self.mesh.vertices, L.Y: self.mesh.vertices,
                        L.V: zero, L.V_PREV: zero - self.dt * self.gravity})
        self.time = 0.0
        self.frame = 0
        self._in_step = False
