"""Reconstructing a bench recording from its schedule alone: no simulation record, no pixel model.

The bench knows what it showed (``schedule.json`` from :mod:`evtk.patterns`)
and where the response lies on the sensor (a region and the pixel of cell
(0, 0), from a calibration or measured by hand); it does not know the
pixels' model. :func:`match_windows` pairs the recording's trigger windows
with the schedule's captures (the camera's clock has its own origin; edges
can be lost or doubled), and :func:`_reconstruct_bench` runs windows,
counts, ``exp(n theta)`` linearisation, the passes, the grid, resampling and
binarisation on what matched, and compares the result with the digital
correlation of the job's patterns, which the bench knows too.
"""

from __future__ import annotations

import os
from typing import TYPE_CHECKING, Any

import numpy as np

from .._arrays import distinct
from ..errors import EvtkError
from ..events import Triggers
from ..optics import response_origin_px
from ..plan import FLAT_ID, LEVEL_ID, Plan, Schedule, as_plan
from .accumulate import accumulate
from .binarize import binarize
from .grid import combine_passes, downsample, sample_response_grid, to_response_grid
from .linearize import flat_field_gain, linearize
from .pipeline import MAX_TIMING_STAMP_US, Reconstruction, check_crop, pair_ideals, response_error, silent_failures
from .summary import ReconstructionSummary
from .windows import Windows, _trim, windows_from_triggers

if TYPE_CHECKING:
    import numpy.typing as npt

__all__ = ["load_schedule", "match_windows", "synchronous_readout", "refuse_synchronous"]


def load_schedule(path: str | os.PathLike) -> Plan:
    """Read and check a bench run's ``schedule.json``: :meth:`evtk.plan.Plan.read`.

    Parameters
    ----------
    path : str or os.PathLike
        The file (:func:`evtk.patterns.write_patterns`; ``docs/formats/schedule.md``).

    Returns
    -------
    Plan
        Its schedule, patterns, bench and timing (``plan.kernels``, ...).
    """
    return Plan.read(path)


