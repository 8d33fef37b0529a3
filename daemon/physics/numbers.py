"""One formula for plain floats and numpy arrays.

The live daemon computes one revolution on Python floats (after its thread
slept, a numpy call on one element costs several times the arithmetic it
stands for); replay computes a block's revolutions as arrays. The physics
functions take either through these: a Python (or numpy) float passes as it
is, anything else becomes a float array.
"""

from __future__ import annotations

import math

import numpy as np


def values(x):
    """`x` itself if a float, else a float array of it."""
    return x if isinstance(x, float) else np.asarray(x, dtype=float)


def positive_or_nan(x):
    """`x` where it is > 0, nan elsewhere (nothing is divided by a speed or time that is not positive)."""
    if isinstance(x, float):
        return x if x > 0.0 else math.nan
    return np.where(x > 0.0, x, np.nan)


def sqrt(x):
    """The square root; nan below 0, as numpy's."""
    if isinstance(x, float):
        return math.sqrt(x) if x >= 0.0 else math.nan
    return np.sqrt(x)
