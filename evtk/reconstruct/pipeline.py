"""Every stage in order: :func:`reconstruct` on a recording, :func:`reconstruct_counts` on window counts."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from .._blas import one_blas_thread
from ..errors import EvtkError
from ..optics import ideal_response, response_origin_px
from ..optics.camera import CellMap
from ..plan import FLAT_ID, LEVEL_ID, Plan, SimulationRecord
from ._batched import reconstruct_windows
from .accumulate import accumulate
from .binarize import binarize, binarize_rule
from .deblur import DEFAULT_LAMBDA, _deblur_system, _solve, relative_noise
from .fit import interior_pixels
from .fixed import fixed_responses, fixed_supported, linear_without_plan
from .grid import combine_passes, downsample, sample_response_grid, to_response_grid
from .linearize import (
    _expected_flat_counts,
    _flat_log_step,
    _model_log_step,
    _model_plan,
    count_curve,
    flat_field_gain,
    linearize,
    linearize_by_model,
)
from .result import Reconstruction
from .route import plan, window_bytes
from .summary import ReconstructionSummary
from .timing import _settle_residual, linearize_by_timing, timing_thresholds
from .windows import WindowCounts

if TYPE_CHECKING:
    import numpy.typing as npt

__all__ = ["Reconstruction", "response_error", "plan", "window_bytes", "wants_times",
    "reconstruct_counts", "silent_failures"]


def response_error(got: npt.ArrayLike, ideal: npt.ArrayLike) -> dict:
    """How far responses are from the ideal: Pearson correlation and two normalised RMS errors.

    Parameters
    ----------
    got, ideal : array_like
        The responses and the ideal, of equal size.

    Returns
    -------
    dict
        ``correlation``; ``nrmse``, the RMS error over the ideal's RMS (the strict one: 1.0 for an all-zero
        guess); ``nrmse_range``, the RMS error over the ideal's peak-to-peak range (the usual NRMSD).
        Undefined values are ``None``.

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


def _reconstruct_record(rec, window="schedule", skip_us=0, length_us=None, size=(16, 16), binarize_method="auto",
                        linear=True, theta=None, crop="valid", region=None, chunk_events=4_000_000, progress=None,
                        deblur=None, flat_field=True, timing=None, record=None, keep_pixels=True):
    """The whole pipeline on an open recording and its simulation record (or none): windows, counts,
    linearisation, passes, grid, binarisation (:func:`~evtk.reconstruct.reconstruct` without a bench plan).

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
        A fixed contrast threshold linearising by ``exp(n theta)``; default
        the recording's simulation metadata, else none: net counts.
    crop : "valid" or "full"
        Which part of the correlation to keep (needs a simulation record).
    region : (x0, x1, y0, y1), optional
        Sensor pixels to use; default the simulation's response region, else
        the whole sensor.
    deblur : bool or None
        With a simulation record and matched scaling, undo the known footprint
        blur (extended sources, pixel area, diffuser, the camera's pose and
        defocus) by solving the sampling model on the full response in two
        dimensions (:mod:`evtk.reconstruct.deblur`), regularised by the noise
        the recording's level captures or flat fields show. ``None``
        (default): deblur when the pixels are flat-field calibrated, where it
        helps on average (see ``benchmarks/bench_accuracy.py``).
    flat_field : bool
        Calibrate each pixel's threshold on the recording's flat-field
        captures, when it has any (:func:`flat_field_gain`).
    timing : bool or None
        Read the light below one threshold from each window's first and last
        ON-event times (:func:`linearize_by_timing`). ``None`` (default):
        wherever the recording's pixel model allows it; ``True``: required.
    record : SimulationRecord or Plan, optional
        The run's plan with its pixel model (or a simulation record, read as
        :meth:`~evtk.plan.Plan.from_record`) in place of the recording's own
        record: its schedule gives the windows, its region the pixels.
    keep_pixels : bool
        Keep every window's counts and per-pixel values (default). ``False``,
        for a recording without a simulation record (every window stands
        alone), keeps only the responses (``cells`` are the responses, the
        counts hold no pixels): windows are counted a batch at a time and the
        responses computed straight from the counts, in memory bounded by
        them and one batch (``evtk.reconstruct._batched``).

    Notes
    -----
    With a simulation record, linearisation inverts the recording's own pixel
    model (:func:`count_curve`, refined by event times); with ``theta`` given
    it uses ``exp(n * theta) - 1``; with neither (fixed windows of a
    recording without a record) nothing says how counts map to light, so the
    responses are net counts ON - OFF.
    """
    check_crop(crop)
    # every window's counts at once, unless responses alone of windows that stand alone (no simulation record)
    whole = keep_pixels or record is not None or SimulationRecord.from_metadata(rec.metadata) is not None
    sim, win, region = plan(rec, window, skip_us, length_us, region, check_memory=whole, record=record)
    if sim is None and not keep_pixels:  # no schedule: each window alone, a batch at a time
        stages = dict(size=size, binarize_method=binarize_method, linear=linear, theta=theta, crop=crop,
                      skip_us=skip_us, length_us=length_us, deblur=deblur, flat_field=flat_field, timing=timing)
        if fixed_supported(stages):
            return fixed_responses(rec, win, region, chunk_events=chunk_events, progress=progress, **stages)
        return reconstruct_windows(rec, win, region, keep_pixels=False, chunk_events=chunk_events,
                                   progress=progress, **stages)
    counts = accumulate(rec, win, region, chunk_events=chunk_events, progress=progress,
                        times=wants_times(sim, linear, theta, timing))
    if sim is not None and not isinstance(sim, Plan):  # the oracle: the plan the simulation record holds
        sim = Plan.from_record(sim)
    return reconstruct_counts(counts, sim, skip_us=skip_us, length_us=length_us, size=size,
                              binarize_method=binarize_method, linear=linear, theta=theta, crop=crop,
                              deblur=deblur, flat_field=flat_field, timing=timing)


