"""Which reconstruction a recording gets: the calibrated route by default, the simulator's oracle on request.

:func:`reconstruct_recording` is what ``evtk reconstruct`` and
``evtk batch reconstruct`` run:

* with a bench schedule (``schedule.json``), or on a simulated recording
  (whose record stands in for the schedule file: patterns, timing, bench
  geometry, nothing of the pixels), the calibrated route:
  :func:`evtk.reconstruct.reconstruct` on the bench's :class:`~evtk.plan.Plan`
  placed by a calibration, by the run's own dot captures, or by the bench
  geometry: trigger windows, a pixel model (the calibration's, or fitted to
  the run's own level captures);
* with ``oracle=True``, :func:`evtk.reconstruct.reconstruct` on the plan read
  from the simulation record (:meth:`evtk.plan.Plan.from_record`: its own
  pixel model and placement, what a perfect calibration would give; not
  available on a bench);
* with fixed windows (triggers or a period) or a fixed ``theta``, the plain
  pipeline, :func:`evtk.reconstruct.reconstruct`.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any, cast

from .errors import EvtkError
from .reconstruct import ReconstructOptions, reconstruct
from .reconstruct.route import has_record
from .settings import check_origin, check_region

if TYPE_CHECKING:  # the calibrated route's modules (the optics, numba, scipy) load only when it is taken
    from .calibrate import Calibration
    from .io.base import BaseRecording
    from .plan import Plan
    from .reconstruct import Reconstruction

__all__ = ["reconstruct_recording"]


def reconstruct_recording(rec: BaseRecording, oracle: bool = False,
                          schedule: Plan | dict[str, Any] | str | os.PathLike[str] | None = None,
                          calibration: Calibration | None = None, origin_px: Sequence[float] | None = None,
                          progress: Callable[[int], object] | None = None, keep_pixels: bool = True,
                          **options: Any) -> Reconstruction:
    """Reconstruct ``rec`` by the route its inputs allow (see the module docstring).

    Parameters
    ----------
    rec : evtk.io.base.BaseRecording
        An open recording (:func:`evtk.io.open`), of a bench run or simulated by evtk.
    oracle : bool
        Use the simulation record's pixel model and placement (simulated
        recordings only); the summary says ``"oracle": true``.
    schedule : Plan, dict, str or os.PathLike, optional
        A bench run's ``schedule.json`` (:func:`evtk.patterns.write_patterns`), or its plan.
    calibration : Calibration, optional
        Where the response lies (:func:`evtk.calibrate.calibrate`); else
        ``options["region"]`` and ``origin_px``, else the run's own dot
        captures, else the bench geometry.
    origin_px : sequence of two float, optional
        Sensor pixel of the response's cell (0, 0), with ``options["region"]``;
        checked to be two finite numbers near the sensor.
    progress : callable, optional
        Called with the captures done.
    keep_pixels : bool
        Keep every window's counts and per-pixel values (default); ``False`` keeps the responses alone of fixed
        windows on a recording without a simulation record (:func:`evtk.reconstruct.reconstruct`'s
        ``keep_pixels``), in memory bounded by them and one batch of windows. Other routes keep their pixels.
    **options : Any
        :class:`~evtk.reconstruct.ReconstructOptions` fields (``size``, ``window``, ``skip_us``, ``region``, ...).

    Returns
    -------
    Reconstruction
        The result; its summary says the route and the placement.

    Raises
    ------
    EvtkError
        When the inputs allow no route: the oracle asked of a recording with no simulation record (or with a
        schedule or calibration), no schedule for a recording that is not simulated (and no fixed windows), a
        calibration of another sensor or response size, fixed windows with the calibrated route, or an
        ``origin_px`` or region off the sensor; and whatever the route itself raises.
    """
    opts = ReconstructOptions(**options)
    sensor = cast("tuple[int, int]", rec.sensor_size)  # evtk.io.open sizes every recording's sensor
    fixed = opts.window != "schedule" or opts.theta is not None
    if fixed and not oracle and schedule is None and calibration is None and origin_px is None and not has_record(
            rec.metadata):  # fixed windows alone: nothing of the plan, the calibration or the optics is needed
        result = reconstruct(rec, None, opts, progress=progress, keep_pixels=keep_pixels)
        result.summary.route = "fixed windows"
        return result
    from .calibrate import calibrate
    from .plan import DOTS_ID, Plan, SimulationRecord, as_plan
    from .reconstruct import ORACLE_ROUTE, schedule_of_record

    record = SimulationRecord.from_metadata(rec.metadata)
    if calibration is not None and tuple(calibration.sensor_size) != tuple(sensor):
        raise EvtkError(f"the calibration is of a {calibration.sensor_size[0]}x{calibration.sensor_size[1]} sensor, "
                        f"the recording of a {sensor[0]}x{sensor[1]} one")
    if oracle:
        if record is None:
            raise EvtkError("the recording carries no simulation record: the oracle is for recordings evtk simulated")
        if schedule is not None or calibration is not None:
            raise EvtkError("the oracle reads the simulation record: leave out the schedule and the calibration")
        result = reconstruct(rec, Plan.from_record(record), opts, progress=progress)
        result.summary.route = ORACLE_ROUTE
        result.summary.oracle = True
        return result
    if schedule is None and record is None and not fixed:
        raise EvtkError("the recording carries no simulation record and no schedule was given: give the bench run's "
                        "schedule.json (evtk reconstruct --schedule S), or reconstruct fixed windows (--window "
                        "triggers, --window period:US)")
    if schedule is None and (record is None or fixed):
        if calibration is not None or origin_px is not None:
            raise EvtkError("a calibration or response origin goes with a schedule (a bench run) or a simulated run")
        result = reconstruct(rec, None, opts, progress=progress, keep_pixels=keep_pixels or record is not None)
        result.summary.route = "fixed windows" if fixed else "windows only: no schedule"
        return result
    if fixed:
        raise EvtkError("the calibrated route takes its windows from the trigger edges matched to the schedule: "
                        "leave out the window and theta settings, or ask for the oracle")
    if origin_px is not None:
        origin_px = check_origin("the response origin", "origin_px", origin_px, sensor)
    if opts.region is not None and schedule is not None:
        check_region("the region", "region", opts.region, sensor)
    if schedule is not None:
        sched = as_plan(schedule)
    elif record is not None:
        sched = schedule_of_record(record)
    else:  # refused or reconstructed by fixed windows above
        raise EvtkError("the recording carries no simulation record and no schedule was given")
    # the plan placed by a calibration, by the run's own dot captures, by hand (region, origin) or by the bench
    run_plan = sched.replace(region=None if opts.region is None else tuple(opts.region),
                             origin_px=None if origin_px is None else tuple(origin_px))
    placed, own = "given", True
    told = []  # what the calibration assumed or left out, said again with the result
    if calibration is not None:
        (kh, kw), (fh, fw) = sched.kernels.shape[1:], sched.features.shape[1:]
        if list(calibration.response_shape) != [fh + kh - 1, fw + kw - 1]:
            raise EvtkError(f"the calibration is of a {calibration.response_shape[0]}x{calibration.response_shape[1]} "
                            f"response, this run's is {fh + kh - 1}x{fw + kw - 1}: calibrate with a run of the same "
                            "kernel and features sizes")
        run_plan, placed = calibration.place(sched), "calibration"
        told = list(calibration.warnings)
    elif opts.region is None and origin_px is None:
        if (sched.schedule.kernel_id == DOTS_ID).any():
            # the run calibrates itself; its pixel model, fitted to its own level captures there, is not fitted again
            cal = calibrate(rec, sched)
            own = cal.pixel_model is None
            run_plan, placed = cal.place(sched, own_levels=own), "the run's own dot captures"
            # fitted again below when the calibration kept no model: what it says of the fit is said again there
            told = [w for w in cal.warnings if not (own and "pixel model" in w)]
        else:
            placed = "the bench geometry"
    result = reconstruct(rec, run_plan, opts, progress=progress)
    summary = result.summary
    if not own and summary.pixel_model_from:
        summary.pixel_model_from = "the run's own level captures"
    fitted_to = {"the run's own level captures": "the run's level captures",
                 "the calibration": "the calibration run's level captures"}.get(summary.pixel_model_from or "")
    summary.route = "calibrated: " + (
        f"a pixel model fitted to {fitted_to}" if fitted_to else
        "exp(n theta), the fitted pixel model misreads the level captures" if summary.pixel_model_rejected
        else "exp(n theta), no level captures to fit a pixel model to")
    summary.placement = placed
    summary.warnings = told + (summary.warnings or [])
    summary.oracle = False
    return result
