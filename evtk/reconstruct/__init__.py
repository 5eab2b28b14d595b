"""From a recording to the responses the device computed: capture windows and event counts.

The stages, each a function usable alone:

1. :class:`Windows`: when each capture's pattern was on, from the schedule a
   simulated recording carries (:func:`windows_from_schedule`), from the DMD's
   trigger edges of a bench recording (:func:`windows_from_triggers`), or at a
   fixed period (:func:`windows_periodic`); any of them shortened or delayed
   (``skip_us``, ``length_us``) to leave out the pixels' settling.
2. :func:`accumulate`: ON and OFF counts per pixel and window in one pass over
   the events (numba), each window found by binary search on the sorted time
   stamps, streamed chunk by chunk from a recording larger than memory.
3. :func:`linearize`: counts back to relative intensity through the pixel
   model (a net rise of ``n`` thresholds is a factor ``exp(n * theta)``;
   :func:`linearize_by_model` inverts a simulated recording's own pixel
   model, and :func:`linearize_by_timing` reads the light within the
   count's band from the first and last ON-event times). A recording's
   flat-field captures (every mirror on) calibrate each pixel's threshold
   first (:func:`flat_field_gain`, :func:`timing_thresholds`). Fixed windows
   of a recording without a plan stay net counts ON - OFF (nothing says how
   counts map to light) unless a ``theta`` is given.
4. :func:`combine_passes`: ``K+F+ - K+F- - K-F+ + K-F-`` per (kernel,
   features, repeat), from whichever passes the schedule holds.
5. :func:`to_response_grid` (the sensor region onto the response's cells, any
   effective stride, by area overlap) and :func:`downsample` (to a target
   size: block means for whole factors, area-weighted resampling otherwise).
6. :func:`binarize`: sign, mean, a fixed threshold or Otsu's (a value at the
   threshold, to rounding, split by one rule whatever the path).

What a run is (its schedule, patterns, placement, pixel model) comes from :mod:`evtk.plan`; nothing here
imports the simulator. :func:`save_reconstruction` and :func:`load_reconstruction` write and read the result.
"""

from __future__ import annotations

import sys
import types
from typing import TYPE_CHECKING, Any

from .._lazymod import lazy_names

# names load with their module on first use (PEP 562): fixed windows reconstructed with numpy alone import no
# compiler, no scipy and none of the stages a schedule needs
_WHERE = {
    **dict.fromkeys(["accumulate"], "accumulate"),
    **dict.fromkeys(["load_schedule", "match_windows"], "bench"),
    **dict.fromkeys(["binarize", "binarize_rule"], "binarize"),
    **dict.fromkeys(["nominal_placement", "schedule_of_record"], "calibrated"),
    **dict.fromkeys(["ORACLE_ROUTE", "reconstruct"], "entry"),
    **dict.fromkeys(["load_reconstruction", "save_reconstruction"], "files"),
    **dict.fromkeys(["PixelFit", "fit_pixel_model", "level_statistics"], "fit"),
    **dict.fromkeys(["combine_passes", "downsample", "footprint_matrix", "overlap_matrix", "sample_response_grid",
                     "to_response_grid"], "grid"),
    **dict.fromkeys(["count_curve", "flat_field_gain", "linearize", "linearize_by_model", "_count_curve",
                     "_expected_flat_counts", "_flat_log_step"], "linearize"),
    **dict.fromkeys(["ReconstructOptions"], "options"),
    **dict.fromkeys(["check_crop", "reconstruct_counts", "response_error", "wants_times"], "pipeline"),
    **dict.fromkeys(["plan", "window_bytes"], "route"),
    **dict.fromkeys(["Reconstruction"], "result"),
    **dict.fromkeys(["ReconstructionSummary"], "summary"),
    **dict.fromkeys(["linearize_by_timing", "timing_thresholds", "_timing_factor"], "timing"),
    **dict.fromkeys(["WindowCounts", "Windows", "windows_from_schedule", "windows_from_triggers", "windows_periodic"], "windows"),
}

if TYPE_CHECKING:
    from .accumulate import accumulate
    from .bench import load_schedule, match_windows
    from .binarize import binarize, binarize_rule
    from .calibrated import nominal_placement, schedule_of_record
    from .entry import ORACLE_ROUTE, reconstruct
    from .files import load_reconstruction, save_reconstruction
    from .fit import fit_pixel_model, level_statistics, PixelFit
    from .grid import combine_passes, downsample, footprint_matrix, overlap_matrix, sample_response_grid, to_response_grid
    from .linearize import count_curve, flat_field_gain, linearize, linearize_by_model
    from .options import ReconstructOptions
    from .pipeline import check_crop, reconstruct_counts, response_error, wants_times
    from .result import Reconstruction
    from .route import plan, window_bytes
    from .summary import ReconstructionSummary
    from .timing import linearize_by_timing, timing_thresholds
    from .windows import WindowCounts, Windows, windows_from_schedule, windows_from_triggers, windows_periodic



__getattr__, __dir__ = lazy_names(__name__, _WHERE)


class _Package(types.ModuleType):
    """The package, whose functions ``accumulate``, ``binarize`` and ``linearize`` keep their names when the
    modules of the same names load (the import system sets a loaded submodule on its package)."""

    def __setattr__(self, name: str, value: Any) -> None:
        if isinstance(value, types.ModuleType) and _WHERE.get(name) == name:
            value = getattr(value, name)
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Package


__all__ = [
    "Windows", "WindowCounts", "windows_from_schedule", "windows_from_triggers", "windows_periodic",
    "ReconstructOptions", "match_windows", "load_schedule", "accumulate", "linearize",
    "combine_passes", "to_response_grid", "downsample", "binarize", "binarize_rule", "plan", "reconstruct",
    "reconstruct_counts", "Reconstruction", "response_error",
    "count_curve", "linearize_by_model", "linearize_by_timing", "timing_thresholds", "wants_times",
    "window_bytes", "flat_field_gain", "schedule_of_record", "nominal_placement",
    "fit_pixel_model", "level_statistics", "PixelFit", "footprint_matrix", "overlap_matrix", "sample_response_grid",
    "check_crop", "load_reconstruction", "save_reconstruction", "ReconstructionSummary", "ORACLE_ROUTE",
]