def wants_times(sim: Plan | SimulationRecord | None, linear: bool = True, theta: float | None = None,
                timing: bool | None = None) -> bool:
    """Whether a reconstruction with these settings reads event times (accumulate with ``times=True``).

    Parameters
    ----------
    sim : Plan, SimulationRecord or None
        The plan (or simulation record) the reconstruction reads.
    linear, theta, timing
        :class:`~evtk.reconstruct.ReconstructOptions`' settings of those names.

    Returns
    -------
    bool
        True when the timing linearisation may read event times.
    """
    return timing is not False and sim is not None and bool(linear) and theta is None


def check_crop(crop: str) -> None:
    """Raise :class:`~evtk.EvtkError` unless ``crop`` is "valid" or "full".

    Parameters
    ----------
    crop : str
        The setting.
    """
    if crop not in ("valid", "full"):
        raise EvtkError(f"crop must be 'valid' or 'full', not {crop!r}")


def reconstruct_counts(counts: WindowCounts, sim: Plan | SimulationRecord | dict | None = None, skip_us: int = 0,
                       length_us: int | None = None, size: tuple = (16, 16), binarize_method: str | float = "auto",
                       linear: bool = True, theta: float | None = None, crop: str = "valid",
                       deblur: bool | None = None, flat_field: bool = True, timing: bool | None = None,
                       curve: tuple | None = None) -> Reconstruction:
    """Every stage after accumulation, on window counts (:func:`reconstruct` without the recording).

    Parameters
    ----------
    counts : WindowCounts
        From :func:`accumulate`, or from :meth:`evtk.simulate.Simulation.responses` through
        :meth:`WindowCounts.from_capture_counts`.
    sim : Plan, SimulationRecord or dict, optional
        The run's plan with its pixel model (:attr:`evtk.plan.Plan.pixels`), or a simulation record (or its dict
        form) read as one (:meth:`evtk.plan.Plan.from_record`): its pixel model is inverted, its schedule,
        patterns and placement used. None (nothing to linearise by): net counts ON - OFF, unless ``theta`` or
        ``curve`` is given. A plan without a pixel model is an :class:`~evtk.EvtkError`.
    skip_us, length_us : int
        The ones the counts were taken with.
    size : tuple of int
        ``(rows, cols)`` of each resampled response.
    binarize_method : str or float
        "auto" (:func:`binarize_rule`), "sign", "mean", "otsu" or a threshold.
    linear : bool
        Linearise counts to light (else net counts ON - OFF).
    theta : float, optional
        A fixed contrast threshold linearising by ``exp(n theta)`` in place of a pixel model; None (default)
        inverts the pixel model, and without one keeps net counts.
    crop : {"valid", "full"}
        Which part of the correlation to keep.
    deblur : bool, optional
        Solve out the footprint blur; None: when the pixels are flat-field calibrated.
    flat_field : bool
        Calibrate each pixel's threshold on the flat-field captures.
    timing : bool, optional
        Read the light below one threshold from the event times; None: where the model allows it.
    curve : tuple, optional
        ``(u, counts)``, as :func:`count_curve` returns, linearising instead of the record's pixel model
        (:func:`evtk.reconstruct.linearize.level_curve`).

    Returns
    -------
    Reconstruction
        The responses, their binarisation and the summary.
    """
    check_crop(crop)
    run = None if sim is None else _model_plan(sim)
    with one_blas_thread():  # small matrices
        return _reconstruct_counts(counts, run, skip_us, length_us, size, binarize_method, linear, theta, crop,
                                   deblur, flat_field, timing, curve)


