"""The Poisson model of eqs. 9-11 in log space: probabilities and the cumulative factor ``C``."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from ..errors import EvtkError

if TYPE_CHECKING:
    import numpy.typing as npt

__all__ = [
    "poisson_log_pmf", "poisson_pmf", "log_cumulative_factor", "cumulative_factor",
    "lowest_cumulative_factor", "capture_terms",
]


# -- Poisson model (eqs. 9-11) ------------------------------------------------------------

_HALF_LOG_2PI = 0.5 * math.log(2 * math.pi)


def _stirlerr(k):
    """``log(k!) - ((k + 1/2) log k - k + log(2 pi)/2)`` for k >= 1, without cancellation."""
    from scipy.special import gammaln

    k = np.asarray(k, dtype=np.float64)
    out = np.empty_like(k)
    small = k < 16
    ks = k[small]
    out[small] = gammaln(ks + 1) - (ks + 0.5) * np.log(ks) + ks - _HALF_LOG_2PI
    kl = k[~small]
    k2 = 1.0 / (kl * kl)
    out[~small] = (1.0 / 12 - k2 * (1.0 / 360 - k2 * (1.0 / 1260 - k2 * (1.0 / 1680)))) / kl
    return out


def _bd0(k, lam):
    """``k log(k / lam) + lam - k`` (>= 0), stable when k is close to lam."""
    k = np.asarray(k, dtype=np.float64)
    lam = np.asarray(lam, dtype=np.float64)
    d = (k - lam) / lam
    near = np.abs(d) < 1e-2
    out = np.empty(np.broadcast(k, lam).shape)
    dn = np.broadcast_to(d, out.shape)[near]
    # (1 + d) log(1 + d) - d = sum_{n>=2} (-1)^n d^n / (n (n - 1))
    series = np.zeros_like(dn)
    term = dn * dn
    for n in range(2, 14):
        series += (term if n % 2 == 0 else -term) / (n * (n - 1))
        term = term * dn
    lam_b = np.broadcast_to(lam, out.shape)
    out[near] = lam_b[near] * series
    far = ~near
    kb = np.broadcast_to(k, out.shape)[far]
    lb = lam_b[far]
    out[far] = kb * np.log(kb / lb) + lb - kb
    return out


def _check_lam(lam, name="lam"):
    lam = np.asarray(lam, dtype=np.float64)
    if not np.all(np.isfinite(lam)) or np.any(lam < 0):
        raise EvtkError(f"{name} (expected photon count) must be finite and >= 0")
    return lam


def poisson_log_pmf(k: npt.ArrayLike, lam: npt.ArrayLike) -> float | np.ndarray:
    """Natural log of the Poisson probability of ``k`` photons at expected count ``lam`` (eq. 9).

    ``log P(X = k) = k log(lam) - lam - log(k!)``, computed through
    Stirling's error term and a deviance that keeps full precision when ``k``
    and ``lam`` are large and close (1e12 photons: about 1e-15 relative
    error, where the textbook formula loses three digits). ``lam = 0`` gives
    0 for ``k = 0`` and ``-inf`` otherwise.

    Parameters
    ----------
    k : array_like of int
        Photon counts, whole numbers >= 0 (integer or whole float values).
    lam : array_like of float
        Expected photon counts ``lambda``, finite and >= 0; broadcast against ``k``.

    Returns
    -------
    float or numpy.ndarray
        ``log P(X = k)`` in nats: a float for scalar inputs, else float64 of the broadcast shape.

    Raises
    ------
    EvtkError
        If ``k`` holds a negative or fractional count, or ``lam`` a negative or non-finite value.

    Examples
    --------
    >>> bool(np.isclose(np.exp(poisson_log_pmf(2, 3.0)), 9 * np.exp(-3) / 2, rtol=1e-14))
    True
    """
    k_arr = np.asarray(k)
    if not np.issubdtype(k_arr.dtype, np.integer):
        kf = np.asarray(k_arr, dtype=np.float64)
        if not np.all(np.isfinite(kf)) or np.any(kf != np.floor(kf)):
            raise EvtkError("photon counts k must be whole numbers")
    kf = np.asarray(k_arr, dtype=np.float64)
    if np.any(kf < 0):
        raise EvtkError("photon counts k must be >= 0")
    lam = _check_lam(lam)
    kb, lb = np.broadcast_arrays(kf, lam)
    out = np.empty(kb.shape)
    zero_k = kb == 0
    out[zero_k] = -lb[zero_k]
    dark = (lb == 0) & ~zero_k
    out[dark] = -np.inf
    rest = ~zero_k & ~dark
    kr, lr = kb[rest], lb[rest]
    out[rest] = -_stirlerr(kr) - _bd0(kr, lr) - 0.5 * np.log(kr) - _HALF_LOG_2PI
    return float(out) if out.ndim == 0 else out


def poisson_pmf(k: npt.ArrayLike, lam: npt.ArrayLike) -> float | np.ndarray:
    """Poisson probability of ``k`` photons at expected count ``lam`` (eq. 9); underflows to 0 honestly.

    Parameters
    ----------
    k : array_like of int
        Photon counts, whole numbers >= 0.
    lam : array_like of float
        Expected photon counts, finite and >= 0; broadcast against ``k``.

    Returns
    -------
    float or numpy.ndarray
        ``P(X = k)`` in [0, 1]: a float for scalar inputs, else float64 of the broadcast shape.

    Raises
    ------
    EvtkError
        As :func:`poisson_log_pmf`.
    """
    v = np.exp(poisson_log_pmf(k, lam))
    return float(v) if np.ndim(v) == 0 else v


def capture_terms(window_us: float, time_unit_us: float = 1.0) -> int:
    """``N_e`` of eq. 10: whole time units in a capture window of ``window_us``.

    Parameters
    ----------
    window_us : float
        Temporal capture window ``e``, us (>= 0).
    time_unit_us : float, optional
        The time unit of the photon flux ``phi``, us (> 0).

    Returns
    -------
    int
        ``floor(window_us / time_unit_us)`` (a window a hair short of a whole unit, 1e-9 units, counts it).

    Raises
    ------
    EvtkError
        If either value is not finite, the window is negative or the unit not positive.
    """
    if not (np.isfinite(window_us) and np.isfinite(time_unit_us)) or window_us < 0 or time_unit_us <= 0:
        raise EvtkError("window_us must be >= 0 and time_unit_us > 0, both finite")
    return int(math.floor(window_us / time_unit_us + 1e-9))


def _log_cf_scalar(lam: float, phi: int, n: int) -> float:
    if n <= 0 or lam == 0.0:
        return -math.inf  # no term, or no photon can arrive: C = 0
    # P(X = i phi) is unimodal in i: start at the best multiple of phi inside [1, n], sum outwards
    cands = {min(max(int(math.floor(lam / phi)), 1), n), min(max(int(math.ceil(lam / phi)), 1), n)}
    logp = lambda i: poisson_log_pmf(np.asarray(i, dtype=np.float64) * phi, lam)  # noqa: E731
    i_m = max(cands, key=lambda i: float(logp(i)))
    top = float(logp(i_m))
    total = 1.0
    for direction in (1, -1):
        start, size = i_m + direction, 256
        while (direction > 0 and start <= n) or (direction < 0 and start >= 1):
            stop = min(n, start + size - 1) if direction > 0 else max(1, start - size + 1)
            idx = np.arange(start, stop + direction, direction, dtype=np.float64)
            rel = np.exp(logp(idx) - top)
            total += float(rel.sum())
            if rel[-1] < 1e-18:  # every later term is smaller still
                break
            start, size = stop + direction, size * 2
    return top + math.log(total)


def log_cumulative_factor(
    lam: npt.ArrayLike, photons_per_unit: int = 1, n_terms: int = 1
) -> float | np.ndarray:
    """Natural log of the cumulative factor ``C`` of eq. 10.

    ``C = sum_{i=1}^{N_e} P(X = i * phi)``: the Poisson probabilities (eq. 9,
    expected count ``lam``, proportional to the source's brightness) of
    receiving a whole number ``i`` of time units' worth of photons at flux
    ``phi = photons_per_unit`` within a capture of ``N_e = n_terms`` time
    units (:func:`capture_terms`). It is 0 (log: ``-inf``) in the dark or with
    no time, and approaches ``1 - exp(-lam)`` for ``phi = 1`` as the window
    grows. Summed in log space from its largest term outward, so it stays
    finite where ``C`` itself would underflow (``lam = 1e12`` with a short
    window gives about ``-1e12``).

    Parameters
    ----------
    lam : array_like of float
        Expected photon counts ``lambda``, finite and >= 0 (any shape).
    photons_per_unit : int, optional
        Photon flux ``phi`` in photons per time unit, a whole number >= 1.
    n_terms : int, optional
        ``N_e``, the time units in the capture window, a whole number >= 0.

    Returns
    -------
    float or numpy.ndarray
        ``log C`` in nats (<= 0, ``-inf`` where ``C = 0``): a float for a scalar ``lam``, else float64 shaped
        like ``lam``.

    Raises
    ------
    EvtkError
        If ``lam`` is negative or not finite, or ``photons_per_unit`` / ``n_terms`` not whole numbers in range.

    Examples
    --------
    >>> from scipy import stats
    >>> c = np.exp(log_cumulative_factor(4.0, 1, 6))
    >>> bool(np.isclose(c, stats.poisson.cdf(6, 4.0) - stats.poisson.pmf(0, 4.0)))
    True
    """
    lam = _check_lam(lam)
    phi = int(photons_per_unit)
    if phi != photons_per_unit or phi < 1:
        raise EvtkError(f"photons_per_unit must be a whole number >= 1, not {photons_per_unit!r}")
    n = int(n_terms)
    if n != n_terms or n < 0:
        raise EvtkError(f"n_terms must be a whole number >= 0, not {n_terms!r}")
    out = np.vectorize(lambda v: _log_cf_scalar(float(v), phi, n), otypes=[np.float64])(lam)
    return float(out) if out.ndim == 0 else out


def cumulative_factor(
    lam: npt.ArrayLike, photons_per_unit: int = 1, n_terms: int = 1
) -> float | np.ndarray:
    """The cumulative factor ``C`` of eq. 10 (``exp`` of :func:`log_cumulative_factor`).

    Parameters
    ----------
    lam : array_like of float
        Expected photon counts ``lambda``, finite and >= 0.
    photons_per_unit : int, optional
        Photon flux ``phi`` in photons per time unit, a whole number >= 1.
    n_terms : int, optional
        ``N_e``, the time units in the capture window, a whole number >= 0.

    Returns
    -------
    float or numpy.ndarray
        ``C`` in [0, 1] (underflows to 0 where :func:`log_cumulative_factor` stays finite), shaped like ``lam``.

    Raises
    ------
    EvtkError
        As :func:`log_cumulative_factor`.
    """
    v = np.exp(log_cumulative_factor(lam, photons_per_unit, n_terms))
    return float(v) if np.ndim(v) == 0 else v


def lowest_cumulative_factor(
    intensities: npt.ArrayLike,
    photons_per_intensity: float,
    photons_per_unit: int = 1,
    n_terms: int = 1,
    log: bool = False,
) -> float | np.ndarray:
    """``C_low`` of eq. 11: the cumulative factor of the dimmest input.

    ``lam_low = photons_per_intensity * min(intensities)`` (``rho_B`` times
    the lowest feature intensity); the bound of eq. 11 scales every
    convolution by this constant. ``log=True`` returns ``log C_low``.

    Parameters
    ----------
    intensities : array_like of float
        Feature intensities ``I_F`` over all inputs and layers, finite and >= 0, non-empty.
    photons_per_intensity : float
        ``rho_B``: expected photons per unit of intensity at the source's brightness (finite, >= 0).
    photons_per_unit : int, optional
        Photon flux ``phi`` in photons per time unit, a whole number >= 1.
    n_terms : int, optional
        ``N_e``, the time units in the capture window (:func:`capture_terms`).
    log : bool, optional
        Return ``log C_low`` (nats) instead of ``C_low``.

    Returns
    -------
    float
        ``C_low`` in [0, 1], or its natural log.

    Raises
    ------
    EvtkError
        If ``intensities`` is empty or holds negative or non-finite values, ``photons_per_intensity`` is
        negative or not finite, or the other arguments are out of range.

    Examples
    --------
    >>> lowest_cumulative_factor([0.5, 2.0, 1.0], 10.0, 1, 100) == cumulative_factor(5.0, 1, 100)
    True
    """
    i = np.asarray(intensities, dtype=np.float64)
    if i.size == 0 or not np.all(np.isfinite(i)) or np.any(i < 0):
        raise EvtkError("intensities must be a non-empty array of finite values >= 0")
    rho = float(photons_per_intensity)
    if not math.isfinite(rho) or rho < 0:
        raise EvtkError("photons_per_intensity must be finite and >= 0")
    f = log_cumulative_factor if log else cumulative_factor
    return f(rho * float(i.min()), photons_per_unit, n_terms)
