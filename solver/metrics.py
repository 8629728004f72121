"""Error measures against the converged Newton solution x* of the same step."""
import math

import numpy as np

from .errors import ConfigError


def relative_error(x: np.ndarray, x_star: np.ndarray, x_n: np.ndarray) -> float:
    """||x - x*|| / ||x* - x_n|| over all (N, 3) coordinates: 0 is exact, 1 is "did not move".

    A step that does not move (x* = x_n exactly) has no scale to measure against: the error is then
    0 where x = x* and infinite otherwise, never an absolute distance in metres.
    """
    try:
        x, x_star, x_n = (np.asarray(a, dtype=float) for a in (x, x_star, x_n))
    except (TypeError, ValueError):
        raise ConfigError("relative_error needs x, x* and x_n as arrays of positions (numbers, m)") from None
    if not x.shape == x_star.shape == x_n.shape:
        raise ConfigError(f"relative_error needs x, x* and x_n of one shape, got {x.shape}, {x_star.shape} and "
                          f"{x_n.shape}; pass positions of the same mesh")
    distance = np.linalg.norm(x - x_star)
    step = np.linalg.norm(x_star - x_n)
    if step == 0:
        return 0.0 if distance == 0 else float("inf")
    return float(distance / step)


def relative_energy_gap(G_x: float, G_star: float, G_n: float) -> float:
    """(G(x) - G(x*)) / (G(x_n) - G(x*)): the fraction of the step's energy decrease still missing. A step
    that lowers nothing (G(x_n) = G(x*)) has no scale: the gap is then 0 where G(x) = G(x*) and +-inf
    otherwise, never an absolute energy in J (as `relative_error`)."""
    gap, denom = float(G_x - G_star), float(G_n - G_star)
    if denom == 0:
        return 0.0 if gap == 0 else math.copysign(math.inf, gap)
    return gap / denom