def _reconstruct_counts(counts, run, skip_us, length_us, size, binarize_method, linear, theta, crop, deblur,
                        flat_field, timing, curve=None):
    """:func:`reconstruct_counts`' stages on a plan ``run`` with a pixel model (:func:`_model_plan`'s), or None."""
    pixels = None if run is None else run.pixels
    if run is None and curve is None:  # nothing in the plan to linearise by: net counts unless a theta is given
        linear = linear_without_plan(linear, theta)
    win = counts.windows
    region = counts.region
    if theta is None:
        theta_on = pixels.sensor.theta_on if pixels else 0.2
        theta_off = pixels.sensor.theta_off if pixels else 0.2
    else:
        theta_on = theta_off = float(theta)
    schedule = bench = None
    if run is not None and len(win) == len(run.schedule):
        schedule, bench = run.schedule, run.bench
    if curve is None:
        curve = count_curve(run, skip_us, length_us) if run is not None and linear and theta is None else None
    needs_net = not linear or curve is not None or (flat_field and schedule is not None)
    net = counts.on.astype(np.float64) - counts.off if needs_net else None
    gain = flat_u = None
    if linear and flat_field and schedule is not None and np.any(schedule.kernel_id == FLAT_ID):
        flat_u = _flat_log_step(run, bench, region)  # the flat field's light per pixel: the gain's and the timing's
        gain = flat_field_gain(net[schedule.kernel_id == FLAT_ID],
                               _expected_flat_counts(run, bench, region, curve, theta_on, flat_u))
    timed_share = thresholds = None
    why = _no_timing(counts, run, schedule, curve, skip_us) if timing is not False else "not asked for"
    if why is not None and timing:
        raise EvtkError(f"timing linearisation is not possible: {why}")
    if not linear:
        values = net
    elif why is None:  # the pixel model, read below one threshold from the event times
        values, timed_share, thresholds = _refine_by_timing(net if gain is None else net * gain, counts, run, bench,
                                                            schedule, curve, gain, theta_on, skip_us, flat_u)
    elif curve is not None:  # invert the recording's own pixel model
        values = linearize_by_model(net if gain is None else net * gain, curve)
    elif gain is None:
        values = linearize(counts.on, counts.off, theta_on, theta_off)
    else:
        values = linearize(counts.on * gain, counts.off * gain, theta_on, theta_off)

    pairs = ideal = regularisation = level_check = None
    deblurred = False
    if schedule is not None:
        kernels, features = run.kernels, run.features
        kh, kw = kernels.shape[1:]
        fh, fw = features.shape[1:]
        if linear:  # relative change -> light above the dark level, in response units
            values = values * pixels.blank_rate_e_per_s / pixels.gain_e_per_s_per_unit
        shape = (fh + kh - 1, fw + kw - 1)
        step = bench.kernel_step_cells / bench.pixel_cells
        placement = run.cell_map
        origin = run.origin_px if run.origin_px is not None else response_origin_px(bench, (kh, kw), (fh, fw))
        aligned = None if placement is None else placement.axis_aligned(shape)
        if aligned is not None:  # shifted or scaled only: along the sensor's axes, not turned
            (origin, step), placement = aligned, None
        view = placement if placement is not None else CellMap.scale_shift(
            origin, step, (bench.sensor_width, bench.sensor_height))
        inner = interior_pixels(region, origin, step, (kh, kw), (fh, fw), cell_map=view)
        is_level = schedule.kernel_id == LEVEL_ID
        if linear and is_level.any() and inner.any():  # the level captures' known light, read back
            level_check = [float(np.median(values[c][inner]) / schedule.level[c]) for c in np.flatnonzero(is_level)
                           if schedule.level[c] > 0]
        if deblur is None:  # a decimated reconstruction does not have the neighbours deblurring needs
            deblur = gain is not None and bench.decimation == 1
        deblurred = bool(deblur) and abs(bench.kernel_step_cells - 1.0) < 1e-9 and bench.decimation == 1
        if deblurred:  # undo the footprint (sources, pixels, diffuser) and the defocus through the whole view
            on_pixels, pairs = combine_passes(values, schedule)
            system = _deblur_system(bench, view, region, shape, run.blur_px)  # kept for the next run
            share = relative_noise(values, schedule.level, is_level, schedule.kernel_id == FLAT_ID, inner)
            noise_var = None
            if share is not None:  # the run's own error against the responses' power
                noise_var = share ** 2 * combine_passes(values ** 2, schedule, signed=False)[0].reshape(len(pairs), -1)
            # else nothing says how much: the plain inverse for a square view, a measured default otherwise
            lam = 0.0 if placement is None and run.blur_px == 0 else DEFAULT_LAMBDA
            solved, regularisation = _solve(on_pixels.reshape(len(pairs), -1), system, lam, noise_var)
            combined = solved.reshape((len(pairs),) + shape)
        else:
            if placement is not None:  # sampled through the map
                cells = sample_response_grid(values, region, placement, shape)
            else:
                cells = to_response_grid(values, region, origin, step, shape)
            combined, pairs = combine_passes(cells, schedule)
        ideal = pair_ideals(pairs, kernels, features, bench)
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
        binarize_method = binarize_rule(run)
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
        # each level capture's light read back (median over the interior) over the light it had: 1 when the
        # linearisation is right
        "level_light_ratio": level_check,
        # the deblur's Tikhonov regularisation, relative to the sampling matrix's largest singular value
        "deblur_regularisation": regularisation,
        "flat_field_captures": 0 if gain is None else int(np.sum(schedule.kernel_id == FLAT_ID)),
        "decimation": 1 if bench is None else int(bench.decimation),
        "linearization": ("counts" if not linear else "pixel model and event times" if timed_share is not None
                          else "pixel model" if curve is not None else "exp(n theta)"),
        "timed_share": timed_share,
        # the default would have read event times but the recording does not allow it: say why
        "timing_skipped": why if timing is None and linear and curve is not None and why is not None else None,
    }
    if ideal is not None:
        summary["error"] = response_error(cells, ideal)
    if schedule is not None:
        summary.update(silent_failures(counts, pairs, cells, len(run.kernels)))
    return Reconstruction(responses, binary, pairs, cells, ideal, counts, ReconstructionSummary.from_dict(summary),
                          thresholds)


