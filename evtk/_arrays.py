"""Small array helpers shared by evtk's parts."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import numpy.typing as npt


def distinct(values: npt.ArrayLike) -> np.ndarray:
    """The values sorted, each once: ``numpy.unique`` of a flattened array without NaN.

    ``numpy.unique`` loads ``numpy.ma`` on its first call (7 ms and more of a fresh process whose whole
    reconstruction takes 0.2 s); a sort and a comparison of neighbours give the same array.

    Parameters
    ----------
    values : array_like
        Any shape; flattened. Without NaN (``numpy.unique`` keeps one NaN, this would keep all).

    Returns
    -------
    numpy.ndarray
        1-d, the dtype of ``values``: its distinct values in increasing order.
    """
    v = np.sort(np.asarray(values).ravel())
    if v.size < 2:
        return v
    keep = np.empty(v.size, bool)
    keep[0] = True
    np.not_equal(v[1:], v[:-1], out=keep[1:])
    return v[keep]


def median(values: npt.ArrayLike) -> float:
    """``numpy.median`` of the flattened values, as a float, without loading ``numpy.ma`` (which numpy's median
    imports on its first call to check for NaN).

    Parameters
    ----------
    values : array_like
        Any shape, at least one value; flattened, as float64.

    Returns
    -------
    float
        The middle value, or the mean of the two middle ones; NaN when a value is NaN. Two middle values
        whose sum leaves float64 (both beyond half its largest value) give their mean, not numpy's inf.
    """
    v = np.asarray(values, np.float64).ravel()
    if v.size == 0 or np.isnan(v).any():
        return float("nan")
    k = v.size // 2
    if v.size % 2:
        return float(np.partition(v, k)[k])
    part = np.partition(v, [k - 1, k])
    lo, hi = float(part[k - 1]), float(part[k])
    mid = (lo + hi) / 2  # numpy's mean of the two, to the bit
    if math.isinf(mid) and math.isfinite(lo) and math.isfinite(hi):
        mid = lo / 2 + hi / 2  # the sum overflowed: halves first (exact for values this large)
    return mid