def match_windows(triggers: Triggers, schedule: Schedule, tolerance_us: float | None = None) -> tuple[Windows, dict]:
    """Pair trigger windows with the schedule's captures.

    The recording's clock and the schedule's differ by an offset, found as
    the one that lines up the most window starts with capture starts (tried
    from the first few windows and captures). A window matches the capture
    it then starts within ``tolerance_us`` of (default: a quarter of the
    shortest gap between captures); a capture gets at most one window.
    ``Windows.capture`` holds the matched capture numbers; ``report`` says
    how many matched, which captures have no window (``missing``), how many
    windows match none (``extra``), the offset, and what the trigger edges
    themselves left out (``dropped``). Missing and extra edges are reported,
    not fatal; no match at all is an error.

    Parameters
    ----------
    triggers : Triggers
        The recording's trigger edges.
    schedule : Schedule
        The captures.
    tolerance_us : float, optional
        How far a window's start may be from its capture's.

    Returns
    -------
    tuple
        ``(Windows, report)``.
    """
    win = windows_from_triggers(triggers)
    t_on = schedule.t_on_us
    if len(win) == 0:
        raise EvtkError("the recording holds no trigger windows (rising then falling edge) to match the schedule")
    gaps = np.diff(np.sort(t_on))
    tol = float(tolerance_us) if tolerance_us is not None else max(1.0, 0.25 * float(gaps.min() if gaps.size
                                                                                    else 1e9))
    order = np.argsort(t_on, kind="stable")
    sorted_on = t_on[order]

    def assign(offset):  # an offset, or a column of them: each window's nearest capture start, per offset
        rel = win.t_start_us - offset
        j = np.clip(np.searchsorted(sorted_on, rel), 1, max(1, len(sorted_on) - 1))
        cand = np.stack([j - 1, np.minimum(j, len(sorted_on) - 1)])
        dist = np.abs(sorted_on[cand] - rel)
        best = np.where(dist[1] < dist[0], cand[1], cand[0])  # the earlier on a tie, as argmin
        ok = np.abs(sorted_on[best] - rel) <= tol
        return best, ok, np.abs(sorted_on[best] - rel)

    # a schedule of equal periods lines up almost as well one capture off: the most matches win, then the
    # smallest total distance (a constant clock offset lines every start up to the microsecond)
    k = min(8, len(win), len(t_on))
    candidates = distinct(win.t_start_us[:k, None] - sorted_on[None, :k])
    # every candidate's matching at once; then, as one at a time did, the first of the most matches with the least
    # total distance
    _, ok_all, dist_all = assign(candidates[:, None])
    matches = ok_all.sum(axis=1)
    spread = np.array([float(d[o].sum()) for d, o in zip(dist_all, ok_all)])
    top = matches == matches.max()
    best_offset = int(candidates[np.flatnonzero(top & (spread == spread[top].min()))[0]])
    idx, ok, dist = assign(best_offset)
    if not ok.any():
        raise EvtkError("no trigger window lines up with the schedule: is it the schedule of this recording?")
    taken: dict[int, int] = {}
    for w in np.flatnonzero(ok):  # a capture keeps its closest window; the others are extra
        c = int(idx[w])
        if c not in taken or dist[w] < dist[taken[c]]:
            taken[c] = int(w)
    caps = np.array(sorted(taken), dtype=np.int64)
    wins = np.array([taken[c] for c in caps], dtype=np.int64)
    matched = Windows(win.t_start_us[wins], win.t_end_us[wins], order[caps], "triggers matched to the schedule",
                      dict(win.dropped))
    missing = sorted(set(range(len(t_on))) - set(order[caps].tolist()))
    report = {"matched": int(len(caps)), "captures": int(len(t_on)), "missing": missing,
              "extra": int(len(win) - len(caps)), "offset_us": int(best_offset),
              "dropped": {k: v for k, v in win.dropped.items() if v}}
    return matched, report


