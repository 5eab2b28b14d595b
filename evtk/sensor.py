"""Event-pixel model: log photoreceptor, contrast thresholds, refractory period, shot noise.

Model of one pixel
------------------
* Photocurrent ``lam`` (photoelectrons/s) = light + dark current, piecewise
  constant because DMD patterns are.
* The photoreceptor output ``V`` follows ``log(lam)`` through a first-order
  low-pass whose time constant grows as light falls,
  ``tau = tau_min + tau_electrons / lam`` (:func:`time_constant_us`): a pixel
  needs about ``tau_electrons`` photoelectrons to follow a change, so dim
  pixels are slow.
* Shot noise: the photoreceptor low-passes a Poisson stream of
  photoelectrons (eq. 9). Through a first-order filter with time constant
  ``tau`` a Poisson rate ``lam`` has relative variance ``1/(2*lam*tau)``, so in
  the log domain ``V`` is an Ornstein-Uhlenbeck process around ``log(lam)``
  with stationary standard deviation ``s = 1/sqrt(2*lam*tau)``
  (:func:`log_noise_std`). At low light ``s`` grows towards
  ``1/sqrt(2*tau_electrons)`` and the pixel's response both shrinks (it is
  slow) and turns noisy; at high light ``s -> 0`` and the response approaches
  the ideal one (the behaviour eqs. 10-11 describe with the factor C).
* Change detection: an ON event when ``V`` rises ``theta_on`` above the
  reference, OFF when it falls ``theta_off`` below; per-pixel thresholds
  scatter (mismatch). After an event the pixel is blind for ``refractory_us``
  and its reference is the value of ``V`` when it wakes.

How it is computed
------------------
Within a segment of constant light and no noise, ``V(t) = L + (V0 - L)
exp(-t/tau)``, so each threshold crossing has a closed form: bright (stiff)
and dark (slow) pixels are exact and cost one logarithm per event.

With shot noise the state is carried as a Gaussian (mean, variance), which the
OU process keeps exactly, as long as the mean path stays more than
``FAR_SD`` standard deviations from both thresholds; the state is sampled
and stepped only near a threshold. Steps use the exact OU transition
(``V' = L + (V - L) a + s sqrt(1 - a^2) N``, ``a = exp(-h/tau)``), valid for
any step ``h``; crossings between two samples are caught with the Brownian
bridge probability ``exp(-2 d0 d1 / (D h))``, ``D = 2 s^2 / tau``. Step size is
``noise_step_fraction * tau`` (at most ``noise_step_max_us``). Stated
tolerance, checked by the tests: at the default step (0.8 tau) mean window
counts stay within 4 % and their variances within 15 % of those at a 20x
finer step, from dim to bright light.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numba
import numpy as np

from ._rng import _normal, _normal_outlined, _rng_state, _uniform
from .errors import EvtkError, check_parameters

__all__ = [
    "SensorModel",
    "time_constant_us",
    "log_noise_std",
    "pixel_thresholds",
    "simulate_pixels",
    "FAR_SD",
]

#: Standard deviations from a threshold beyond which the noisy state is advanced without sampling.
FAR_SD = 5.0


@dataclass(frozen=True)
class SensorModel:
    """Parameters of the event camera's pixels.

    The defaults are plausible for a DVXplorer-class sensor; they are not a
    calibration of one.

    Attributes
    ----------
    theta_on, theta_off : float
        Contrast thresholds in natural-log units.
    theta_mismatch : float
        Standard deviation of the per-pixel thresholds (log units).
    refractory_us : float
        Time a pixel is blind after an event (at least 1 us).
    tau_min_us : float
        Photoreceptor time constant in bright light.
    tau_electrons : float
        Photoelectrons per time constant in dim light (``tau -> tau_electrons/lam``).
    dark_current_e_per_s : float
        Photodiode dark current (must be positive).
    shot_noise : bool
        Simulate photon shot noise (False: deterministic, exact crossings).
    noise_step_fraction : float
        Noise step as a fraction of the time constant.
    noise_step_max_us : float
        Upper bound of the noise step.
    background_rate_hz : float
        Background-activity (leak) events per pixel per second, random polarity.
    hot_pixel_fraction : float
        Fraction of pixels that fire at ``hot_pixel_rate_hz`` regardless of light.
    hot_pixel_rate_hz : float
    readout_period_us : float
        How the sensor reads its pixels out. 0 (default): asynchronously,
        each event stamped when it happens (DAVIS-like). Above 0: in frames,
        as the DVXplorer family does (a few thousand readouts per second),
        every event stamped at the end of the readout frame it fell in, so
        time stamps are multiples of the period.
    """

    theta_on: float = 0.2
    theta_off: float = 0.2
    theta_mismatch: float = 0.02
    refractory_us: float = 1.0
    tau_min_us: float = 100.0
    tau_electrons: float = 100.0
    dark_current_e_per_s: float = 5e4
    shot_noise: bool = True
    noise_step_fraction: float = 0.8
    noise_step_max_us: float = 1000.0
    background_rate_hz: float = 0.1
    hot_pixel_fraction: float = 0.0
    hot_pixel_rate_hz: float = 1000.0
    readout_period_us: float = 0.0

    def __post_init__(self):
        def finite(name, low, strict):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) \
                    or (v <= low if strict else v < low):
                rel = ">" if strict else ">="
                raise EvtkError(f"sensor {name} must be a finite number {rel} {low}, not {v!r}")
            object.__setattr__(self, name, float(v))

        for name in ("theta_on", "theta_off", "tau_min_us", "tau_electrons", "dark_current_e_per_s",
                     "noise_step_fraction", "noise_step_max_us"):
            finite(name, 0.0, True)
        for name in ("theta_mismatch", "background_rate_hz", "hot_pixel_rate_hz", "hot_pixel_fraction",
                     "readout_period_us"):
            finite(name, 0.0, False)
        finite("refractory_us", 1.0, False)
        if self.hot_pixel_fraction > 1:
            raise EvtkError(f"sensor hot_pixel_fraction must be at most 1, not {self.hot_pixel_fraction!r}")
        # physical ceilings: beyond them thresholds never cross (a threshold of 1e18 log units indexed outside
        # the pixel's events) or time constants overflow the simulator's steps
        for name, top in (("theta_on", 100.0), ("theta_off", 100.0), ("theta_mismatch", 10.0), ("tau_min_us", 1e6),
                          ("tau_electrons", 1e12), ("dark_current_e_per_s", 1e15), ("noise_step_fraction", 1.0),
                          ("noise_step_max_us", 1e9), ("background_rate_hz", 1e6), ("hot_pixel_rate_hz", 1e6),
                          ("readout_period_us", 1e9), ("refractory_us", 1e9)):
            if getattr(self, name) > top:
                raise EvtkError(f"sensor {name} = {getattr(self, name)!r} must be at most {top:g}")
        # floors of the noise step: a step of 1e-300 us never reaches the end of a window
        for name, low in (("noise_step_fraction", 0.01), ("noise_step_max_us", 10.0)):
            if getattr(self, name) < low:
                raise EvtkError(f"sensor {name} = {getattr(self, name)!r} must be at least {low:g}")
        if not isinstance(self.shot_noise, bool):
            raise EvtkError(f"sensor shot_noise must be true or false, not {self.shot_noise!r}")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def stamp(self, t_us):
        """Event time stamps as the sensor reports them: unchanged when asynchronous, else the end of each
        event's readout frame (``ceil(t / readout_period_us) * readout_period_us``, whole microseconds)."""
        t_us = np.asarray(t_us)
        if self.readout_period_us <= 0:
            return t_us
        period = self.readout_period_us
        return (np.ceil(t_us / period) * period).round().astype(np.int64)

    @classmethod
    def from_dict(cls, d: dict) -> SensorModel:
        check_parameters("sensor", cls, d)
        return cls(**d)

    def replace(self, **changes) -> SensorModel:
        return dataclasses.replace(self, **changes)


