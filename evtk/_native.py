"""evtk's optional compiled kernels (``evtk._ckernels``, built at install where a C compiler is present), behind
wrappers that check their arguments and say when the Python route must be taken instead: the counting of fixed
windows (:func:`count_windows`) and the sums of their net counts (:func:`net_sums`), the counting of a schedule's
windows with their ON-event times (:func:`accumulate_chunk`) and the timing linearisation's solve
(:func:`timing_solve`), the AEDAT4 reader's batches
of LZ4 event packets (:func:`decode_lz4_batch`), and Prophesee EVT 3.0 words (:func:`evt3_run`), EVT 2.0 words
(:func:`evt2_run`) and DAT events (:func:`dat_run`), with their counting passes (:func:`prophesee_scan`), and Event
Stream DVS and ATIS bytes (:func:`es_run`); the
reader's whole range of LZ4 batches (and of Zstandard ones, where the system has libzstd), its reads from the file
included, goes through :func:`decode_lz4_range`.

The kernels release the GIL, so parts of one piece of work run on several cores at once; numpy's scattered adds
(``np.add.at``), which the numpy route counts with, keep it, and so does the Python loop over a batch's
packets (EVT 3.0's numpy decoder takes it back after each of its fifty-odd calls a slice). ``EVTK_NATIVE=0``
(read at each call) turns them off, to compare the two routes; the results are the same to the last bit.
"""

from __future__ import annotations

import sys
from typing import Any

import numpy as np

from ._threads import switched_off

_kernel_count_windows: Any
_kernel_decode_lz4_batch: Any
_kernel_evt3_run: Any
_kernel_evt3_scan: Any
_kernel_evt2_run: Any
_kernel_dat_run: Any
_kernel_evt2_scan: Any
_kernel_dat_scan: Any
_kernel_es_run: Any
try:
    from ._ckernels import count_windows as _kernel_count_windows
    from ._ckernels import decode_lz4_batch as _kernel_decode_lz4_batch
except ImportError:  # built without a compiler: the numpy route
    _kernel_count_windows = _kernel_decode_lz4_batch = None
try:  # apart: an install built before the Prophesee kernels has the two above
    from ._ckernels import dat_run as _kernel_dat_run
    from ._ckernels import dat_scan as _kernel_dat_scan
    from ._ckernels import evt2_run as _kernel_evt2_run
    from ._ckernels import evt2_scan as _kernel_evt2_scan
    from ._ckernels import evt3_run as _kernel_evt3_run
    from ._ckernels import evt3_scan as _kernel_evt3_scan
except ImportError:
    _kernel_dat_run = _kernel_dat_scan = _kernel_evt2_run = _kernel_evt2_scan = None
    _kernel_evt3_run = _kernel_evt3_scan = None
try:  # apart: an install built before the Event Stream kernel has the ones above
    from ._ckernels import es_run as _kernel_es_run
except ImportError:
    _kernel_es_run = None
_kernel_net_sums: Any
try:  # apart: an install built before the net counts' sums has the ones above
    from ._ckernels import net_sums as _kernel_net_sums
except ImportError:
    _kernel_net_sums = None
_kernel_timing_solve: Any
_kernel_accumulate_chunk: Any
try:  # apart: an install built before the timing solve and the timed counting has the ones above
    from ._ckernels import accumulate_chunk as _kernel_accumulate_chunk
    from ._ckernels import timing_solve as _kernel_timing_solve
except ImportError:
    _kernel_timing_solve = _kernel_accumulate_chunk = None
_kernel_decode_lz4_range: Any
try:  # apart: an install built before the whole range of batches in one call has the ones above
    from ._ckernels import decode_lz4_range as _kernel_decode_lz4_range
except ImportError:
    _kernel_decode_lz4_range = None
try:  # a build whose count_windows clears the windows it is given says so
    from ._ckernels import COUNT_CLEARS as _COUNT_CLEARS
except ImportError:
    _COUNT_CLEARS = 0
try:  # a build whose range takes Zstandard packets too says so
    from ._ckernels import RANGE_CODECS as _RANGE_CODECS
except ImportError:
    _RANGE_CODECS = 1

#: Whether the install's kernels include :func:`timing_solve` and :func:`accumulate_chunk` (a build before them
#: does not).
TIMED_KERNELS = _kernel_timing_solve is not None

#: Whether :func:`decode_lz4_range` takes Zstandard packets (a build before it took LZ4 only).
RANGE_ZSTD = _RANGE_CODECS >= 2

#: Whether the install built the compiled kernels (a C compiler was present). They read the files' little-endian
#: numbers as the machine's own: on a big-endian machine they are left unused.
BUILT = _kernel_count_windows is not None and sys.byteorder == "little"

#: Every uint16 coordinate: the length of :func:`count_windows`' tables.
TABLE_SIZE = 1 << 16

_NO_PICKS = np.zeros(0, np.int64)  # what count_windows passes for the picks of a slice (the kernel reads none)


def enabled() -> bool:
    """Whether the compiled kernels are present and not turned off by ``EVTK_NATIVE=0``.

    Returns
    -------
    bool
        True where :func:`count_windows` counts.
    """
    return BUILT and not switched_off("EVTK_NATIVE")


