"""Colour maps: a sequential map for scalar fields and a palette for colour sets and bodies (RGB in [0, 1])."""
import numpy as np

BODY_RGB = (0.30, 0.55, 0.85)
FIXED_RGB = (0.35, 0.35, 0.38)

# Dark blue -> teal -> green -> yellow, in the spirit of perceptually ordered maps.
_SEQUENTIAL_STOPS = np.array([
    [0.18, 0.05, 0.33],
    [0.23, 0.32, 0.55],
    [0.13, 0.57, 0.55],
    [0.37, 0.79, 0.38],
    [0.99, 0.91, 0.15],
])

# Twelve well separated hues for colour sets; fixed or scripted vertices are drawn grey.
_PALETTE = np.array([
    [0.90, 0.30, 0.25], [0.25, 0.55, 0.90], [0.30, 0.75, 0.35], [0.95, 0.70, 0.15],
    [0.60, 0.35, 0.80], [0.15, 0.80, 0.80], [0.95, 0.45, 0.70], [0.55, 0.40, 0.25],
    [0.60, 0.80, 0.20], [0.20, 0.30, 0.55], [0.85, 0.85, 0.85], [0.05, 0.50, 0.45],
])


# The palette's hues for bodies, blue first: no red (the ghost's colour) and no grey (held bodies).
_BODY_HUES = np.array([1, 3, 2, 4, 5, 7, 8, 11, 6, 9])


def normalise(values, lo, hi, log=False):
    """Map values to [0, 1] linearly (or in log10) between lo and hi, clamping outside."""
    v = np.asarray(values, float)
    if log:
        v, lo, hi = np.log10(np.maximum(v, lo)), np.log10(lo), np.log10(hi)
    return np.clip((v - lo) / (hi - lo), 0.0, 1.0)


def sequential(t):
    """RGB for parameters t in [0, 1]."""
    x = np.asarray(t, float) * (len(_SEQUENTIAL_STOPS) - 1)
    i = np.minimum(x.astype(int), len(_SEQUENTIAL_STOPS) - 2)
    frac = (x - i)[..., None]
    return _SEQUENTIAL_STOPS[i] * (1 - frac) + _SEQUENTIAL_STOPS[i + 1] * frac


def categorical(index):
    """RGB per integer label; negative labels (fixed vertices) are grey."""
    index = np.asarray(index)
    rgb = _PALETTE[np.mod(index, len(_PALETTE))]
    rgb[index < 0] = FIXED_RGB
    return rgb


def uniform(n, rgb=BODY_RGB):
    """The same colour for n vertices."""
    return np.tile(np.asarray(rgb, float), (n, 1))


def per_body(bodies, pinned):
    """(N, 3) RGB of the bodies: BODY_RGB where there is one body; where there are several, each body its
    own hue (`_BODY_HUES` in turn, in the order of its first vertex), and a body whose every vertex is
    pinned (fixed or kinematic, such as a box the others fall into) grey. bodies (N,) int labels, pinned (N,)
    bool."""
    labels, body = np.unique(np.asarray(bodies), return_inverse=True)
    if len(labels) == 1:
        return uniform(len(body))
    held = np.bincount(body, weights=~np.asarray(pinned, bool), minlength=len(labels)) == 0
    hue = _BODY_HUES[np.mod(np.cumsum(~held) - 1, len(_BODY_HUES))]
    return categorical(np.where(held, -1, hue)[body])
