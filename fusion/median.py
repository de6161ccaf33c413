"""The median of a few values, as ``np.median`` gives it, without ``np.median``'s import of ``numpy.ma`` (its NaN
check asks whether the array is a masked one, which loads the masked-array module at the first call of a
process): the engine's sample period, the readers' IMU period, the installation's steps, the time sync's fits.
"""
from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt


def median(a: npt.ArrayLike) -> float:
    """``np.median`` of a 1-d sequence, the same float, from one partition.

    Parameters
    ----------
    a : array_like (n,)
        Numbers (ints or floats; int64 stamps in ns are summed as floats, as ``np.median`` does).

    Returns
    -------
    float
        The middle value, or the mean of the two middle values for an even count; NaN when ``a`` holds a NaN
        or nothing (``np.median`` warns there, this does not).
    """
    a = np.asarray(a)
    n = len(a)
    if n == 0:
        return math.nan
    h = n // 2
    p = np.partition(a, (h - 1, h, n - 1) if n % 2 == 0 else (h, n - 1))
    if p.dtype.kind == "f" and np.isnan(p[-1]):
        return math.nan
    return float(p[h]) if n % 2 else (float(p[h - 1]) + float(p[h])) / 2
