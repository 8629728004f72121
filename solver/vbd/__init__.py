"""The lecture's solver: Vertex Block Descent [Chen et al. 2024].

`simulation` (the driver: step -> predict y -> iterations -> colours -> velocity; its plumbing in
`settings`, `state` and `global_methods`, the steps of the global methods), `implicit_euler`
(predict y, update v), `vertex_solve` (f_i, H_i and the 3x3 step of one vertex, Alg. 1),
`chebyshev` (Sec. 3.8), `orientation` (inversion-free guesses), `translation` (the rigid-translation
correction), `energy` (G over the whole mesh), `layout` (the array layout the kernels share).
"""
from .implicit_euler import InitialGuess
from .simulation import IterationRecord, Settings, Simulation
