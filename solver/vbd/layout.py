"""How a simulation's state and settings are laid out in the arrays its kernels share.

Every kernel of the solver is a module-level `ti.kernel` taking `ti.types.ndarray()` arguments, so it
is compiled once per process and shared by every `Simulation`; a kernel launch passes a handful of
arrays, so the per-vertex 3-vectors live as rows of one (STATE_ROWS, N) array of 3-vectors and the
scalar settings as one (PARAM_COUNT,) array.

Why the kernels list their arrays one by one instead of taking one argument pack: Taichi 1.7.4's
`ti.types.argpack` does hold ndarrays on the CPU (same results, one compile per dtype), but launching
costs more: nine ndarrays in one pack 67 us a launch, as nine arguments 54 us; one ndarray 22 against
18 us (CPU time, interleaved runs on a loaded 2-core machine, 2026-11-24). And Quadrants has no argument
packs (it takes Python dataclasses of ndarrays, which Taichi 1.7.4 refuses), so no grouped signature
runs on both. The settings are an ndarray, not a `ti.types.struct`: a kernel taking an ndarray and 13
floats costs 140 us a launch with the floats as a struct, 22 us with them as a second ndarray.
"""
from .._ti import ti

# Rows of `state`, shape (STATE_ROWS, N) of 3-vectors.
X = 0          # current iterate x
X_N = 1        # positions at the start of the step, x_n
Y = 2          # inertial target y = x_n + h v_n + h^2 g
V = 3          # velocities v_n
V_PREV = 4     # velocities v_{n-1}, for the adaptive initial guess
X_PREV = 5     # x^(k-1), for Chebyshev acceleration
X_PREV2 = 6    # x^(k-2), for Chebyshev acceleration
STATE_ROWS = 7

# Entries of `params`, shape (PARAM_COUNT,), same float type as the state.
TIME_STEP = 0         # time step h in s
MU = 1                # Neo-Hookean mu in Pa
LAM = 2               # Neo-Hookean lambda in Pa
DAMPING = 3           # k_d in s (VBD Eq. 10-11), 0 for none
GROUND = 4            # 1 with a ground plane, 0 without
GROUND_HEIGHT = 5     # z of the plane in m
GROUND_STIFFNESS = 6  # k_c in N/m
FRICTION = 7          # Coulomb mu_f
FRICTION_SPEED = 8    # sliding speed below which friction is smoothed, m/s
GRAVITY_X = 9         # gravity g in m/s^2, three entries
KEEP_ORIENTATION = 12  # 1: no vertex step may invert a tet (`vertex_solve.step_limit`), 0: plain VBD
PARAM_COUNT = 13

# Columns of the per-entry adjacency array `adj_f`, shape (E, 6): q (3), c, |m_i|^2, rest volume.
Q = 0
C = 3
M_SQ = 4
VOLUME = 5
ADJ_FLOATS = 6


@ti.kernel
def write_row(state: ti.types.ndarray(), row: ti.i32, values: ti.types.ndarray(dtype=ti.f64, ndim=2),
              dtype: ti.template(), serial: ti.template()):
    """state[row, i] = values[i] for values (N, 3) float64 (a numpy array: one launch, no staging array),
    rounded to the state's float type dtype as numpy's astype rounds; serial: on one thread (small
    meshes on the CPU, `vertex_solve.serial_sweep`)."""
    ti.loop_config(serialize=serial)
    for i in range(values.shape[0]):
        state[row, i] = ti.cast(ti.Vector([values[i, 0], values[i, 1], values[i, 2]]), dtype)


@ti.kernel
def read_row(state: ti.types.ndarray(), row: ti.i32, out: ti.types.ndarray(dtype=ti.f64, ndim=2),
             serial: ti.template()):
    """out[i] = state[row, i] for out (N, 3) float64 (a numpy array): one row of the state, so that reading
    positions copies N, not 7N, vectors, in one launch; serial as in `write_row`."""
    ti.loop_config(serialize=serial)
    for i in range(out.shape[0]):
        x = ti.cast(state[row, i], ti.f64)
        for k in ti.static(range(3)):
            out[i, k] = x[k]