def time_constant_us(rate_e_per_s, model: SensorModel):
    """Photoreceptor time constant ``tau = tau_min + tau_electrons / lam`` in us.

    Dim pixels are slow; the result is finite for any rate since the dark
    current is added by the caller (``rate_e_per_s`` must be > 0).
    """
    lam_per_us = np.asarray(rate_e_per_s, dtype=np.float64) * 1e-6
    return model.tau_min_us + model.tau_electrons / lam_per_us


def log_noise_std(rate_e_per_s, model: SensorModel):
    """Stationary shot-noise std of the log photoreceptor, ``1/sqrt(2*lam*tau)`` (eqs. 9-10).

    ``lam*tau = lam*tau_min + tau_electrons``: bounded above by
    ``1/sqrt(2*tau_electrons)`` in the dark and falling as ``1/sqrt(lam)`` in
    bright light. Zero when shot noise is off.
    """
    lam_per_us = np.asarray(rate_e_per_s, dtype=np.float64) * 1e-6
    if not model.shot_noise:
        return np.zeros_like(lam_per_us)
    return 1.0 / np.sqrt(2.0 * (lam_per_us * model.tau_min_us + model.tau_electrons))


def pixel_thresholds(model: SensorModel, n_pixels: int, rng: np.random.Generator):
    """Per-pixel ON and OFF thresholds with mismatch, never below 1 % of nominal."""
    on = model.theta_on + model.theta_mismatch * rng.standard_normal(n_pixels)
    off = model.theta_off + model.theta_mismatch * rng.standard_normal(n_pixels)
    return np.maximum(on, 0.01 * model.theta_on), np.maximum(off, 0.01 * model.theta_off)


