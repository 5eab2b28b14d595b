"""The bench description (:class:`Bench`) and its TOML/JSON files."""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from .._atomic import AtomicFile
from ..errors import EvtkError, check_parameters
from ..settings import MAX_SIDE, Spec, check_origin, check_value, read_table, toml_text
from .geometry import (
    PHOTON_ENERGY_J_PER_NM,
    effective_stride,
    min_capture_window_us,
    optical_scaling,
    shadow_magnification,
    software_scaling,
)

if TYPE_CHECKING:
    from ..sensor import SensorModel

__all__ = ["Bench", "load_bench", "save_bench", "BENCH_SPECS", "MAX_DMD_SIDE"]

#: Most mirrors along one side of a DMD (the largest made have 3840 x 2160).
MAX_DMD_SIDE = 16384

#: The physical range of each bench setting (``origin_px`` is checked against the sensor on its own).
BENCH_SPECS = {
    "u_mm": Spec("float", 0, 1e6, lo_open=True, unit="mm"),
    "z_mm": Spec("float", 0, 1e6, lo_open=True, unit="mm"),
    "mirror_pitch_um": Spec("float", 0, 1e4, lo_open=True, unit="µm"),
    "dmd_cols": Spec("int", 1, MAX_DMD_SIDE, unit="mirrors"),
    "dmd_rows": Spec("int", 1, MAX_DMD_SIDE, unit="mirrors"),
    "feature_upsample": Spec("int", 1, MAX_DMD_SIDE, unit="mirrors per features element"),
    "kernel_upsample": Spec("int", 1, MAX_DMD_SIDE, unit="mirrors per kernel element", optional=True),
    "sensor_pitch_um": Spec("float", 0, 1e7, lo_open=True, unit="µm"),
    "decimation": Spec("int", 1, MAX_SIDE),
    "sensor_width": Spec("int", 1, MAX_SIDE, unit="pixels"),
    "sensor_height": Spec("int", 1, MAX_SIDE, unit="pixels"),
    "kernel_hz": Spec("float", 0, 1e7, lo_open=True, unit="Hz"),
    "features_hz": Spec("float", 0, 1e7, lo_open=True, unit="Hz"),
    "pixel_latency_us": Spec("float", 0, 1e9, lo_open=True, unit="µs"),
    "wavelength_nm": Spec("float", 10, 1e6, unit="nm"),
    "power_mw": Spec("float", 0, 1e9, unit="mW"),
    "efficiency": Spec("float", 0, 1, unit="photoelectrons per photon"),
    "dmd_contrast": Spec("float", 1, 1e12),
    "stray_light": Spec("float", 0, 1e9, unit="units of light"),
    "psf_sigma_um": Spec("float", 0, 1e7, unit="µm"),
    "source_extent": Spec("str", choices=("point", "area")),
    "kernel_flipped": Spec("bool"),
    "diffraction": Spec("bool"),
}


