"""Geometry and light transport of the two-DMD shadow-casting bench.

Coordinates and conventions
---------------------------
The laser lights the kernel DMD; a relay images the kernel onto a diffuser,
which turns every lit kernel element into an incoherent source. The feature
DMD sits ``z_mm`` after the diffuser and the screen ``u_mm`` after the feature
DMD. A source at position ``s`` in the diffuser plane lights screen point ``X``
through feature-DMD point ``m = s*u/(u+z) + X*z/(u+z)``. Two consequences:

* the feature mask lands on the screen magnified by ``M = (u+z)/z``
  (:func:`shadow_magnification`);
* displacing the source by ``s`` moves the shadow across the mask by
  ``s/sigma`` with ``sigma = (u+z)/u`` (eq. 3): a feature element of pitch
  ``F_pt`` corresponds to an extent ``sigma*F_pt`` in the diffuser plane, which is
  the "effective extent" of eq. 2, and the kernel element that matches it is
  ``varsigma*K_pt`` with ``varsigma`` from eq. 4.

Screen point ``X`` therefore sees ``sum_j K_j F(X/(M F_pt) + offset_j)``: the
shadows of sources at increasing positions sample the mask at increasing
positions. The device computes a **cross-correlation** (``out[i] = sum_j K[j]
F[i+j]``, scipy's ``correlate2d``), the same form as the paper's discretised
response with a light-transport matrix. If the relay between kernel DMD and
diffuser inverts the image (a single imaging lens does), the kernel reaches the
diffuser flipped and the device computes a true convolution
(``convolve2d``); :attr:`Bench.kernel_flipped` selects this.

Response units: :func:`screen_response` returns, per sensor pixel, the light
it collects in units of "one fully lit kernel element seen through one open
feature element", averaged over the pixel's footprint. In the ideal case
(matched scaling, stride 1, point sources, no blur) it equals the digital
correlation of kernel and features exactly.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
from dataclasses import dataclass, field

import numpy as np
from scipy import special

from .errors import EvtkError, check_parameters

__all__ = [
    "Bench",
    "effective_extents_um",
    "optical_scaling",
    "software_scaling",
    "stride_mm",
    "effective_stride",
    "min_capture_window_us",
    "shadow_magnification",
    "screen_response",
    "ideal_response",
    "glow_response",
    "brightest_response",
    "response_region",
    "response_origin_px",
    "response_to_sensor_grid",
    "load_bench",
    "save_bench",
    "PHOTON_ENERGY_J_PER_NM",
]

#: Planck constant times speed of light (J*nm): photon energy = this / wavelength_nm.
PHOTON_ENERGY_J_PER_NM = 6.62607015e-34 * 299792458.0 * 1e9


# --------------------------------------------------------------------------------------
# The paper's equations, one function each
# --------------------------------------------------------------------------------------

def optical_scaling(u_mm, z_mm):
    """Optical scaling factor ``sigma = (u + z) / u`` (eq. 3).

    Parameters
    ----------
    u_mm : float
        Feature DMD to screen distance.
    z_mm : float
        Diffuser (kernel image) to feature DMD distance.

    Examples
    --------
    >>> optical_scaling(300.0, 100.0)
    1.3333333333333333
    """
    _positive(u_mm=u_mm, z_mm=z_mm)
    return (u_mm + z_mm) / u_mm


def software_scaling(sigma, feature_pitch_um, kernel_pitch_um):
    """Kernel upsampling ``varsigma = sigma * F_pt / K_pt`` that matches element extents (eq. 4).

    Examples
    --------
    >>> software_scaling(4 / 3, 45.36, 7.56)
    8.0
    """
    _positive(sigma=sigma, feature_pitch_um=feature_pitch_um, kernel_pitch_um=kernel_pitch_um)
    return sigma * feature_pitch_um / kernel_pitch_um


def effective_extents_um(kernel_pitch_um, feature_pitch_um, sigma, varsigma):
    """Effective extents ``K_eff = varsigma*K_pt`` and ``F_eff = sigma*F_pt`` (eq. 2).

    Both are lengths in the diffuser plane; they are equal when ``varsigma``
    comes from :func:`software_scaling`.

    Returns
    -------
    (k_eff_um, f_eff_um) : tuple of float
    """
    _positive(kernel_pitch_um=kernel_pitch_um, feature_pitch_um=feature_pitch_um, sigma=sigma, varsigma=varsigma)
    return varsigma * kernel_pitch_um, sigma * feature_pitch_um


def stride_mm(u_mm, z_mm, sensor_pitch_um):
    """Stride in the diffuser plane per sensor pixel, ``S_mm = z * Phi_pt / u`` (eq. 5).

    ``sensor_pitch_um`` is the footprint of one sensor pixel on the screen.
    """
    _positive(u_mm=u_mm, z_mm=z_mm, sensor_pitch_um=sensor_pitch_um)
    return z_mm * (sensor_pitch_um * 1e-3) / u_mm


def effective_stride(u_mm, z_mm, sensor_pitch_um, feature_pitch_um, decimation=1, k_eff_um=None):
    """Effective stride in kernel elements per output sample (eq. 6).

    ``S_eff = S_mm * Delta / K_eff``. With ``k_eff_um`` omitted the kernel is
    taken as matched (``K_eff = sigma * F_pt``), which gives the closed form
    ``z * Phi_pt * Delta / (F_pt * (u + z))``.

    Examples
    --------
    >>> round(effective_stride(300.0, 100.0, 181.44, 45.36), 12)
    1.0
    >>> round(effective_stride(300.0, 100.0, 181.44, 45.36, decimation=2), 12)
    2.0
    """
    if int(decimation) != decimation or decimation < 1:
        raise EvtkError(f"decimation must be a positive integer, not {decimation!r}")
    s_mm = stride_mm(u_mm, z_mm, sensor_pitch_um)
    if k_eff_um is None:
        _positive(feature_pitch_um=feature_pitch_um)
        return z_mm * sensor_pitch_um * decimation / (feature_pitch_um * (u_mm + z_mm))
    _positive(k_eff_um=k_eff_um)
    return s_mm * 1e3 * decimation / k_eff_um


def min_capture_window_us(kernel_hz, features_hz, pixel_latency_us):
    """Shortest capture window ``e_min = 1 / h_min``, ``h_min = min(K_hz, F_hz, 1/S_I)`` (eq. 7).

    Examples
    --------
    >>> min_capture_window_us(9523.0, 9523.0, 200.0)
    200.0
    """
    _positive(kernel_hz=kernel_hz, features_hz=features_hz, pixel_latency_us=pixel_latency_us)
    h_min_hz = min(kernel_hz, features_hz, 1e6 / pixel_latency_us)
    return 1e6 / h_min_hz


def shadow_magnification(u_mm, z_mm):
    """Magnification ``M = (u + z) / z`` of the feature mask's shadow on the screen."""
    _positive(u_mm=u_mm, z_mm=z_mm)
    return (u_mm + z_mm) / z_mm


