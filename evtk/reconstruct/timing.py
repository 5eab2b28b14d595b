"""Light within a count's band, read from each pixel's first and last ON-event times (the noise-free crossing chain)."""

from __future__ import annotations

import math

import numpy as np

from .._lazyjit import njit, numba_ready
from .._native import TIMED_KERNELS as NATIVE_SOLVE
from .._native import enabled as native_enabled
from .._native import timing_solve as native_timing_solve
from ..errors import EvtkError
from ..sensor import SensorModel, time_constant_us
from .linearize import _count_bands, _on_threads

__all__ = ["linearize_by_timing", "timing_thresholds"]

#: (window, pixel) pairs up to which :func:`linearize_by_timing` solves with numpy while numba is not loaded:
#: numpy takes about 150 ns a pair on one thread (numba's kernel 120 ns, on every thread), numba's start in a
#: fresh process about 0.6 s (docs/performance.md), so up to this numpy (0.3 s) finishes first on any core count.
_NUMPY_MAX_PAIRS = 2_000_000
#: Pairs numpy solves at a time: bounded work arrays, which also stay in cache.
_NUMPY_CHUNK_PAIRS = 32_768


def _decay(t_us, tau_us) -> np.ndarray:
    """``exp(-t / tau)`` of times ``t_us >= 0`` and time constants ``tau_us >= 0``: where no time passes, 1, and
    where the time constant is 0 (a log-node pixel follows the light at once), 0 once any time has passed; no
    0 / 0 (back-to-back or empty windows of such a pixel gave NaN)."""
    t, tau = np.broadcast_arrays(np.asarray(t_us, np.float64), np.asarray(tau_us, np.float64))
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.exp(-t / tau)
    return np.where(t <= 0, 1.0, np.where(tau > 0, out, 0.0))


def _settle_residual(u, t_on_us, t_off_us, sensor, blank_rate_e_per_s):
    """How far above the dark level (log units) each pixel's photoreceptor still is at each pattern's onset.

    The darkness between patterns is finite, so a pixel starts a window a
    little above the dark level, from where the timing estimate measures its
    step. Noise-free mean path through the windows ``[t_on_us, t_off_us)`` in
    time order, from a settled first window, with the light of each window
    taken as ``u`` (its log step over the dark level).
    """

    order = np.argsort(t_on_us, kind="stable")
    t_on = np.asarray(t_on_us, np.int64)[order]
    t_off = np.asarray(t_off_us, np.int64)[order]
    tau_dark = float(time_constant_us(blank_rate_e_per_s, sensor))
    gap = np.maximum(t_on[1:] - t_off[:-1], 0)
    dark_decay = np.concatenate([[0.0], _decay(gap, tau_dark)])  # the first window starts settled
    u_t = np.ascontiguousarray(u[order]).reshape(len(order), -1)
    lit = np.maximum(t_off - t_on, 0).astype(np.float64)
    lit_decay = _decay(lit[:, None], time_constant_us(blank_rate_e_per_s * np.exp(u_t), sensor))
    eps = np.empty_like(u)
    eps[order] = _settle_path(u_t, lit_decay, dark_decay).reshape((len(order),) + u.shape[1:])
    return eps


def _settle_path(u, lit_decay, dark_decay):
    """Each window's starting level above the dark level (log units), window after window (numpy, per window)."""
    eps = np.empty_like(u)
    level = np.zeros(u.shape[1])
    for w in range(u.shape[0]):
        level *= dark_decay[w]
        eps[w] = level
        level = u[w] + (level - u[w]) * lit_decay[w]
    return eps


@njit(cache=True, inline="always")
def _timing_factor_jit(n, a_us, b_us, log_rate, tau_min_us, tau_electrons, refr_us):
    """:func:`_timing_factor` of one pixel, for :func:`_timing_solve_jit`."""
    tau = tau_min_us + tau_electrons / (np.exp(log_rate) * 1e-6)
    r = refr_us / tau
    x = (b_us - a_us) / tau - (n - 1) * r
    if not x > 0.0:
        return -1.0
    big = b_us / tau
    if big < 700.0:  # (1 - q) (exp(-(n-1) r - A) - exp(-B)) = (1 - q) exp(-B) expm1(x)
        return -np.expm1(-(n - 1) * r) / (-np.expm1(-r) * np.exp(-big) * np.expm1(x))
    # the same in logs, where exp(-B) would underflow
    log_den = np.log(-np.expm1(-r)) - big + x + np.log1p(-np.exp(-x))
    return np.exp(np.log(-np.expm1(-(n - 1) * r)) - log_den)