def _reconstruct_bench(rec, schedule, region, origin_px=None, size=(16, 16), binarize_method="auto", theta=0.2,
                      skip_us=0, length_us=None, crop="valid", tolerance_us=None, flat_field=True,
                      progress=None, cell_map=None) -> Reconstruction:
    """The whole pipeline on a bench recording, driven by its schedule; no simulation record is read.

    Parameters
    ----------
    rec : Recording
        Events and the DMD's trigger edges.
    schedule : str, os.PathLike or dict
        ``schedule.json`` (:func:`evtk.patterns.write_patterns`), a :class:`~evtk.plan.Plan` or a schedule's dict.
    region : (x0, x1, y0, y1)
        Sensor pixels to count (half-open).
    origin_px : (x, y), optional
        Sensor pixel that sees cell (0, 0) of the full response; default the
        bench geometry's (the response centred on the sensor).
    size, binarize_method, skip_us, length_us, crop
        As :func:`~evtk.reconstruct.reconstruct`; ``"auto"`` binarises by sign
        when the job is signed, else at each response's mean.
    theta : float
        Contrast threshold of ``exp(n theta) - 1`` (:func:`linearize`).
    tolerance_us : float, optional
        How far a window start may be from its capture's (see :func:`match_windows`).
    flat_field : bool
        Calibrate each pixel's threshold on the matched flat-field captures:
        without a pixel model, what a nominal pixel would count there is
        taken as the 5x5 median of its neighbours' counts (the flat response
        is smooth; threshold mismatch is not), see :func:`flat_field_gain`.
    cell_map : CellMap, optional
        A calibration's map from cells to pixels; one that is not an upright scale and shift (a mirrored,
        turned, tilted or distorted view) is sampled through, else it gives the origin and the step.

    Returns
    -------
    Reconstruction
        Its ``ideal`` is the digital correlation of the job's patterns and its
        ``summary`` carries the trigger match (``match``) and the error against
        the ideal after the best scale (``error``: responses are relative
        intensity, not the ideal's units). Pairs with a pass that has no
        window are left out and listed.
    """

    check_crop(crop)
    sched = as_plan(schedule)
    s, kernels, features, bench = sched.schedule, sched.kernels, sched.features, sched.bench
    win, report = match_windows(rec.triggers(), s, tolerance_us)
    start, end = _trim(win.t_start_us, win.t_end_us, skip_us, length_us, "matched")
    win = Windows(start, end, win.capture, win.source, win.dropped)
    kh, kw = kernels.shape[1:]
    fh, fw = features.shape[1:]
    origin = tuple(float(v) for v in (origin_px if origin_px is not None
                                      else response_origin_px(bench, (kh, kw), (fh, fw))))
    flat = s.kernel_id[win.capture] == FLAT_ID
    lit = flat | (s.kernel_id[win.capture] == LEVEL_ID)
    lit = lit if lit.any() else np.ones(len(win), bool)
    refuse_synchronous(rec, win.t_start_us[lit], win.t_end_us[lit])
    counts = accumulate(rec, win, region, progress=progress)
    gain = None
    if flat_field and flat.any():
        gain = neighbourhood_flat_gain(counts.on[flat].astype(np.float64) - counts.off[flat])
    values = linearize(counts.on, counts.off, theta) if gain is None else \
        linearize(counts.on * gain, counts.off * gain, theta)
    step = bench.kernel_step_cells / bench.pixel_cells
    full = (fh + kh - 1, fw + kw - 1)
    aligned = None if cell_map is None else cell_map.axis_aligned(full)
    if aligned is not None:
        origin, step = aligned
    if cell_map is not None and aligned is None:  # mirrored, turned, tilted or distorted: through the map
        cells = sample_response_grid(values, counts.region, cell_map, full)
    else:
        cells = to_response_grid(values, counts.region, origin, step, full)
    # the passes of each (kernel, features, repeat) pair: only pairs whose every pass has a window
    keep, complete = _complete_mask(s, win.capture)
    kept = s.take(win.capture[keep])
    combined, pairs = combine_passes(cells[keep], kept)
    ideal = pair_ideals(pairs, kernels, features, bench)
    if crop == "valid":
        sl = (slice(None), slice(kh - 1, fh), slice(kw - 1, fw))
        combined, ideal = combined[sl], ideal[sl]
    signed = bool(np.min(kernels) < 0 or np.min(features) < 0)
    method = ("sign" if signed else "mean") if binarize_method == "auto" else binarize_method
    responses = downsample(combined, size)
    binary = binarize(responses, method)
    scale = float(np.sum(combined * ideal) / np.sum(combined * combined)) if np.any(combined) else 1.0
    checks = silent_failures(counts, pairs, combined, len(kernels))
    if scale < 0:  # scored after the scale's size only: an inverted result keeps its sign
        checks["warnings"].append(
            f"the responses are inverted against the ideal (best scale {scale:.3g}): the correlation is reported "
            "with its sign. Is the camera's polarity swapped, or does exp(n theta) not describe these pixels "
            "(a frame readout, a pixel model that failed)?")
    summary = {
        "captures": int(len(s)), "windows": int(len(win)), "window_source": win.source,
        "windows_dropped": win.dropped, "events_used": counts.events_used, "region": list(counts.region),
        "response_origin_px": list(origin), "responses": int(responses.shape[0]), "size": list(responses.shape[1:]),
        "linear": True, "theta_on": float(theta), "binarize": str(method), "skip_us": int(skip_us),
        "length_us": None if length_us is None else int(length_us), "linearization": "exp(n theta)",
        "deblurred": False, "flat_field_captures": int(flat.sum()) if gain is not None else 0,
        "decimation": int(bench.decimation),
        "match": report, "pairs_left_out": sorted(_all_pairs(s) - complete),
        "error": response_error(combined * abs(scale), ideal), "scale_to_ideal": scale, **checks,
    }
    return Reconstruction(responses, binary, pairs, combined, ideal, counts, ReconstructionSummary.from_dict(summary))


