"""Which solver minimises G in each time step, and how `Method.AUTO` chooses.

VBD is block Gauss-Seidel: a stiff or finely meshed step, whose elastic waves cross
N_c = h sqrt(E/rho)/dx cells (`wave_cells`), needs about N_c^2 sweeps per decade of error
(lecture notes, chapters 5 and 7). The global methods add the channel VBD lacks.
"""
from enum import Enum

import numpy as np

from .errors import enum_value


class Method(Enum):
    """The solver of each time step of a `Simulation` (what each setting means for each: `vbd/settings.py`)."""

    VBD = "vbd"                  # `iterations` VBD iterations (the lecture's method)
    NEWTON = "newton"            # projected Newton, sparse direct solve (`newton/direct.py`)
    PCG = "pcg"                  # inexact Newton, CG preconditioned by VBD's colour sweep (`newton/pcg.py`)
    MULTILEVEL = "multilevel"    # two-level VBD: coarse-cage correction + VBD sweeps (`newton/multilevel.py`)
    AUTO = "auto"                # VBD where waves cross few cells per step, else two-level VBD


def wave_cells(mesh, material, dt: float) -> float:
    """N_c = h sqrt(E / rho) / dx: how many cells an elastic wave crosses in one step of dt seconds
    (dx: the mesh's typical cell size, (6 x mean tet volume)^(1/3)). VBD needs about N_c^2 sweeps per
    decade of error, a two-level cycle about a constant (lecture notes, chapter 7)."""
    dx = float(np.mean(mesh.rest_volumes()) * 6) ** (1 / 3)
    return float(dt * np.sqrt(material.youngs_modulus / material.density) / dx)


AUTO_VBD_BELOW = 6.0   # N_c under which plain VBD reaches 1e-2 first (benchmarks/results/multilevel; chapter 7)


MULTILEVEL_CYCLE_SWEEPS = 4   # fine sweeps of one two-level cycle: 2 before the coarse correction, 2 after


def multilevel_cycles(iterations: int) -> int:
    """Two-level cycles per step for a budget of `iterations` fine sweeps: whole cycles of 2 + 2 sweeps, the
    budget rounded down (`check_method` refuses a budget below one cycle)."""
    return iterations // MULTILEVEL_CYCLE_SWEEPS


def as_method(value) -> Method:
    """Accept a `Method` or its name ("vbd", "newton", "pcg", "multilevel", "auto")."""
    return enum_value(Method, value, "method")


def choose(wave_cells: float) -> tuple:
    """(method, reason) for `Method.AUTO` given N_c."""
    if wave_cells < AUTO_VBD_BELOW:
        return Method.VBD, (f"N_c = {wave_cells:.1f} cells per step < {AUTO_VBD_BELOW:g}: "
                            "plain VBD carries the step in a few sweeps")
    return Method.MULTILEVEL, (f"N_c = {wave_cells:.1f} cells per step >= {AUTO_VBD_BELOW:g}: VBD alone would "
                               "need about N_c^2 sweeps per decade; two-level VBD adds a coarse channel")
