"""How good the device's numbers are: SINAD and ENOB (eq. 8), flip rates, and the Poisson factors (eqs. 9-11).

* :func:`sinad` measures the signal-to-noise-and-distortion ratio of repeated
  captures of one scene (eq. 8) and :func:`enob_bits` turns it into effective
  bits; jackknife confidence intervals over repeats have close to nominal
  coverage, and :class:`SinadAccumulator` measures more repeats than fit in
  memory.
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
    "SinadAccumulator",
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
        Confidence interval over repeats (may reach ``+inf``).
    confidence : float
    interval : str or None
        How the interval was formed (``"jackknife"`` or ``"bootstrap"``).
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
    interval: str | None = None

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
            "interval": self.interval,
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


#: Most groups of repeats an interval resamples: more repeats are grouped in contiguous blocks.
MAX_BOOTSTRAP_GROUPS = 64

#: Interval methods of :func:`sinad`.
INTERVALS = ("jackknife", "bootstrap", None)


class SinadAccumulator:
    """SINAD (eq. 8) of repeated captures of one scene, fed a block of repeats at a time.

    Keeps, per contiguous group of repeats (a repeat a group up to
    :data:`MAX_BOOTSTRAP_GROUPS` repeats, contiguous blocks beyond), the
    group's per-pixel mean, its summed squared deviation and its summed
    squares, merged block by block with Chan's pairwise update (exact for
    large means with tiny noise). Memory is groups x pixels whatever the
    number of repeats, so a minute of 10 ms windows is measured in one pass;
    :func:`sinad` is one accumulator given every repeat at once.

    Parameters
    ----------
    repeats : int
        How many repeats will be added in all (at least two).
    shape : tuple of int
        Shape of one capture.

    Examples
    --------
    >>> acc = SinadAccumulator(4, (2,))
    >>> acc.add([[3.0, 1.0], [5.0, 1.0]])
    >>> acc.add([[3.0, 1.0], [5.0, 1.0]])
    >>> a = acc.report(interval=None).sinad_db
    >>> b = sinad([[3.0, 1.0], [5.0, 1.0]] * 2, interval=None).sinad_db
    >>> abs(a - b) < 1e-12
    True
    """

    def __init__(self, repeats, shape):
        repeats = int(repeats)
        if repeats < 2:
            raise EvtkError(f"SINAD needs at least two repeated captures, got {repeats}")
        self.shape = tuple(int(s) for s in np.atleast_1d(shape)) if len(tuple(np.atleast_1d(shape))) else (1,)
        p = int(np.prod(self.shape))
        if p == 0:
            raise EvtkError("SINAD: the captures hold no pixels")
        self.repeats = repeats
        g = min(repeats, MAX_BOOTSTRAP_GROUPS)
        self._bounds = np.linspace(0, repeats, g + 1).round().astype(np.int64)
        self._n = np.zeros(g)
        self._mean = np.zeros((g, p))
        self._m2 = np.zeros(g)  # squared deviations from the group's mean, summed over its repeats and pixels
        self._m2_px = np.zeros(p)  # the same per pixel, summed over groups
        self._sq = np.zeros(g)  # squares of the group's values, summed
        self._sq_px = np.zeros(p)
        self.added = 0

    def add(self, captures):
        """Add the next repeats, shape ``(k, *shape)``, in their order."""
        x = np.asarray(captures)
        if x.dtype == object or not (np.issubdtype(x.dtype, np.number) or x.dtype == bool):
            raise EvtkError(f"SINAD: the captures must be numeric, not {x.dtype}")
        p = self._mean.shape[1]
        if x.ndim < 1 or x.size != x.shape[0] * p:
            raise EvtkError(f"SINAD: each capture must hold {p} values, got shape {x.shape}")
        x = x.reshape(x.shape[0], p).astype(np.float64, copy=False)
        if self.added + x.shape[0] > self.repeats:
            raise EvtkError(f"SINAD: more than the {self.repeats} repeats announced")
        if not np.all(np.isfinite(x)):
            raise EvtkError("SINAD: the captures hold NaN or infinite values")
        i = 0
        while i < x.shape[0]:
            at = self.added + i
            g = int(np.searchsorted(self._bounds, at, side="right")) - 1
            block = x[i:i + int(self._bounds[g + 1]) - at]
            k = block.shape[0]
            had = self._n[g]
            ref = self._mean[g] if had else block[0]  # a shift near the data keeps the sums exact
            dev = block - ref
            s1 = dev.sum(axis=0)
            s2 = np.einsum("rp,rp->p", dev, dev)
            block_m2 = np.maximum(s2 - s1 * s1 / k, 0.0)
            sq = k * ref * ref + 2.0 * ref * s1 + s2
            delta = ref + s1 / k - self._mean[g]
            w = had * k / (had + k)
            self._m2_px += block_m2 + w * delta * delta
            self._m2[g] += float(block_m2.sum()) + w * float(delta @ delta)
            self._mean[g] += delta * (k / (had + k))
            self._sq_px += sq
            self._sq[g] += float(sq.sum())
            self._n[g] += k
            i += k
        self.added += x.shape[0]

    def _centred(self):
        """Each group's mean centred on the overall mean, and its squared norm."""
        off = self._mean - (self._n @ self._mean) / self.repeats
        return off, np.einsum("gp,gp->g", off, off)

    def _group_terms(self):
        """``(M, N, P, n)`` of the groups, for the intervals.

        With ``xc`` the captures centred per pixel and ``d_ij = mean_p (xc_i - xc_j)^2 / 2`` (half the squared
        difference of repeats i and j, pooled over pixels): ``M[g, h]`` the sum of ``d_ij`` over i in g and j
        in h (i != j; twice the within-group sum on the diagonal), ``N`` the number of such pairs, ``P[g]`` the
        summed mean square of g's repeats and ``n[g]`` their number. No repeat-by-repeat matrix is formed.
        """
        p = self._mean.shape[1]
        n = self._n
        off, between = self._centred()
        s1 = n[:, None] * off  # per group: its centred values, summed over its repeats
        a = (self._m2 + n * between) / p  # per group: mean square of its centred repeats, summed
        k = s1 @ s1.T / p
        m = (n[None, :] * a[:, None] + n[:, None] * a[None, :] - 2.0 * k) / 2.0  # between groups
        np.fill_diagonal(m, n * a - np.diag(k))  # twice the within-group sum
        pairs = np.outer(n, n)
        np.fill_diagonal(pairs, n * (n - 1))
        return m, pairs, self._sq / p, n

    def report(self, per_pixel=False, interval="jackknife", confidence=0.95, resamples=1000,
               seed=0) -> SinadReport:
        """The :class:`SinadReport` of the repeats (all ``repeats`` must have been added); see :func:`sinad`."""
        if self.added != self.repeats:
            raise EvtkError(f"SINAD: {self.added} of the {self.repeats} repeats announced were added")
        if interval not in INTERVALS:
            raise EvtkError(f"interval must be one of {INTERVALS}, not {interval!r}")
        if not 0 < confidence < 1:
            raise EvtkError(f"confidence must be between 0 and 1, not {confidence}")
        r, p = self.repeats, self._mean.shape[1]
        n = self._n
        off, between = self._centred()
        power = float(self._sq.sum()) / (r * p)
        if power == 0.0:
            raise EvtkError("SINAD: the signal is zero everywhere (no light reached the pixels?)")
        noise = float(self._m2.sum() + n @ between) / ((r - 1) * p)  # pooled per-pixel variance, ddof 1
        s_db = _ratio_db(power, noise)
        report = SinadReport(s_db, enob_bits(s_db), noise == 0.0, math.sqrt(power), math.sqrt(noise), r, p,
                             confidence=confidence)
        if interval is not None and r >= 3 and (interval == "jackknife" or resamples):
            terms = self._group_terms()
            if interval == "jackknife":
                lo, hi = _jackknife_interval_db(terms, s_db, confidence)
            else:
                boot = np.sort(_bootstrap_db(terms, int(resamples), seed))
                tail = (1.0 - confidence) / 2
                lo = float(boot[int(math.floor(tail * (boot.size - 1)))])
                hi = float(boot[int(math.ceil((1 - tail) * (boot.size - 1)))])
            report.ci_db = (lo, hi)
            report.ci_enob = (enob_bits(lo), enob_bits(hi))
            report.interval = interval
        if per_pixel:
            var = (self._m2_px + n @ (off * off)) / (r - 1)
            ms = self._sq_px / r
            pp = np.full(p, np.inf)
            noisy = var > 0
            pp[noisy] = 10.0 * np.log10(ms[noisy] / var[noisy])
            report.per_pixel_db = np.ma.masked_array(pp, mask=ms == 0).reshape(self.shape)
        return report


