"""Vertex Block Descent time stepping for elastic tet meshes (VBD [Chen et al. 2024], Alg. 1).

One time step of implicit Euler minimises the incremental potential

    G(x) = sum_i m_i / (2 h^2) |x_i - y_i|^2 + sum_tets vol Psi(F),   y = x_n + h v_n + h^2 g,

one vertex at a time: all vertices of one colour are solved in parallel, each by one 3x3 Newton step
on its local energy (lecture notes, chapter 3). `Simulation` holds the state and drives the loop,
which reads like the lecture:

    step():  predict y, pick the initial guess                          (begin_step)
             for each iteration: for each colour: solve that colour      (run_iterations)
             v = (x - x_n) / h                                           (end_step)

The physics lives in free functions beside their numpy twins (`vertex_solve.py`, `material.py`,
`contact.py`, `chebyshev.py`, `implicit_euler.py`, `energy.py`), the adjacency in `topology.py`.
"""

from dataclasses import dataclass
from typing import Callable, NamedTuple, Optional
from weakref import WeakKeyDictionary

import numpy as np
from .._ti import ti

from . import energy as energy_kernels
from . import implicit_euler, orientation
from . import layout as L
from . import translation, vertex_solve
from ..backend import as_precision, ensure_taichi
from .chebyshev import chebyshev_omega, chebyshev_step, chebyshev_update
from .contact_state import ContactStage, as_contact   # contact hook (issue 17)
from ..mesh.bodies import body_labels
from ..mesh.coloring import Coloring, VertexOrder, color_vertices
from ..physics.ground import Ground
from ..errors import ConfigError, VBDError
from .implicit_euler import InitialGuess
from ..physics.material import Material, vertex_force_hessian
from ..method import Method, as_method, choose, multilevel_cycles, wave_cells
from ..mesh.tetmesh import TetMesh
from ..todo import require_implemented
from ..mesh.topology import Topology, build_topology, grad_rows

__all__ = ["Ground", "InitialGuess", "IterationRecord", "Simulation", "SweepArrays"]


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
    """One entry of `Simulation.history`: G and the largest |f_i| after `iteration` iterations."""

    iteration: int
    energy: float
    max_residual: float


