"""The capture schedule and the patterns a run shows, now in :mod:`evtk.plan.schedule` (this path is kept for
code that imports it from here)."""

from __future__ import annotations

from ..plan.schedule import (
    DOTS_ID,
    FLAT_ID,
    LEVEL_ID,
    METADATA_KEY,
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
    split_passes,
)

__all__ = [
    "split_passes", "Schedule", "CaptureCounts", "load_patterns", "dot_grid", "FLAT_ID",
    "DOTS_ID", "LEVEL_ID", "level_kernel", "level_steps", "default_features", "METADATA_KEY", "check_schedule",
    "check_patterns", "read_schedule", "SCHEDULE_SPECS",
]