def sinad(captures, per_pixel=False, interval="jackknife", confidence=0.95, resamples=1000,
          seed=0) -> SinadReport:
    """Signal-to-noise-and-distortion ratio of repeated captures of one scene (eq. 8).

    ``SINAD = 10 log10(RMS(I)^2 / std(I)^2)``: ``RMS`` over every capture and
    pixel, ``std`` the standard deviation over repeats of each pixel (ddof 1),
    pooled over pixels as the mean variance. ENOB follows from eq. 8
    (:func:`enob_bits`). Time and memory are linear in the captures; for more
    captures than fit in memory feed a :class:`SinadAccumulator`.

    Parameters
    ----------
    captures : array_like, shape (repeats, ...)
        Repeated captures (responses, counts, images) of one scene.
    per_pixel : bool
        Also report each pixel's own SINAD.
    interval : "jackknife", "bootstrap" or None
        Confidence interval over repeats (needs at least three).
        ``"jackknife"`` (default): delete-one-group jackknife of the SINAD in
        dB with a Student t quantile on groups - 1 degrees of freedom; its
        coverage is close to nominal from three repeats on, for noise
        independent between repeats and for noise shared by a whole repeat
        (tested by simulation in ``tests/test_metrics.py``).
        ``"bootstrap"``: percentile interval of ``resamples`` resamplings of
        the repeats; it undercovers with few repeats (about 60-75 % at three
        for a nominal 95 %) and is kept for comparison.
    confidence : float
        Nominal coverage of the interval.
    resamples : int
        Resamples of the bootstrap interval.
    seed : int
        Seed of the resampling.

    Raises
    ------
    EvtkError
        Fewer than two repeats, NaN or infinite values, or an all-zero signal.

    Examples
    --------
    >>> r = sinad([[1.0, 2.0], [1.0, 2.0]], interval=None)
    >>> r.sinad_db, r.noise_free
    (inf, True)
    >>> round(sinad([[3.0], [5.0]], interval=None).sinad_db, 4)   # 10 log10(17 / 2)
    9.2942
    """
    x = _as_repeats(captures, "SINAD")
    acc = SinadAccumulator(x.shape[0], x.shape[1:])
    acc.add(x)
    return acc.report(per_pixel=per_pixel, interval=interval, confidence=confidence, resamples=resamples, seed=seed)


