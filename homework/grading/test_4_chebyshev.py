"""Task chebyshev: Chebyshev acceleration of the VBD iterations (lecture notes, chapter 6)."""
import numpy as np
import pytest
import taichi as ti

import solver
from gradelib import bar, reference, require, simulation
from solver.vbd.chebyshev import chebyshev_omega, chebyshev_update
from solver.vbd.layout import STATE_ROWS, X, X_PREV, X_PREV2

pytestmark = pytest.mark.task("chebyshev")


@pytest.mark.parametrize("rho", [0.5, 0.9, 0.97])
def test_weights(rho):
    require("chebyshev")
    omega = [chebyshev_omega(1, rho, 1.0)]
    for k in range(2, 30):
        omega.append(chebyshev_omega(k, rho, omega[-1]))
    assert omega[0] == 1.0
    assert omega[1] == pytest.approx(2.0 / (2.0 - rho * rho), rel=1e-12)
    for k in range(2, len(omega)):
        assert omega[k] == pytest.approx(4.0 / (4.0 - rho * rho * omega[k - 1]), rel=1e-12)
    assert 1.0 < omega[-1] < 2.0


@ti.kernel
def _update_free(state: ti.types.ndarray(), color_order: ti.types.ndarray(), omega: ti.f64):
    for k in range(color_order.shape[0]):
        chebyshev_update(state, color_order[k], omega)


def test_update_and_history():
    require("chebyshev")
    sim = simulation(bar(cells=(3, 1, 1)), chebyshev_rho=0.9)
    n = sim.mesh.n_vertices
    rng = np.random.default_rng(0)
    x, x1, x2 = (rng.normal(size=(n, 3)) for _ in range(3))
    rows = np.zeros((STATE_ROWS, n, 3))
    rows[X], rows[X_PREV], rows[X_PREV2] = x, x1, x2
    state = ti.Vector.ndarray(3, ti.f64, (STATE_ROWS, n))
    state.from_numpy(rows)
    order = ti.ndarray(ti.i32, sim.topology.n_slots)
    order.from_numpy(sim.topology.color_order)
    omega = 1.37
    _update_free(state, order, omega)
    out = state.to_numpy()
    free = sim.free_mask
    expected = omega * (x - x2) + x2
    assert np.allclose(out[X][free], expected[free], rtol=1e-12, atol=1e-12)
    assert np.array_equal(out[X][~free], x[~free]), "pinned vertices must not move"
    assert np.allclose(out[X_PREV][free], expected[free], rtol=1e-12, atol=1e-12)
    assert np.array_equal(out[X_PREV2][free], x1[free])


def test_acceleration_reduces_the_error():
    require("chebyshev")
    errors = {}
    for rho in (None, 0.95):
        sim, x_star = reference("stiff_long_bar", iterations=60, chebyshev_rho=rho)
        x_n = sim.positions
        sim.step()
        errors[rho] = solver.relative_error(sim.positions, x_star, x_n)
    assert errors[0.95] < 0.5 * errors[None], errors
