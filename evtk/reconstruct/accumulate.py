"""ON and OFF event counts per window and pixel, in one streamed pass over the events (numba)."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numba
import numpy as np

from ..errors import EvtkError
from ..events import Events
from ..limits import require_memory
from .windows import WindowCounts, Windows

__all__ = ["accumulate"]

_END = object()


def _prefetched(chunks):
    """Yield the items of the iterator ``chunks`` while the next one is produced on another thread: the next
    chunk is read and decoded (on the I/O threads) while this one is counted."""
    with ThreadPoolExecutor(1, thread_name_prefix="evtk-prefetch") as ex:
        pending = ex.submit(next, chunks, _END)
        while True:
            item = pending.result()
            if item is _END:
                return
            pending = ex.submit(next, chunks, _END)
            yield item


@numba.njit(cache=True, nogil=True)
def _accumulate_chunk(t, x, y, p, starts, ends, x0, x1, y0, y1, counts, total, started, first, last):
    """Add the chunk's events to every window; returns the number counted.

    ``counts`` is the flat (2, windows, y1 - y0, x1 - x0) array, OFF then ON,
    not yet zeroed: a window's frames are zeroed when it is first reached
    (``started``), which also brings them into cache just before the scattered
    increments. ``total``: events per window so far (for the overflow check).
    ``first``/``last``: flat (windows, y1 - y0, x1 - x0) times of the first and
    last ON event since the window's start (-1: none yet), or empty arrays
    when times are not wanted.
    """
    used = 0
    n = t.size
    if n == 0:
        return 0
    t_first = t[0]
    t_last = t[n - 1]
    w_px = x1 - x0
    frame = (y1 - y0) * w_px
    plane = starts.size * frame
    full = x0 == 0 and y0 == 0
    timed = first.size > 0
    for w in range(starts.size):
        a = starts[w]
        b = ends[w]
        if b <= t_first or a > t_last:
            continue
        lo = np.searchsorted(t, a)
        hi = np.searchsorted(t, b)
        total[w] += hi - lo
        base = w * frame
        if not started[w]:
            counts[base:base + frame] = 0
            counts[plane + base:plane + base + frame] = 0
            if timed:
                first[base:base + frame] = -1
                last[base:base + frame] = -1
            started[w] = True
        if full and x1 >= 0 and y1 >= 0 and not timed:
            # every event is on the sensor (the reader checked), so inside a full-sensor region
            for i in range(lo, hi):
                counts[np.int64(p[i]) * plane + base + np.int64(y[i]) * w_px + np.int64(x[i])] += 1
            used += hi - lo
        else:
            for i in range(lo, hi):
                xi = np.int64(x[i]) - x0
                yi = np.int64(y[i]) - y0
                if xi < 0 or xi >= w_px or yi < 0 or yi >= y1 - y0:
                    continue
                k = base + yi * w_px + xi
                counts[np.int64(p[i]) * plane + k] += 1
                used += 1
                if timed and p[i] != 0:
                    dt = np.int32(t[i] - a)  # windows shorter than 2**31 us (checked by the caller)
                    if first[k] < 0:
                        first[k] = dt
                    last[k] = dt
    return used


def accumulate(source, windows: Windows, region=None, chunk_events=4_000_000, progress=None,
               out=None, times=False) -> WindowCounts:
    """ON and OFF counts per window and pixel of ``region``.

    Parameters
    ----------
    source : Events or Recording
        Events (sorted by time, or sorted here) or an open recording, which is
        read in chunks of ``chunk_events`` over the span of the windows only.
    windows : Windows
    region : (x0, x1, y0, y1), optional
        Sensor pixels to count (half-open); default the whole sensor. Counting
        only the pixels a response needs keeps the output small, which is
        most of the cost (fresh memory is slow to touch).
    out : ndarray, optional
        A C-contiguous int32 array of shape (2, windows, height, width) to
        reuse (OFF counts, then ON counts); zeroed here.
    times : bool
        Also keep each pixel's first and last ON-event time per window
        (``on_first_us``/``on_last_us``), which the timing linearisation
        (:func:`linearize_by_timing`) reads below one threshold.

    Returns
    -------
    WindowCounts
        Counts are int32; a window holding more than 2**31 - 1 events raises
        rather than wrap.

    Raises
    ------
    EvtkError
        A region off the sensor, or counts larger than the memory budget
        (:func:`evtk.limits.require_memory`, checked before they are allocated).

    Examples
    --------
    >>> ev = Events([5, 15, 16, 30], [1, 1, 2, 0], [0, 0, 1, 1], [1, 0, 1, 1], (3, 2))
    >>> w = Windows([0, 10], [10, 20], [0, 1], "example")
    >>> c = accumulate(ev, w)
    >>> c.on[1].tolist(), c.off[1].tolist()
    ([[0, 0, 0], [0, 0, 1]], [[0, 1, 0], [0, 0, 0]])
    """
    sensor = tuple(source.sensor_size)
    if region is None:
        region = (0, sensor[0], 0, sensor[1])
    x0, x1, y0, y1 = (int(v) for v in region)
    if not (0 <= x0 < x1 <= sensor[0] and 0 <= y0 < y1 <= sensor[1]):
        raise EvtkError(f"region {tuple(region)} is not a non-empty part of the {sensor[0]}x{sensor[1]} sensor")
    n_w = len(windows)
    shape = (2, n_w, y1 - y0, x1 - x0)
    # int32 ON and OFF counts (and the first and last ON times) of every window, and 17 bytes a window
    require_memory(n_w * ((y1 - y0) * (x1 - x0) * 4 * ((0 if out is not None else 2) + (2 if times else 0)) + 17),
                   f"counting {n_w:,} windows over {x1 - x0}x{y1 - y0} pixels")
    if out is None:
        counts = np.empty(shape, np.int32)  # each window zeroed when first reached
    else:
        counts = out
        if counts.shape != shape or counts.dtype != np.int32 or not counts.flags.c_contiguous:
            raise EvtkError(f"out must be a C-contiguous int32 array of shape {shape}")
    on, off = counts[1], counts[0]
    first: np.ndarray | None = None
    last: np.ndarray | None = None
    if times:
        if n_w and int(windows.length_us.max()) >= 2**31:
            raise EvtkError("event times are kept relative to their window as int32: windows must be "
                            "shorter than 2**31 us")
        first, last = np.empty(shape[1:], np.int32), np.empty(shape[1:], np.int32)
    if n_w == 0:
        return WindowCounts(on, off, windows, (x0, x1, y0, y1), 0, first, last)
    started = np.zeros(n_w, np.bool_)
    order = np.argsort(windows.t_start_us, kind="stable")
    starts = windows.t_start_us[order]
    ends = windows.t_end_us[order]
    span = (int(starts.min()), int(ends.max()))
    if isinstance(source, Events):
        chunks = [source.sorted()]
    else:
        chunks = _prefetched(source.iter_events(chunk_events=chunk_events, t_start_us=span[0], t_end_us=span[1]))
    used = 0
    total = np.zeros(n_w, np.int64)
    flat = counts.reshape(-1)
    no_times = np.empty(0, np.int32)  # the numba loop keeps no times when given empty arrays
    first_flat = first.reshape(-1) if first is not None else no_times
    last_flat = last.reshape(-1) if last is not None else no_times
    period = None
    for ev in chunks:
        if times and period is None:
            period = ev.stamp_period_us()
        used += _accumulate_chunk(ev.t, ev.x, ev.y, ev.p, starts, ends, x0, x1, y0, y1, flat, total, started,
                                  first_flat, last_flat)
        if total.max() > np.iinfo(np.int32).max:
            w = int(order[np.argmax(total)])
            raise EvtkError(f"window {w} holds more than 2**31 - 1 events: its int32 counts could overflow")
        if progress is not None:
            progress(len(ev))
    counts[:, ~started] = 0  # windows no event reached (positions in start order)
    if first is not None and last is not None:
        first[~started] = -1
        last[~started] = -1
    if not np.array_equal(order, np.arange(n_w)):  # back to the caller's window order
        inv = np.empty_like(order)
        inv[order] = np.arange(n_w)
        counts[:] = counts[:, inv]
        on, off = counts[1], counts[0]
        if first is not None and last is not None:
            first, last = first[inv], last[inv]
    return WindowCounts(on, off, windows, (x0, x1, y0, y1), int(used), first, last, period)
