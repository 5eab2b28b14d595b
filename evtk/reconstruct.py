"""From a recording to the responses the device computed: capture windows and event counts.

This module holds the first two stages of reconstruction:

1. :class:`Windows`: when each capture's pattern was on, from the schedule a
   simulated recording carries (:func:`windows_from_schedule`), from the DMD's
   trigger edges of a bench recording (:func:`windows_from_triggers`), or at a
   fixed period (:func:`windows_periodic`); any of them shortened or delayed
   (``skip_us``, ``length_us``) to leave out the pixels' settling.
2. :func:`accumulate`: ON and OFF counts per pixel and window in one pass over
   the events (numba), each window found by binary search on the sorted time
   stamps, streamed chunk by chunk from a recording larger than memory.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numba
import numpy as np

from .errors import EvtkError
from .events import Events, TriggerKind, Triggers

__all__ = [
    "Windows",
    "WindowCounts",
    "windows_from_schedule",
    "windows_from_triggers",
    "windows_periodic",
    "accumulate",
]

_RISING = (TriggerKind.EXTERNAL_SIGNAL_RISING_EDGE, TriggerKind.EXTERNAL_GENERATOR_RISING_EDGE)
_FALLING = (TriggerKind.EXTERNAL_SIGNAL_FALLING_EDGE, TriggerKind.EXTERNAL_GENERATOR_FALLING_EDGE)


@dataclass
class Windows:
    """Half-open time windows ``[t_start_us, t_end_us)``, one per capture.

    ``capture`` is the schedule's capture index (or the window's own index
    when there is no schedule); ``dropped`` says, per reason, how many windows
    could not be formed.
    """

    t_start_us: np.ndarray
    t_end_us: np.ndarray
    capture: np.ndarray
    source: str
    dropped: dict = field(default_factory=dict)

    def __post_init__(self):
        self.t_start_us = np.ascontiguousarray(self.t_start_us, dtype=np.int64)
        self.t_end_us = np.ascontiguousarray(self.t_end_us, dtype=np.int64)
        self.capture = np.ascontiguousarray(self.capture, dtype=np.int64)
        if not (self.t_start_us.shape == self.t_end_us.shape == self.capture.shape) or self.t_start_us.ndim != 1:
            raise EvtkError("window starts, ends and capture indices must be 1-D arrays of equal length")
        if np.any(self.t_end_us <= self.t_start_us):
            i = int(np.flatnonzero(self.t_end_us <= self.t_start_us)[0])
            raise EvtkError(f"window {i} is empty or reversed: [{self.t_start_us[i]}, {self.t_end_us[i]}) us")

    def __len__(self):
        return int(self.t_start_us.size)

    @property
    def length_us(self) -> np.ndarray:
        return self.t_end_us - self.t_start_us


@dataclass
class WindowCounts:
    """Event counts per window and pixel: ``on``/``off`` of shape (windows, y1 - y0, x1 - x0).

    ``region`` is (x0, x1, y0, y1) on the sensor; ``events_used`` counts the
    events that fell in a window and the region.
    """

    on: np.ndarray
    off: np.ndarray
    windows: Windows
    region: tuple
    events_used: int


def _trim(t_on, t_off, skip_us, length_us, what):
    skip_us = int(skip_us)
    if skip_us < 0:
        raise EvtkError(f"skip_us must be >= 0, not {skip_us}")
    start = t_on + skip_us
    end = t_off.copy()
    if length_us is not None:
        length_us = int(length_us)
        if length_us < 1:
            raise EvtkError(f"length_us must be >= 1, not {length_us}")
        end = np.minimum(end, start + length_us)
    if np.any(end <= start):
        shortest = int(np.min(t_off - t_on)) if t_on.size else 0
        raise EvtkError(f"skip_us={skip_us} leaves nothing of the {what} windows (shortest: {shortest} us)")
    return start, end


def windows_from_schedule(schedule, skip_us=0, length_us=None) -> Windows:
    """Windows of a simulated recording's captures.

    ``schedule`` is an :class:`evtk.simulate.Schedule`, a recording's metadata
    dict (with a ``simulation`` record) or that record itself.
    """
    from .simulate import METADATA_KEY, Schedule

    if isinstance(schedule, dict):
        rec = schedule.get(METADATA_KEY, schedule)
        if "schedule" not in rec:
            raise EvtkError("the recording carries no capture schedule; use its triggers or a period instead")
        schedule = Schedule.from_dict(rec["schedule"])
    start, end = _trim(schedule.t_on_us, schedule.t_off_us, skip_us, length_us, "scheduled")
    return Windows(start, end, schedule.capture, "schedule")


def windows_from_triggers(triggers: Triggers, skip_us=0, length_us=None) -> Windows:
    """Windows from the DMD's trigger edges: each rising edge to the next falling edge.

    Edge cases are defined, and counted in ``Windows.dropped``: a rising edge
    while a window is open (its falling edge is missing: that window is
    dropped), a falling edge with no open window (ignored), and a window still
    open when the triggers end (the recording ends mid-window: dropped).
    Triggers of other kinds are ignored.
    """
    order = np.argsort(triggers.t, kind="stable")
    t = triggers.t[order]
    kind = triggers.kind[order]
    rising = np.isin(kind, _RISING)
    falling = np.isin(kind, _FALLING)
    starts, ends = [], []
    dropped = {"missing falling edge": 0, "falling edge without rising edge": 0, "recording ends mid-window": 0}
    open_at = None
    for ti, r, f in zip(t.tolist(), rising.tolist(), falling.tolist()):
        if r:
            if open_at is not None:
                dropped["missing falling edge"] += 1
            open_at = ti
        elif f:
            if open_at is None:
                dropped["falling edge without rising edge"] += 1
            elif ti > open_at:
                starts.append(open_at)
                ends.append(ti)
                open_at = None
            else:  # rising and falling at the same microsecond: nothing was shown
                dropped.setdefault("zero-length window", 0)
                dropped["zero-length window"] += 1
                open_at = None
    if open_at is not None:
        dropped["recording ends mid-window"] += 1
    if not starts:
        raise EvtkError("no complete window in the triggers: no rising edge followed by a falling edge "
                        f"({int(rising.sum())} rising, {int(falling.sum())} falling)")
    t_on = np.array(starts, np.int64)
    t_off = np.array(ends, np.int64)
    start, end = _trim(t_on, t_off, skip_us, length_us, "triggered")
    return Windows(start, end, np.arange(t_on.size), "triggers", {k: v for k, v in dropped.items() if v})


def windows_periodic(t_start_us, t_end_us, period_us, skip_us=0, length_us=None) -> Windows:
    """Back-to-back windows of ``period_us`` from ``t_start_us``; a last partial period is dropped."""
    period_us = int(period_us)
    if period_us < 1:
        raise EvtkError(f"period_us must be >= 1, not {period_us}")
    t0, t1 = int(t_start_us), int(t_end_us)
    n = (t1 - t0) // period_us if t1 > t0 else 0
    if n < 1:
        raise EvtkError(f"the recording ({t0} .. {t1} us) is shorter than one period of {period_us} us")
    t_on = t0 + period_us * np.arange(n, dtype=np.int64)
    start, end = _trim(t_on, t_on + period_us, skip_us, length_us, "periodic")
    dropped = {"partial last period": 1} if t0 + n * period_us < t1 else {}
    return Windows(start, end, np.arange(n), "period", dropped)


@numba.njit(cache=True)
def _accumulate_chunk(t, x, y, p, starts, ends, x0, x1, y0, y1, counts, total, started):
    """Add the chunk's events to every window; returns the number counted.

    ``counts`` is the flat (2, windows, y1 - y0, x1 - x0) array, OFF then ON,
    not yet zeroed: a window's frames are zeroed when it is first reached
    (``started``), which also brings them into cache just before the scattered
    increments. ``total``: events per window so far (for the overflow check).
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
            started[w] = True
        if full and x1 >= 0 and y1 >= 0:
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
                counts[np.int64(p[i]) * plane + base + yi * w_px + xi] += 1
                used += 1
    return used


