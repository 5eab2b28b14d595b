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
   model (a net rise of ``n`` thresholds is a factor ``exp(n * theta)``).
   A recording's flat-field captures (every mirror on) calibrate each
   pixel's threshold first (:func:`flat_field_gain`).
4. :func:`combine_passes`: ``K+F+ - K+F- - K-F+ + K-F-`` per (kernel,
   features, repeat), from whichever passes the schedule holds.
5. :func:`to_response_grid` (the sensor region onto the response's cells, any
   effective stride, by area overlap) and :func:`downsample` (to a target
   size: block means for whole factors, area-weighted resampling otherwise).
6. :func:`binarize`: sign, mean, a fixed threshold or Otsu's.
"""

from __future__ import annotations

import functools
import json
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
    "linearize",
    "combine_passes",
    "to_response_grid",
    "downsample",
    "binarize",
    "plan",
    "reconstruct",
    "reconstruct_counts",
    "Reconstruction",
    "response_error",
    "save_reconstruction",
    "contact_sheet",
    "count_curve",
    "linearize_by_model",
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
    on = np.asarray(on, dtype=np.float64)
    theta_off = theta_on if theta_off is None else theta_off
    for name, v in (("theta_on", theta_on), ("theta_off", theta_off)):
        v = np.asarray(v, dtype=np.float64)
        if not np.all(np.isfinite(v)) or np.any(v <= 0):
            raise EvtkError(f"{name} must be positive and finite")
    rise = on * theta_on
    if off is not None:
        rise = rise - np.asarray(off, dtype=np.float64) * theta_off
    # exp overflows beyond ~709: that many thresholds is not a physical count
    if np.any(rise > 700):
        raise EvtkError("counts imply an intensity rise beyond exp(700): not a linearisable response")
    return np.expm1(rise)


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


def plan(rec, window="schedule", skip_us=0, length_us=None, region=None):
    """What :func:`reconstruct` will count: ``(simulation record or None, Windows, region)``."""
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
        win = windows_periodic(info["t_start_us"], info["t_end_us"] + 1, window[1], skip_us, length_us)
    else:
        raise EvtkError(f"window must be 'schedule', 'triggers' or ('period', US), not {window!r}")
    if region is None:
        region = tuple(sim["response_region"]) if sim is not None else (0, rec.sensor_size[0], 0, rec.sensor_size[1])
    return sim, win, tuple(region)


def reconstruct(rec, window="schedule", skip_us=0, length_us=None, size=(16, 16), binarize_method="sign",
                linear=True, theta=None, crop="valid", region=None, chunk_events=4_000_000, progress=None,
                deblur=None, flat_field=True):
    """The whole pipeline on an open recording: windows, counts, linearisation, passes, grid, binarisation.

    Parameters
    ----------
    rec : Recording
    window : "schedule", "triggers" or ("period", period_us)
    skip_us, length_us : int
        Shorten or delay every window (leave out the pixels' settling).
    size : (rows, cols)
        Output size of each response.
    binarize_method : "sign", "mean", "otsu" or a number
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

    With a simulation record, linearisation inverts the recording's own pixel
    model (:func:`count_curve`); otherwise (or with ``theta`` given) it uses
    ``exp(n * theta) - 1``.
    """
    _check_crop(crop)
    sim, win, region = plan(rec, window, skip_us, length_us, region)
    counts = accumulate(rec, win, region, chunk_events=chunk_events, progress=progress)
    return reconstruct_counts(counts, sim, skip_us=skip_us, length_us=length_us, size=size,
                              binarize_method=binarize_method, linear=linear, theta=theta, crop=crop,
                              deblur=deblur, flat_field=flat_field)


def _check_crop(crop):
    if crop not in ("valid", "full"):
        raise EvtkError(f"crop must be 'valid' or 'full', not {crop!r}")


def reconstruct_counts(counts, sim=None, skip_us=0, length_us=None, size=(16, 16), binarize_method="sign",
                       linear=True, theta=None, crop="valid", deblur=None, flat_field=True):
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
    net = counts.on.astype(np.float64) - counts.off
    gain = None
    if linear and flat_field and schedule is not None and np.any(schedule.kernel_id < 0):
        gain = flat_field_gain(net[schedule.kernel_id < 0], _expected_flat_counts(sim, bench, region, curve, theta_on))
    if not linear:
        values = net
    elif curve is not None:  # invert the recording's own pixel model
        values = linearize_by_model(net if gain is None else net * gain, curve)
    else:
        g = 1.0 if gain is None else gain
        values = linearize(counts.on * g, counts.off * g, theta_on, theta_off)

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
    }
    if ideal is not None:
        summary["error"] = response_error(cells, ideal)
    return Reconstruction(responses, binary, pairs, cells, ideal, counts, summary)


def save_reconstruction(path, result: Reconstruction, sensor_size, metadata=None):
    """Write a reconstruction as ``.npz`` or as evtk HDF5 (``.h5``/``.hdf5``), atomically.

    Arrays: ``responses``, ``binary``, ``cells``, ``ideal`` (when known),
    ``pairs``, ``window_start_us``/``window_end_us``, ``on``/``off`` counts;
    the summary (parameters, errors) as JSON (``summary`` in NPZ, in the
    metadata in HDF5, together with ``metadata``).
    """
    import os

    arrays = {"responses": result.responses, "binary": result.binary, "cells": result.cells,
              "window_start_us": result.counts.windows.t_start_us, "window_end_us": result.counts.windows.t_end_us,
              "on": result.counts.on, "off": result.counts.off}
    if result.ideal is not None:
        arrays["ideal"] = result.ideal
    if result.pairs is not None:
        arrays["pairs"] = result.pairs
    meta = {"reconstruction": result.summary, **(metadata or {})}
    ext = os.path.splitext(os.fspath(path))[1].lower()
    if ext == ".npz":
        from .io._atomic import AtomicFile

        with AtomicFile(path) as f:
            np.savez_compressed(f.file, summary=np.array(json.dumps(meta)), **arrays)
    elif ext in (".h5", ".hdf5"):
        from .io.hdf5 import Hdf5Writer

        with Hdf5Writer(path, sensor_size, "lz4", meta) as w:
            for name, a in arrays.items():
                w.write_array(f"reconstruction/{name}", a)
    else:
        raise EvtkError(f"cannot tell the output format from {ext!r}: use .npz, .h5 or .hdf5")


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
    n = np.asarray(net_counts, dtype=np.float64)
    if not np.all(np.isfinite(n)):
        raise EvtkError("counts to linearise must be finite")
    levels, mid = _count_steps(curve)
    return np.expm1(np.interp(n, levels, mid))


def _expected_flat_counts(sim, bench, region, curve, theta_on):
    """Net count a nominal pixel gives in a flat-field window, per pixel of ``region`` (y, x).

    The light is the optics' own (every mirror on, borders included); with
    a count curve the count is the curve read continuously, else
    ``log-step / theta_on``.
    """
    from .optics import screen_response

    kshape = np.asarray(sim["kernels"]).shape[1:]
    fshape = np.asarray(sim["features"]).shape[1:]
    light = screen_response(np.ones(kshape), np.ones(fshape), bench, tuple(region))
    rate = float(sim["gain_e_per_s_per_unit"]) * light + float(sim["sensor"]["dark_current_e_per_s"])
    u = np.log(np.maximum(rate, 1e-300) / float(sim["blank_rate_e_per_s"]))
    if curve is None:
        return u / theta_on
    levels, mid = _count_steps(curve)
    return np.interp(u, mid, levels)


def _count_steps(curve):
    """Whole counts 0..top of a :func:`count_curve` and the log-light step each stands for (its middle)."""
    u, n_of_u = curve
    top = int(n_of_u[-1])
    levels = np.arange(top + 2)
    first = np.searchsorted(n_of_u, levels, side="left")  # first grid index reaching each count
    lo = u[np.minimum(first[:-1], u.size - 1)]
    hi = np.where(first[1:] < u.size, u[np.minimum(first[1:], u.size - 1)], u[-1])
    mid = 0.5 * (lo + hi)
    mid[0] = 0.0
    return levels[:-1], mid


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
