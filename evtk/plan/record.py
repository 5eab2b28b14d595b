"""The simulation record: what a simulated recording says about how it was made, the whole plan of its run.

:class:`SimulationRecord` is the typed form of the ``simulation`` entry of
a recording's metadata (``docs/formats/schedule.md``). It is what the oracle
reconstruction (``evtk reconstruct --oracle``) and the error against the
ideal read; a bench recording has none.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import EvtkError
from ..optics import Bench
from ..optics.camera import Camera, CellMap
from ..sensor import SensorModel
from ..settings import MAX_BLUR_PX, MAX_COUNT, MAX_US, Spec, check_matrix, check_origin, check_region, check_table, check_value
from .schedule import METADATA_KEY, Schedule, check_patterns

#: What each number of a simulation record may be (the arrays, tables and pixels are checked on their own).
RECORD_SPECS = {
    "window_us": Spec("int", 1, MAX_US, unit="µs"),
    "settle_us": Spec("int", 1, MAX_US, unit="µs"),
    "start_us": Spec("int", 0, MAX_US, unit="µs, where the run's first capture starts (time is from 0)"),
    "end_us": Spec("int", 0, 2 * MAX_US, unit="µs, where the run ends (time is from 0)"),
    "gain_e_per_s_per_unit": Spec("float", 0, 1e30, unit="photoelectrons per second and unit of light"),
    "blank_rate_e_per_s": Spec("float", 0, 1e30, lo_open=True, unit="photoelectrons per second"),
    "seed": Spec("int", 0, 2 ** 63 - 1, optional=True),
    "noise_seed": Spec("int", 0, 2 ** 63 - 1, optional=True),
    "repeat": Spec("int", 1, MAX_COUNT),
    "flat_field": Spec("int", 0, MAX_COUNT),
    "calibration": Spec("int", 0, MAX_COUNT),
    "dot_spacing": Spec("int", 2, 32767, unit="features elements between dots"),
    "levels": Spec("int", 0, MAX_COUNT),
    "light_delay_us": Spec("int", 0, MAX_US, unit="µs"),
    "light_rise_us": Spec("float", 0, MAX_US, unit="µs, the light's exponential rise and fall time"),
    "correlation": Spec("str", choices=("correlation", "convolution")),
    "evtk_version": Spec("str"),
}


def _check_cell_map(where, cm, sensor_size, kernel_shape, features_shape) -> dict:
    """A record's fitted ``cell_map`` ({"matrix", "k1", "blur_px"}), checked: a non-singular map that keeps the
    response on one side of its horizon, a distortion within +-0.3 and a blur up to :data:`MAX_BLUR_PX`."""
    if not isinstance(cm, dict) or "matrix" not in cm or "k1" not in cm:
        raise EvtkError(f"{where}: cell_map must be a table with matrix (3x3), k1 and optionally blur_px")
    rows, cols = (a + b - 1 for a, b in zip(features_shape, kernel_shape))
    corners = [(0, 0), (cols, 0), (0, rows), (cols, rows)]
    out = dict(cm, matrix=check_matrix(where, "cell_map.matrix", cm["matrix"], corners).tolist())
    out["k1"] = check_value(where, "cell_map.k1", cm["k1"], Spec("float", -0.3, 0.3))
    if "blur_px" in cm:
        out["blur_px"] = check_value(where, "cell_map.blur_px", cm["blur_px"], Spec("float", 0, MAX_BLUR_PX, unit="px"))
    return out

__all__ = ["SimulationRecord", "RECORD_SPECS"]


@dataclass(frozen=True, eq=False)
class SimulationRecord:
    """How a simulated recording was made (:meth:`evtk.simulate.Simulation.record`).

    Parameters
    ----------
    bench : Bench
        The bench's geometry and light.
    sensor : SensorModel
        The pixel model the run was simulated with.
    kernels, features : ndarray of int (n, h, w)
        The patterns, -1, 0 or 1.
    schedule : Schedule
        The captures.
    window_us, settle_us, start_us, end_us : int
        Capture timing and the recording's span (µs).
    response_region : tuple
        ``(x0, x1, y0, y1)``: sensor pixels the response falls on.
    response_origin_px : tuple
        ``(x, y)``: sensor pixel of the full response's cell (0, 0).
    gain_e_per_s_per_unit : float
        Photoelectrons per second one unit of response adds to a pixel.
    blank_rate_e_per_s : float
        A pixel's photocurrent with both DMDs dark (dark current and glow).
    seed, noise_seed : int or None
        The seeds of the patterns' draw and of the pixels' noise.
    repeat, flat_field, levels : int
        Repeats of each pair, flat-field captures, level steps.
    calibration : bool
        Calibration (dot grid) captures in the run (their number, as an int, in the dict form).
    dot_spacing : int
        Features elements between calibration dots.
    camera : dict or None
        The simulated camera's pose and lens (:class:`evtk.optics.camera.Camera` fields), None for the nominal
        view.
    cell_map : dict or None
        A fitted map from cells to pixels (``{"matrix": 3x3, "k1": float}``, optionally ``"blur_px"``), which
        takes the place of ``response_origin_px``.
    light_delay_us : int
        How long after each trigger edge the light changed (µs).
    light_rise_us : float
        Time constant of the light's exponential rise after its rising edge and fall after its falling one (µs;
        0 for a step).
    correlation : str
        "correlation" or "convolution" (a flipped kernel).
    evtk_version : str
        The evtk that made the run.
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
    #: time constant of the light's exponential rise and fall at its edges (µs; 0: a step)
    light_rise_us: float = 0.0
    correlation: str = "correlation"
    evtk_version: str = ""

    _REQUIRED = ("bench", "sensor", "kernels", "features", "schedule", "window_us", "settle_us",
                 "response_region", "response_origin_px", "gain_e_per_s_per_unit", "blank_rate_e_per_s")

    def placement(self) -> CellMap | None:
        """The map from response cells to sensor pixels, when it is more than the origin and the bench's step.

        Returns
        -------
        CellMap or None
            A fitted ``cell_map``, or the simulated camera's pose and lens; None for the nominal view
            (``response_origin_px`` and the bench's step).
        """
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

    def replace(self, **changes: Any) -> SimulationRecord:
        """A copy with some attributes changed (e.g. another pixel model, to test a mismatched reconstruction).

        Parameters
        ----------
        **changes
            Attributes and their new values.

        Returns
        -------
        SimulationRecord
            The copy.
        """
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        """The JSON-ready form stored in a recording's metadata under ``simulation``.

        Returns
        -------
        dict
            Every attribute, the arrays and tables as lists and dicts.
        """
        d = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        d.update(bench=self.bench.to_dict(), sensor=self.sensor.to_dict(), kernels=self.kernels.tolist(),
                 features=self.features.tolist(), schedule=self.schedule.to_dict(),
                 response_region=[int(v) for v in self.response_region],
                 response_origin_px=[float(v) for v in self.response_origin_px])
        return d

    @classmethod
    def from_dict(cls, d: dict | SimulationRecord, where: str = "the simulation record") -> SimulationRecord:
        """Read the record from its dict form (or pass a record through), every value checked.

        Parameters
        ----------
        d : dict or SimulationRecord
            :meth:`to_dict`'s form.
        where : str
            Where it was read from, for messages.

        Returns
        -------
        SimulationRecord
            A bad value is one :class:`EvtkError` naming the key and what is allowed.
        """
        if isinstance(d, cls):
            return d
        if not isinstance(d, dict):
            raise EvtkError(f"{where} must be a dict, not {type(d).__name__}")
        missing = [k for k in cls._REQUIRED if k not in d]
        if missing:
            raise EvtkError(f"{where} lacks {', '.join(missing)}")
        known = {f.name for f in dataclasses.fields(cls)}
        where = f"{where} is malformed"
        kw = check_table(where, {k: v for k, v in d.items() if k in known}, RECORD_SPECS, unknown="keep")
        for key, build in (("bench", Bench.from_dict), ("sensor", SensorModel.from_dict)):
            if not isinstance(d[key], dict):
                raise EvtkError(f"{where}: {key} must be a table of parameters")
            try:
                kw[key] = build(d[key])
            except (EvtkError, TypeError) as exc:
                raise EvtkError(f"{where}: {exc}") from None
        size = (kw["bench"].sensor_width, kw["bench"].sensor_height)
        kw["kernels"] = check_patterns(where, "kernels", d["kernels"])
        kw["features"] = check_patterns(where, "features", d["features"])
        k = kw["kernels"]
        kw["schedule"] = Schedule.from_dict(d["schedule"], where, len(k), len(kw["features"]), k.shape[1] * k.shape[2])
        kw["response_region"] = check_region(where, "response_region", d["response_region"], size)
        kw["response_origin_px"] = check_origin(where, "response_origin_px", d["response_origin_px"], size)
        kw.setdefault("start_us", 0)
        kw.setdefault("end_us", 0)
        if kw["end_us"] < kw["start_us"]:
            raise EvtkError(f"{where}: end_us = {kw['end_us']} comes before start_us = {kw['start_us']}")
        if kw.get("light_delay_us", 0) >= kw["settle_us"]:
            raise EvtkError(f"{where}: light_delay_us = {kw['light_delay_us']} must be shorter than settle_us = "
                            f"{kw['settle_us']}")
        if d.get("camera") is not None:
            try:
                kw["camera"] = Camera.from_dict(d["camera"]).to_dict()
            except (EvtkError, TypeError, ValueError) as exc:
                raise EvtkError(f"{where}: {exc}") from None
        if d.get("cell_map") is not None:
            kw["cell_map"] = _check_cell_map(where, d["cell_map"], size, k.shape[1:], kw["features"].shape[1:])
        return cls(**kw)

    @classmethod
    def from_metadata(cls, metadata: dict | None) -> SimulationRecord | None:
        """The record in a recording's metadata, or None when it has none (a bench recording).

        Parameters
        ----------
        metadata : dict or None
            The recording's metadata (its ``simulation`` entry is read and checked).

        Returns
        -------
        SimulationRecord or None
            The record.
        """
        d = (metadata or {}).get(METADATA_KEY)
        return None if d is None else cls.from_dict(d)
