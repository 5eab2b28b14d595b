"""The plan of a run as one typed value: :class:`Plan`, what :func:`evtk.reconstruct.reconstruct` consumes."""

from __future__ import annotations

import dataclasses
import os
import warnings
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import EvtkError
from ..optics import Bench
from ..optics.camera import Camera, CellMap
from ..sensor import SensorModel
from .record import SimulationRecord
from .schedule import Schedule, read_schedule

__all__ = ["Plan", "PixelModel", "as_plan"]

#: The entries of the schedule's old dict form, still readable from a plan by key (deprecated: attributes).
SCHEDULE_KEYS = ("schedule", "kernels", "features", "bench", "window_us", "settle_us", "dot_spacing")


@dataclass(frozen=True)
class PixelModel:
    """The pixels' model in the units of light a run's responses are in: what the reconstruction inverts.

    Parameters
    ----------
    sensor : SensorModel
        The pixels' thresholds, time constants, refractory period and noise.
    gain_e_per_s_per_unit : float
        Photoelectrons per second one unit of response adds to a pixel.
    blank_rate_e_per_s : float
        A pixel's photocurrent with both DMDs dark (the dark level every step of light is taken over).
    """

    sensor: SensorModel
    gain_e_per_s_per_unit: float
    blank_rate_e_per_s: float


