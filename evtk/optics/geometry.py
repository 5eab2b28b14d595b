"""The bench's geometry in closed form: scalings, extents, strides and the shortest window (eqs. 2-7)."""

from __future__ import annotations

import math

from ..errors import EvtkError

__all__ = [
    "effective_extents_um", "optical_scaling", "software_scaling", "stride_mm", "effective_stride",
    "min_capture_window_us", "shadow_magnification", "PHOTON_ENERGY_J_PER_NM",
]


PHOTON_ENERGY_J_PER_NM = 6.62607015e-34 * 299792458.0 * 1e9



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