def padded_table(values: np.ndarray, fill: int) -> np.ndarray:
    """A coordinate's look-up table over every uint16 coordinate: ``values`` (one per sensor column or row) as
    int64, then ``fill`` (where a coordinate off the sensor goes).

    Parameters
    ----------
    values : ndarray
        The table's first entries (integers, at most 65536 of them).
    fill : int
        The rest.

    Returns
    -------
    ndarray
        int64, 65536 entries.
    """
    table = np.full(TABLE_SIZE, fill, np.int64)
    table[:len(values)] = values
    return table


def count_windows(x: np.ndarray, y: np.ndarray, p: np.ndarray, where: slice | np.ndarray, at: np.ndarray,
                  ky: np.ndarray, kx: np.ndarray, on_step: int, limit: int, per_window: int, dump: int, net: bool,
                  out: np.ndarray, clear: tuple[int, int] = (0, 0)) -> bool:
    """Count picked events into their windows' bins with the compiled kernel, the GIL released.

    Window ``w`` (``0 <= w < len(at) - 1``) holds the picks ``at[w]:at[w + 1]`` (of ``where``: a slice of the
    events, or their indices). An event's bin within its window is ``k = ky[y] + kx[x]`` (plus ``on_step`` when
    it is ON); it is counted in bin ``w * per_window + k`` of ``out`` when ``0 <= k < limit``, else in bin
    ``dump``. Each event adds 1, or with ``net`` its sign (+1 ON, -1 OFF), wrapping in the bins' type.

    Parameters
    ----------
    x, y : ndarray
        The events' coordinates (uint16).
    p : ndarray
        Their polarities (uint8, 0 OFF).
    where : slice or ndarray
        The picked events: a slice (step 1) or int64 indices into ``x``, ``y``, ``p``.
    at : ndarray
        Each window's first pick, then the end of the last window's (int64).
    ky, kx : ndarray
        Each coordinate's part of the bin (int64, 65536 entries: :func:`padded_table`).
    on_step : int
        Added to an ON event's bin.
    limit : int
        Bins within a window are ``0 .. limit - 1`` (at most ``per_window``).
    per_window : int
        Bins between one window's and the next's.
    dump : int
        The bin of events outside every window's ``limit``.
    net : bool
        Add signs instead of ones.
    out : ndarray
        The bins: int16 or int32, contiguous, writable, holding every window's bins and ``dump``.
    clear : tuple of int
        Windows ``clear[0] <= w < clear[1]`` have their ``per_window`` bins set to 0 just before their events are
        counted, while they stay in cache (clearing a batch of windows ahead evicts its first windows' bins before
        they are counted).

    Returns
    -------
    bool
        True when counted; False (nothing counted) when the kernel is off or missing, or an argument is not in
        the form it takes: then the caller counts with numpy.
    """
    if not enabled() or out.dtype not in (np.int16, np.int32) or not out.flags.c_contiguous or not out.flags.writeable:
        return False
    cols = (x, y, p)
    if (any(not c.flags.c_contiguous for c in cols) or (x.dtype, y.dtype, p.dtype) != (np.uint16, np.uint16, np.uint8)
            or not len(x) == len(y) == len(p)):
        return False
    tables = (ky, kx, at)
    if any(t.dtype != np.int64 or not t.flags.c_contiguous for t in tables) or len(ky) != TABLE_SIZE or len(kx) != TABLE_SIZE:
        return False
    n_w = len(at) - 1
    if n_w < 1 or not 0 <= limit <= per_window or not 0 <= dump < out.size or n_w * per_window > out.size:
        return False
    if isinstance(where, slice):
        if where.step not in (None, 1):
            return False
        first, _, _ = where.indices(len(x))
        picks: Any = _NO_PICKS
    else:
        if where.dtype != np.int64 or not where.flags.c_contiguous:
            return False
        first, picks = 0, where
    lo, hi = max(0, int(clear[0])), min(n_w, int(clear[1]))
    if hi > lo and not _COUNT_CLEARS:  # (a build before the kernel cleared them)
        out[lo * per_window:hi * per_window] = 0
    _kernel_count_windows(x, y, p, picks, not isinstance(where, slice), first, at, ky, kx, int(on_step), int(limit),
                          int(per_window), int(dump), bool(net), out, out.itemsize,
                          *((lo, hi) if hi > lo and _COUNT_CLEARS else ()))
    return True


