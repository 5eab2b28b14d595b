"""What a run is: the plan the bench, the simulator and the reconstruction share.

A run of the accelerator is described by

* **the capture schedule** (:class:`Schedule`): which kernel and features pattern each capture shows, which
  +/- pass, when (µs), and the setup captures beside the job's (flat fields :data:`FLAT_ID`, calibration
  dots :data:`DOTS_ID`, level steps :data:`LEVEL_ID`); read from a ``schedule.json`` by the checked
  :func:`read_schedule`, and written with the patterns by :func:`evtk.patterns.write_patterns`;
* **the patterns** themselves and the bench geometry they are shown on;
* **the camera's placement**: where the response's cells fall on the sensor (``response_origin_px`` and the
  bench's step, or a whole :class:`~evtk.optics.camera.CellMap`, :meth:`SimulationRecord.placement`);
* **the pixel model** (:class:`PixelModel`: a :class:`~evtk.sensor.SensorModel`, with the photon rates that put
  light in its units);
* **the light's delay** after each trigger edge (``light_delay_us``).

:class:`Plan` holds what is known of it, as :func:`evtk.reconstruct.reconstruct` takes it: a bench run's
(:meth:`Plan.read` of its ``schedule.json``, with a calibration's placement and pixel model), or a simulated
one's (:meth:`Plan.from_record`, the oracle). :class:`SimulationRecord` holds all of it, checked, as the
simulator records it in a recording's metadata under :data:`METADATA_KEY` (``docs/formats/schedule.md``). The
simulator (:mod:`evtk.simulate`) and the calibration (:mod:`evtk.calibrate`) produce plans; the reconstruction
(:mod:`evtk.reconstruct`) consumes them and imports nothing from the simulator.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from .._lazymod import lazy_names

# names load with their module on first use (PEP 562): the schedule's alone does not pull the optics and the
# pixel model (numba, scipy), so that reading a schedule or cutting windows stays light
_WHERE = {
    **dict.fromkeys(["PixelModel", "Plan", "as_plan"], "core"),
    **dict.fromkeys(["RECORD_SPECS", "SimulationRecord"], "record"),
    **dict.fromkeys(["DOT_MARKER_MIN", "DOTS_ID", "FLAT_ID", "LEVEL_ID", "SCHEDULE_SPECS",
                     "CaptureCounts", "Schedule", "check_patterns", "check_schedule", "default_features", "dot_grid",
                     "level_kernel", "level_steps", "load_patterns", "read_schedule", "sign_pass", "split_passes"],
                    "schedule"),
}

#: Key of the simulation record in a recording's evtk metadata (here, not with the schedule: whether a recording
#: carries a record is asked of every recording, fixed windows too, which need no schedule).
METADATA_KEY = "simulation"

if TYPE_CHECKING:
    from .core import PixelModel, Plan, as_plan
    from .record import RECORD_SPECS, SimulationRecord
    from .schedule import (
        DOT_MARKER_MIN,
        DOTS_ID,
        FLAT_ID,
        LEVEL_ID,
        SCHEDULE_SPECS,
        CaptureCounts,
        Schedule,
        check_patterns,
        check_schedule,
        default_features,
        dot_grid,
        level_kernel,
        level_steps,
        load_patterns,
        read_schedule,
        sign_pass,
        split_passes,
    )


__getattr__, __dir__ = lazy_names(__name__, _WHERE)


__all__ = [
    "Plan", "PixelModel", "as_plan", "SimulationRecord", "RECORD_SPECS",
    "Schedule", "CaptureCounts", "read_schedule", "check_schedule",
    "check_patterns", "SCHEDULE_SPECS", "METADATA_KEY", "FLAT_ID", "DOTS_ID", "LEVEL_ID", "DOT_MARKER_MIN",
    "split_passes", "sign_pass", "level_kernel", "level_steps", "dot_grid", "default_features", "load_patterns",
]
