"""The error measure against x*: its definition, including the step that does not move."""
import numpy as np
import pytest

import solver


def test_relative_error_is_distance_over_step_length():
    x_n = np.zeros((2, 3))
    x_star = np.array([[3.0, 0.0, 0.0], [0.0, 4.0, 0.0]])         # a step of length 5
    assert solver.relative_error(x_n, x_star, x_n) == 1.0         # did not move
    assert solver.relative_error(x_star, x_star, x_n) == 0.0
    assert solver.relative_error(x_star + [[0.0, 0.0, 0.5]] * 2, x_star, x_n) == pytest.approx(np.sqrt(0.5) / 5)


def test_a_step_that_does_not_move_has_no_scale():
    """Previously this returned the absolute distance in metres, silently mixing units."""
    x_n = np.ones((4, 3))
    assert solver.relative_error(x_n.copy(), x_n, x_n) == 0.0
    assert solver.relative_error(x_n + 1e-3, x_n, x_n) == np.inf


def test_mismatched_shapes_are_a_config_error():
    with pytest.raises(solver.ConfigError, match=r"one shape, got \(3, 3\), \(4, 3\) and \(4, 3\)"):
        solver.relative_error(np.zeros((3, 3)), np.zeros((4, 3)), np.zeros((4, 3)))


def test_positions_that_are_not_numbers_are_a_config_error():
    with pytest.raises(solver.ConfigError, match="arrays of positions"):
        solver.relative_error("a", "b", "c")


def test_an_energy_gap_without_a_decrease_has_no_scale():
    """It returned the absolute energy difference in J where the step lowered nothing."""
    assert solver.relative_energy_gap(1.5, 1.0, 3.0) == 0.25
    assert solver.relative_energy_gap(2.0, 2.0, 2.0) == 0.0
    assert solver.relative_energy_gap(2.5, 2.0, 2.0) == np.inf
    assert solver.relative_energy_gap(1.5, 2.0, 2.0) == -np.inf