@dataclass(frozen=True, eq=False)
class Plan:
    """What a run is, as far as it is known: the schedule and patterns always; the camera's placement, the pixel
    model and the light's delay when a calibration or the simulator says them.

    The reconstruction (:func:`evtk.reconstruct.reconstruct`) chooses its route from what the plan holds: the
    simulation ``record`` (the oracle: the simulator's own pixel model and placement); a ``pixel_model`` fitted
    by a calibration, or level captures to fit one to (inverted); neither (``exp(n theta)``, each pixel's
    threshold from the flat fields). Its entries are attributes (``plan.kernels``); reading the schedule's seven
    entries by key (``plan["kernels"]``, the dict ``read_schedule`` once returned) still works but is deprecated.

    Parameters
    ----------
    schedule : Schedule
        The captures: which patterns, which pass, when.
    kernels, features : ndarray
        The patterns (n, h, w), -1, 0 or 1.
    bench : Bench
        The bench's geometry and light.
    window_us, settle_us : int
        How long each capture shows its patterns, and the darkness after it (µs).
    dot_spacing : int
        Features elements between the calibration dots.
    region : tuple of int, optional
        ``(x0, x1, y0, y1)``: the sensor pixels the response falls on (a calibration's), else the bench
        geometry's.
    origin_px : tuple of float, optional
        ``(x, y)``: the sensor pixel of the full response's cell (0, 0), else the bench geometry's.
    cell_map : CellMap, optional
        A calibration's whole map from cells to pixels (a rotated, tilted or distorted camera).
    blur_px : float
        The camera's defocus (pixels), deblurred with the footprint.
    pixel_model : dict, optional
        A pixel model fitted by a calibration (:meth:`evtk.reconstruct.PixelFit.to_dict`), for the calibrated
        route to use when the run has no level captures of its own.
    own_levels : bool
        Fit the pixel model to the run's own level captures when it has any (else use ``pixel_model``).
    light_delay_us : int
        How long after each trigger edge the light changes (µs), when known.
    record : SimulationRecord, optional
        The simulation record the plan was read from (:meth:`from_record`): it says the run was simulated, so
        the reconstruction takes its windows from the schedule (the recording's clock).
    pixels : PixelModel, optional
        The pixel model the stages after counting invert (:func:`evtk.reconstruct.reconstruct_counts`): the
        simulator's (:meth:`from_record`), or the one the calibrated route fitted, in its units of light.
    camera : Camera, optional
        The simulated camera's pose and lens, when the run was simulated through one: the light it shows each
        pixel of a flat field (``cell_map`` holds its map from cells to pixels).
    """

    schedule: Schedule
    kernels: np.ndarray
    features: np.ndarray
    bench: Bench
    window_us: int
    settle_us: int
    dot_spacing: int = 4
    region: tuple | None = None
    origin_px: tuple | None = None
    cell_map: CellMap | None = None
    blur_px: float = 0.0
    pixel_model: dict | None = None
    own_levels: bool = True
    light_delay_us: int = 0
    record: SimulationRecord | None = None
    pixels: PixelModel | None = None
    camera: Camera | None = None

    def __getitem__(self, key: str) -> Any:
        if key not in SCHEDULE_KEYS:
            raise KeyError(key)
        warnings.warn(f"plan[{key!r}] is deprecated: read plan.{key}", DeprecationWarning, stacklevel=2)
        return getattr(self, key)

    @property
    def signed(self) -> bool:
        """Whether a kernel or features pattern holds -1 (responses combine ± passes)."""
        return bool(np.min(self.kernels) < 0 or np.min(self.features) < 0)

    def replace(self, **changes: Any) -> Plan:
        """A copy with some entries changed (a placement, a pixel model).

        Parameters
        ----------
        **changes
            Entries and their new values.

        Returns
        -------
        Plan
            The copy.
        """
        return dataclasses.replace(self, **changes)

    @classmethod
    def read(cls, path: str | os.PathLike) -> Plan:
        """The plan of a bench run's ``schedule.json`` (:func:`~evtk.plan.read_schedule`, every value checked).

        Parameters
        ----------
        path : str or os.PathLike
            The file.

        Returns
        -------
        Plan
            The schedule, patterns, bench and timing; no placement, no pixel model.
        """
        return read_schedule(path)

    @classmethod
    def from_schedule(cls, d: Mapping) -> Plan:
        """The plan of a schedule's dict form (its seven entries, as ``read_schedule`` once returned them).

        Parameters
        ----------
        d : Mapping
            ``schedule``, ``kernels``, ``features``, ``bench``, ``window_us``, ``settle_us`` and optionally
            ``dot_spacing``.

        Returns
        -------
        Plan
            The schedule part of a plan.
        """
        missing = [k for k in SCHEDULE_KEYS[:6] if k not in d]
        if missing:
            raise EvtkError(f"the schedule lacks {', '.join(missing)}")
        return cls(**{k: d[k] for k in SCHEDULE_KEYS if k in d})

    @classmethod
    def from_record(cls, record: SimulationRecord | dict, oracle: bool = True) -> Plan:
        """The plan a simulation record holds.

        Parameters
        ----------
        record : SimulationRecord or dict
            The record (or its dict form, checked).
        oracle : bool
            Keep the whole record (the simulator's placement, pixel model and light delay: the oracle); False
            keeps only what a bench's ``schedule.json`` would hold (schedule, patterns, bench, timing).

        Returns
        -------
        Plan
            The plan.
        """
        r = SimulationRecord.from_dict(record)
        plan = cls(r.schedule, r.kernels, r.features, r.bench, r.window_us, r.settle_us, r.dot_spacing)
        if not oracle:
            return plan
        # a fitted cell map takes the place of the simulated camera (as the record's placement says)
        camera = Camera.from_dict(r.camera) if r.camera is not None and r.cell_map is None else None
        return plan.replace(region=tuple(r.response_region), origin_px=tuple(r.response_origin_px),
                            cell_map=r.placement(), blur_px=r.blur_px, light_delay_us=r.light_delay_us, record=r,
                            pixels=PixelModel(r.sensor, r.gain_e_per_s_per_unit, r.blank_rate_e_per_s),
                            camera=camera)


def as_plan(schedule: Plan | Mapping | str | os.PathLike) -> Plan:
    """A plan from what callers pass for a run's schedule.

    Parameters
    ----------
    schedule : Plan, dict, str or os.PathLike
        A plan (returned as it is), a schedule's dict form, or a ``schedule.json`` path.

    Returns
    -------
    Plan
        The plan.
    """
    if isinstance(schedule, Plan):
        return schedule
    if isinstance(schedule, Mapping):
        return Plan.from_schedule(schedule)
    return Plan.read(schedule)
