"""Vertex Block Descent time stepping for elastic tet meshes (VBD [Chen et al. 2024], Alg. 1).

One time step of implicit Euler minimises the incremental potential

    G(x) = sum_i m_i / (2 h^2) |x_i - y_i|^2 + sum_tets vol Psi(F),   y = x_n + h v_n + h^2 g,

one vertex at a time: all vertices of one colour are solved in parallel, each by one 3x3 Newton step
on its local energy (lecture notes, chapter 3). The loop reads like the lecture:

    step():  predict y, pick the initial guess          (begin_step)
             for each iteration: for each colour: solve that colour   (run_iterations)
             v = (x - x_n) / h                           (end_step)
"""

from dataclasses import dataclass
from enum import Enum
from typing import Callable, Optional

import numpy as np
import taichi as ti

from .backend import as_precision, ensure_taichi
from .coloring import Coloring, VertexOrder, color_vertices
from .errors import ConfigError
from .material import Material, psi, vertex_force_hessian
from .mesh import TetMesh
from .todo import require_implemented
from .topology import vertex_tet_adjacency


class InitialGuess(Enum):
    """Where the iterations of a step start (VBD [Chen et al. 2024] Sec. 3.7)."""

    PREVIOUS = "previous"    # x_n
    INERTIA = "inertia"      # x_n + h v_n
    INERTIAL = "inertial"    # y = x_n + h v_n + h^2 g
    ADAPTIVE = "adaptive"    # x_n + h v_n + h^2 a~ g, a~ = clamp(a_n . g / |g|^2, 0, 1)


@dataclass(frozen=True)
class Ground:
    """A ground plane z = height with penalty contact.

    stiffness: penalty k_c in N/m per vertex, energy k_c/2 d^2 for penetration depth d.
    friction: Coulomb coefficient mu_f (dimensionless, 0 = frictionless), smoothed below the
    sliding speed `friction_speed` (m/s) as in IPC's lagged friction.
    """

    height: float = 0.0
    stiffness: float = 1e5
    friction: float = 0.0
    friction_speed: float = 1e-3

    def __post_init__(self):
        if not np.isfinite(self.height):
            raise ConfigError(f"ground height must be finite, got {self.height}")
        if not (np.isfinite(self.stiffness) and self.stiffness > 0):
            raise ConfigError(f"ground stiffness must be > 0 N/m, got {self.stiffness}")
        if not (np.isfinite(self.friction) and self.friction >= 0):
            raise ConfigError(f"ground friction must be >= 0, got {self.friction}")
        if not (np.isfinite(self.friction_speed) and self.friction_speed > 0):
            raise ConfigError(f"friction_speed must be > 0 m/s, got {self.friction_speed}")


@dataclass(frozen=True)
class IterationRecord:
    """One entry of `Simulation.history`: G and the largest |f_i| after `iteration` iterations."""

    iteration: int
    energy: float
    max_residual: float


def _index_mask(value, n: int, name: str) -> np.ndarray:
    """A boolean (n,) mask from None, a boolean mask or an index array."""
    if value is None:
        return np.zeros(n, dtype=bool)
    arr = np.asarray(value)
    if arr.dtype == bool:
        if arr.shape != (n,):
            raise ConfigError(f"{name} mask has shape {arr.shape}, expected ({n},) for {n} vertices")
        return arr.copy()
    if arr.size and not np.issubdtype(arr.dtype, np.integer):
        raise ConfigError(f"{name} must be a boolean mask or integer vertex indices, got {arr.dtype}")
    arr = arr.astype(np.int64).ravel()
    if arr.size and (arr.min() < 0 or arr.max() >= n):
        raise ConfigError(f"{name} has vertex indices outside 0..{n - 1}")
    mask = np.zeros(n, dtype=bool)
    mask[arr] = True
    return mask


def _positive(value, name: str, unit: str) -> float:
    if not isinstance(value, (int, float, np.integer, np.floating)) or not np.isfinite(value) or value <= 0:
        raise ConfigError(f"{name} must be a positive number of {unit}, got {value!r}")
    return float(value)


