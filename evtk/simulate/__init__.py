"""Simulated device: kernels and features in, an event recording (or responses) out.

A run shows every (kernel, features) pair ``repeat`` times. Signed patterns
are split into the non-negative passes K+F+, K+F-, K-F+, K-F- (a pass that is
identically zero is left out). Each pass is one *capture*: both DMDs show
their pattern for ``window_us``, then both go dark for ``settle_us``. The
recording starts with ``settle_us`` of darkness. The DMD trigger output is
recorded as trigger events: a rising edge when a pattern appears, a falling
edge when it goes.

Two ways to run:

* :meth:`Simulation.iter_events` / :meth:`Simulation.write`: the event
  stream of the whole sensor, in time order, streamed capture batch by
  capture batch (memory bounded by a batch).
* :meth:`Simulation.responses`: the fast path, per-window event counts
  without events. Each pixel's counts are drawn from a table of the same
  pixel model's counts over light and threshold (:meth:`Simulation.count_table`,
  built once per bench, sensor and timing); ``method="exact"`` runs the
  model over the pixels that see the pattern instead, history included.

Outside the pattern's reach the screen is uniform; those pixels are
simulated without shot noise (only if the glow could make them fire) and
their noise is background activity at the sensor's rate.

Everything needed to reproduce or reconstruct a run (bench, sensor, patterns,
schedule, seed) is in :meth:`Simulation.metadata`, stored with the recording;
see ``docs/formats/schedule.md``. The schedule, the patterns' helpers and the record are
:mod:`evtk.plan`'s (what a run is); they are re-exported here under their older paths.
"""

from __future__ import annotations

from ..plan.record import SimulationRecord
from ..plan.schedule import (
    DOTS_ID,
    FLAT_ID,
    LEVEL_ID,
    METADATA_KEY,  # noqa: F401  (the record's key in a recording's metadata)
    CaptureCounts,
    Schedule,
    default_features,
    dot_grid,
    level_kernel,
    level_steps,
    load_patterns,
    split_passes,
)
from .run import Simulation

__all__ = [
    "split_passes", "Schedule", "Simulation", "SimulationRecord", "CaptureCounts", "load_patterns", "dot_grid", "FLAT_ID",
    "DOTS_ID", "LEVEL_ID", "level_kernel", "level_steps", "default_features", "METADATA_KEY",
]
