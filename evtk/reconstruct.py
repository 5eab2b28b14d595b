"""From a recording to the responses the device computed: capture windows and event counts.

The stages, each a function usable alone:

1. :class:`Windows`: when each capture's pattern was on, from the schedule a
   simulated recording carries (:func:`windows_from_schedule`), from the DMD's
   trigger edges of a bench recording (:func:`windows_from_triggers`), or at a
   fixed period (:func:`windows_periodic`); any of them shortened or delayed
   (``skip_us``, ``length_us``) to leave out the pixels' settling.
2. :func:`accumulate`: ON and OFF counts per pixel and window in one pass over
   the events (numba), each window found by binary search on the sorted time
   stamps, streamed chunk by chunk from a recording larger than memory.
3. :func:`linearize`: counts back to relative intensity through the pixel
   model (a net rise of ``n`` thresholds is a factor ``exp(n * theta)``;
   :func:`linearize_by_model` inverts a simulated recording's own pixel
   model, and :func:`linearize_by_timing` reads the light within the
   count's band from the first and last ON-event times). A recording's
   flat-field captures (every mirror on) calibrate each pixel's threshold
   first (:func:`flat_field_gain`, :func:`timing_thresholds`).
4. :func:`combine_passes`: ``K+F+ - K+F- - K-F+ + K-F-`` per (kernel,
   features, repeat), from whichever passes the schedule holds.
5. :func:`to_response_grid` (the sensor region onto the response's cells, any
   effective stride, by area overlap) and :func:`downsample` (to a target
   size: block means for whole factors, area-weighted resampling otherwise).
6. :func:`binarize`: sign, mean, a fixed threshold or Otsu's.
"""

from __future__ import annotations

import contextlib
import functools
import json
import math
from dataclasses import dataclass, field

import numba
import numpy as np

from .errors import EvtkError
from .events import Events, TriggerKind, Triggers
from .io.reconstruction import save_reconstruction  # noqa: F401  (public here since 0.1)
from .limits import require_memory

