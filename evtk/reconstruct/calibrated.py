"""The calibrated route: a recording, what the bench showed, where the response lies; the pixel model fitted.

:func:`_reconstruct_calibrated` is what ``evtk reconstruct`` runs by default,
on a bench recording (``--schedule``) and on a simulated one alike. It reads
no answer only the simulator knows:

1. trigger windows matched to the schedule's captures (:func:`match_windows`);
2. counts and event times over the response's region;
3. a pixel model fitted to the run's own level captures
   (:mod:`evtk.reconstruct.fit`), when it has any;
4. then the oracle's stages on that model (:func:`reconstruct_counts`, on
   the bench's plan with the fitted model in it, :class:`~evtk.plan.PixelModel`):
   flat field, linearisation by the model and the event times, passes,
   grid, deblurring, resampling, binarisation.

Without level captures it falls back to :func:`_reconstruct_bench`
(``exp(n theta)``) and says so. A simulated recording's own record serves
only for what a bench also has (the schedule, patterns and bench geometry:
:func:`schedule_of_record`) and for the error against the ideal;
``evtk reconstruct --oracle`` runs the model of the record instead.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from .._arrays import median
from ..errors import EvtkError
from ..optics import response_origin_px, response_region
from ..optics.camera import CellMap
from ..plan import FLAT_ID, LEVEL_ID, PixelModel, Plan, Schedule, SimulationRecord, as_plan
from .accumulate import accumulate
from .bench import (
    _all_pairs,
    _complete_mask,
    _reconstruct_bench,
    match_windows,
    neighbourhood_flat_gain,
    refuse_synchronous,
)
from .fit import (
    MAX_DELAY_US,
    NOMINAL_BLANK_E_PER_S,
    PixelFit,
    describe_pixels,
    fit_pixel_model,
    fit_refractory,
    hot_pixels,
    interior_pixels,
    level_off_times,
    level_rise_times,
    level_statistics,
    on_gaps,
    refractory_bound,
    rise_orders,
)
from .linearize import level_curve, level_table_values
from .pipeline import MAX_TIMING_STAMP_US, check_crop, reconstruct_counts
from .windows import WindowCounts, Windows, _trim

if TYPE_CHECKING:
    import numpy.typing as npt

__all__ = ["schedule_of_record", "nominal_placement", "fit_on_edges", "MAX_LEVEL_ERROR",
           "MAX_TABLE_ERROR", "LEAD_US", "held_out_table_error", "PHYSICAL_RANGE", "level_readback",
           "refuse_pixel_fit"]

#: The most a fitted pixel model may misread the level captures' light (as a factor, either way) before the
#: calibrated route gives it up for exp(n theta).
MAX_LEVEL_ERROR = 2.0

#: The most the level captures' table may misread a level left out of it (as a factor, median over the levels)
#: for the calibrated route to read the counts through it where the pixel model misreads them: a pixel that
#: saturates (a 40 µs refractory period) reads 1.5x off and is left to exp(n theta); a log-node pixel 1.04x.
MAX_TABLE_ERROR = 1.25


def schedule_of_record(record: SimulationRecord | dict) -> Plan:
    """What a simulated run's ``schedule.json`` would hold, from its record: no pixel model, no photon rates.

    Parameters
    ----------
    record : SimulationRecord or dict
        The record (or its dict form).

    Returns
    -------
    Plan
        :meth:`Plan.from_record` without the oracle's part: the schedule, patterns, bench and timing.
    """
    return Plan.from_record(record, oracle=False)


def nominal_placement(schedule: Plan | dict | str | os.PathLike) -> tuple:
    """Where the bench geometry alone puts the response (centred on the sensor).

    Parameters
    ----------
    schedule : Plan, dict, str or os.PathLike
        The run's plan, a schedule's dict form or its ``schedule.json``.

    Returns
    -------
    tuple
        ``(region, origin_px)``: ``(x0, x1, y0, y1)`` and the sensor pixel ``(x, y)`` of cell (0, 0).
    """
    sched = as_plan(schedule)
    b, ks, fs = sched.bench, sched.kernels.shape[1:], sched.features.shape[1:]
    return tuple(int(v) for v in response_region(b, ks, fs)), tuple(float(v) for v in response_origin_px(b, ks, fs))


def _fitted_plan(sched: Plan, fit: PixelFit, sub, t_on_us, t_off_us, region, origin_px, cell_map, blur_px) -> Plan:
    """The bench plan the stages after counting read (:func:`reconstruct_counts`), with the fitted pixel model.

    ``sub`` holds the matched captures, ``t_on_us``/``t_off_us`` their windows on the recording's clock; the
    photon rates are the fit's, relative to :data:`~evtk.reconstruct.fit.NOMINAL_BLANK_E_PER_S` (glow folded
    into the dark level); ``blur_px`` is the calibration's defocus, which goes with ``cell_map``.
    """
    bench = sched.bench
    matched = dataclasses.replace(sub, t_on_us=np.asarray(t_on_us, np.int64), t_off_us=np.asarray(t_off_us, np.int64))
    view = None if cell_map is None else CellMap(np.asarray(cell_map.matrix, np.float64), float(cell_map.k1),
                                                 (bench.sensor_width, bench.sensor_height))
    return sched.replace(schedule=matched, region=tuple(int(v) for v in region),
                         origin_px=tuple(float(v) for v in origin_px), cell_map=view,
                         blur_px=0.0 if cell_map is None else float(blur_px), camera=None, record=None,
                         pixels=PixelModel(fit.sensor, NOMINAL_BLANK_E_PER_S / fit.blank, NOMINAL_BLANK_E_PER_S))


def _reconstruct_calibrated(rec, schedule, region=None, origin_px=None, size=(16, 16), binarize_method="auto",
                           skip_us=0, length_us=None, crop="valid", flat_field=True, deblur=None, timing=None,
                           linear=True, tolerance_us=None, progress=None, pixel_model=None, cell_map=None,
                           blur_px=0.0, own_levels=True, linearization="auto"):
    """The whole pipeline with a pixel model fitted to the recording's own level captures.

    Parameters
    ----------
    rec : Recording
        Events and the DMD's trigger edges.
    schedule : Plan, str, os.PathLike or dict
        The run's plan (:func:`load_schedule`'s, :func:`schedule_of_record`'s), its
        ``schedule.json`` (:func:`evtk.patterns.write_patterns`) or a schedule's dict form.
    region, origin_px
        Where the response lies (from :func:`evtk.calibrate.calibrate`);
        default :func:`nominal_placement`.
    size, binarize_method, skip_us, length_us, crop, flat_field, deblur, timing, linear
        As :func:`~evtk.reconstruct.reconstruct`.
    tolerance_us : float, optional
        As :func:`match_windows`.
    pixel_model : PixelFit or dict, optional
        A model fitted before (``evtk calibrate`` on a calibration run with
        level captures), used when this run has no level captures of its own
        (same bench, light and camera settings assumed).
    cell_map : CellMap, optional
        The calibration's whole map from cells to pixels
        (:meth:`evtk.calibrate.Calibration.cell_map`), through which the
        pipeline deblurs (:mod:`evtk.reconstruct.deblur`), or, without
        deblurring, samples each cell (:func:`~evtk.reconstruct.grid.sample_response_grid`).
    blur_px : float
        The camera's defocus (:attr:`evtk.calibrate.Calibration.blur_px`),
        deblurred with the footprint (:mod:`evtk.reconstruct.deblur`); it goes
        with ``cell_map``.
    own_levels : bool
        Fit the pixel model to the run's own level captures when it has any
        (default); False uses ``pixel_model`` even then (one fitted to these
        very captures before).
    linearization : {"auto", "model", "table"}
        How counts become light: "model" inverts the fitted pixel model
        (falling back to exp(n theta) when it misreads the level captures by
        more than :data:`MAX_LEVEL_ERROR`); "table" reads them through the
        level captures' own monotone table of mean counts against light
        (:func:`~evtk.reconstruct.linearize.level_curve`, no model, no event
        times); "auto" (default) takes the model while it reads the level
        captures back within :data:`MAX_LEVEL_ERROR`, else the table where
        the table reads each level left out of it within
        :data:`MAX_TABLE_ERROR` (:func:`held_out_table_error`), else exp(n theta).

    Returns
    -------
    Reconstruction
        Its summary holds the trigger match (``match``), the fitted model
        (``pixel_model``) and the error against the ideal correlation of the
        schedule's patterns.
    """
    check_crop(crop)
    sched = as_plan(schedule)
    s = sched.schedule
    if region is None or origin_px is None:
        nominal = nominal_placement(sched)
        region = nominal[0] if region is None else region
        origin_px = nominal[1] if origin_px is None else origin_px
    levels_here = bool(np.any(s.kernel_id == LEVEL_ID)) and (own_levels or pixel_model is None)
    if not levels_here and pixel_model is None:
        result = _reconstruct_bench(rec, sched, region, origin_px, size=size, binarize_method=binarize_method,
                                   skip_us=skip_us, length_us=length_us, crop=crop, flat_field=flat_field,
                                   tolerance_us=tolerance_us, progress=progress)
        result.summary["pixel_model"] = None
        result.summary["pixel_model_note"] = ("the run has no level captures (a job with levels = N) and no "
                                              "calibration brought a pixel model: counts linearised by exp(n theta)")
        return result
    win, report = match_windows(rec.triggers(), s, tolerance_us)
    # every setup capture, and the pairs all of whose passes have a window
    keep, complete = _complete_mask(s, win.capture)
    caps = win.capture[keep]
    edge_on, edge_off = win.t_start_us[keep], win.t_end_us[keep]

    sub = s.take(caps)
    lit = (sub.kernel_id == FLAT_ID) | (sub.kernel_id == LEVEL_ID)
    lit = lit if lit.any() else np.ones(caps.size, bool)
    refuse_synchronous(rec, edge_on[lit], edge_off[lit])  # counts that fall in bright light: named, not fitted
    warnings = []
    if levels_here:
        hot = hot_pixels(rec, win.t_start_us, win.t_end_us)
        if hot.any():
            warnings.append(f"left {describe_pixels(hot)} out of the pixel model's fit: they fire in the dark far "
                            "more than the rest (hot pixels)")
        fit = fit_on_edges(rec, edge_on, edge_off, sub, sched, region, origin_px, skip_us, cell_map=cell_map, hot=hot)
        source = "the run's own level captures"
    else:
        fit = pixel_model if isinstance(pixel_model, PixelFit) else PixelFit.from_dict(pixel_model)
        source = "the calibration"

    def fall_back(note, **about):  # exp(n theta) on the bench route, saying why
        out = _reconstruct_bench(rec, sched, region, origin_px, size=size, binarize_method=binarize_method,
                                skip_us=skip_us, length_us=length_us, crop=crop, flat_field=flat_field,
                                tolerance_us=tolerance_us, progress=progress)
        out.summary.update(pixel_model_from=None, pixel_model_rejected=True, pixel_model_note=note, **about)
        out.summary["warnings"] = warnings + [note] + out.summary["warnings"]
        return out

    # a model no camera has is not used; one that only misreads its own level captures is judged below, where
    # the level captures' own table may read the counts instead (else exp(n theta), saying why)
    if linearization not in ("auto", "model", "table"):
        raise EvtkError(f"linearization must be 'auto', 'model' or 'table', not {linearization!r}")
    refused = refuse_pixel_fit(fit, readback=False)
    # the level captures' statistics come with the fit, whether fitted here or by the calibration; their own
    # table needs no model, so a refused model can still leave it to read the counts (its delay in range)
    table_error = held_out_table_error(fit.statistics.light, fit.statistics.counts)
    table_ok = (table_error is not None and table_error < np.log(MAX_TABLE_ERROR) and np.isfinite(fit.blank)
                and fit.blank > 0)
    delay_ok = np.isfinite(fit.delay_us) and PHYSICAL_RANGE["light_delay_us"][0] <= fit.delay_us \
        <= PHYSICAL_RANGE["light_delay_us"][1]
    if refused is not None and not (linearization != "model" and table_ok and delay_ok):
        return fall_back(refused + "; the counts were linearised by exp(n theta)", pixel_model=None,
                         refused_pixel_model=fit.to_dict(), level_light_ratio=level_readback(fit).tolist())
    shift = int(round(fit.delay_us))  # the windows follow the light, shift us after the trigger edges
    start, end = _trim(edge_on + shift, edge_off + shift, skip_us, length_us, "matched")
    counts = accumulate(rec, Windows(start, end, np.arange(caps.size), "triggers matched to the schedule",
                                     win.dropped), region, progress=progress, times=True)
    record = _fitted_plan(sched, fit, sub, edge_on + shift, edge_off + shift, counts.region, origin_px, cell_map,
                          blur_px)
    counts = WindowCounts(counts.on, counts.off, Windows(start, end, sub.capture, counts.windows.source,
                                                         counts.windows.dropped),
                          counts.region, counts.events_used, counts.on_first_us, counts.on_last_us,
                          counts.stamp_period_us)
    if refused is None:
        result = reconstruct_counts(counts, record, skip_us=skip_us, length_us=length_us, size=size,
                                    binarize_method=binarize_method, linear=linear, crop=crop, deblur=deblur,
                                    flat_field=flat_field, timing=timing)
        ratios = result.summary.get("level_light_ratio")
        model_error = _level_error(ratios)
        misreads = bool(ratios) and not all(np.isfinite(r) and 1 / MAX_LEVEL_ERROR <= r <= MAX_LEVEL_ERROR
                                            for r in ratios)
    else:  # a model outside physical ranges: the table reads the counts, and the note says why
        ratios, model_error, misreads = None, float("inf"), True
    table_holds = table_ok and table_error < model_error
    if linearization == "table" or (linearization == "auto" and misreads and table_holds):
        curve = level_curve(fit.statistics.light, fit.statistics.counts, fit.blank)
        result = reconstruct_counts(counts, record, skip_us=skip_us, length_us=length_us, size=size,
                                    binarize_method=binarize_method, linear=linear, crop=crop, deblur=deblur,
                                    flat_field=flat_field, timing=False, curve=curve)
        result.summary.update(linearization="the level captures' table", level_table_error=table_error,
                              pixel_model_level_error=model_error)
        if misreads and linearization == "auto":
            why = (refused if refused is not None else
                   f"the fitted pixel model reads the level captures' light back as {min(ratios):.3g} to "
                   f"{max(ratios):.3g} times what it was: it does not describe these pixels")
            result.summary.update(pixel_model_rejected=True, pixel_model_note=(
                f"{why}; so the counts were linearised by the level captures' own table (a level left out of it "
                f"is read within a factor {np.exp(table_error):.3g})"))
        ratios = None
    if ratios and not all(np.isfinite(r) and 1 / MAX_LEVEL_ERROR <= r <= MAX_LEVEL_ERROR for r in ratios):
        # the model reads the run's own level captures back wrong: it does not describe these pixels
        return fall_back(f"the fitted pixel model reads the level captures' light back as {min(ratios):.3g} to "
                         f"{max(ratios):.3g} times what it was: it does not describe these pixels, so the counts "
                         "were linearised by exp(n theta)", pixel_model=fit.to_dict(), level_light_ratio=ratios)
    result.summary.update(match=report, pairs_left_out=sorted(_all_pairs(s) - complete), pixel_model_from=source,
                          response_origin_px=[float(v) for v in origin_px], pixel_model=fit.to_dict(),
                          level_captures=int(np.sum(sub.kernel_id == LEVEL_ID)), windows_after_edges_us=shift)
    result.summary["warnings"] = warnings + result.summary.get("warnings", [])
    return result


def _level_error(ratios) -> float:
    """The median misreading ``|log(read / true)|`` of the level captures' light (inf without any)."""
    r = np.asarray(ratios if ratios else [], np.float64)
    r = r[np.isfinite(r) & (r > 0)]
    return float(np.median(np.abs(np.log(r)))) if r.size and r.size == len(ratios) else float("inf")


