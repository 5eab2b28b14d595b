"""Windows without a schedule straight to their responses: numpy, or evtk's optional compiled counting; no JIT, no scipy.

Each window of a recording without a schedule stands alone, and its response needs only its pixels' ON and
OFF counts. :func:`fixed_responses` reads the events a batch of windows at a time (through the recording's
time-window API; where a batch's responses take work of their own, the next chunk decoded on another thread
meanwhile), maps each event to its window (binary search of the window bounds in the sorted time stamps) and by
unsigned arithmetic on its coordinates to the bin of the region it counts for, and counts with
:func:`numpy.bincount`, or where evtk's compiled kernel was built (:mod:`evtk._native`) with it, in one pass
that needs no keys in memory and releases the GIL:

* net counts (``linear=False``) resized by whole factors: each event straight to its output cell, so a batch
  is (windows, cells) integers and the response is the exact mean the whole-run path computes;
* otherwise each event to its pixel of the region (windows, pixels) a few windows at a time, linearised by
  the same ``expm1`` table as :func:`evtk.reconstruct.linearize` and resized by
  :func:`evtk.reconstruct.downsample`.

Memory stays bounded by the responses and one batch (:data:`BATCH_BINS` counts), never windows x sensor.
A chunk's windows are counted in runs of whole windows on several threads (:mod:`evtk._parallel`: half of
``EVTK_THREADS`` or the cores), each run into its own windows' bins, so the counts are one thread's exactly.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, Any

import numpy as np

from .._native import TABLE_SIZE, padded_table
from .._native import count_windows as native_count_windows
from .._native import enabled as native_enabled
from .._parallel import cuts, parts, run
from .._threads import workers
from ..errors import EvtkError
from ..events import Events
from ..limits import memory_limit_bytes, require_memory
from .binarize import binarize, binarize_rule
from .grid import downsample
from .windows import WindowCounts, Windows

if TYPE_CHECKING:
    from .result import Reconstruction

#: Most count bins (int32) one batch of windows holds: 8 MB, small enough to stay in cache.
BATCH_BINS = 1 << 21

#: Most events read at once, whatever larger ``chunk_events`` a caller gives: a chunk's columns (13 MB) are
#: reused by the allocator from one chunk to the next, where 4 M-event chunks (52 MB, 32 MB of them time stamps)
#: were mapped and faulted in afresh each time (a fresh 20 M-event count: peak RSS 133 -> 65 MB, a quarter fewer
#: page faults, no slower).
READ_EVENTS = 1 << 20

#: Largest (ON, OFF) table of ``expm1`` values looked up; larger counts are linearised directly.
_TABLE_MAX = 1 << 20

#: The settings :func:`fixed_responses` takes (the rest need a schedule or the per-pixel stages).
FIXED_OPTIONS = frozenset({"size", "binarize_method", "linear", "theta", "crop", "skip_us", "length_us", "deblur",
                           "flat_field", "timing"})


def linear_without_plan(linear: bool, theta: float | None) -> bool:
    """Whether counts without a plan are linearised: only by a theta given (``exp(n theta)``).

    Without a pixel model or a flat-field gain nothing says how counts map to light, so the responses are net
    counts ON - OFF unless the user states a contrast threshold. The one rule of :func:`fixed_responses`,
    :func:`evtk.reconstruct.reconstruct_counts` without a plan and :func:`evtk.sweeps.recording_noise`.

    Parameters
    ----------
    linear : bool
        Linearisation asked for (``--linearize``, the default) or not (``--counts``).
    theta : float, optional
        The contrast threshold given, if any.

    Returns
    -------
    bool
        True only for ``linear`` with a ``theta``.
    """
    return bool(linear) and theta is not None


def fixed_supported(options: dict) -> bool:
    """Whether :func:`fixed_responses` takes these :func:`evtk.reconstruct.reconstruct_counts` settings.

    Parameters
    ----------
    options : dict
        The settings.

    Returns
    -------
    bool
        True when every setting is one it takes, ``theta`` is a positive number or None and ``timing`` is
        not asked for (without a pixel model there are no event times to read).
    """
    theta = options.get("theta")
    return (set(options) <= FIXED_OPTIONS and options.get("timing") is not True
            and (theta is None or (np.ndim(theta) == 0 and np.isfinite(theta) and float(theta) > 0))
            and options.get("crop", "valid") in ("valid", "full"))


def _region(source: Any, region: tuple) -> tuple[int, int, int, int]:
    """``region`` as four ints, or an error when it is not a non-empty part of the source's sensor."""
    sensor = tuple(source.sensor_size)
    x0, x1, y0, y1 = (int(v) for v in region)
    if not (0 <= x0 < x1 <= sensor[0] and 0 <= y0 < y1 <= sensor[1]):
        raise EvtkError(f"region {tuple(region)} is not a non-empty part of the {sensor[0]}x{sensor[1]} sensor")
    return x0, x1, y0, y1


