"""The simulation record, now in :mod:`evtk.plan.record` (this path is kept for code that imports it from here)."""

from __future__ import annotations

from ..plan.record import RECORD_SPECS, SimulationRecord

__all__ = ["SimulationRecord", "RECORD_SPECS"]