def held_out_table_error(level_light: npt.ArrayLike, level_counts: npt.ArrayLike) -> float | None:
    """How well the level captures' table reads a level it did not see: each interior level (not the dimmest
    nor the brightest, which a table can only extrapolate to) left out, read through the table of the others
    (:func:`~evtk.reconstruct.linearize.level_table_values`).

    Parameters
    ----------
    level_light, level_counts : array_like, shape (levels,)
        The level captures' light (response units) and mean net counts.

    Returns
    -------
    float or None
        The median ``|log(read / true)|`` over the levels left out; None with
        fewer than three levels of light.
    """
    light = np.asarray(level_light, np.float64)
    counts = np.asarray(level_counts, np.float64)
    order = np.argsort(light, kind="stable")
    light, counts = light[order], counts[order]
    if np.sum(light > 0) < 3:
        return None
    errs = []
    for j in range(1, light.size - 1):
        rest = np.arange(light.size) != j
        try:
            read = float(level_table_values(counts[j], counts[rest], light[rest]))
        except EvtkError:
            return None
        errs.append(abs(np.log(read / light[j])) if read > 0 and light[j] > 0 else np.inf)
    return median(errs)


#: How long before the trigger edges the pixel model's statistics are first counted (µs): a light that comes a
#: little before its edge (a late trigger) still shows its whole rise, and the fit measures the delay either way.
LEAD_US = 20