class PixelState:
    """State of a set of pixels carried from one call of :func:`simulate_pixels` to the next.

    ``mean``/``var`` describe the photoreceptor output (a Gaussian when not
    yet sampled), ``vref`` the reference level and ``blind_until_us`` the end of
    the refractory period, relative to the start of the next call.
    """

    def __init__(self, level, noise_std, theta_on, theta_off, rng: np.random.Generator):
        level = np.asarray(level, dtype=np.float64)
        n = level.size
        self.theta_on = np.ascontiguousarray(theta_on, dtype=np.float64)
        self.theta_off = np.ascontiguousarray(theta_off, dtype=np.float64)
        s = np.broadcast_to(np.asarray(noise_std, dtype=np.float64), (n,))
        # steady state in the first light, freshly reset
        self.mean = level + s * rng.standard_normal(n)
        self.var = np.zeros(n)
        self.vref = self.mean.copy()
        self.blind_until_us = np.full(n, -np.inf)

    def __len__(self):
        return self.mean.size


def simulate_pixels(state: PixelState, level, tau_us, noise_std, seg_start_us, seg_end_us, model: SensorModel,
                    seed: int, *, emit=True, count_slot=None, n_slots=0):
    """Advance pixels through segments of constant light; return events and/or counts.

    Parameters
    ----------
    state : PixelState
        Updated in place; times in it are shifted to be relative to ``seg_end_us[-1]``.
    level, tau_us, noise_std : ndarray, shape (n_segments, n_pixels)
        ``log(lam)``, the time constant and the log-domain noise std per segment.
    seg_start_us, seg_end_us : ndarray, shape (n_segments,)
        Contiguous segment bounds (float us, relative to the call's start).
    seed : int
        Seeds numba's generator for this call (determinism).
    emit : bool
        Return the events (time in us as float64, pixel index, polarity).
    count_slot : ndarray of int, shape (n_segments,), optional
        Count ON/OFF events of segment k into slot ``count_slot[k]`` (-1: not counted).

    Returns
    -------
    (t_us, pixel, polarity, on_counts, off_counts)
        Events in pixel order, not sorted by time. Counts have shape
        ``(n_slots, n_pixels)`` (empty when ``count_slot`` is None).
    """
    level = np.ascontiguousarray(level, dtype=np.float64)
    tau_us = np.ascontiguousarray(tau_us, dtype=np.float64)
    noise_std = np.ascontiguousarray(noise_std, dtype=np.float64)
    n_seg, n_pix = level.shape
    if count_slot is None:
        count_slot = np.full(n_seg, -1, dtype=np.int64)
        n_slots = 0
    count_slot = np.ascontiguousarray(count_slot, dtype=np.int64)
    seg_start = np.ascontiguousarray(seg_start_us, dtype=np.float64)
    seg_end = np.ascontiguousarray(seg_end_us, dtype=np.float64)
    refr = float(model.refractory_us)
    seg_len = np.maximum(seg_end - seg_start, 0.0)
    per_pixel_bound = int(np.sum(np.floor(seg_len / refr) + 2.0)) if n_seg else 0
    cap = max(1 << 16, 4 * per_pixel_bound) if emit else 0
    out_t = np.empty(cap, np.float64)
    out_i = np.empty(cap, np.int64)
    out_p = np.empty(cap, np.uint8)
    on_c = np.zeros((n_slots, n_pix), np.int32)
    off_c = np.zeros((n_slots, n_pix), np.int32)
    n = 0
    i0 = 0
    seed = int(seed) & 0x7FFFFFFF
    while True:
        i0, n = _run_pixels(level, tau_us, noise_std, seg_start, seg_end, state.theta_on, state.theta_off,
                            refr, model.noise_step_fraction, model.noise_step_max_us, state.mean, state.var,
                            state.vref, state.blind_until_us, (seed + 7919 * i0) & 0x7FFFFFFF, emit, count_slot,
                            on_c, off_c, i0, out_t, out_i, out_p, n, per_pixel_bound)
        if i0 >= n_pix:
            break
        grow = max(2 * out_t.size, n + per_pixel_bound)
        out_t = np.concatenate([out_t[:n], np.empty(grow - n, np.float64)])
        out_i = np.concatenate([out_i[:n], np.empty(grow - n, np.int64)])
        out_p = np.concatenate([out_p[:n], np.empty(grow - n, np.uint8)])
    state.blind_until_us -= seg_end[-1] if n_seg else 0.0
    return out_t[:n], out_i[:n], out_p[:n], on_c, off_c