#: Pixel-frames a synchronous readout must show fired in the next frame too (busy pixels) before the absence of
#: two events from one pixel in one frame names it (:func:`synchronous_readout`).
SYNC_MIN_RUNS = 50


def synchronous_readout(rec: Any, t_on_us: npt.ArrayLike, t_off_us: npt.ArrayLike,
                        max_windows: int = 16) -> float | None:
    """The frame period (µs) when the recording's pixels are read out synchronously, else None.

    A synchronous readout (a frame every period, at most one event a pixel and frame) stamps every event on
    the frame grid, and never stamps two from one pixel in one frame, however bright: its counts stop growing
    with the light and even fall, which no linearisation undoes. Asynchronous pixels stamped on a frame grid
    (the DVXplorer's) fire several times a frame at a bright onset. Read from the events of the first
    ``max_windows`` windows ``[t_on_us, t_off_us)``: a grid coarser than
    :data:`~evtk.reconstruct.pipeline.MAX_TIMING_STAMP_US`, no pixel twice in one stamp, and at least
    :data:`SYNC_MIN_RUNS` pixel-frames followed by the same pixel in the next frame (busy enough that
    asynchronous pixels would have doubled).

    Parameters
    ----------
    rec : Recording
        The open recording.
    t_on_us, t_off_us : array of int
        Windows with light in them (flat fields, level captures).
    max_windows : int
        Windows read at most.

    Returns
    -------
    float or None
        The frame period (µs), or None for an asynchronous readout.
    """
    w = int(rec.sensor_size[0])
    bounds = list(zip(np.asarray(t_on_us)[:max_windows].tolist(), np.asarray(t_off_us)[:max_windows].tolist()))
    if _asynchronous_early(rec, bounds):
        return None
    parts = [rec.events(int(a), int(b)) for a, b in bounds]
    parts = [e for e in parts if e.t.size]
    if not parts:
        return None
    t = np.concatenate([e.t for e in parts]).astype(np.int64, copy=False)
    steps = np.diff(t)
    if steps.size and steps.min() >= 0:  # windows in time order: the distinct stamps' steps are the rises
        steps = steps[steps > 0]
    else:
        steps = np.diff(distinct(t))
    if steps.size + 1 < 16:  # a few windows of a few frames each: the grid's step is the stamps' common divisor
        return None
    period = int(np.gcd.reduce(steps))
    if period <= MAX_TIMING_STAMP_US:
        return None
    pix = np.concatenate([e.y.astype(np.int64) * w + e.x for e in parts])
    order = np.lexsort((t, pix))
    t, pix = t[order], pix[order]
    same = pix[1:] == pix[:-1]
    dt = np.diff(t)
    doubled = int(np.sum(same & (dt == 0)))
    runs = int(np.sum(same & (np.abs(dt - period) <= 1)))
    return float(period) if doubled <= 1e-4 * t.size and runs >= SYNC_MIN_RUNS else None


#: Events a chunk of :func:`_asynchronous_early`'s probe holds, and most events it reads.
SYNC_PROBE_EVENTS = 1 << 14
SYNC_PROBE_MAX_EVENTS = 1 << 18


