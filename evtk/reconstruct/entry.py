"""The one entry: :func:`reconstruct` a recording by the route its plan allows."""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Any

from ..errors import EvtkError
from .options import ReconstructOptions
from .result import Reconstruction
from .route import has_record

if TYPE_CHECKING:
    from ..plan import Plan, SimulationRecord

__all__ = ["reconstruct", "LINEARIZATIONS", "ORACLE_ROUTE"]

#: How a bench plan's counts may become light (:func:`reconstruct`'s ``linearization``).
LINEARIZATIONS = ("auto", "model", "table", "exp(n theta)")

#: What a summary's ``route`` says of the oracle (a simulated run's own pixel model and placement), wherever it is
#: taken (``evtk reconstruct --oracle``, ``evtk enob`` on a simulated recording).
ORACLE_ROUTE = "oracle: the simulation record's own pixel model and placement"


def reconstruct(rec: Any, plan: Plan | SimulationRecord | None = None, options: ReconstructOptions | None = None, *,
                progress: Any = None, chunk_events: int = 4_000_000, linearization: str = "auto",
                tolerance_us: float | None = None, keep_pixels: bool = True, **settings: Any) -> Reconstruction:
    """The whole pipeline on an open recording, by the route its plan allows.

    The route follows from what the plan holds:

    * **no plan**: the recording's own simulation record when it carries one (the oracle: the simulator's
      pixel model inverted, refined by the event times, each pixel's threshold from the flat fields), else
      windows only (``window="triggers"`` or a period): net counts ON - OFF, nothing saying how counts map to
      light (``exp(n theta)`` where the options give a ``theta``);
    * **a plan with a pixel model** (:meth:`evtk.plan.Plan.from_record`, or a
      :class:`~evtk.plan.SimulationRecord`): the oracle, the plan's pixel model inverted on the windows of its
      schedule;
    * **a bench plan** (:meth:`evtk.plan.Plan.read` of a ``schedule.json``, with a calibration's placement and
      pixel model): trigger windows matched to the schedule; a pixel model (the plan's, or one fitted to the
      run's own level captures) inverted; without one, or when it misreads the level captures, the level
      captures' own table or ``exp(n theta)`` with each pixel's threshold from the flat fields, saying why in
      the summary.

    Parameters
    ----------
    rec : Recording
        The open recording (events and, for a bench plan, the DMD's trigger edges).
    plan : Plan or SimulationRecord, optional
        What the run is; None reads the recording's own record.
    options : ReconstructOptions, optional
        The settings (windows, size, binarisation, linear, theta, crop, region, deblur, flat field, timing);
        default :class:`ReconstructOptions`'s.
    progress : callable, optional
        Called with the share of the events counted.
    chunk_events : int
        Events read at a time (the oracle's route).
    linearization : {"auto", "model", "table", "exp(n theta)"}
        A bench plan's linearisation: "auto" (default) the pixel model while it reads the level captures back,
        else their table, else ``exp(n theta)``; "model" and "table" ask for one; "exp(n theta)" uses no pixel
        model at all (``theta`` from the options, default 0.2). Only "auto" goes with a plan that holds a pixel model.
    tolerance_us : float, optional
        How far a trigger window's start may be from its capture's (:func:`~evtk.reconstruct.match_windows`).
    keep_pixels : bool
        Keep every window's counts and per-pixel values (default). ``False`` keeps only the responses of windows
        without a schedule (``window="triggers"`` or a period, no simulation record): counted a batch at a time,
        in memory bounded by the responses and one batch.
    **settings
        Single settings of :class:`ReconstructOptions` (``window=``, ``size=``, ...), taking the place of the
        ``options``' own.

    Returns
    -------
    Reconstruction
        The responses, their binarisation, the counts and a :class:`~evtk.reconstruct.ReconstructionSummary`
        (``linearization`` says which was used).

    Raises
    ------
    EvtkError
        When ``rec`` is not an open recording (in-memory events included), a setting is unknown or does not
        go with the plan's route, or the work would not fit the memory budget.

    Examples
    --------
    >>> import evtk, tempfile, os
    >>> from evtk.simulate import Simulation
    >>> path = os.path.join(tempfile.mkdtemp(), "r.h5")
    >>> _ = Simulation([[1, 0], [0, 1]], [[0, 1, 1], [1, 0, 1], [1, 1, 0]], repeat=2, seed=1).write(path)
    >>> with evtk.open(path) as rec:
    ...     result = reconstruct(rec, size=(4, 4))
    >>> result.responses.shape, result.summary.linearization
    ((2, 4, 4), 'pixel model and event times')
    """
    if not (hasattr(rec, "metadata") and hasattr(rec, "iter_events")):
        what = "in-memory Events" if type(rec).__name__ == "Events" else type(rec).__name__
        raise EvtkError(f"reconstruct takes an open recording (with evtk.open(path) as rec: ...), not {what}; "
                        "events in memory can be written first (evtk.write_events), or their fixed windows "
                        "counted with evtk.reconstruct.fixed.fixed_responses")
    opts = options if options is not None else ReconstructOptions()
    if settings:
        unknown = sorted(set(settings) - {f.name for f in dataclasses.fields(ReconstructOptions)})
        if unknown:
            raise EvtkError(f"reconstruct takes no setting {', '.join(unknown)}")
        opts = dataclasses.replace(opts, **settings)
    if linearization not in LINEARIZATIONS:
        raise EvtkError(f"linearization must be one of {', '.join(LINEARIZATIONS)}, not {linearization!r}")
    if (plan is None and not keep_pixels and linearization == "auto" and opts.window != "schedule"
            and not has_record(rec.metadata)):
        # windows that stand alone, responses only: counted with numpy (no compiler, no scipy) when it can
        from .fixed import fixed_responses, fixed_supported
        from .route import plan as windows_of

        stages = {k: v for k, v in opts.kwargs().items() if k not in ("window", "region")}
        if fixed_supported(stages):
            window: Any = opts.window  # (checked by plan)
            _, win, pixels = windows_of(rec, window, opts.skip_us, opts.length_us, opts.region, check_memory=False)
            return fixed_responses(rec, win, pixels, chunk_events=chunk_events, progress=progress, **stages)
    from ..plan import Plan, SimulationRecord
    from .bench import _reconstruct_bench
    from .calibrated import _reconstruct_calibrated, nominal_placement
    from .pipeline import _reconstruct_record

    if plan is not None and not isinstance(plan, (Plan, SimulationRecord)):
        hint = (f"; give windows as window={plan!r}" if isinstance(plan, (str, tuple)) else "")
        raise EvtkError(f"plan must be an evtk.plan.Plan or a SimulationRecord, not {type(plan).__name__}{hint}")
    # a simulated run's plan holds its pixel model (Plan.from_record): the oracle, on the schedule's own windows
    if plan is None or isinstance(plan, SimulationRecord) or plan.pixels is not None:
        if linearization != "auto":
            raise EvtkError("a simulation record's plan linearises by its own pixel model: leave linearization out")
        return _reconstruct_record(rec, progress=progress, chunk_events=chunk_events, record=plan,
                                   keep_pixels=keep_pixels, **opts.kwargs())
    if not keep_pixels:
        raise EvtkError("keep_pixels=False is for windows without a schedule; a bench plan's route keeps its pixels")
    if opts.window != "schedule" or (opts.theta is not None and linearization != "exp(n theta)"):
        raise EvtkError("a bench plan's windows are the trigger edges matched to its schedule, linearised by its "
                        "pixel model: leave out the window and theta settings (theta goes with "
                        "linearization='exp(n theta)')")
    region = plan.region if plan.region is not None else opts.region
    common = dict(size=opts.size, binarize_method=opts.binarize_method, skip_us=opts.skip_us,
                  length_us=opts.length_us, crop=opts.crop, flat_field=opts.flat_field, tolerance_us=tolerance_us,
                  progress=progress)
    if linearization == "exp(n theta)":
        if not opts.linear:
            raise EvtkError("linearization='exp(n theta)' linearises: leave linear=False out")
        if region is None:
            region = nominal_placement(plan)[0]
        return _reconstruct_bench(rec, plan, region, plan.origin_px, cell_map=plan.cell_map,
                                  theta=0.2 if opts.theta is None else float(opts.theta), **common)
    return _reconstruct_calibrated(rec, plan, region, plan.origin_px, deblur=opts.deblur, timing=opts.timing,
                                   linear=opts.linear, pixel_model=plan.pixel_model, cell_map=plan.cell_map,
                                   blur_px=plan.blur_px, own_levels=plan.own_levels, linearization=linearization,
                                   **common)
