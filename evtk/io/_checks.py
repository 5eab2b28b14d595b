"""One-pass validation of decoded event columns (numba), and what writers require of their input."""

from __future__ import annotations

import numpy as np
from numba import njit

from ..errors import EvtkError


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


def require_readable(events, sensor_size, t_before=None, first_index=0, fmt="this format"):
    """Raise :class:`~evtk.EvtkError` unless ``events`` are in time order (after ``t_before``) and on the
    sensor: what the HDF5 and Parquet readers require, checked by their writers so that nothing written
    is refused on reading. ``first_index`` numbers the events in the message."""
    back, outside = scan_events(events.t, events.x, events.y, sensor_size, t_before)
    if back >= 0:
        raise EvtkError(f"events must be in time order for {fmt}: time goes backwards at event "
                        f"{first_index + back} (sort them first, or pass sort=True)")
    if outside >= 0:
        w, h = sensor_size
        raise EvtkError(f"event {first_index + outside} lies outside the {w}x{h} sensor")


def sorted_for_writing(events, sort, fmt):
    """``events`` in time order: as they are when sorted, sorted (stable) when ``sort``, else an error."""
    if events.is_sorted:
        return events
    if not sort:
        require_readable(events, (65536, 65536), fmt=fmt)
    return events.sorted()