def silent_failures(counts: WindowCounts, pairs: np.ndarray, cells: np.ndarray, n_kernels: int) -> dict:
    """What would otherwise pass unseen in a reconstruction's counts and responses, as summary entries.

    A window with no event over the region reads as darkness, though every capture of a schedule shows light
    (:func:`~evtk.simulate.split_passes` leaves dark passes out); a kernel with no capture (all mirrors off,
    nothing to show) has no response; a response that is zero everywhere has vanished.

    Parameters
    ----------
    counts : WindowCounts
        The windows' counts (``counts.windows.capture``: the capture each shows).
    pairs : ndarray (n, 3)
        (kernel_id, features_id, repeat) of each response.
    cells : ndarray (n, ...)
        The responses.
    n_kernels : int
        Kernels the job holds.

    Returns
    -------
    dict
        ``empty_windows`` (the number of windows with no event), ``vanished_responses`` (responses zero
        everywhere), ``kernels_without_response`` (kernel ids), and ``warnings``: one sentence for each that
        is not zero or empty.
    """
    events = counts.on.reshape(len(counts.on), -1).sum(axis=1) + counts.off.reshape(len(counts.off), -1).sum(axis=1)
    empty = np.flatnonzero(events == 0)
    caps = np.asarray(counts.windows.capture)[empty] if len(counts.windows.capture) == len(events) else empty
    flat = np.asarray(cells, np.float64).reshape(len(cells), -1)
    vanished = np.flatnonzero(~np.any(flat != 0, axis=1)) if flat.size else np.zeros(0, np.int64)
    shown = set(np.asarray(pairs)[:, 0].tolist()) if len(pairs) else set()
    missing = sorted(set(range(int(n_kernels))) - shown)
    warnings = []
    if empty.size:
        warnings.append(f"{empty.size} of {len(events)} windows hold no event over the region and read as darkness "
                        f"(captures {caps[:10].tolist()}{' ...' if empty.size > 10 else ''}): a lost stretch of the "
                        "recording, windows off the light, or a region off the response?")
    if vanished.size:
        which = sorted({int(pairs[i][0]) for i in vanished})
        warnings.append(f"{vanished.size} of {len(flat)} responses are zero everywhere (kernels {which[:10]}): "
                        "their windows saw nothing")
    if missing:
        warnings.append(f"{len(missing)} of {int(n_kernels)} kernels have no capture and no response (kernels "
                        f"{missing[:10]}: all mirrors off, nothing to show)")
    return {"empty_windows": int(empty.size), "vanished_responses": int(vanished.size),
            "kernels_without_response": missing, "warnings": warnings}


