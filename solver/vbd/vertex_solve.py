"""The VBD sweep: each vertex's force f_i and Hessian H_i, its 3x3 Newton step, one colour at a time.

VBD [Chen et al. 2024] Alg. 1: for each colour, in parallel over its vertices i,

    f_i = m_i/h^2 (y_i - x_i) - sum_{tets t of i} vol_t dPsi/dx_i      (Eq. 5)
    H_i = m_i/h^2 I         + sum_{tets t of i} vol_t d2Psi/dx_i2    (Eq. 6)
    x_i <- x_i + H_i^-1 f_i                                           (Alg. 1, lines 7-10)

plus optional damping (Eq. 10-11) and ground contact; each term of G comes from its file in
solver/physics/ (inertia, material, ground). The kernels are module-level and take arrays
(`layout.py`), so they compile once per process and every `Simulation` shares them; one launch of
`vbd_iteration` runs all colours of one iteration.

Arguments shared by the functions below (S free vertices in colour order, E = their (vertex, tet) pairs):
state (STATE_ROWS, N) 3-vectors; mass (N,) kg; color_order (S,) int32 vertex of each slot;
offsets (S + 1,) int32 first adjacency entry of each slot; others (E, 3) int32; adj_f (E, ADJ_FLOATS);
params (PARAM_COUNT,); see `topology.Topology` and `layout.py`.
"""
from .._ti import running_config, ti

from ..physics.ground import ground_force_hessian
from ..physics.inertia import inertia_block, inertia_gradient
from .layout import (ADJ_FLOATS, C, DAMPING, FRICTION, FRICTION_SPEED, GROUND, GROUND_HEIGHT,
                     GROUND_STIFFNESS, KEEP_ORIENTATION, LAM, M_SQ, MU, Q, TIME_STEP, VOLUME, X,
                     X_N, Y)
from ..physics.material import vertex_force_hessian

assert ADJ_FLOATS == VOLUME + 1
J_MIN = 0.1   # with keep_orientation, no vertex step compresses a tet below a tenth of its rest volume
MAX_CONDITION_F64, MAX_CONDITION_F32 = 1e12, 1e6     # `max_condition`


# Below this many tets a CPU sweep on two threads runs each colour on one thread: the barrier that ends a
# parallel colour costs tens of us on the CPU backend, more than the second thread saves on a mesh up to
# about 40,000 tets. benchmarks/throughput.py, float64, 2 shared cores: 49 ns per tet-iteration in parallel
# colours at 12,000 tets (its results at bed6e26, threshold 6,000) against 28 on one thread now, 37 / 27 at
# 30,240, and at 96,000 18 in parallel against 28 on one thread; the crossover, between those, from a
# soft bar's step timed at 36,000 tets (29.6 in parallel against 27.8). With only one thread, one thread
# whatever the size (96,000 tets: 43 in that thread's parallel loops, 28 now).
SERIAL_SWEEP_TETS = 40000


def serial_sweep(n_tets: int, on_cpu: bool) -> bool:
    """Whether `vbd_iteration` (and the step's other loops) should run each colour serially: on the CPU,
    always with one thread, and with T threads below SERIAL_SWEEP_TETS (1/2) / (1 - 1/T) tets, where the
    share of the work that T - 1 more threads take over pays for the barriers as it does for one more
    (measured on two threads only; the barriers taken to cost the same with more)."""
    if not on_cpu:
        return False
    threads = running_config().cpu_max_num_threads         # Taichi runs: `Simulation` initialised it first
    return threads == 1 or n_tets < SERIAL_SWEEP_TETS * 0.5 / (1 - 1 / threads)


def unrolled_colors(n_colors: int, serial: bool) -> int:
    """The `n_colors` argument of the sweep kernels, a compile-time constant: the colour count when each
    colour is its own parallel loop, 0 for the serial sweep, which reads the count from color_starts when it
    runs, so that one compiled kernel serves every mesh (a new constant means a new compile, about 0.5 s)."""
    return 0 if serial else n_colors


