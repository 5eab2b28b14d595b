"""The bench's geometry in closed form: scalings, extents, strides and the shortest window (eqs. 2-7)."""

from __future__ import annotations

from ..errors import EvtkError, check_positive

__all__ = [
    "effective_extents_um", "optical_scaling", "software_scaling", "stride_mm", "effective_stride",
    "min_capture_window_us", "shadow_magnification", "PHOTON_ENERGY_J_PER_NM",
]


PHOTON_ENERGY_J_PER_NM = 6.62607015e-34 * 299792458.0 * 1e9



def optical_scaling(u_mm: float, z_mm: float) -> float:
    """Optical scaling factor ``sigma = (u + z) / u`` (eq. 3).

    Parameters
    ----------
    u_mm : float
        Feature DMD to screen distance, mm.
    z_mm : float
        Diffuser (kernel image) to feature DMD distance, mm.

    Returns
    -------
    float
        ``sigma``, dimensionless and greater than 1.

    Raises
    ------
    EvtkError
        If either distance is not a positive finite number.

    Examples
    --------
    >>> optical_scaling(300.0, 100.0)
    1.3333333333333333
    """
    check_positive(u_mm=u_mm, z_mm=z_mm)
    return (u_mm + z_mm) / u_mm


def software_scaling(sigma: float, feature_pitch_um: float, kernel_pitch_um: float) -> float:
    """Kernel upsampling ``varsigma = sigma * F_pt / K_pt`` that matches element extents (eq. 4).

    Parameters
    ----------
    sigma : float
        Optical scaling factor of eq. 3 (:func:`optical_scaling`).
    feature_pitch_um : float
        Mirror pitch ``F_pt`` of the feature DMD, um.
    kernel_pitch_um : float
        Mirror pitch ``K_pt`` of the kernel DMD, um.

    Returns
    -------
    float
        ``varsigma``: how many kernel-DMD mirrors one kernel element must span (dimensionless; not rounded).

    Raises
    ------
    EvtkError
        If any argument is not a positive finite number.

    Examples
    --------
    >>> software_scaling(4 / 3, 45.36, 7.56)
    8.0
    """
    check_positive(sigma=sigma, feature_pitch_um=feature_pitch_um, kernel_pitch_um=kernel_pitch_um)
    return sigma * feature_pitch_um / kernel_pitch_um


def effective_extents_um(
    kernel_pitch_um: float, feature_pitch_um: float, sigma: float, varsigma: float
) -> tuple[float, float]:
    """Effective extents ``K_eff = varsigma*K_pt`` and ``F_eff = sigma*F_pt`` (eq. 2).

    Both are lengths in the diffuser plane; they are equal when ``varsigma``
    comes from :func:`software_scaling`.

    Parameters
    ----------
    kernel_pitch_um : float
        Mirror pitch ``K_pt`` of the kernel DMD, um.
    feature_pitch_um : float
        Mirror pitch ``F_pt`` of the feature DMD, um.
    sigma : float
        Optical scaling factor of eq. 3.
    varsigma : float
        Software scaling (kernel upsampling) factor of eq. 4.

    Returns
    -------
    k_eff_um : float
        Effective extent of one kernel element, um.
    f_eff_um : float
        Effective extent of one feature element, um.

    Raises
    ------
    EvtkError
        If any argument is not a positive finite number.
    """
    check_positive(kernel_pitch_um=kernel_pitch_um, feature_pitch_um=feature_pitch_um, sigma=sigma, varsigma=varsigma)
    return varsigma * kernel_pitch_um, sigma * feature_pitch_um


