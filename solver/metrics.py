"""Error measures against the converged Newton solution x* of the same step."""
import numpy as np


def relative_error(x: np.ndarray, x_star: np.ndarray, x_n: np.ndarray) -> float:
    """||x - x*|| / ||x* - x_n|| over all (N, 3) coordinates: 0 is exact, 1 is "did not move"."""
    denom = np.linalg.norm(x_star - x_n)
    return float(np.linalg.norm(x - x_star) / denom) if denom > 0 else float(np.linalg.norm(x - x_star))


def relative_energy_gap(G_x: float, G_star: float, G_n: float) -> float:
    """(G(x) - G(x*)) / (G(x_n) - G(x*)): the fraction of the step's energy decrease still missing."""
    denom = G_n - G_star
    return float((G_x - G_star) / denom) if denom != 0 else float(G_x - G_star)
