"""What a reconstruction counts: its plan (or none), windows and region (:func:`plan`), light enough for the
fixed windows' route (the plan's heavier modules load only for a recording that carries a simulation record)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from ..errors import EvtkError
from ..limits import require_memory
from ..plan import METADATA_KEY
from .windows import Windows, windows_from_schedule, windows_from_triggers, windows_periodic

if TYPE_CHECKING:
    from ..plan import Plan, SimulationRecord

__all__ = ["plan", "window_bytes", "has_record"]


def has_record(metadata: dict | None) -> bool:
    """Whether a recording's metadata holds a simulation record (without reading it).

    Parameters
    ----------
    metadata : dict or None
        The recording's metadata.

    Returns
    -------
    bool
        True when it has the :data:`evtk.plan.METADATA_KEY` entry.
    """
    return (metadata or {}).get(METADATA_KEY) is not None


def plan(rec: Any, window: str | tuple = "schedule", skip_us: int = 0, length_us: int | None = None,
         region: tuple | None = None, check_memory: bool = True,
         record: SimulationRecord | Plan | None = None) -> tuple[SimulationRecord | Plan | None, Windows, tuple]:
    """What :func:`reconstruct` will count: the record (or plan), the windows and the region.

    Parameters
    ----------
    rec : Recording
        The open recording.
    window : "schedule", "triggers" or ("period", period_us)
        Where the windows come from.
    skip_us, length_us : int
        Shorten or delay every window.
    region : tuple, optional
        ``(x0, x1, y0, y1)``; default the record's response region (a plan's ``region``), else the whole
        sensor.
    check_memory : bool
        Require the counts of every window at once to fit the memory budget
        (:func:`evtk.limits.require_memory`).
    record : SimulationRecord or Plan, optional
        Takes the place of the one in the recording's metadata: a simulated run's record, or its plan (the
        schedule's times on the recording's clock).

    Returns
    -------
    tuple
        ``(simulation record or the plan given, or None; Windows; region)``.
    """
    if record is not None or has_record(rec.metadata):
        from ..plan import Plan, SimulationRecord

        sim = record if record is not None else SimulationRecord.from_metadata(rec.metadata)
    else:
        sim = None
    if window == "schedule":
        if sim is None:
            raise EvtkError("the recording carries no capture schedule: use window='triggers' or a period")
        win = windows_from_schedule(sim.schedule if isinstance(sim, Plan) else sim, skip_us, length_us)
    elif window == "triggers":
        win = windows_from_triggers(rec.triggers(), skip_us, length_us)
    elif isinstance(window, tuple) and len(window) == 2 and window[0] == "period":
        info = rec.info()
        end = None if info["t_end_us"] is None else info["t_end_us"] + 1
        win = windows_periodic(info["t_start_us"], end, window[1], skip_us, length_us, events=info["events"])
    else:
        raise EvtkError(f"window must be 'schedule', 'triggers' or ('period', US), not {window!r}")
    if region is None:
        region = (sim.region if isinstance(sim, Plan) else sim.response_region) if sim is not None else None
    if region is None:
        region = (0, rec.sensor_size[0], 0, rec.sensor_size[1])
    x0, x1, y0, y1 = (int(v) for v in region)
    if check_memory:
        require_memory(len(win) * window_bytes(region, sim is not None),
                       f"counting {len(win):,} windows over {max(0, x1 - x0)}x{max(0, y1 - y0)} pixels")
    return sim, win, tuple(region)


def window_bytes(region: tuple, simulated: bool) -> int:
    """Estimated peak bytes a window costs a reconstruction over a region.

    Per pixel: ON and OFF counts (int32), with a simulation record the first
    and last ON times, and the float64 stages after them (a minute of 10 ms
    windows over 320x240 peaked at 53 bytes a window-pixel without a record:
    measured, killed at 24 GB).

    Parameters
    ----------
    region : tuple
        ``(x0, x1, y0, y1)``.
    simulated : bool
        With a simulation record (event times are kept too).

    Returns
    -------
    int
        Bytes.
    """
    x0, x1, y0, y1 = (int(v) for v in region)
    return max(0, x1 - x0) * max(0, y1 - y0) * (80 if simulated else 64)
