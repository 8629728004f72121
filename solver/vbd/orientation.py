"""Keeping tets the right way out: an inverted tet (det F <= 0) is a tangle VBD rarely undoes.

Slivers (nearly flat tets) in meshes from other tools invert easily: the first step's guess moves the
free vertices by h v + h^2 g while pinned ones stay, and a sliver beside the pinned set is pulled
through itself before the first iteration; unconverged VBD then never recovers. Two remedies, used
together when a simulation keeps orientation:

* the guess: vertices of tets that the initial guess inverts go back to x_n (repeated until no tet
  that was upright at x_n is inverted, or the whole guess goes back to x_n);
* the iterations: each vertex step is shortened so that no tet around the vertex is compressed below
  a tenth of its rest volume (`vertex_solve.step_limit`), so an upright tet stays upright with a
  margin that round-off cannot eat.

state (STATE_ROWS, N) 3-vectors; tets (M,) 4-vectors of int32; free (N,) int32.
"""
from .._ti import ti

from .layout import X, X_N


@ti.func
def edge_determinant(state: ti.template(), tets: ti.template(), t, row: ti.template()):
    """det[x_b - x_a, x_c - x_a, x_d - x_a] of tet t = (a, b, c, d) at state row `row`: 6 times its
    signed volume, positive for an upright tet (rest tets are positively oriented, so det F has its
    sign; computed without Dm^-1, whose large entries would drown a sliver's sign in round-off)."""
    a, b, c, d = tets[t][0], tets[t][1], tets[t][2], tets[t][3]
    x_a = state[row, a]
    return ti.Matrix.cols([state[row, b] - x_a, state[row, c] - x_a, state[row, d] - x_a]).determinant()


@ti.kernel
def count_inverted(state: ti.types.ndarray(), tets: ti.types.ndarray()) -> ti.i32:
    """Number of tets with det F <= 0 (inverted or flat) at the current positions."""
    n = 0
    for t in range(tets.shape[0]):
        if edge_determinant(state, tets, t, X) <= 0:
            n += 1
    return n


@ti.kernel
def undo_inverting_guess(state: ti.types.ndarray(), tets: ti.types.ndarray(), free: ti.types.ndarray()) -> ti.i32:
    """Put the free vertices of every tet that is inverted now but was upright at x_n back to x_n;
    return how many tets that concerned (0: the guess inverts nothing)."""
    n = 0
    for t in range(tets.shape[0]):
        if edge_determinant(state, tets, t, X) <= 0 < edge_determinant(state, tets, t, X_N):
            n += 1
            for v in ti.static(range(4)):
                if free[tets[t][v]]:
                    state[X, tets[t][v]] = state[X_N, tets[t][v]]
    return n