#: The range (low, high) of each fitted value a pixel model may hold (:func:`refuse_pixel_fit`): a fit beyond
#: them explains the level captures with a pixel no camera has (threshold 7.9, a dark time constant of 347 s, a
#: light 100 µs before its trigger edge, all seen on benches the model did not describe).
PHYSICAL_RANGE = {
    "theta_on": (0.02, 1.5),
    "theta_off": (0.02, 1.5),
    "tau_min_us": (1.0, 1e4),
    "tau_dark_us": (1.0, 1e6),
    "light_delay_us": (-float(LEAD_US), MAX_DELAY_US),
}


def level_readback(fit: PixelFit) -> np.ndarray:
    """The light each level step's mean count reads back through the fitted model, over the light it had.

    The model's mean count (:meth:`PixelFit.mean_counts`, made monotonic) is inverted on a grid up to twice
    the brightest step; 1 where the model describes the pixels. A count beyond the model's reach reads 2x.

    Parameters
    ----------
    fit : PixelFit
        The fitted model, with the level statistics it was fitted to.

    Returns
    -------
    ndarray
        One ratio per level step of ``fit.statistics``.
    """
    st = fit.statistics
    light = np.asarray(st.light, np.float64)
    if light.size == 0:
        return np.zeros(0)
    grid = np.linspace(0.0, 2.0 * float(light.max()), 81)
    curve = np.maximum.accumulate(np.nan_to_num(fit.mean_counts(grid)))
    read = np.interp(np.asarray(st.counts, np.float64), curve, grid)
    return read / np.maximum(light, 1e-12)