def _count(value, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ConfigError(f"{name} must be an integer >= 1, got {value!r}")
    return int(value)


@ti.data_oriented
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
    precision: "float64" or "float32"; arch: "cpu" or "gpu"; record_history: keep G and max |f_i|
    after every iteration of the last step in `history`.
    """

    def __init__(self, mesh: TetMesh, material: Material, dt: float = 1 / 60, gravity=(0.0, 0.0, -9.81),
                 fixed=None, iterations: int = 100, initial_guess: InitialGuess = InitialGuess.ADAPTIVE,
                 chebyshev_rho: Optional[float] = None, damping: float = 0.0, ground: Optional[Ground] = None,
                 tolerance: Optional[float] = None, check_every: int = 5, kinematic=None,
                 kinematic_motion: Optional[Callable] = None, precision="float64", arch: str = "cpu",
                 coloring_order: VertexOrder = VertexOrder.NATURAL, record_history: bool = False):
        if not isinstance(mesh, TetMesh):
            raise ConfigError(f"mesh must be a solver.TetMesh, got {type(mesh).__name__}; "
                              "use solver.load_mesh or solver.box_mesh")
        if not isinstance(material, Material):
            raise ConfigError(f"material must be a solver.Material, got {type(material).__name__}")
        if not isinstance(initial_guess, InitialGuess):
            raise ConfigError(f"initial_guess must be a solver.InitialGuess, got {initial_guess!r}")
        if ground is not None and not isinstance(ground, Ground):
            raise ConfigError(f"ground must be a solver.Ground or None, got {type(ground).__name__}")
        self.mesh = mesh
        self.material = material
        self._dt = _positive(dt, "dt", "seconds")
        self.iterations = _count(iterations, "iterations")
        self.gravity = np.asarray(gravity, dtype=np.float64)
        if self.gravity.shape != (3,) or not np.isfinite(self.gravity).all():
            raise ConfigError(f"gravity must be three finite numbers in m/s^2, got {gravity!r}")
        self.initial_guess = initial_guess
        if chebyshev_rho is not None and not (0.0 < chebyshev_rho < 1.0):
            raise ConfigError(f"chebyshev_rho must be in (0, 1), got {chebyshev_rho!r}")
        self.chebyshev_rho = chebyshev_rho
        if not (np.isfinite(damping) and damping >= 0):
            raise ConfigError(f"damping must be >= 0 seconds, got {damping!r}")
        self.damping = float(damping)
        self.ground = ground
        self.tolerance = None if tolerance is None else _positive(tolerance, "tolerance", "(relative)")
        self.check_every = _count(check_every, "check_every")
        self.precision = as_precision(precision)
        self.record_history = bool(record_history)
        n = mesh.n_vertices
        fixed_mask = _index_mask(fixed, n, "fixed")
        kinematic_mask = _index_mask(kinematic, n, "kinematic")
        if kinematic_mask.any() and kinematic_motion is None:
            raise ConfigError("kinematic vertices need kinematic_motion(t, rest) -> (K, 3) positions")
        if kinematic_motion is not None and not callable(kinematic_motion):
            raise ConfigError("kinematic_motion must be a function (t, rest) -> (K, 3) positions")
        self.kinematic_motion = kinematic_motion
        self.fixed_mask = fixed_mask & ~kinematic_mask
        self.kinematic_mask = kinematic_mask
        self.free_mask = ~(fixed_mask | kinematic_mask)
        if not self.free_mask.any():
            raise ConfigError("every vertex is fixed or kinematic; nothing is left to simulate")
        ensure_taichi(arch)

        require_implemented(vertex_force_hessian, Simulation._force_hessian, Simulation._solve_vertex)
        if chebyshev_rho is not None:
            require_implemented(Simulation._chebyshev_omega, Simulation._chebyshev)
        self.coloring: Coloring = color_vertices(mesh.tets, n, coloring_order, key=mesh.topology_key())
        self._build_fields()
        self.history: list[IterationRecord] = []
        self.last_iterations = 0
        self.time = 0.0
        self.frame = 0
        self._in_step = False
        self.reset()

    # -----------------------------------------------------------------------------------------
    # Set-up: everything is allocated and uploaded once, here.
    # -----------------------------------------------------------------------------------------
    def _build_fields(self):
        mesh, dtype = self.mesh, self.precision.ti_dtype
        n, m = mesh.n_vertices, mesh.n_tets
        self.dtype = dtype
        self.x = ti.Vector.field(3, dtype, n)        # current iterate x
        self.x_n = ti.Vector.field(3, dtype, n)      # positions at the start of the step
        self.v = ti.Vector.field(3, dtype, n)        # velocities v_n
        self.v_prev = ti.Vector.field(3, dtype, n)   # v_{n-1}, for the adaptive initial guess
        self.y = ti.Vector.field(3, dtype, n)        # inertial target y
        self.mass = ti.field(dtype, n)               # lumped masses m_i
        self.free = ti.field(ti.i32, n)              # 1 for vertices VBD solves
        self.f = ti.Vector.field(3, dtype, n)        # residual f_i, filled on request
        self.H = ti.Matrix.field(3, 3, dtype, n)     # local Hessian H_i, filled on request
        self.tets = ti.Vector.field(4, ti.i32, m)
        self.Dm_inv = ti.Matrix.field(3, 3, dtype, m)
        self.vol = ti.field(dtype, m)
        self.h = ti.field(dtype, ())
        self.mu = ti.field(dtype, ())
        self.lam = ti.field(dtype, ())
        self.g = ti.Vector.field(3, dtype, ())

        X = mesh.vertices
        T = mesh.tets
        Dm = np.stack([X[T[:, k]] - X[T[:, 0]] for k in (1, 2, 3)], axis=-1)
        Dm_inv = np.linalg.inv(Dm)
        vol = np.abs(np.linalg.det(Dm)) / 6.0
        rows = np.concatenate([-Dm_inv.sum(axis=1, keepdims=True), Dm_inv], axis=1)   # (M, 4, 3): m_k
        self._rest_vol = vol
        self._grad_rows = rows
        self.tets.from_numpy(T)
        self.Dm_inv.from_numpy(Dm_inv)
        self.vol.from_numpy(vol)

        self.free.from_numpy(self.free_mask.astype(np.int32))

        # Colour sets with fixed and kinematic vertices left out: slot k of `color_order` holds a
        # vertex id, sorted by colour, and colour c owns the slots in `_color_ranges[c]`.
        colors = np.where(self.free_mask, self.coloring.colors, -1)
        order = np.argsort(colors, kind="stable")
        order = order[colors[order] >= 0].astype(np.int32)
        counts = np.bincount(colors[order])
        counts = counts[counts > 0]
        ends = np.cumsum(counts)
        self._color_ranges = tuple((int(e - c), int(e)) for c, e in zip(counts, ends))
        self.color_order = ti.field(ti.i32, len(order))
        self.color_order.from_numpy(order)

        # Slot-major copy of the tets around each free vertex i, so that one colour reads one
        # sequential stream (lecture notes, chapter 3, "Computing f_i fast"): for each tet, its
        # other vertices j1, j2, j3; q = (m_j . m_i)_j so that F m_i = sum_j (x_j - x_i) q_j;
        # c = 1 / det(Ds) at rest with Ds = [x_j - x_i], so that J = c det(Ds); |m_i|^2; volume.
        offsets, adj_tet, adj_local = vertex_tet_adjacency(T, n)
        degree = np.diff(offsets)[order]
        slot_offsets = np.concatenate([[0], np.cumsum(degree)])
        entry = np.repeat(offsets[order] - slot_offsets[:-1], degree) + np.arange(slot_offsets[-1])
        adj_tet, adj_local = adj_tet[entry], adj_local[entry]
        others = (adj_local[:, None] + np.arange(1, 4)[None, :]) % 4                  # (E, 3)
        m_i = rows[adj_tet, adj_local]                                                  # (E, 3)
        m_j = np.take_along_axis(rows[adj_tet], others[:, :, None], axis=1)             # (E, 3, 3)
        j = np.take_along_axis(T[adj_tet], others, axis=1)
        Ds = (X[j] - X[T[adj_tet, adj_local]][:, None, :]).transpose(0, 2, 1)
        n_entries = len(adj_tet)
        self.adj_offsets = ti.field(ti.i32, len(order) + 1)
        self.adj_others = ti.Vector.field(3, ti.i32, n_entries)
        self.adj_q = ti.Vector.field(3, dtype, n_entries)
        self.adj_c = ti.field(dtype, n_entries)
        self.adj_m_sq = ti.field(dtype, n_entries)
        self.adj_vol = ti.field(dtype, n_entries)
        self.adj_offsets.from_numpy(slot_offsets.astype(np.int32))
        self.adj_others.from_numpy(j.astype(np.int32))
        self.adj_q.from_numpy(np.einsum("ejk,ek->ej", m_j, m_i))
        self.adj_c.from_numpy(1.0 / np.linalg.det(Ds))
        self.adj_m_sq.from_numpy(np.einsum("ek,ek->e", m_i, m_i))
        self.adj_vol.from_numpy(vol[adj_tet])

        kin = np.flatnonzero(self.kinematic_mask).astype(np.int32)
        self._kinematic_rest = X[kin]
        if len(kin):
            self.kin_ids = ti.field(ti.i32, len(kin))
            self.kin_target = ti.Vector.field(3, dtype, len(kin))
            self.kin_ids.from_numpy(kin)
        if self.chebyshev_rho is not None:
            self.x_prev = ti.Vector.field(3, dtype, n)    # x^(k-1)
            self.x_prev2 = ti.Vector.field(3, dtype, n)   # x^(k-2)
        self._has_ground = self.ground is not None
        self._accelerated = self.chebyshev_rho is not None
        self.set_material(self.material)
        self.h[None] = self._dt
        self.g[None] = self.gravity

    # -----------------------------------------------------------------------------------------
    # Public state access
    # -----------------------------------------------------------------------------------------
    @property
    def dt(self) -> float:
        """Time step h in seconds (settable)."""
        return self._dt

    @dt.setter
    def dt(self, value):
        self._dt = _positive(value, "dt", "seconds")
        self.h[None] = self._dt

    @property
    def positions(self) -> np.ndarray:
        """(N, 3) float64 copy of the current positions x."""
        return self.x.to_numpy().astype(np.float64)

    @property
    def velocities(self) -> np.ndarray:
        """(N, 3) float64 copy of the velocities v."""
        return self.v.to_numpy().astype(np.float64)

    @property
    def colors(self) -> np.ndarray:
        """(N,) int32 colour of every vertex, -1 for fixed and kinematic vertices."""
        return np.where(self.free_mask, self.coloring.colors, -1).astype(np.int32)

    @property
    def n_colors(self) -> int:
        return len(self._color_ranges)

    @property
    def masses(self) -> np.ndarray:
        """(N,) lumped vertex masses in kg."""
        return self.mass.to_numpy().astype(np.float64)

    def set_material(self, material: Material) -> None:
        """Change E, nu and density without rebuilding anything."""
        if not isinstance(material, Material):
            raise ConfigError(f"material must be a solver.Material, got {type(material).__name__}")
        self.material = material
        self.mu[None] = material.mu
        self.lam[None] = material.lam
        mass = np.zeros(self.mesh.n_vertices)
        np.add.at(mass, self.mesh.tets.ravel(), np.repeat(material.density * self._rest_vol / 4.0, 4))
        self.mass.from_numpy(mass)

    def set_positions(self, x: np.ndarray) -> None:
        """Overwrite the positions (N, 3) in metres, e.g. to start from a deformed state."""
        self.x.from_numpy(self._checked_state(x, "positions"))

    def set_velocities(self, v: np.ndarray) -> None:
        """Overwrite the velocities (N, 3) in m/s; the adaptive guess treats this as free fall."""
        v = self._checked_state(v, "velocities")
        self.v.from_numpy(v)
        self.v_prev.from_numpy(v - self._dt * self.gravity)

    def _checked_state(self, a, name):
        a = np.asarray(a, dtype=np.float64)
        if a.shape != (self.mesh.n_vertices, 3):
            raise ConfigError(f"{name} must have shape ({self.mesh.n_vertices}, 3), got {a.shape}")
        if not np.isfinite(a).all():
            raise ConfigError(f"{name} contain NaN or infinite values")
        return a

    def reset(self) -> None:
        """Back to the rest shape at rest, time 0."""
        self.x.from_numpy(self.mesh.vertices)
        self.x_n.from_numpy(self.mesh.vertices)
        self.set_velocities(np.zeros_like(self.mesh.vertices))
        self.time = 0.0
        self.frame = 0
        self._in_step = False

    # -----------------------------------------------------------------------------------------
    # The time step
    # -----------------------------------------------------------------------------------------
    def step(self, n: int = 1) -> None:
        """Advance `n` time steps."""
        for _ in range(_count(n, "n")):
            self.begin_step()
            self.run_iterations(self.iterations)
            self.end_step()

    def begin_step(self) -> None:
        """Save x_n, move kinematic vertices to their targets at t + h, predict y, set the guess."""
        if self._in_step:
            raise ConfigError("begin_step() called twice; call end_step() first")
        self._in_step = True
        self._save_start()
        if self.kinematic_mask.any():
            self.kin_target.from_numpy(self._kinematic_targets(self.time + self._dt))
            self._place_kinematic()
        self._predict(self.initial_guess)
        self._iteration = 0
        self.last_iterations = 0
        self.history = []
        if self.chebyshev_rho is not None:
            self._chebyshev_start()
        self._omega = 1.0
        self._stop_below = None
        if self.tolerance is not None:
            weight = float(self.masses.max() * np.linalg.norm(self.gravity))
            eps = np.finfo(np.float64 if self.dtype == ti.f64 else np.float32).eps
            roundoff = 100 * eps * self.material.mu * float(np.mean(self._rest_vol)) ** (2 / 3)
            self._stop_below = max(self.tolerance * max(self.max_residual(), weight), roundoff)
        if self.record_history:
            self.history.append(IterationRecord(0, self.energy(), self.max_residual()))

    def run_iterations(self, k: int) -> int:
        """Run up to `k` VBD iterations of the current step; returns how many ran."""
        if not self._in_step:
            raise ConfigError("run_iterations() needs begin_step() first")
        ran = 0
        for _ in range(_count(k, "k")):
            self._iteration += 1
            self._omega = self._chebyshev_omega(self._iteration, self._omega)
            self._iterate(self._omega)
            ran += 1
            if self.record_history:
                self.history.append(IterationRecord(self._iteration, self.energy(), self.max_residual()))
            if (self._stop_below is not None and self._iteration % self.check_every == 0
                    and self.max_residual() <= self._stop_below):
                break
        self.last_iterations = self._iteration
        return ran

    def end_step(self) -> None:
        """v = (x - x_n) / h; advance the clock."""
        if not self._in_step:
            raise ConfigError("end_step() needs begin_step() first")
        self._update_velocity()
        self._in_step = False
        self.time += self._dt
        self.frame += 1

    def _chebyshev_omega(self, k: int, omega_prev: float) -> float:
        """Chebyshev weight omega_k (VBD Eq. 19): 1, 2/(2 - rho^2), 4/(4 - rho^2 omega_{k-1})."""
        rho = self.chebyshev_rho
        if rho is None:
            return 1.0
        # BEGIN SOLUTION task=chebyshev
        if k == 1:
            return 1.0
        if k == 2:
            return 2.0 / (2.0 - rho * rho)
        return 4.0 / (4.0 - rho * rho * omega_prev)
        # END SOLUTION

    def _kinematic_targets(self, t: float) -> np.ndarray:
        target = np.asarray(self.kinematic_motion(t, self._kinematic_rest.copy()), dtype=np.float64)
        if target.shape != self._kinematic_rest.shape or not np.isfinite(target).all():
            raise ConfigError(f"kinematic_motion must return finite positions of shape "
                              f"{self._kinematic_rest.shape}, got {target.shape}")
        return target

    # -----------------------------------------------------------------------------------------
    # Kernels
    # -----------------------------------------------------------------------------------------
    @ti.kernel
    def _save_start(self):
        for i in self.x:
            self.x_n[i] = self.x[i]

    @ti.kernel
    def _place_kinematic(self):
        for k in self.kin_ids:
            self.x[self.kin_ids[k]] = self.kin_target[k]

    @ti.kernel
    def _predict(self, guess: ti.template()):
        """y = x_n + h v_n + h^2 g (VBD Eq. 2) and the initial guess (VBD Sec. 3.7) for free vertices."""
        h = self.h[None]
        g = self.g[None]
        g2 = g.dot(g)
        for i in self.x:
            self.y[i] = self.x_n[i] + h * self.v[i] + h * h * g
            if self.free[i]:
                if ti.static(guess == InitialGuess.PREVIOUS):
                    self.x[i] = self.x_n[i]
                elif ti.static(guess == InitialGuess.INERTIA):
                    self.x[i] = self.x_n[i] + h * self.v[i]
                elif ti.static(guess == InitialGuess.INERTIAL):
                    self.x[i] = self.y[i]
                else:
                    a_tilde = ti.cast(0.0, self.dtype)
                    if g2 > 0:
                        a_n = (self.v[i] - self.v_prev[i]) / h
                        a_tilde = ti.math.clamp(a_n.dot(g) / g2, 0.0, 1.0)
                    self.x[i] = self.x_n[i] + h * self.v[i] + h * h * a_tilde * g

    @ti.func
    def _deformation_gradient(self, t):
        """F = Ds Dm^-1 of tet t at the current positions."""
        a, b, c, d = self.tets[t][0], self.tets[t][1], self.tets[t][2], self.tets[t][3]
        x0 = self.x[a]
        Ds = ti.Matrix.cols([self.x[b] - x0, self.x[c] - x0, self.x[d] - x0])
        return Ds @ self.Dm_inv[t]

    @ti.func
    def _tet_kinematics(self, i, e):
        """F m_i, J = det F and w = dJ/dx_i of the tet behind adjacency entry e of vertex i.

        With d_j = x_j - x_i for the other three vertices: F m_i = sum_j q_j d_j, and
        det(Ds) = d_1 . n with n = (d_2 - d_1) x (d_3 - d_1) the area normal of the face opposite i,
        so J = c d_1 . n and w = dJ/dx_i = -c n. No 3x3 matrix product is needed.
        """
        x_i = self.x[i]
        j = self.adj_others[e]
        d1 = self.x[j[0]] - x_i
        d2 = self.x[j[1]] - x_i
        d3 = self.x[j[2]] - x_i
        n = (d2 - d1).cross(d3 - d1)
        c = self.adj_c[e]
        q = self.adj_q[e]
        return q[0] * d1 + q[1] * d2 + q[2] * d3, c * d1.dot(n), -c * n

    @ti.func
    def _force_hessian(self, k):
        """f_i = -dG/dx_i and H_i = d2G/dx_i2 of the vertex i in colour slot k, at the current x.

        VBD [Chen et al. 2024] Eq. 5-6: inertia, elasticity of the tets around i, then the optional
        damping (Eq. 10-11) and ground contact, which compile away when a scene does not use them.
        """
        i = self.color_order[k]
        h = self.h[None]
        mu, lam = self.mu[None], self.lam[None]
        # BEGIN SOLUTION task=vbd_sweep
        m_h2 = self.mass[i] / (h * h)
        f = m_h2 * (self.y[i] - self.x[i])
        H = ti.Matrix.diag(3, m_h2)
        f_el = ti.Vector.zero(self.dtype, 3)
        H_el = ti.Matrix.zero(self.dtype, 3, 3)
        for e in range(self.adj_offsets[k], self.adj_offsets[k + 1]):
            Fm, J, w = self._tet_kinematics(i, e)
            df, dH = vertex_force_hessian(Fm, J, w, self.adj_m_sq[e], self.adj_vol[e], mu, lam)
            f_el += df
            H_el += dH
        f += f_el
        H += H_el
        # END SOLUTION
        if ti.static(self.damping > 0):
            k_d = ti.static(self.damping)
            f -= (k_d / h) * (H_el @ (self.x[i] - self.x_n[i]))
            H += (k_d / h) * H_el
        if ti.static(self._has_ground):
            k_c = ti.static(self.ground.stiffness)
            depth = ti.static(self.ground.height) - self.x[i][2]
            if depth > 0:
                f[2] += k_c * depth
                H[2, 2] += k_c
                if ti.static(self.ground.friction > 0):
                    # Lagged, smoothed Coulomb friction on the tangential displacement of this step.
                    mu_f = ti.static(self.ground.friction)
                    eps_u = ti.static(self.ground.friction_speed) * h
                    u = self.x[i] - self.x_n[i]
                    u[2] = 0.0
                    s = u.norm()
                    scale = (2.0 - s / eps_u) / eps_u   # f1(s)/s of IPC's smoothed friction
                    if s >= eps_u:
                        scale = 1.0 / s
                    k_f = mu_f * k_c * depth * scale
                    f -= k_f * u
                    H[0, 0] += k_f
                    H[1, 1] += k_f
        return f, H

    @ti.func
    def _solve_vertex(self, k):
        """x_i <- x_i + H_i^-1 f_i for the vertex i in colour slot k, skipping a (near) singular H_i
        (VBD Alg. 1, lines 7-10)."""
        # BEGIN SOLUTION task=vbd_sweep
        i = self.color_order[k]
        f, H = self._force_hessian(k)
        det = H.determinant()
        if ti.abs(det) > 1e-15 * H.norm_sqr() ** 1.5:
            self.x[i] += H.inverse() @ f
        # END SOLUTION

    def _iterate(self, omega: float) -> None:
        """One VBD iteration: each colour in turn, all vertices of a colour in parallel, then the
        optional Chebyshev step (VBD Eq. 18)."""
        for start, end in self._color_ranges:
            self._solve_color(start, end)
        if self._accelerated:
            self._chebyshev(omega)

    @ti.kernel
    def _solve_color(self, start: ti.i32, end: ti.i32):
        """Solve every vertex of one colour, in parallel: no two of them share a tet."""
        for k in range(start, end):
            self._solve_vertex(k)

    @ti.kernel
    def _chebyshev(self, omega: ti.f64):
        """x = omega (x - x^(k-2)) + x^(k-2) for the free vertices (VBD Eq. 18)."""
        for k in self.color_order:
            i = self.color_order[k]
            # BEGIN SOLUTION task=chebyshev
            x_accel = ti.cast(omega, self.dtype) * (self.x[i] - self.x_prev2[i]) + self.x_prev2[i]
            self.x_prev2[i] = self.x_prev[i]
            self.x_prev[i] = x_accel
            self.x[i] = x_accel
            # END SOLUTION

    @ti.kernel
    def _chebyshev_start(self):
        for i in self.x:
            self.x_prev[i] = self.x[i]
            self.x_prev2[i] = self.x[i]

    @ti.kernel
    def _update_velocity(self):
        inv_h = 1.0 / self.h[None]
        for i in self.x:
            self.v_prev[i] = self.v[i]
            self.v[i] = (self.x[i] - self.x_n[i]) * inv_h

    @ti.kernel
    def _compute_residual(self) -> ti.f64:
        """Fill `f` with f_i (zero at fixed and kinematic vertices); return max_i |f_i|."""
        for i in self.f:
            self.f[i] = ti.Vector.zero(self.dtype, 3)
        result = ti.cast(0.0, ti.f64)
        for k in self.color_order:
            f, _ = self._force_hessian(k)
            self.f[self.color_order[k]] = f
            ti.atomic_max(result, ti.cast(f.norm(), ti.f64))
        return result

    @ti.kernel
    def _compute_local_systems(self):
        for i in self.f:
            self.f[i] = ti.Vector.zero(self.dtype, 3)
            self.H[i] = ti.Matrix.zero(self.dtype, 3, 3)
        for k in self.color_order:
            f, H = self._force_hessian(k)
            self.f[self.color_order[k]] = f
            self.H[self.color_order[k]] = H

    @ti.kernel
    def _energy(self) -> ti.f64:
        G = ti.cast(0.0, ti.f64)
        h = self.h[None]
        for i in self.x:
            if self.free[i]:
                d = self.x[i] - self.y[i]
                G += ti.cast(0.5 * self.mass[i] / (h * h) * d.dot(d), ti.f64)
                if ti.static(self._has_ground):
                    depth = ti.static(self.ground.height) - self.x[i][2]
                    if depth > 0:
                        G += ti.cast(0.5 * ti.static(self.ground.stiffness) * depth * depth, ti.f64)
        for t in self.tets:
            G += ti.cast(self.vol[t] * psi(self._deformation_gradient(t), self.mu[None], self.lam[None]), ti.f64)
        return G

    # -----------------------------------------------------------------------------------------
    # Measurements
    # -----------------------------------------------------------------------------------------
    def energy(self) -> float:
        """Incremental potential G(x) in J at the current positions, for the current step's y.

        Damping and friction are not potentials and are not included.
        """
        return float(self._energy())

    def residual(self) -> np.ndarray:
        """(N, 3) float64 per-vertex force residual f_i = -dG/dx_i (0 at fixed/kinematic vertices)."""
        self._compute_residual()
        return self.f.to_numpy().astype(np.float64)

    def local_systems(self):
        """Per-vertex f_i (N, 3) and H_i (N, 3, 3) at the current positions (zero at constrained
        vertices): the 3x3 system each vertex solves, for plots and tests."""
        self._compute_local_systems()
        return self.f.to_numpy().astype(np.float64), self.H.to_numpy().astype(np.float64)

    def max_residual(self) -> float:
        """max_i |f_i| in newtons."""
        return float(self._compute_residual())

    def inertial_target(self) -> np.ndarray:
        """(N, 3) y = x_n + h v_n + h^2 g for a step taken from the current state."""
        return self.positions + self._dt * self.velocities + self._dt ** 2 * self.gravity

    def step_problem(self):
        """The minimisation the next `step()` solves, as a `StepProblem` for the Newton reference."""
        from .newton import StepProblem

        x = self.positions
        if self._in_step:
            raise ConfigError("step_problem() is defined between steps; call end_step() first")
        targets = x.copy()
        if self.kinematic_mask.any():
            targets[self.kinematic_mask] = self._kinematic_targets(self.time + self._dt)
        if self.damping > 0 or (self.ground is not None and self.ground.friction > 0):
            raise ConfigError("the Newton reference minimises G, which has no damping or friction; "
                              "set damping=0 and ground friction=0 to compare against it")
        return StepProblem(tets=self.mesh.tets, grad_rows=self._grad_rows, volumes=self._rest_vol,
                           masses=self.masses, y=self.inertial_target(), free=self.free_mask.copy(),
                           constrained_positions=targets, h=self._dt, mu=self.material.mu,
                           lam=self.material.lam, ground=self.ground)

    def newton_reference(self, tolerance: float = 1e-10, max_iterations: int = 50, x0=None) -> np.ndarray:
        """(N, 3) converged global Newton solution x* of the next step, from the current state.

        x0: (N, 3) start of the Newton iterations (default y); the simulation itself is not changed.
        To measure a VBD step cheaply, build `problem = sim.step_problem()` before `sim.step()` and
        warm-start `solver.newton_solve(problem, sim.positions)` after it.
        """
        from .newton import newton_solve

        problem = self.step_problem()
        start = problem.y_with_constraints() if x0 is None else self._checked_state(x0, "x0")
        return newton_solve(problem, start, tolerance, max_iterations).x