@ti.func
def tet_kinematics(state: ti.template(), x_i, j, a):
    """F m_i, J = det F and w = dJ/dx_i of one tet around vertex i at x_i: j (3,) its other vertices
    (`others[e]`), a (ADJ_FLOATS,) its row of `adj_f`, both read once per adjacency entry e.

    With d_j = x_j - x_i for the other three vertices: F m_i = sum_j q_j d_j, and
    det(Ds) = d_1 . n with n = (d_2 - d_1) x (d_3 - d_1) the area normal of the face opposite i,
    so J = c d_1 . n and w = dJ/dx_i = -c n. No 3x3 matrix product is needed.
    """
    d1 = state[X, j[0]] - x_i
    d2 = state[X, j[1]] - x_i
    d3 = state[X, j[2]] - x_i
    n = (d2 - d1).cross(d3 - d1)
    c = a[C]
    return a[Q] * d1 + a[Q + 1] * d2 + a[Q + 2] * d3, c * d1.dot(n), -c * n


@ti.func
def force_hessian(state: ti.template(), mass: ti.template(), color_order: ti.template(), offsets: ti.template(),
                  others: ti.template(), adj_f: ti.template(), params: ti.template(), k, dtype: ti.template()):
    """f_i = -dG/dx_i and H_i = d2G/dx_i2 of the vertex i in colour slot k, at the current x.

    VBD [Chen et al. 2024] Eq. 5-6: inertia, elasticity of the tets around i, then damping
    (Eq. 10-11) and ground contact when the settings ask for them.
    """
    i = color_order[k]
    h = params[TIME_STEP]
    mu, lam = params[MU], params[LAM]
    x_i = state[X, i]
    # BEGIN SOLUTION task=vbd_sweep
    m_h2 = mass[i] / (h * h)
    f = -inertia_gradient(m_h2, x_i, state[Y, i])
    H = inertia_block(m_h2)
    f_el = ti.Vector.zero(dtype, 3)
    H_el = ti.Matrix.zero(dtype, 3, 3)
    for e in range(offsets[k], offsets[k + 1]):
        a = adj_f[e]
        Fm, J, w = tet_kinematics(state, x_i, others[e], a)
        df, dH = vertex_force_hessian(Fm, J, w, a[M_SQ], a[VOLUME], mu, lam)
        f_el += df
        H_el += dH
    f += f_el
    H += H_el
    # END SOLUTION
    k_d = params[DAMPING]
    if k_d > 0:
        f -= (k_d / h) * (H_el @ (x_i - state[X_N, i]))
        H += (k_d / h) * H_el
    if params[GROUND] > 0:
        f_c, H_c = ground_force_hessian(x_i, x_i - state[X_N, i], h, params[GROUND_HEIGHT],
                                        params[GROUND_STIFFNESS], params[FRICTION], params[FRICTION_SPEED],
                                        dtype)
        f += f_c
        H += H_c
    return f, H


@ti.func
def max_condition(dtype: ti.template()):
    """The largest condition number of H_i that `newton_step` solves: a 3x3 solve loses about
    log10(cond) of the precision's digits, so float64 keeps at least 4 of its 16 and float32 1 of its 7.
    A contact block is stiff along its normal only (the barrier's k against the material's soft
    directions): cond ~ 1e9 is common there and float64 solves it; a test on det H_i / ||H_i||^3, which
    falls as cond^-2, would skip that vertex and freeze it against its partner."""
    limit = MAX_CONDITION_F32
    if ti.static(dtype == ti.f64):
        limit = MAX_CONDITION_F64
    return limit


@ti.func
def step_limit(state: ti.template(), others: ti.template(), adj_f: ti.template(), offsets: ti.template(), i, k, dx):
    """The largest alpha in [0, 1] for which the step x_i + alpha dx keeps det F of every tet around
    vertex i (slot k) at or above J_MIN, or does not shrink it further where it already is below.

    J = det F is affine in x_i with gradient w, so along the step J(alpha) = J + alpha w . dx exactly:
    a tet that shrinks (w . dx < 0) allows alpha <= (J - J_MIN) / -(w . dx).
    """
    alpha = 1.0
    x_i = state[X, i]
    for e in range(offsets[k], offsets[k + 1]):
        _, J, w = tet_kinematics(state, x_i, others[e], adj_f[e])
        dJ = w.dot(dx)
        if J + dJ < J_MIN and dJ < 0:
            alpha = ti.min(alpha, ti.max(J - J_MIN, 0) / -dJ)
    return alpha


@ti.func
def newton_step(f, H, dtype: ti.template()):
    """dx = H_i^-1 f_i, the 3x3 Newton step of a vertex with force f_i (3,) and Hessian H_i (3x3), or 0
    where H_i is singular or too ill-conditioned to solve in this precision (VBD Alg. 1, lines 7-10):
    its condition number ||H_i||_F ||H_i^-1||_F at or above `max_condition(dtype)`."""
    # BEGIN SOLUTION task=vbd_sweep
    dx = ti.Vector.zero(dtype, 3)
    H_inv = H.inverse()
    if H.norm() * H_inv.norm() < max_condition(dtype):
        dx = ti.cast(H_inv @ f, dtype)
    # END SOLUTION
    return dx


