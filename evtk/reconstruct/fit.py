"""A pixel model fitted to the recording's own level captures, so the model-based stages run without a record.

The level captures (:data:`evtk.simulate.LEVEL_ID`) light the response's
interior with 1 ... K units (kernel elements) of light. Over their interior
pixels :func:`level_statistics` takes, per step, the mean net count and the
median time of the first and the last ON event; :func:`level_rise_times`
adds the median time of the ON event half-way up each step's rise, and
:func:`level_off_times` the decay's OFF events. :func:`fit_pixel_model`
then finds the pixel model whose noise-free response to the same steps, in
the same windows, gives those numbers:

* the contrast threshold ``theta`` and the light of the dark level
  ``blank`` (in the same units: the pixel sees ``log(1 + light / blank)``)
  from the counts;
* the time constant in bright light ``tau_min_us`` and at the dark level
  ``tau_dark_us`` (:func:`evtk.sensor.time_constant_us`: ``tau = tau_min +
  tau_electrons / rate``) from the rise's and the decay's event times.

Absolute photon rates are not observable from events; the fitted model
states them relative to a nominal dark rate, which is all the
reconstruction needs. The calibrated route puts the model in the run's
:class:`~evtk.plan.Plan` (:class:`~evtk.plan.PixelModel`) for
:func:`~evtk.reconstruct.reconstruct_counts`: the oracle's pipeline, with a
model the recording itself gave.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import EvtkError
from ..optics.camera import CellMap
from ..sensor import PixelState, SensorModel, simulate_pixels, time_constant_us
from .windows import WindowCounts

if TYPE_CHECKING:
    import numpy.typing as npt

__all__ = ["LevelStatistics", "PixelFit", "interior_pixels", "level_statistics", "level_off_times", "level_rise_times",
           "rise_orders", "refractory_bound",
           "on_gaps", "fit_refractory", "GAP_QUANTILES",
           "predict_levels", "fit_pixel_model", "hot_pixels", "describe_pixels"]

#: Thresholds sampled across the mismatch when predicting a step's mean count (smooths the counts' steps).
SPREAD_POINTS = 25

#: Weight (µs per unit residual) of the rise's median ON times in :func:`fit_pixel_model` (a sweep of 1, 3 and 10 µs
#: over nine simulated cameras and poses kept the calibrated route within 1.17, 1.06 and 1.23x the oracle).
RISE_SCALE_US = 3.0

#: Largest trigger-to-light delay (µs, either sign) :func:`fit_pixel_model` fits and a pixel model may hold.
MAX_DELAY_US = 200.0

#: Nominal dark-level photoelectron rate the fitted model is stated against (only ratios are observable).
NOMINAL_BLANK_E_PER_S = 1e5


@dataclass(frozen=True)
class LevelStatistics:
    """Per light step: ``light`` (units), mean net ``counts``, median ``first_us``/``last_us`` ON-event times
    from the window start (NaN where no interior pixel fired), ``pixels`` averaged, and the mean time of the
    OFF events after the step ends (``off_mean_us``, :func:`level_off_times`).

    Every array has one entry per step, the steps in increasing light.

    Parameters
    ----------
    light : numpy.ndarray
        float64: each step's light, in response units above the dark level (kernel elements on, with every
        feature element on).
    counts : numpy.ndarray
        float64: the mean net count ON - OFF of an interior pixel in a window of the step (flat-field gain
        applied where there is one).
    first_us, last_us : numpy.ndarray
        float64: median time (µs from the window's start) of an interior pixel's first and last ON event in
        the step's windows; NaN where no interior pixel fired.
    pixels : int
        Interior pixels averaged.
    off_mean_us : numpy.ndarray, optional
        float64: mean time (µs after the pattern's falling edge) of the interior pixels' OFF events while the
        step decays to the dark level (:func:`level_off_times`); NaN where there were none.
    off_counts : numpy.ndarray, optional
        float64: mean number of those OFF events a pixel fires in a decay (they measure the OFF threshold).
    rise_order : numpy.ndarray, optional
        int64: which ON event of each step (1 = the first) ``rise_us`` times, about half the step's count
        (:func:`rise_orders`).
    rise_us : numpy.ndarray, optional
        float64: median time (µs from the window's start) of each interior pixel's ``rise_order``-th ON event
        (:func:`level_rise_times`); NaN where no pixel fired that often.
    """

    light: np.ndarray
    counts: np.ndarray
    first_us: np.ndarray
    last_us: np.ndarray
    pixels: int
    #: mean time of the OFF events after the pattern goes (from its falling edge): the decay to the dark level
    off_mean_us: np.ndarray | None = None
    #: mean number of those OFF events a pixel fires (the same log step down: the OFF threshold)
    off_counts: np.ndarray | None = None
    #: which ON event of each step :attr:`rise_us` times (about half the step's count, :func:`rise_orders`)
    rise_order: np.ndarray | None = None
    #: median time of each pixel's ``rise_order``-th ON event from the window start (:func:`level_rise_times`)
    rise_us: np.ndarray | None = None


@dataclass(frozen=True)
class PixelFit:
    """The fitted pixel model: :class:`~evtk.sensor.SensorModel` plus the dark level's light ``blank``
    (response units), the residuals and the statistics it was fitted to.

    Absolute photon rates are not observable from events: the model states them relative to a dark-level rate
    of :data:`NOMINAL_BLANK_E_PER_S` photoelectrons per second, whose light is ``blank``.

    Parameters
    ----------
    sensor : SensorModel
        The fitted pixel: ON and OFF thresholds (log-intensity units) and their mismatch, ``tau_min_us``, the
        time constant's photoelectron term (from ``tau_dark_us``), the refractory period; noise-free.
    blank : float
        Light of the dark level, in response units: the pixel sees ``log(1 + light / blank)``.
    tau_dark_us : float
        The pixel's time constant at the dark level, µs (>= ``sensor.tau_min_us``).
    rms_counts : float
        Root-mean-square residual of the steps' mean net counts, in counts (NaN when unknown).
    rms_time_us : float
        Root-mean-square residual of the rise's ON times the fit used, µs (NaN when none was fitted).
    statistics : LevelStatistics
        The level captures' numbers the model was fitted to.
    window_us : int
        Length of the windows the steps were counted in, µs (default 1000).
    settle_us : int
        Darkness before each step, µs (default 0).
    refractory_bound_us : float, optional
        Shortest ON-event spacing at the brightest step (:func:`refractory_bound`), µs: the refractory period is
        no longer. None when not measured.
    refractory_resolved : bool
        Whether the ON-event gaps measured the refractory period (:func:`fit_refractory`); else the model keeps
        1 µs (default False).
    delay_us : float
        Time from a trigger edge to the light's change at the pixels, µs (the DMD's latency, default 0): windows
        follow the light by this much.
    """

    sensor: SensorModel
    blank: float
    tau_dark_us: float
    rms_counts: float
    rms_time_us: float
    statistics: LevelStatistics
    window_us: int = 1000
    settle_us: int = 0
    #: shortest ON-event spacing at the brightest step (:func:`refractory_bound`): the refractory period is no longer
    refractory_bound_us: float | None = None
    #: whether the ON-event gaps measured the refractory period (:func:`fit_refractory`); else the model keeps 1 µs
    refractory_resolved: bool = False
    #: time from a trigger edge to the light's change at the pixels (µs; the DMD's latency), fitted from the rise's
    #: first and half-way ON times (:func:`fit_pixel_model`); windows follow the light by this much
    delay_us: float = 0.0

    @property
    def params(self) -> np.ndarray:
        """``(theta, blank, tau_min_us, tau_dark_us)``, as :func:`predict_levels` takes them."""
        return np.array([self.sensor.theta_on, self.blank, self.sensor.tau_min_us, self.tau_dark_us])

    @property
    def spread(self) -> float:
        """The thresholds' relative spread the model was fitted with."""
        return self.sensor.theta_mismatch / self.sensor.theta_on

    def mean_counts(self, light: npt.ArrayLike) -> np.ndarray:
        """The model's mean net count for a step of each light in its windows.

        Parameters
        ----------
        light : array_like
            Steps of light (response units above the dark level).

        Returns
        -------
        ndarray
            The mean net count of each.
        """
        light = np.asarray(light, np.float64)
        return predict_levels(self.params, light, self.window_us, self.settle_us, 0, self.sensor.refractory_us,
                              self.spread)[0]

    def to_dict(self) -> dict:
        """The model as plain numbers (a calibration file's ``pixel_model``; :meth:`from_dict` reads it).

        Returns
        -------
        dict
            Thresholds, time constants, dark level, spread, refractory period, the light's delay, errors.
        """
        s = self.sensor
        return {"theta_on": s.theta_on, "theta_off": s.theta_off, "tau_min_us": s.tau_min_us,
                "tau_dark_us": self.tau_dark_us, "blank_units": self.blank,
                "threshold_spread": s.theta_mismatch / s.theta_on, "refractory_us": s.refractory_us,
                "rms_counts": _finite(self.rms_counts), "rms_time_us": _finite(self.rms_time_us),
                "levels": self.statistics.light.tolist(), "level_counts": self.statistics.counts.tolist(),
                "level_first_us": [None if not np.isfinite(v) else float(v) for v in self.statistics.first_us],
                "level_last_us": [None if not np.isfinite(v) else float(v) for v in self.statistics.last_us],
                "level_rise_order": None if self.statistics.rise_order is None
                else [int(v) for v in self.statistics.rise_order],
                "level_rise_us": None if self.statistics.rise_us is None
                else [None if not np.isfinite(v) else float(v) for v in self.statistics.rise_us],
                "pixels": int(self.statistics.pixels), "window_us": int(self.window_us),
                "refractory_bound_us": self.refractory_bound_us, "refractory_resolved": self.refractory_resolved,
                "settle_us": int(self.settle_us), "light_delay_us": float(self.delay_us)}

    @classmethod
    def from_dict(cls, d: dict) -> PixelFit:
        """The model :meth:`to_dict` wrote (a calibration file's ``pixel_model``); a bad one is an EvtkError.

        Parameters
        ----------
        d : dict
            :meth:`to_dict`'s form.

        Returns
        -------
        PixelFit
            The model (no level statistics).
        """
        try:
            theta, blank = float(d["theta_on"]), float(d["blank_units"])
            tau_min, tau_dark = float(d["tau_min_us"]), float(d["tau_dark_us"])
            spread = float(d.get("threshold_spread", 0.02))
            refractory = float(d.get("refractory_us", 1.0))
            delay = float(d.get("light_delay_us", 0.0))
            light = np.asarray(d.get("levels", []), np.float64)
            counts = np.asarray(d.get("level_counts", np.zeros(light.size)), np.float64)
            # a missing time: None in JSON, -1 in TOML
            first = np.asarray([np.nan if v is None or v < 0 else v
                                for v in d.get("level_first_us", [None] * light.size)], np.float64)
            last = np.asarray([np.nan if v is None or v < 0 else v
                               for v in d.get("level_last_us", [None] * light.size)], np.float64)
            rise_order = d.get("level_rise_order")
            rise_order = None if rise_order is None else np.asarray(rise_order, np.int64)
            rise = d.get("level_rise_us")
            rise = None if rise is None else np.asarray([np.nan if v is None or v < 0 else v for v in rise], np.float64)
        except (KeyError, TypeError, ValueError) as exc:
            raise EvtkError(f"a pixel model needs theta_on, blank_units, tau_min_us and tau_dark_us "
                            f"({type(exc).__name__}: {exc})") from None
        vals = (theta, blank, tau_min, tau_dark, spread, refractory)
        if not all(np.isfinite(v) and v >= 0 for v in vals) or min(theta, blank, tau_min, tau_dark) <= 0 \
                or tau_dark < tau_min:
            raise EvtkError(f"a pixel model's values must be finite and positive, tau_dark_us >= tau_min_us: {d!r}")
        if not (np.isfinite(delay) and abs(delay) < MAX_DELAY_US):
            raise EvtkError(f"a pixel model's light_delay_us must be finite and within +-{MAX_DELAY_US:g} us, "
                            f"not {delay!r}")
        sensor = _model((theta, blank, tau_min, tau_dark), max(refractory, 1.0), 0.0).replace(
            theta_mismatch=spread * theta, theta_off=float(d.get("theta_off", theta)))
        stats = LevelStatistics(light, counts, first, last, int(d.get("pixels", 0)), rise_order=rise_order,
                                rise_us=rise)
        rms_c, rms_t = d.get("rms_counts"), d.get("rms_time_us")
        return cls(sensor, blank, tau_dark, np.nan if rms_c is None else float(rms_c),
                   np.nan if rms_t is None else float(rms_t), stats, int(d.get("window_us", 1000)),
                   int(d.get("settle_us", 0)), d.get("refractory_bound_us"), bool(d.get("refractory_resolved", False)),
                   delay)


def _finite(v):
    return float(v) if np.isfinite(v) else None


def interior_pixels(region: Sequence[int], origin_px: Sequence[float], step_px: float, kernel_shape: Sequence[int],
                    features_shape: Sequence[int], margin: int = 1, cell_map: CellMap | None = None) -> np.ndarray:
    """Pixels of ``region`` (y, x) whose cell lies ``margin`` cells inside the flat response's interior.

    Cell ``(i, j)`` is centred on ``origin + (j, i) * step_px`` (the
    convention of :func:`~evtk.reconstruct.to_response_grid`), or wherever
    ``cell_map`` (:class:`evtk.optics.camera.CellMap`) puts it; the interior
    is where a flat features field overlaps every kernel element, cells
    ``kernel - 1`` to ``features - 1`` along each axis.

    Parameters
    ----------
    region : sequence of int
        ``(x0, x1, y0, y1)``: the sensor pixels (half-open).
    origin_px : sequence of float
        ``(x, y)``: the sensor pixel that sees cell (0, 0) (unused with ``cell_map``).
    step_px : float
        Sensor pixels per cell, > 0 (unused with ``cell_map``).
    kernel_shape, features_shape : sequence of int
        ``(rows, cols)`` of the kernel and of the features, in elements.
    margin : int
        Cells kept clear of the interior's edge on every side.
    cell_map : CellMap, optional
        A general map from cells to pixels; each pixel's cell is the nearest to where the inverse map puts it.

    Returns
    -------
    numpy.ndarray
        bool, shape (y1 - y0, x1 - x0): True on the interior pixels.

    Raises
    ------
    EvtkError
        When ``step_px`` is not positive (without ``cell_map``).
    """
    x0, x1, y0, y1 = (int(v) for v in region)
    kh, kw = (int(v) for v in kernel_shape)
    fh, fw = (int(v) for v in features_shape)
    if cell_map is not None:  # a general map (rotation, tilt, distortion): each pixel's cell through its inverse
        yy, xx = np.mgrid[y0:y1, x0:x1]
        cells = np.rint(cell_map.to_cells(np.stack([xx.ravel(), yy.ravel()], 1).astype(np.float64)))
        col, row = cells[:, 0].reshape(xx.shape), cells[:, 1].reshape(xx.shape)
        return ((col >= kw - 1 + margin) & (col <= fw - 1 - margin) & (row >= kh - 1 + margin)
                & (row <= fh - 1 - margin))
    step = float(step_px)
    if not step > 0:
        raise EvtkError(f"step_px must be positive, not {step_px!r}")
    col = np.rint((np.arange(x0, x1) - float(origin_px[0])) / step)
    row = np.rint((np.arange(y0, y1) - float(origin_px[1])) / step)
    in_x = (col >= kw - 1 + margin) & (col <= fw - 1 - margin)
    in_y = (row >= kh - 1 + margin) & (row <= fh - 1 - margin)
    return in_y[:, None] & in_x[None, :]


def level_statistics(counts: WindowCounts, is_level: npt.ArrayLike, level: npt.ArrayLike, interior: npt.ArrayLike,
                     gain: np.ndarray | None = None) -> LevelStatistics:
    """The numbers :func:`fit_pixel_model` fits, from accumulated counts (with ``times=True``).

    ``is_level`` selects the level windows of ``counts``, ``level`` holds
    their kernel element counts, ``interior`` the pixels whose light the step
    sets (:func:`interior_pixels`), ``gain`` each
    pixel's flat-field count gain (applied to the counts only).

    Parameters
    ----------
    counts : WindowCounts
        Every window's counts over the region, with event times (:func:`~evtk.reconstruct.accumulate` with
        ``times=True``).
    is_level : array_like of bool
        Which windows are level captures, shape (windows,).
    level : array_like of int
        Kernel elements on in each window's level pattern, shape (windows,) (read where ``is_level``).
    interior : array_like of bool
        The pixels the steps light alike, shape (y1 - y0, x1 - x0) (:func:`interior_pixels`).
    gain : numpy.ndarray, optional
        Each pixel's flat-field count gain, shape (y1 - y0, x1 - x0) (multiplies the net counts, not the times).

    Returns
    -------
    LevelStatistics
        ``light``, ``counts``, ``first_us``, ``last_us`` and ``pixels`` of each distinct level, in increasing
        light (the OFF and rise numbers left None: :func:`level_off_times`, :func:`level_rise_times`).

    Raises
    ------
    EvtkError
        Counts without event times, no level capture, or no interior pixel.
    """
    first_us, last_us = counts.on_first_us, counts.on_last_us
    if first_us is None or last_us is None:
        raise EvtkError("fitting the pixel model needs event times (accumulate with times=True)")
    sel = np.flatnonzero(np.asarray(is_level, bool))
    lv = np.asarray(level)[sel]
    mask = np.asarray(interior, bool)
    if sel.size == 0:
        raise EvtkError("the recording has no level captures to fit a pixel model to (a job with levels = N)")
    if not mask.any():
        raise EvtkError("no pixel lies inside the flat response's interior: the region or origin misses the response")
    net = counts.on[sel].astype(np.float64) - counts.off[sel]
    if gain is not None:
        net = net * gain
    steps = np.unique(lv)
    n, first, last = [], [], []
    for m in steps:
        w = lv == m
        n.append(net[w][:, mask].mean())
        f = first_us[sel][w][:, mask]
        la = last_us[sel][w][:, mask]
        fired = f >= 0
        first.append(float(np.median(f[fired])) if fired.any() else np.nan)
        last.append(float(np.median(la[fired])) if fired.any() else np.nan)
    return LevelStatistics(steps.astype(np.float64), np.array(n), np.array(first), np.array(last), int(mask.sum()))


#: Longest stretch before the first trigger edge (µs) :func:`hot_pixels` reads.
HOT_LEAD_US = 200_000

#: Fewest events in the dark for a pixel to count as hot (:func:`hot_pixels`).
HOT_MIN_EVENTS = 5


def hot_pixels(rec: Any, t_on_us: npt.ArrayLike, t_off_us: npt.ArrayLike, max_gaps: int = 64) -> np.ndarray:
    """Pixels that fire in the dark far more than the rest: a bool mask (height, width) over the sensor.

    The dark is the time before the first trigger edge (at most :data:`HOT_LEAD_US`) and the last quarter of
    the gaps between windows ``[t_on_us, t_off_us)`` but their last sixteenth (at most ``max_gaps`` of them),
    where the pixels lit before have settled and a light a little ahead of its edge has not come. A pixel is
    hot when it fires there at least :data:`HOT_MIN_EVENTS` times, more than four times the 90th percentile of
    its 11x11 neighbourhood's counts plus six of its Poisson deviations (a response's pixels, noisier in the
    dark than the bare sensor, are judged against each other), and in a third of the dark stretches or more
    (a pixel still decaying from a bright window fires in a few, not steadily). A hot pixel
    inside the response would be a dot of its own and a pixel of its own model.

    Parameters
    ----------
    rec : Recording
        The open recording (its events in the dark stretches are read).
    t_on_us, t_off_us : array_like of int
        The trigger windows (any order), µs.
    max_gaps : int
        Most gaps between windows read (the first ones in time).

    Returns
    -------
    numpy.ndarray
        bool, shape (height, width) of the sensor: True on the hot pixels.
    """
    w, h = (int(v) for v in rec.sensor_size)
    order = np.argsort(np.asarray(t_on_us, np.int64))
    on, off = np.asarray(t_on_us, np.int64)[order], np.asarray(t_off_us, np.int64)[order]
    stretches = []
    gaps = (on[1:] - off[:-1]).tolist()
    margin = int(max(gaps) // 16) if gaps else 0  # a light a little before its trigger edge is not darkness
    if on.size:
        stretches.append((int(on[0]) - HOT_LEAD_US, int(on[0]) - margin - 1))
    for a, b in list(zip(off[:-1].tolist(), on[1:].tolist()))[:int(max_gaps)]:
        if b - a >= 16:
            stretches.append((b - (b - a) // 4, b - (b - a) // 16))
    counts = np.zeros(w * h, np.int64)
    seen = np.zeros(w * h, np.int64)
    for a, b in stretches:
        ev = rec.events(a, b)
        if ev.t.size == 0:
            continue
        n = np.bincount(ev.y.astype(np.int64) * w + ev.x.astype(np.int64), minlength=w * h)
        counts += n
        seen += n > 0
    dark = counts.reshape(h, w)
    # against its own neighbourhood: a response's pixels fire in the dark more than the bare sensor around it,
    # and at the response's edge half the neighbours are outside: the busiest tenth of 11x11 is the reference
    from scipy.ndimage import percentile_filter  # (scipy where a step uses it: not on import)

    local = percentile_filter(dark.astype(np.float64), 90, size=11, mode="nearest")
    limit = np.maximum(HOT_MIN_EVENTS, 4.0 * local + 6.0 * np.sqrt(local + 1.0))
    return (dark >= limit) & (3 * seen.reshape(h, w) >= max(1, len(stretches)))


def describe_pixels(mask: np.ndarray, most: int = 8) -> str:
    """Where a sensor mask's pixels are, for a message.

    Parameters
    ----------
    mask : ndarray of bool, shape (height, width)
        The pixels to name.
    most : int
        How many to name.

    Returns
    -------
    str
        ``"N pixels at (x, y), ..."``, the first ``most`` of them in row order.
    """
    ys, xs = np.nonzero(np.asarray(mask, bool))
    where = ", ".join(f"({x}, {y})" for x, y in zip(xs[:most].tolist(), ys[:most].tolist()))
    return f"{xs.size} pixel{'s' if xs.size != 1 else ''} at {where}{' ...' if xs.size > most else ''}"


def _interior_events(rec, t0_us, t1_us, polarity, region, interior):
    """Times and region-flat pixel indices of the ``polarity`` events in ``[t0_us, t1_us)`` on ``interior`` pixels."""
    x0, x1, y0, y1 = (int(v) for v in region)
    ev = rec.events(int(t0_us), int(t1_us))
    sel = (ev.p == polarity) & (ev.x >= x0) & (ev.x < x1) & (ev.y >= y0) & (ev.y < y1)
    xs, ys = ev.x[sel].astype(np.int64) - x0, ev.y[sel].astype(np.int64) - y0
    use = np.asarray(interior, bool)[ys, xs]
    return ev.t[sel][use], (ys * (x1 - x0) + xs)[use]


def _by_pixel(t, pix):
    """Event times and pixels sorted by pixel, then time."""
    order = np.lexsort((t, pix))
    return t[order], pix[order]


def _successive_gaps(t, pix):
    """The gaps between each pixel's successive events (``t``, ``pix`` sorted by :func:`_by_pixel`), and the
    pixel of each."""
    same = pix[1:] == pix[:-1]
    return np.diff(t)[same], pix[1:][same]


def _on_events_by_pixel(rec, t0_us, t1_us, region, interior):
    """:func:`_interior_events`' ON events, sorted by pixel and then time."""
    return _by_pixel(*_interior_events(rec, t0_us, t1_us, 1, region, interior))


def level_off_times(rec: Any, t_off_us: npt.ArrayLike, level: npt.ArrayLike, settle_us: int, region: Sequence[int],
                    interior: npt.ArrayLike, stamp_period_us: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Mean time (µs after the falling edge) of the interior pixels' OFF events while each level step decays, and
    their mean number a pixel and step: ``(off_mean_us, off_counts)``.

    The decay runs at the dark level's time constant, which the level
    windows themselves (all bright) hardly show. Events stamped at the end of
    a readout frame are moved back half a frame (their mean delay).

    Parameters
    ----------
    rec : Recording
        The open recording.
    t_off_us : array_like of int
        The falling edge of each level window, µs.
    level : array_like of int
        Each of those windows' level (kernel elements on), same length.
    settle_us : int
        How long after each falling edge the decay's events are read, µs (the darkness between patterns).
    region : sequence of int
        ``(x0, x1, y0, y1)``: the sensor pixels ``interior`` covers.
    interior : array_like of bool
        The pixels read, shape (y1 - y0, x1 - x0) (:func:`interior_pixels`).
    stamp_period_us : float, optional
        Spacing of the recording's time stamps, µs (above 1: a frame readout; events move back half of it).

    Returns
    -------
    off_mean_us : numpy.ndarray
        float64, one per distinct level in increasing order: the OFF events' mean time after the falling edge,
        µs; NaN where there were none.
    off_counts : numpy.ndarray
        float64, same shape: their mean number per interior pixel and window.
    """
    n_pixels = int(np.asarray(interior, bool).sum())
    lv = np.asarray(level)
    steps = np.unique(lv)
    shift = 0.5 * float(stamp_period_us) if stamp_period_us and stamp_period_us > 1 else 0.0
    out, counts = [], []
    for m in steps:
        times = []
        for t in np.asarray(t_off_us)[lv == m].tolist():
            t_ev, _ = _interior_events(rec, t, t + int(settle_us), 0, region, interior)
            times.append(t_ev.astype(np.float64) - t - shift)
        allt = np.concatenate(times) if times else np.zeros(0)
        out.append(float(allt.mean()) if allt.size else np.nan)
        counts.append(allt.size / max(1, len(times) * n_pixels))
    return np.array(out), np.array(counts)


def rise_orders(counts: npt.ArrayLike) -> np.ndarray:
    """Which ON event of each level step :func:`level_rise_times` times: half the step's mean count, at least the
    first. Half-way up the rise the time is tens of time constants' percent, far above a time stamp's tick.

    Parameters
    ----------
    counts : array_like
        Each level step's mean net count.

    Returns
    -------
    ndarray of int64
        The ON event's number (1 = the first) for each step.
    """
    c = np.nan_to_num(np.asarray(counts, np.float64), nan=0.0)
    return np.maximum(1, np.rint(0.5 * c)).astype(np.int64)


def level_rise_times(rec: Any, t_on_us: npt.ArrayLike, t_off_us: npt.ArrayLike, level: npt.ArrayLike,
                     orders: Sequence[int] | np.ndarray, region: Sequence[int], interior: npt.ArrayLike) -> np.ndarray:
    """Median time (µs from the window start ``t_on_us``) of each interior pixel's ``orders[s]``-th ON event in the
    windows of level step ``s`` (the steps sorted as :func:`level_statistics` sorts them); NaN where no pixel fired
    that often.

    Parameters
    ----------
    rec : Recording
        The open recording.
    t_on_us, t_off_us : array_like of int
        The level windows ``[t_on_us, t_off_us)``, µs.
    level : array_like of int
        Each window's level (kernel elements on), same length.
    orders : sequence of int
        Which ON event (1 = the first) to time for each distinct level, in increasing level (:func:`rise_orders`).
    region : sequence of int
        ``(x0, x1, y0, y1)``: the sensor pixels ``interior`` covers.
    interior : array_like of bool
        The pixels read, shape (y1 - y0, x1 - x0) (:func:`interior_pixels`).

    Returns
    -------
    numpy.ndarray
        float64, one per distinct level: the median time, µs from the window's start; NaN where no pixel fired
        that often.
    """
    lv = np.asarray(level)
    steps = np.unique(lv)
    out = np.full(steps.size, np.nan)
    for s, m in enumerate(steps):
        k = int(orders[s])
        times = []
        for a, b in zip(np.asarray(t_on_us)[lv == m].tolist(), np.asarray(t_off_us)[lv == m].tolist()):
            t, pix = _on_events_by_pixel(rec, a, b, region, interior)
            start = np.r_[0, np.flatnonzero(np.diff(pix)) + 1]
            n = np.diff(np.r_[start, pix.size])
            ok = n >= k
            times.append(t[start[ok] + k - 1].astype(np.float64) - a)
        allt = np.concatenate(times) if times else np.zeros(0)
        if allt.size:
            out[s] = float(np.median(allt))
    return out


def on_gaps(rec: Any, t_on_us: npt.ArrayLike, t_off_us: npt.ArrayLike, region: Sequence[int],
            interior: npt.ArrayLike) -> np.ndarray:
    """The gaps (µs) between each interior pixel's successive ON events inside the windows ``[t_on_us,
    t_off_us)``, pooled over pixels and windows.

    Parameters
    ----------
    rec : Recording
        The open recording.
    t_on_us, t_off_us : array_like of int
        The windows (a bright level step's), µs.
    region : sequence of int
        ``(x0, x1, y0, y1)``, half-open: where ``interior`` lies on the sensor.
    interior : array_like of bool
        Mask of the pixels whose gaps are pooled, shape (y1 - y0, x1 - x0) (:func:`interior_pixels`).

    Returns
    -------
    numpy.ndarray
        float64, 1-D: every gap, µs (empty without windows).
    """
    gaps = []
    for a, b in zip(np.asarray(t_on_us).tolist(), np.asarray(t_off_us).tolist()):
        gaps.append(_successive_gaps(*_on_events_by_pixel(rec, a, b, region, interior))[0])
    return np.concatenate(gaps).astype(np.float64) if gaps else np.zeros(0)


def refractory_bound(gaps: npt.ArrayLike, quantile: float = 0.01) -> float | None:
    """An upper bound of the refractory period: a low quantile of the ON-event gaps of a bright step.

    A pixel cannot fire again sooner.

    Parameters
    ----------
    gaps : array_like
        The gaps (µs, :func:`on_gaps`).
    quantile : float
        Which quantile.

    Returns
    -------
    float or None
        The bound (µs); None with fewer than 20 gaps.
    """
    g = np.asarray(gaps, np.float64)
    return float(np.quantile(g, quantile)) if g.size >= 20 else None


#: Quantiles of the brightest step's ON-event gaps :func:`fit_refractory` matches.
GAP_QUANTILES = (0.05, 0.1, 0.25)

#: How many times the gaps' own spread (their 25 % quantile less their 5 %) the 5 % quantile must stand above the
#: model's at the least period before :func:`fit_refractory` reads a period from them. Measured on the brightest
#: step: evtk's pixel with a 10 µs period 3.8 times, with 5 µs 1.6 times (read as 3.5 µs), with 3 µs under 1; a
#: v2e-like pixel (a 250 µs bandwidth floor, the light rising over 8 µs) with a 1 µs period 1.3 times, which the
#: old test (the predicted gaps moved by over 1 µs) read as a 3.5 µs period.
REFRACTORY_SIGNIFICANCE = 1.5


def _grouped_quantiles(n0, pmf, qs):
    """Quantiles ``qs`` of a whole-µs distribution (``pmf`` over ``n0, n0 + 1, ...``), spread evenly over the
    µs below each value: continuous in the probabilities, so a model's can be matched to a camera's."""
    cdf = np.cumsum(pmf) / max(float(np.sum(pmf)), 1e-300)
    j = np.minimum(np.searchsorted(cdf, np.asarray(qs, np.float64)), cdf.size - 1)
    below = np.where(j > 0, cdf[np.maximum(j - 1, 0)], 0.0)
    return n0 + j - 1 + (np.asarray(qs) - below) / np.maximum(cdf[j] - below, 1e-12)


def gap_quantiles(gaps, qs=GAP_QUANTILES):
    """Quantiles ``qs`` of whole-µs ON-event gaps (:func:`on_gaps`), spread over the µs below each value
    (:func:`_grouped_quantiles`); NaN for fewer than 20 gaps."""
    g = np.rint(np.asarray(gaps, np.float64)).astype(np.int64)
    if g.size < 20:
        return np.full(len(qs), np.nan)
    return _grouped_quantiles(int(g.min()), np.bincount(g - g.min()).astype(np.float64), qs)


def _stamped_gap_quantiles(gap_us, weight, qs):
    """:func:`gap_quantiles` of noise-free gaps ``gap_us`` (weighted) as a camera stamps them: a gap ``g``
    between two events stamped in whole µs rounded down reads ``floor(g) + 1`` with probability ``g - floor(g)``
    (the first event's fraction of a µs being even), else ``floor(g)``."""
    lo = np.floor(gap_us)
    frac = gap_us - lo
    n0 = int(lo.min())
    k = (lo - n0).astype(np.int64)
    pmf = np.bincount(k, weights=weight * (1 - frac), minlength=k.max() + 2) \
        + np.bincount(k + 1, weights=weight * frac, minlength=k.max() + 2)
    return _grouped_quantiles(n0, pmf, qs)


def fit_refractory(fit: PixelFit, light: float, gaps: npt.ArrayLike, skip_us: float = 0,
                   max_us: float | None = None) -> tuple[float, bool]:
    """The refractory period that makes the fitted pixel model's ON-event gaps on a step of ``light`` match the
    observed ``gaps`` (:func:`on_gaps`) at :data:`GAP_QUANTILES`: ``(refractory_us, resolved)``.

    After an event a pixel is blind for the refractory period, then needs
    the next threshold's worth of rise: a gap is the period plus a crossing
    time. The model is searched on a grid of 0.5 µs from its least, 1 µs, to
    ``max_us`` (default twice the smallest gap). ``resolved`` is False when
    the fitted period moves the predicted gaps by less than a time stamp's
    1 µs from the least period's (the crossings themselves are slower: the
    gaps bound the period from above only), when the gaps' lowest quantile
    stands above the least period's prediction by no more than
    :data:`REFRACTORY_SIGNIFICANCE` times the gaps' own spread (a pixel
    slower to its first crossings than the model, not a period), or the
    model gives no gaps at all (a fit that failed, e.g. on counts a long period flattened, which
    the calibrated route then catches on the level captures); the model then
    keeps its period.

    Parameters
    ----------
    fit : PixelFit
        The fitted pixel model (its refractory period is the one kept when the gaps do not resolve one).
    light : float
        The step's light, response units (the brightest level's).
    gaps : array_like
        The observed ON-event gaps on that step, µs (:func:`on_gaps`); fewer than 20 resolve nothing.
    skip_us : float
        Microseconds left out at the start of each window, as the gaps were read.
    max_us : float, optional
        Longest period searched, µs; default twice the gaps' 1 % quantile.

    Returns
    -------
    refractory_us : float
        The refractory period, µs (the model's own when not resolved).
    resolved : bool
        Whether the gaps measured it.
    """
    g = np.asarray(gaps, np.float64)
    if g.size < 20:
        return fit.sensor.refractory_us, False
    qs = np.asarray(GAP_QUANTILES)
    observed = gap_quantiles(g, qs)
    hi = float(max_us) if max_us is not None else 2.0 * float(np.quantile(g, 0.01))
    grid = np.arange(1.0, max(hi, 1.0) + 0.25, 0.5)
    predicted = np.array([_predicted_gaps(fit.params, float(light), fit.window_us, fit.settle_us, skip_us, r,
                                          fit.spread, qs) for r in grid])
    if not np.isfinite(predicted).any(axis=1).all():
        return fit.sensor.refractory_us, False
    # significant only when the gaps' floor stands above the least period's prediction by more than the gaps' own
    # spread can explain: slower first crossings than the model's (a light that rises over microseconds, a
    # bandwidth with a hard floor) lengthen every gap a little, which a period must not be read from
    excess = observed[0] - predicted[0][0]
    if not excess > REFRACTORY_SIGNIFICANCE * (observed[-1] - observed[0]):
        return fit.sensor.refractory_us, False
    i = int(np.argmin(np.nansum((predicted - observed) ** 2, axis=1)))
    if not np.nanmax(np.abs(predicted[i] - predicted[0])) > 1.0:
        return fit.sensor.refractory_us, False
    return float(grid[i]), True


def _predicted_gaps(params, light, window_us, settle_us, skip_us, refractory_us, spread, qs):
    """Quantiles ``qs`` of the noise-free model's ON-event gaps on one step of ``light``, over its thresholds'
    spread (each pixel's gaps weighted by its share)."""
    t, idx, p, _, _, weight = _simulate_steps(params, np.array([light]), window_us, settle_us, refractory_us, spread)
    z, w = float(settle_us), float(window_us)
    keep = (t >= z + float(skip_us)) & (t < z + w) & (p == 1)
    gap, who = _successive_gaps(*_by_pixel(t[keep], idx[keep]))
    if gap.size == 0:
        return np.full(len(qs), np.nan)
    return _stamped_gap_quantiles(gap, weight[who % weight.size], qs)


def _model(params, refractory_us, mismatch):
    theta, blank, tau_min, tau_dark = params
    tau_e = max(tau_dark - tau_min, 1e-6) * 1e-6 * NOMINAL_BLANK_E_PER_S  # tau = tau_min + tau_e / rate (s)
    return SensorModel(theta_on=theta, theta_off=theta, theta_mismatch=mismatch, refractory_us=refractory_us,
                       tau_min_us=tau_min, tau_electrons=tau_e, dark_current_e_per_s=NOMINAL_BLANK_E_PER_S,
                       shot_noise=False, background_rate_hz=0.0)


def predict_levels(params: npt.ArrayLike, light: np.ndarray, window_us: float, settle_us: float, skip_us: float,
                   refractory_us: float, spread: float, orders: npt.ArrayLike | None = None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """What the noise-free pixel model ``params`` (theta, blank, tau_min_us, tau_dark_us) gives on the level
    steps ``light``, over thresholds spread by ``spread``: mean net count, median first and last ON times, mean
    time and number of the OFF events of the decay, and the median time of the ``orders``-th ON event (NaN without
    ``orders``): what :func:`level_statistics`, :func:`level_off_times` and :func:`level_rise_times` measure.

    Each step is simulated as darkness for ``settle_us``, the light for ``window_us`` and darkness again, from a
    pixel settled at the dark level, over :data:`SPREAD_POINTS` thresholds (a Gaussian weighting out to two
    standard deviations).

    Parameters
    ----------
    params : array_like
        ``(theta, blank, tau_min_us, tau_dark_us)``: the contrast threshold (log-intensity units), the dark
        level's light (response units), the time constants in bright light and at the dark level (µs), as
        :attr:`PixelFit.params` holds them.
    light : numpy.ndarray
        float64, 1-D: each step's light, response units above the dark level.
    window_us : float
        How long each step is lit, µs.
    settle_us : float
        Darkness before and after each step, µs.
    skip_us : float
        Microseconds left out at the start of the window for the ON times (the counts take the whole window).
    refractory_us : float
        The pixel's refractory period, µs.
    spread : float
        The thresholds' relative standard deviation (0: one threshold).
    orders : array_like of int, optional
        Which ON event (1 = the first) each step's rise time is of; None leaves the rise times NaN.

    Returns
    -------
    counts : numpy.ndarray
        Mean net count ON - OFF of each step.
    first_us, last_us : numpy.ndarray
        Median time of the first and last ON event, µs after the window's start plus ``skip_us``; NaN where
        none fired.
    off_mean_us : numpy.ndarray
        Mean time of the decay's OFF events, µs after the step ends; NaN where none.
    off_counts : numpy.ndarray
        Mean number of those OFF events.
    rise_us : numpy.ndarray
        Median time of the ``orders``-th ON event, µs after the window's start plus ``skip_us``; NaN without
        ``orders`` or where none fired that often.
    """
    t, idx, p, on, off, weight = _simulate_steps(params, light, window_us, settle_us, refractory_us, spread)
    rel_size = weight.size
    z, w = float(settle_us), float(window_us)
    a = z + float(skip_us)
    u_size = light.size * rel_size
    # the slot counts the whole lit segment; the reconstruction's window starts skip_us in
    decay = (t >= z + w) & (p == 0)
    off_count = np.bincount(idx[decay], minlength=u_size).reshape(light.size, rel_size) @ weight
    off_time = np.bincount(idx[decay], weights=t[decay] - (z + w), minlength=u_size).reshape(light.size, rel_size)
    off_mean = np.where(off_count > 0, (off_time @ weight) / np.maximum(off_count, 1e-12), np.nan)
    keep = (t >= a) & (t < z + w) & (p == 1)
    first = np.full(u_size, np.nan)
    last = np.full(u_size, np.nan)
    rise = np.full(u_size, np.nan)
    if keep.any():
        ti, ii = _by_pixel(t[keep] - a, idx[keep])
        starts_i = np.r_[0, np.flatnonzero(np.diff(ii)) + 1]
        ends_i = np.r_[starts_i[1:] - 1, ii.size - 1]
        first[ii[starts_i]] = ti[starts_i]
        last[ii[ends_i]] = ti[ends_i]
        if orders is not None:  # each pixel's k-th ON event, k its step's order
            k = np.asarray(orders, np.int64)[ii[starts_i] // rel_size]
            ok = ends_i - starts_i + 1 >= k
            rise[ii[starts_i][ok]] = ti[(starts_i + k - 1)[ok]]
    net = (on[0] - off[0]).astype(np.float64).reshape(light.size, rel_size)
    counts = net @ weight
    f = first.reshape(light.size, rel_size)
    la = last.reshape(light.size, rel_size)
    first_m, last_m = _row_median(f), _row_median(la)
    return counts, first_m, last_m, off_mean, off_count, _row_median(rise.reshape(light.size, rel_size))


def _simulate_steps(params, light, window_us, settle_us, refractory_us, spread):
    """The noise-free model's pixels through dark, a step of each ``light`` for ``window_us``, and dark again,
    over :data:`SPREAD_POINTS` thresholds spread by ``spread``: ``(t, idx, p, on, off, weight)`` (the events,
    each pixel's counts, the thresholds' weights; pixel ``i`` has light ``i // weight.size``)."""
    theta, blank = params[0], params[1]
    sm = _model(params, refractory_us, 0.0)
    rel = np.linspace(-2.0, 2.0, SPREAD_POINTS) * spread
    weight = np.exp(-0.5 * (rel / spread) ** 2) if spread > 0 else np.ones(1)
    rel = rel if spread > 0 else np.zeros(1)
    weight = weight / weight.sum()
    th = np.repeat(theta * (1 + rel)[None, :], light.size, axis=0).ravel()
    u = np.repeat(np.log1p(light / blank), rel.size)
    b0 = math.log(NOMINAL_BLANK_E_PER_S)
    z, w = float(settle_us), float(window_us)
    starts, ends = np.array([0.0, z, z + w]), np.array([z, z + w, 2 * z + w])
    lvl = np.stack([np.full(u.size, b0), b0 + u, np.full(u.size, b0)])
    slot = np.array([-1, 0, -1])
    st = PixelState(lvl[0], 0.0, np.maximum(th, 1e-6), np.maximum(th, 1e-6))
    t, idx, p, on, off = simulate_pixels(st, lvl, time_constant_us(np.exp(lvl), sm), np.zeros_like(lvl), starts,
                                         ends, sm, 0, emit=True, count_slot=slot, n_slots=1)
    return t, idx, p, on, off, weight


def _row_median(a):
    """Median of each row's finite values; NaN for a row with none (a light too dim for any event)."""
    s = np.sort(a, axis=1)  # NaN sorts last
    n = np.isfinite(a).sum(axis=1)
    rows = np.arange(a.shape[0])
    lo, hi = s[rows, np.maximum(n - 1, 0) // 2], s[rows, np.maximum(n, 1) // 2 - (n == 0)]
    return np.where(n > 0, 0.5 * (lo + hi), np.nan)


def _theta_for(counts, light, blank):
    """The threshold of ``counts = log(1 + light / blank) / theta`` at a given blank (least squares)."""
    v = np.log1p(light / blank)
    return float(np.sum(v * v) / max(np.sum(v * counts), 1e-12))


def _time_constants_guess(stats, theta, blank, start, times=True, offset_us=0.0):
    """``(tau_min_us, tau_dark_us)`` from closed forms: the first ON crossing of the brightest step,
    ``t1 = -tau ln(1 - theta / u)``, and the mean OFF crossing of the decays, ``tau * mean_k(-ln(1 - k theta / u))``,
    their times taken ``offset_us`` after the light's changes.
    """
    u = np.log1p(stats.light / blank)
    tau_min, tau_dark = start.tau_min_us, None
    if stats.off_mean_us is not None:
        est = []
        for uk, off in zip(u.tolist(), stats.off_mean_us.tolist()):
            k = np.arange(1, int(uk / theta) + 1)
            if k.size and np.isfinite(off) and off > offset_us:
                est.append((off - offset_us) / float(np.mean(-np.log1p(-np.minimum(k * theta / uk, 0.999)))))
        tau_dark = float(np.median(est)) if est else None
    bright = int(np.argmax(u))
    if times and np.isfinite(stats.first_us[bright]) and u[bright] > theta:
        tau_b = max(stats.first_us[bright] + 0.5 - offset_us, 0.5) / -np.log1p(-theta / u[bright])
        if tau_dark is not None:  # tau = tau_min + (tau_dark - tau_min) / (1 + light / blank)
            r = 1.0 / (1.0 + stats.light[bright] / blank)
            tau_min = (tau_b - r * tau_dark) / (1 - r)
        else:
            tau_min = tau_b
    tau_min = float(np.clip(tau_min, 1.0, 1e5)) if np.isfinite(tau_min) else start.tau_min_us
    if tau_dark is None or not np.isfinite(tau_dark):
        tau_dark = float(time_constant_us(NOMINAL_BLANK_E_PER_S, start.replace(
            dark_current_e_per_s=NOMINAL_BLANK_E_PER_S)))
    return tau_min, max(tau_dark, 1.5 * tau_min)


def fit_pixel_model(stats: LevelStatistics, window_us: int, settle_us: int, skip_us: float = 0,
                    refractory_us: float = 1.0, spread: float = 0.05, start: SensorModel | None = None,
                    times: bool = True, lead_us: float = 0.0, delay_us: float = 0.0) -> PixelFit:
    """Fit ``theta``, ``blank``, ``tau_min_us`` and ``tau_dark_us`` to the level statistics.

    Least squares over the steps of the counts (in counts), the rise's ON
    times (in µs) and the mean OFF times of the decays (in units of 20 µs).
    The rise is timed by the median first ON event (a few µs in, where a
    1 µs tick lets the time constant wander by 15 % along the
    threshold/time constant valley) and, when the statistics have it, by the
    median time of each pixel's ``stats.rise_order``-th ON event
    (:func:`level_rise_times`, about half its count: tens of µs, where a
    tick hardly matters), which then pins the time constant.
    A trust-region fit starts from three points along the threshold/dark-level
    valley (the counts' log fit, :func:`_fit_log_response`, and a blank level
    half and twice it) with closed-form time constants
    (:func:`_time_constants_guess`); Nelder-Mead polishes the best. ``spread``
    is the threshold mismatch (relative standard deviation, e.g. of the
    flat-field gains), which smooths the counts the same way the sensor's
    pixels do. With ``times`` False (time stamps too coarse, a frame
    readout) the ON times are left out and ``tau_min_us`` stays the
    ``start`` model's. The OFF threshold follows from the decays' OFF counts.
    The refractory period is ``refractory_us`` (:func:`fit_refractory` measures it).

    With the rise timed both by the first and the half-way ON events, a
    delay of the light after the windows' edges is fitted too: it shifts
    every time alike, and the first events (a few µs into the rise) say how
    much, the half-way ones the time constant. The statistics' windows start
    ``lead_us`` before the trigger edges; the light is taken to follow the
    edges by ``delay_us`` where the delay is not fitted, and the fit starts
    from it where it is. The returned ``delay_us`` is the light's after the
    edges.

    Parameters
    ----------
    stats : LevelStatistics
        The level captures' numbers (:func:`level_statistics`, with :func:`level_off_times` and
        :func:`level_rise_times` where measured); at least two steps.
    window_us : int
        Length of the level windows, µs.
    settle_us : int
        Darkness before each level window, µs.
    skip_us : float
        Microseconds left out at the start of each window, as the statistics were taken.
    refractory_us : float
        The refractory period the model keeps, µs.
    spread : float
        The thresholds' relative standard deviation (e.g. of the flat-field gains).
    start : SensorModel, optional
        The model the fit starts from (and keeps ``tau_min_us`` and shot noise of); default
        :class:`~evtk.sensor.SensorModel`'s.
    times : bool
        Fit the ON times too (False for coarse time stamps or a frame readout).
    lead_us : float
        How long before the trigger edges the statistics' windows start, µs.
    delay_us : float
        The light's delay after the trigger edges where it is not fitted (the fit's start where it is), µs.

    Returns
    -------
    PixelFit
        The model, its residuals, the statistics, ``window_us``, ``settle_us`` and the light's delay after the
        edges.

    Raises
    ------
    EvtkError
        With fewer than two level steps, or less than one event a pixel on every step.
    """
    light, counts = stats.light, stats.counts
    if light.size < 2:
        raise EvtkError("fitting the pixel model needs at least two level steps (levels = 2 or more)")
    if not np.any(counts > 1):
        raise EvtkError("the level captures gave less than one event a pixel: too little light to fit a pixel model")
    start = start or SensorModel()
    b0, th0 = _fit_log_response(np.r_[0.0, np.maximum.accumulate(counts)], np.r_[0.0, light])
    if not np.isfinite(b0):
        b0, th0 = float(light.max()), start.theta_on
    delay_scale = 10.0  # us: the delay's unit in the fit's parameter vector
    offset = float(lead_us) + float(delay_us)  # the light's change after the statistics' window starts
    x0 = np.r_[np.log([th0, b0] + list(_time_constants_guess(stats, th0, b0, start, times, offset))),
               offset / delay_scale]
    off_scale = 20.0  # us: the OFF events' mean time, over thousands of us
    has_off = np.isfinite(stats.off_mean_us) if stats.off_mean_us is not None else np.zeros(light.size, bool)
    # the rise is timed by the first ON event (a few us: a tick is a quarter of it) and, where measured, half-way
    # up (tens of us, far above a tick); the last ON event jumps with every whole count, so it is left out
    orders = stats.rise_order if stats.rise_us is not None and stats.rise_order is not None \
        and bool(np.isfinite(stats.rise_us).any()) else None
    # time stamps are whole us rounded down (as the timing linearisation takes them): half a tick on average
    first_t = stats.first_us + 0.5
    rise_t = stats.rise_us + 0.5 if orders is not None and stats.rise_us is not None else None
    has_first = np.isfinite(first_t) & bool(times)
    has_rise = np.isfinite(rise_t) & bool(times) if rise_t is not None else np.zeros(light.size, bool)
    # a light that follows the trigger edges late shifts every time alike: the first ON events (a few us into the
    # rise) then say how late, the half-way ones (tens of us) the time constant
    fit_delay = bool(has_rise.any() and has_first.any())
    # theta and blank from the counts; tau_min from the rise's ON times, tau_dark from them and the OFF decay
    free = np.array([True, True, bool(times), bool(times) or bool(has_off.any()), fit_delay])
    # us a unit residual: the first ON time's tick; the rise's median, over pixels whose thresholds spread it by
    # several us, is known to about as many us as the counts to a count tenth (1 or 10 us let one of them pull)
    first_scale, rise_scale = 1.0, RISE_SCALE_US
    use_first = has_first & (fit_delay or orders is None)

    def params(x):
        full = x0.copy()
        full[free] = x
        p = np.exp(full[:4])
        if p[3] <= p[2]:  # tau_dark below tau_min: outside the model, penalised smoothly
            p[3] = p[2] * 1.001
        return p, float(np.clip(full[4] * delay_scale, -MAX_DELAY_US, MAX_DELAY_US))

    def residuals(x):
        p, delay = params(x)
        n, f, _, off, _, rise = predict_levels(p, light, window_us, settle_us, skip_us, refractory_us, spread,
                                               orders)
        parts = [n - counts]
        if has_off.any():  # the decay after each step: the dark level's time constant
            parts.append(np.where(np.isfinite(off), off + delay - stats.off_mean_us, 5 * off_scale)[has_off]
                         / off_scale)
        if use_first.any():
            parts.append(np.where(np.isfinite(f), f + delay - first_t, 5 * first_scale)[use_first] / first_scale)
        if has_rise.any():
            parts.append(np.where(np.isfinite(rise), rise + delay - rise_t, 5 * rise_scale)[has_rise] / rise_scale)
        return np.concatenate(parts)

    def loss(x):
        return float(np.sum(residuals(x) ** 2))

    from scipy.optimize import least_squares, minimize

    # a trust region on finite differences coarser than the counts' steps, then Nelder-Mead to polish
    # from the log fit's blank level and from two either side of it: theta and blank trade off along a valley
    starts = []
    for db in (0.0, np.log(0.5), np.log(2.0)):
        xs = x0.copy()
        xs[1] += db
        xs[0] = np.log(_theta_for(counts, light, np.exp(xs[1])))
        starts.append(xs)
    tries = [least_squares(residuals, xs[free], method="trf", diff_step=0.02, x_scale=0.3, max_nfev=150)
             for xs in starts]
    best = min(tries, key=lambda r: r.cost).x
    res = minimize(loss, best, method="Nelder-Mead", options={"xatol": 1e-4, "fatol": 1e-5, "maxiter": 400})
    if res.fun > loss(best):
        res.x = best
    p, delay = params(res.x)
    theta, blank, tau_min, tau_dark = (float(v) for v in p)
    n, f, _, _, off_n, rise = predict_levels(p, light, window_us, settle_us, skip_us, refractory_us, spread, orders)
    t, observed_t, ok = (f, first_t, has_first) if orders is None else (rise, rise_t, has_rise)
    ok = ok & np.isfinite(t)
    rms_t = float(np.sqrt(np.mean((t + delay - observed_t)[ok] ** 2))) if ok.any() else float("nan")
    sensor = _model((theta, blank, tau_min, tau_dark), refractory_us, 0.0).replace(
        theta_mismatch=float(spread) * theta, shot_noise=start.shot_noise)
    if stats.off_counts is not None:  # OFF counts scale as 1 / theta_off: the model's at theta_on, over the data's
        ok = np.isfinite(stats.off_counts) & (stats.off_counts > 0) & (off_n > 0)
        if ok.any():
            sensor = sensor.replace(theta_off=theta * float(np.sum(off_n[ok]) / np.sum(stats.off_counts[ok])))
    return PixelFit(sensor, blank, tau_dark, float(np.sqrt(np.mean((n - counts) ** 2))), rms_t, stats,
                    int(window_us), int(settle_us), delay_us=delay - float(lead_us))


def _fit_log_response(counts, light):
    """``(blank, theta)`` of ``counts = log(1 + light / blank) / theta`` by least squares over the curve's points.

    The blank level is searched on a logarithmic grid (theta is then linear);
    with a single step or a curve straighter than any log, ``(inf, nan)``.
    """
    c, x = counts[1:], light[1:]
    if c.size < 2:
        return np.inf, np.nan
    grid = np.geomspace(1e-4, 1e4, 801) * float(x.max())
    v = np.log1p(x[None, :] / grid[:, None])
    inv_theta = np.sum(v * c, axis=1) / np.sum(v * v, axis=1)
    sse = np.sum((c - inv_theta[:, None] * v) ** 2, axis=1)
    i = int(np.argmin(sse))
    if i == grid.size - 1:  # no curvature: the straight line is the fit
        return np.inf, np.nan
    return float(grid[i]), float(1.0 / inv_theta[i])
