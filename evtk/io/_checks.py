"""One-pass validation of decoded event columns (numpy, a block at a time), and what writers require of their input."""

from __future__ import annotations

import numpy as np

from ..errors import EvtkError

#: Events checked at a time: the temporaries stay a few MiB whatever the length of the columns.
SCAN_BLOCK = 1 << 20


def _first(mask) -> int:
    """Index of the first True of ``mask``, or -1."""
    if not len(mask):
        return -1
    i = int(np.argmax(mask))
    return i if mask[i] else -1


def scan_events(t, x, y, sensor_size, t_before=None):
    """(first index where time goes backwards, first index outside the sensor), -1 for none.

    ``t_before`` is the time stamp that precedes ``t[0]`` (from an earlier
    chunk), so a chunked read checks order across chunk boundaries. Vectorised
    over blocks of :data:`SCAN_BLOCK` events (no compiler to load: readers of
    HDF5 and Parquet and every writer call it).

    Parameters
    ----------
    t, x, y : numpy.ndarray
        The time stamps and coordinates.
    sensor_size : (int, int)
        ``(width, height)``.
    t_before : int, optional
        The stamp before ``t[0]``.

    Returns
    -------
    back, outside : int, int
        The first index whose stamp is below the one before it, the first index off the sensor; -1 for none.
    """
    w, h = (int(v) for v in sensor_size)
    n = len(t)
    back = outside = -1
    prev = np.iinfo(np.int64).min if t_before is None else int(t_before)
    for lo in range(0, n, SCAN_BLOCK):
        hi = min(n, lo + SCAN_BLOCK)
        if back < 0:
            tb = t[lo:hi]
            if tb[0] < prev:
                back = lo
            else:
                k = _first(tb[1:] < tb[:-1])
                if k >= 0:
                    back = lo + k + 1
            prev = tb[-1]
        if outside < 0:
            k = _first((x[lo:hi] >= w) | (y[lo:hi] >= h))
            if k >= 0:
                outside = lo + k
        if back >= 0 and outside >= 0:
            break
    return back, outside


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