def refuse_pixel_fit(fit: PixelFit, readback: bool = True) -> str | None:
    """Why a fitted pixel model must not be used, with what to change; None when it may.

    Refused: a value outside :data:`PHYSICAL_RANGE`, or (with ``readback``) a model that reads its own level
    captures back (:func:`level_readback`) more than :data:`MAX_LEVEL_ERROR` times off, either way.

    Parameters
    ----------
    fit : PixelFit
        The fitted model, with the level statistics it was fitted to.
    readback : bool
        Also refuse a model that misreads its own level captures (``evtk calibrate`` saves no such model; the
        reconstruction judges it itself, where the level captures' table may take over).

    Returns
    -------
    str or None
        The reason and what to change, or None.
    """
    d = fit.to_dict()
    problems = [f"{name} {d[name]:.4g} (a camera's lies within {lo:g} to {hi:g})"
                for name, (lo, hi) in PHYSICAL_RANGE.items() if not (np.isfinite(d[name]) and lo <= d[name] <= hi)]
    ratios = level_readback(fit) if readback else np.zeros(0)
    if ratios.size and not np.all((ratios >= 1 / MAX_LEVEL_ERROR) & (ratios <= MAX_LEVEL_ERROR)):
        problems.append(f"it reads the level captures' light back as {ratios.min():.3g} to {ratios.max():.3g} "
                        "times what it was")
    if not problems:
        return None
    return ("the pixel model fitted to the level captures was refused: " + "; ".join(problems) + ". What to "
            "change: check that the camera reads out asynchronously and its trigger edges come with the light "
            "(a light before its edge by more than 20 us is cut off), show more level steps spanning the job's "
            "light (levels = 6 or more), with windows long enough for the brightest (window_us) and dark time "
            "for the decay (settle_us)")