def _positive(**values):
    for name, v in values.items():
        try:
            ok = math.isfinite(float(v)) and float(v) > 0
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise EvtkError(f"{name} must be a positive finite number, not {v!r}")


# --------------------------------------------------------------------------------------
# The bench description
# --------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Bench:
    """Everything about the optical bench that the simulator needs.

    Defaults follow the paper's hardware (514 nm laser, two 0.65-inch 1080p
    DMDs with 7.56 um mirrors, a DVXplorer Lite at 320x240). Distances, the
    screen-side pixel pitch and the light budget are not given in the paper;
    the defaults are chosen so that scaling is matched (eq. 4 gives a whole
    number of mirrors) and the effective stride is 1 (eq. 6).

    Attributes
    ----------
    u_mm, z_mm : float
        Feature DMD to screen, and diffuser to feature DMD distances.
    mirror_pitch_um : float
        Mirror pitch of both DMDs (``K_pt`` for the kernel).
    dmd_cols, dmd_rows : int
        Mirrors per DMD; a displayed pattern must fit.
    feature_upsample : int
        Mirrors per feature element along each axis (``F_pt`` = this x pitch).
    kernel_upsample : int or None
        Mirrors per kernel element; None takes eq. 4 rounded to a whole number.
    sensor_pitch_um : float
        Footprint of one sensor pixel on the screen (``Phi_pt``).
    decimation : int
        Keep every ``decimation``-th sensor pixel when reconstructing (``Delta``).
    sensor_width, sensor_height : int
        Event camera resolution.
    kernel_hz, features_hz : float
        Pattern rates of the two DMDs.
    pixel_latency_us : float
        Event camera pixel latency (``S_I`` of eq. 7).
    wavelength_nm, power_mw : float
        Laser.
    efficiency : float
        Photoelectrons produced in the pixel that images one feature element
        per photon leaving one kernel element (diffuser spread, feature DMD,
        screen scatter, camera lens, quantum efficiency together).
    dmd_contrast : float
        On/off contrast of each DMD; an off mirror passes ``1/dmd_contrast``.
    stray_light : float
        Ambient light on the screen, in response units (a floor).
    psf_sigma_um : float
        Gaussian blur of the diffuser on the screen (standard deviation).
    source_extent : {"point", "area"}
        "area": each kernel element is a uniform square source; "point": it
        emits from its centre (the idealised device).
    kernel_flipped : bool
        The relay inverts the kernel image, turning correlation into convolution.
    origin_px : tuple of float or None
        Sensor pixel (x, y) where the full response begins; None centres it.
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

    def __post_init__(self):
        _positive(u_mm=self.u_mm, z_mm=self.z_mm, mirror_pitch_um=self.mirror_pitch_um,
                  sensor_pitch_um=self.sensor_pitch_um, kernel_hz=self.kernel_hz, features_hz=self.features_hz,
                  pixel_latency_us=self.pixel_latency_us, wavelength_nm=self.wavelength_nm,
                  dmd_contrast=self.dmd_contrast)
        for name in ("dmd_cols", "dmd_rows", "feature_upsample", "decimation", "sensor_width", "sensor_height"):
            v = getattr(self, name)
            if isinstance(v, bool) or int(v) != v or v < 1:
                raise EvtkError(f"bench {name} must be a positive integer, not {v!r}")
            object.__setattr__(self, name, int(v))
        if self.sensor_width > 32767 or self.sensor_height > 32767:
            raise EvtkError("bench sensor size must be at most 32767 pixels per side")
        if self.kernel_upsample is not None:
            v = self.kernel_upsample
            if isinstance(v, bool) or int(v) != v or v < 1:
                raise EvtkError(f"bench kernel_upsample must be a positive integer or None, not {v!r}")
            object.__setattr__(self, "kernel_upsample", int(v))
        for name in ("power_mw", "efficiency", "stray_light", "psf_sigma_um"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise EvtkError(f"bench {name} must be a finite number >= 0, not {v!r}")
        if self.dmd_contrast < 1:
            raise EvtkError(f"bench dmd_contrast must be >= 1, not {self.dmd_contrast!r}")
        if self.source_extent not in ("point", "area"):
            raise EvtkError(f"bench source_extent must be 'point' or 'area', not {self.source_extent!r}")
        if self.origin_px is not None:
            o = tuple(float(v) for v in self.origin_px)
            if len(o) != 2 or not all(math.isfinite(v) for v in o):
                raise EvtkError(f"bench origin_px must be two finite numbers (x, y), not {self.origin_px!r}")
            object.__setattr__(self, "origin_px", o)

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

    def shadow_model_note(self) -> str | None:
        """A sentence saying why the ray-optics shadow model does not hold for this bench, or None when it does."""
        if self.fresnel_number >= 1.0:
            return None
        pixels = self.diffraction_spread_um / self.sensor_pitch_um
        return (f"Fresnel number {self.fresnel_number:.3g} < 1: each feature element diffracts over about "
                f"{self.diffraction_spread_um / 1000:.3g} mm on the screen ({pixels:.3g} sensor pixels), which the "
                "simulated shadows leave out (shorter u_mm or larger feature elements make them valid)")

    def photons_per_s(self) -> float:
        """Laser photon rate."""
        return self.power_mw * 1e-3 * self.wavelength_nm / PHOTON_ENERGY_J_PER_NM

    def electrons_per_s_per_unit(self, kernel_shape) -> float:
        """Photoelectron rate of a pixel per response unit (see :func:`screen_response`).

        The laser is spread over the kernel's footprint (all its elements, lit
        or not); a pixel collects in proportion to its footprint area.
        """
        kh, kw = kernel_shape
        return self.photons_per_s() / (kh * kw) * self.efficiency * self.pixel_cells ** 2

    def check_pattern(self, kernel_shape, features_shape):
        """Raise if a kernel or feature pattern does not fit its DMD."""
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
        d = dataclasses.asdict(self)
        if d["origin_px"] is not None:
            d["origin_px"] = list(d["origin_px"])
        return d

    @classmethod
    def from_dict(cls, d: dict) -> Bench:
        check_parameters("bench", cls, d)
        return cls(**d)

    def replace(self, **changes) -> Bench:
        return dataclasses.replace(self, **changes)


# --------------------------------------------------------------------------------------
# Bench files (TOML or JSON); an optional [sensor] table is returned alongside
# --------------------------------------------------------------------------------------

def load_bench(path):
    """Read a bench description; returns ``(Bench, sensor_dict)``.

    TOML (``.toml``) or JSON (anything else). Top-level keys are :class:`Bench`
    fields; an optional ``sensor`` table holds :class:`evtk.sensor.SensorModel`
    fields.
    """
    path = os.fspath(path)
    try:
        with open(path, "rb") as f:
            raw = f.read()
    except OSError as exc:
        raise EvtkError(f"{path}: cannot read bench file: {exc.strerror or exc}") from None
    try:
        if path.lower().endswith(".toml"):
            try:
                import tomllib
            except ModuleNotFoundError:  # Python 3.10
                import tomli as tomllib
            data = tomllib.loads(raw.decode("utf-8"))
        else:
            data = json.loads(raw.decode("utf-8"))
    except Exception as exc:  # noqa: BLE001 - any parse failure is the user's file
        raise EvtkError(f"{path}: not a valid bench file: {exc}") from None
    if not isinstance(data, dict):
        raise EvtkError(f"{path}: a bench file holds a table of parameters")
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


def _toml_value(v):
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        if isinstance(v, float) and not math.isfinite(v):
            raise EvtkError(f"cannot store {v!r} in a bench file")
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise EvtkError(f"cannot store {v!r} in a bench file")


def save_bench(path, bench: Bench, sensor=None):
    """Write a bench description as TOML (``.toml``) or JSON; atomic.

    ``sensor`` is an optional :class:`evtk.sensor.SensorModel` or dict. Unset
    optional values (None) are left out.
    """
    from .io._atomic import AtomicFile

    data = bench.to_dict()
    sdata = None
    if sensor is not None:
        sdata = sensor.to_dict() if hasattr(sensor, "to_dict") else dict(sensor)
    path = os.fspath(path)
    if path.lower().endswith(".toml"):
        lines = ["# evtk bench description"]
        lines += [f"{k} = {_toml_value(v)}" for k, v in data.items() if v is not None]
        if sdata:
            lines += ["", "[sensor]"] + [f"{k} = {_toml_value(v)}" for k, v in sdata.items() if v is not None]
        text = "\n".join(lines) + "\n"
    else:
        out = {k: v for k, v in data.items() if v is not None}
        if sdata:
            out["sensor"] = {k: v for k, v in sdata.items() if v is not None}
        text = json.dumps(out, indent=2) + "\n"
    with AtomicFile(path) as f:
        f.write(text.encode("utf-8"))


# --------------------------------------------------------------------------------------
# Light transport
# --------------------------------------------------------------------------------------

def _phi1(x):
    """First antiderivative of the normal CDF: x*Phi(x) + phi(x)."""
    return x * special.ndtr(x) + np.exp(-0.5 * x * x) / math.sqrt(2 * math.pi)


def _phi2(x):
    """Second antiderivative of the normal CDF: ((x^2+1)*Phi(x) + x*phi(x)) / 2."""
    return 0.5 * ((x * x + 1.0) * special.ndtr(x) + x * np.exp(-0.5 * x * x) / math.sqrt(2 * math.pi))


def _footprint_cdf(t, a, b, s):
    """CDF at ``t`` of U(0,a) + U(0,b) + N(0,s^2); ``b`` and ``s`` may be 0.

    ``a`` is the pixel footprint, ``b`` the source extent and ``s`` the blur,
    all in feature elements. Closed forms only, so the ideal case is exact.
    """
    t = np.asarray(t, dtype=np.float64)
    tiny = 1e-4 * a
    if s <= tiny:
        if b <= 0:
            return np.clip(t / a, 0.0, 1.0)
        r = lambda v: np.maximum(v, 0.0) ** 2  # noqa: E731
        return np.clip((r(t) - r(t - a) - r(t - b) + r(t - a - b)) / (2 * a * b), 0.0, 1.0)
    if b <= 0:
        return np.clip(s / a * (_phi1(t / s) - _phi1((t - a) / s)), 0.0, 1.0)
    return np.clip(s * s / (a * b) * (_phi2(t / s) - _phi2((t - a) / s) - _phi2((t - b) / s)
                                      + _phi2((t - a - b) / s)), 0.0, 1.0)


def _axis_weights(pixels, n_cells, k, bench: Bench, origin, psf_cells):
    """W[j, i, n]: share of pixel ``pixels[i]``'s view of kernel element ``j``'s shadow in cell ``n``."""
    pixels = np.asarray(pixels)
    if pixels.size and np.array_equal(pixels, np.arange(pixels[0], pixels[0] + pixels.size)):
        # the usual call: a run of pixels; the same geometry recurs for every capture of a run
        return _axis_weights_run(int(pixels[0]), int(pixels.size), int(n_cells), int(k), bench.pixel_cells,
                                 bench.kernel_step_cells, bench.source_extent, bool(bench.kernel_flipped),
                                 float(origin), float(psf_cells))
    return _axis_weights_of(pixels, n_cells, k, bench.pixel_cells, bench.kernel_step_cells, bench.source_extent,
                            bench.kernel_flipped, origin, psf_cells)


@functools.lru_cache(maxsize=64)
def _axis_weights_run(p0, n, n_cells, k, s1, kappa, source_extent, flipped, origin, psf_cells):
    w = _axis_weights_of(np.arange(p0, p0 + n), n_cells, k, s1, kappa, source_extent, flipped, origin, psf_cells)
    w.setflags(write=False)
    return w


def _axis_weights_of(pixels, n_cells, k, s1, kappa, source_extent, flipped, origin, psf_cells):
    b = kappa if source_extent == "area" else 0.0
    j = np.arange(k, dtype=np.float64)
    if flipped:
        j = j[::-1].copy()
    # footprint centre of pixel x for element j: (x - origin) * s1 + (j - (k - 1)) * kappa + 1/2
    centre = (np.asarray(pixels, np.float64)[None, :] - origin) * s1 + (j[:, None] - (k - 1)) * kappa + 0.5
    low = centre - 0.5 * (s1 + b)  # start of U(0, s1) + U(0, b)
    edges = np.arange(n_cells + 1, dtype=np.float64)
    cdf = _footprint_cdf(edges[None, None, :] - low[:, :, None], s1, b, psf_cells)
    # rounding in the blurred closed form can make the CDF dip by ~1e-15: keep light non-negative
    return np.diff(np.maximum.accumulate(cdf, axis=2), axis=2)


def response_origin_px(bench: Bench, kernel_shape, features_shape):
    """Sensor pixel (x, y) whose footprint sees cell (0, 0) of the full response.

    ``bench.origin_px`` when set, else the position that centres the full
    response on the sensor.
    """
    if bench.origin_px is not None:
        return bench.origin_px
    kh, kw = kernel_shape
    fh, fw = features_shape
    # centre the full response: it spans (f + k - 1) * kappa... in cells, i.e. that / s1 pixels
    span_x = (fw + (kw - 1) * bench.kernel_step_cells) / bench.pixel_cells
    span_y = (fh + (kh - 1) * bench.kernel_step_cells) / bench.pixel_cells
    return (math.floor((bench.sensor_width - span_x) / 2), math.floor((bench.sensor_height - span_y) / 2))


def response_region(bench: Bench, kernel_shape, features_shape):
    """Sensor pixels the pattern's shadow can reach: ``(x0, x1, y0, y1)``, half-open, clipped."""
    kh, kw = kernel_shape
    fh, fw = features_shape
    ox, oy = response_origin_px(bench, kernel_shape, features_shape)
    s1 = bench.pixel_cells
    kappa = bench.kernel_step_cells
    # the footprint of a pixel spreads half a pixel and half a source element each way, plus blur
    spread = 0.5 * s1 + (0.5 * kappa if bench.source_extent == "area" else 0.0)
    spread += 6.0 * bench.psf_sigma_um / (shadow_magnification(bench.u_mm, bench.z_mm) * bench.feature_pitch_um)

    def span(origin, k, f, n):
        # pixel x sees cells (x - origin) * s1 + (j - (k-1)) * kappa + 1/2 +- spread, j in [0, k)
        lo = origin + (-(spread + 0.5)) / s1
        hi = origin + (f - 0.5 + (k - 1) * kappa + spread) / s1
        return max(0, math.floor(lo)), min(n, math.floor(hi) + 1)

    x0, x1 = span(ox, kw, fw, bench.sensor_width)
    y0, y1 = span(oy, kh, fh, bench.sensor_height)
    return x0, max(x0, x1), y0, max(y0, y1)


