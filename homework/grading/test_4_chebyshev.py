"""Task chebyshev: Chebyshev acceleration of the VBD iterations (lecture notes, chapter 6)."""
import numpy as np
import pytest

import solver
from gradelib import bar, require, simulation

pytestmark = pytest.mark.task("chebyshev")


@pytest.mark.parametrize("rho", [0.5, 0.9, 0.97])
def test_weights(rho):
    require("chebyshev")
    sim = simulation(bar(cells=(2, 1, 1)), chebyshev_rho=rho)
    omega = [sim._chebyshev_omega(1, 1.0)]
    for k in range(2, 30):
        omega.append(sim._chebyshev_omega(k, omega[-1]))
    assert omega[0] == 1.0
    assert omega[1] == pytest.approx(2.0 / (2.0 - rho * rho), rel=1e-12)
    for k in range(2, len(omega)):
        assert omega[k] == pytest.approx(4.0 / (4.0 - rho * rho * omega[k - 1]), rel=1e-12)
    assert 1.0 < omega[-1] < 2.0


def test_update_and_history():
    require("chebyshev")
    sim = simulation(bar(cells=(3, 1, 1)), chebyshev_rho=0.9)
    rng = np.random.default_rng(0)
    x, x1, x2 = (rng.normal(size=(sim.mesh.n_vertices, 3)) for _ in range(3))
    sim.x.from_numpy(x)
    sim.x_prev.from_numpy(x1)
    sim.x_prev2.from_numpy(x2)
    omega = 1.37
    sim._chebyshev(omega)
    free = sim.free_mask
    expected = omega * (x - x2) + x2
    assert np.allclose(sim.x.to_numpy()[free], expected[free], rtol=1e-12, atol=1e-12)
    assert np.array_equal(sim.x.to_numpy()[~free], x[~free]), "pinned vertices must not move"
    assert np.allclose(sim.x_prev.to_numpy()[free], expected[free], rtol=1e-12, atol=1e-12)
    assert np.array_equal(sim.x_prev2.to_numpy()[free], x1[free])


def test_acceleration_reduces_the_error():
    require("chebyshev")
    mesh = bar(cells=(16, 2, 2), size=(0.8, 0.1, 0.1))
    errors = {}
    for rho in (None, 0.95):
        sim = simulation(mesh, youngs_modulus=1e6, iterations=60, chebyshev_rho=rho)
        x_n = sim.positions
        x_star = sim.newton_reference()
        sim.step()
        errors[rho] = solver.relative_error(sim.positions, x_star, x_n)
    assert errors[0.95] < 0.5 * errors[None], errors