@ti.func
def solve_vertex(state: ti.template(), mass: ti.template(), color_order: ti.template(), offsets: ti.template(),
                 others: ti.template(), adj_f: ti.template(), params: ti.template(), k, dtype: ti.template()):
    """x_i <- x_i + dx for the vertex i in colour slot k, the step shortened by `step_limit` when the
    simulation keeps tets from inverting."""
    i = color_order[k]
    f, H = force_hessian(state, mass, color_order, offsets, others, adj_f, params, k, dtype)
    dx = newton_step(f, H, dtype)
    if params[KEEP_ORIENTATION] > 0:
        dx *= ti.cast(step_limit(state, others, adj_f, offsets, i, k, dx), dtype)
    state[X, i] += dx


@ti.kernel
def vbd_iteration(state: ti.types.ndarray(), mass: ti.types.ndarray(), color_order: ti.types.ndarray(),
                  offsets: ti.types.ndarray(), others: ti.types.ndarray(), adj_f: ti.types.ndarray(),
                  color_starts: ti.types.ndarray(), params: ti.types.ndarray(), n_colors: ti.template(),
                  dtype: ti.template(), serial: ti.template()):
    """One VBD iteration: each colour in turn, all vertices of a colour in parallel.

    color_starts (colours + 1,) int32: colour c owns the slots color_starts[c] <= k < color_starts[c + 1].
    serial: one CPU thread visits every slot in order (`serial_sweep`), i.e. colour 0, then colour 1, ...;
    the vertices of a colour are independent, so the result is the same, without a barrier per colour
    (and one loop to compile instead of one per colour). n_colors: `unrolled_colors`.
    """
    if ti.static(serial):
        ti.loop_config(serialize=True)
        for k in range(color_starts[0], color_starts[color_starts.shape[0] - 1]):
            solve_vertex(state, mass, color_order, offsets, others, adj_f, params, k, dtype)
    else:
        for c in ti.static(range(n_colors)):
            for k in range(color_starts[c], color_starts[c + 1]):
                solve_vertex(state, mass, color_order, offsets, others, adj_f, params, k, dtype)


@ti.kernel
def vbd_color(state: ti.types.ndarray(), mass: ti.types.ndarray(), color_order: ti.types.ndarray(),
              offsets: ti.types.ndarray(), others: ti.types.ndarray(), adj_f: ti.types.ndarray(),
              params: ti.types.ndarray(), start: ti.i32, end: ti.i32, dtype: ti.template(), serial: ti.template()):
    """Solve the vertices in slots start <= k < end (one colour), in parallel: no two share a tet (on one
    thread where serial, as `vbd_iteration`)."""
    ti.loop_config(serialize=serial)
    for k in range(start, end):
        solve_vertex(state, mass, color_order, offsets, others, adj_f, params, k, dtype)


@ti.kernel
def local_systems(state: ti.types.ndarray(), mass: ti.types.ndarray(), color_order: ti.types.ndarray(),
                  offsets: ti.types.ndarray(), others: ti.types.ndarray(), adj_f: ti.types.ndarray(),
                  params: ti.types.ndarray(), f_out: ti.types.ndarray(), H_out: ti.types.ndarray(),
                  dtype: ti.template(), serial: ti.template()) -> ti.f64:
    """Fill f_out (N,) 3-vectors and H_out (N,) 3x3 with every free vertex's f_i and H_i (zero at the
    others) at the current x; return max_i |f_i| in N. serial: on one thread, as `vbd_iteration`."""
    ti.loop_config(serialize=serial)
    for i in range(f_out.shape[0]):
        f_out[i] = ti.Vector.zero(dtype, 3)
        H_out[i] = ti.Matrix.zero(dtype, 3, 3)
    result = ti.cast(0.0, ti.f64)
    ti.loop_config(serialize=serial)
    for k in range(color_order.shape[0]):
        f, H = force_hessian(state, mass, color_order, offsets, others, adj_f, params, k, dtype)
        f_out[color_order[k]] = f
        H_out[color_order[k]] = H
        ti.atomic_max(result, ti.cast(f.norm(), ti.f64))
    return result
