"""ON and OFF event counts per window and pixel, in one streamed pass over the events (evtk's compiled kernel where
built, else numba or numpy)."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

from .._lazyjit import njit, numba_ready  # numba loads on the first count, when neither C nor numpy counts
from .._native import TIMED_KERNELS as NATIVE_COUNTS
from .._native import accumulate_chunk as native_accumulate_chunk
from .._native import enabled as native_enabled
from .._threads import Helpers, Pool, helpers, use_helpers
from ..errors import EvtkError
from ..events import Events
from ..limits import memory_limit_bytes, require_memory
from .windows import WindowCounts, Windows

__all__ = ["accumulate", "accumulate_batches", "batch_size", "span_chunks"]

_END = object()


def _in_time_order(chunks: Iterator[Events], source: Any) -> Iterator[Events]:
    """The chunks of a read of the recording ``source``, refused where a time stamp goes back (within a chunk or
    from one to the next): the windows find their events by binary search in each chunk and hand a batch on once
    a chunk passes its end, so events out of order would be counted in other windows or not at all without a
    word (an AEDAT4 file may hold them; the readers return events in file order). One comparison an event.

    Raises
    ------
    EvtkError
        At the first stamp earlier than the one before it.
    """
    last = None
    for ev in chunks:
        t = ev.t
        if len(t):
            back = last is not None and int(t[0]) < last
            shared = helpers()  # on a prefetching thread: a long chunk's check shared with the consumer
            if not back and ev._sorted is None and shared is not None and len(t) >= 4 * _SORT_PIECE:
                ev = Events._trusted(t, ev.x, ev.y, ev.p, ev.sensor_size, _sorted_shared(t, shared))
            if back or not ev.is_sorted:  # (Events' own check, kept with the chunk; a simulation's is known)
                k = 0 if back else int(np.argmax(t[1:] < t[:-1])) + 1
                before = last if k == 0 else int(t[k - 1])
                raise EvtkError(f"{getattr(source, 'path', 'the recording')}: its events are not in time order (a "
                                f"stamp of {int(t[k])} us after one of {before} us), which counting windows needs: "
                                "`evtk convert --sort` writes a sorted copy")
            last = int(t[-1])
        yield ev


#: Stamps a thread compares at a time in :func:`_sorted_shared`.
_SORT_PIECE = 1 << 16


def _sorted_shared(t: np.ndarray, shared: Helpers) -> bool:
    """Whether the stamps ``t`` never decrease, checked a piece at a time by this prefetching thread and the
    consumer it offers the pieces to through ``shared`` (the same answer as :attr:`evtk.Events.is_sorted`)."""
    n = len(t)
    pieces = iter(range(0, n - 1, _SORT_PIECE))
    back: list[int] = []

    def runner() -> None:
        for a in pieces:
            if back:
                return
            b = min(n - 1, a + _SORT_PIECE)
            if not np.all(t[a + 1:b + 1] >= t[a:b]):
                back.append(a)

    shared.share(runner)
    return not back


def _prefetched(chunks):
    """Yield the items of the iterator ``chunks`` while the next one is produced on another thread: the next
    chunk is read and decoded (on the I/O threads) while this one is counted, and once this one is, the
    consumer decodes beside them rather than waiting (:class:`evtk._threads.Helpers`: as many busy threads as
    cores all along)."""
    ex = Pool(1, "evtk-prefetch")
    help_ = Helpers()

    def produce():
        use_helpers(help_)
        try:
            return next(chunks, _END)
        finally:
            use_helpers(None)
            help_.finish()

    help_.start()
    pending = ex.submit(produce)
    try:
        while True:
            help_.wait()
            item = pending.result()
            if item is _END:
                return
            help_.start()
            pending = ex.submit(produce)
            yield item
    finally:  # closed early too: the chunk under way is finished before the chunks' source is let go
        try:
            pending.result()
        except BaseException:  # noqa: BLE001 - raised where it was met, or not needed
            pass
        ex.shutdown()


@njit(cache=True, nogil=True)
def _accumulate_chunk(t, x, y, p, starts, ends, x0, x1, y0, y1, whole, counts, total, started, first, last):
    """Add the chunk's events to every window; returns the number counted.

    ``whole``: the region is the whole sensor, so every event is inside it (the reader checked).
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
        if whole and not timed:
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


