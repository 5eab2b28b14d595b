"""One-pass validation of decoded event columns (numba)."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def _scan(t, x, y, width, height, t_before):
    back = -1
    outside = -1
    prev = t_before
    for i in range(len(t)):
        if back < 0 and t[i] < prev:
            back = i
        prev = t[i]
        if outside < 0 and (x[i] >= width or y[i] >= height):
            outside = i
        if back >= 0 and outside >= 0:
            break
    return back, outside


def scan_events(t, x, y, sensor_size, t_before=None):
    """(first index where time goes backwards, first index outside the sensor), -1 for none.

    ``t_before`` is the time stamp that precedes ``t[0]`` (from an earlier
    chunk), so a chunked read checks order across chunk boundaries.
    """
    w, h = sensor_size
    prev = np.iinfo(np.int64).min if t_before is None else int(t_before)
    if len(t) == 0:
        return -1, -1
    return _scan(t, x, y, int(w), int(h), np.int64(prev))
