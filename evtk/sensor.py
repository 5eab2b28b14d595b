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

Other physics
-------------
``SensorModel.pixel`` chooses the photoreceptor and change detector, so that
reconstruction can be judged on pixels of another form than the one it fits
(descriptions after the published models, not their code):

* ``"evtk"`` (default): the model above.
* ``"v2e"``: after Hu, Liu and Delbruck's v2e (2021). The photoreceptor is a
  first-order low-pass of ``log(lam)`` whose time constant follows the light
  down to a floor, ``tau = max(tau_min_us, tau_electrons / lam)``: a hard
  bandwidth knee (:func:`time_constant_us`), flat above
  ``lam = tau_electrons / tau_min_us``. The state is stepped (exact
  Ornstein-Uhlenbeck transitions, steps of at most a quarter of ``tau``);
  a crossing's time is interpolated linearly within its step, and after
  each event the reference is reset to the photoreceptor's present level.
  ``leak_rate_hz`` lets the reference sink by ``theta_on`` that often (leak
  ON events), ``shot_event_rate_hz`` adds shot-noise events of either
  polarity (most in the dark, their rate falling as ``sqrt(dark / lam)``).
* ``"log-node"``: after ESIM (Rebecq, Gehrig and Scaramuzza 2018): no
  low-pass, the pixel sees ``log(lam)`` itself, sampled every ``sample_us``
  and linearly interpolated between samples; an event whenever it has moved
  one threshold from the last event's level, the reference moving by exactly
  one threshold per event, each crossing timed by the interpolation. No
  refractory period and no photoreceptor noise (ESIM has none).

``frame_compare`` (with ``readout_period_us`` > 0) replaces the stamped
asynchronous readout by a synchronous one, as the DVXplorer family reads its
pixels: once per frame each pixel compares its level with its reference and
fires at most one event, stamped on the frame grid, its reference reset to
the level it compared.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from ._lazyjit import njit, numba_ready  # numba loads on the first stochastic or large run
from ._rng import normal, normal_outlined, rng_state, uniform
from .errors import EvtkError, check_parameters

if TYPE_CHECKING:
    import numpy.typing as npt

__all__ = [
    "PIXELS",
    "SensorModel",
    "time_constant_us",
    "log_noise_std",
    "pixel_thresholds",
    "simulate_pixels",
    "FAR_SD",
]

#: Standard deviations from a threshold beyond which the noisy state is advanced without sampling.
FAR_SD = 5.0

# simulate_pixels' numpy loop for noise-free pixels (_run_pixels_numpy) costs about 40 us per round (all active
# pixels' next event) on top of about as much per event as numba's kernel: it runs while numba is not loaded
# (numba's start, about 0.5 s, costs more than 10_000 rounds) and, once it is, for at least _NUMPY_WARM_PIXELS
# pixels, where its vector arithmetic is as fast as the compiled loop (docs/performance.md)
_NUMPY_MAX_ROUNDS = 10_000
_NUMPY_WARM_PIXELS = 4000

#: The pixel physics :class:`SensorModel` offers (its ``pixel`` field).
PIXELS = ("evtk", "v2e", "log-node")