_INT32_MAX = np.iinfo(np.int32).max

#: Most work counted in numpy in a process while numba is not loaded, in events (a window's pixel costs a fifth of one):
#: numpy costs about 12 ns an event more than numba (with times; 6 without) and 2-2.5 ns a window's pixel (zeroed
#: and added once per window), numba's start in a fresh process 0.4-0.6 s (docs/performance.md).
_NUMPY_MAX_EVENTS = 20_000_000


#: Work counted in numpy in this process so far (as in :data:`_NUMPY_MAX_EVENTS`).
_numpy_work = 0


def _chunk_counter(events: int | None, window_pixels: int):
    """The chunk counter for a count of about ``events`` events (None: unknown) into ``window_pixels`` pixels of
    all windows: evtk's compiled kernel where the install built it; else numpy while numba is not loaded and this
    count, with those counted in numpy before it in this process, is small enough that numba's start would cost
    more than numpy's slower loop."""
    global _numpy_work
    if native_enabled() and NATIVE_COUNTS:
        return _accumulate_chunk_native
    if numba_ready() or events is None:
        return _accumulate_chunk
    work = events + window_pixels // 5
    if _numpy_work + work > _NUMPY_MAX_EVENTS:
        return _accumulate_chunk
    _numpy_work += work
    return _accumulate_chunk_numpy


def _accumulate_chunk_native(t, x, y, p, starts, ends, x0, x1, y0, y1, whole, counts, total, started, first, last):
    """:func:`_accumulate_chunk` in evtk's compiled kernel (:func:`evtk._native.accumulate_chunk`: the same counts,
    totals and times), which holds no GIL while it counts; for a chunk not in the kernel's form (columns of
    other types), numba's counter once numba is loaded, else numpy's."""
    used = native_accumulate_chunk(t, x, y, p, starts, ends, (x0, x1, y0, y1), counts, total, started, first, last)
    if used is not None:
        return used
    other = _accumulate_chunk if numba_ready() else _accumulate_chunk_numpy
    return other(t, x, y, p, starts, ends, x0, x1, y0, y1, whole, counts, total, started, first, last)


