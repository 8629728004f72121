"""Helpers shared by the graded tests."""
import importlib
from pathlib import Path

import numpy as np

from demo.homework import REFERENCE_CASES, REFERENCE_FILE, TASKS_BY_ID, cantilever, measurements
from solver.todo import require_implemented


def _resolve(spec: str):
    """'solver/vbd/vertex_solve.py:newton_step' -> the function object."""
    path, name = spec.split(":")
    obj = importlib.import_module(path[:-3].replace("/", "."))
    for part in name.split("."):
        obj = getattr(obj, part)
    return obj


def require(task_id: str) -> None:
    """Fail with the TODO message of `task_id`, then of the tasks it builds on, if any is unfinished."""
    task = TASKS_BY_ID[task_id]
    require_implemented(*[_resolve(spec) for spec in task.functions])
    for dependency in task.depends:
        try:
            require_implemented(*[_resolve(spec) for spec in TASKS_BY_ID[dependency].functions])
        except NotImplementedError as e:
            raise NotImplementedError(f"{e} (task {task_id} builds on it)") from None


def bar(cells=(8, 2, 2), size=(0.4, 0.1, 0.1)):
    import solver

    return solver.box_mesh(size=size, cells=cells)


def simulation(mesh, youngs_modulus=1e4, **kwargs):
    """A cantilever: the mesh pinned at x = min, nu = 0.3, rho = 1000, h = 1/60, float64, CPU."""
    return cantilever(mesh, youngs_modulus, **kwargs)


def reference(name: str, **kwargs):
    """(simulation of `REFERENCE_CASES[name]` at rest with the settings `kwargs`, its converged first
    step x* (N, 3))."""
    return REFERENCE_CASES[name].simulation(**kwargs), stored(name)


def stored(name: str):
    """A result of the solution: from `reference.npz` next to this file (written with the starter); in the
    project itself, which has no such file, made by the project (its global Newton, its task 5 answers)."""
    path = Path(__file__).resolve().parent / REFERENCE_FILE
    if path.exists():
        with np.load(path) as data:
            return data[name]
    if name in REFERENCE_CASES:
        return REFERENCE_CASES[name].simulation().newton_reference()
    return measurements()[name]


def random_rotation(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def elastic_gradient(rest, tets, x, mu, lam):
    """(N, 3) dE/dx of E = sum_t vol_t Psi(F_t), from the stress P(F) of solver/physics/material.py.

    rest, x: (N, 3) rest and current positions; tets: (T, 4) vertex ids."""
    from solver.physics.material import dpsi_dF_np

    Dm = np.stack([rest[tets[:, k]] - rest[tets[:, 0]] for k in (1, 2, 3)], axis=-1)
    Ds = np.stack([x[tets[:, k]] - x[tets[:, 0]] for k in (1, 2, 3)], axis=-1)
    Dm_inv = np.linalg.inv(Dm)
    rows = np.concatenate([-Dm_inv.sum(axis=1, keepdims=True), Dm_inv], axis=1)     # (T, 4, 3): dF/dx_k = . m_k
    vol = np.abs(np.linalg.det(Dm)) / 6.0
    per_vertex = vol[:, None, None] * np.einsum("tab,tkb->tka", dpsi_dF_np(Ds @ Dm_inv, mu, lam), rows)
    gradient = np.zeros_like(x)
    np.add.at(gradient, tets, per_vertex)
    return gradient


def elastic_hessian_blocks(rest, tets, x, mu, lam, eps=1e-7):
    """(N, 3, 3) d2E/dx_i2 of every vertex by central differences of `elastic_gradient`."""
    H = np.zeros((len(x), 3, 3))
    for i in range(len(x)):
        for b in range(3):
            xp, xm = x.copy(), x.copy()
            xp[i, b] += eps
            xm[i, b] -= eps
            H[i, :, b] = (elastic_gradient(rest, tets, xp, mu, lam)[i] - elastic_gradient(rest, tets, xm, mu, lam)[i]) / (2 * eps)
    return H


def student_local_systems(mesh, x, density=1000.0, youngs_modulus=1e4):
    """The student's f_i (N, 3) and H_i (N, 3, 3) at positions x (N, 3), inside the first step of a
    cantilever of `mesh` at rest; also y (N, 3), the masses m (N,), h and the free-vertex mask (N,)."""
    import solver

    material = solver.Material(youngs_modulus=youngs_modulus, poisson_ratio=0.3, density=density)
    fixed = mesh.vertices[:, 0] < mesh.vertices[:, 0].min() + 1e-9
    sim = solver.Simulation(mesh, material, dt=1 / 60, fixed=fixed)
    y = sim.inertial_target()
    sim.begin_step()
    sim.set_positions(x)
    f, H = sim.local_systems()
    return f, H, y, sim.masses, sim.dt, sim.free_mask, material
