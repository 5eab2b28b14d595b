"""How good the device's numbers are: SINAD and ENOB (eq. 8), flip rates, and the Poisson factors (eqs. 9-11).

* :func:`sinad` measures the signal-to-noise-and-distortion ratio of repeated
  captures of one scene (eq. 8) and :func:`enob_bits` turns it into effective
  bits; bootstrap confidence intervals resample the repeats.
* :func:`flip_rates` counts binarised pixels that change between repeated
  captures, pairwise and against the majority vote (the paper's Fig. 3).
* :func:`poisson_log_pmf` (eq. 9) and :func:`log_cumulative_factor` (the
  factor ``C`` of eq. 10, and ``C_low`` of eq. 11 through
  :func:`lowest_cumulative_factor`) work in log space, so photon counts from
  1e-12 to 1e12 neither underflow nor overflow.

Every statistic is float64. Degenerate input is either a defined answer
(zero noise is ``SINAD = +inf`` with ``noise_free=True``) or an
:class:`evtk.EvtkError`, never NaN.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .errors import EvtkError

__all__ = [
    "SinadReport",
    "sinad",
    "enob_bits",
    "FlipReport",
    "flip_rates",
    "poisson_log_pmf",
    "poisson_pmf",
    "log_cumulative_factor",
    "cumulative_factor",
    "lowest_cumulative_factor",
    "capture_terms",
]


def _json_float(v):
    """inf/-inf/NaN as JSON null; everything else a plain float."""
    return float(v) if v is not None and np.isfinite(v) else None


def enob_bits(sinad_db):
    """Effective number of bits from SINAD in dB (eq. 8): ``(SINAD - 1.76) / 6.02``.

    ``+inf`` (noise-free) stays ``+inf``.

    Examples
    --------
    >>> round(enob_bits(6.02 * 8 + 1.76), 12)
    8.0
    """
    s = np.asarray(sinad_db, dtype=np.float64)
    if np.any(np.isnan(s)):
        raise EvtkError("SINAD is NaN")
    out = (s - 1.76) / 6.02
    return float(out) if out.ndim == 0 else out


@dataclass
class SinadReport:
    """What :func:`sinad` measured.

    Attributes
    ----------
    sinad_db, enob_bits : float
        Pooled over pixels; ``+inf`` when no pixel varies between repeats.
    noise_free : bool
        True when the pooled noise is exactly zero.
    signal_rms, noise_std : float
        ``RMS`` over all captures and pixels, and the pooled per-pixel
        standard deviation over repeats (ddof 1).
    repeats, pixels : int
    ci_db, ci_enob : (low, high) or None
        Bootstrap percentile interval over repeats (may reach ``+inf``).
    confidence : float
    per_pixel_db : numpy.ma.MaskedArray or None
        Per-pixel SINAD (shape of one capture), masked where a pixel has no
        signal at all; ``+inf`` where it has signal but no noise.
    """

    sinad_db: float
    enob_bits: float
    noise_free: bool
    signal_rms: float
    noise_std: float
    repeats: int
    pixels: int
    ci_db: tuple | None = None
    ci_enob: tuple | None = None
    confidence: float = 0.95
    per_pixel_db: np.ma.MaskedArray | None = None

    def to_dict(self) -> dict:
        """JSON-safe: infinities become ``null`` (see ``noise_free``)."""
        d = {
            "sinad_db": _json_float(self.sinad_db),
            "enob_bits": _json_float(self.enob_bits),
            "noise_free": bool(self.noise_free),
            "signal_rms": float(self.signal_rms),
            "noise_std": float(self.noise_std),
            "repeats": int(self.repeats),
            "pixels": int(self.pixels),
            "confidence": float(self.confidence),
            "ci_db": None if self.ci_db is None else [_json_float(v) for v in self.ci_db],
            "ci_enob": None if self.ci_enob is None else [_json_float(v) for v in self.ci_enob],
        }
        if self.per_pixel_db is not None:
            pp = self.per_pixel_db
            d["per_pixel_db"] = np.where(pp.mask | ~np.isfinite(pp.filled(0.0)), None,
                                         pp.filled(0.0)).tolist()
        return d


def _as_repeats(captures, what):
    x = np.asarray(captures)
    if x.dtype == object or not (np.issubdtype(x.dtype, np.number) or x.dtype == bool):
        raise EvtkError(f"{what} must be numeric, not {x.dtype}")
    if x.ndim < 1 or x.shape[0] < 2:
        raise EvtkError(f"{what} needs at least two repeated captures along the first axis, "
                        f"got shape {x.shape}")
    if x.size == 0:
        raise EvtkError(f"{what} holds no pixels")
    return x


#: Most groups of repeats the bootstrap resamples: more repeats are resampled in contiguous blocks.
MAX_BOOTSTRAP_GROUPS = 64


def _group_terms(x, groups):
    """Sufficient statistics of contiguous groups of repeats, in one pass over the captures.

    With ``xc`` the captures centred per pixel and ``d_ij = mean_p (xc_i - xc_j)^2 / 2`` (half the squared
    difference of repeats i and j, pooled over pixels), returns ``(M, N, P, n)``: ``M[g, h]`` the sum of
    ``d_ij`` over i in g and j in h (i != j; twice the within-group sum on the diagonal), ``N`` the number
    of such pairs, ``P[g]`` the summed mean square of g's repeats and ``n[g]`` their number. Memory is
    groups x pixels; no repeat-by-repeat matrix is formed. Centring keeps large means with tiny noise exact.
    """
    r, p = x.shape
    bounds = np.linspace(0, r, groups + 1).round().astype(np.int64)
    n = np.diff(bounds).astype(np.float64)
    mean = x.mean(axis=0)
    s1 = np.empty((groups, p))
    a = np.empty(groups)
    power = np.empty(groups)
    for g in range(groups):
        block = x[bounds[g]:bounds[g + 1]]
        xc = block - mean
        s1[g] = xc.sum(axis=0)
        a[g] = np.einsum("rp,rp->", xc, xc) / p
        power[g] = np.einsum("rp,rp->", block, block) / p
    k = s1 @ s1.T / p
    m = (n[None, :] * a[:, None] + n[:, None] * a[None, :] - 2.0 * k) / 2.0  # between groups
    np.fill_diagonal(m, n * a - np.diag(k))  # twice the within-group sum
    pairs = np.outer(n, n)
    np.fill_diagonal(pairs, n * (n - 1))
    return m, pairs, power, n


def sinad(captures, per_pixel=False, bootstrap=1000, confidence=0.95, seed=0) -> SinadReport:
    """Signal-to-noise-and-distortion ratio of repeated captures of one scene (eq. 8).

    ``SINAD = 10 log10(RMS(I)^2 / std(I)^2)``: ``RMS`` over every capture and
    pixel, ``std`` the standard deviation over repeats of each pixel (ddof 1),
    pooled over pixels as the mean variance. ENOB follows from eq. 8
    (:func:`enob_bits`).

    Parameters
    ----------
    captures : array_like, shape (repeats, ...)
        Repeated captures (responses, counts, images) of one scene.
    per_pixel : bool
        Also report each pixel's own SINAD.
    bootstrap : int
        Resamples of the repeats for the confidence interval (0: none).
    confidence : float
        Coverage of the percentile interval.
    seed : int
        Seed of the resampling.

    Raises
    ------
    EvtkError
        Fewer than two repeats, NaN or infinite values, or an all-zero signal.

    Examples
    --------
    >>> r = sinad([[1.0, 2.0], [1.0, 2.0]], bootstrap=0)
    >>> r.sinad_db, r.noise_free
    (inf, True)
    >>> round(sinad([[3.0], [5.0]], bootstrap=0).sinad_db, 4)   # 10 log10(17 / 2)
    9.2942
    """
    x = _as_repeats(captures, "SINAD")
    x = x.reshape(x.shape[0], -1).astype(np.float64)
    if not np.all(np.isfinite(x)):
        raise EvtkError("SINAD: the captures hold NaN or infinite values")
    if not 0 < confidence < 1:
        raise EvtkError(f"confidence must be between 0 and 1, not {confidence}")
    r, p = x.shape
    power = float(np.einsum("rp,rp->", x, x) / x.size)
    if power == 0.0:
        raise EvtkError("SINAD: the signal is zero everywhere (no light reached the pixels?)")
    xc = x - x.mean(axis=0)
    noise = float(np.einsum("rp,rp->", xc, xc) / ((r - 1) * p))  # pooled per-pixel variance, ddof 1
    del xc
    s_db = _ratio_db(power, noise)
    report = SinadReport(s_db, enob_bits(s_db), noise == 0.0, math.sqrt(power), math.sqrt(noise), r, p,
                         confidence=confidence)
    if bootstrap and r >= 3:
        boot = _bootstrap_db(_group_terms(x, min(r, MAX_BOOTSTRAP_GROUPS)), int(bootstrap), seed)
        a = (1.0 - confidence) / 2
        srt = np.sort(boot)
        lo = srt[int(math.floor(a * (srt.size - 1)))]
        hi = srt[int(math.ceil((1 - a) * (srt.size - 1)))]
        report.ci_db = (float(lo), float(hi))
        report.ci_enob = (enob_bits(lo), enob_bits(hi))
    if per_pixel:
        mean = x.mean(axis=0)
        var = ((x - mean) ** 2).sum(axis=0) / (r - 1)
        ms = (x * x).mean(axis=0)
        pp = np.full(p, np.inf)
        noisy = var > 0
        pp[noisy] = 10.0 * np.log10(ms[noisy] / var[noisy])
        report.per_pixel_db = np.ma.masked_array(pp, mask=ms == 0).reshape(np.shape(captures)[1:])
    return report


def _ratio_db(power, noise):
    return math.inf if noise == 0.0 else 10.0 * math.log10(power / noise)


def _bootstrap_db(terms, n, seed):
    """SINAD of ``n`` resamplings of the groups of repeats (:func:`_group_terms`; one repeat a group up to
    :data:`MAX_BOOTSTRAP_GROUPS` repeats, contiguous blocks beyond), noise from pairs of distinct repeats only.

    Resampling a repeat twice adds a pair with no difference; the pooled
    variance is a mean over pairs, so only pairs of different original
    repeats enter (a U-statistic bootstrap), which keeps the interval centred
    on the estimate. With a resample's group counts ``c`` the noise is
    ``c'Mc / c'Nc`` and the power ``c.P / c.n``: time and memory grow with the
    groups and the resamples, not with the repeats. Resamples without a pair
    of distinct repeats are skipped.
    """
    m, pairs, power, sizes = terms
    g = sizes.size
    rng = np.random.default_rng(seed)
    out = []
    batch = min(n, 4096)
    offsets = (np.arange(batch) * g)[:, None]
    while len(out) < n:
        idx = rng.integers(0, g, size=(batch, g))
        c = np.bincount((idx + offsets).ravel(), minlength=batch * g).reshape(batch, g).astype(np.float64)
        npairs = np.einsum("bg,gh,bh->b", c, pairs, c)
        ok = npairs > 0
        noise = np.einsum("bg,gh,bh->b", c[ok], m, c[ok]) / npairs[ok]
        pw = (c[ok] @ power) / (c[ok] @ sizes)
        with np.errstate(divide="ignore"):
            out.extend(np.where(noise > 0, 10.0 * np.log10(pw / np.where(noise > 0, noise, 1.0)), np.inf))
    return np.asarray(out[:n])


@dataclass
class FlipReport:
    """What :func:`flip_rates` measured (percentages of pixels).

    ``pairwise_pct``: mean over all pairs of repeats of the share of pixels
    that differ; ``majority_pct``: share of (repeat, pixel) values that differ
    from the pixel's majority vote (ties count as +1, as
    :func:`evtk.reconstruct.binarize` maps 0 to +1); ``per_pixel``: each
    pixel's share of repeats that disagree with its majority.
    """

    pairwise_pct: float
    majority_pct: float
    repeats: int
    pixels: int
    per_pixel: np.ndarray

    def to_dict(self) -> dict:
        return {"pairwise_pct": self.pairwise_pct, "majority_pct": self.majority_pct,
                "repeats": self.repeats, "pixels": self.pixels}


def flip_rates(binary) -> FlipReport:
    """Flip rates of repeated binarised captures of one scene.

    Parameters
    ----------
    binary : array_like, shape (repeats, ...)
        Values in {-1, +1}, {0, 1} or bool.

    Examples
    --------
    >>> r = flip_rates([[1, 1, -1, -1], [1, -1, -1, -1], [1, 1, -1, 1]])
    >>> round(r.pairwise_pct, 4), round(r.majority_pct, 4)   # 4 of 12 pair-pixels; 2 of 12 values
    (33.3333, 16.6667)
    """
    b = _as_repeats(binary, "flip rates")
    vals = np.unique(b)
    if not (set(vals.tolist()) <= {-1, 1} or set(vals.tolist()) <= {0, 1}):
        raise EvtkError(f"flip rates need binary values (-1/+1, 0/1 or bool), found {vals[:6].tolist()}")
    ones = (b > 0).reshape(b.shape[0], -1)
    r, p = ones.shape
    k = ones.sum(axis=0, dtype=np.int64)
    pairwise = float((k * (r - k)).sum()) / (p * r * (r - 1) / 2)
    majority_one = 2 * k >= r
    disagree = np.where(majority_one, r - k, k)
    return FlipReport(100.0 * pairwise, 100.0 * float(disagree.sum()) / (r * p), r, p,
                      (disagree / r).reshape(b.shape[1:]))


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


def poisson_log_pmf(k, lam):
    """Natural log of the Poisson probability of ``k`` photons at expected count ``lam`` (eq. 9).

    ``log P(X = k) = k log(lam) - lam - log(k!)``, computed through
    Stirling's error term and a deviance that keeps full precision when ``k``
    and ``lam`` are large and close (1e12 photons: about 1e-15 relative
    error, where the textbook formula loses three digits). ``lam = 0`` gives
    0 for ``k = 0`` and ``-inf`` otherwise.

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