def _asynchronous_early(rec: Any, bounds: list) -> bool:
    """Whether the first events that fall in the windows ``bounds`` already rule a frame grid out.

    The grid :func:`synchronous_readout` looks for is the greatest common divisor of the differences between all
    its stamps; that of a subset is a multiple of the whole set's. So once the stamps read so far have a divisor
    of at most :data:`~evtk.reconstruct.pipeline.MAX_TIMING_STAMP_US`, the whole set's is too and the answer is
    None, as the full test would find: an asynchronous camera shows it within its first events, and the rest of
    the windows need not be read. The recording is read from its start, a chunk at a time, keeping the stamps
    inside a window, for at most :data:`SYNC_PROBE_MAX_EVENTS` events or until past the last window: a
    recording that can read one window alone (AEDAT4) would first scan every packet's times for it, which costs
    a fresh process more than the whole test.
    """
    if not bounds:
        return False
    lo = np.array([a for a, _ in bounds], np.int64)
    hi = np.array([b for _, b in bounds], np.int64)
    order = np.argsort(lo, kind="stable")
    lo, reach = lo[order], np.maximum.accumulate(hi[order])  # a stamp is in a window if below the reach of
    t0 = None                                                # the windows starting at or before it
    g = 0
    read = 0
    for chunk in rec.iter_events(SYNC_PROBE_EVENTS):
        t = chunk.t.astype(np.int64, copy=False)
        k = np.searchsorted(lo, t, side="right") - 1
        t = t[(k >= 0) & (t < reach[np.maximum(k, 0)])]
        if t.size:
            if t0 is None:
                t0 = int(t[0])
            g = int(np.gcd.reduce(np.abs(t - t0), initial=g))
            if 0 < g <= MAX_TIMING_STAMP_US:
                return True
        read += chunk.t.size
        if read >= SYNC_PROBE_MAX_EVENTS or (chunk.t.size and int(chunk.t[-1]) >= int(reach[-1])):
            return False
    return False


def refuse_synchronous(rec: Any, t_on_us: npt.ArrayLike, t_off_us: npt.ArrayLike) -> None:
    """Raise :class:`~evtk.EvtkError`, naming the readout and what to do, when :func:`synchronous_readout`
    finds one in the windows ``[t_on_us, t_off_us)``.

    Parameters
    ----------
    rec : Recording
        The open recording.
    t_on_us, t_off_us : array of int
        Windows with light in them.
    """
    period = synchronous_readout(rec, t_on_us, t_off_us)
    if period is not None:
        raise EvtkError(
            f"the recording comes from a synchronous frame readout (events on a {period:g} us grid, never two from "
            "one pixel in a frame): a pixel's count stops growing with its light and falls again when bright, so "
            "no linearisation of its counts is right; record with the camera's asynchronous readout (or a readout "
            "period far below the pixels' rise)")


def _all_pairs(s):
    use = (s.kernel_id >= 0) & (s.features_id >= 0)
    return {(int(k), int(f), int(r)) for k, f, r in zip(s.kernel_id[use], s.features_id[use], s.repeat[use])}


def neighbourhood_flat_gain(net_flat):
    """:func:`flat_field_gain` without a pixel model: what a nominal pixel would count in the flat windows
    ``net_flat`` (windows, rows, cols) is taken as the 5x5 median of its neighbours' mean (the flat response is
    smooth; threshold mismatch is not)."""
    from scipy.ndimage import median_filter  # (scipy where a step uses it: not on import)

    return flat_field_gain(net_flat, median_filter(net_flat.mean(axis=0), size=5, mode="nearest"))


def _complete_mask(s, captures):
    """Which of the matched ``captures`` to keep (the setup captures, and every pass of the pairs all of whose
    passes have a window), and the set of those complete (kernel, features, repeat) pairs."""
    complete = _complete_pairs(s, set(np.asarray(captures).tolist()))
    keep = np.array([s.kernel_id[c] < 0 or (int(s.kernel_id[c]), int(s.features_id[c]), int(s.repeat[c])) in complete
                     for c in np.asarray(captures).tolist()], bool)
    return keep, complete


def _complete_pairs(s, have):
    """The (kernel, features, repeat) pairs all of whose captures are in ``have``."""
    out = {}
    for c in range(len(s)):
        if s.kernel_id[c] < 0:
            continue
        key = (int(s.kernel_id[c]), int(s.features_id[c]), int(s.repeat[c]))
        out[key] = out.get(key, True) and c in have
    return {k for k, v in out.items() if v}
