"""Helpers shared by the graded tests."""
import importlib

import numpy as np

from demo.homework import TASKS_BY_ID
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
    import solver

    material = solver.Material(youngs_modulus=youngs_modulus, poisson_ratio=0.3, density=1000.0)
    fixed = mesh.vertices[:, 0] < mesh.vertices[:, 0].min() + 1e-9
    kwargs.setdefault("initial_guess", solver.InitialGuess.INERTIAL)
    return solver.Simulation(mesh, material, dt=1 / 60, fixed=fixed, **kwargs)


def random_rotation(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q