@dataclass(frozen=True)
class SensorModel:
    """Parameters of the event camera's pixels.

    The defaults are plausible for a DVXplorer-class sensor; they are not a
    calibration of one.

    Parameters
    ----------
    theta_on : float
        ON contrast threshold in natural-log units.
    theta_off : float
        OFF contrast threshold in natural-log units.
    theta_mismatch : float
        Standard deviation of the per-pixel thresholds (log units).
    refractory_us : float
        Time a pixel is blind after an event (at least 1 us).
    tau_min_us : float
        Photoreceptor time constant in bright light.
    tau_electrons : float
        Photoelectrons per time constant in dim light (``tau -> tau_electrons/lam``).
    dark_current_e_per_s : float
        Photodiode dark current, photoelectrons per second (must be positive).
    shot_noise : bool
        Simulate photon shot noise (False: deterministic, exact crossings).
    noise_step_fraction : float
        Noise step as a fraction of the time constant.
    noise_step_max_us : float
        Upper bound of the noise step, us.
    background_rate_hz : float
        Background-activity (leak) events per pixel per second, random polarity.
    hot_pixel_fraction : float
        Fraction of pixels that fire at ``hot_pixel_rate_hz`` regardless of light.
    hot_pixel_rate_hz : float
        Event rate of a hot pixel, per second.
    readout_period_us : float
        How the sensor reads its pixels out. 0 (default): asynchronously,
        each event stamped when it happens (DAVIS-like). Above 0: in frames,
        as the DVXplorer family does (a few thousand readouts per second),
        every event stamped at the end of the readout frame it fell in, so
        time stamps are multiples of the period.
    pixel : {"evtk", "v2e", "log-node"}
        The pixel's physics (see the module's notes): evtk's own
        (default), a v2e-style pixel with a hard bandwidth knee, or an
        ESIM-like log-node pixel.
    frame_compare : bool
        With ``readout_period_us`` > 0: a synchronous readout that compares
        each pixel once per frame and fires at most one event per pixel per
        frame (False: asynchronous events stamped at their frame's end).
    leak_rate_hz : float
        Leak events per pixel per second from a sinking reference (``v2e`` and
        ``log-node`` pixels, or a frame-compared readout; 0 otherwise).
    shot_event_rate_hz : float
        Shot-noise events per pixel per second in the dark (falling as
        ``sqrt(dark / lam)``), of either polarity (as ``leak_rate_hz``).
    sample_us : float
        A ``log-node`` pixel's sampling of the light (linear interpolation in between).
    clock_drift_ppm : float
        The camera's clock against the DMD's: event time stamps run this many
        parts per million fast (negative: slow) from the start of the run,
        while the trigger edges keep the DMD's time.

    Raises
    ------
    EvtkError
        If a value is not finite, of the wrong kind or outside its physical range, the pixel is unknown, or
        the rates and readout settings do not fit the chosen pixel.
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
    pixel: str = "evtk"
    frame_compare: bool = False
    leak_rate_hz: float = 0.0
    shot_event_rate_hz: float = 0.0
    sample_us: float = 1.0
    clock_drift_ppm: float = 0.0

    def __post_init__(self) -> None:
        def finite(name: str, low: float, strict: bool) -> None:
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) \
                    or (v <= low if strict else v < low):
                rel = ">" if strict else ">="
                raise EvtkError(f"sensor {name} must be a finite number {rel} {low}, not {v!r}")
            object.__setattr__(self, name, float(v))

        for name in ("theta_on", "theta_off", "tau_min_us", "tau_electrons", "dark_current_e_per_s",
                     "noise_step_fraction", "noise_step_max_us", "sample_us"):
            finite(name, 0.0, True)
        for name in ("theta_mismatch", "background_rate_hz", "hot_pixel_rate_hz", "hot_pixel_fraction",
                     "readout_period_us", "leak_rate_hz", "shot_event_rate_hz"):
            finite(name, 0.0, False)
        finite("clock_drift_ppm", -1e5, True)
        finite("refractory_us", 1.0, False)
        if self.hot_pixel_fraction > 1:
            raise EvtkError(f"sensor hot_pixel_fraction must be at most 1, not {self.hot_pixel_fraction!r}")
        for name in ("shot_noise", "frame_compare"):
            if not isinstance(getattr(self, name), bool):
                raise EvtkError(f"sensor {name} must be true or false, not {getattr(self, name)!r}")
        if self.pixel not in PIXELS:
            raise EvtkError(f"sensor pixel must be one of {', '.join(PIXELS)}, not {self.pixel!r}")
        if self.frame_compare and self.readout_period_us <= 0:
            raise EvtkError("sensor frame_compare needs a readout_period_us above 0 (the frame period)")
        if (self.leak_rate_hz or self.shot_event_rate_hz) and not self.stepped:
            raise EvtkError("sensor leak_rate_hz and shot_event_rate_hz belong to the v2e and log-node pixels and "
                            "to a frame-compared readout; evtk's asynchronous pixel has background_rate_hz")
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

    @property
    def stepped(self) -> bool:
        """Whether the pixels are stepped in time (:func:`simulate_pixels`' second loop): any physics but evtk's
        own asynchronous pixel."""
        return self.pixel != "evtk" or self.frame_compare

    def to_dict(self) -> dict:
        """The parameters as a plain dict, for TOML/JSON.

        Returns
        -------
        dict
            Field name to value; :meth:`from_dict` reads it back.
        """
        return dataclasses.asdict(self)

    def stamp(self, t_us: npt.ArrayLike, origin_us: int = 0) -> np.ndarray:
        """Event time stamps as the sensor reports them.

        Parameters
        ----------
        t_us : array_like
            The events' true times (whole us).
        origin_us : int
            Where the camera's clock agrees with the DMD's (the start of the run), for ``clock_drift_ppm``.

        Returns
        -------
        numpy.ndarray
            Unchanged when asynchronous, else the end of each event's readout
            frame (``ceil(t / readout_period_us) * readout_period_us``, whole
            microseconds); then run through the camera's clock,
            ``t + round((t - origin_us) * clock_drift_ppm / 1e6)``.
        """
        t: np.ndarray = np.asarray(t_us)
        if self.readout_period_us > 0:
            period = self.readout_period_us
            t = (np.ceil(t / period) * period).round().astype(np.int64)
        if self.clock_drift_ppm:
            t = t + np.round((t - origin_us) * (self.clock_drift_ppm * 1e-6)).astype(np.int64)
        return t

    @classmethod
    def from_dict(cls, d: dict) -> SensorModel:
        """A sensor model from a dict of parameters (missing ones take their defaults).

        Parameters
        ----------
        d : dict
            Field name to value, as :meth:`to_dict` writes (a bench file's ``sensor`` table).

        Returns
        -------
        SensorModel
            The checked model.

        Raises
        ------
        EvtkError
            If a key is not a parameter, a value has the wrong kind or is out of range.
        """
        check_parameters("sensor", cls, d)
        return cls(**d)

    def replace(self, **changes: Any) -> SensorModel:
        """A copy with some parameters changed (checked again).

        Parameters
        ----------
        **changes : Any
            Field name to new value.

        Returns
        -------
        SensorModel
            The new model.
        """
        return dataclasses.replace(self, **changes)


def time_constant_us(rate_e_per_s: npt.ArrayLike, model: SensorModel) -> np.ndarray:
    """Photoreceptor time constant in us.

    Parameters
    ----------
    rate_e_per_s : array_like
        Photocurrent, dark current included, photoelectrons per second (must be > 0).
    model : SensorModel
        The pixel model (its ``pixel``, ``tau_min_us`` and ``tau_electrons``).

    Returns
    -------
    numpy.ndarray
        float64, shaped like ``rate_e_per_s``, us.
        evtk's pixel: ``tau_min + tau_electrons / lam`` (dim pixels are slow,
        smoothly). A v2e pixel: ``max(tau_min, tau_electrons / lam)``, a hard
        knee at ``lam = tau_electrons / tau_min`` above which it is flat. A
        log-node pixel: 0 (it follows the light at once).
    """
    lam_per_us = np.asarray(rate_e_per_s, dtype=np.float64) * 1e-6
    if model.pixel == "v2e":
        return np.maximum(model.tau_min_us, model.tau_electrons / lam_per_us)
    if model.pixel == "log-node":
        return np.zeros_like(lam_per_us)
    return model.tau_min_us + model.tau_electrons / lam_per_us


def log_noise_std(rate_e_per_s: npt.ArrayLike, model: SensorModel) -> np.ndarray:
    """Stationary shot-noise std of the log photoreceptor, ``1/sqrt(2*lam*tau)`` (eqs. 9-10).

    ``lam*tau = lam*tau_min + tau_electrons``: bounded above by
    ``1/sqrt(2*tau_electrons)`` in the dark and falling as ``1/sqrt(lam)`` in
    bright light. Zero when shot noise is off.

    Parameters
    ----------
    rate_e_per_s : array_like
        Photocurrent, dark current included, photoelectrons per second (must be > 0).
    model : SensorModel
        The pixel model (its ``shot_noise``, ``pixel`` and time-constant parameters).

    Returns
    -------
    numpy.ndarray
        float64, shaped like ``rate_e_per_s``: the standard deviation in natural-log units (zeros when shot noise
        is off or for a log-node pixel).
    """
    lam_per_us = np.asarray(rate_e_per_s, dtype=np.float64) * 1e-6
    if not model.shot_noise or model.pixel == "log-node":
        return np.zeros_like(lam_per_us)
    if model.pixel == "v2e":  # the same 1/sqrt(2 lam tau) with the knee's time constant
        return 1.0 / np.sqrt(2.0 * lam_per_us * time_constant_us(rate_e_per_s, model))
    return 1.0 / np.sqrt(2.0 * (lam_per_us * model.tau_min_us + model.tau_electrons))


def pixel_thresholds(model: SensorModel, n_pixels: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel ON and OFF thresholds with mismatch, never below 1 % of nominal.

    Parameters
    ----------
    model : SensorModel
        Nominal thresholds and their mismatch (standard deviation), natural-log units.
    n_pixels : int
        How many pixels.
    rng : numpy.random.Generator
        Draws the mismatch (ON thresholds first, then OFF).

    Returns
    -------
    theta_on : numpy.ndarray
        float64, shape ``(n_pixels,)``, natural-log units.
    theta_off : numpy.ndarray
        float64, shape ``(n_pixels,)``, natural-log units.
    """
    on = model.theta_on + model.theta_mismatch * rng.standard_normal(n_pixels)
    off = model.theta_off + model.theta_mismatch * rng.standard_normal(n_pixels)
    return np.maximum(on, 0.01 * model.theta_on), np.maximum(off, 0.01 * model.theta_off)


class PixelState:
    """State of a set of pixels carried from one call of :func:`simulate_pixels` to the next.

    ``mean``/``var`` describe the photoreceptor output (a Gaussian when not
    yet sampled), ``vref`` the reference level and ``blind_until_us`` the end of
    the refractory period, relative to the start of the next call.

    Parameters
    ----------
    level : array_like
        ``log(lam)`` of each pixel in the first light (``lam`` in photoelectrons per second), shape ``(n,)``.
    noise_std : array_like
        Log-domain noise standard deviation, per pixel or one for all.
    theta_on : array_like
        Per-pixel ON thresholds (:func:`pixel_thresholds`), natural-log units.
    theta_off : array_like
        Per-pixel OFF thresholds.
    rng : numpy.random.Generator, optional
        Draws the starting state (steady state in the first light, freshly reset). None where every pixel's
        ``noise_std`` is 0: the state is then the light itself, and numpy.random (12 ms of a fresh process) is
        not loaded.

    Raises
    ------
    EvtkError
        Without ``rng`` where a pixel has noise.
    """

    def __init__(self, level: npt.ArrayLike, noise_std: npt.ArrayLike, theta_on: npt.ArrayLike,
                 theta_off: npt.ArrayLike, rng: np.random.Generator | None = None) -> None:
        level = np.asarray(level, dtype=np.float64)
        n = level.size
        self.theta_on = np.ascontiguousarray(theta_on, dtype=np.float64)
        self.theta_off = np.ascontiguousarray(theta_off, dtype=np.float64)
        s = np.broadcast_to(np.asarray(noise_std, dtype=np.float64), (n,))
        # steady state in the first light, freshly reset
        if rng is not None:
            self.mean = level + s * rng.standard_normal(n)
        elif np.any(s != 0):
            raise EvtkError("PixelState: pixels with noise need an rng to draw their starting state")
        else:
            self.mean = level + 0.0  # the values level + 0 * a normal draw gives
        self.var = np.zeros(n)
        self.vref = self.mean.copy()
        self.blind_until_us = np.full(n, -np.inf)

    def __len__(self) -> int:
        return self.mean.size


def simulate_pixels(
    state: PixelState,
    level: npt.ArrayLike,
    tau_us: npt.ArrayLike,
    noise_std: npt.ArrayLike,
    seg_start_us: npt.ArrayLike,
    seg_end_us: npt.ArrayLike,
    model: SensorModel,
    seed: int,
    *,
    emit: bool = True,
    count_slot: npt.ArrayLike | None = None,
    n_slots: int = 0,
    t0_us: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Advance pixels through segments of constant light; return events and/or counts.

    evtk's own pixel without noise (no shot noise, a state without variance) runs in numpy, all pixels a round
    at a time, while numba is not loaded (a fresh process, where numba's start costs 0.5 s) or for thousands of
    pixels (as fast as the compiled loop): the same events and counts as numba's kernel, times to rounding.

    Parameters
    ----------
    state : PixelState
        Updated in place; times in it are shifted to be relative to ``seg_end_us[-1]``.
    level : array_like, shape (n_segments, n_pixels)
        ``log(lam)`` per segment and pixel (``lam`` in photoelectrons per second).
    tau_us : array_like, shape (n_segments, n_pixels)
        The photoreceptor time constant (:func:`time_constant_us`), us.
    noise_std : array_like, shape (n_segments, n_pixels)
        The log-domain noise standard deviation (:func:`log_noise_std`).
    seg_start_us : array_like, shape (n_segments,)
        Segment starts (float us, relative to the call's start).
    seg_end_us : array_like, shape (n_segments,)
        Segment ends; segments are contiguous.
    model : SensorModel
        The pixel physics and readout.
    seed : int
        Seeds numba's generator for this call (determinism).
    emit : bool
        Return the events (time in us as float64, pixel index, polarity).
    count_slot : ndarray of int, shape (n_segments,), optional
        Count ON/OFF events of segment k into slot ``count_slot[k]`` (-1: not counted).
    n_slots : int
        Number of count slots (ignored when ``count_slot`` is None).
    t0_us : float
        Absolute time of the call's start (a frame-compared readout's frames fall on multiples of the period).

    Returns
    -------
    t_us : numpy.ndarray
        float64 event times, us relative to the call's start; events in pixel order, not sorted by time
        (empty when ``emit`` is False).
    pixel : numpy.ndarray
        int64 pixel index of each event.
    polarity : numpy.ndarray
        uint8 polarity of each event (1 ON, 0 OFF).
    on_counts : numpy.ndarray
        int32, shape ``(n_slots, n_pixels)``: ON events per slot (empty when ``count_slot`` is None).
    off_counts : numpy.ndarray
        int32, the same for OFF events.
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
    if _numpy_path(state, level, tau_us, noise_std, seg_start, seg_end, model):
        on_c = np.zeros((n_slots, n_pix), np.int32)
        off_c = np.zeros((n_slots, n_pix), np.int32)
        ev_t, ev_i, ev_p = _run_pixels_numpy(level, tau_us, seg_start, seg_end, state.theta_on, state.theta_off,
                                             refr, state.mean, state.vref, state.blind_until_us, emit, count_slot,
                                             on_c, off_c)
        state.blind_until_us -= seg_end[-1] if n_seg else 0.0
        return ev_t, ev_i, ev_p, on_c, off_c
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
    if model.stepped:
        period = model.readout_period_us if model.frame_compare else 0.0
        if period > 0:  # at most one event per frame
            per_pixel_bound = int(np.sum(np.floor(seg_len / period) + 2.0)) if n_seg else 0
        per_pixel_bound += int(np.sum(seg_len) * 1e-6 * (model.leak_rate_hz + model.shot_event_rate_hz) * 4) + 16
        cap = max(1 << 16, 4 * per_pixel_bound) if emit else 0
        out_t = np.empty(cap, np.float64)
        out_i = np.empty(cap, np.int64)
        out_p = np.empty(cap, np.uint8)
        mode = PIXELS.index(model.pixel)
        params = np.array([refr, model.noise_step_max_us, period, float(t0_us) % period if period > 0 else 0.0,
                           model.leak_rate_hz * 1e-6, model.shot_event_rate_hz * 1e-6,
                           math.log(model.dark_current_e_per_s), model.sample_us])
    while True:
        if model.stepped:
            i0, n = _run_stepped(mode, params, level, tau_us, noise_std, seg_start, seg_end, state.theta_on,
                                 state.theta_off, state.mean, state.vref, state.blind_until_us,
                                 (seed + 7919 * i0) & 0x7FFFFFFF, emit, count_slot, on_c, off_c, i0, out_t, out_i,
                                 out_p, n, per_pixel_bound)
        else:
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


def _numpy_path(state: PixelState, level: np.ndarray, tau_us: np.ndarray, noise_std: np.ndarray, seg_start: np.ndarray,
                seg_end: np.ndarray, model: SensorModel) -> bool:
    """Whether :func:`simulate_pixels` runs :func:`_run_pixels_numpy`: evtk's asynchronous pixel with no noise
    and an exact state (:func:`_run_pixels`' closed-form branch only), in few enough rounds
    (:data:`_NUMPY_MAX_ROUNDS`), while numba is not loaded or for many pixels (:data:`_NUMPY_WARM_PIXELS`)."""
    n_seg, n_pix = level.shape
    if model.stepped or np.any(noise_std) or np.any(state.var) or (numba_ready() and n_pix < _NUMPY_WARM_PIXELS):
        return False
    if not n_seg * n_pix:
        return True
    # within a segment each event takes the photoreceptor at least one threshold nearer the light's level, so a
    # pixel has at most span / theta + 1 events there, two rounds each (the event, the wake-up)
    span = max(level.max(), state.mean.max()) - min(level.min(), state.mean.min())
    theta = min(state.theta_on.min(), state.theta_off.min()) if n_pix else 1.0
    live = np.count_nonzero(seg_end > seg_start)
    if not live * 2.0 * (span / theta + 2.0) <= _NUMPY_MAX_ROUNDS:  # NaN: numba
        return False
    # a time constant that is not a positive finite number turns the kernel's variance into NaN (its noisy branch)
    return bool(np.all(np.isfinite(tau_us) & (tau_us > 0.0)))


def _run_pixels_numpy(level: np.ndarray, tau: np.ndarray, seg_start: np.ndarray, seg_end: np.ndarray,
                      th_on: np.ndarray, th_off: np.ndarray, refr: float, mean: np.ndarray, vref: np.ndarray,
                      blind: np.ndarray, emit: bool, count_slot: np.ndarray, on_c: np.ndarray,
                      off_c: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_run_pixels` without noise, in numpy: the same closed-form steps, taken by all pixels at once.

    Within each segment the still-active pixels advance one event at a time together: a blind pixel wakes
    (its reference the photoreceptor's level then), an awake one crosses a threshold at
    ``t + tau log((m - L) / (b - L))`` or relaxes to the segment's end. The operations, their order and
    their comparisons (NaN included) are :func:`_run_pixels`' own, so counts and state agree with it up to
    the last bit of numpy's ``exp``/``log`` against the C library's. ``mean``, ``vref`` and ``blind`` are
    updated in place (times not shifted). Returns the events (time, pixel, polarity) in pixel order.
    """
    n_seg, n_pix = level.shape
    ev_t: list[np.ndarray] = []
    ev_i: list[np.ndarray] = []
    ev_p: list[np.ndarray] = []
    with np.errstate(all="ignore"):  # NaN and inf take the kernel's own paths through the comparisons
        for k in range(n_seg):
            t0, t_end = float(seg_start[k]), float(seg_end[k])
            if not t0 < t_end:
                continue
            slot = int(count_slot[k])
            idx = np.arange(n_pix)
            L, tk, ton, toff = level[k], tau[k], th_on, th_off
            m, vr, bl = mean.copy(), vref.copy(), blind.copy()
            t = np.full(n_pix, t0)
            while idx.size:
                asleep = bl > t
                if asleep.any():  # blind: relax to the wake-up (or the segment's end); the reference is set there
                    tr = np.where(bl < t_end, bl, t_end)
                    m = np.where(asleep, L + (m - L) * np.exp(-(tr - t) / tk), m)
                    t = np.where(asleep, tr, t)
                    woken = asleep & ~(bl >= t_end)
                    vr = np.where(woken, m, vr)
                    asleep &= ~woken
                bon = vr + ton
                boff = vr - toff
                up = L > bon
                cross = up | (L < boff)
                b = np.where(up, bon, boff)
                tc = np.where(cross, t + tk * np.log((m - L) / (b - L)), -1.0)
                miss = ~asleep & ((tc < 0.0) | (tc >= t_end))
                if miss.any():  # no crossing in the segment: relax to its end
                    dt = t_end - t
                    m = np.where(miss & ~(dt <= 0.0), L + (m - L) * np.exp(-dt / tk), m)
                event = ~asleep & ~miss
                m = np.where(event, b, m)
                bl = np.where(event, tc + refr, bl)
                if event.any():
                    who = idx[event]
                    pol = up[event]
                    if slot >= 0:
                        on_c[slot, who[pol]] += 1
                        off_c[slot, who[~pol]] += 1
                    if emit:
                        ev_t.append(tc[event])
                        ev_i.append(who)
                        ev_p.append(pol.astype(np.uint8))
                done = ~(event & (tc < t_end))
                if done.any():
                    out = idx[done]
                    mean[out], vref[out], blind[out] = m[done], vr[done], bl[done]
                    keep = ~done
                    idx, m, vr, bl, t = idx[keep], m[keep], vr[keep], bl[keep], tc[keep]
                    L, tk, ton, toff = L[keep], tk[keep], ton[keep], toff[keep]
                else:
                    t = tc
    if not ev_t:
        return np.empty(0, np.float64), np.empty(0, np.int64), np.empty(0, np.uint8)
    pix = np.concatenate(ev_i)
    order = np.argsort(pix, kind="stable")  # the kernel's order: pixel by pixel, each in time
    return np.concatenate(ev_t)[order], pix[order], np.concatenate(ev_p)[order]


@njit(cache=True, inline="always")
def _record(emit, n, tc, i, pol, slot, out_t, out_i, out_p, on_c, off_c):
    """Write one event (when emitting) and count it in its slot; returns the events written."""
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
    return n


@njit(cache=True)
def _advance(m, v, L, tau, s, dt):
    if dt <= 0.0:
        return m, v
    a = math.exp(-dt / tau)
    m = L + (m - L) * a
    v = v * a * a + s * s * (1.0 - a * a)
    return m, v


@njit(cache=True, error_model="numpy")
def _run_pixels(level, tau, noise, seg_start, seg_end, th_on, th_off, refr, step_frac, step_max,
                mean, var, vref, blind, seed, emit, count_slot, on_c, off_c, i0, out_t, out_i, out_p, n,
                per_pixel_bound):
    """Pixels i0.. until done or the output might overflow; returns (next pixel, events written)."""
    rs = rng_state(seed)
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
                            m += q_refr * normal(rs)
                    else:
                        m, v = _advance(m, v, L, tk, sk, tr - t)
                    t = tr
                    if bl >= t_end:
                        break
                    if v > 0.0:
                        m = m + math.sqrt(v) * normal_outlined(rs)
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
                        m = m + math.sqrt(v) * normal_outlined(rs)
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
                        m1 = L + (m - L) * a + q * normal(rs)
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
                                u = uniform(rs)
                                if u < p_on:
                                    tc = t + h * uniform(rs)
                                    pol = 1
                                elif u < p_on + p_off:
                                    tc = t + h * uniform(rs)
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
                n = _record(emit, n, tc, i, pol, slot, out_t, out_i, out_p, on_c, off_c)  # an event at tc
                t = tc
                bl = tc + refr
        mean[i] = m
        var[i] = v
        vref[i] = vr
        blind[i] = bl
    return n_pix, n


@njit(cache=True, error_model="numpy")
def _run_stepped(mode, params, level, tau, noise, seg_start, seg_end, th_on, th_off, mean, vref, blind, seed,
                 emit, count_slot, on_c, off_c, i0, out_t, out_i, out_p, n, per_pixel_bound):
    """The stepped pixels (``mode``: index in :data:`PIXELS`), i0.. until done or the output might overflow.

    ``params``: refractory (us), largest step (us), frame period (0: asynchronous), the call's start modulo the
    period, leak and shot-event rates (per us), log of the dark current, the log-node's sampling (us).
    Returns (next pixel, events written).
    """
    rs = rng_state(seed)
    n_seg, n_pix = level.shape
    cap = out_t.size
    refr, step_max, period, phase = params[0], params[1], params[2], params[3]
    leak, shot, log_dark, sample = params[4], params[5], params[6], params[7]
    lognode = mode == 2
    for i in range(i0, n_pix):
        if emit and n + per_pixel_bound > cap:
            return i, n
        m = mean[i]
        vr = vref[i]
        bl = blind[i]
        ton = th_on[i]
        toff = th_off[i]
        # the next frame, relative to the call's start
        tick = period - phase  # (a frame at the call's very start was the previous call's last)
        for k in range(n_seg):
            t = seg_start[k]
            t_end = seg_end[k]
            L = level[k, i]
            tk = tau[k, i]
            sk = noise[k, i]
            slot = count_slot[k]
            r_shot = shot * math.sqrt(min(1.0, math.exp(log_dark - L))) if shot > 0.0 else 0.0
            if lognode:
                if period <= 0.0 and L != m:
                    # the light's change, linearly interpolated over one sample: one event per threshold
                    ramp = min(sample, t_end - t)
                    while L - vr >= ton:
                        vr += ton
                        tc = t + ramp * max(0.0, (vr - m) / (L - m))
                        n = _record(emit, n, tc, i, 1, slot, out_t, out_i, out_p, on_c, off_c)
                    while vr - L >= toff:
                        vr -= toff
                        tc = t + ramp * max(0.0, (vr - m) / (L - m))
                        n = _record(emit, n, tc, i, 0, slot, out_t, out_i, out_p, on_c, off_c)
                m = L
                if period <= 0.0 and leak <= 0.0 and r_shot <= 0.0:
                    continue
            while t < t_end:
                h = t_end - t
                if period > 0.0:
                    h = min(h, tick - t)
                elif not lognode:
                    h = min(h, 0.25 * tk, step_max)
                else:
                    h = min(h, step_max)
                if bl > t:
                    h = min(h, bl - t)
                if h < 0.0:
                    h = 0.0
                # the photoreceptor over the step (exact OU transition), the reference sinking by the leak
                if lognode:
                    m1 = L
                else:
                    a = math.exp(-h / tk)
                    m1 = L + (m - L) * a
                    if sk > 0.0:
                        m1 += sk * math.sqrt(1.0 - a * a) * normal(rs)
                vr1 = vr - leak * ton * h
                t1 = t + h
                awake = bl <= t
                if period > 0.0:
                    m = m1
                    vr = vr1
                    t = t1
                    if t >= tick - 1e-9:  # a frame: compare once, fire at most once, reset to the level
                        tick += period
                        if bl <= t:
                            pol = -1
                            if m - vr >= ton:
                                pol = 1
                            elif vr - m >= toff:
                                pol = 0
                            if pol >= 0:
                                n = _record(emit, n, t, i, pol, slot, out_t, out_i, out_p, on_c, off_c)
                                vr = m
                                bl = t + refr
                    continue
                if awake and r_shot > 0.0 and uniform(rs) < r_shot * h:  # a shot-noise event in this step
                    tc = t + h * uniform(rs)
                    pol = 1 if uniform(rs) < 0.5 else 0
                    n = _record(emit, n, tc, i, pol, slot, out_t, out_i, out_p, on_c, off_c)
                    m = m + (m1 - m) * (tc - t) / h if h > 0.0 else m1
                    vr = m
                    t = tc
                    bl = tc + refr
                    continue
                d0 = m - vr
                d1 = m1 - vr1
                pol = -1
                if awake and d1 >= ton:
                    pol = 1
                    b = ton
                elif awake and d1 <= -toff:
                    pol = 0
                    b = -toff
                if pol < 0:
                    m = m1
                    vr = vr1
                    t = t1
                    continue
                f = (b - d0) / (d1 - d0) if d1 != d0 else 1.0
                f = min(max(f, 0.0), 1.0)
                tc = t + h * f
                n = _record(emit, n, tc, i, pol, slot, out_t, out_i, out_p, on_c, off_c)
                m = m + (m1 - m) * f
                if lognode:  # ESIM: the reference moves by one threshold
                    vr = vr + (vr1 - vr) * f + b
                else:  # v2e: reset to the present level
                    vr = m
                t = tc
                if not lognode:
                    bl = tc + refr
        mean[i] = m
        vref[i] = vr
        blind[i] = bl
    return n_pix, n