def _jackknife_interval_db(terms, estimate_db, confidence):
    """Delete-one-group jackknife interval of the SINAD in dB, Student t on groups - 1 degrees of freedom.

    Each leave-one-group-out estimate keeps only pairs of distinct repeats
    outside the left-out group (the estimate's own U-statistic). Where
    leaving a group out leaves no noise, the interval reaches ``+inf``.
    """
    from scipy import stats

    m, pairs, power, sizes = terms
    g = sizes.size
    keep = np.ones((g, g)) - np.eye(g)  # row j: every group but j
    noise = np.einsum("jg,gh,jh->j", keep, m, keep) / np.einsum("jg,gh,jh->j", keep, pairs, keep)
    pw = (keep @ power) / (keep @ sizes)
    if not math.isfinite(estimate_db):
        return math.inf, math.inf
    if np.any(noise <= 0):  # some leave-outs see no noise: no finite upper end
        finite = noise > 0
        lo = min(float(np.min(10.0 * np.log10(pw[finite] / noise[finite]))), estimate_db)
        return lo, math.inf
    loo = 10.0 * np.log10(pw / noise)
    se = math.sqrt((g - 1) / g * float(np.sum((loo - loo.mean()) ** 2)))
    t = float(stats.t.ppf(0.5 + confidence / 2, g - 1))
    return estimate_db - t * se, estimate_db + t * se


def _ratio_db(power, noise):
    return math.inf if noise == 0.0 else 10.0 * math.log10(power / noise)


def _bootstrap_db(terms, n, seed):
    """SINAD of ``n`` resamplings of the groups of repeats (``SinadAccumulator._group_terms``; one repeat a group up to
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