class _Cells:
    """How an event's pixel and polarity map to its bin within its window, by arithmetic in a small unsigned type.

    Along each axis a sensor coordinate ``c`` goes to ``min(c - lo, n) // per`` (``c - lo`` wrapping below ``lo``
    to a value past ``n``): its block inside ``[lo, lo + n)`` and one extra (dump) place past the last block
    outside it. The bin is ``row * (cols + 1) + col + p * plane`` (OFF counts, then ON counts). Coordinates and
    keys stay in ``dtype`` (uint16 where a window's bins fit it: 2-byte passes, no look-up tables, whose
    ``take`` casts every index to intp), so a key costs a few cheap passes before :func:`numpy.bincount`.
    """

    def __init__(self, region: tuple[int, int, int, int], sensor: tuple[int, int], fy: int, fx: int, cols: int,
                 plane: int) -> None:
        x0, x1, y0, y1 = region
        # uint16 where every key of a window and every wrapped coordinate (below 2**16 + lo) fits it
        self.dtype: type[np.unsignedinteger] = (np.uint16 if 2 * plane <= 1 << 16 and max(sensor) <= 1 << 15
                                                else np.uint32 if 2 * plane <= 1 << 32 else np.uint64)
        u = self.dtype
        # (lo, n, per, mul) of y, then of x; None where the step changes nothing. The clip to n is kept on a
        # whole-sensor axis too: a coordinate off the sensor (the readers refuse them, but a source that did not)
        # goes to the dump place, never to another pixel's or window's bin
        self.y = (u(y0) if y0 else None, u(y1 - y0), u(fy) if fy > 1 else None, u(cols + 1))
        self.x = (u(x0) if x0 else None, u(x1 - x0), u(fx) if fx > 1 else None, None)
        self.plane = u(plane)
        self._tables: tuple[np.ndarray, np.ndarray] | None = None

    def keys(self, x: np.ndarray, y: np.ndarray, p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Each event's bin within its window into ``a`` (``b``: room of the same size and type); returns ``a``."""
        self._axis(y, self.y, a)
        self._axis(x, self.x, b)
        a += b
        np.multiply(p, self.plane, out=b)
        a += b
        return a

    def tables(self) -> tuple[np.ndarray, np.ndarray]:
        """``(ky, kx)``: :meth:`keys` as look-up tables over every uint16 coordinate (int64, for
        :func:`evtk._native.count_windows`): an event's bin within its window is ``ky[y] + kx[x] + p * plane``."""
        if self._tables is None:
            c = np.arange(TABLE_SIZE, dtype=self.dtype)
            ky, kx = np.empty_like(c), np.empty_like(c)
            self._axis(c, self.y, ky)
            self._axis(c, self.x, kx)
            self._tables = ky.astype(np.int64), kx.astype(np.int64)
        return self._tables

    @staticmethod
    def _axis(c: np.ndarray, spec: tuple, out: np.ndarray) -> None:
        lo, n, per, mul = spec
        if lo is not None:
            np.subtract(c, lo, out=out)  # wraps below lo: past n, clipped to the dump place next
            c = out
        np.minimum(c, n, out=out)
        if per is not None:
            np.floor_divide(out, per, out=out)
        if mul is not None:
            np.multiply(out, mul, out=out)


def _window_events(source: Any, windows: Windows, first: int, last: int, chunk_events: int
                   ) -> Iterator[Events]:
    """The events of windows ``first .. last - 1`` in time order, in chunks: slices of sorted in-memory events,
    or a recording's time-window reads."""
    a = int(windows.t_start_us[first:last].min())
    z = int(windows.t_end_us[first:last].max())
    if isinstance(source, Events):
        i, j = (int(v) for v in np.searchsorted(source.t, [a, z], side="left"))
        for k in range(i, j, chunk_events):
            yield source[k:min(j, k + chunk_events)]
        return
    from .accumulate import _in_time_order

    yield from _in_time_order(source.iter_events(chunk_events=chunk_events, t_start_us=a, t_end_us=z), source)


def _check_on_sensor(ev: Events, i: int, j: int) -> None:
    """Refuse in-memory events ``i:j`` that lie off their sensor (``Events`` does not check its coordinates
    against its size; the readers do): their bins would be another pixel's or out of the tables."""
    if j <= i:
        return
    w, h = ev.sensor_size
    x_max, y_max = int(ev.x[i:j].max()), int(ev.y[i:j].max())
    if x_max >= w or y_max >= h:
        raise EvtkError(f"events lie outside their {w}x{h} sensor (x up to {x_max}, y up to {y_max}): give the "
                        "Events the sensor size they were recorded on")


#: Events counted at a time, so that their keys stay in cache.
_PIECE = 1 << 16


def _window_picks(ev: Events, starts: np.ndarray, ends: np.ndarray) -> tuple[np.ndarray, slice | np.ndarray]:
    """Each window's number of events in the chunk (``[start, end)`` by binary search in its sorted time stamps;
    windows may overlap or come in any order) and what picks them out, window after window: one slice when
    they lie back to back, else the indices."""
    lo = np.searchsorted(ev.t, starts, side="left")
    hi = np.searchsorted(ev.t, ends, side="left")
    n = hi - lo
    total = int(n.sum())
    a, z = (int(lo[0]), int(hi[-1])) if len(n) else (0, 0)
    if z - a == total and np.array_equal(lo[1:], hi[:-1]):  # back to back: one slice, no gather
        return n, slice(a, z)
    return n, np.arange(total, dtype=np.int64) + np.repeat(lo - (np.cumsum(n) - n), n)


def _batches(source: Any, windows: Windows, firsts: list[int], nexts: list[int], chunk_events: int,
             progress: Callable[[int], Any] | None, batch: Callable[[int], Any], add: Callable[..., None],
             finished: Callable[..., Any], overlap: bool = True) -> Iterator[Any]:
    """Count the windows a batch at a time (windows ``firsts[b]:nexts[b]``), yielding ``finished(i, j, *state)``
    of each batch in order: ``batch(b)`` makes a batch's state, ``add(ev, i, j, *state)`` counts a chunk of
    events into it. Windows in time order, none overlapping an earlier one, take one pass over the events, each
    chunk counted into the batches it reaches and a batch handed on as soon as a chunk passes its last window's
    end (later chunks are later in time); others go a batch at a time through the time-window reads.

    ``overlap``: the next chunk is decoded on another thread while this one is counted and its batches used,
    this thread decoding beside it once it has counted (:class:`evtk._threads.Helpers`; where the caller's work
    on a batch is long and mostly outside the GIL: enob's sums, and any compiled counting); False: each chunk is
    decoded on the reader's threads, then counted (where numpy's counting is all there is: its bincount holds the
    GIL and its many small calls take it back from the decoding; 3 % quicker in a fresh `reconstruct -o` than the
    overlap)."""
    from .accumulate import _prefetched, span_chunks

    starts, ends = windows.t_start_us, windows.t_end_us
    n_w = len(windows)
    if n_w == 1 or np.all(starts[1:] >= np.maximum.accumulate(ends)[:-1]):
        last_end = np.maximum.accumulate(ends)[[j - 1 for j in nexts]]
        b = 0
        current = None
        chunks = span_chunks(source, int(starts[0]), int(last_end[-1]), chunk_events, overlap=overlap)
        for ev in _prefetched(chunks) if overlap else chunks:
            t_last = int(ev.t[-1]) if len(ev) else None
            while b < len(firsts) and t_last is not None:
                i, j = firsts[b], nexts[b]
                if int(starts[i]) > t_last:  # this batch starts after the chunk
                    break
                if current is None:
                    current = batch(b)
                add(ev, i, j, *current)
                if int(last_end[b]) > t_last:  # the next chunk may hold more of it
                    break
                yield finished(i, j, *current)
                b, current = b + 1, None
            if progress is not None:
                progress(len(ev))
        for rest in range(b, len(firsts)):  # batches the last events did not close (or reach)
            yield finished(firsts[rest], nexts[rest], *(current if current is not None else batch(rest)))
            current = None
        return

    def batch_chunks() -> Iterator[tuple[int, Events]]:
        for b, i in enumerate(firsts):
            for ev in _window_events(source, windows, i, nexts[b], chunk_events):
                yield b, ev

    chunks = _prefetched(batch_chunks())
    pending = next(chunks, None)
    for b, i in enumerate(firsts):
        state = batch(b)
        while pending is not None and pending[0] == b:
            add(pending[1], i, nexts[b], *state)
            if progress is not None:
                progress(len(pending[1]))
            pending = next(chunks, None)
        yield finished(i, nexts[b], *state)


def _count(ev: Events, starts: np.ndarray, ends: np.ndarray, cells: _Cells, out: np.ndarray) -> np.ndarray:
    """Add the chunk's events to ``out`` (flat int32 bins, ``per_window`` each): each window's events (``[start,
    end)``, by binary search in the sorted time stamps; windows may overlap or come in any order) to their bin
    within the window (:class:`_Cells`) in their window's bins, a cache-sized piece at a time. Returns the number
    of events of each window."""
    n, where = _window_picks(ev, starts, ends)
    total = int(n.sum())
    if total == 0:
        return n
    per_window = out.size // len(starts)
    if native_enabled():  # compiled, the GIL released: no keys in memory
        ky, kx = cells.tables()
        at = np.zeros(len(n) + 1, np.int64)
        np.cumsum(n, out=at[1:])
        if native_count_windows(ev.x, ev.y, ev.p, where, at, ky, kx, int(cells.plane), per_window, per_window, 0,
                                 False, out):
            return n
    x, y, p = ev.x[where], ev.y[where], ev.p[where]
    bounds = [0, *np.cumsum(n).tolist()]  # of each window's events, in x, y, p
    room = min(total, _PIECE)
    a, b = np.empty(room, cells.dtype), np.empty(room, cells.dtype)
    keys = np.empty(room, np.uint64)  # (as intp below: every key is under the batch's bins)
    w = 0
    for s in range(0, total, _PIECE):
        e = min(total, s + _PIECE)
        m = e - s
        inside = cells.keys(x[s:e], y[s:e], p[s:e], a[:m], b[:m])
        key = keys[:m]
        while bounds[w + 1] <= s:  # the piece's first window
            w += 1
        first = v = w
        while v < len(n) and bounds[v] < e:  # each window's events of the piece: its offset among the span's bins
            lo, hi = max(bounds[v], s) - s, min(bounds[v + 1], e) - s
            np.add(inside[lo:hi], np.uint64((v - first) * per_window), out=key[lo:hi])
            v += 1
        span = out[first * per_window:v * per_window]
        if span.size <= 4 * m:  # few bins: count them all (faster than scattered adds)
            span += np.bincount(key.view(np.intp), minlength=span.size)
        else:
            np.add.at(span, key.view(np.intp), span.dtype.type(1))  # (a typed one: numpy's fast path)
    return n


def _linearised(on: np.ndarray, off: np.ndarray, theta: float) -> np.ndarray:
    """``expm1(on * theta - off * theta)`` computed as :func:`evtk.reconstruct.linearize` computes it (its
    look-up table of the distinct counts where that fits, else directly; the same rise, refused beyond exp(700))."""
    hi_on, hi_off = int(on.max(initial=0)), int(off.max(initial=0))
    if (hi_on + 1) * (hi_off + 1) <= _TABLE_MAX and hi_on * theta <= 700:  # else only the rises that occur
        rise = np.arange(hi_on + 1.0)[:, None] * theta - np.arange(hi_off + 1.0)[None, :] * theta
        index = np.multiply(on, hi_off + 1, dtype=np.int32)  # below 2**20: the table's size
        index += off
        return np.expm1(rise).ravel().take(index)
    rise = on.astype(np.float64) * theta - off.astype(np.float64) * theta
    if np.any(rise > 700):
        raise EvtkError("counts imply an intensity rise beyond exp(700): not a linearisable response")
    return np.expm1(rise)


def pixel_values(on: np.ndarray, off: np.ndarray, linear: bool, theta: float) -> np.ndarray:
    """Each pixel's value from its ON and OFF counts, as the whole-run path computes it.

    Parameters
    ----------
    on, off : ndarray of int
        ON and OFF counts, of one shape.
    linear : bool
        ``expm1(on * theta - off * theta)`` (:func:`evtk.reconstruct.linearize`), else the net counts.
    theta : float
        The contrast threshold (log units).

    Returns
    -------
    ndarray of float64
        The values, the counts' shape.

    Raises
    ------
    EvtkError
        A rise beyond exp(700).
    """
    return _linearised(on, off, theta) if linear else (on - off).astype(np.float64)


def count_batches(source: Events | Any, windows: Windows, region: tuple[int, int, int, int],
                  cells: tuple[int, int] | None = None, kept_bytes: int = 0, batch_windows: int | None = None,
                  chunk_events: int = 4_000_000, progress: Callable[[int], Any] | None = None,
                  overlap: bool = True) -> Iterator[tuple[int, np.ndarray, np.ndarray, int]]:
    """ON and OFF counts of the windows over a region's pixels (or whole-factor blocks of them), a batch of
    windows at a time, with numpy.

    Parameters
    ----------
    source : Events or Recording
        The events (in-memory events sorted by time) or an open recording.
    windows : Windows
        The windows, in any order (a batch spans consecutive ones).
    region : tuple of int
        (x0, x1, y0, y1), half-open sensor pixels.
    cells : tuple of int, optional
        (rows, cols) dividing the region's height and width: count each block of pixels as one.
    kept_bytes : int
        What the caller keeps for the whole run beside the batches (checked with them against the budget).
    batch_windows : int, optional
        Windows a batch; default as many as :data:`BATCH_BINS` counts (and a quarter of the budget) hold.
    chunk_events : int
        Most events read at once (at most :data:`READ_EVENTS`).
    progress : callable, optional
        Called with the number of events of each chunk read.
    overlap : bool
        Decode the next chunk on another thread while one is counted and the batches it closes are used (for
        callers with much work on each batch); False: decode each chunk, then count it (quicker in a fresh
        process where the counting is all the work).

    Yields
    ------
    tuple of (int, ndarray, ndarray, int)
        The batch's first window, its ON and OFF counts (int32, (windows, rows, cols): views valid until the
        next batch) and the number of events they hold.

    Raises
    ------
    EvtkError
        A region off the sensor, more memory than the budget allows, or a window holding more than 2**31 - 1
        events.
    """
    x0, x1, y0, y1 = _region(source, region)
    if isinstance(source, Events):
        source = source.sorted()
        _check_on_sensor(source, 0, len(source))
    h_px, w_px = y1 - y0, x1 - x0
    n_w = len(windows)
    sensor = (int(source.sensor_size[0]), int(source.sensor_size[1]))
    fy, fx = (h_px // cells[0], w_px // cells[1]) if cells is not None else (1, 1)
    rows, cols = h_px // fy, w_px // fx  # of bins, each with one more (the pixels outside the region)
    plane = (rows + 1) * (cols + 1)  # OFF counts, then ON counts
    per_window = 2 * plane
    # a window's int32 bins, and for pixels their float64 values and what the caller makes of them
    window_bytes = 4 * per_window + (0 if cells is not None else 24 * h_px * w_px)
    if batch_windows is None:
        fits = (memory_limit_bytes() // 4 - kept_bytes) // window_bytes
        nb = max(1, min(n_w, BATCH_BINS // per_window, fits))
    else:
        nb = max(1, min(n_w, int(batch_windows)))
    require_memory(kept_bytes + nb * window_bytes + _PIECE * 16,
                   f"counting {n_w:,} windows over {w_px}x{h_px} pixels, {nb:,} at a time")
    keys = _Cells((x0, x1, y0, y1), sensor, fy, fx, cols, plane)
    firsts = list(range(0, n_w, nb))
    nexts = [min(i + nb, n_w) for i in firsts]
    starts, ends = windows.t_start_us, windows.t_end_us

    def batch(b: int) -> tuple[np.ndarray, np.ndarray]:
        j = nexts[b] - firsts[b]
        return np.zeros(j * per_window, np.int32), np.zeros(j, np.int64)

    def finished(i: int, j: int, out: np.ndarray, totals: np.ndarray) -> tuple[int, np.ndarray, np.ndarray, int]:
        bins = out.reshape(j - i, 2, rows + 1, cols + 1)
        outside = int(bins[:, :, rows, :].sum()) + int(bins[:, :, :rows, cols].sum())
        return i, bins[:, 1, :rows, :cols], bins[:, 0, :rows, :cols], int(totals.sum()) - outside

    def add(ev: Events, i: int, j: int, out: np.ndarray, totals: np.ndarray) -> None:
        # runs of whole windows (about equal events), one a thread: each counts into its own windows' bins
        n = np.searchsorted(ev.t, ends[i:j], side="left") - np.searchsorted(ev.t, starts[i:j], side="left")
        bounds = cuts(n, parts(int(n.sum()), gil_free=native_enabled()))
        totals += np.concatenate(run(_count, [(ev, starts[i + a:i + z], ends[i + a:i + z], keys,
                                               out[a * per_window:z * per_window])
                                              for a, z in zip(bounds, bounds[1:])]))
        if totals.max(initial=0) > np.iinfo(np.int32).max:
            raise EvtkError(f"window {i + int(np.argmax(totals))} holds more than 2**31 - 1 events: its int32 "
                            "counts could overflow")

    yield from _batches(source, windows, firsts, nexts, max(1, min(int(chunk_events), READ_EVENTS)), progress,
                        batch, add, finished, overlap)


def fixed_responses(source: Events | Any, windows: Windows, region: tuple, size: tuple = (16, 16),
                    binarize_method: str | float = "auto", linear: bool = True, theta: float | None = None,
                    skip_us: int = 0, length_us: int | None = None, chunk_events: int = 4_000_000,
                    progress: Callable[[int], Any] | None = None, batch_windows: int | None = None,
                    **ignored: Any) -> Reconstruction:
    """The responses of windows without a schedule, counted with numpy a batch of windows at a time.

    What :func:`evtk.reconstruct.reconstruct_counts` gives the same windows' counts without a plan (the same
    responses to rounding, the same binary responses and summary), in memory bounded by the responses and one
    batch: only the region's pixels are counted, in int32 bins (net counts resized by whole factors go
    straight to their output cell), and no window's pixels are kept.

    Parameters
    ----------
    source : Events or Recording
        The events (in-memory events sorted by time) or an open recording.
    windows : Windows
        The windows, in any order (the responses keep it); windows in time order read each event once.
    region : tuple of int
        (x0, x1, y0, y1), half-open sensor pixels.
    size : tuple of int
        (rows, cols) of each response.
    binarize_method : str or float
        As :func:`evtk.reconstruct.binarize`; ``"auto"``: :func:`evtk.reconstruct.binarize_rule` without a plan.
    linear : bool
        Linearise by ``exp(n theta) - 1`` (eq. of :func:`evtk.reconstruct.linearize`), else net counts ON - OFF.
        Only with ``theta`` given: without a plan nothing else says how counts map to light.
    theta : float, optional
        The contrast threshold of ``exp(n theta)``; None (default): net counts.
    skip_us, length_us : int
        Recorded in the summary (the windows already hold them).
    chunk_events : int
        Most events read at once (at most :data:`READ_EVENTS`).
    progress : callable, optional
        Called with the number of events of each chunk read.
    batch_windows : int, optional
        Windows counted at a time; default as many as :data:`BATCH_BINS` counts hold.
    **ignored
        Settings that change nothing without a schedule (``crop``, ``deblur``, ``flat_field``, ``timing``).

    Returns
    -------
    Reconstruction
        ``responses`` (float64, (windows, rows, cols)), ``binary``, ``cells`` (the responses themselves) and
        the summary; the counts hold no pixels (``on``/``off`` of shape (windows, 0, 0)).

    Raises
    ------
    EvtkError
        No windows, a region off the sensor, a size below 1, counts whose rise exceeds exp(700), or more
        memory than the budget allows.
    """
    n_w = len(windows)
    if n_w == 0:
        raise EvtkError("no windows to reconstruct")
    x0, x1, y0, y1 = _region(source, region)
    h_px, w_px = y1 - y0, x1 - x0
    oh, ow = (int(v) for v in size)
    if oh < 1 or ow < 1:
        raise EvtkError(f"size must be positive, not {size}")
    linear = linear_without_plan(linear, theta)
    theta_on = 0.2 if theta is None else float(theta)
    cells = not linear and h_px % oh == 0 and w_px % ow == 0  # each event straight to its output cell
    responses = np.empty((n_w, oh, ow), np.float64)
    used = 0
    # straight to the cells, a batch needs nothing but its counts: with numpy's counting (which holds the GIL)
    # each chunk decoded, then counted; the compiled counting releases it, so the next chunk decodes meanwhile
    for i, on, off, n_used in count_batches(source, windows, (x0, x1, y0, y1), (oh, ow) if cells else None,
                                            n_w * oh * ow * 9, batch_windows, chunk_events, progress,
                                            overlap=not cells or native_enabled()):
        used += n_used
        if cells:  # the block mean of net counts: their exact sum over the block's pixel count
            responses[i:i + len(on)] = (on - off).astype(np.float64) / ((h_px // oh) * (w_px // ow))
        else:
            responses[i:i + len(on)] = downsample(pixel_values(on, off, linear, theta_on), (oh, ow))
    method = binarize_rule(None) if isinstance(binarize_method, str) and binarize_method == "auto" else binarize_method
    binary = binarize(responses, method)
    summary = {
        "captures": None, "windows": n_w, "window_source": windows.source, "windows_dropped": windows.dropped,
        "events_used": used, "region": [x0, x1, y0, y1], "responses": n_w, "size": [oh, ow], "linear": bool(linear),
        "theta_on": theta_on, "binarize": str(method), "skip_us": int(skip_us),
        "length_us": None if length_us is None else int(length_us), "deblurred": False, "level_light_ratio": None,
        "deblur_regularisation": None, "flat_field_captures": 0, "decimation": 1,
        "linearization": "exp(n theta)" if linear else "counts", "timed_share": None, "timing_skipped": None,
    }
    from .result import Reconstruction  # (here: enob's net counts need neither)
    from .summary import ReconstructionSummary

    empty = np.zeros((n_w, 0, 0), np.int32)
    return Reconstruction(responses, binary, None, responses, None,
                          WindowCounts(empty, empty, windows, (x0, x1, y0, y1), used),
                          ReconstructionSummary.from_dict(summary))


def net_count_batches(source: Events | Any, windows: Windows, region: tuple[int, int, int, int],
                      batch_windows: int | list[int] | np.ndarray | None = None, chunk_events: int = 4_000_000,
                      progress: Callable[[int], Any] | None = None) -> Iterator[tuple[int, np.ndarray, int]]:
    """Net counts ON - OFF of the windows over a region's pixels, a batch of windows at a time, with numpy.

    Each event adds its polarity's sign (+1 ON, -1 OFF) to its window's pixel in one integer frame a batch: the
    net counts :func:`pixel_values` gives without linearisation, without the separate ON and OFF counts or a
    float copy. Windows in time order, none overlapping an earlier one, are counted in one pass over the
    events; the others a batch at a time through the recording's time-window reads.

    Parameters
    ----------
    source : Events or Recording
        The events (in-memory events sorted by time) or an open recording.
    windows : Windows
        The windows, in any order (a batch spans consecutive ones).
    region : tuple of int
        (x0, x1, y0, y1), half-open sensor pixels.
    batch_windows : int or list of int or ndarray, optional
        Windows a batch, or the first window of each batch (increasing, from 0); default as many windows as
        :data:`BATCH_BINS` counts hold.
    chunk_events : int
        Most events read at once.
    progress : callable, optional
        Called with the number of events of each chunk read.

    Yields
    ------
    tuple of (int, ndarray, int)
        The batch's first window, its net counts ((windows, rows, cols), C-contiguous: valid until the next
        batch; int16 where no window of the batch holds more than 32,767 events, else int32) and the most
        events one of its windows holds (a bound on every net count's magnitude).

    Raises
    ------
    EvtkError
        A region off the sensor, batches that do not start at 0 and increase, more memory than the budget
        allows, or a window holding more than 2**31 - 1 events.
    """
    x0, x1, y0, y1 = _region(source, region)
    if isinstance(source, Events):
        source = source.sorted()
        _check_on_sensor(source, 0, len(source))
    h_px, w_px = y1 - y0, x1 - x0
    frame = h_px * w_px
    n_w = len(windows)
    if n_w == 0:
        return
    if batch_windows is None or np.ndim(batch_windows) == 0:
        step = max(1, BATCH_BINS // frame if batch_windows is None else int(batch_windows))  # type: ignore[arg-type]
        firsts = list(range(0, n_w, step))
    else:
        firsts = [int(v) for v in batch_windows]  # type: ignore[union-attr]
        if not firsts or firsts[0] != 0 or any(b <= a for a, b in zip(firsts, firsts[1:])) or firsts[-1] >= n_w:
            raise EvtkError(f"batches must start at window 0 and increase below {n_w}")
    nexts = firsts[1:] + [n_w]  # each batch's end
    nb = max(j - i for i, j in zip(firsts, nexts))
    dumps = workers()  # a dump bin a counting thread (events outside the region)
    require_memory(4 * (nb * frame + dumps) + _PIECE * 16,
                   f"counting {n_w:,} windows over {w_px}x{h_px} pixels, {nb:,} at a time")
    # keys: window * frame + pixel inside the region; a pixel outside it gets a key past every window's frame,
    # clipped to its thread's dump bin after the batch's frames
    dump = nb * frame
    dtype: type[np.signedinteger] = np.int32 if 3 * dump + dumps < 2**31 else np.int64
    sensor = (int(source.sensor_size[0]), int(source.sensor_size[1]))
    by_y = np.full(sensor[1], dump, dtype)
    by_y[y0:y1] = np.arange(h_px, dtype=dtype) * w_px
    by_x = np.full(sensor[0], dump, dtype)
    by_x[x0:x1] = np.arange(w_px, dtype=dtype)
    whole = (x0, x1, y0, y1) == (0, sensor[0], 0, sensor[1])
    # the compiled kernel's tables (every uint16 coordinate; off the sensor: the dump), where it counts
    tables = (padded_table(by_y, dump), padded_table(by_x, dump)) if native_enabled() else None
    starts, ends = windows.t_start_us, windows.t_end_us

    def add(ev: Events, i: int, j: int, state: list) -> None:
        n, where = _window_picks(ev, starts[i:j], ends[i:j])
        out, totals, cleared = state
        totals += n
        most = int(totals.max(initial=0))
        if most > np.iinfo(np.int32).max:
            raise EvtkError(f"window {i + int(np.argmax(totals))} holds more than 2**31 - 1 events: its int32 "
                            "counts could overflow")
        total = int(n.sum())
        if total == 0:
            return
        if out.dtype == np.int16 and most > np.iinfo(np.int16).max:  # a pixel's net count could leave int16
            state[0] = out = _widened(out, frames)
        at = np.concatenate(([0], np.cumsum(n)))  # each window's events among the picked ones
        # each window is cleared once, in the first chunk that reaches it or a later one (just before its events
        # are counted); those before `cleared` hold counts already, which later chunks add to
        reach = int(np.flatnonzero(n)[-1]) + 1
        clear = (cleared, max(cleared, reach))
        state[2] = clear[1]
        # runs of whole windows, one a thread: each writes its own windows' frames and its own dump bin
        bounds = cuts(n, min(dumps, parts(total, gil_free=tables is not None)))
        run(_net_count_run, [(ev, where, at, wa, wb, r, j - i, frame, w_px, whole, by_y, by_x, dtype, out, tables,
                              clear) for r, (wa, wb) in enumerate(zip(bounds, bounds[1:]))])

    frames = np.empty(nb * frame + dumps, np.int32)  # one buffer for every batch (its pages touched once)

    def batch(b: int) -> tuple[list]:  # the shared frames: a batch is used before the next
        # int16 frames (half the memory to clear, count into and sum) until a window's events could exceed them;
        # a window's frame is cleared when it is first counted (or when the batch is finished, if never), the
        # dump bins now
        n_b = nexts[b] - firsts[b]
        out = frames.view(np.int16)[:n_b * frame + dumps]
        out[n_b * frame:] = 0
        return [out, np.zeros(n_b, np.int64), 0],

    def finished(i: int, j: int, state: list) -> tuple[int, np.ndarray, int]:
        out, totals, cleared = state
        out[cleared * frame:(j - i) * frame] = 0  # the windows no event reached
        return i, out[:(j - i) * frame].reshape(j - i, h_px, w_px), int(totals.max(initial=0))

    yield from _batches(source, windows, firsts, nexts, max(1, min(int(chunk_events), READ_EVENTS)), progress,
                        batch, add, finished)


def _widened(out: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """int16 bins ``out`` (the start of the int32 buffer ``frames``) as int32 bins at the start of ``frames``,
    for counts that could leave int16 (a window of more than 32,767 events)."""
    wide = out.astype(np.int32)  # (a copy: the int32 bins overlap the int16 ones)
    frames[:wide.size] = wide
    return frames[:wide.size]


def _net_count_run(ev: Events, where: slice | np.ndarray, at: np.ndarray, wa: int, wb: int, r: int, n_w: int,
                   frame: int, w_px: int, whole: bool, by_y: np.ndarray, by_x: np.ndarray, dtype: Any,
                   out: np.ndarray, tables: tuple[np.ndarray, np.ndarray] | None = None,
                   clear: tuple[int, int] = (0, 0)) -> None:
    """Add the signs of the picked events of windows ``wa .. wb - 1`` (``at``: each window's first among them)
    to their frames in ``out`` (``n_w`` windows of ``frame`` bins, then a dump bin per run: this run's is
    ``n_w * frame + r``), the frames of windows ``clear[0] .. clear[1] - 1`` among them set to 0 first. Runs of
    different windows write different bins, so they may go on threads. With ``tables`` (``by_y`` and ``by_x`` over
    every uint16 coordinate) the compiled kernel counts (and clears each window's frame as it reaches it) where it
    can."""
    a, z = int(at[wa]), int(at[wb])
    lo, hi = max(clear[0], wa), min(clear[1], wb)  # the run's windows to clear
    if z <= a:
        out[lo * frame:hi * frame] = 0
        return
    if tables is not None and native_count_windows(ev.x, ev.y, ev.p, where, at[wa:wb + 1], *tables, 0, frame, frame,
                                                    (n_w - wa) * frame + r, True, out[wa * frame:],
                                                    (lo - wa, hi - wa)):
        return
    out[lo * frame:hi * frame] = 0
    pick = slice(where.start + a, where.start + z) if isinstance(where, slice) else where[a:z]
    if whole:  # the region is the sensor: the key by arithmetic, no table look-ups
        key = np.multiply(ev.y[pick], w_px, dtype=dtype)
        key += ev.x[pick]
    else:
        key = by_y.take(ev.y[pick])
        key += by_x.take(ev.x[pick])
    for w in range(max(wa, 1), wb):  # each window's frame after the first: a slice each, no per-event offsets
        if at[w + 1] > at[w]:
            key[at[w] - a:at[w + 1] - a] += dtype(w * frame)
    if not whole:
        np.minimum(key, dtype(n_w * frame + r), out=key)  # every key outside the region: this run's dump bin
    sign = np.multiply(ev.p[pick], 2, dtype=out.dtype)  # +1 ON, -1 OFF, in the bins' type (numpy's fast path)
    sign -= 1
    np.add.at(out, key, sign)