@dataclass(frozen=True)
class Bench:
    """Everything about the optical bench that the simulator needs.

    Defaults follow the paper's hardware (514 nm laser, two 0.65-inch 1080p
    DMDs with 7.56 um mirrors, a DVXplorer Lite at 320x240). Distances, the
    screen-side pixel pitch and the light budget are not given in the paper;
    the defaults are chosen so that scaling is matched (eq. 4 gives a whole
    number of mirrors) and the effective stride is 1 (eq. 6).

    Parameters
    ----------
    u_mm : float
        Feature DMD to screen distance ``u``, mm.
    z_mm : float
        Diffuser to feature DMD distance ``z``, mm.
    mirror_pitch_um : float
        Mirror pitch of both DMDs (``K_pt`` for the kernel), um.
    dmd_cols : int
        Mirrors per row of each DMD; a displayed pattern must fit.
    dmd_rows : int
        Mirror rows of each DMD.
    feature_upsample : int
        Mirrors per feature element along each axis (``F_pt`` = this x pitch).
    kernel_upsample : int or None
        Mirrors per kernel element; None takes eq. 4 rounded to a whole number.
    sensor_pitch_um : float
        Footprint of one sensor pixel on the screen (``Phi_pt``), um.
    decimation : int
        Keep every ``decimation``-th sensor pixel when reconstructing (``Delta``).
    sensor_width : int
        Event camera resolution along x, pixels.
    sensor_height : int
        Event camera resolution along y, pixels.
    kernel_hz : float
        Pattern rate ``K_hz`` of the kernel DMD (eq. 7), Hz.
    features_hz : float
        Pattern rate ``F_hz`` of the feature DMD (eq. 7), Hz.
    pixel_latency_us : float
        Event camera pixel latency (``S_I`` of eq. 7), us.
    wavelength_nm : float
        Laser wavelength, nm.
    power_mw : float
        Laser power, mW.
    efficiency : float
        Photoelectrons produced in the pixel that images one feature element
        per photon leaving one kernel element (diffuser spread, feature DMD,
        screen scatter, camera lens, quantum efficiency together).
    dmd_contrast : float
        On/off contrast of each DMD; an off mirror passes ``1/dmd_contrast``.
    stray_light : float
        Ambient light on the screen, in response units (a floor).
    psf_sigma_um : float
        Gaussian blur of the diffuser on the screen (standard deviation), um.
    source_extent : {"point", "area"}
        "area": each kernel element is a uniform square source; "point": it
        emits from its centre (the idealised device).
    kernel_flipped : bool
        The relay inverts the kernel image, turning correlation into convolution.
    origin_px : tuple of float or None
        Sensor pixel (x, y) where the full response begins; None centres it.
    diffraction : bool
        Blur the feature elements' shadows by their diffraction too
        (:attr:`diffraction_sigma_um`, a Gaussian approximation), which
        matters when :attr:`fresnel_number` is below about 1. Off by default:
        the ray-optics shadows.

    Raises
    ------
    EvtkError
        If a setting is outside its physical range (``BENCH_SPECS``) or ``origin_px`` is off the sensor.
    """

    u_mm: float = 300.0
    z_mm: float = 100.0
    mirror_pitch_um: float = 7.56
    dmd_cols: int = 1920
    dmd_rows: int = 1080
    feature_upsample: int = 6
    kernel_upsample: int | None = None
    sensor_pitch_um: float = 181.44
    decimation: int = 1
    sensor_width: int = 320
    sensor_height: int = 240
    kernel_hz: float = 9523.0
    features_hz: float = 9523.0
    pixel_latency_us: float = 200.0
    wavelength_nm: float = 514.0
    power_mw: float = 20.0
    efficiency: float = 3.5e-10
    dmd_contrast: float = 1000.0
    stray_light: float = 1e-4
    psf_sigma_um: float = 0.0
    source_extent: str = "area"
    kernel_flipped: bool = False
    origin_px: tuple | None = field(default=None)
    diffraction: bool = False

    def __post_init__(self) -> None:
        where = "bench"
        for name, spec in BENCH_SPECS.items():
            object.__setattr__(self, name, check_value(where, name, getattr(self, name), spec))
        if self.origin_px is not None:
            object.__setattr__(self, "origin_px", check_origin(where, "origin_px", self.origin_px,
                                                               (self.sensor_width, self.sensor_height)))

    # derived geometry ------------------------------------------------------------
    @functools.cached_property  # fields are frozen: compute once
    def sigma(self) -> float:
        """Optical scaling (eq. 3)."""
        return optical_scaling(self.u_mm, self.z_mm)

    @functools.cached_property
    def feature_pitch_um(self) -> float:
        """Feature element pitch ``F_pt`` on the feature DMD."""
        return self.feature_upsample * self.mirror_pitch_um

    @functools.cached_property
    def varsigma(self) -> float:
        """Matching kernel upsampling from eq. 4 (a real number)."""
        return software_scaling(self.sigma, self.feature_pitch_um, self.mirror_pitch_um)

    @functools.cached_property
    def kernel_mirrors(self) -> int:
        """Mirrors per kernel element actually displayed."""
        if self.kernel_upsample is not None:
            return self.kernel_upsample
        return max(1, int(round(self.varsigma)))

    @functools.cached_property
    def k_eff_um(self) -> float:
        """Kernel element extent in the diffuser plane (eq. 2, as displayed)."""
        return self.kernel_mirrors * self.mirror_pitch_um

    @functools.cached_property
    def f_eff_um(self) -> float:
        """Feature element extent mapped into the diffuser plane (eq. 2)."""
        return self.sigma * self.feature_pitch_um

    @functools.cached_property
    def kernel_step_cells(self) -> float:
        """Shift of the shadow per kernel element, in feature elements (1 when matched)."""
        return self.k_eff_um / self.f_eff_um

    @functools.cached_property
    def pixel_cells(self) -> float:
        """Width of one sensor pixel's footprint in feature elements (the stride at decimation 1)."""
        return self.sensor_pitch_um / (shadow_magnification(self.u_mm, self.z_mm) * self.feature_pitch_um)

    @functools.cached_property
    def stride_eff(self) -> float:
        """Effective stride in kernel elements per output sample (eq. 6, as displayed)."""
        return effective_stride(self.u_mm, self.z_mm, self.sensor_pitch_um, self.feature_pitch_um,
                                self.decimation, k_eff_um=self.k_eff_um)

    @functools.cached_property
    def min_window_us(self) -> float:
        """Shortest capture window (eq. 7)."""
        return min_capture_window_us(self.kernel_hz, self.features_hz, self.pixel_latency_us)

    @functools.cached_property
    def leak(self) -> float:
        """Fraction of light an off mirror passes."""
        return 1.0 / self.dmd_contrast

    @functools.cached_property
    def fresnel_number(self) -> float:
        """Fresnel number of one feature element seen from the screen: ``F_pt^2 / (lambda u)``.

        Ray optics (the shadow model evtk simulates) holds when it is well above
        1; at the default bench it is about 0.013, where each element diffracts.
        """
        return (self.feature_pitch_um * 1e-6) ** 2 / (self.wavelength_nm * 1e-9 * self.u_mm * 1e-3)

    @functools.cached_property
    def diffraction_spread_um(self) -> float:
        """Width on the screen of the far-field diffraction of one feature element, ``lambda u / F_pt``
        (first zeros of a slit, halved): what the shadow model leaves out when :attr:`fresnel_number` < 1."""
        return self.wavelength_nm * 1e-3 * self.u_mm * 1e3 / self.feature_pitch_um

    @functools.cached_property
    def diffraction_sigma_um(self) -> float:
        """The diffraction of one feature element as a Gaussian blur on the screen (standard deviation, µm).

        A documented approximation, not a Fresnel propagation: the blur of a
        slit of width ``F_pt`` at distance ``u`` is taken as ``0.376 max(lambda u
        / F_pt, sqrt(lambda u))``. In the far field (Fresnel number below 1)
        that is the Gaussian with the half-maximum width of the slit's sinc^2
        pattern (0.886 lambda u / F_pt). In the near field it is the same
        share of the Fresnel zone ``sqrt(lambda u)``, which sets how far an
        edge's ringing reaches. The two meet at a Fresnel number of 1.
        """
        lam_u = self.wavelength_nm * 1e-3 * self.u_mm * 1e3  # um^2
        return 0.376 * max(lam_u / self.feature_pitch_um, math.sqrt(lam_u))

    @functools.cached_property
    def shadow_sigma_um(self) -> float:
        """Gaussian blur of the shadows on the screen: the diffuser's, and the diffraction's when modelled."""
        return math.hypot(self.psf_sigma_um, self.diffraction_sigma_um if self.diffraction else 0.0)

    def shadow_model_note(self) -> str | None:
        """A sentence saying why the ray-optics shadow model does not hold for this bench, or None when it does.

        Returns
        -------
        str or None
            The warning (Fresnel number below 1 and diffraction not modelled), or None.
        """
        if self.fresnel_number >= 1.0 or self.diffraction:
            return None
        pixels = self.diffraction_spread_um / self.sensor_pitch_um
        return (f"Fresnel number {self.fresnel_number:.3g} < 1: each feature element diffracts over about "
                f"{self.diffraction_spread_um / 1000:.3g} mm on the screen ({pixels:.3g} sensor pixels), which the "
                "simulated shadows leave out (shorter u_mm or larger feature elements make them valid; "
                "[bench] diffraction = true blurs them by it)")

    def photons_per_s(self) -> float:
        """Laser photon rate, ``P lambda / (h c)``.

        Returns
        -------
        float
            Photons per second leaving the laser.
        """
        return self.power_mw * 1e-3 * self.wavelength_nm / PHOTON_ENERGY_J_PER_NM

    def electrons_per_s_per_unit(self, kernel_shape: tuple[int, int]) -> float:
        """Photoelectron rate of a pixel per response unit (see :func:`screen_response`).

        The laser is spread over the kernel's footprint (all its elements, lit
        or not); a pixel collects in proportion to its footprint area.

        Parameters
        ----------
        kernel_shape : tuple of int
            ``(rows, cols)`` of the kernel, in kernel elements.

        Returns
        -------
        float
            Photoelectrons per second per response unit.
        """
        kh, kw = kernel_shape
        return self.photons_per_s() / (kh * kw) * self.efficiency * self.pixel_cells ** 2

    def check_pattern(self, kernel_shape: tuple[int, int], features_shape: tuple[int, int]) -> None:
        """Raise if a kernel or feature pattern does not fit its DMD.

        Parameters
        ----------
        kernel_shape : tuple of int
            ``(rows, cols)`` of the kernel, in elements (each :attr:`kernel_mirrors` mirrors wide).
        features_shape : tuple of int
            ``(rows, cols)`` of the features, in elements (each ``feature_upsample`` mirrors wide).

        Raises
        ------
        EvtkError
            If either pattern needs more mirrors than its DMD has.
        """
        kh, kw = kernel_shape
        fh, fw = features_shape
        m = self.kernel_mirrors
        if kh * m > self.dmd_rows or kw * m > self.dmd_cols:
            raise EvtkError(f"a {kh}x{kw} kernel at {m} mirrors per element needs {kw * m}x{kh * m} mirrors; "
                            f"the kernel DMD has {self.dmd_cols}x{self.dmd_rows}")
        m = self.feature_upsample
        if fh * m > self.dmd_rows or fw * m > self.dmd_cols:
            raise EvtkError(f"{fh}x{fw} features at {m} mirrors per element need {fw * m}x{fh * m} mirrors; "
                            f"the feature DMD has {self.dmd_cols}x{self.dmd_rows}")

    def to_dict(self) -> dict:
        """The fields as a plain dict (``origin_px`` as a list), for TOML/JSON.

        Returns
        -------
        dict
            Field name to value; :meth:`from_dict` reads it back.
        """
        d = dataclasses.asdict(self)
        if d["origin_px"] is not None:
            d["origin_px"] = list(d["origin_px"])
        return d

    @classmethod
    def from_dict(cls, d: dict) -> Bench:
        """A bench from a dict of fields (as :meth:`to_dict` writes; missing fields take their defaults).

        Parameters
        ----------
        d : dict
            Field name to value.

        Returns
        -------
        Bench
            The checked bench.

        Raises
        ------
        EvtkError
            If a key is not a field, a value has the wrong kind or is out of range.
        """
        check_parameters("bench", cls, d)
        return cls(**d)

    def replace(self, **changes: Any) -> Bench:
        """A copy with some fields changed (checked again).

        Parameters
        ----------
        **changes : Any
            Field name to new value.

        Returns
        -------
        Bench
            The new bench.
        """
        return dataclasses.replace(self, **changes)



