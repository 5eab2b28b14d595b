"""Windows without a schedule, a batch at a time: memory bounded by a batch, not by windows x sensor.

Windows without a capture schedule (periodic or from trigger edges) stand alone: each one's response depends on
its own counts only. :func:`~evtk.reconstruct.accumulate.accumulate_batches` counts them a batch at a time (each
batch's events through the recording's time-window API, decoded on another thread while the last chunk is
counted); :func:`reconstruct_windows` runs the stages after accumulation on each batch (the responses alone go
the numpy route of :mod:`evtk.reconstruct.fixed`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from ..errors import EvtkError
from ..limits import require_memory
from .accumulate import _checked_region, accumulate_batches
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