def _accumulate_chunk_numpy(t, x, y, p, starts, ends, x0, x1, y0, y1, whole, counts, total, started, first, last):
    """:func:`_accumulate_chunk` in numpy, window by window (the same counts, totals and times).

    Each window's events are one slice of the time-sorted chunk (``searchsorted``), so a window costs a few
    numpy calls on its own events, none of them a selection: each event's bin in a frame one column wider and
    one row taller than the region (that column and row hold the events outside it: coordinates less the
    region's corner, unsigned so that those below it wrap past its far edge, clipped there), OFF then ON, one
    ``bincount`` of them all, and with times the least and greatest time of each bin (``minimum.at`` /
    ``maximum.at``), of which the region's ON bins are kept. ``whole`` (the region is the sensor) changes nothing.
    """
    n = t.size
    if n == 0:
        return 0
    w_px = x1 - x0
    h_px = y1 - y0
    frame = h_px * w_px
    plane = starts.size * frame
    timed = first.size > 0
    live = np.flatnonzero((ends > t[0]) & (starts <= t[n - 1]))
    if live.size == 0:
        return 0
    los = np.searchsorted(t, starts[live])
    his = np.searchsorted(t, ends[live])
    stride = w_px + 1
    ext = (h_px + 1) * stride  # the frame with its extra column and row
    unsigned = x.dtype.kind == "u" and y.dtype.kind == "u"  # (Events' are uint16)
    used = 0
    for w, lo, hi in zip(live.tolist(), los.tolist(), his.tolist()):
        total[w] += hi - lo
        base = w * frame
        off_w, on_w = counts[base:base + frame], counts[plane + base:plane + base + frame]
        if not started[w]:
            off_w[...] = 0
            on_w[...] = 0
            if timed:
                first[base:base + frame] = -1
                last[base:base + frame] = -1
            started[w] = True
        if hi == lo:
            continue
        xs, ys = x[lo:hi], y[lo:hi]
        if not unsigned:  # (read as int64 once clipped)
            xs, ys = xs.astype(np.uint64), ys.astype(np.uint64)
        xs = np.subtract(xs, xs.dtype.type(x0))
        ys = np.subtract(ys, ys.dtype.type(y0))
        np.minimum(xs, xs.dtype.type(w_px), out=xs)
        np.minimum(ys, ys.dtype.type(h_px), out=ys)
        key = ys.astype(np.intp)
        key *= stride
        key += xs if unsigned else xs.view(np.int64)
        key += (p[lo:hi] != 0) * np.intp(ext)  # ON events in the second frame
        both = np.bincount(key, minlength=2 * ext).reshape(2, h_px + 1, stride)[:, :h_px, :w_px]
        np.add(off_w, both[0].ravel(), out=off_w, casting="unsafe")  # (each below 2**31: the caller checks)
        np.add(on_w, both[1].ravel(), out=on_w, casting="unsafe")
        used += int(both.sum())
        if timed:
            dt = np.subtract(t[lo:hi], starts[w]).astype(np.int32)  # windows shorter than 2**31 us (checked by the caller)
            least = np.full(2 * ext, _INT32_MAX, np.int32)
            np.minimum.at(least, key, dt)
            most = np.full(2 * ext, -1, np.int32)
            np.maximum.at(most, key, dt)
            f = first[base:base + frame]
            new = least.reshape(2, h_px + 1, stride)[1, :h_px, :w_px].ravel()
            fresh = (f < 0) & (new != _INT32_MAX)  # an earlier chunk's first time stays (times are sorted)
            f[fresh] = new[fresh]
            lw = last[base:base + frame]
            np.maximum(lw, most.reshape(2, h_px + 1, stride)[1, :h_px, :w_px].ravel(), out=lw)
    return used


#: Least events a chunk of a whole read holds when it is split so that counting overlaps decoding (:func:`span_chunks`).
OVERLAP_CHUNK_EVENTS = 1 << 18