@njit(cache=True, nogil=True)
def _timing_solve_jit(n_on, first, last, theta, theta_nominal, band_lo, band_hi, offset_us, log_blank, tau_min_us,
                  tau_electrons, refr_us, out):
    """Log-light steps from ON-event times, :func:`linearize_by_timing`'s work, per (window, pixel): numba's
    scalar loop, which :func:`_timing_solve_np` does on arrays."""
    n_w, n_px = n_on.shape
    top = band_lo.size - 1
    for w in range(n_w):
        for i in range(n_px):
            n = n_on[w, i]
            out[w, i] = np.nan
            if n < 2 or first[w, i] < 0 or last[w, i] < first[w, i]:
                continue
            a = first[w, i] + offset_us + 0.5  # time stamps are whole us, rounded down
            b = last[w, i] + offset_us + 0.5
            th = theta[i]
            # Search where the count allows: its band (scaled to the pixel's threshold) and the next one,
            # since the reference a pixel starts from may sit up to one threshold above the dark level,
            # widened by a threshold. (Far outside, a much brighter and faster pixel can fit the same
            # two times: h has a second root there.)
            s = th / theta_nominal
            lo = max(0.0, band_lo[min(n, top)] * s - th)
            # the last band reaches the brightest light, whatever the pixel's threshold
            hi = band_hi[n + 1] * s + th if n + 1 < top else band_hi[top] * max(s, 1.0) + th
            # secant steps on h(u) = u - theta * factor(u) from the middle of the band; the time constant
            # changes slowly with the light, so this takes a few steps; the bracketed method otherwise
            u0 = 0.5 * (lo + hi)
            f = _timing_factor_jit(n, a, b, log_blank + u0, tau_min_us, tau_electrons, refr_us)
            if f < 0.0:  # depends on the times only
                continue
            h0 = u0 - th * f
            u1 = th * f
            done = False
            for _ in range(10):
                h1 = u1 - th * _timing_factor_jit(n, a, b, log_blank + u1, tau_min_us, tau_electrons, refr_us)
                if abs(h1) <= 1e-4 * (1.0 + abs(u1)):
                    done = lo <= u1 <= hi
                    break
                if h1 == h0:
                    break
                u0, h0, u1 = u1, h1, u1 - h1 * (u1 - u0) / (h1 - h0)
                if not (-1.0 < u1 < 2.0 * hi + 1.0):
                    break
            if done:
                out[w, i] = u1
                continue
            f = _timing_factor_jit(n, a, b, log_blank + lo, tau_min_us, tau_electrons, refr_us)
            h_lo = lo - th * f
            h_hi = hi - th * _timing_factor_jit(n, a, b, log_blank + hi, tau_min_us, tau_electrons, refr_us)
            if not (h_lo < 0.0 < h_hi):
                continue
            side = 0
            u = lo
            for _ in range(100):  # Illinois method
                u = (lo * h_hi - hi * h_lo) / (h_hi - h_lo)
                h = u - th * _timing_factor_jit(n, a, b, log_blank + u, tau_min_us, tau_electrons, refr_us)
                if abs(h) <= 1e-6 * (1.0 + u) or hi - lo <= 1e-9:
                    break
                if h > 0.0:
                    hi, h_hi = u, h
                    if side == 1:
                        h_lo *= 0.5
                    side = 1
                else:
                    lo, h_lo = u, h
                    if side == -1:
                        h_hi *= 0.5
                    side = -1
            out[w, i] = u