def pair_ideals(pairs, kernels, features, bench):
    """The ideal response of each (kernel_id, features_id, repeat) row of ``pairs``, computed once per pair."""
    per_pair = {}
    for k, f, _ in pairs.tolist():
        if (k, f) not in per_pair:
            per_pair[(k, f)] = ideal_response(kernels[k], features[f], bench)
    return np.stack([per_pair[(k, f)] for k, f, _ in pairs.tolist()])


def _no_timing(counts, run, schedule, curve, skip_us):
    """Why event times cannot refine this reconstruction's linearisation (None: they can)."""
    if curve is None:
        return "it needs the recording's pixel model (a simulated recording, linear, no fixed theta)"
    if counts.on_first_us is None:
        return "the counts hold no event times (accumulate with times=True)"
    if schedule is None or not np.array_equal(counts.windows.t_start_us, schedule.t_on_us + int(skip_us)):
        return "the windows must start skip_us after each pattern's onset (schedule windows)"
    period = counts.stamp_period_us
    if period is not None and period > MAX_TIMING_STAMP_US:
        return (f"the event time stamps lie on a {period:g} us grid (a sensor that reads its pixels out in "
                f"frames): too coarse to time threshold crossings (at most {MAX_TIMING_STAMP_US:g} us)")
    return None


#: Coarsest time-stamp grid the timing linearisation accepts; coarser stamps (frame readout) fall back to counts.
MAX_TIMING_STAMP_US = 10.0


def _refine_by_timing(net, counts, run, bench, schedule, curve, gain, theta_on, skip_us, flat_u=None):
    """Light from :func:`linearize_by_timing` wherever the times determine it, else from the (calibrated)
    net counts ``net`` through :func:`linearize_by_model`.

    Thresholds: nominal, or per pixel from the flat-field windows' times
    (:func:`timing_thresholds`), else from the flat-field count gain.
    Returns the values (``exp(u) - 1``), the share of pixel-windows the times set, and each pixel's threshold.
    """
    sm = run.pixels.sensor
    blank = run.pixels.blank_rate_e_per_s
    theta = np.full(counts.on.shape[1:], float(theta_on))
    if gain is not None:
        ff = schedule.kernel_id == FLAT_ID
        if flat_u is None:
            flat_u = _flat_log_step(run, bench, counts.region)
        flat_u = np.broadcast_to(flat_u, (int(ff.sum()),) + theta.shape)
        flat_u = flat_u - _settle_residual(flat_u, schedule.t_on_us[ff], schedule.t_off_us[ff], sm, blank)
        t = timing_thresholds(counts.on[ff], counts.on_first_us[ff], counts.on_last_us[ff], flat_u, sm, blank,
                              skip_us)
        # a threshold the times put far from nominal says the model does not fit this pixel (a camera whose
        # pixels differ from the record's): the count gain is the safer estimate there
        plausible = np.isfinite(t) & (t > 0.25 * theta) & (t < 4.0 * theta)
        theta = np.where(plausible, t, theta * gain)
    u = linearize_by_timing(counts.on, counts.on_first_us, counts.on_last_us, theta, sm, blank, curve, skip_us)
    ok = np.isfinite(u)
    u[~ok] = _model_log_step(net[~ok], curve)
    u[ok] += _settle_residual(u, schedule.t_on_us, schedule.t_off_us, sm, blank)[ok]
    return np.expm1(u), float(ok.mean()) if ok.size else 0.0, theta
