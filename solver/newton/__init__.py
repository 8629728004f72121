"""Global solvers: the numpy Newton oracle (`oracle`, with contact `contact_term`; the independent check),
the Taichi Newton with a sparse direct solver (`direct`, `hessian`, with contact `contact_pairs`),
Newton-PCG (`pcg`) and two-level VBD (`multilevel`, `prolongation`). They read the terms of G from the
physics wing.
"""
from .direct import LinearSolver, fast_newton_solve
from .damped_newton import NewtonResult
from .oracle import StepProblem, newton_solve
from .pcg import Preconditioner, newton_pcg