def accumulate(source, windows: Windows, region=None, chunk_events=4_000_000, progress=None,
               out=None) -> WindowCounts:
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

    Returns
    -------
    WindowCounts
        Counts are int32; a window holding more than 2**31 - 1 events raises
        rather than wrap.

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
    if out is None:
        counts = np.empty(shape, np.int32)  # each window zeroed when first reached
    else:
        counts = out
        if counts.shape != shape or counts.dtype != np.int32 or not counts.flags.c_contiguous:
            raise EvtkError(f"out must be a C-contiguous int32 array of shape {shape}")
    on, off = counts[1], counts[0]
    if n_w == 0:
        return WindowCounts(on, off, windows, (x0, x1, y0, y1), 0)
    started = np.zeros(n_w, np.bool_)
    order = np.argsort(windows.t_start_us, kind="stable")
    starts = windows.t_start_us[order]
    ends = windows.t_end_us[order]
    span = (int(starts.min()), int(ends.max()))
    if isinstance(source, Events):
        chunks = [source if source.is_sorted else source[np.argsort(source.t, kind="stable")]]
    else:
        chunks = source.iter_events(chunk_events=chunk_events, t_start_us=span[0], t_end_us=span[1])
    used = 0
    total = np.zeros(n_w, np.int64)
    flat = counts.reshape(-1)
    for ev in chunks:
        used += _accumulate_chunk(ev.t, ev.x, ev.y, ev.p, starts, ends, x0, x1, y0, y1, flat, total, started)
        if total.max() > np.iinfo(np.int32).max:
            w = int(order[np.argmax(total)])
            raise EvtkError(f"window {w} holds more than 2**31 - 1 events: its int32 counts could overflow")
        if progress is not None:
            progress(len(ev))
    counts[:, ~started] = 0  # windows no event reached (positions in start order)
    if not np.array_equal(order, np.arange(n_w)):  # back to the caller's window order
        inv = np.empty_like(order)
        inv[order] = np.arange(n_w)
        counts[:] = counts[:, inv]
        on, off = counts[1], counts[0]
    return WindowCounts(on, off, windows, (x0, x1, y0, y1), int(used))