def poisson_pmf(k, lam):
    """Poisson probability of ``k`` photons at expected count ``lam`` (eq. 9); underflows to 0 honestly."""
    v = np.exp(poisson_log_pmf(k, lam))
    return float(v) if np.ndim(v) == 0 else v


def capture_terms(window_us, time_unit_us=1.0):
    """``N_e`` of eq. 10: whole time units in a capture window of ``window_us``."""
    if not (np.isfinite(window_us) and np.isfinite(time_unit_us)) or window_us < 0 or time_unit_us <= 0:
        raise EvtkError("window_us must be >= 0 and time_unit_us > 0, both finite")
    return int(math.floor(window_us / time_unit_us + 1e-9))


def _log_cf_scalar(lam, phi, n):
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


def log_cumulative_factor(lam, photons_per_unit=1, n_terms=1):
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


def cumulative_factor(lam, photons_per_unit=1, n_terms=1):
    """The cumulative factor ``C`` of eq. 10 (``exp`` of :func:`log_cumulative_factor`)."""
    v = np.exp(log_cumulative_factor(lam, photons_per_unit, n_terms))
    return float(v) if np.ndim(v) == 0 else v


def lowest_cumulative_factor(intensities, photons_per_intensity, photons_per_unit=1, n_terms=1, log=False):
    """``C_low`` of eq. 11: the cumulative factor of the dimmest input.

    ``lam_low = photons_per_intensity * min(intensities)`` (``rho_B`` times
    the lowest feature intensity); the bound of eq. 11 scales every
    convolution by this constant. ``log=True`` returns ``log C_low``.

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