def net_sums(net: np.ndarray, size: tuple[int, int] | None = None,
             out: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray, int,
                                                                        np.ndarray | None] | None:
    """Each pixel's sum and sum of squares over ``k`` windows' net counts, each window's sums over the blocks of a
    ``size`` grid, and the counts' largest magnitude, in one pass of the compiled kernel with the GIL released
    (runs of rows on evtk's counting threads: :func:`evtk._parallel.parts`).

    What :meth:`evtk.metrics.SinadAccumulator.add_sums` takes for eq. 8 from whole-number repeats, and what
    :func:`evtk.reconstruct.downsample` averages a window into (the block sums over the block's pixel count).
    Exact where the caller's bounds hold: ``k * big**2 < 2**63`` for the squares and ``(h * w // (rows * cols)) *
    big < 2**63`` for the blocks (beyond them the int64 sums wrap).

    Parameters
    ----------
    net : ndarray
        int16 or int32 counts, shape ``(k, h, w)``, C-contiguous.
    size : tuple of int, optional
        ``(rows, cols)`` of the blocks' grid: block sums only where it divides ``(h, w)``.
    out : tuple of ndarray, optional
        Two distinct int64 arrays of shape ``(h, w)``, C-contiguous and writable, to hold ``s1`` and ``s2``
        (a caller summing batch after batch reuses them: fresh arrays of a whole frame's pixels are new pages
        each time, one page fault each 4 KiB); others are not used, and new arrays are made.

    Returns
    -------
    tuple or None
        ``(s1, s2, big, blocks)``: the int64 sums over the windows, shape ``(h, w)``, the largest magnitude (a
        Python int) and the int64 block sums, shape ``(k, rows, cols)`` (None without a dividing ``size``). None,
        nothing done, when the kernel is off or missing or ``net`` is not in the form it takes: the caller then
        sums with numpy.
    """
    if not enabled() or _kernel_net_sums is None:
        return None
    if net.ndim != 3 or net.dtype not in (np.int16, np.int32) or not net.flags.c_contiguous or 0 in net.shape:
        return None
    k, h, w = (int(v) for v in net.shape)
    if h > 1 << 20 or w > 1 << 20:
        return None
    fy = fx = 0
    if size is not None and int(size[0]) > 0 and int(size[1]) > 0 and h % int(size[0]) == 0 and w % int(size[1]) == 0:
        fy, fx = h // int(size[0]), w // int(size[1])
    if out is not None and len(out) == 2 and all(
            isinstance(a, np.ndarray) and a.dtype == np.int64 and a.shape == (h, w) and a.flags.c_contiguous
            and a.flags.writeable for a in out) and not np.may_share_memory(out[0], out[1]):
        s1, s2 = out
    else:
        s1 = np.empty((h, w), np.int64)
        s2 = np.empty((h, w), np.int64)
    blocks = np.zeros((k, h // fy, w // fx) if fy else (0,), np.int64)
    from ._parallel import parts, run  # (here: a read needs none of it)

    unit = fy or 1  # runs of whole block rows: each run adds to its own blocks
    units = h // unit
    n = min(parts(net.size, gil_free=True), units)
    rows = [unit * (units * r // n) for r in range(n + 1)]
    bigs = run(lambda a, z: _kernel_net_sums(net, net.itemsize, k, h, w, a, z, fy, fx, s1, s2, blocks),
               list(zip(rows, rows[1:])))
    return s1, s2, int(max(bigs)), blocks if fy else None


def accumulate_chunk(t: np.ndarray, x: np.ndarray, y: np.ndarray, p: np.ndarray, starts: np.ndarray,
                     ends: np.ndarray, region: tuple[int, int, int, int], counts: np.ndarray, total: np.ndarray,
                     started: np.ndarray, first: np.ndarray, last: np.ndarray) -> int | None:
    """Add a chunk of time-sorted events to every window it meets with the compiled kernel, the GIL released:
    :func:`evtk.reconstruct.accumulate._accumulate_chunk`'s work (the same counts, totals and ON-event times).

    Parameters
    ----------
    t, x, y, p : ndarray
        The chunk's columns: int64 times (sorted), uint16 coordinates, uint8 polarities (not 0: ON).
    starts, ends : ndarray
        int64, the windows (half-open, us).
    region : tuple of int
        ``(x0, x1, y0, y1)``: the sensor pixels counted.
    counts : ndarray
        int32, flat ``(2, windows, y1 - y0, x1 - x0)``: OFF then ON, each window's frames zeroed when it is
        first met (``started``).
    total : ndarray
        int64, events per window so far.
    started : ndarray
        bool, one per window.
    first, last : ndarray
        int32, flat ``(windows, y1 - y0, x1 - x0)``: the first and last ON event's time from its window's start
        (-1: none); or both empty, for no times.

    Returns
    -------
    int or None
        The events counted inside the region; None, nothing done, when the kernel is off or missing or an array
        is not in the form it takes (the caller then counts with numba or numpy).
    """
    if not enabled() or _kernel_accumulate_chunk is None:
        return None
    n, n_w = t.shape[0], starts.shape[0]
    x0, x1, y0, y1 = (int(v) for v in region)
    frame = (x1 - x0) * (y1 - y0)
    forms = ((t, _I64, n), (x, np.uint16, n), (y, np.uint16, n), (p, np.uint8, n), (starts, _I64, n_w),
             (ends, _I64, n_w), (counts, np.int32, 2 * n_w * frame), (total, _I64, n_w), (started, np.bool_, n_w),
             (first, np.int32, first.size), (last, np.int32, first.size))
    if any(a.dtype != d or a.ndim != 1 or a.shape[0] != size or not a.flags.c_contiguous for a, d, size in forms):
        return None
    if first.size not in (0, n_w * frame) or not (0 <= x0 < x1 <= TABLE_SIZE and 0 <= y0 < y1 <= TABLE_SIZE):
        return None
    if not all(a.flags.writeable for a in (counts, total, started, first, last)):
        return None
    if n_w == 0 or n == 0:
        return 0
    from ._parallel import cuts, parts, run  # (here: a read needs none of it)

    live = np.flatnonzero((ends > t[0]) & (starts <= t[n - 1]))
    if live.size == 0:
        return 0
    weights = np.searchsorted(t, ends[live]) - np.searchsorted(t, starts[live]) + frame // 8
    # runs of windows of about equal work (their events, and the zeroing of their frames), each on its own thread:
    # no two write the same window; the windows between live ones that meet no event are skipped by the kernel
    bounds = [int(live[c]) for c in cuts(weights, parts(int(weights.sum()), gil_free=True))[:-1]]
    bounds.append(int(live[-1]) + 1)
    used = run(lambda a, z: _kernel_accumulate_chunk(t, x, y, p, starts, ends, x0, x1, y0, y1, counts, total,
                                                     started, first, last, a, z), list(zip(bounds, bounds[1:])))
    return int(sum(used))


def timing_solve(n_on: np.ndarray, first: np.ndarray, last: np.ndarray, theta: np.ndarray, band_lo: np.ndarray,
                 band_hi: np.ndarray, out: np.ndarray, rows: tuple[int, int], theta_nominal: float, offset_us: float,
                 log_blank: float, tau_min_us: float, tau_electrons: float, refr_us: float) -> bool:
    """The timing linearisation's steps of the windows ``rows`` (``(a, z)``: rows ``a .. z - 1``) with the compiled
    kernel, the GIL released: :func:`evtk.reconstruct.timing._timing_solve_jit`'s scalar method, the same
    operations in the same order.

    Parameters
    ----------
    n_on, first, last : ndarray
        int64, shape ``(windows, pixels)``, C-contiguous: each pair's ON count and first and last ON-event times.
    theta : ndarray
        float64, one per pixel: the thresholds.
    band_lo, band_hi : ndarray
        float64, of one length (at least 1): the count bands' ends (``_count_bands``).
    out : ndarray
        float64 like ``n_on``, whose rows ``rows`` are set (a step, or NaN).
    rows : tuple of int
        The windows to solve.
    theta_nominal, offset_us, log_blank, tau_min_us, tau_electrons, refr_us : float
        As :func:`evtk.reconstruct.timing._timing_solve`.

    Returns
    -------
    bool
        True when the kernel solved them; False, nothing done, when it is off or missing or an array is not in
        the form it takes (the caller then solves with numba or numpy).
    """
    if not enabled() or _kernel_timing_solve is None:
        return False
    pairs = (n_on, first, last, out)
    if n_on.ndim != 2 or any(a.shape != n_on.shape or not a.flags.c_contiguous for a in pairs):
        return False
    if out.dtype != np.float64 or any(a.dtype != np.int64 for a in pairs[:3]) or not out.flags.writeable:
        return False
    bands = (theta, band_lo, band_hi)
    if any(a.dtype != np.float64 or a.ndim != 1 or not a.flags.c_contiguous for a in bands):
        return False
    if theta.size != n_on.shape[1] or band_lo.size == 0 or band_lo.size != band_hi.size:
        return False
    a, z = (int(v) for v in rows)
    if n_on.size == 0:  # no windows or no pixels: nothing to solve
        return True
    _kernel_timing_solve(n_on, first, last, theta, band_lo, band_hi, out, n_on.shape[1], a, z, float(theta_nominal),
                         float(offset_us), float(log_blank), float(tau_min_us), float(tau_electrons), float(refr_us))
    return True


_I64 = np.dtype(np.int64)


def decode_lz4_batch(raw: np.ndarray, heads: np.ndarray, sids: np.ndarray, sizes: np.ndarray, counts: np.ndarray,
                     verify: bool, lz4f: tuple[int, int, int, int], stage: np.ndarray, floor_bytes: int, ratio: int,
                     most_bytes: int, columns: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
                     sensor_size: tuple[int, int]) -> bool:
    """Decode one batch of the AEDAT4 reader's LZ4 event packets into the columns with the compiled kernel, the
    GIL released: the packet-by-packet work of :meth:`evtk.io.aedat4.reader.Recording._batcher`'s batches.

    Packet ``j``'s 8-byte header (stream id, body size: int32) lies at ``raw[heads[j]]`` and must match ``sids[j]``
    and ``sizes[j]``; its body is one LZ4 frame, decompressed into ``stage`` (at most ``min(most_bytes,
    floor_bytes + ratio * size)`` bytes: :func:`evtk.io._compression.output_limit`), checked as
    :func:`evtk.io._compression.lz4_into_at` checks it, and its FlatBuffer's event vector (identifier ``EVTS``,
    the checks of :func:`evtk.io._fbpy._root_vector_at`) must hold ``counts[j]`` events, whose coordinates lie on
    the sensor. The events go into the columns one packet after another; a polarity byte other than 0 is ON (1).

    Parameters
    ----------
    raw : ndarray
        The batch's bytes as read from the file (uint8, contiguous).
    heads : ndarray
        Each packet's header position in ``raw`` (int64).
    sids, sizes, counts : ndarray
        Each packet's stream id, body size and event count from the data table (int64).
    verify : bool
        Check the checksums the frames carry; False: a frame that carries any goes to the Python route.
    lz4f : tuple of int
        The addresses of ``LZ4F_decompress``, ``LZ4F_isError`` and ``LZ4F_resetDecompressionContext`` and of this
        thread's decompression context (:func:`evtk.io._compression.lz4f_addresses`).
    stage : ndarray
        This thread's room for one decompressed body (uint8, contiguous, writable).
    floor_bytes, ratio, most_bytes : int
        :func:`evtk.io._compression.output_limit`'s terms.
    columns : tuple of ndarray
        ``t`` (int64), ``x``, ``y`` (uint16) and ``p`` (uint8) for the batch's events: contiguous, writable, as
        long as ``counts`` adds up to.
    sensor_size : tuple of int
        (width, height).

    Returns
    -------
    bool
        True when every packet decoded. False when the kernel is off or missing, an argument is not in the form it
        takes, or anything in the batch is not as expected (a fault, a frame larger than ``stage``, checksums to
        leave unread): the caller then decodes the batch in Python, which names any fault; the columns may hold
        part of the batch.
    """
    if not enabled() or _kernel_decode_lz4_batch is None:
        return False
    t, x, y, p = columns
    arrays = (raw, heads, sids, sizes, counts, stage, t, x, y, p)
    if (any(not a.flags.c_contiguous for a in arrays) or raw.dtype != np.uint8 or stage.dtype != np.uint8
            or any(a.dtype != _I64 for a in (heads, sids, sizes, counts)) or t.dtype != _I64
            or (x.dtype, y.dtype, p.dtype) != (np.uint16, np.uint16, np.uint8)
            or not all(a.flags.writeable for a in (stage, t, x, y, p))):
        return False
    return bool(_kernel_decode_lz4_batch(raw, heads, sids, sizes, counts, verify, *lz4f, stage, int(floor_bytes),
                                         int(ratio), int(most_bytes), t, x, y, p, int(sensor_size[0]),
                                         int(sensor_size[1])))


def decode_lz4_range(fd: int, offs: np.ndarray, sids: np.ndarray, sizes: np.ndarray, counts: np.ndarray,
                     starts: np.ndarray, k0: int, k1: int, batch_events: int, slack: int, raw: np.ndarray,
                     verify: bool, lz4f: tuple[int, int, int, int], stage: np.ndarray, floor_bytes: int, ratio: int,
                     most_bytes: int, columns: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
                     sensor_size: tuple[int, int],
                     zstd: tuple[int, int, int, int, int] | None = None) -> tuple[int, int, int, int, bool] | None:
    """Read and decode the AEDAT4 reader's LZ4 (or, given ``zstd``, Zstandard) event packets ``k0 .. k1 - 1`` batch
    after batch with the compiled kernel, the GIL released from the first batch to the last: the loop of
    :meth:`evtk.io.aedat4.reader.Recording._batcher`'s batches, each batch's bytes read with ``pread`` and decoded
    as :func:`decode_lz4_batch` decodes them.

    A Zstandard packet must be one frame filling its body, of its stated content size if it states one, within the
    same output limit: :func:`evtk.io._compression.decompress`'s rule; the library checks the frame's checksum,
    if it has one. Anything else stops the call at its batch, for the Python loop (which decompresses with
    zstandard), as a faulty LZ4 packet does.

    Each batch is cut as the reader cuts it: from row ``k`` up to the row before the first whose start passes
    ``starts[k] + batch_events`` (at least one row, at most ``k1``). A batch whose packets lie far apart in the
    file (more than twice their bytes plus ``slack``), whose read comes back short, or that the decoding declines
    stops the call at its first row, for the Python loop, which names any fault.

    Parameters
    ----------
    fd : int
        The file's descriptor, open for reading.
    offs : ndarray
        Each row's packet body offset in the file, after its 8-byte header (int64).
    sids, sizes, counts : ndarray
        Each row's stream id, body size and event count from the data table (int64).
    starts : ndarray
        Each row's first event in the columns, then the end of the last row's (int64, one more than the rows,
        non-decreasing).
    k0, k1 : int
        The rows to decode.
    batch_events : int
        Events a batch aims at.
    slack : int
        Bytes of other packets a batch's read may take in beside its own.
    raw : ndarray
        Room for a batch's bytes (uint8, contiguous, writable).
    verify : bool
        Check the checksums the frames carry, as :func:`decode_lz4_batch`.
    lz4f : tuple of int
        As :func:`decode_lz4_batch` (not used with ``zstd``).
    stage : ndarray
        This thread's room for a decompressed body (uint8, contiguous, writable): at least 16 bytes an event of
        the batch plus three ``slack``.
    floor_bytes, ratio, most_bytes : int
        :func:`evtk.io._compression.output_limit`'s terms.
    columns : tuple of ndarray
        ``t`` (int64), ``x``, ``y`` (uint16) and ``p`` (uint8), written at ``starts``: contiguous and writable.
    sensor_size : tuple of int
        (width, height).
    zstd : tuple of int, optional
        The packets are Zstandard frames: :func:`evtk.io._compression.zstd_addresses` (the system library's
        functions and this thread's context).

    Returns
    -------
    tuple or None
        ``(k, need_raw, need_stage, batches, back)``: ``k`` is ``k1`` when every batch decoded, else the first row
        of the batch left; ``need_raw`` or ``need_stage``, when not 0, the bytes ``raw`` or ``stage`` needs for
        that batch (grow it and call again); both 0: the Python loop takes that batch. ``batches``: how many were
        decoded. ``back``: whether the stamps of a packet among them go back in time within the packet (each
        stamp compared with the one before it as the events are split; False says that every decoded packet's
        stamps are in order, not that one packet's follow the last's). None when the kernel is off or missing
        (or, for Zstandard packets, built before it took them), the platform has no ``pread``, or an argument is
        not in the form it takes (the Python loop then takes every batch).
    """
    if not enabled() or _kernel_decode_lz4_range is None or fd < 0 or (zstd is not None and not RANGE_ZSTD):
        return None
    t, x, y, p = columns
    tables = (offs, sids, sizes, counts, starts)
    if (any(a.dtype != _I64 or not a.flags.c_contiguous for a in tables) or len(starts) != len(offs) + 1
            or any(len(a) != len(offs) for a in (sids, sizes, counts)) or not 0 <= k0 <= k1 <= len(offs)):
        return None
    buffers = (raw, stage, t, x, y, p)
    if (any(not a.flags.c_contiguous or not a.flags.writeable for a in buffers) or raw.dtype != np.uint8
            or stage.dtype != np.uint8 or t.dtype != _I64 or (x.dtype, y.dtype, p.dtype) != (np.uint16, np.uint16,
                                                                                            np.uint8)
            or not len(t) == len(x) == len(y) == len(p)):
        return None
    if zstd is None:
        codec: tuple[int, ...] = ()
    else:  # libzstd's decompress, is_error, frame_bytes in the LZ4 functions' places; the context; content_size
        dec, err, frame_bytes, ctx, content_size = zstd
        lz4f, codec = (dec, err, frame_bytes, ctx), (1, content_size)
    k, need_raw, need_stage, batches, back = _kernel_decode_lz4_range(
        int(fd), offs, sids, sizes, counts, starts, int(k0), int(k1), int(batch_events), int(slack), raw,
        bool(verify), *lz4f, stage, int(floor_bytes), int(ratio), int(most_bytes), t, x, y, p, int(sensor_size[0]),
        int(sensor_size[1]), *codec)
    if batches < 0:  # a platform without pread
        return None
    return int(k), int(need_raw), int(need_stage), int(batches), bool(back)


def _words_as(words: Any, dtype: type[np.unsignedinteger]) -> np.ndarray | None:
    """``words`` as contiguous ``dtype`` in the machine's order (no copy where they are), or None where they are not
    a 1-d array of integers of its size."""
    w = np.asarray(words)
    if w.ndim != 1 or w.dtype.kind not in "ui" or w.dtype.itemsize != np.dtype(dtype).itemsize:
        return None
    return np.ascontiguousarray(w.astype(dtype, copy=False))


#: The most an epoch or a vector base of a decoder's state may be for the kernels (each word adds at most 12 to
#: either; the kernels refuse more, so that nothing they add can overflow).
_STATE_MOST = 1 << 40


def _sensor_ok(width: int, height: int) -> bool:
    """Whether a sensor is one the decoders' kernels take: 0 to 65536 pixels a side (the kernels refuse others)."""
    return 0 <= width <= 1 << 16 and 0 <= height <= 1 << 16


def _state_ok(state: np.ndarray, lowest: tuple[int, ...], above: tuple[int, ...]) -> bool:
    """Whether a decoder's state is the int64 values the kernels update in place (contiguous, writable), each
    ``lowest[k] <= state[k] < above[k]``: the states a decoder's words can leave (the kernels check the same)."""
    return (state.dtype == _I64 and state.shape == (len(lowest),) and state.flags.c_contiguous
            and state.flags.writeable and all(lo <= v < hi for lo, v, hi in zip(lowest, state.tolist(), above)))


def evt3_run(words: Any, state: np.ndarray, width: int, height: int, decode: bool, t: np.ndarray, x: np.ndarray,
             y: np.ndarray, p: np.ndarray, tt: np.ndarray, tk: np.ndarray, tch: np.ndarray,
             status: tuple[int, int, int, int]) -> tuple[int, int, int, int, int, int] | None:
    """Decode or count EVT 3.0 words with the compiled kernel, the GIL released: what
    :func:`evtk.io.prophesee._evt3.run` does with numpy, to the same results (``tests/test_prophesee_numpy.py``
    compares both with a word-by-word loop).

    Parameters
    ----------
    words : array_like
        The words (16-bit, in the machine's order).
    state : ndarray
        The decoder's state before the words (six int64: time high, time low, epoch, y, vector base x,
        polarity), updated in place to the state after the words whose effects stand. Values no EVT 3.0 words
        leave (a time part of 4096 or more, say) go to numpy.
    width, height : int
        The sensor: an event off it stops the decoding. The kernel takes 0 to 65536 pixels a side (others go to
        numpy).
    decode : bool
        Write the events and triggers; else only count them.
    t, x, y, p : ndarray
        The events' columns (int64, uint16, uint16, uint8; one length, the most events written).
    tt, tk, tch : ndarray
        The triggers' time, kind and channel (int64, uint8, uint8; one length).
    status : tuple of int
        The status codes to return for none, a word of no type, an event off the sensor, and full outputs.

    Returns
    -------
    tuple of int or None
        ``(events, triggers, status, index of the word stopped at or -1, min t, max t)``, as the numpy decoder's;
        None when the kernel is off or missing, or an argument is not in the form it takes (then the caller
        decodes with numpy).
    """
    if not enabled() or _kernel_evt3_run is None:
        return None
    w = _words_as(words, np.uint16)
    # time high, time low, epoch (below 2**39: the kernel packs the time's parts into one int64), y, vector base
    # x, polarity
    if w is None or not _state_ok(state, (0, 0, 0, 0, 0, 0), (4096, 4096, 1 << 39, 2048, _STATE_MOST, 2)):
        return None
    if not _columns_ok(t, x, y, p, tt, tk, tch) or not _sensor_ok(width, height):
        return None
    n, m, outcome, bad, lo, hi = _kernel_evt3_run(w, state, int(width), int(height), bool(decode), t, x, y, p, tt, tk,
                                                  tch)
    return n, m, status[outcome], bad, lo, hi


def _columns_ok(t: np.ndarray, x: np.ndarray, y: np.ndarray, p: np.ndarray, tt: np.ndarray, tk: np.ndarray,
                tch: np.ndarray) -> bool:
    """Whether a decoder's events' and triggers' columns are in the form the kernels write: contiguous, writable,
    int64 / uint16 / uint16 / uint8 and int64 / uint8 / uint8, each set of one length."""
    cols = (t, x, y, p, tt, tk, tch)
    return not (any(not c.flags.c_contiguous or not c.flags.writeable for c in cols) or t.dtype != _I64
                or tt.dtype != _I64
                or (x.dtype, y.dtype, p.dtype, tk.dtype, tch.dtype) != (np.uint16, np.uint16, np.uint8, np.uint8,
                                                                        np.uint8)
                or not len(t) == len(x) == len(y) == len(p) or not len(tt) == len(tk) == len(tch))


def evt2_run(words: Any, state: np.ndarray, width: int, height: int, decode: bool, t: np.ndarray, x: np.ndarray,
             y: np.ndarray, p: np.ndarray, tt: np.ndarray, tk: np.ndarray, tch: np.ndarray,
             status: tuple[int, int, int, int]) -> tuple[int, int, int, int, int, int] | None:
    """Decode or count Prophesee EVT 2.0 words with the compiled kernel, the GIL released: what the numpy decoder
    (:func:`evtk.io.prophesee._fallbacks._evt2_numpy_run`) does, to the same results.

    Parameters
    ----------
    words : array_like
        The words (uint32, in the machine's order).
    state : ndarray
        The decoder's state (two int64: the last time high, the epoch), updated in place. Values no EVT 2.0
        words leave (a time high of 2**28 or more, an epoch of 2**40) go to numpy.
    width, height : int
        The sensor: an event off it stops the decoding. The kernel takes 0 to 65536 pixels a side (others go to
        numpy).
    decode : bool
        Write the events and triggers; else only count them.
    t, x, y, p : ndarray
        The events' columns (int64, uint16, uint16, uint8). Where they fill up, the decoding stops at the event
        word that no longer fits (status full; numpy's decoder needs them as long as the words).
    tt, tk, tch : ndarray
        The triggers' time, kind and channel (int64, uint8, uint8), likewise.
    status : tuple of int
        The status codes to return for none, a word of no type, an event off the sensor, and full outputs.

    Returns
    -------
    tuple of int or None
        ``(events, triggers, status, index of the word stopped at or -1, min t, max t)`` (``2**62, -2**62``
        without events); None when the kernel is off or missing, or an argument is not in the form it takes (then
        the caller decodes with numpy).
    """
    if not enabled() or _kernel_evt2_run is None:
        return None
    w = _words_as(words, np.uint32)
    if (w is None or not _state_ok(state, (0, 0), (1 << 28, _STATE_MOST))  # time high, epoch
            or not _columns_ok(t, x, y, p, tt, tk, tch) or not _sensor_ok(width, height)):
        return None
    n, m, outcome, bad, lo, hi = _kernel_evt2_run(w, state, int(width), int(height), bool(decode), t, x, y, p, tt, tk,
                                                  tch)
    return n, m, status[outcome], bad, lo, hi


def dat_run(words: Any, state: np.ndarray, width: int, height: int, decode: bool, t: np.ndarray, x: np.ndarray,
            y: np.ndarray, p: np.ndarray, status: tuple[int, int, int, int]) -> tuple[int, int, int, int, int, int] | None:
    """Decode or count Prophesee DAT events with the compiled kernel, the GIL released: what the numpy decoder
    (:func:`evtk.io.prophesee._fallbacks._dat_numpy_run`) does, to the same results.

    Parameters
    ----------
    words : array_like
        The events as pairs of uint32 (time stamp, data), in the machine's order; a last odd word is left.
    state : ndarray
        The decoder's state (two int64: the last raw time stamp, -1 before the first, and the epoch), updated in
        place. Values no DAT events leave (a stamp of 2**32 or more, an epoch of 2**40) go to numpy.
    width, height : int
        The sensor: an event off it stops the decoding. The kernel takes 0 to 65536 pixels a side (others go to
        numpy).
    decode : bool
        Write the events; else only count them.
    t, x, y, p : ndarray
        The events' columns (int64, uint16, uint16, uint8); where they fill up, as :func:`evt2_run`.
    status : tuple of int
        The status codes to return for none, a word of no type, an event off the sensor, and full outputs.

    Returns
    -------
    tuple of int or None
        ``(events, 0, status, index of the event stopped at or -1, min t, max t)``, as :func:`evt2_run`'s; None when
        the kernel is off or missing, or an argument is not in the form it takes.
    """
    if not enabled() or _kernel_dat_run is None:
        return None
    w = _words_as(words, np.uint32)
    if (w is None or not _state_ok(state, (-1, 0), (1 << 32, _STATE_MOST))  # last stamp, epoch
            or not _columns_ok(t, x, y, p, t[:0], p[:0], p[:0]) or not _sensor_ok(width, height)):
        return None
    n, m, outcome, bad, lo, hi = _kernel_dat_run(w, state, int(width), int(height), bool(decode), t, x, y, p)
    return n, m, status[outcome], bad, lo, hi


def es_run(data: Any, state: np.ndarray, width: int, height: int, decode: bool, atis: bool, t: np.ndarray,
           x: np.ndarray, y: np.ndarray, p: np.ndarray,
           status: tuple[int, int, int, int]) -> tuple[int, int, int, int, int, int] | None:
    """Decode or count Event Stream 2.x DVS or ATIS bytes with the compiled kernel, the GIL released: what
    :func:`evtk.io.prophesee._fallbacks._es_dvs_run` and :func:`~evtk.io.prophesee._fallbacks._es_atis_run` do, to the
    same results.

    Parameters
    ----------
    data : array_like
        The bytes (uint8).
    state : ndarray
        The decoder's state (six int64: the time, the position inside an event, x, y, the flags, the ATIS
        threshold crossings left out), updated in place. Values no bytes leave go to the other decoders.
    width, height : int
        The sensor: an event off it stops the decoding. The kernel takes 0 to 65536 pixels a side.
    decode : bool
        Write the events; else only count them.
    atis : bool
        ATIS bytes (threshold crossings counted and left out); else DVS bytes.
    t, x, y, p : ndarray
        The events' columns (int64, uint16, uint16, uint8; one length), decoding at least ``len(data) // 5 + 1``.
    status : tuple of int
        The status codes to return for none, a word of no type, an event off the sensor, and full outputs.

    Returns
    -------
    tuple of int or None
        ``(events, 0, status, index of the byte stopped at or -1, min t, max t)``, as :func:`evt2_run`'s; None
        when the kernel is off or missing, or an argument is not in the form it takes.
    """
    if not enabled() or _kernel_es_run is None:
        return None
    b = _words_as(data, np.uint8)
    # time, position, x, y, flags, threshold crossings left out
    if (b is None or not _state_ok(state, (0,) * 6, (1 << 62, 5, 1 << 16, 1 << 16, 4, 1 << 62))
            or not _columns_ok(t, x, y, p, t[:0], p[:0], p[:0]) or not _sensor_ok(width, height)
            or (decode and len(t) < len(b) // 5 + 1)):
        return None
    n, m, outcome, bad, lo, hi = _kernel_es_run(b, state, int(width), int(height), bool(decode), bool(atis), t, x,
                                                y, p)
    return n, m, status[outcome], bad, lo, hi


#: Each Prophesee encoding's counting kernel and word type.
_SCANS = {"evt3": (_kernel_evt3_scan, np.uint16), "evt2": (_kernel_evt2_scan, np.uint32),
          "dat": (_kernel_dat_scan, np.uint32)}


def prophesee_scan(encoding: str, words: Any) -> tuple[int, int, int, tuple[int, ...]] | None:
    """Count EVT 3.0 words (``"evt3"``), EVT 2.0 words (``"evt2"``) or DAT events (``"dat"``) and sum up their
    effect on the decoder's state with the compiled kernel, the GIL released: the counting pass of a whole read on
    threads (:func:`evtk.io.prophesee._whole.read_whole`).

    Parameters
    ----------
    encoding : str
        ``"evt3"``, ``"evt2"`` or ``"dat"``.
    words : array_like
        The words (16-bit for EVT 3.0, else 32-bit, in the machine's order; DAT: pairs of them, a last odd word
        left).

    Returns
    -------
    tuple or None
        ``(events, triggers, index of the first word of no type or -1, effect)``: the events counted up to that
        word (off the sensor too) and the words' effect on the state: for EVT 3.0 as
        :func:`evtk.io.prophesee._evt3.advance` takes it, for EVT 2.0 and DAT the first and last time high or time
        stamp (-1 where there is none) and the wraps between them. None when the kernel is off or missing, or the
        words are not in a form it takes.
    """
    kernel, dtype = _SCANS[encoding]
    if not enabled() or kernel is None:
        return None
    w = _words_as(words, dtype)
    if w is None:
        return None
    n_ev, n_tr, stop, effect = kernel(w)
    return n_ev, n_tr, stop, effect