def linearize_by_timing(on: np.ndarray, on_first_us: np.ndarray, on_last_us: np.ndarray, theta: float | np.ndarray,
                        sensor: SensorModel | dict, dark_rate_e_per_s: float, curve: tuple,
                        offset_us: float = 0) -> np.ndarray:
    """Log-light step of each window from the times of its first and last ON event, below one threshold.

    A count alone places the step somewhere in a band one threshold wide (a
    22 % band of light at ``theta = 0.2``). When the pixel's time constant is
    known (a simulated recording's pixel model: ``tau = tau_min +
    tau_electrons / lam``, refractory period), the times at which the noise-free
    photoreceptor crosses its thresholds fix the step within that band
    (:func:`_timing_factor`). The estimate does not depend on the reference the
    pixel started the window with, so the residue earlier captures leave does
    not bias it. With shot noise the times scatter and the estimate with them;
    it still beats the count's band at nominal light (see
    ``benchmarks/bench_accuracy.py``).

    Parameters
    ----------
    on, on_first_us, on_last_us : ndarray (windows, ...)
        ON counts and first/last ON-event times from the window's start
        (:func:`accumulate` with ``times=True``).
    theta : float or ndarray (...)
        Each pixel's ON threshold.
    sensor : SensorModel or dict
        The pixel model (``theta_on`` nominal, ``tau_min_us``,
        ``tau_electrons``, ``refractory_us``).
    dark_rate_e_per_s : float
        Photoelectron rate of the dark level the step starts from.
    curve : (u, counts)
        The pixel model's :func:`count_curve` for these windows: the search
        stays within the steps a pixel's count allows.
    offset_us : float
        Time from the step (the pattern's onset) to the window's start.

    Returns
    -------
    ndarray (windows, ...)
        The step ``u`` (natural log of light over the dark level); NaN where
        the times do not determine it (fewer than two ON events, or times no
        noise-free pixel with that count produces): fall back to the count there.
    """
    sm = _as_sensor(sensor)
    n = np.asarray(on)
    first = np.asarray(on_first_us)
    last = np.asarray(on_last_us)
    if not (n.shape == first.shape == last.shape) or n.ndim < 1:
        raise EvtkError(f"counts {n.shape} and event times {first.shape}/{last.shape} must have one shape")
    th = np.broadcast_to(np.asarray(theta, dtype=np.float64), n.shape[1:])
    if not (np.all(np.isfinite(th)) and np.all(th > 0)):
        raise EvtkError("thresholds must be finite and positive")
    log_blank = _log_dark_rate(dark_rate_e_per_s)
    _, band_lo, band_hi = _count_bands(curve)
    rows = n.shape[0]
    out = np.empty(n.shape, np.float64)
    cols = math.prod(n.shape[1:])  # (not -1: no windows is (0, pixels))
    n2, first2, last2 = (np.ascontiguousarray(a.reshape(rows, cols), np.int64) for a in (n, first, last))
    th2, out2 = np.ascontiguousarray(th.ravel()), out.reshape(rows, cols)
    lo_band, hi_band = np.ascontiguousarray(band_lo, np.float64), np.ascontiguousarray(band_hi, np.float64)

    # the compiled kernel where the install built it; else numpy's arrays where they cost less than numba's start
    # would, numba's loop once that is paid or for work large enough to pay it
    native = native_enabled() and NATIVE_SOLVE
    jit = not native and (numba_ready() or n2.size > _NUMPY_MAX_PAIRS)

    def rows_of(a, b):  # windows a..b: each pixel-window is solved alone, so any split gives the same numbers
        _timing_solve(n2[a:b], first2[a:b], last2[a:b], th2, sm.theta_on, lo_band, hi_band, float(offset_us),
                      log_blank, sm.tau_min_us, sm.tau_electrons, sm.refractory_us, out2[a:b], jit)

    if native or jit:  # both release the GIL
        _on_threads(rows_of, rows, max(1, 4096 // max(1, cols)))
    else:  # numpy's many short calls hold the GIL between them: more threads add CPU time, not speed
        rows_of(0, rows)
    return out


def _log_dark_rate(rate_e_per_s):
    """``log`` of the dark level's photoelectron rate, which must be finite and positive."""
    if not (math.isfinite(rate_e_per_s) and rate_e_per_s > 0):
        raise EvtkError(f"the dark level's rate must be finite and positive, not {rate_e_per_s!r}")
    return math.log(rate_e_per_s)


def _as_sensor(sensor):
    """A :class:`~evtk.sensor.SensorModel` from one or from its dict (a recording's record)."""

    return sensor if isinstance(sensor, SensorModel) else SensorModel.from_dict(dict(sensor))


def timing_thresholds(flat_on: np.ndarray, flat_first_us: np.ndarray, flat_last_us: np.ndarray,
                      flat_u: float | np.ndarray, sensor: SensorModel | dict, dark_rate_e_per_s: float,
                      offset_us: float = 0) -> np.ndarray:
    """Each pixel's ON threshold from flat-field windows of known step and their ON-event times.

    The inverse of :func:`linearize_by_timing`: with the step known,
    ``theta = u / factor``, averaged over the flat-field windows whose times
    determine it; NaN for a pixel none does.

    Parameters
    ----------
    flat_on, flat_first_us, flat_last_us : ndarray (windows, ...)
        The flat-field windows' ON counts and first/last ON-event times.
    flat_u : float or ndarray
        The step of each window and pixel, or of each pixel.
    sensor : SensorModel or dict
        The pixel model.
    dark_rate_e_per_s : float
        Photoelectron rate of the dark level.
    offset_us : float
        Time from the step to the window's start.

    Returns
    -------
    ndarray (...)
        Each pixel's ON threshold (log units), NaN where no window's times determine it.
    """
    sm = _as_sensor(sensor)
    n = np.asarray(flat_on, dtype=np.int64)
    if n.ndim < 1 or n.shape[0] == 0:
        raise EvtkError("threshold calibration needs at least one flat-field window")
    if not (n.shape == np.shape(flat_first_us) == np.shape(flat_last_us)):
        raise EvtkError("flat-field counts and event times must have one shape")
    rows = n.shape[0]
    fu = np.ascontiguousarray(np.broadcast_to(np.asarray(flat_u, dtype=np.float64), n.shape).reshape(rows, -1))
    theta = _timing_theta(n.reshape(rows, -1), np.asarray(flat_first_us, np.int64).reshape(rows, -1),
                          np.asarray(flat_last_us, np.int64).reshape(rows, -1), fu, float(offset_us),
                          _log_dark_rate(dark_rate_e_per_s), sm.tau_min_us, sm.tau_electrons, sm.refractory_us)
    return theta.reshape(n.shape[1:])


def _timing_factor(n, a_us, b_us, log_rate, tau_min_us, tau_electrons, refr_us):
    """``u / theta`` for pixels whose ``n`` (>= 2) ON events after a step of ``u`` from the dark level came
    first at ``a_us`` and last at ``b_us`` after the step, the light being ``exp(log_rate)`` photoelectrons/s
    (arrays of one shape, or scalars).

    Noise-free, the photoreceptor approaches its new level as ``V = L - u exp(-t/tau)``. Each event
    raises the reference by ``theta`` above V, and the refractory period lets V climb on by a factor
    ``q = exp(-refr/tau)`` of what remains. Writing ``E = exp(-t/tau)`` at event times, that chain is
    ``u (q E_k - E_(k+1)) = theta``, whose solution from the first to the last event is
    ``u / theta = (1 - q^(n-1)) / ((1 - q)(q^(n-1) E_1 - E_n))``, free of the reference the pixel started
    from. Computed directly, or in logs where ``exp(-b/tau)`` would underflow (no overflow for any times).
    -1 where the times cannot come from such a chain (``b - a <= (n - 1) refr``).
    """
    f = _factor(-(np.asarray(n) - 1.0), np.subtract(b_us, a_us), np.asarray(b_us, np.float64),
                np.asarray(log_rate, np.float64), tau_min_us, tau_electrons, refr_us)
    return f if f.ndim else f[()]


def _factor(m, d_us, b_us, log_rate, tau_min_us, tau_electrons, refr_us):
    """:func:`_timing_factor` of ``m = 1 - n`` and ``d_us = b_us - a_us`` (float arrays of one shape)."""
    with np.errstate(all="ignore"):
        tau = tau_min_us + tau_electrons / (np.exp(log_rate) * 1e-6)
        r = refr_us / tau
        m_r = m * r
        x = d_us / tau + m_r
        big = b_us / tau
        chain = x > 0.0
        small = big < 700.0
        if np.all(chain & small):  # (1 - q) (exp(-(n-1) r - A) - exp(-B)) = (1 - q) exp(-B) expm1(x)
            return -np.expm1(m_r) / (-np.expm1(-r) * np.exp(-big) * np.expm1(x))
        f = np.full(x.shape, -1.0)
        k = chain & small
        f[k] = -np.expm1(m_r[k]) / (-np.expm1(-r[k]) * np.exp(-big[k]) * np.expm1(x[k]))
        k = chain & ~small  # the same in logs, where exp(-B) would underflow
        log_den = np.log(-np.expm1(-r[k])) - big[k] + x[k] + np.log1p(-np.exp(-x[k]))
        f[k] = np.exp(np.log(-np.expm1(m_r[k])) - log_den)
    return f


def _timing_solve(n_on, first, last, theta, theta_nominal, band_lo, band_hi, offset_us, log_blank, tau_min_us,
                  tau_electrons, refr_us, out, jit):
    """:func:`linearize_by_timing`'s work on a block of windows: the compiled kernel where built (the same
    operations as numba's), else numba's kernel if ``jit``, else numpy's."""
    if native_timing_solve(n_on, first, last, theta, band_lo, band_hi, out, (0, n_on.shape[0]), theta_nominal,
                           offset_us, log_blank, tau_min_us, tau_electrons, refr_us):
        return
    if jit:
        _timing_solve_jit(n_on, first, last, theta, theta_nominal, band_lo, band_hi, offset_us, log_blank,
                          tau_min_us, tau_electrons, refr_us, out)
        return
    step = max(1, _NUMPY_CHUNK_PAIRS // max(1, n_on.shape[1]))  # bounded work arrays, and faster in cache
    for w in range(0, n_on.shape[0], step):
        _timing_solve_np(n_on[w:w + step], first[w:w + step], last[w:w + step], theta, theta_nominal, band_lo,
                         band_hi, offset_us, log_blank, tau_min_us, tau_electrons, refr_us, out[w:w + step])


def _timing_solve_np(n_on, first, last, theta, theta_nominal, band_lo, band_hi, offset_us, log_blank, tau_min_us,
                     tau_electrons, refr_us, out):
    """Log-light steps from ON-event times, :func:`linearize_by_timing`'s work, for every (window, pixel) at once.

    Each pair is solved alone, as the scalar method would: secant steps from the middle of the band its count
    allows, then the Illinois method within the band where they fail. The arrays hold the pairs still being
    solved, and shrink as pairs finish.
    """
    top = band_lo.size - 1
    res = np.full(n_on.size, np.nan)
    fn, ff, fl = n_on.ravel(), first.ravel(), last.ravel()
    pos = np.flatnonzero((fn >= 2) & (ff >= 0) & (fl >= ff))
    n = fn[pos]
    b = fl[pos] + offset_us + 0.5  # time stamps are whole us, rounded down
    d = b - (ff[pos] + offset_us + 0.5)
    m = -(n - 1.0)
    th = np.broadcast_to(theta, n_on.shape).ravel()[pos]
    # Search where the count allows: its band (scaled to the pixel's threshold) and the next one, since the
    # reference a pixel starts from may sit up to one threshold above the dark level, widened by a threshold.
    # (Far outside, a much brighter and faster pixel can fit the same two times: h has a second root there.)
    s = th / theta_nominal
    lo = np.maximum(0.0, band_lo[np.minimum(n, top)] * s - th)
    # the last band reaches the brightest light, whatever the pixel's threshold
    hi = np.where(n + 1 < top, band_hi[np.minimum(n + 1, top)] * s + th, band_hi[top] * np.maximum(s, 1.0) + th)

    def h_of(u, m, d, b, th):  # h(u) = u - theta * factor(u)
        return u - th * _factor(m, d, b, log_blank + u, tau_min_us, tau_electrons, refr_us)

    # secant steps on h from the middle of the band; the time constant changes slowly with the light, so
    # this takes a few steps; the bracketed method otherwise
    u0 = 0.5 * (lo + hi)
    f = _factor(m, d, b, log_blank + u0, tau_min_us, tau_electrons, refr_us)
    k = ~(f < 0.0)  # f < 0 depends on the times only: no chain gives them
    if not k.all():
        pos, m, d, b, th, lo, hi, u0, f = (v[k] for v in (pos, m, d, b, th, lo, hi, u0, f))
    h0 = u0 - th * f
    u1 = th * f
    unsolved = np.zeros(pos.size, bool)
    # the pairs still stepping, one row a quantity (one compress a step); indices are exact in float64
    live = np.stack([np.arange(pos.size, dtype=np.float64), m, d, b, th, lo, hi, u0, h0, u1])
    with np.errstate(all="ignore"):
        for _ in range(10):
            if not live.shape[1]:
                break
            j, m_j, d_j, b_j, th_j, lo_j, hi_j, u0, h0, u1 = live
            j = j.astype(np.intp)
            h1 = h_of(u1, m_j, d_j, b_j, th_j)
            close = np.abs(h1) <= 1e-4 * (1.0 + np.abs(u1))
            done = close & (lo_j <= u1) & (u1 <= hi_j)
            res[pos[j[done]]] = u1[done]
            stuck = ~close & (h1 == h0)
            go = ~(close | stuck)
            step = u1 - h1 * (u1 - u0) / (h1 - h0)
            keep = go & (-1.0 < step) & (step < 2.0 * hi_j + 1.0)
            unsolved[j[~(done | keep)]] = True  # out of band, stuck or diverging: the bracketed method
            live[7], live[8], live[9] = u1, h1, step
            if not keep.all():
                live = live[:, keep]
        unsolved[live[0].astype(np.intp)] = True  # no answer in ten steps
        # the Illinois method within the band, where the band brackets a root
        pos, m, d, b, th, lo, hi = (v[unsolved] for v in (pos, m, d, b, th, lo, hi))
        h_lo, h_hi = h_of(lo, m, d, b, th), h_of(hi, m, d, b, th)
        k = (h_lo < 0.0) & (0.0 < h_hi)
        pos, m, d, b, th, lo, hi, h_lo, h_hi = (v[k] for v in (pos, m, d, b, th, lo, hi, h_lo, h_hi))
        side = np.zeros(pos.size, np.int8)
        u = lo
        for _ in range(100):
            if not pos.size:
                break
            u = (lo * h_hi - hi * h_lo) / (h_hi - h_lo)
            h = h_of(u, m, d, b, th)
            stop = (np.abs(h) <= 1e-6 * (1.0 + u)) | (hi - lo <= 1e-9)
            res[pos[stop]] = u[stop]
            k = ~stop
            pos, m, d, b, th, lo, hi, h_lo, h_hi, side, u, h = (
                v[k] for v in (pos, m, d, b, th, lo, hi, h_lo, h_hi, side, u, h))
            up = h > 0.0
            h_lo = np.where(up & (side == 1), 0.5 * h_lo, h_lo)
            h_hi = np.where(~up & (side == -1), 0.5 * h_hi, h_hi)
            hi, h_hi = np.where(up, u, hi), np.where(up, h, h_hi)
            lo, h_lo = np.where(up, lo, u), np.where(up, h_lo, h)
            side = np.where(up, 1, -1).astype(np.int8)
        res[pos] = u  # the 100-step cap: the last estimate
    out[...] = res.reshape(out.shape)


def _timing_theta(n_on, first, last, flat_u, offset_us, log_blank, tau_min_us, tau_electrons, refr_us):
    """Each pixel's threshold, the mean of ``u / factor`` over the windows whose times determine it."""
    use = (n_on >= 2) & (first >= 0)
    f = np.full(n_on.shape, -1.0)
    f[use] = _timing_factor(n_on[use], first[use] + offset_us + 0.5, last[use] + offset_us + 0.5,
                            log_blank + flat_u[use], tau_min_us, tau_electrons, refr_us)
    good = f > 0.0
    total = np.zeros(n_on.shape[1])
    for w in range(n_on.shape[0]):  # window by window: the sum in the order of the windows
        total += np.where(good[w], flat_u[w] / np.where(good[w], f[w], 1.0), 0.0)
    k = good.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(k > 0, total / k, np.nan)