#: A fitted delay of the light this much (µs) or more off the one the first pass took has the statistics counted
#: and fitted again in windows that follow the light, up to :data:`RECOUNT_ROUNDS` times.
RECOUNT_DELAY_US = 1.0
RECOUNT_ROUNDS = 3


def fit_on_edges(rec: Any, edge_on_us: npt.ArrayLike, edge_off_us: npt.ArrayLike, sub: Schedule, sched: Plan,
                 region: Sequence[int], origin_px: Sequence[float], skip_us: int = 0,
                 cell_map: CellMap | None = None, hot: np.ndarray | None = None) -> PixelFit:
    """:func:`fit_pixel_model` on the level captures of ``sub`` (a schedule of captures whose trigger edges are
    ``edge_on_us``/``edge_off_us``), the flat fields giving the pixels' threshold spread.

    The captures are counted (with event times) in windows from
    :data:`LEAD_US` before their edges. The fit's ``delay_us`` is the
    light's delay after the edges (0 where the times cannot tell: a frame
    readout). The first pass (:func:`_fit_on_counts`) takes the light to
    come with the edges to time the refractory period from the gaps; where
    the delay comes out :data:`RECOUNT_DELAY_US` or more from that, the
    statistics are counted and fitted again in windows that start with the
    light. ``hot`` (a sensor mask, :func:`~evtk.reconstruct.fit.hot_pixels`) leaves pixels out of the fit.

    Parameters
    ----------
    rec : Recording
        The open recording.
    edge_on_us, edge_off_us : array_like of int
        The rising and falling trigger edge of each capture of ``sub``, µs on the recording's clock.
    sub : Schedule
        The captures the edges belong to (its level and flat-field captures are used, the rest left out).
    sched : Plan
        The run: its kernels and features (the response's interior), bench (cells per pixel) and timing
        (``window_us``, ``settle_us``).
    region : sequence of int
        ``(x0, x1, y0, y1)``: the sensor pixels counted (half-open).
    origin_px : sequence of float
        ``(x, y)``: the sensor pixel that sees cell (0, 0) of the full response.
    skip_us : int
        Microseconds left out at the start of every window, >= 0.
    cell_map : CellMap, optional
        The calibrated map from cells to pixels (rotation, tilt, distortion); None: ``origin_px`` and the bench's
        nominal scale.
    hot : numpy.ndarray, optional
        bool, shape (height, width) of the sensor: pixels left out of the fit.

    Returns
    -------
    PixelFit
        The fitted model, its refractory period timed from the brightest level's ON-event gaps and
        ``delay_us`` the light's delay after the edges.

    Raises
    ------
    EvtkError
        When the captures hold no level captures, too few steps or too little light to fit, no interior pixel,
        or counts larger than the memory budget.
    """
    use = (sub.kernel_id == LEVEL_ID) | (sub.kernel_id == FLAT_ID)
    sub = sub.take(np.flatnonzero(use))
    edge_on, edge_off = np.asarray(edge_on_us)[use], np.asarray(edge_off_us)[use]

    def fit_from(lead_us, delay_us):  # windows lead_us before the edges, the light taken delay_us after them
        a, b = _trim(edge_on - lead_us, edge_off - lead_us, skip_us, None, "matched")
        counts = accumulate(rec, Windows(a, b, np.arange(sub.capture.size), "level and flat-field captures"),
                            region, times=True)
        return _fit_on_counts(rec, counts, sub, edge_off - lead_us, sched, origin_px, skip_us, cell_map, lead_us,
                              delay_us, hot)

    fit, assumed = fit_from(LEAD_US, 0.0), 0.0
    for _ in range(RECOUNT_ROUNDS):
        if abs(fit.delay_us - assumed) < RECOUNT_DELAY_US:
            break
        assumed = fit.delay_us
        fit = fit_from(-int(round(assumed)), assumed)
    return fit