def _binary(name, a):
    a = np.asarray(a)
    if a.ndim != 2 or a.size == 0:
        raise EvtkError(f"{name} must be a non-empty 2-D array, got shape {a.shape}")
    if not np.all(np.isfinite(a)) or not np.all((a == 0) | (a == 1)):
        raise EvtkError(f"{name} must be a binary DMD pattern (0/1); split signed patterns into passes first")
    return a.astype(np.float64)


def screen_response(kernel, features, bench: Bench, region=None, *, leak=True):
    """Light collected by each sensor pixel for one displayed (kernel, features) pair.

    Parameters
    ----------
    kernel, features : array_like of {0, 1}
        The binary patterns shown on the two DMDs (one pass).
    bench : Bench
    region : (x0, x1, y0, y1), optional
        Sensor pixels to compute (half-open); default the whole sensor.
    leak : bool
        Include off-mirror leakage and stray light (True for a real bench).

    Returns
    -------
    ndarray, shape (y1 - y0, x1 - x0), float64
        In units of one lit kernel element seen through one open feature
        element, averaged over the pixel's footprint. Pixels away from the
        pattern see the uniform glow of leaking mirrors plus stray light.
    """
    k = _binary("kernel", kernel)
    f = _binary("features", features)
    bench.check_pattern(k.shape, f.shape)
    if region is None:
        region = (0, bench.sensor_width, 0, bench.sensor_height)
    x0, x1, y0, y1 = region
    lk = bench.leak if leak else 0.0
    k_eff = k + lk * (1.0 - k)  # off kernel mirrors in the lit footprint leak
    out = np.zeros((y1 - y0, x1 - x0))
    if leak:  # the whole feature DMD glows where it is off ...
        out += glow_response(k, bench)
    # ... and the pattern adds (1 - lk) where its elements are on
    rx0, rx1, ry0, ry1 = response_region(bench, k.shape, f.shape)
    ax0, ax1, ay0, ay1 = max(x0, rx0), min(x1, rx1), max(y0, ry0), min(y1, ry1)
    if ax1 <= ax0 or ay1 <= ay0 or not f.any():
        return out
    ox, oy = response_origin_px(bench, k.shape, f.shape)
    psf_cells = bench.psf_sigma_um / (shadow_magnification(bench.u_mm, bench.z_mm) * bench.feature_pitch_um)
    wx = _axis_weights(np.arange(ax0, ax1), f.shape[1], k.shape[1], bench, ox, psf_cells)  # (kw, nx, fw)
    wy = _axis_weights(np.arange(ay0, ay1), f.shape[0], k.shape[0], bench, oy, psf_cells)  # (kh, ny, fh)
    patch = np.zeros((ay1 - ay0, ax1 - ax0))
    for r in range(k.shape[0]):
        a = wy[r] @ f  # (ny, fw)
        for c in range(k.shape[1]):
            if k_eff[r, c] != 0:
                patch += k_eff[r, c] * (a @ wx[c].T)
    out[ay0 - y0:ay1 - y0, ax0 - x0:ax1 - x0] += (1.0 - lk) * patch
    return out


