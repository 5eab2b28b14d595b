"""Windows without a schedule, a batch at a time: memory bounded by a batch, not by windows x sensor.

Windows without a capture schedule (periodic or from trigger edges) stand alone: each one's response depends on
its own counts only. :func:`~evtk.reconstruct.accumulate.accumulate_batches` counts them a batch at a time (each
batch's events through the recording's time-window API, decoded on another thread while the last chunk is
counted); :func:`reconstruct_windows` runs the stages after accumulation on each batch, and
:func:`reconstruct_responses` goes from the counts straight to the responses in one compiled pass (no per-pixel
array of values).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import numba
import numpy as np

from ..errors import EvtkError
from ..limits import require_memory
from .accumulate import _checked_region, _counted_batches, accumulate_batches, batch_size
from .binarize import binarize
from .grid import overlap_matrix
from .summary import ReconstructionSummary
from .windows import WindowCounts, Windows


def reconstruct_windows(source, windows: Windows, region, keep_pixels: bool = True, batch_windows: int | None = None,
                        chunk_events: int = 4_000_000, progress: Callable[[int], Any] | None = None,
                        **options: Any):
    """:func:`evtk.reconstruct.reconstruct` of windows without a schedule, a batch of windows at a time.

    Each window stands alone (no passes to combine, no flat fields), so every stage after accumulation
    (:func:`evtk.reconstruct.reconstruct_counts` without a simulation record) runs on one batch's counts and
    gives each window the response the whole run would.

    Parameters
    ----------
    source : Events or Recording
        The events.
    windows : Windows
        Windows of a recording without a simulation record.
    region : tuple of int
        (x0, x1, y0, y1), half-open sensor pixels.
    keep_pixels : bool
        Keep every window's counts and per-pixel values (``counts.on``/``off`` and ``cells``: windows x region,
        as the whole-run path holds them). False keeps the responses and binary responses only, in memory
        bounded by them and one batch: ``cells`` are then the responses and the counts hold no pixels
        (``on``/``off`` of shape (windows, 0, 0)).
    batch_windows : int, optional
        Windows per batch; default :func:`batch_size`.
    chunk_events : int
        Most events read at once.
    progress : callable, optional
        Called with the number of events of each chunk read.
    **options
        :func:`evtk.reconstruct.reconstruct_counts`'s settings (``size``, ``binarize_method``, ``linear``,
        ``theta``, ``skip_us``, ``length_us``, ...).

    Returns
    -------
    Reconstruction
        Responses, binary responses and the summary, as the whole-run path gives them.

    Raises
    ------
    EvtkError
        A region off the sensor, or more memory than the budget allows.
    """
    from .pipeline import Reconstruction, reconstruct_counts

    n_w = len(windows)
    x0, x1, y0, y1 = _checked_region(source, region)
    h_px, w_px = y1 - y0, x1 - x0
    if keep_pixels:  # int32 ON and OFF counts and float64 values of every window
        require_memory(n_w * h_px * w_px * 16, f"keeping the counts of {n_w:,} windows over {w_px}x{h_px} pixels")
    responses = binary = cells = on = off = None
    summary: Mapping[str, Any] = {}
    used = 0
    for i, counts in accumulate_batches(source, windows, region, batch_windows, chunk_events, progress):
        part = reconstruct_counts(counts, None, **options)
        j = i + len(counts.windows)
        if keep_pixels and i == 0 and j == n_w:  # one batch: the whole-run result itself, no copies
            return part
        if responses is None:
            size = part.responses.shape[1:]
            require_memory(n_w * 9 * int(np.prod(size)), f"the responses of {n_w:,} windows")
            responses = np.empty((n_w,) + size, part.responses.dtype)
            binary = np.empty((n_w,) + size, part.binary.dtype)
            if keep_pixels:
                cells = np.empty((n_w,) + part.cells.shape[1:], part.cells.dtype)
                on = np.empty((n_w, h_px, w_px), np.int32)
                off = np.empty((n_w, h_px, w_px), np.int32)
        assert responses is not None and binary is not None
        responses[i:j] = part.responses
        binary[i:j] = part.binary
        if keep_pixels:
            assert cells is not None and on is not None and off is not None
            cells[i:j] = part.cells
            on[i:j] = counts.on
            off[i:j] = counts.off
        used += counts.events_used
        summary = part.summary
    if responses is None or binary is None:
        raise EvtkError("no windows to reconstruct")
    if not keep_pixels:
        cells = responses
        on = off = np.zeros((n_w, 0, 0), np.int32)
    assert cells is not None and on is not None and off is not None
    whole = ReconstructionSummary.from_dict(dict(summary, windows=n_w, windows_dropped=windows.dropped,
                                                 events_used=int(used), responses=int(n_w)))
    return Reconstruction(responses, binary, None, cells, None, WindowCounts(on, off, windows, (x0, x1, y0, y1),
                                                                              int(used)), whole)


@numba.njit(cache=True, nogil=True)
def _respond(counts, table, stride, theta_on, theta_off, linear, row_cell, row_weight, col_cell, col_weight, out,
             line):
    """Add each window's response, straight from its counts (int32, (2, windows, height, width), OFF then ON),
    to ``out`` (windows, rows, cols): every pixel's linearised value (``table[on * stride + off]``, or
    ``expm1(on * theta_on - off * theta_off)`` / ``on - off`` beyond the table; 0 for a pixel without events)
    spread over the output cells its area overlaps, a pixel row at a time into ``line`` (one output row), then
    the row over the output rows (``row_cell``/``row_weight``: each pixel row's cells and shares, ``col_*``
    each column's; padded with zero shares). Returns the largest rise computed beyond the table (the exp(700)
    check)."""
    n_w = counts.shape[1]
    h = counts.shape[2]
    w = counts.shape[3]
    cols = out.shape[2]
    on_max = table.size // stride
    worst = 0.0
    for k in range(n_w):
        for yy in range(h):
            line[:] = 0.0
            for xx in range(w):
                a = counts[1, k, yy, xx]
                b = counts[0, k, yy, xx]
                if a < on_max and b < stride:
                    v = table[a * stride + b]
                elif linear:
                    rise = a * theta_on - b * theta_off
                    worst = max(worst, rise)
                    v = np.expm1(rise)
                else:
                    v = np.float64(a) - np.float64(b)
                for j in range(col_cell.shape[1]):
                    line[col_cell[xx, j]] += v * col_weight[xx, j]
            for i in range(row_cell.shape[1]):
                wy = row_weight[yy, i]
                r = row_cell[yy, i]
                for c in range(cols):
                    out[k, r, c] += wy * line[c]
    return worst


#: Counts up to this (ON and OFF each) are linearised by table look-up in :func:`_respond`.
_TABLE_COUNTS = 64


def _value_table(theta_on: float, theta_off: float, linear: bool) -> tuple[np.ndarray, int]:
    """Each (ON, OFF) count pair's value, as :func:`evtk.reconstruct.linearize` computes it (the same rise,
    ``expm1``), flattened, and its stride; only ON counts whose rise stays within exp(700)."""
    on_max = _TABLE_COUNTS if not linear else max(1, min(_TABLE_COUNTS, int(700 // theta_on) + 1))
    on = np.arange(on_max + 0.0)[:, None]
    off = np.arange(_TABLE_COUNTS + 0.0)[None, :]
    values = np.expm1(on * theta_on - off * theta_off) if linear else on - off
    return np.ascontiguousarray(values).reshape(-1), _TABLE_COUNTS


def _shares(n_cells: int, n_pixels: int) -> tuple[np.ndarray, np.ndarray]:
    """For each pixel along one axis, the output cells it overlaps and its share of each (padded with 0)."""
    m = overlap_matrix(n_cells, 0.0, n_pixels / n_cells, n_pixels).T  # (pixels, cells), as downsample weighs
    k = max(1, int((m > 0).sum(axis=1).max()))
    cell = np.zeros((n_pixels, k), np.int64)
    share = np.zeros((n_pixels, k), np.float64)
    for px in range(n_pixels):
        nz = np.flatnonzero(m[px] > 0)
        cell[px, :nz.size] = nz
        share[px, :nz.size] = m[px, nz]
    return cell, share


def reconstruct_responses(source, windows: Windows, region, batch_windows: int | None = None,
                          chunk_events: int = 4_000_000, progress: Callable[[int], Any] | None = None,
                          **options: Any):
    """The responses of windows without a schedule, straight from their counts: no per-pixel float stage.

    What :func:`reconstruct_windows` gives with ``keep_pixels=False`` (the same responses to rounding), for
    the settings it supports (:func:`fused_supported`): each window's counts (one batch of windows at a time,
    in one reused buffer) go through one compiled pass that looks each pixel's linearised value up and
    spreads it over the output cells its area overlaps (the weights of :func:`evtk.reconstruct.downsample`),
    with no per-pixel array of values.

    Parameters
    ----------
    source : Events or Recording
        The events.
    windows : Windows
        Windows of a recording without a simulation record.
    region : tuple of int
        (x0, x1, y0, y1), half-open sensor pixels.
    batch_windows : int, optional
        Windows per batch; default :func:`batch_size`.
    chunk_events : int
        Most events read at once.
    progress : callable, optional
        Called with the number of events of each chunk read.
    **options
        :func:`evtk.reconstruct.reconstruct_counts`'s settings (checked by it on the first window).

    Returns
    -------
    Reconstruction
        As :func:`reconstruct_windows` with ``keep_pixels=False``.

    Raises
    ------
    EvtkError
        Settings the fused pass does not support, a region off the sensor, or counts whose rise exceeds
        exp(700).
    """
    from .pipeline import Reconstruction, reconstruct_counts

    if not fused_supported(options):
        raise EvtkError(f"the fused response pass does not support {sorted(options)}")
    n_w = len(windows)
    region = _checked_region(source, region)
    x0, x1, y0, y1 = region
    oh, ow = (int(v) for v in options.get("size", (16, 16)))
    require_memory(n_w * 17 * oh * ow, f"the responses of {n_w:,} windows")
    responses = None
    rows = cols = None
    used = 0
    first = None
    nb = batch_size(region, n_w) if batch_windows is None else max(1, int(batch_windows))
    for i, win, counts, n_used in _counted_batches(source, windows, region, nb, chunk_events, progress, reuse=True):
        if first is None:  # one empty pixel through the whole-run stages: the settings checked, the summary made
            nothing = np.zeros((1, 1, 1), np.int32)
            one = WindowCounts(nothing, nothing, win[:1], region, 0)
            first = reconstruct_counts(one, None, **options)
            linear = bool(first.summary["linear"])  # the whole-run path's choice of linearisation
            theta_on = theta_off = float(first.summary["theta_on"])
            responses = np.zeros((n_w,) + first.responses.shape[1:], np.float64)
            rows = _shares(oh, y1 - y0)
            cols = _shares(ow, x1 - x0)
            table, stride = _value_table(theta_on, theta_off, linear)
            line = np.zeros(ow, np.float64)
        assert responses is not None and rows is not None and cols is not None
        worst = _respond(counts, table, stride, theta_on, theta_off, linear, rows[0], rows[1], cols[0], cols[1],
                         responses[i:i + len(win)], line)
        if worst > 700:
            raise EvtkError("counts imply an intensity rise beyond exp(700): not a linearisable response")
        used += n_used
    if first is None or responses is None:
        raise EvtkError("no windows to reconstruct")
    binary = binarize(responses, first.summary["binarize"])
    empty = np.zeros((n_w, 0, 0), np.int32)
    summary = ReconstructionSummary.from_dict(dict(first.summary, windows=n_w, windows_dropped=windows.dropped,
                                                   events_used=int(used), responses=int(n_w)))
    return Reconstruction(responses, binary, None, responses, None,
                          WindowCounts(empty, empty, windows, region, int(used)), summary)


#: The settings :func:`reconstruct_responses` takes (the others change nothing without a simulation record, or
#: need the per-pixel stages).
_FUSED_OPTIONS = {"size", "binarize_method", "linear", "theta", "crop", "skip_us", "length_us", "deblur",
                  "flat_field"}


def fused_supported(options: dict) -> bool:
    """Whether :func:`reconstruct_responses` takes these :func:`evtk.reconstruct.reconstruct_counts` settings.

    Parameters
    ----------
    options : dict
        The settings.

    Returns
    -------
    bool
        True when every setting is one it takes, ``theta`` is a number or None and ``timing`` is not asked
        for.
    """
    extra = set(options) - _FUSED_OPTIONS - {"timing"}
    theta = options.get("theta")
    return not extra and options.get("timing") is not True and (theta is None or np.ndim(theta) == 0)