def _fit_on_counts(rec, counts, sub, t_off_us, sched, origin_px, skip_us, cell_map, lead_us, delay_us,
                   hot=None) -> PixelFit:
    """:func:`fit_pixel_model` on accumulated counts (with times) of the captures ``sub`` (a schedule of the
    windows counted, ``t_off_us`` their ends, ``lead_us`` before the falling edges), the light taken to follow
    the edges by ``delay_us`` until its delay is fitted."""
    kh, kw = sched.kernels.shape[1:]
    fh, fw = sched.features.shape[1:]
    bench = sched.bench
    inside = interior_pixels(counts.region, origin_px, bench.kernel_step_cells / bench.pixel_cells, (kh, kw),
                             (fh, fw), cell_map=cell_map)
    if hot is not None:
        x0, x1, y0, y1 = counts.region
        inside = inside & ~np.asarray(hot, bool)[y0:y1, x0:x1]
    flat = sub.kernel_id == FLAT_ID
    gain = None
    if flat.any():
        net_flat = counts.on[flat].astype(np.float64) - counts.off[flat]
        gain = neighbourhood_flat_gain(net_flat)
    is_level = sub.kernel_id == LEVEL_ID
    stats = level_statistics(counts, is_level, sub.level, inside, gain)
    off_mean, off_counts = level_off_times(rec, np.asarray(t_off_us)[is_level], sub.level[is_level],
                                           sched.settle_us, counts.region, inside, counts.stamp_period_us)
    stats = dataclasses.replace(stats, off_mean_us=off_mean, off_counts=off_counts)
    spread = float(np.clip(np.std(gain[inside]) if gain is not None else 0.05, 0.005, 0.3))
    # event times on a frame readout's grid are too coarse to time a pixel by: fit the counts and the decay
    fine = counts.stamp_period_us is None or counts.stamp_period_us <= MAX_TIMING_STAMP_US
    bright = is_level & (sub.level == sub.level[is_level].max()) if is_level.any() else is_level
    t_on = np.asarray(t_off_us)[bright] - int(sched.window_us)
    gaps = on_gaps(rec, t_on, np.asarray(t_off_us)[bright], counts.region, inside) if fine else np.zeros(0)
    # first timed by the first ON events, which no refractory period delays, the light taken to come delay_us
    # after the edges, so that the gaps can measure the period
    fit = fit_pixel_model(stats, sched.window_us, sched.settle_us, skip_us, spread=spread, times=fine,
                          lead_us=lead_us, delay_us=delay_us)
    refractory, resolved = fit_refractory(fit, stats.light.max(), gaps, skip_us)
    if fine:  # then timed half-way up the rise as well, with the period, and the light's delay fitted
        orders = rise_orders(stats.counts)
        t_lv = np.asarray(t_off_us)[is_level]
        rise = level_rise_times(rec, t_lv - int(sched.window_us) + int(skip_us), t_lv, sub.level[is_level], orders,
                                counts.region, inside)
        stats = dataclasses.replace(stats, rise_order=orders, rise_us=rise)
    if fine or resolved:  # a period that shows in the gaps limits the bright steps' counts too
        fit = fit_pixel_model(stats, sched.window_us, sched.settle_us, skip_us, refractory_us=refractory,
                              spread=spread, times=fine, lead_us=lead_us, delay_us=delay_us)
    return dataclasses.replace(fit, refractory_bound_us=refractory_bound(gaps), refractory_resolved=resolved)