def span_chunks(source: Events | Any, a: int, z: int, chunk_events: int, starts: np.ndarray | None = None,
                ends: np.ndarray | None = None, overlap: bool = True) -> Iterator[Events]:
    """The events from ``a`` to ``z`` (us, half-open) in time order, in chunks, and perhaps others beside them.

    A recording whose span is at most twice ``z - a`` is read whole, without its time-window filter (which
    costs more than counting the events outside the span): the counting leaves out what no window holds. Its
    chunks are then an eighth of it (at least :data:`OVERLAP_CHUNK_EVENTS`, at most ``chunk_events``), so that
    :func:`accumulate` counts one while the reader's threads decode the next; given the windows themselves
    (``starts``, ``ends``), a reader that knows its packets' spans (AEDAT4's ``iter_events_meeting``) then leaves
    out the packets that meet none of them (the dark time between a bench's captures).

    Parameters
    ----------
    source : Events or Recording
        Events sorted by time, or an open recording.
    a, z : int
        The span, us (half-open).
    chunk_events : int
        Most events a chunk holds.
    starts, ends : numpy.ndarray, optional
        The windows within the span (µs, half-open), when only their events are wanted.
    overlap : bool
        Whether each chunk is counted while the next is decoded (then a whole read comes in eighths at least);
        False: chunks of ``chunk_events``, each decoded on the reader's threads before it is counted.

    Yields
    ------
    Events
        The chunks, in time order.
    """
    if isinstance(source, Events):
        i, j = (int(v) for v in np.searchsorted(source.t, [a, z], side="left"))
        for k in range(i, j, chunk_events):
            yield source[k:min(j, k + chunk_events)]
        return
    info = source.info()
    first, last = info.get("t_start_us"), info.get("t_end_us")
    meeting = getattr(source, "iter_events_meeting", None) if starts is not None and ends is not None else None
    if first is not None and last is not None and int(last) - int(first) <= 2 * (z - a):
        n = info.get("events")
        if overlap and isinstance(n, int) and n > 0:  # eight chunks at least: each counted while the next decodes
            chunk_events = min(chunk_events, max(OVERLAP_CHUNK_EVENTS, -(-n // 8)))
        if meeting is not None:
            yield from _in_time_order(meeting(starts, ends, chunk_events=chunk_events), source)
        else:
            yield from _in_time_order(source.iter_events(chunk_events=chunk_events), source)
    else:
        yield from _in_time_order(source.iter_events(chunk_events=chunk_events, t_start_us=a, t_end_us=z), source)


def accumulate(source: Events | Any, windows: Windows, region: tuple[int, int, int, int] | None = None,
               chunk_events: int = 4_000_000, progress: Callable[[int], Any] | None = None,
               out: np.ndarray | None = None, times: bool = False) -> WindowCounts:
    """ON and OFF counts per window and pixel of ``region``.

    Parameters
    ----------
    source : Events or Recording
        Events (sorted by time, or sorted here) or an open recording, which is
        read in chunks of ``chunk_events`` over the span of the windows only.
    windows : Windows
        The windows to count, in any order (the counts keep their order); time stamps in µs.
    region : tuple of int, optional
        ``(x0, x1, y0, y1)``:
        Sensor pixels to count (half-open); default the whole sensor. Counting
        only the pixels a response needs keeps the output small, which is
        most of the cost (fresh memory is slow to touch).
    chunk_events : int
        Most events read from a recording at once (the memory of one chunk; ignored for :class:`Events`).
    progress : callable, optional
        Called with the number of events of each chunk counted.
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
        ``on`` and ``off`` of shape (windows, y1 - y0, x1 - x0), int32 (views of ``out`` when given); a window
        holding more than 2**31 - 1 events raises rather than wrap. With ``times``, ``on_first_us`` and
        ``on_last_us`` (int32, -1 where a window holds no ON event) and ``stamp_period_us``.

    Raises
    ------
    EvtkError
        A region off the sensor, counts larger than the memory budget
        (:func:`evtk.limits.require_memory`, checked before they are allocated), an ``out`` of the wrong
        shape, dtype or layout, a window holding more than 2**31 - 1 events, or (with ``times``) a window of
        2**31 µs or longer.

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
    x0, x1, y0, y1 = _checked_region(source, region)
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
    flat = counts.reshape(-1)
    count = _chunk_counter(len(source) if isinstance(source, Events) else _recording_events(source), flat.size // 2)
    if isinstance(source, Events):
        chunks: Any = [source.sorted()]
    elif count is not _accumulate_chunk_numpy:
        # the compiled and numba's counters hold no GIL: each counts one chunk while another thread decodes the next
        chunks = _prefetched(span_chunks(source, span[0], span[1], chunk_events, starts, ends))
    else:
        # numpy's counter makes many small calls, each taking the GIL back from the decoding threads: decoding a
        # chunk on the reader's threads, then counting it, is quicker
        chunks = span_chunks(source, span[0], span[1], chunk_events, starts, ends, overlap=False)
    used = 0
    total = np.zeros(n_w, np.int64)
    no_times = np.empty(0, np.int32)  # the numba loop keeps no times when given empty arrays
    first_flat = first.reshape(-1) if first is not None else no_times
    last_flat = last.reshape(-1) if last is not None else no_times
    period = None
    whole = (x0, x1, y0, y1) == (0, sensor[0], 0, sensor[1])
    for ev in chunks:
        if times and period is None:
            period = ev.stamp_period_us()
        used += count(ev.t, ev.x, ev.y, ev.p, starts, ends, x0, x1, y0, y1, whole, flat, total, started,
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


#: Most memory one batch of windows may take (its counts and the float stages after them), in bytes.
BATCH_BYTES = 256 << 20

#: Peak bytes a window-pixel costs in a batch: ON and OFF counts (int32), the counts of one chunk (int64 each) and
#: the float64 stages after them (net counts, linearised values, their copies).
BYTES_PER_WINDOW_PIXEL = 64

def batch_size(region: tuple[int, int, int, int], n_windows: int) -> int:
    """How many windows of ``region`` (x0, x1, y0, y1) one batch holds: :data:`BATCH_BYTES` or a quarter of the
    memory budget, whichever is less, and at least one (checked against the budget).

    Parameters
    ----------
    region : tuple of int
        (x0, x1, y0, y1), half-open sensor pixels.
    n_windows : int
        Windows to count in all.

    Returns
    -------
    int
        Windows per batch, between 1 and ``n_windows`` (1 when there are none).

    Raises
    ------
    EvtkError
        When even one window does not fit the memory budget.
    """
    x0, x1, y0, y1 = (int(v) for v in region)
    per_window = max(1, (x1 - x0) * (y1 - y0) * BYTES_PER_WINDOW_PIXEL)
    require_memory(per_window, f"one window over {x1 - x0}x{y1 - y0} pixels")
    n = max(1, min(BATCH_BYTES, memory_limit_bytes() // 4) // per_window)
    return int(max(1, min(n, int(n_windows))))


def _recording_events(source) -> int | None:
    """Events an open recording holds, when its header says (None otherwise)."""
    info = getattr(source, "info", None)
    n = info().get("events") if callable(info) else None
    return n if isinstance(n, int) else None


def _checked_region(source, region) -> tuple[int, int, int, int]:
    """``region`` as four ints, or an error when it is not a non-empty part of the source's sensor."""
    sensor = tuple(source.sensor_size)
    x0, x1, y0, y1 = (int(v) for v in region)
    if not (0 <= x0 < x1 <= sensor[0] and 0 <= y0 < y1 <= sensor[1]):
        raise EvtkError(f"region {tuple(region)} is not a non-empty part of the {sensor[0]}x{sensor[1]} sensor")
    return x0, x1, y0, y1


def _batch_events(source, bounds, chunk_events: int) -> Iterator[tuple[int, Events]]:
    """(batch, chunk) pairs: each batch's events, in time order, through the time-window API of a recording
    (or slices of sorted in-memory events); ``bounds`` holds each batch's (first start, last end) in us."""
    if isinstance(source, Events):
        ev = source.sorted()
        for b, (a, z) in enumerate(bounds):
            i, j = np.searchsorted(ev.t, [a, z], side="left")
            for k in range(int(i), int(j), chunk_events):
                yield b, ev[k:min(int(j), k + chunk_events)]
        return
    for b, (a, z) in enumerate(bounds):
        for chunk in _in_time_order(source.iter_events(chunk_events=chunk_events, t_start_us=int(a), t_end_us=int(z)),
                                    source):
            yield b, chunk


def accumulate_batches(source: Events | Any, windows: Windows, region: tuple[int, int, int, int],
                       batch_windows: int | None = None,
                       chunk_events: int = 4_000_000,
                       progress: Callable[[int], Any] | None = None,
                       reuse: bool = False) -> Iterator[tuple[int, WindowCounts]]:
    """ON and OFF counts of ``windows`` over ``region``, a batch of windows at a time, in the windows' order.

    Parameters
    ----------
    source : Events or Recording
        Events (sorted here if they are not) or an open recording.
    windows : Windows
        The windows, in any order (a batch spans consecutive windows; windows in time order read each event
        once).
    region : tuple of int
        (x0, x1, y0, y1), half-open sensor pixels to count.
    batch_windows : int, optional
        Windows per batch; default :func:`batch_size`.
    chunk_events : int
        Most events read at once.
    progress : callable, optional
        Called with the number of events of each chunk read.
    reuse : bool
        Count every batch into one buffer: each batch's counts are valid only until the next batch is asked
        for (no fresh memory per batch).

    Yields
    ------
    tuple of (int, WindowCounts)
        The index of the batch's first window, and its counts (int32, as :func:`evtk.reconstruct.accumulate`
        gives them, without event times).

    Raises
    ------
    EvtkError
        A region off the sensor, a batch larger than the memory budget, or a window holding more than
        2**31 - 1 events.
    """
    region = _checked_region(source, region)
    x0, x1, y0, y1 = region
    n_w = len(windows)
    if n_w == 0:
        return
    nb = batch_size(region, n_w) if batch_windows is None else max(1, int(batch_windows))
    require_memory(min(nb, n_w) * (x1 - x0) * (y1 - y0) * BYTES_PER_WINDOW_PIXEL,
                   f"counting {min(nb, n_w):,} windows at a time over {x1 - x0}x{y1 - y0} pixels")
    for i, win, counts, used in _counted_batches(source, windows, region, nb, chunk_events, progress, reuse):
        yield i, WindowCounts(counts[1], counts[0], win, region, used)


def _counted_batches(source, windows: Windows, region, nb: int, chunk_events: int, progress, reuse: bool):
    """(first window, its batch's Windows, int32 counts (2, windows, height, width), events used) per batch of
    ``nb`` windows: one buffer for every batch when ``reuse`` (each batch's counts valid until the next one)."""
    x0, x1, y0, y1 = region
    n_w = len(windows)
    frame = (x1 - x0) * (y1 - y0)
    chunk_events = max(1, int(chunk_events))
    firsts = list(range(0, n_w, nb))
    bounds = [(int(windows.t_start_us[i:i + nb].min()), int(windows.t_end_us[i:i + nb].max())) for i in firsts]
    chunks = _prefetched(_batch_events(source, bounds, chunk_events))
    pending = next(chunks, None)
    no_times = np.empty(0, np.int32)
    buffer = np.empty(2 * min(nb, n_w) * frame, np.int32) if reuse else None
    count = _chunk_counter(len(source) if isinstance(source, Events) else _recording_events(source), n_w * frame)
    sensor = tuple(source.sensor_size)
    whole = (x0, x1, y0, y1) == (0, sensor[0], 0, sensor[1])
    for b, i in enumerate(firsts):
        win = windows[i:i + nb]
        m = len(win)
        flat = buffer[:2 * m * frame] if buffer is not None else np.empty(2 * m * frame, np.int32)
        started = np.zeros(m, np.bool_)
        totals = np.zeros(m, np.int64)
        used = 0
        while pending is not None and pending[0] == b:
            ev = pending[1]
            used += count(ev.t, ev.x, ev.y, ev.p, win.t_start_us, win.t_end_us, x0, x1, y0, y1, whole, flat,
                                      totals, started, no_times, no_times)
            if totals.max(initial=0) > np.iinfo(np.int32).max:
                raise EvtkError(f"window {i + int(np.argmax(totals))} holds more than 2**31 - 1 events: its int32 "
                                "counts could overflow")
            if progress is not None:
                progress(len(ev))
            pending = next(chunks, None)
        counts = flat.reshape(2, m, y1 - y0, x1 - x0)
        counts[:, ~started] = 0  # windows no event reached
        yield i, win, counts, int(used)