@numba.njit(cache=True)
def _advance(m, v, L, tau, s, dt):
    if dt <= 0.0:
        return m, v
    a = math.exp(-dt / tau)
    m = L + (m - L) * a
    v = v * a * a + s * s * (1.0 - a * a)
    return m, v


@numba.njit(cache=True, error_model="numpy")
def _run_pixels(level, tau, noise, seg_start, seg_end, th_on, th_off, refr, step_frac, step_max,
                mean, var, vref, blind, seed, emit, count_slot, on_c, off_c, i0, out_t, out_i, out_p, n,
                per_pixel_bound):
    """Pixels i0.. until done or the output might overflow; returns (next pixel, events written)."""
    rs = _rng_state(seed)
    n_seg, n_pix = level.shape
    cap = out_t.size
    Z = FAR_SD
    for i in range(i0, n_pix):
        if emit and n + per_pixel_bound > cap:
            return i, n
        m = mean[i]
        v = var[i]
        vr = vref[i]
        bl = blind[i]
        ton = th_on[i]
        toff = th_off[i]
        for k in range(n_seg):
            t = seg_start[k]
            t_end = seg_end[k]
            L = level[k, i]
            tk = tau[k, i]
            sk = noise[k, i]
            slot = count_slot[k]
            a_refr = -1.0  # exp(-refr/tau), computed at the first event of the segment
            q_refr = 0.0
            h0 = -1.0  # noise step and its constants, computed when first needed
            a0 = q0 = D = 0.0
            while t < t_end:
                if bl > t:  # blind: advance to the wake-up time
                    tr = bl if bl < t_end else t_end
                    if tr - t == refr and v == 0.0:  # woken inside the segment of its event
                        if a_refr < 0.0:
                            a_refr = math.exp(-refr / tk)
                            q_refr = sk * math.sqrt(1.0 - a_refr * a_refr)
                        m = L + (m - L) * a_refr
                        if sk > 0.0:
                            m += q_refr * _normal(rs)
                    else:
                        m, v = _advance(m, v, L, tk, sk, tr - t)
                    t = tr
                    if bl >= t_end:
                        break
                    if v > 0.0:
                        m = m + math.sqrt(v) * _normal_outlined(rs)
                        v = 0.0
                    vr = m
                bon = vr + ton
                boff = vr - toff
                tc = -1.0
                pol = 0
                if sk <= 0.0 and v <= 0.0:
                    # deterministic: closed-form crossing time
                    if L > bon:
                        tc = t + tk * math.log((m - L) / (bon - L))
                        pol = 1
                    elif L < boff:
                        tc = t + tk * math.log((m - L) / (boff - L))
                        pol = 0
                    if tc < 0.0 or tc >= t_end:
                        m, v = _advance(m, v, L, tk, sk, t_end - t)
                        t = t_end
                        break
                    m = bon if pol == 1 else boff
                else:
                    sd = sk if v <= sk * sk else math.sqrt(v)
                    heading_out = L >= bon or L <= boff  # the mean path itself crosses: just step
                    if not heading_out and m + Z * sd < bon and m - Z * sd > boff:  # far now: and later?
                        m_end = L + (m - L) * math.exp(-(t_end - t) / tk)
                        if max(m, m_end) + Z * sd < bon and min(m, m_end) - Z * sd > boff:
                            m, v = _advance(m, v, L, tk, sk, t_end - t)
                            t = t_end
                            break
                        # far now, near later: jump to where the mean path enters the near zone
                        target = bon - Z * sd if L > m else boff + Z * sd
                        dt = tk * math.log((m - L) / (target - L))
                        m, v = _advance(m, v, L, tk, sk, dt)
                        t += dt
                    if v > 0.0:
                        m = m + math.sqrt(v) * _normal_outlined(rs)
                        v = 0.0
                    if h0 < 0.0:
                        h0 = min(step_frac * tk, step_max)
                        D = 2.0 * sk * sk / tk
                        a0 = math.exp(-h0 / tk)
                        q0 = sk * math.sqrt(1.0 - a0 * a0)
                    steps = 0
                    while t < t_end:
                        h = h0
                        a = a0
                        q = q0
                        if t + h0 > t_end:
                            h = t_end - t
                            a = math.exp(-h / tk)
                            q = sk * math.sqrt(1.0 - a * a)
                        m1 = L + (m - L) * a + q * _normal(rs)
                        if m1 >= bon or m1 <= boff:
                            # crossed within the step: where the mean path crosses, if it does in
                            # this step (exact without noise), else by linear interpolation
                            pol = 1 if m1 >= bon else 0
                            b = bon if pol == 1 else boff
                            if (L - b) * (b - m) > 0.0:
                                tc = t + tk * math.log((m - L) / (b - L))
                            if not (t <= tc <= t + h):
                                tc = t + h * (b - m) / (m1 - m)
                        elif D > 0.0:
                            # Brownian-bridge chance of a crossing between the two samples
                            dh = 0.5 * D * h
                            x_on = (bon - m) * (bon - m1)
                            x_off = (m - boff) * (m1 - boff)
                            if x_on < 35.0 * dh or x_off < 35.0 * dh:
                                p_on = math.exp(-x_on / dh) if x_on < 35.0 * dh else 0.0
                                p_off = math.exp(-x_off / dh) if x_off < 35.0 * dh else 0.0
                                u = _uniform(rs)
                                if u < p_on:
                                    tc = t + h * _uniform(rs)
                                    pol = 1
                                elif u < p_on + p_off:
                                    tc = t + h * _uniform(rs)
                                    pol = 0
                        if tc >= 0.0:
                            m = bon if pol == 1 else boff
                            break
                        m = m1
                        t += h
                        steps += 1
                        if (steps & 7) == 0 and t < t_end:  # far again for the rest of the segment?
                            m_end = L + (m - L) * math.exp(-(t_end - t) / tk)
                            if max(m, m_end) + Z * sk < bon and min(m, m_end) - Z * sk > boff:
                                m, v = _advance(m, v, L, tk, sk, t_end - t)
                                t = t_end
                                break
                    if tc < 0.0:
                        break
                # an event at tc
                if emit:
                    out_t[n] = tc
                    out_i[n] = i
                    out_p[n] = pol
                    n += 1
                if slot >= 0:
                    if pol == 1:
                        on_c[slot, i] += 1
                    else:
                        off_c[slot, i] += 1
                t = tc
                bl = tc + refr
        mean[i] = m
        var[i] = v
        vref[i] = vr
        blind[i] = bl
    return n_pix, n