def _number(value, name: str, unit: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ConfigError(f"{name} must be a number of {unit}, got {value!r}")
    if not np.isfinite(value):
        raise ConfigError(f"{name} must be finite, got {value!r}")
    return float(value)


def _positive(value, name: str, unit: str) -> float:
    value = _number(value, name, unit)
    if value <= 0:
        raise ConfigError(f"{name} must be a positive number of {unit}, got {value!r}")
    return value


def _count(value, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ConfigError(f"{name} must be an integer >= 1, got {value!r}")
    return int(value)


def _index_mask(value, n: int, name: str) -> np.ndarray:
    """A boolean (n,) mask from None, a boolean mask or an index array."""
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
            arr = arr.astype(np.int64).ravel()
            if arr.size and (arr.min() < 0 or arr.max() >= n):
                raise ConfigError(f"{name} has vertex indices outside 0..{n - 1}")
            mask[arr] = True
    return mask


def _read_only(mask: np.ndarray) -> np.ndarray:
    mask.flags.writeable = False
    return mask


def _gravity(value) -> np.ndarray:
    try:
        g = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        g = None
    if g is None or g.shape != (3,) or not np.isfinite(g).all():
        raise ConfigError(f"gravity must be three finite numbers in m/s^2, e.g. (0, 0, -9.81), got {value!r}")
    g.flags.writeable = False
    return g


def _rho(value) -> Optional[float]:
    if value is None:
        return None
    rho = _number(value, "chebyshev_rho", "(dimensionless)")
    if not 0.0 < rho < 1.0:
        raise ConfigError(f"chebyshev_rho must be in (0, 1) or None, got {value!r}")
    return rho


_READ_ONLY = {
    "mesh": "the mesh", "fixed_mask": "the fixed vertices", "kinematic_mask": "the kinematic vertices",
    "free_mask": "the free vertices", "precision": "the float type", "arch": "the backend",
    "coloring": "the colouring", "topology": "the adjacency", "method": "the solver",
    "method_reason": "why the solver was chosen",
}
_DEVICE_TOPOLOGY: "WeakKeyDictionary[Topology, dict]" = WeakKeyDictionary()
_GUESS_REPAIR_PASSES = 10   # each pass puts the vertices of newly inverted tets back to x_n; then all


class Simulation:
    """A VBD simulation of one elastic body.

    mesh: the `TetMesh`; material: its `Material`; dt: time step h in s; gravity: (3,) m/s^2;
    fixed: vertices held at their rest position (boolean (N,) mask or index array);
    iterations: VBD iterations per step (the cap when `tolerance` is set);
    initial_guess: an `InitialGuess`; chebyshev_rho: spectral radius estimate rho for Chebyshev
    acceleration (VBD Eq. 18-19), None for none; damping: k_d in s (VBD Eq. 10-11), 0 for none;
    ground: a `Ground` or None; tolerance: stop a step once max_i |f_i| falls below this fraction of
    the larger of its value at the initial guess and the heaviest vertex's weight max_i m_i |g|
    (or to round-off level), checked every `check_every` iterations (a check costs about one
    iteration); kinematic: vertices whose positions `kinematic_motion(t, rest)` scripts, rest
    being their (K, 3) rest positions and the result their (K, 3) positions at time t;
    precision: "float64" or "float32"; arch: "cpu", "gpu" or None (the backend Taichi already runs on,
    else the CPU); coloring_order: a `VertexOrder`;
    translation_correction: end every step of a body without fixed or kinematic vertices with the
    rigid-translation correction (`translation.py`), which removes the sideways drift of unconverged
    VBD; keep_orientation: never let an upright tet invert (the guess and every vertex step are
    limited, `orientation.py`; costs about a third more per iteration), for meshes with slivers;
    method: the solver of each step, a `Method` or its name: "vbd" (default), "newton" (projected
    Newton to convergence), "pcg" (Newton-PCG with VBD's colour sweep as preconditioner),
    "multilevel" (two-level VBD, `iterations` fine sweeps per step in cycles of 2 + coarse + 2),
    "auto" (chosen from N_c, see `method_reason`); the global ones minimise G, so they need
    damping 0 and no ground friction;
    record_history: keep G and max |f_i| after every iteration of the last step in `history`;
    contact: a `Contact` between the mesh's bodies (`bodies`, `merge_meshes`) and within one, or None
    (`contact_state.py`; method "vbd" only, Chebyshev skips the vertices that touched this step, and the
    translation correction, which needs every vertex free, moves all bodies together).

    Live settings, used from the next iteration or step on: `dt`, `gravity`, `damping`, `ground`,
    `chebyshev_rho`, `material` (or `set_material`), `iterations`, `tolerance`, `check_every`,
    `initial_guess`, `translation_correction`, `keep_orientation`, `kinematic_motion`,
    `record_history`, `contact`. Fixed at construction
    (assigning raises `ConfigError`): `mesh`, `fixed_mask`, `kinematic_mask`, `free_mask`,
    `precision`, `arch`, `coloring`, `topology`.

    Every kernel is shared by all simulations in the process: a second `Simulation` of the same
    mesh compiles nothing and reuses the colouring and the adjacency (`topology`).
    """

    def __init__(self, mesh: TetMesh, material: Material, dt: float = 1 / 60, gravity=(0.0, 0.0, -9.81),
                 fixed=None, iterations: int = 100, initial_guess: InitialGuess = InitialGuess.ADAPTIVE,
                 chebyshev_rho: Optional[float] = None, damping: float = 0.0, ground: Optional[Ground] = None,
                 tolerance: Optional[float] = None, check_every: int = 5, kinematic=None,
                 kinematic_motion: Optional[Callable] = None, precision="float64", arch: Optional[str] = None,
                 coloring_order: VertexOrder = VertexOrder.NATURAL,
                 translation_correction: bool = True, keep_orientation: bool = False,
                 method=Method.VBD, record_history: bool = False, contact=None):
        if not isinstance(mesh, TetMesh):
            raise ConfigError(f"mesh must be a solver.TetMesh, got {type(mesh).__name__}; "
                              "use solver.load_mesh or solver.box_mesh")
        if not isinstance(coloring_order, VertexOrder):
            raise ConfigError(f"coloring_order must be a solver.VertexOrder, got {coloring_order!r}")
        n = mesh.n_vertices
        self.mesh = mesh
        self.precision = as_precision(precision)
        fixed_mask = _index_mask(fixed, n, "fixed")
        kinematic_mask = _index_mask(kinematic, n, "kinematic")
        if kinematic_mask.any() and kinematic_motion is None:
            raise ConfigError("kinematic vertices need kinematic_motion(t, rest) -> (K, 3) positions")
        self.kinematic_mask = _read_only(kinematic_mask)
        self.fixed_mask = _read_only(fixed_mask & ~kinematic_mask)
        self.free_mask = _read_only(~(fixed_mask | kinematic_mask))
        if not self.free_mask.any():
            raise ConfigError("every vertex is fixed or kinematic; nothing is left to simulate")

        self._settings_ready = False
        self.initial_guess = initial_guess
        self.translation_correction = translation_correction
        self.keep_orientation = keep_orientation
        self.dt = dt
        self.gravity = gravity
        self.iterations = iterations
        self.chebyshev_rho = chebyshev_rho
        self.damping = damping
        self.ground = ground
        self.tolerance = tolerance
        self.check_every = check_every
        self.kinematic_motion = kinematic_motion
        self.record_history = record_history
        self._contact = as_contact(contact)     # contact hook (issue 17): read by the choice of method
        if not isinstance(material, Material):
            raise ConfigError(f"material must be a solver.Material, got {type(material).__name__}")

        ensure_taichi(arch)
        self.arch = arch
        require_implemented(vertex_force_hessian, vertex_solve.force_hessian, vertex_solve.newton_step)
        self._choose_method(method, material, dt)
        self.coloring: Coloring = color_vertices(mesh.tets, n, coloring_order, key=mesh.topology_key())
        self.topology: Topology = build_topology(mesh.vertices, mesh.tets,
                                                 np.where(self.free_mask, self.coloring.colors, -1))
        self._allocate()
        self._settings_ready = True
        self.material = material
        self.history: list[IterationRecord] = []
        self.last_iterations = 0
        self.reset()
        self._contact_stage = None     # contact hook (issue 17)
        self.contact = contact
        self._constructed = True

    def _choose_method(self, method, material, dt):
        method = as_method(method)
        self.method_reason = f"method={method.value} was asked for"
        if method is Method.AUTO:
            method, self.method_reason = choose(wave_cells(self.mesh, material, float(dt)))
            if self._contact is not None and method is not Method.VBD:      # contact hook (issue 17)
                method, self.method_reason = Method.VBD, f"{self.method_reason}; but only 'vbd' has contact"
        self._refuse_non_potential(method, self._damping, self._ground)
        self._refuse_contact(method, self._contact)
        self.method = method
        self._two_level = None

    @staticmethod
    def _refuse_contact(method, contact):
        """Contact hook (issue 17): only VBD and the numpy Newton reference have the contact term yet."""
        if method is not Method.VBD and contact is not None:
            raise ConfigError(f"method={method.value!r} has no contact term yet; use method='vbd' with contact "
                              "(sim.newton_reference() solves the same step with contact)")

    @staticmethod
    def _refuse_non_potential(method, damping, ground):
        if method is not Method.VBD and (damping > 0 or (ground is not None and ground.friction > 0)):
            raise ConfigError(f"method={method.value!r} minimises G, which has no damping or friction; "
                              "set damping=0 and ground friction=0, or use method='vbd'")

    @property
    def wave_cells(self) -> float:
        """N_c = h sqrt(E / rho) / dx: cells an elastic wave crosses in one step (`method.wave_cells`)."""
        return wave_cells(self.mesh, self._material, self._dt)

    def __setattr__(self, name, value):
        if name in _READ_ONLY and getattr(self, "_constructed", False):
            raise ConfigError(f"Simulation.{name} ({_READ_ONLY[name]}) is fixed at construction; "
                              f"build a new Simulation with the {name} you want")
        super().__setattr__(name, value)

    # -----------------------------------------------------------------------------------------
    # Set-up: everything is allocated and uploaded once, here.
    # -----------------------------------------------------------------------------------------
    def _allocate(self):
        mesh = self.mesh
        dtype = self.dtype = self.precision.ti_dtype
        self._np_dtype = np.float64 if dtype == ti.f64 else np.float32
        n, m = mesh.n_vertices, mesh.n_tets
        self.state = ti.Vector.ndarray(3, dtype, (L.STATE_ROWS, n))   # rows: layout.X, X_N, Y, ...
        self._mass = ti.ndarray(dtype, n)
        self._params = ti.ndarray(dtype, L.PARAM_COUNT)
        self._f = ti.Vector.ndarray(3, dtype, n)
        self._row_buffer = ti.Vector.ndarray(3, dtype, n)
        self._H = ti.Matrix.ndarray(3, 3, dtype, n)
        self._free = ti.ndarray(ti.i32, n)
        self._free.from_numpy(self.free_mask.astype(np.int32))
        self._translation = ti.Vector.ndarray(3, ti.f64, 2)

        X, T = mesh.vertices, mesh.tets
        self._grad_rows = grad_rows(X, T)                  # (M, 4, 3): rows 1-3 are Dm^-1
        Dm_inv = self._grad_rows[:, 1:]
        self._rest_vol = mesh.rest_volumes()
        self._size = float(np.ptp(X, axis=0).max())      # m, the body's largest extent
        self._tets = ti.Vector.ndarray(4, ti.i32, m)
        self._Dm_inv = ti.Matrix.ndarray(3, 3, dtype, m)
        self._volume = ti.ndarray(dtype, m)
        self._tets.from_numpy(T.astype(np.int32))
        self._Dm_inv.from_numpy(Dm_inv.astype(self._np_dtype))
        self._volume.from_numpy(self._rest_vol.astype(self._np_dtype))
        self._adjacency = self._device_topology()

        kin = np.flatnonzero(self.kinematic_mask).astype(np.int32)
        self._kinematic_rest = X[kin]
        self._n_kinematic = len(kin)
        self._kin_ids = ti.ndarray(ti.i32, max(len(kin), 1))
        self._kin_targets = ti.Vector.ndarray(3, dtype, max(len(kin), 1))
        self._kin_ids.from_numpy(np.resize(kin, max(len(kin), 1)))

    def _device_topology(self):
        """The topology's arrays on the device, shared by simulations of the same mesh and precision."""
        top = self.topology
        per_dtype = _DEVICE_TOPOLOGY.setdefault(top, {})
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

    def _upload_params(self):
        if not self._settings_ready:
            return
        p = np.zeros(L.PARAM_COUNT)
        p[L.TIME_STEP] = self._dt
        p[L.MU], p[L.LAM] = self._material.mu, self._material.lam
        p[L.DAMPING] = self._damping
        if self._ground is not None:
            p[L.GROUND] = 1.0
            p[L.GROUND_HEIGHT] = self._ground.height
            p[L.GROUND_STIFFNESS] = self._ground.stiffness
            p[L.FRICTION] = self._ground.friction
            p[L.FRICTION_SPEED] = self._ground.friction_speed
        p[L.GRAVITY_X:L.GRAVITY_X + 3] = self._gravity
        p[L.KEEP_ORIENTATION] = float(self._keep_orientation)
        self._params.from_numpy(p.astype(self._np_dtype))

    # -----------------------------------------------------------------------------------------
    # Live settings
    # -----------------------------------------------------------------------------------------
    @property
    def dt(self) -> float:
        """Time step h in s."""
        return self._dt

    @dt.setter
    def dt(self, value):
        self._dt = _positive(value, "dt", "seconds")
        self._upload_params()

    @property
    def gravity(self) -> np.ndarray:
        """(3,) gravitational acceleration g in m/s^2 (read-only array; assign a new one)."""
        return self._gravity

    @gravity.setter
    def gravity(self, value):
        self._gravity = _gravity(value)
        self._upload_params()

    @property
    def damping(self) -> float:
        """Damping coefficient k_d in s (VBD Eq. 10-11), 0 for none."""
        return self._damping

    @damping.setter
    def damping(self, value):
        value = _number(value, "damping", "seconds")
        if value < 0:
            raise ConfigError(f"damping must be >= 0 seconds, got {value!r}")
        if hasattr(self, "method"):
            self._refuse_non_potential(self.method, value, self._ground)
        self._damping = value
        self._upload_params()

    @property
    def ground(self) -> Optional[Ground]:
        """The `Ground` plane, or None."""
        return self._ground

    @ground.setter
    def ground(self, value):
        if value is not None and not isinstance(value, Ground):
            raise ConfigError(f"ground must be a solver.Ground or None, got {type(value).__name__}")
        if hasattr(self, "method"):
            self._refuse_non_potential(self.method, self._damping, value)
        self._ground = value
        self._upload_params()

    @property
    def contact(self):
        """Contact between bodies and within one (a `Contact`), or None (issue 17)."""
        return self._contact

    @contact.setter
    def contact(self, value):
        value = as_contact(value)
        if hasattr(self, "method"):
            self._refuse_contact(self.method, value)
        stage = None if value is None else ContactStage(self.mesh, self.free_mask, value, self.dtype)
        if stage is not None:
            stage.check_apart(self.state, self.positions)
        self._contact, self._contact_stage = value, stage

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

    @property
    def chebyshev_rho(self) -> Optional[float]:
        """Spectral radius estimate rho of Chebyshev acceleration (VBD Eq. 18-19), None for none."""
        return self._rho

    @chebyshev_rho.setter
    def chebyshev_rho(self, value):
        rho = _rho(value)
        if rho is not None:
            require_implemented(chebyshev_omega, chebyshev_update)
        self._rho = rho

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
        mass = np.zeros(self.mesh.n_vertices)
        np.add.at(mass, self.mesh.tets.ravel(), np.repeat(material.density * self._rest_vol / 4.0, 4))
        self._mass.from_numpy(mass.astype(self._np_dtype))
        self._max_mass = float(mass.max())
        self._upload_params()

    @property
    def initial_guess(self) -> InitialGuess:
        """Where the iterations of a step start (an `InitialGuess`)."""
        return self._initial_guess

    @initial_guess.setter
    def initial_guess(self, value):
        if not isinstance(value, InitialGuess):
            raise ConfigError(f"initial_guess must be a solver.InitialGuess, got {value!r}")
        self._initial_guess = value

    @property
    def translation_correction(self) -> bool:
        """Whether steps end with the rigid-translation correction (bodies without fixed or kinematic
        vertices only)."""
        return self._translation_correction

    @translation_correction.setter
    def translation_correction(self, value):
        if not isinstance(value, (bool, np.bool_)):
            raise ConfigError(f"translation_correction must be True or False, got {value!r}")
        self._translation_correction = bool(value)

    @property
    def keep_orientation(self) -> bool:
        """Whether the guess and the vertex steps are limited so that no upright tet inverts."""
        return self._keep_orientation

    @keep_orientation.setter
    def keep_orientation(self, value):
        if not isinstance(value, (bool, np.bool_)):
            raise ConfigError(f"keep_orientation must be True or False, got {value!r}")
        self._keep_orientation = bool(value)
        self._upload_params()

    @property
    def iterations(self) -> int:
        """VBD iterations per step (the cap when `tolerance` is set)."""
        return self._iterations

    @iterations.setter
    def iterations(self, value):
        self._iterations = _count(value, "iterations")

    @property
    def tolerance(self) -> Optional[float]:
        """Relative residual at which a step stops early, or None to always run `iterations`."""
        return self._tolerance

    @tolerance.setter
    def tolerance(self, value):
        self._tolerance = None if value is None else _positive(value, "tolerance", "(relative)")

    @property
    def check_every(self) -> int:
        """Iterations between two tolerance checks."""
        return self._check_every

    @check_every.setter
    def check_every(self, value):
        self._check_every = _count(value, "check_every")

    @property
    def kinematic_motion(self) -> Optional[Callable]:
        """kinematic_motion(t, rest (K, 3)) -> (K, 3) positions of the kinematic vertices at time t."""
        return self._kinematic_motion

    @kinematic_motion.setter
    def kinematic_motion(self, value):
        if value is not None and not callable(value):
            raise ConfigError("kinematic_motion must be a function (t, rest) -> (K, 3) positions")
        if value is None and self.kinematic_mask.any():
            raise ConfigError("kinematic vertices need kinematic_motion(t, rest) -> (K, 3) positions")
        self._kinematic_motion = value

    # -----------------------------------------------------------------------------------------
    # Public state access
    # -----------------------------------------------------------------------------------------
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

    def _row(self, row: int) -> np.ndarray:
        L.read_row(self.state, row, self._row_buffer)
        return self._row_buffer.to_numpy().astype(np.float64)

    @property
    def arrays(self) -> "SweepArrays":
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
        """Overwrite the positions (N, 3) in metres, e.g. to start from a deformed state."""
        x = self._checked_state(x, "positions")
        self._set_rows({L.X: x})
        if self._contact_stage is not None:      # contact hook (issue 17)
            self._contact_stage.check_apart(self.state, x)

    def set_velocities(self, v: np.ndarray, previous: Optional[np.ndarray] = None) -> None:
        """Overwrite the velocities v_n (N, 3) in m/s. previous: the velocities v_{n-1} (N, 3) of the
        step before, which the adaptive initial guess reads; by default v - h g, i.e. free fall."""
        v = self._checked_state(v, "velocities")
        v_prev = v - self._dt * self._gravity if previous is None else self._checked_state(previous, "previous")
        self._set_rows({L.V: v, L.V_PREV: v_prev})

    def _set_rows(self, rows: dict) -> None:
        for row, value in rows.items():
            self._row_buffer.from_numpy(np.asarray(value, dtype=self._np_dtype))
            L.write_row(self.state, row, self._row_buffer)

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
        self.state.from_numpy(saved["state"])
        self.time, self.frame = saved["time"], saved["frame"]
        self._in_step = False

    def reset(self) -> None:
        """Back to the rest shape at rest, time 0."""
        zero = np.zeros_like(self.mesh.vertices)
        self._set_rows({L.X: self.mesh.vertices, L.X_N: self.mesh.vertices, L.Y: self.mesh.vertices,
                        L.V: zero, L.V_PREV: zero - self._dt * self._gravity})
        self.time = 0.0
        self.frame = 0
        self._in_step = False

    # -----------------------------------------------------------------------------------------
    # The time step
    # -----------------------------------------------------------------------------------------
    def step(self, n: int = 1) -> None:
        """Advance `n` time steps with the simulation's `method`."""
        for _ in range(_count(n, "n")):
            if self.method is Method.VBD:
                self.begin_step()
                self.run_iterations(self.iterations)
                self.end_step()
            elif self.method is Method.MULTILEVEL:
                self._multilevel().step()
            else:
                self._global_step()

    def _multilevel(self):
        from ..newton.multilevel import TwoLevelVBD

        cycles = multilevel_cycles(self._iterations)
        if self._two_level is None or self._two_level.cycles != cycles:
            self._two_level = TwoLevelVBD(self, cycles=cycles)
        return self._two_level

    def _global_step(self):
        """One step minimised to convergence by the global Newton (direct or PCG), from VBD's guess."""
        from ..newton.direct import fast_newton_solve
        from ..newton.pcg import newton_pcg

        problem = self.step_problem()
        self.begin_step()
        if self.method is Method.NEWTON:
            result = fast_newton_solve(problem, self.positions, tolerance=1e-8)
        else:
            result = newton_pcg(problem.tets, problem.free).solve(problem, self.positions, tolerance=1e-8)
        self._set_rows({L.X: result.x})
        self.last_iterations = result.iterations
        self.end_step()

    def begin_step(self) -> None:
        """Save x_n, move kinematic vertices to their targets at t + h, predict y, set the guess."""
        if self._in_step:
            raise ConfigError("begin_step() called twice; call end_step() first")
        if self._n_kinematic:
            self._kin_targets.from_numpy(self._kinematic_targets(self.time + self._dt).astype(self._np_dtype))
        implicit_euler.begin_step(self.state, self._free, self._kin_ids, self._kin_targets, self._n_kinematic,
                                  self._params, self._initial_guess.code, self.dtype)
        if self._keep_orientation:
            for _ in range(_GUESS_REPAIR_PASSES):
                if orientation.undo_inverting_guess(self.state, self._tets, self._free) == 0:
                    break
            else:
                implicit_euler.return_to_start(self.state)    # x_n: upright wherever the last step was
        if self._contact_stage is not None:      # contact hook (issue 17): detect at x_n, clamp the guess
            self._contact_stage.begin_step(self.state, self._adjacency[0])
        self._in_step = True
        self._iteration = 0
        self._omega = 1.0
        self.last_iterations = 0
        self.history = []
        self._stop_below = None
        if self._tolerance is not None:
            weight = self._max_mass * float(np.linalg.norm(self._gravity))
            eps = np.finfo(self._np_dtype).eps
            roundoff = 100 * eps * self._material.mu * float(np.mean(self._rest_vol)) ** (2 / 3)
            self._stop_below = max(self._tolerance * max(self.max_residual(), weight), roundoff)
        if self.record_history:
            self.history.append(IterationRecord(0, self.energy(), self.max_residual()))

    def run_iterations(self, k: int) -> int:
        """Run up to `k` VBD iterations of the current step; returns how many ran."""
        if not self._in_step:
            raise ConfigError("run_iterations() needs begin_step() first")
        color_order, offsets, others, adj_f, color_starts = self._adjacency
        ran = 0
        for _ in range(_count(k, "k")):
            self._iteration += 1
            if self._rho is not None:
                self._omega = chebyshev_omega(self._iteration, self._rho, self._omega)
            if self._contact_stage is not None:  # contact hook (issue 17): no Chebyshev where a vertex touched
                self._contact_stage.iterate(self.state, self._mass, self._adjacency, self._params, self.n_colors,
                                            self.dtype, None if self._rho is None else self._omega)
            else:
                vertex_solve.vbd_iteration(self.state, self._mass, color_order, offsets, others, adj_f,
                                           color_starts, self._params, self.n_colors, self.dtype)
                if self._rho is not None:
                    chebyshev_step(self.state, color_order, self._omega, self.dtype)
            ran += 1
            if self.record_history:
                self.history.append(IterationRecord(self._iteration, self.energy(), self.max_residual()))
            if (self._stop_below is not None and self._iteration % self._check_every == 0
                    and self.max_residual() <= self._stop_below):
                break
        self.last_iterations = self._iteration
        return ran

    def solve_color(self, c: int) -> None:
        """Solve the vertices of colour c once (part of an iteration; for plots of one colour sweep)."""
        if not self._in_step:
            raise ConfigError("solve_color() needs begin_step() first")
        if self._contact_stage is not None:      # contact hook (issue 17)
            raise ConfigError("solve_color() runs the sweep without contact; use run_iterations() with contact")
        if isinstance(c, bool) or not isinstance(c, (int, np.integer)) or not 0 <= c < self.n_colors:
            raise ConfigError(f"colour must be an integer in 0..{self.n_colors - 1}, got {c!r}")
        color_order, offsets, others, adj_f, _ = self._adjacency
        start, end = self.topology.color_ranges[c]
        vertex_solve.vbd_color(self.state, self._mass, color_order, offsets, others, adj_f, self._params,
                               start, end, self.dtype)

    def end_step(self) -> None:
        """The translation correction (free bodies), v = (x - x_n) / h, advance the clock. A step that
        diverged raises `VBDError` and leaves the simulation at x_n, as before the step."""
        if not self._in_step:
            raise ConfigError("end_step() needs begin_step() first")
        if self._translation_correction and self.free_mask.all():
            color_order, offsets, others, adj_f, _ = self._adjacency
            translation.translation_system(self.state, self._mass, color_order, offsets, others, adj_f,
                                           self._params, self._translation, self.dtype)
            translation.translate(self.state, color_order, self._translation, self.dtype)
        moved = implicit_euler.largest_displacement(self.state)
        size = self._size
        if not moved <= 10 * size:
            implicit_euler.return_to_start(self.state)
            self._in_step = False
            what = "non-finite positions" if not np.isfinite(moved) else f"a vertex moved {moved:.3g} m in one step"
            hint = ("lower chebyshev_rho (or switch it off)" if self._rho is not None
                    else "use a smaller dt, more iterations, or a softer material")
            raise VBDError(f"the step diverged ({what}, body size {size:.3g} m); {hint}. "
                           "The simulation is back at the start of the step.")
        implicit_euler.end_step(self.state, self._params)
        self._in_step = False
        self.time += self._dt
        self.frame += 1

    def _kinematic_targets(self, t: float) -> np.ndarray:
        shape = self._kinematic_rest.shape
        try:
            target = np.asarray(self._kinematic_motion(t, self._kinematic_rest.copy()), dtype=np.float64)
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
                                                       self._Dm_inv, self._volume, self._params))
        if self._contact_stage is not None:      # contact hook (issue 17): + E_c
            G += self._contact_stage.energy(self.state, self.dtype)
        return G

    def _local_systems(self) -> float:
        color_order, offsets, others, adj_f, _ = self._adjacency
        largest = float(vertex_solve.local_systems(self.state, self._mass, color_order, offsets, others, adj_f,
                                                   self._params, self._f, self._H, self.dtype))
        if self._contact_stage is not None:      # contact hook (issue 17): + the pairs' terms
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
        return self.positions + self._dt * self.velocities + self._dt ** 2 * self._gravity

    def step_problem(self):
        """The minimisation the next `step()` solves, as a `StepProblem` for the Newton reference."""
        from ..newton.oracle import StepProblem

        if self._in_step:
            raise ConfigError("step_problem() is defined between steps; call end_step() first")
        x = self.positions
        targets = x.copy()
        if self.kinematic_mask.any():
            targets[self.kinematic_mask] = self._kinematic_targets(self.time + self._dt)
        if self._damping > 0 or (self._ground is not None and self._ground.friction > 0):
            raise ConfigError("the Newton reference minimises G, which has no damping or friction; "
                              "set damping=0 and ground friction=0 to compare against it")
        return StepProblem(tets=self.mesh.tets, grad_rows=self._grad_rows, volumes=self._rest_vol,
                           masses=self.masses, y=self.inertial_target(), free=self.free_mask.copy(),
                           constrained_positions=targets, h=self._dt, mu=self._material.mu,
                           lam=self._material.lam, ground=self._ground, contact=self._contact_term())

    def _contact_term(self):
        """Contact hook (issue 17): the numpy contact term of the Newton reference, or None."""
        from ..newton.contact_term import ContactTerm

        if self._contact is None:
            return None
        if self._contact.friction > 0:
            raise ConfigError("the Newton reference minimises G, which has no friction; "
                              "set contact friction=0 to compare against it")
        return ContactTerm(self._contact, self.mesh.tets, self.mesh.vertices, self.free_mask)

    def newton_reference(self, tolerance: float = 1e-10, max_iterations: int = 50, x0=None) -> np.ndarray:
        """(N, 3) converged global Newton solution x* of the next step, from the current state.

        x0: (N, 3) start of the Newton iterations (default y; x_n with contact, solved by the numpy
        `newton_solve`, since y may lie across a body); the simulation itself is not changed.
        To measure a VBD step cheaply, build `problem = sim.step_problem()` before `sim.step()` and
        warm-start `solver.fast_newton_solve(problem, sim.positions)` after it. Solved by the Taichi
        Newton (`global_newton`); `solver.newton_solve` is its independent numpy twin.
        """
        from ..newton.direct import fast_newton_solve
        from ..newton.oracle import newton_solve

        tolerance = _positive(tolerance, "tolerance", "(relative)")
        max_iterations = _count(max_iterations, "max_iterations")
        problem = self.step_problem()
        if problem.contact is not None:      # contact hook (issue 17): numpy Newton from x_n, never y
            start = problem.constrained_positions if x0 is None else self._checked_state(x0, "x0")
            return newton_solve(problem, start, tolerance, max_iterations).x
        start = problem.y_with_constraints() if x0 is None else self._checked_state(x0, "x0")
        return fast_newton_solve(problem, start, tolerance, max_iterations).x
