"""The simulation record: what a simulated recording says about how it was made.

:class:`SimulationRecord` is the typed form of the ``simulation`` entry of
a recording's metadata (``docs/formats/schedule.md``). It is what the oracle
reconstruction (``evtk reconstruct --oracle``) and the error against the
ideal read; a bench recording has none.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from ..errors import EvtkError
from ..optics import Bench
from ..optics.camera import Camera, CellMap
from ..sensor import SensorModel
from .schedule import METADATA_KEY, Schedule

__all__ = ["SimulationRecord"]


@dataclass(frozen=True, eq=False)
class SimulationRecord:
    """How a simulated recording was made (:meth:`evtk.simulate.Simulation.record`).

    Attributes
    ----------
    bench : Bench
    sensor : SensorModel
    kernels, features : ndarray of int (n, h, w)
    schedule : Schedule
    window_us, settle_us, start_us, end_us : int
        Capture timing and the recording's span (µs).
    response_region : (x0, x1, y0, y1)
        Sensor pixels the response falls on.
    response_origin_px : (x, y)
        Sensor pixel of the full response's cell (0, 0).
    gain_e_per_s_per_unit : float
        Photoelectrons per second one unit of response adds to a pixel.
    blank_rate_e_per_s : float
        A pixel's photocurrent with both DMDs dark (dark current and glow).
    seed, noise_seed, repeat, flat_field, calibration, dot_spacing, levels, correlation, evtk_version
        The rest of the run's settings.
    """

    bench: Bench
    sensor: SensorModel
    kernels: np.ndarray
    features: np.ndarray
    schedule: Schedule
    window_us: int
    settle_us: int
    start_us: int
    end_us: int
    response_region: tuple
    response_origin_px: tuple
    gain_e_per_s_per_unit: float
    blank_rate_e_per_s: float
    seed: int | None = None
    noise_seed: int | None = None
    repeat: int = 1
    flat_field: int = 0
    calibration: bool = False
    dot_spacing: int = 4
    levels: int = 0
    #: the simulated camera's pose and lens (:class:`evtk.optics.camera.Camera` fields), None for the nominal view
    camera: dict | None = None
    #: a fitted map from cells to pixels ({"matrix": 3x3, "k1": float}: :class:`evtk.optics.camera.CellMap`), which
    #: takes the place of ``response_origin_px`` (a calibration of a camera that is rotated, tilted or distorted);
    #: an optional ``"blur_px"`` holds the defocus the calibration measured
    cell_map: dict | None = None
    #: how long after each trigger edge the light changed (µs; the schedule holds the light's times)
    light_delay_us: int = 0
    correlation: str = "correlation"
    evtk_version: str = ""

    _REQUIRED = ("bench", "sensor", "kernels", "features", "schedule", "window_us", "settle_us",
                 "response_region", "response_origin_px", "gain_e_per_s_per_unit", "blank_rate_e_per_s")

    def placement(self) -> CellMap | None:
        """The map from response cells to sensor pixels when it is more than ``response_origin_px`` and the
        bench's step (a fitted ``cell_map``, or the simulated camera's pose and lens), else None."""
        size = (self.bench.sensor_width, self.bench.sensor_height)
        if self.cell_map is not None:
            return CellMap(np.asarray(self.cell_map["matrix"], np.float64), float(self.cell_map["k1"]), size)
        if self.camera is None:
            return None
        cam = Camera.from_dict(self.camera)
        nominal = CellMap.scale_shift(self.response_origin_px, self.bench.kernel_step_cells / self.bench.pixel_cells,
                                      size)
        return CellMap(cam.homography(size) @ nominal.matrix, cam.k1, size)

    @property
    def blur_px(self) -> float:
        """The camera's defocus on the sensor (Gaussian standard deviation, pixels): the calibration's
        measurement with a fitted ``cell_map``, else the simulated camera's, else 0."""
        if self.cell_map is not None:
            return float(self.cell_map.get("blur_px", 0.0))
        return 0.0 if self.camera is None else Camera.from_dict(self.camera).defocus_px

    @property
    def signed(self) -> bool:
        """Whether a kernel or features pattern holds -1 (responses combine ± passes)."""
        return bool(np.min(self.kernels) < 0 or np.min(self.features) < 0)

    def replace(self, **changes) -> SimulationRecord:
        """A copy with some attributes changed (e.g. another pixel model, to test a mismatched reconstruction)."""
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        """The JSON-ready form stored in a recording's metadata under ``simulation``."""
        d = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        d.update(bench=self.bench.to_dict(), sensor=self.sensor.to_dict(), kernels=self.kernels.tolist(),
                 features=self.features.tolist(), schedule=self.schedule.to_dict(),
                 response_region=[int(v) for v in self.response_region],
                 response_origin_px=[float(v) for v in self.response_origin_px])
        return d

    @classmethod
    def from_dict(cls, d) -> SimulationRecord:
        """Read the record from its dict form (or pass a record through); a bad one is an :class:`EvtkError`."""
        if isinstance(d, cls):
            return d
        if not isinstance(d, dict):
            raise EvtkError(f"a simulation record must be a dict, not {type(d).__name__}")
        missing = [k for k in cls._REQUIRED if k not in d]
        if missing:
            raise EvtkError(f"the simulation record lacks {', '.join(missing)}")
        known = {f.name for f in dataclasses.fields(cls)}
        try:
            kw = {k: v for k, v in d.items() if k in known}
            kw.update(bench=Bench.from_dict(d["bench"]), sensor=SensorModel.from_dict(d["sensor"]),
                      kernels=np.asarray(d["kernels"], dtype=np.int64),
                      features=np.asarray(d["features"], dtype=np.int64),
                      schedule=Schedule.from_dict(d["schedule"]),
                      response_region=tuple(int(v) for v in d["response_region"]),
                      response_origin_px=tuple(float(v) for v in d["response_origin_px"]),
                      gain_e_per_s_per_unit=float(d["gain_e_per_s_per_unit"]),
                      blank_rate_e_per_s=float(d["blank_rate_e_per_s"]),
                      window_us=int(d["window_us"]), settle_us=int(d["settle_us"]),
                      start_us=int(d.get("start_us", 0)), end_us=int(d.get("end_us", 0)),
                      light_delay_us=int(d.get("light_delay_us", 0)))
        except EvtkError:
            raise
        except (TypeError, ValueError) as exc:
            raise EvtkError(f"the simulation record is malformed ({type(exc).__name__}: {exc})") from None
        if kw["kernels"].ndim != 3 or kw["features"].ndim != 3 or len(kw["response_region"]) != 4 \
                or len(kw["response_origin_px"]) != 2:
            raise EvtkError("the simulation record is malformed (kernels and features must be (n, h, w), "
                            "the region four numbers and the origin two)")
        return cls(**kw)

    @classmethod
    def from_metadata(cls, metadata) -> SimulationRecord | None:
        """The record in a recording's metadata, or None when it has none (a bench recording)."""
        d = (metadata or {}).get(METADATA_KEY)
        return None if d is None else cls.from_dict(d)