def glow_response(kernel, bench: Bench) -> float:
    """Light every pixel gets whatever the features show: off feature mirrors leak.

    ``leak * sum(K')`` with ``K' = K + leak * (1 - K)`` (off kernel mirrors
    leak too), plus stray light, in the units of :func:`screen_response`.
    With both DMDs dark (``kernel`` all zero) it is the blank level.
    """
    k = np.asarray(kernel, dtype=np.float64)
    lk = bench.leak
    return float(lk * (k + lk * (1.0 - k)).sum() + bench.stray_light)


def brightest_response(kernel_shape, bench: Bench) -> float:
    """The most light a pixel can get: every kernel element through open features, plus stray light."""
    kh, kw = kernel_shape
    return float(kh * kw + bench.stray_light)


def ideal_response(kernel, features, bench: Bench | None = None):
    """The digital response the device approximates: full 2-D correlation (or convolution).

    ``scipy.signal.correlate2d(features, kernel, mode="full")``, or
    ``convolve2d`` when ``bench.kernel_flipped``. Accepts signed patterns.
    """
    from scipy import signal

    k = np.asarray(kernel, dtype=np.float64)
    f = np.asarray(features, dtype=np.float64)
    if bench is not None and bench.kernel_flipped:
        return signal.convolve2d(f, k, mode="full")
    return signal.correlate2d(f, k, mode="full")


def response_to_sensor_grid(bench: Bench, kernel_shape, features_shape):
    """Sensor pixel centres (x, y) of each cell of the full ideal response, in pixel units.

    Cell ``(i, j)`` of :func:`ideal_response` is centred on sensor coordinate
    ``origin + i * kappa / s1`` (kappa the kernel step, s1 the pixel footprint,
    both in feature elements; pixel ``x`` is centred on ``x``). At stride 1
    that cell is exactly pixel ``origin + i``'s footprint.
    """
    kh, kw = kernel_shape
    fh, fw = features_shape
    ox, oy = response_origin_px(bench, kernel_shape, features_shape)
    step = bench.kernel_step_cells / bench.pixel_cells
    # full-response cell i sits where element (k-1) of pixel x sees cell i - (k-1) -> x = origin + i*kappa/s1
    xs = ox + np.arange(fw + kw - 1) * step
    ys = oy + np.arange(fh + kh - 1) * step
    return xs, ys
