"""The terms of G (lecture notes ch. 1): inertia (`inertia`), elasticity (`material`), ground contact and
friction (`ground`), contact between bodies (`contact`, `contact_detection`).

Each term is written once, as `ti.func`s with numpy twins: its energy, gradient, per-vertex 3x3 block
and per-tet Hessian blocks. Every solver (the VBD sweep, energy(), the Taichi Newton, the PCG products,
the two-level coarse operator, the translation correction) calls these; the numpy Newton oracle keeps
its own assembly as the independent check. Imports only the mesh wing and the root utilities.
"""
from .ground import Ground
from .material import Material
from .contact import Contact