def stride_mm(u_mm: float, z_mm: float, sensor_pitch_um: float) -> float:
    """Stride in the diffuser plane per sensor pixel, ``S_mm = z * Phi_pt / u`` (eq. 5).

    ``sensor_pitch_um`` is the footprint of one sensor pixel on the screen.

    Parameters
    ----------
    u_mm : float
        Feature DMD to screen distance, mm.
    z_mm : float
        Diffuser to feature DMD distance, mm.
    sensor_pitch_um : float
        Footprint ``Phi_pt`` of one sensor pixel on the screen, um.

    Returns
    -------
    float
        ``S_mm``, the source displacement in the diffuser plane that moves the response by one sensor pixel, mm.

    Raises
    ------
    EvtkError
        If any argument is not a positive finite number.
    """
    check_positive(u_mm=u_mm, z_mm=z_mm, sensor_pitch_um=sensor_pitch_um)
    return z_mm * (sensor_pitch_um * 1e-3) / u_mm


def effective_stride(
    u_mm: float,
    z_mm: float,
    sensor_pitch_um: float,
    feature_pitch_um: float,
    decimation: int = 1,
    k_eff_um: float | None = None,
) -> float:
    """Effective stride in kernel elements per output sample (eq. 6).

    ``S_eff = S_mm * Delta / K_eff``. With ``k_eff_um`` omitted the kernel is
    taken as matched (``K_eff = sigma * F_pt``), which gives the closed form
    ``z * Phi_pt * Delta / (F_pt * (u + z))``.

    Parameters
    ----------
    u_mm : float
        Feature DMD to screen distance, mm.
    z_mm : float
        Diffuser to feature DMD distance, mm.
    sensor_pitch_um : float
        Footprint ``Phi_pt`` of one sensor pixel on the screen, um.
    feature_pitch_um : float
        Mirror pitch ``F_pt`` of the feature DMD, um (used only for the matched closed form).
    decimation : int, optional
        Decimation factor ``Delta``: keep every ``Delta``-th sensor pixel (a positive integer).
    k_eff_um : float or None, optional
        Effective kernel element extent ``K_eff`` of eq. 2, um; None takes the matched kernel.

    Returns
    -------
    float
        ``S_eff``, kernel elements per output sample (fractional strides allowed).

    Raises
    ------
    EvtkError
        If ``decimation`` is not a positive integer or a length is not a positive finite number.

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
        check_positive(feature_pitch_um=feature_pitch_um)
        return z_mm * sensor_pitch_um * decimation / (feature_pitch_um * (u_mm + z_mm))
    check_positive(k_eff_um=k_eff_um)
    return s_mm * 1e3 * decimation / k_eff_um


def min_capture_window_us(kernel_hz: float, features_hz: float, pixel_latency_us: float) -> float:
    """Shortest capture window ``e_min = 1 / h_min``, ``h_min = min(K_hz, F_hz, 1/S_I)`` (eq. 7).

    Parameters
    ----------
    kernel_hz : float
        Refresh rate ``K_hz`` of the kernel DMD, Hz.
    features_hz : float
        Refresh rate ``F_hz`` of the feature DMD, Hz.
    pixel_latency_us : float
        Pixel latency ``S_I`` of the event camera, us.

    Returns
    -------
    float
        ``e_min``, the shortest capture window the slowest device allows, us.

    Raises
    ------
    EvtkError
        If any argument is not a positive finite number.

    Examples
    --------
    >>> min_capture_window_us(9523.0, 9523.0, 200.0)
    200.0
    """
    check_positive(kernel_hz=kernel_hz, features_hz=features_hz, pixel_latency_us=pixel_latency_us)
    h_min_hz = min(kernel_hz, features_hz, 1e6 / pixel_latency_us)
    return 1e6 / h_min_hz


def shadow_magnification(u_mm: float, z_mm: float) -> float:
    """Magnification ``M = (u + z) / z`` of the feature mask's shadow on the screen.

    Parameters
    ----------
    u_mm : float
        Feature DMD to screen distance, mm.
    z_mm : float
        Diffuser to feature DMD distance, mm.

    Returns
    -------
    float
        ``M``, dimensionless and greater than 1.

    Raises
    ------
    EvtkError
        If either distance is not a positive finite number.
    """
    check_positive(u_mm=u_mm, z_mm=z_mm)
    return (u_mm + z_mm) / z_mm