__all__ = [
    "Windows",
    "WindowCounts",
    "windows_from_schedule",
    "windows_from_triggers",
    "windows_periodic",
    "accumulate",
    "linearize",
    "combine_passes",
    "to_response_grid",
    "downsample",
    "binarize",
    "binarize_rule",
    "plan",
    "reconstruct",
    "reconstruct_counts",
    "Reconstruction",
    "response_error",
    "save_reconstruction",
    "contact_sheet",
    "count_curve",
    "linearize_by_model",
    "linearize_by_timing",
    "timing_thresholds",
    "wants_times",
    "window_bytes",
    "flat_field_gain",
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

    def __getitem__(self, index):
        """The windows at ``index`` (a slice or indices), as :class:`Windows` of the same source."""
        return Windows(self.t_start_us[index], self.t_end_us[index], self.capture[index], self.source,
                       dict(self.dropped))


@dataclass
class WindowCounts:
    """Event counts per window and pixel: ``on``/``off`` of shape (windows, y1 - y0, x1 - x0).

    ``region`` is (x0, x1, y0, y1) on the sensor; ``events_used`` counts the
    events that fell in a window and the region. ``on_first_us`` and
    ``on_last_us`` (int32, same shape, -1 where a window holds no ON event),
    when accumulated with ``times=True``, are the time stamps of each pixel's
    first and last ON event in the window, counted from the window's start.
    """

    on: np.ndarray
    off: np.ndarray
    windows: Windows
    region: tuple
    events_used: int
    on_first_us: np.ndarray | None = None
    on_last_us: np.ndarray | None = None

    @classmethod
    def from_capture_counts(cls, cc):
        """Window counts from the simulator's fast path (:meth:`evtk.simulate.Simulation.responses`)."""
        s = cc.schedule
        win = Windows(s.t_on_us, s.t_off_us, s.capture, "schedule")
        return cls(cc.on, cc.off, win, tuple(cc.region), int(cc.on.sum() + cc.off.sum()))


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
    if t_start_us is None or t_end_us is None:
        raise EvtkError("the recording has no events, so no time span to cut into periods")
    t0, t1 = int(t_start_us), int(t_end_us)
    n = (t1 - t0) // period_us if t1 > t0 else 0
    if n < 1:
        raise EvtkError(f"the recording ({t0} .. {t1} us) is shorter than one period of {period_us} us")
    require_memory(n * 40, f"{n:,} windows of {period_us} us")
    t_on = t0 + period_us * np.arange(n, dtype=np.int64)
    start, end = _trim(t_on, t_on + period_us, skip_us, length_us, "periodic")
    dropped = {"partial last period": 1} if t0 + n * period_us < t1 else {}
    return Windows(start, end, np.arange(n), "period", dropped)


@numba.njit(cache=True)
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
    first = last = None
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
        chunks = [source if source.is_sorted else source[np.argsort(source.t, kind="stable")]]
    else:
        chunks = source.iter_events(chunk_events=chunk_events, t_start_us=span[0], t_end_us=span[1])
    used = 0
    total = np.zeros(n_w, np.int64)
    flat = counts.reshape(-1)
    no_times = np.empty(0, np.int32)  # the numba loop keeps no times when given empty arrays
    first_flat = first.reshape(-1) if times else no_times
    last_flat = last.reshape(-1) if times else no_times
    for ev in chunks:
        used += _accumulate_chunk(ev.t, ev.x, ev.y, ev.p, starts, ends, x0, x1, y0, y1, flat, total, started,
                                  first_flat, last_flat)
        if total.max() > np.iinfo(np.int32).max:
            w = int(order[np.argmax(total)])
            raise EvtkError(f"window {w} holds more than 2**31 - 1 events: its int32 counts could overflow")
        if progress is not None:
            progress(len(ev))
    counts[:, ~started] = 0  # windows no event reached (positions in start order)
    if times:
        first[~started] = -1
        last[~started] = -1
    if not np.array_equal(order, np.arange(n_w)):  # back to the caller's window order
        inv = np.empty_like(order)
        inv[order] = np.arange(n_w)
        counts[:] = counts[:, inv]
        on, off = counts[1], counts[0]
        if times:
            first, last = first[inv], last[inv]
    return WindowCounts(on, off, windows, (x0, x1, y0, y1), int(used), first, last)


def linearize(on, off=None, theta_on=0.2, theta_off=None):
    """Relative intensity change over each window from its event counts.

    A pixel that fires ``on`` ON and ``off`` OFF events has seen its log
    intensity rise by about ``on * theta_on - off * theta_off``; the returned
    value is ``exp(that) - 1``: 0 for no change, 1 for a doubling. Over a
    dark-to-pattern window it is proportional to the pattern's light above
    the dark level. Counts are quantised to whole thresholds, so the result
    is too (a factor ``exp(theta)`` per count).

    Examples
    --------
    >>> linearize(np.array([0, 5]), theta_on=np.log(2) / 5).round(6).tolist()
    [0.0, 1.0]
    """
    theta_off = theta_on if theta_off is None else theta_off
    for name, v in (("theta_on", theta_on), ("theta_off", theta_off)):
        v = np.asarray(v, dtype=np.float64)
        if not np.all(np.isfinite(v)) or np.any(v <= 0):
            raise EvtkError(f"{name} must be positive and finite")
    table = _count_table(on, off, theta_on, theta_off)
    if table is not None:  # integer counts and one threshold each: look the few distinct values up
        return table
    on = np.asarray(on, dtype=np.float64)
    rise = on * theta_on
    if off is not None:
        rise = rise - np.asarray(off, dtype=np.float64) * theta_off
    # exp overflows beyond ~709: that many thresholds is not a physical count
    if np.any(rise > 700):
        raise EvtkError("counts imply an intensity rise beyond exp(700): not a linearisable response")
    return np.expm1(rise)


#: Largest table of distinct (ON, OFF) counts :func:`linearize` looks values up in.
_TABLE_MAX = 1 << 20


def _count_table(on, off, theta_on, theta_off):
    """:func:`linearize` of integer counts with scalar thresholds by table look-up (None when it does not apply).

    A window holds few distinct counts, so ``expm1`` of each distinct
    (ON, OFF) pair, looked up per pixel, is exact and several times faster
    than ``expm1`` per pixel.
    """
    on = np.asarray(on)
    if off is None:
        off = np.zeros_like(on)
    off = np.asarray(off)
    if (on.dtype.kind not in "iu" or off.dtype.kind not in "iu" or np.ndim(theta_on) or np.ndim(theta_off)
            or on.shape != off.shape or on.size < 4096):
        return None
    on_flat = np.ascontiguousarray(on).reshape(-1)
    off_flat = np.ascontiguousarray(off).reshape(-1)
    lo, hi_on, hi_off = (int(v) for v in _count_extent(on_flat, off_flat))
    if lo < 0 or (hi_on + 1) * (hi_off + 1) > _TABLE_MAX:
        return None
    rise = np.arange(hi_on + 1.0)[:, None] * float(theta_on) - np.arange(hi_off + 1.0)[None, :] * float(theta_off)
    if rise.max() > 700:
        raise EvtkError("counts imply an intensity rise beyond exp(700): not a linearisable response")
    out = np.empty(on.shape, np.float64)
    with _thread_budget():
        _look_up(on_flat, off_flat, np.expm1(rise).ravel(), hi_off + 1, out.reshape(-1))
    return out


@numba.njit(cache=True)
def _count_extent(on, off):
    lo = 0
    hi_on = 0
    hi_off = 0
    for i in range(on.size):
        a = on[i]
        b = off[i]
        lo = min(lo, a, b)
        hi_on = max(hi_on, a)
        hi_off = max(hi_off, b)
    return lo, hi_on, hi_off


@numba.njit(cache=True, parallel=True)
def _look_up(on, off, table, stride, out):
    for i in numba.prange(on.size):
        out[i] = table[on[i] * stride + off[i]]


def combine_passes(values, schedule):
    """Signed responses: ``sum(kernel_sign * features_sign * values[c])`` over each pair's captures.

    Parameters
    ----------
    values : ndarray, shape (captures, ...)
        One response per capture, in schedule order.
    schedule : evtk.simulate.Schedule or dict
        The capture schedule (``kernel_id``, ``features_id``, signs, ``repeat``).

    Returns
    -------
    (combined, pairs)
        ``combined`` has shape (pairs, ...); ``pairs`` is an int array of
        (kernel_id, features_id, repeat) rows, sorted. Flat-field captures
        (ids -1) are not responses and are left out.
    """
    from .simulate import Schedule

    if isinstance(schedule, dict):
        schedule = Schedule.from_dict(schedule)
    values = np.asarray(values)
    if values.shape[0] != len(schedule):
        raise EvtkError(f"{values.shape[0]} responses for a schedule of {len(schedule)} captures")
    use = (schedule.kernel_id >= 0) & (schedule.features_id >= 0)
    if not use.any():
        raise EvtkError("the schedule holds no (kernel, features) captures, only flat fields")
    keys = np.stack([schedule.kernel_id, schedule.features_id, schedule.repeat], axis=1)[use]
    pairs, which = np.unique(keys, axis=0, return_inverse=True)
    which = np.asarray(which).reshape(-1)
    sign = (schedule.kernel_sign * schedule.features_sign).astype(np.float64)[use]
    out = np.zeros((len(pairs),) + values.shape[1:], dtype=np.float64)
    np.add.at(out, which, values[use] * sign.reshape((-1,) + (1,) * (values.ndim - 1)))
    return out, pairs


def _overlap_matrix(n_cells, first_edge, step, n_pixels):
    """W[c, x]: share of cell c (an interval of ``step`` pixels from ``first_edge + c*step``) covered by pixel x."""
    lo = first_edge + step * np.arange(n_cells)[:, None]
    hi = lo + step
    px = np.arange(n_pixels)[None, :]
    return np.clip(np.minimum(hi, px + 1) - np.maximum(lo, px), 0, None) / step


def to_response_grid(values, region, origin_px, step_px, shape):
    """Resample responses over a sensor region onto the response's cell grid.

    Pixel ``x`` is centred on ``x`` and cell ``(i, j)`` on
    ``origin + (j, i) * step_px`` (the optics' convention), each ``step_px``
    pixels wide; a cell's value is the area-weighted mean of the pixels it
    overlaps. Cells larger
    than pixels (effective stride below 1) average whole and partial pixels;
    cells smaller than pixels (stride above 1) take the value of the pixel
    they lie in, as the sensor cannot resolve them. Parts of a cell outside
    the region count as zero light.

    Parameters
    ----------
    values : ndarray, shape (..., y1 - y0, x1 - x0)
    region : (x0, x1, y0, y1)
    origin_px : (x, y)
        Sensor pixel that sees cell (0, 0) (``response_origin_px`` in the metadata).
    step_px : float
        Sensor pixels per cell: ``decimation / effective stride``.
    shape : (rows, cols)
        Cells wanted (the full response is ``features + kernel - 1``).
    """
    values = np.asarray(values, dtype=np.float64)
    x0, x1, y0, y1 = (int(v) for v in region)
    if values.shape[-2:] != (y1 - y0, x1 - x0):
        raise EvtkError(f"values of shape {values.shape[-2:]} do not cover the region {tuple(region)}")
    if not (np.isfinite(step_px) and step_px > 0):
        raise EvtkError(f"step_px must be positive, not {step_px}")
    rows, cols = (int(v) for v in shape)
    ox, oy = (float(v) for v in origin_px)
    # in edge units (pixel x spans [x, x + 1)) cell c starts at origin + 1/2 - step/2 + c * step
    wy = _overlap_matrix(rows, oy + 0.5 - 0.5 * step_px - y0, step_px, y1 - y0)
    wx = _overlap_matrix(cols, ox + 0.5 - 0.5 * step_px - x0, step_px, x1 - x0)
    return wy @ values @ wx.T


def downsample(values, size=(16, 16)):
    """Resize the last two axes to ``size``: block means for whole factors, else area-weighted.

    Area weighting treats each input element as a unit square and each output
    element as the mean over the squares it covers, which conserves the mean
    for any ratio (up or down).

    Examples
    --------
    >>> downsample(np.arange(16.0).reshape(4, 4), (2, 2)).tolist()
    [[2.5, 4.5], [10.5, 12.5]]
    """
    values = np.asarray(values, dtype=np.float64)
    h, w = values.shape[-2:]
    oh, ow = (int(v) for v in size)
    if oh < 1 or ow < 1:
        raise EvtkError(f"size must be positive, not {size}")
    if h % oh == 0 and w % ow == 0:
        fy, fx = h // oh, w // ow
        return values.reshape(values.shape[:-2] + (oh, fy, ow, fx)).mean(axis=(-3, -1))
    wy = _overlap_matrix(oh, 0.0, h / oh, h)
    wx = _overlap_matrix(ow, 0.0, w / ow, w)
    return wy @ values @ wx.T


def binarize_rule(sim) -> str:
    """The binarisation ``"auto"`` stands for: ``"sign"`` for signed responses, ``"mean"`` for the rest.

    A response is signed when the recording's schedule shows a kernel or
    features holding -1 (its captures are combined from + and - passes, so
    zero is the natural threshold). An unsigned kernel on 0/1 features gives
    a response that is positive wherever light falls (the sign would be +1
    almost everywhere), and a recording without a schedule has no sign to
    go by: both are split at each response's mean.
    """
    if sim is not None and (np.min(sim["kernels"]) < 0 or np.min(sim["features"]) < 0):
        return "sign"
    return "mean"


def binarize(values, method="sign"):
    """+1 where a response reaches the threshold, -1 elsewhere (int8), per response.

    ``method``: "sign" (threshold 0), "mean" (each response's mean), "otsu"
    (Otsu's threshold of each response, scikit-image), or a number. A
    constant response is all +1 under "mean" and "otsu".

    Examples
    --------
    >>> binarize(np.array([[-1.0, 0.0], [2.0, 0.5]]), "mean").tolist()
    [[-1, -1], [1, 1]]
    """
    values = np.asarray(values, dtype=np.float64)
    if values.ndim < 2:
        raise EvtkError("binarize needs responses of at least 2 dimensions")
    if not np.all(np.isfinite(values)):
        raise EvtkError("cannot binarize responses holding NaN or infinity")
    flat = values.reshape((-1,) + values.shape[-2:])
    if method == "sign":
        thr = np.zeros(len(flat))
    elif method == "mean":
        thr = flat.mean(axis=(1, 2))
    elif method == "otsu":
        from skimage.filters import threshold_otsu

        const = np.array([np.ptp(r) == 0 for r in flat], bool)
        thr = np.array([r.flat[0] if c else threshold_otsu(r) for r, c in zip(flat, const)])
        # Otsu's threshold is the last value of the lower class: strictly above it is "high"
        high = flat > thr[:, None, None]
        high[const] = True
        return np.where(high, 1, -1).astype(np.int8).reshape(values.shape)
    else:
        try:
            thr = np.full(len(flat), float(method))
        except (TypeError, ValueError):
            raise EvtkError(f"binarize method must be sign, mean, otsu or a number, not {method!r}") from None
        if not np.isfinite(thr).all():
            raise EvtkError(f"binarize threshold must be finite, not {method!r}")
    return np.where(flat >= thr[:, None, None], 1, -1).astype(np.int8).reshape(values.shape)


@dataclass
class Reconstruction:
    """What :func:`reconstruct` found.

    Attributes
    ----------
    responses : ndarray (n, rows, cols)
        One signed response per (kernel, features, repeat) of the schedule, or
        per window when the recording has none, resampled to ``size``.
    binary : ndarray (n, rows, cols) of int8 (+1/-1)
    pairs : ndarray (n, 3) or None
        (kernel_id, features_id, repeat) of each response.
    cells : ndarray (n, h, w)
        The responses on the response's own cell grid, before resampling.
    ideal : ndarray or None
        Ground truth on the same cell grid (simulated recordings only).
    counts : WindowCounts
    summary : dict
        Captures, windows, events used and dropped, parameters, errors.
    """

    responses: np.ndarray
    binary: np.ndarray
    pairs: np.ndarray | None
    cells: np.ndarray
    ideal: np.ndarray | None
    counts: WindowCounts
    summary: dict

    def groups(self) -> dict:
        """Indices of the responses of each scene: ``{(kernel_id, features_id): [i, ...]}`` over repeats.

        Without a schedule every window counts as a repeat of one scene, keyed ``(-1, -1)``.
        """
        if self.pairs is None:
            return {(-1, -1): np.arange(self.cells.shape[0])}
        out = {}
        for i, (k, f, _) in enumerate(self.pairs.tolist()):
            out.setdefault((k, f), []).append(i)
        return {key: np.asarray(v) for key, v in out.items()}


def response_error(got, ideal):
    """How far responses are from the ideal: Pearson correlation and two normalised RMS errors.

    ``nrmse`` is the RMS error over the ideal's RMS (the strict one: 1.0 for
    an all-zero guess); ``nrmse_range`` is the RMS error over the ideal's
    peak-to-peak range (the usual NRMSD). Undefined values are ``None``.

    Examples
    --------
    >>> e = response_error([1.0, -1.0, 2.0, 0.0], [1.0, -1.0, 2.0, 1.0])
    >>> round(e["nrmse"], 3), round(e["nrmse_range"], 3)
    (0.378, 0.167)
    """
    got = np.asarray(got, dtype=np.float64).ravel()
    ideal = np.asarray(ideal, dtype=np.float64).ravel()
    if got.shape != ideal.shape:
        raise EvtkError(f"responses ({got.size} values) and ideal ({ideal.size} values) differ in size")
    if not np.all(np.isfinite(got)):
        raise EvtkError("responses hold NaN or infinite values")
    rms = float(np.sqrt(np.mean(ideal ** 2))) if ideal.size else 0.0
    if got.size < 2:
        corr = None
    elif np.ptp(got) == 0 or np.ptp(ideal) == 0:
        corr = 1.0 if np.allclose(got, ideal) else 0.0
    else:
        corr = float(np.corrcoef(got, ideal)[0, 1])
    rmse = float(np.sqrt(np.mean((got - ideal) ** 2))) if got.size else 0.0
    span = float(np.ptp(ideal)) if ideal.size else 0.0
    return {"correlation": corr, "nrmse": rmse / rms if rms > 0 else None,
            "nrmse_range": rmse / span if span > 0 else None}


def _footprint_matrix(bench, origin, p0, p1, n_cells, step):
    """M[c, i]: what a unit response at full-response cell i puts into cell c after sampling (one axis).

    The optics' footprint (pixel width, source extent, diffuser blur) followed
    by :func:`to_response_grid`'s area overlap; valid for matched scaling.
    """
    from .optics import _axis_weights, shadow_magnification

    psf_cells = bench.psf_sigma_um / (shadow_magnification(bench.u_mm, bench.z_mm) * bench.feature_pitch_um)
    w = _axis_weights(np.arange(p0, p1), n_cells, 1, bench, origin, psf_cells)[0]  # (pixels, cells)
    t = _overlap_matrix(n_cells, origin + 0.5 - 0.5 * step - p0, step, p1 - p0)  # (cells, pixels)
    return t @ w


def plan(rec, window="schedule", skip_us=0, length_us=None, region=None, check_memory=True):
    """What :func:`reconstruct` will count: ``(simulation record or None, Windows, region)``.

    With ``check_memory`` the counts of every window at once must fit the
    memory budget (:func:`evtk.limits.require_memory`).
    """
    from .simulate import METADATA_KEY

    sim = (rec.metadata or {}).get(METADATA_KEY)
    if window == "schedule":
        if sim is None:
            raise EvtkError("the recording carries no capture schedule: use window='triggers' or a period")
        win = windows_from_schedule(sim, skip_us, length_us)
    elif window == "triggers":
        win = windows_from_triggers(rec.triggers(), skip_us, length_us)
    elif isinstance(window, tuple) and len(window) == 2 and window[0] == "period":
        info = rec.info()
        end = None if info["t_end_us"] is None else info["t_end_us"] + 1
        win = windows_periodic(info["t_start_us"], end, window[1], skip_us, length_us)
    else:
        raise EvtkError(f"window must be 'schedule', 'triggers' or ('period', US), not {window!r}")
    if region is None:
        region = tuple(sim["response_region"]) if sim is not None else (0, rec.sensor_size[0], 0, rec.sensor_size[1])
    x0, x1, y0, y1 = (int(v) for v in region)
    if check_memory:
        require_memory(len(win) * window_bytes(region, sim is not None),
                       f"counting {len(win):,} windows over {max(0, x1 - x0)}x{max(0, y1 - y0)} pixels")
    return sim, win, tuple(region)


def window_bytes(region, simulated):
    """Estimated peak bytes a window costs a reconstruction over ``region`` (x0, x1, y0, y1).

    Per pixel: ON and OFF counts (int32), with a simulation record the first
    and last ON times, and the float64 stages after them (a minute of 10 ms
    windows over 320x240 peaked at 53 bytes a window-pixel without a record:
    measured, killed at 24 GB).
    """
    x0, x1, y0, y1 = (int(v) for v in region)
    return max(0, x1 - x0) * max(0, y1 - y0) * (80 if simulated else 64)


def reconstruct(rec, window="schedule", skip_us=0, length_us=None, size=(16, 16), binarize_method="auto",
                linear=True, theta=None, crop="valid", region=None, chunk_events=4_000_000, progress=None,
                deblur=None, flat_field=True, timing=None):
    """The whole pipeline on an open recording: windows, counts, linearisation, passes, grid, binarisation.

    Parameters
    ----------
    rec : Recording
    window : "schedule", "triggers" or ("period", period_us)
    skip_us, length_us : int
        Shorten or delay every window (leave out the pixels' settling).
    size : (rows, cols)
        Output size of each response.
    binarize_method : "auto", "sign", "mean", "otsu" or a number
        ``"auto"`` (default): :func:`binarize_rule` (sign for signed
        responses, each response's mean otherwise).
    linear : bool
        Linearise counts to light (else net counts ON - OFF).
    theta : float, optional
        Contrast threshold for linearisation; default the recording's
        simulation metadata, else 0.2.
    crop : "valid" or "full"
        Which part of the correlation to keep (needs a simulation record).
    region : (x0, x1, y0, y1), optional
        Sensor pixels to use; default the simulation's response region, else
        the whole sensor.
    deblur : bool or None
        With a simulation record and matched scaling, undo the known footprint
        blur (extended sources, pixel area, diffuser) by solving the linear
        sampling model on the full response. It restores the scale but
        amplifies what is left of count quantisation and threshold mismatch
        (up to 4x at the finest detail). ``None`` (default): deblur when the
        pixels are flat-field calibrated, where it helps on average (see
        ``benchmarks/bench_accuracy.py``).
    flat_field : bool
        Calibrate each pixel's threshold on the recording's flat-field
        captures, when it has any (:func:`flat_field_gain`).
    timing : bool or None
        Read the light below one threshold from each window's first and last
        ON-event times (:func:`linearize_by_timing`). ``None`` (default):
        wherever the recording's pixel model allows it; ``True``: required.

    Notes
    -----
    With a simulation record, linearisation inverts the recording's own pixel
    model (:func:`count_curve`, refined by event times); otherwise (or with
    ``theta`` given) it uses ``exp(n * theta) - 1``.
    """
    _check_crop(crop)
    sim, win, region = plan(rec, window, skip_us, length_us, region)
    counts = accumulate(rec, win, region, chunk_events=chunk_events, progress=progress,
                        times=wants_times(sim, linear, theta, timing))
    return reconstruct_counts(counts, sim, skip_us=skip_us, length_us=length_us, size=size,
                              binarize_method=binarize_method, linear=linear, theta=theta, crop=crop,
                              deblur=deblur, flat_field=flat_field, timing=timing)


def wants_times(sim, linear=True, theta=None, timing=None):
    """Whether a reconstruction with these settings reads event times (accumulate with ``times=True``)."""
    return timing is not False and sim is not None and bool(linear) and theta is None


def _check_crop(crop):
    if crop not in ("valid", "full"):
        raise EvtkError(f"crop must be 'valid' or 'full', not {crop!r}")


def reconstruct_counts(counts, sim=None, skip_us=0, length_us=None, size=(16, 16), binarize_method="auto",
                       linear=True, theta=None, crop="valid", deblur=None, flat_field=True, timing=None):
    """Every stage after accumulation, on window counts (:func:`reconstruct` without the recording).

    ``counts`` is a :class:`WindowCounts` (from :func:`accumulate`, or from
    :meth:`evtk.simulate.Simulation.responses` through
    :meth:`WindowCounts.from_capture_counts`); ``sim`` the simulation record
    (a recording's ``simulation`` metadata) or None. The other parameters
    are :func:`reconstruct`'s; ``skip_us``/``length_us`` must be the ones
    the counts were taken with.
    """
    from .optics import Bench
    from .simulate import Schedule

    _check_crop(crop)
    win = counts.windows
    region = counts.region
    if theta is None:
        theta_on = float(sim["sensor"]["theta_on"]) if sim else 0.2
        theta_off = float(sim["sensor"]["theta_off"]) if sim else 0.2
    else:
        theta_on = theta_off = float(theta)
    schedule = bench = None
    if sim is not None and len(win) == len(sim["schedule"]["capture"]):
        schedule = Schedule.from_dict(sim["schedule"])
        bench = Bench.from_dict(sim["bench"])
    curve = count_curve(sim, skip_us, length_us) if sim is not None and linear and theta is None else None
    needs_net = not linear or curve is not None or (flat_field and schedule is not None)
    net = counts.on.astype(np.float64) - counts.off if needs_net else None
    gain = None
    if linear and flat_field and schedule is not None and np.any(schedule.kernel_id < 0):
        gain = flat_field_gain(net[schedule.kernel_id < 0], _expected_flat_counts(sim, bench, region, curve, theta_on))
    timed_share = None
    why = _no_timing(counts, sim, schedule, curve, skip_us) if timing is not False else "not asked for"
    if why is not None and timing:
        raise EvtkError(f"timing linearisation is not possible: {why}")
    if not linear:
        values = net
    elif why is None:  # the pixel model, read below one threshold from the event times
        values, timed_share = _refine_by_timing(net if gain is None else net * gain, counts, sim, bench, schedule,
                                                curve, gain, theta_on, skip_us)
    elif curve is not None:  # invert the recording's own pixel model
        values = linearize_by_model(net if gain is None else net * gain, curve)
    elif gain is None:
        values = linearize(counts.on, counts.off, theta_on, theta_off)
    else:
        values = linearize(counts.on * gain, counts.off * gain, theta_on, theta_off)

    pairs = ideal = None
    deblurred = False
    if schedule is not None:
        kernels = np.asarray(sim["kernels"])
        features = np.asarray(sim["features"])
        kh, kw = kernels.shape[1:]
        fh, fw = features.shape[1:]
        if linear:  # relative change -> light above the dark level, in response units
            values = values * sim["blank_rate_e_per_s"] / sim["gain_e_per_s_per_unit"]
        step = bench.kernel_step_cells / bench.pixel_cells
        cells = to_response_grid(values, region, sim["response_origin_px"], step, (fh + kh - 1, fw + kw - 1))
        combined, pairs = combine_passes(cells, schedule)
        if deblur is None:  # a decimated reconstruction does not have the neighbours deblurring needs
            deblur = gain is not None and bench.decimation == 1
        deblurred = bool(deblur) and abs(bench.kernel_step_cells - 1.0) < 1e-9
        if deblurred:  # undo the footprint blur of sources, pixels and diffuser
            my = _footprint_matrix(bench, sim["response_origin_px"][1], region[2], region[3], fh + kh - 1, step)
            mx = _footprint_matrix(bench, sim["response_origin_px"][0], region[0], region[1], fw + kw - 1, step)
            combined = np.linalg.solve(my, np.linalg.solve(mx, combined.transpose(0, 2, 1)).transpose(0, 2, 1))
        from .optics import ideal_response

        ideal = np.stack([ideal_response(kernels[k], features[f], bench) for k, f, _ in pairs])
        if crop == "valid":
            sl = (slice(None), slice(kh - 1, fh), slice(kw - 1, fw))
            combined, ideal = combined[sl], ideal[sl]
        if bench.decimation > 1:  # every decimation-th sensor pixel: a strided response (eq. 6)
            if abs(step - 1.0) > 1e-9:
                raise EvtkError("decimation is only supported with matched scaling (one pixel per cell)")
            d = int(bench.decimation)
            combined, ideal = combined[:, ::d, ::d], ideal[:, ::d, ::d]
        cells = combined
    else:
        cells = values
    responses = downsample(cells, size)
    if isinstance(binarize_method, str) and binarize_method == "auto":
        binarize_method = binarize_rule(sim)
    binary = binarize(responses, binarize_method)
    summary = {
        "captures": int(len(schedule)) if schedule is not None else None,
        "windows": len(win),
        "window_source": win.source,
        "windows_dropped": win.dropped,
        "events_used": counts.events_used,
        "region": list(counts.region),
        "responses": int(responses.shape[0]),
        "size": list(responses.shape[1:]),
        "linear": bool(linear),
        "theta_on": theta_on,
        "binarize": str(binarize_method),
        "skip_us": int(skip_us),
        "length_us": None if length_us is None else int(length_us),
        "deblurred": bool(deblurred),
        "flat_field_captures": 0 if gain is None else int(np.sum(schedule.kernel_id < 0)),
        "decimation": 1 if bench is None else int(bench.decimation),
        "linearization": ("counts" if not linear else "pixel model and event times" if timed_share is not None
                          else "pixel model" if curve is not None else "exp(n theta)"),
        "timed_share": timed_share,
    }
    if ideal is not None:
        summary["error"] = response_error(cells, ideal)
    return Reconstruction(responses, binary, pairs, cells, ideal, counts, summary)


def _no_timing(counts, sim, schedule, curve, skip_us):
    """Why event times cannot refine this reconstruction's linearisation (None: they can)."""
    if curve is None:
        return "it needs the recording's pixel model (a simulated recording, linear, no fixed theta)"
    if counts.on_first_us is None:
        return "the counts hold no event times (accumulate with times=True)"
    if schedule is None or not np.array_equal(counts.windows.t_start_us, schedule.t_on_us + int(skip_us)):
        return "the windows must start skip_us after each pattern's onset (schedule windows)"
    return None


def _refine_by_timing(net, counts, sim, bench, schedule, curve, gain, theta_on, skip_us):
    """Light from :func:`linearize_by_timing` wherever the times determine it, else from the (calibrated)
    net counts ``net`` through :func:`linearize_by_model`.

    Thresholds: nominal, or per pixel from the flat-field windows' times
    (:func:`timing_thresholds`), else from the flat-field count gain.
    Returns the values (``exp(u) - 1``) and the share of pixel-windows the times set.
    """
    sm = _as_sensor(sim["sensor"])
    blank = float(sim["blank_rate_e_per_s"])
    theta = np.full(counts.on.shape[1:], float(theta_on))
    if gain is not None:
        ff = schedule.kernel_id < 0
        flat_u = np.broadcast_to(_flat_log_step(sim, bench, counts.region), (int(ff.sum()),) + theta.shape)
        flat_u = flat_u - _settle_residual(flat_u, schedule.t_on_us[ff], schedule.t_off_us[ff], sm, blank)
        t = timing_thresholds(counts.on[ff], counts.on_first_us[ff], counts.on_last_us[ff], flat_u, sm, blank,
                              skip_us)
        theta = np.where(np.isfinite(t), t, theta * gain)
    u = linearize_by_timing(counts.on, counts.on_first_us, counts.on_last_us, theta, sm, blank, curve, skip_us)
    ok = np.isfinite(u)
    u[~ok] = _model_log_step(net[~ok], curve)
    u[ok] += _settle_residual(u, schedule.t_on_us, schedule.t_off_us, sm, blank)[ok]
    return np.expm1(u), float(ok.mean()) if ok.size else 0.0


def _settle_residual(u, t_on_us, t_off_us, sensor, blank_rate_e_per_s):
    """How far above the dark level (log units) each pixel's photoreceptor still is at each pattern's onset.

    The darkness between patterns is finite, so a pixel starts a window a
    little above the dark level, from where the timing estimate measures its
    step. Noise-free mean path through the windows ``[t_on_us, t_off_us)`` in
    time order, from a settled first window, with the light of each window
    taken as ``u`` (its log step over the dark level).
    """
    from .sensor import time_constant_us

    order = np.argsort(t_on_us, kind="stable")
    t_on = np.asarray(t_on_us, np.int64)[order]
    t_off = np.asarray(t_off_us, np.int64)[order]
    tau_dark = float(time_constant_us(blank_rate_e_per_s, sensor))
    gap = np.maximum(t_on[1:] - t_off[:-1], 0)
    dark_decay = np.concatenate([[0.0], np.exp(-gap / tau_dark)])  # the first window starts settled
    u_t = np.ascontiguousarray(u[order]).reshape(len(order), -1)
    lit = np.maximum(t_off - t_on, 0).astype(np.float64)
    lit_decay = np.exp(-lit[:, None] / time_constant_us(blank_rate_e_per_s * np.exp(u_t), sensor))
    eps = np.empty_like(u)
    eps[order] = _settle_path(u_t, lit_decay, dark_decay).reshape((len(order),) + u.shape[1:])
    return eps


@numba.njit(cache=True)
def _settle_path(u, lit_decay, dark_decay):
    eps = np.empty_like(u)
    level = np.zeros(u.shape[1])
    for w in range(u.shape[0]):
        for i in range(u.shape[1]):
            level[i] *= dark_decay[w]
            eps[w, i] = level[i]
            level[i] = u[w, i] + (level[i] - u[w, i]) * lit_decay[w, i]
    return eps


def contact_sheet(path, result: Reconstruction, max_rows=8):
    """PNG of captured responses beside the ideal ones (when known) and the binary result.

    One row per response (at most ``max_rows``); columns: captured (on the
    response's cell grid), ideal, binarised. Written atomically.
    """
    from .plots import pyplot, save_png

    plt = pyplot()
    n = min(len(result.cells), int(max_rows))
    if n == 0:
        raise EvtkError("no responses to draw")
    cols = [("captured", result.cells)]
    if result.ideal is not None:
        cols.append(("ideal", result.ideal))
    cols.append(("binary", result.binary))
    fig, axes = plt.subplots(n, len(cols), figsize=(2.2 * len(cols), 2.2 * n), squeeze=False)
    for r in range(n):
        for c, (title, arr) in enumerate(cols):
            ax = axes[r][c]
            ax.imshow(arr[r], cmap="gray", interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(title)
        if result.pairs is not None:
            k, f, rep = result.pairs[r]
            axes[r][0].set_ylabel(f"K{k} F{f} #{rep}")
    save_png(fig, path, dpi=80)


def count_curve(sim_record, skip_us=0, length_us=None, points=4000):
    """Net counts a noise-free pixel with nominal thresholds gives, against its log-light step.

    Runs the simulation's own pixel model (``sim_record``: a recording's
    ``simulation`` metadata) for a dark-to-pattern step of ``u`` (natural
    log of light over the dark level) from 0 to the brightest possible
    pattern, counting in the same window as the reconstruction, from a
    settled pixel whose reference is the dark level. (A pixel in steady
    operation keeps some residual from earlier captures; over random
    patterns a fresh reference inverts the counts better than modelling the
    previous capture at the same light.) Returns ``(u, counts)``, counts
    non-decreasing in ``u`` (read-only arrays, shared by calls with the same
    bench, sensor and window: a batch of recordings computes it once).
    """
    keys = ("sensor", "blank_rate_e_per_s", "gain_e_per_s_per_unit", "bench", "window_us", "settle_us")
    key = json.dumps({**{k: sim_record[k] for k in keys}, "kernel_shape": np.shape(sim_record["kernels"])[1:],
                      "skip_us": float(skip_us), "length_us": None if length_us is None else float(length_us),
                      "points": int(points)}, sort_keys=True, default=_plain)
    return _count_curve(key)


def _plain(value):
    """numpy scalars and arrays as JSON values (for cache keys)."""
    if hasattr(value, "tolist"):
        return value.tolist()
    raise TypeError(f"{type(value).__name__} is not JSON-serialisable")


@functools.lru_cache(maxsize=16)
def _count_curve(key):
    from .optics import Bench, brightest_response
    from .sensor import PixelState, SensorModel, log_noise_std, simulate_pixels, time_constant_us

    sim_record = json.loads(key)
    skip_us, length_us, points = sim_record["skip_us"], sim_record["length_us"], sim_record["points"]
    sm = SensorModel.from_dict({**sim_record["sensor"], "shot_noise": False, "theta_mismatch": 0.0})
    blank = float(sim_record["blank_rate_e_per_s"])
    gain = float(sim_record["gain_e_per_s_per_unit"])
    bench = Bench.from_dict(sim_record["bench"])
    dark = sm.dark_current_e_per_s
    bright = gain * brightest_response(tuple(sim_record["kernel_shape"]), bench) + dark
    u_max = max(np.log(bright / blank), 1e-6) * 1.01
    u = np.linspace(0.0, u_max, int(points))
    w, z = float(sim_record["window_us"]), float(sim_record["settle_us"])
    a = z + float(skip_us)
    b = z + w if length_us is None else min(z + w, a + float(length_us))
    bounds = sorted({0.0, z, a, b, z + w, 2 * z + w})
    starts, ends = np.array(bounds[:-1]), np.array(bounds[1:])
    lit = (starts >= z) & (starts < z + w)
    lvl = np.where(lit[:, None], np.log(blank) + u[None, :], np.log(blank))
    slot = np.where((starts >= a) & (ends <= b), 0, -1)
    st = PixelState(lvl[0], 0.0, np.full(u.size, sm.theta_on), np.full(u.size, sm.theta_off),
                    np.random.default_rng(0))
    _, _, _, on, off = simulate_pixels(st, lvl, time_constant_us(np.exp(lvl), sm), log_noise_std(np.exp(lvl), sm),
                                       starts, ends, sm, 0, emit=False, count_slot=slot, n_slots=1)
    counts = np.maximum.accumulate(on[0] - off[0])
    u.flags.writeable = counts.flags.writeable = False
    return u, counts


def linearize_by_model(net_counts, curve):
    """Log-light step behind each net count, by inverting :func:`count_curve`; returns ``exp(u) - 1``.

    A count ``n`` stands for the middle of the steps that give ``n``; 0 stays
    0 (no light cannot be told from light below one threshold), and counts
    beyond the curve take its end. Fractional counts (calibrated by
    :func:`flat_field_gain`) interpolate between neighbouring whole counts.
    """
    return np.expm1(_model_log_step(net_counts, curve))


def _model_log_step(net_counts, curve):
    """:func:`linearize_by_model`'s step ``u`` itself."""
    n = np.asarray(net_counts, dtype=np.float64)
    if not np.all(np.isfinite(n)):
        raise EvtkError("counts to linearise must be finite")
    levels, mid = _count_steps(curve)
    return np.interp(n, levels, mid)


@numba.njit(cache=True, inline="always")
def _timing_factor(n, a_us, b_us, log_rate, tau_min_us, tau_electrons, refr_us):
    """``u / theta`` for a pixel whose ``n`` (>= 2) ON events after a step of ``u`` from the dark level came
    first at ``a_us`` and last at ``b_us`` after the step, the light being ``exp(log_rate)`` photoelectrons/s.

    Noise-free, the photoreceptor approaches its new level as ``V = L - u exp(-t/tau)``. Each event
    raises the reference by ``theta`` above V, and the refractory period lets V climb on by a factor
    ``q = exp(-refr/tau)`` of what remains. Writing ``E = exp(-t/tau)`` at event times, that chain is
    ``u (q E_k - E_(k+1)) = theta``, whose solution from the first to the last event is
    ``u / theta = (1 - q^(n-1)) / ((1 - q)(q^(n-1) E_1 - E_n))``, free of the reference the pixel started
    from. Computed directly, or in logs where ``exp(-b/tau)`` would underflow (no overflow for any times).
    -1 when the times cannot come from such a chain (``b - a <= (n - 1) refr``).
    """
    tau = tau_min_us + tau_electrons / (np.exp(log_rate) * 1e-6)
    r = refr_us / tau
    x = (b_us - a_us) / tau - (n - 1) * r
    if not x > 0.0:
        return -1.0
    big = b_us / tau
    if big < 700.0:  # (1 - q) (exp(-(n-1) r - A) - exp(-B)) = (1 - q) exp(-B) expm1(x)
        return -np.expm1(-(n - 1) * r) / (-np.expm1(-r) * np.exp(-big) * np.expm1(x))
    # the same in logs, where exp(-B) would underflow
    log_den = np.log(-np.expm1(-r)) - big + x + np.log1p(-np.exp(-x))
    return np.exp(np.log(-np.expm1(-(n - 1) * r)) - log_den)


@numba.njit(cache=True, parallel=True)
def _timing_solve(n_on, first, last, theta, theta_nominal, band_lo, band_hi, offset_us, log_blank, tau_min_us,
                  tau_electrons, refr_us, out):
    """Log-light steps from ON-event times, :func:`linearize_by_timing`'s work, per (window, pixel)."""
    n_w, n_px = n_on.shape
    top = band_lo.size - 1
    for w in numba.prange(n_w):
        for i in range(n_px):
            n = n_on[w, i]
            out[w, i] = np.nan
            if n < 2 or first[w, i] < 0 or last[w, i] < first[w, i]:
                continue
            a = first[w, i] + offset_us + 0.5  # time stamps are whole us, rounded down
            b = last[w, i] + offset_us + 0.5
            th = theta[i]
            # Search where the count allows: its band (scaled to the pixel's threshold) and the next one,
            # since the reference a pixel starts from may sit up to one threshold above the dark level,
            # widened by a threshold. (Far outside, a much brighter and faster pixel can fit the same
            # two times: h has a second root there.)
            s = th / theta_nominal
            lo = max(0.0, band_lo[min(n, top)] * s - th)
            # the last band reaches the brightest light, whatever the pixel's threshold
            hi = band_hi[n + 1] * s + th if n + 1 < top else band_hi[top] * max(s, 1.0) + th
            # secant steps on h(u) = u - theta * factor(u) from the middle of the band; the time constant
            # changes slowly with the light, so this takes a few steps; the bracketed method otherwise
            u0 = 0.5 * (lo + hi)
            f = _timing_factor(n, a, b, log_blank + u0, tau_min_us, tau_electrons, refr_us)
            if f < 0.0:  # depends on the times only
                continue
            h0 = u0 - th * f
            u1 = th * f
            done = False
            for _ in range(10):
                h1 = u1 - th * _timing_factor(n, a, b, log_blank + u1, tau_min_us, tau_electrons, refr_us)
                if abs(h1) <= 1e-4 * (1.0 + abs(u1)):
                    done = lo <= u1 <= hi
                    break
                if h1 == h0:
                    break
                u0, h0, u1 = u1, h1, u1 - h1 * (u1 - u0) / (h1 - h0)
                if not (-1.0 < u1 < 2.0 * hi + 1.0):
                    break
            if done:
                out[w, i] = u1
                continue
            f = _timing_factor(n, a, b, log_blank + lo, tau_min_us, tau_electrons, refr_us)
            h_lo = lo - th * f
            h_hi = hi - th * _timing_factor(n, a, b, log_blank + hi, tau_min_us, tau_electrons, refr_us)
            if not (h_lo < 0.0 < h_hi):
                continue
            side = 0
            u = lo
            for _ in range(100):  # Illinois method
                u = (lo * h_hi - hi * h_lo) / (h_hi - h_lo)
                h = u - th * _timing_factor(n, a, b, log_blank + u, tau_min_us, tau_electrons, refr_us)
                if abs(h) <= 1e-6 * (1.0 + u) or hi - lo <= 1e-9:
                    break
                if h > 0.0:
                    hi, h_hi = u, h
                    if side == 1:
                        h_lo *= 0.5
                    side = 1
                else:
                    lo, h_lo = u, h
                    if side == -1:
                        h_hi *= 0.5
                    side = -1
            out[w, i] = u


def linearize_by_timing(on, on_first_us, on_last_us, theta, sensor, dark_rate_e_per_s, curve, offset_us=0):
    """Log-light step of each window from the times of its first and last ON event, below one threshold.

    A count alone places the step somewhere in a band one threshold wide (a
    22 % band of light at ``theta = 0.2``). When the pixel's time constant is
    known (a simulated recording's pixel model: ``tau = tau_min +
    tau_electrons / lam``, refractory period), the times at which the noise-free
    photoreceptor crosses its thresholds fix the step within that band
    (:func:`_timing_factor`). The estimate does not depend on the reference the
    pixel started the window with, so the residue earlier captures leave does
    not bias it. With shot noise the times scatter and the estimate with them;
    it still beats the count's band at nominal light (see
    ``benchmarks/bench_accuracy.py``).

    Parameters
    ----------
    on, on_first_us, on_last_us : ndarray (windows, ...)
        ON counts and first/last ON-event times from the window's start
        (:func:`accumulate` with ``times=True``).
    theta : float or ndarray (...)
        Each pixel's ON threshold.
    sensor : SensorModel or dict
        The pixel model (``theta_on`` nominal, ``tau_min_us``,
        ``tau_electrons``, ``refractory_us``).
    dark_rate_e_per_s : float
        Photoelectron rate of the dark level the step starts from.
    curve : (u, counts)
        The pixel model's :func:`count_curve` for these windows: the search
        stays within the steps a pixel's count allows.
    offset_us : float
        Time from the step (the pattern's onset) to the window's start.

    Returns
    -------
    ndarray (windows, ...)
        The step ``u`` (natural log of light over the dark level); NaN where
        the times do not determine it (fewer than two ON events, or times no
        noise-free pixel with that count produces): fall back to the count there.
    """
    sm = _as_sensor(sensor)
    n = np.asarray(on)
    first = np.asarray(on_first_us)
    last = np.asarray(on_last_us)
    if not (n.shape == first.shape == last.shape) or n.ndim < 1:
        raise EvtkError(f"counts {n.shape} and event times {first.shape}/{last.shape} must have one shape")
    th = np.broadcast_to(np.asarray(theta, dtype=np.float64), n.shape[1:])
    if not (np.all(np.isfinite(th)) and np.all(th > 0)):
        raise EvtkError("thresholds must be finite and positive")
    log_blank = _log_dark_rate(dark_rate_e_per_s)
    _, band_lo, band_hi = _count_bands(curve)
    rows = n.shape[0]
    out = np.empty(n.shape, np.float64)
    with _thread_budget():
        _timing_solve(n.reshape(rows, -1).astype(np.int64), first.reshape(rows, -1).astype(np.int64),
                      last.reshape(rows, -1).astype(np.int64), np.ascontiguousarray(th.ravel()), sm.theta_on,
                      np.ascontiguousarray(band_lo, np.float64), np.ascontiguousarray(band_hi, np.float64),
                      float(offset_us), log_blank, sm.tau_min_us, sm.tau_electrons, sm.refractory_us,
                      out.reshape(rows, -1))
    return out


@contextlib.contextmanager
def _thread_budget():
    """numba's parallel loops on as many threads as evtk's decoding (``EVTK_IO_THREADS``; a local cluster's
    workers each get their share), restored afterwards."""
    from .io._compression import workers

    before = numba.get_num_threads()
    numba.set_num_threads(max(1, min(workers(), numba.config.NUMBA_NUM_THREADS)))
    try:
        yield
    finally:
        numba.set_num_threads(before)


def _log_dark_rate(rate_e_per_s):
    """``log`` of the dark level's photoelectron rate, which must be finite and positive."""
    if not (math.isfinite(rate_e_per_s) and rate_e_per_s > 0):
        raise EvtkError(f"the dark level's rate must be finite and positive, not {rate_e_per_s!r}")
    return math.log(rate_e_per_s)


def _as_sensor(sensor):
    """A :class:`~evtk.sensor.SensorModel` from one or from its dict (a recording's record)."""
    from .sensor import SensorModel

    return sensor if isinstance(sensor, SensorModel) else SensorModel.from_dict(dict(sensor))


def _flat_log_step(sim, bench, region):
    """Log-light step ``u`` each pixel of ``region`` (y, x) sees in a flat-field window (every mirror on)."""
    from .optics import screen_response

    kshape = np.asarray(sim["kernels"]).shape[1:]
    fshape = np.asarray(sim["features"]).shape[1:]
    light = screen_response(np.ones(kshape), np.ones(fshape), bench, tuple(region))
    rate = float(sim["gain_e_per_s_per_unit"]) * light + float(sim["sensor"]["dark_current_e_per_s"])
    return np.log(np.maximum(rate, 1e-300) / float(sim["blank_rate_e_per_s"]))


def timing_thresholds(flat_on, flat_first_us, flat_last_us, flat_u, sensor, dark_rate_e_per_s, offset_us=0):
    """Each pixel's ON threshold from flat-field windows of known step ``flat_u`` and their ON-event times.

    ``flat_u``: the step of each window and pixel, or of each pixel.

    The inverse of :func:`linearize_by_timing`: with the step known,
    ``theta = u / factor``, averaged over the flat-field windows whose times
    determine it; NaN for a pixel none does.
    """
    sm = _as_sensor(sensor)
    n = np.asarray(flat_on, dtype=np.int64)
    if n.ndim < 1 or n.shape[0] == 0:
        raise EvtkError("threshold calibration needs at least one flat-field window")
    if not (n.shape == np.shape(flat_first_us) == np.shape(flat_last_us)):
        raise EvtkError("flat-field counts and event times must have one shape")
    rows = n.shape[0]
    fu = np.ascontiguousarray(np.broadcast_to(np.asarray(flat_u, dtype=np.float64), n.shape).reshape(rows, -1))
    theta = _timing_theta(n.reshape(rows, -1), np.asarray(flat_first_us, np.int64).reshape(rows, -1),
                          np.asarray(flat_last_us, np.int64).reshape(rows, -1), fu, float(offset_us),
                          _log_dark_rate(dark_rate_e_per_s), sm.tau_min_us, sm.tau_electrons, sm.refractory_us)
    return theta.reshape(n.shape[1:])


@numba.njit(cache=True)
def _timing_theta(n_on, first, last, flat_u, offset_us, log_blank, tau_min_us, tau_electrons, refr_us):
    n_w, n_px = n_on.shape
    out = np.full(n_px, np.nan)
    for i in range(n_px):
        total = 0.0
        k = 0
        for w in range(n_w):
            if n_on[w, i] < 2 or first[w, i] < 0:
                continue
            f = _timing_factor(n_on[w, i], first[w, i] + offset_us + 0.5, last[w, i] + offset_us + 0.5,
                               log_blank + flat_u[w, i], tau_min_us, tau_electrons, refr_us)
            if f > 0.0:
                total += flat_u[w, i] / f
                k += 1
        if k > 0:
            out[i] = total / k
    return out


def _expected_flat_counts(sim, bench, region, curve, theta_on):
    """Net count a nominal pixel gives in a flat-field window, per pixel of ``region`` (y, x).

    The light is the optics' own (every mirror on, borders included); with
    a count curve the count is the curve read continuously, else
    ``log-step / theta_on``.
    """
    u = _flat_log_step(sim, bench, region)
    if curve is None:
        return u / theta_on
    levels, mid = _count_steps(curve)
    return np.interp(u, mid, levels)


def _count_steps(curve):
    """Whole counts 0..top of a :func:`count_curve` and the log-light step each stands for (its middle)."""
    levels, lo, hi = _count_bands(curve)
    mid = 0.5 * (lo + hi)
    mid[0] = 0.0
    return levels, mid


def _count_bands(curve):
    """Whole counts 0..top of a :func:`count_curve` and the band ``[lo, hi)`` of log-light steps giving each."""
    u, n_of_u = curve
    top = int(n_of_u[-1])
    levels = np.arange(top + 2)
    first = np.searchsorted(n_of_u, levels, side="left")  # first grid index reaching each count
    lo = u[np.minimum(first[:-1], u.size - 1)]
    hi = np.where(first[1:] < u.size, u[np.minimum(first[1:], u.size - 1)], u[-1])
    return levels[:-1], lo, hi


def flat_field_gain(flat_counts, expected_counts, min_counts=3, limits=(0.5, 2.0)):
    """Per-pixel count gain from flat-field captures: ``expected / observed``.

    A pixel with threshold ``theta`` counts a log-light step ``u`` as about
    ``u / theta`` events, so its threshold mismatch is a gain on all its
    counts. ``flat_counts`` (captures, ...) are net counts of windows whose
    light is known up to that gain (every mirror on); ``expected_counts``
    (...) is what a pixel with nominal thresholds counts there (the pixel
    model's :func:`count_curve` at the light the optics give each pixel, or
    the region's median on a bench without a model). Multiplying a pixel's
    counts by its gain puts them on the nominal threshold's scale.

    Pixels expecting fewer than ``min_counts`` events, or observing none,
    keep a gain of 1; gains are clipped to ``limits``.

    Examples
    --------
    >>> flat_field_gain(np.array([[30, 25, 0]]), np.array([27.5, 27.5, 27.5])).tolist()
    [0.9166666666666666, 1.1, 1.0]
    """
    obs = np.asarray(flat_counts, dtype=np.float64)
    exp_ = np.asarray(expected_counts, dtype=np.float64)
    if obs.ndim < 1 or obs.shape[0] == 0:
        raise EvtkError("flat-field calibration needs at least one flat-field capture")
    if obs.shape[1:] != exp_.shape:
        raise EvtkError(f"flat-field counts {obs.shape[1:]} and expected counts {exp_.shape} differ in shape")
    obs = obs.mean(axis=0)
    ok = (exp_ >= min_counts) & (obs > 0) & np.isfinite(exp_)
    gain = np.ones(exp_.shape)
    gain[ok] = exp_[ok] / obs[ok]
    return np.clip(gain, *limits)
