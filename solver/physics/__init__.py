"""The terms of G (lecture notes ch. 1): elasticity (`material`), ground contact and friction (`ground`),
contact between bodies (`contact`).

Each term is written once, as `ti.func`s with numpy twins; every solver (the VBD sweep, energy(),
the Taichi Newton, the PCG products, the two-level coarse operator, the translation correction) calls
these. Imports only the mesh wing and the root utilities.
"""
from .ground import Ground
from .material import Material
from .contact import Contact