def load_bench(path: str | os.PathLike[str]) -> tuple[Bench, dict]:
    """Read a bench description; returns ``(Bench, sensor_dict)``.

    TOML (``.toml``) or JSON (anything else). Top-level keys are :class:`Bench`
    fields; an optional ``sensor`` table holds :class:`evtk.sensor.SensorModel`
    fields.

    Parameters
    ----------
    path : str or os.PathLike
        The bench file.

    Returns
    -------
    bench : Bench
        The bench.
    sensor : dict
        The ``sensor`` table's parameters (empty when the file has none), for
        :meth:`evtk.sensor.SensorModel.from_dict`.

    Raises
    ------
    EvtkError
        If the file cannot be read or parsed, or a setting is unknown or out of range (the message names the file).
    """
    path = os.fspath(path)
    data = read_table(path, "bench")
    data = dict(data)
    sensor = data.pop("sensor", {})
    if not isinstance(sensor, dict):
        raise EvtkError(f"{path}: 'sensor' must be a table of parameters")
    try:
        return Bench.from_dict(data), sensor
    except EvtkError as exc:
        raise EvtkError(f"{path}: {exc}") from None
    except TypeError as exc:
        raise EvtkError(f"{path}: {exc}") from None


def save_bench(path: str | os.PathLike[str], bench: Bench, sensor: SensorModel | dict | None = None) -> None:
    """Write a bench description as TOML (``.toml``) or JSON; atomic.

    ``sensor`` is an optional :class:`evtk.sensor.SensorModel` or dict. Unset
    optional values (None) are left out.

    Parameters
    ----------
    path : str or os.PathLike
        Where to write; a name ending ``.toml`` writes TOML, anything else JSON.
    bench : Bench
        The bench.
    sensor : SensorModel or dict or None, optional
        Sensor parameters written as the ``sensor`` table; None writes none.
    """

    data = bench.to_dict()
    sdata = None
    if sensor is not None:
        sdata = sensor.to_dict() if hasattr(sensor, "to_dict") else dict(sensor)
    path = os.fspath(path)
    if path.lower().endswith(".toml"):
        table: dict[str, object] = {k: v for k, v in data.items() if v is not None}
        if sdata:
            table["sensor"] = {k: v for k, v in sdata.items() if v is not None}
        text = toml_text(table, "bench", comment="evtk bench description")
    else:
        out = {k: v for k, v in data.items() if v is not None}
        if sdata:
            out["sensor"] = {k: v for k, v in sdata.items() if v is not None}
        text = json.dumps(out, indent=2) + "\n"
    with AtomicFile(path) as f:
        f.write(text.encode("utf-8"))
