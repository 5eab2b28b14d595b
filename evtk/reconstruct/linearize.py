"""Counts back to light: ``exp(n theta) - 1``, the inverse of a recording's own pixel model, and flat-field gains."""

from __future__ import annotations

import functools
import json
import threading
from collections import OrderedDict
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from .._lazyjit import njit, numba_ready
from .._parallel import run
from .._threads import workers
from ..errors import EvtkError
from ..optics import Bench, brightest_response, response_origin_px, screen_response
from ..optics.camera import footprint_light
from ..plan import Plan, SimulationRecord
from ..sensor import PixelState, SensorModel, log_noise_std, simulate_pixels, time_constant_us

if TYPE_CHECKING:
    import numpy.typing as npt

__all__ = ["linearize", "count_curve", "linearize_by_model", "flat_field_gain", "isotonic", "level_table_values", "level_curve"]


def linearize(on: npt.ArrayLike, off: npt.ArrayLike | None = None, theta_on: float | np.ndarray = 0.2,
              theta_off: float | np.ndarray | None = None) -> np.ndarray:
    """Relative intensity change over each window from its event counts.

    A pixel that fires ``on`` ON and ``off`` OFF events has seen its log
    intensity rise by about ``on * theta_on - off * theta_off``; the returned
    value is ``exp(that) - 1``: 0 for no change, 1 for a doubling. Over a
    dark-to-pattern window it is proportional to the pattern's light above
    the dark level. Counts are quantised to whole thresholds, so the result
    is too (a factor ``exp(theta)`` per count).

    Parameters
    ----------
    on : array_like
        ON counts (any shape; calibrated counts may be fractional).
    off : array_like, optional
        OFF counts, the shape of ``on`` (none when None).
    theta_on : float or ndarray
        The ON contrast threshold (log units), per pixel or one for all.
    theta_off : float or ndarray, optional
        The OFF threshold; default ``theta_on``.

    Returns
    -------
    ndarray
        ``exp(on * theta_on - off * theta_off) - 1``.

    Examples
    --------
    >>> linearize(np.array([0, 5]), theta_on=np.log(2) / 5).round(6).tolist()
    [0.0, 1.0]
    """
    theta_off = theta_on if theta_off is None else theta_off
    for name, v in (("theta_on", theta_on), ("theta_off", theta_off)):
        v = np.asarray(v, dtype=np.float64)
        if not np.all(np.isfinite(v)) or np.any(v <= 0):
            raise EvtkError(f"{name} must be positive and finite")
    table = _count_table(on, off, theta_on, theta_off)
    if table is not None:  # integer counts and one threshold each: look the few distinct values up
        return table
    on = np.asarray(on, dtype=np.float64)
    rise = on * theta_on
    if off is not None:
        rise = rise - np.asarray(off, dtype=np.float64) * theta_off
    # exp overflows beyond ~709: that many thresholds is not a physical count
    if np.any(rise > 700):
        raise EvtkError("counts imply an intensity rise beyond exp(700): not a linearisable response")
    return np.expm1(rise)


#: Largest table of distinct (ON, OFF) counts :func:`linearize` looks values up in.
_TABLE_MAX = 1 << 20


def _count_table(on, off, theta_on, theta_off):
    """:func:`linearize` of integer counts with scalar thresholds by table look-up (None when it does not apply).

    A window holds few distinct counts, so ``expm1`` of each distinct
    (ON, OFF) pair, looked up per pixel, is exact and several times faster
    than ``expm1`` per pixel.
    """
    on = np.asarray(on)
    if off is None:
        off = np.zeros_like(on)
    off = np.asarray(off)
    if (on.dtype.kind not in "iu" or off.dtype.kind not in "iu" or np.ndim(theta_on) or np.ndim(theta_off)
            or on.shape != off.shape or on.size < 4096):
        return None
    on_flat = np.ascontiguousarray(on).reshape(-1)
    off_flat = np.ascontiguousarray(off).reshape(-1)
    jit = numba_ready()  # numpy until something has paid numba's start (a few ms more a million counts)
    extent, look_up = (_count_extent_jit, _look_up_jit) if jit else (_count_extent, _look_up)
    lo, hi_on, hi_off = (int(v) for v in extent(on_flat, off_flat))
    if lo < 0 or (hi_on + 1) * (hi_off + 1) > _TABLE_MAX:
        return None
    rise = np.arange(hi_on + 1.0)[:, None] * float(theta_on) - np.arange(hi_off + 1.0)[None, :] * float(theta_off)
    if rise.max() > 700:
        raise EvtkError("counts imply an intensity rise beyond exp(700): not a linearisable response")
    out = np.empty(on.shape, np.float64)
    flat, table, stride = out.reshape(-1), np.expm1(rise).ravel(), hi_off + 1
    _on_threads(lambda a, b: look_up(on_flat[a:b], off_flat[a:b], table, stride, flat[a:b]), on_flat.size, 1 << 16)
    return out


def _count_extent(on: np.ndarray, off: np.ndarray) -> tuple[int, int, int]:
    """The least count of both (0 when none is negative), the greatest ON count and the greatest OFF count."""
    lo = min(0, int(on.min(initial=0)), int(off.min(initial=0)))
    return lo, max(0, int(on.max(initial=0))), max(0, int(off.max(initial=0)))


def _look_up(on: np.ndarray, off: np.ndarray, table: np.ndarray, stride: int, out: np.ndarray) -> None:
    """``out = table[on * stride + off]`` (numpy releases the GIL for each step, so blocks run on threads)."""
    key = on.astype(np.intp)
    key *= stride
    key += off
    np.take(table, key, out=out)


@njit(cache=True)
def _count_extent_jit(on, off):
    """:func:`_count_extent` in one pass (numba)."""
    lo = 0
    hi_on = 0
    hi_off = 0
    for i in range(on.size):
        a = on[i]
        b = off[i]
        lo = min(lo, a, b)
        hi_on = max(hi_on, a)
        hi_off = max(hi_off, b)
    return lo, hi_on, hi_off


@njit(cache=True, nogil=True)
def _look_up_jit(on, off, table, stride, out):
    """:func:`_look_up` without the keys' array (numba)."""
    for i in range(on.size):
        out[i] = table[on[i] * stride + off[i]]


def count_curve(sim_record: SimulationRecord | dict, skip_us: float = 0, length_us: float | None = None,
                points: int = 4000) -> tuple[np.ndarray, np.ndarray]:
    """Net counts a noise-free pixel with nominal thresholds gives, against its log-light step.

    Runs the simulation's own pixel model (``sim_record``: a
    :class:`~evtk.simulate.SimulationRecord` or its dict form) for a dark-to-pattern step of ``u`` (natural
    log of light over the dark level) from 0 to the brightest possible
    pattern, counting in the same window as the reconstruction, from a
    settled pixel whose reference is the dark level. (A pixel in steady
    operation keeps some residual from earlier captures; over random
    patterns a fresh reference inverts the counts better than modelling the
    previous capture at the same light.) Returns ``(u, counts)``, counts
    non-decreasing in ``u`` (read-only arrays, shared by calls with the same
    bench, sensor and window: a batch of recordings computes it once).

    Parameters
    ----------
    sim_record : SimulationRecord or dict
        The record whose sensor model (without shot noise or threshold mismatch), dark level, gain, bench,
        window and settling time are run.
    skip_us : float
        Microseconds left out at the start of the capture window, as the reconstruction's windows.
    length_us : float, optional
        Most microseconds counted after ``skip_us``; None counts to the window's end.
    points : int
        Log-light steps sampled, evenly from 0 to just past the brightest response.

    Returns
    -------
    u : numpy.ndarray
        float64, shape ``(points,)``: the log-light steps (natural log of light over the dark level), read-only.
    counts : numpy.ndarray
        Net counts ON - OFF at each step, same shape, non-decreasing, read-only.
    """
    r = _model_plan(sim_record)
    pixels = r.pixels
    assert pixels is not None  # _model_plan refuses a plan without one
    key = json.dumps({"sensor": pixels.sensor.to_dict(), "blank_rate_e_per_s": pixels.blank_rate_e_per_s,
                      "gain_e_per_s_per_unit": pixels.gain_e_per_s_per_unit, "bench": r.bench.to_dict(),
                      "window_us": r.window_us, "settle_us": r.settle_us, "kernel_shape": r.kernels.shape[1:],
                      "skip_us": float(skip_us), "length_us": None if length_us is None else float(length_us),
                      "points": int(points)}, sort_keys=True, default=_plain)
    return _count_curve(key)


def _model_plan(sim: Plan | SimulationRecord | dict) -> Plan:
    """The plan the stages after counting read: a plan with a pixel model as it is, a simulation record (or its
    dict form) through :meth:`Plan.from_record` (the oracle's)."""
    plan = sim if isinstance(sim, Plan) else Plan.from_record(sim)
    if plan.pixels is None:
        raise EvtkError("the plan holds no pixel model to invert (a simulation record's, or one fitted to level "
                        "captures): reconstruct it with evtk.reconstruct.reconstruct, which fits one or uses "
                        "exp(n theta)")
    return plan


def _plain(value):
    """numpy scalars and arrays as JSON values (for cache keys)."""
    if hasattr(value, "tolist"):
        return value.tolist()
    raise TypeError(f"{type(value).__name__} is not JSON-serialisable")


@functools.lru_cache(maxsize=16)
def _count_curve(key):
    sim_record = json.loads(key)
    skip_us, length_us, points = sim_record["skip_us"], sim_record["length_us"], sim_record["points"]
    sm = SensorModel.from_dict({**sim_record["sensor"], "shot_noise": False, "theta_mismatch": 0.0})
    blank = float(sim_record["blank_rate_e_per_s"])
    gain = float(sim_record["gain_e_per_s_per_unit"])
    bench = Bench.from_dict(sim_record["bench"])
    dark = sm.dark_current_e_per_s
    bright = gain * brightest_response(tuple(sim_record["kernel_shape"]), bench) + dark
    u_max = max(np.log(bright / blank), 1e-6) * 1.01
    u = np.linspace(0.0, u_max, int(points))
    w, z = float(sim_record["window_us"]), float(sim_record["settle_us"])
    a = z + float(skip_us)
    b = z + w if length_us is None else min(z + w, a + float(length_us))
    bounds = sorted({0.0, z, a, b, z + w, 2 * z + w})
    starts, ends = np.array(bounds[:-1]), np.array(bounds[1:])
    lit = (starts >= z) & (starts < z + w)
    lvl = np.where(lit[:, None], np.log(blank) + u[None, :], np.log(blank))
    slot = np.where((starts >= a) & (ends <= b), 0, -1)
    noise = log_noise_std(np.exp(lvl), sm)
    # a noise-free pixel is causal: the segments after the last counted one (the dark after the window, whose
    # OFF events took as many rounds as the window's ON ones) cannot change its counts; with noise every
    # segment's draws stay, so that the random stream is the same
    n_seg = len(starts) if np.any(noise) or not np.any(slot >= 0) else int(np.flatnonzero(slot >= 0)[-1]) + 1
    st = PixelState(lvl[0], 0.0, np.full(u.size, sm.theta_on), np.full(u.size, sm.theta_off))
    _, _, _, on, off = simulate_pixels(st, lvl[:n_seg], time_constant_us(np.exp(lvl[:n_seg]), sm), noise[:n_seg],
                                       starts[:n_seg], ends[:n_seg], sm, 0, emit=False, count_slot=slot[:n_seg],
                                       n_slots=1)
    counts = np.maximum.accumulate(on[0] - off[0])
    u.flags.writeable = counts.flags.writeable = False
    return u, counts


def linearize_by_model(net_counts: npt.ArrayLike, curve: tuple) -> np.ndarray:
    """Log-light step behind each net count, by inverting :func:`count_curve`.

    A count ``n`` stands for the middle of the steps that give ``n``; 0 stays
    0 (no light cannot be told from light below one threshold), and counts
    beyond the curve take its end. Fractional counts (calibrated by
    :func:`flat_field_gain`) interpolate between neighbouring whole counts.

    Parameters
    ----------
    net_counts : array_like
        ON minus OFF counts, any shape.
    curve : tuple
        ``(u, counts)``, as :func:`count_curve` or :func:`level_curve` returns.

    Returns
    -------
    ndarray
        ``exp(u) - 1``, the shape of ``net_counts``.
    """
    return np.expm1(_model_log_step(net_counts, curve))


def _model_log_step(net_counts, curve):
    """:func:`linearize_by_model`'s step ``u`` itself."""
    n = np.asarray(net_counts, dtype=np.float64)
    if not np.all(np.isfinite(n)):
        raise EvtkError("counts to linearise must be finite")
    levels, mid = _count_steps(curve)
    return np.interp(n, levels, mid)


def _on_threads(kernel: Callable[[int, int], object], rows: int, least_rows: int = 1) -> None:
    """Run ``kernel(lo, hi)`` over the rows ``[0, rows)`` in contiguous blocks, one per thread of evtk's budget
    (:func:`evtk._threads.workers`: ``--threads`` / ``EVTK_THREADS``, else the cores this process may use), at
    least ``least_rows`` rows a block; the calling thread takes the first block.

    ``kernel`` is numpy work that releases the GIL (or a numba function compiled with ``nogil=True``) that writes
    each row independently, so the result does not depend on the number of threads. Plain Python threads, not
    numba's parallel loops: no threading layer to start in a fresh process, and no worker threads left spinning
    after the loop while the next stage (or the reader's threads) wants the cores.
    """
    n = max(1, min(workers(), rows // max(1, least_rows)))
    bounds = [rows * i // n for i in range(n + 1)]
    run(kernel, list(zip(bounds, bounds[1:])))  # (evtk._parallel's shared threads, not a pool made per call)


def _flat_log_step(sim, bench, region):
    """Log-light step ``u`` each pixel of ``region`` (y, x) sees in a flat-field window (every mirror on), as the
    plan ``sim`` (or a simulation record) places the response and models the pixels."""
    plan = _model_plan(sim)
    if plan.camera is not None:  # the simulated camera's view of the flat field
        k, f = np.ones(plan.kernels.shape[1:], np.int8), np.ones(plan.features.shape[1:], np.int8)
        return _log_step(plan, plan.camera.view(k, f, bench, tuple(region)))
    return _log_step(plan, _flat_light(bench, plan.kernels.shape[1:], plan.features.shape[1:], plan.origin_px,
                                       plan.cell_map, region))


#: Flat-field light per pixel kept between reconstructions through one placement (:func:`_flat_light`).
_FLAT_LIGHT_KEPT = 16
_flat_lights: OrderedDict[tuple, np.ndarray] = OrderedDict()
_flat_lights_lock = threading.Lock()


def _flat_light(bench: Bench, kernel_shape: tuple, features_shape: tuple, origin_px, cell_map, region) -> np.ndarray:
    """The light (response units) each pixel of ``region`` (y, x) receives in a flat-field window, where the
    origin (default: the bench geometry's) or the fitted ``cell_map`` places the response.

    It depends on the bench and the placement only, not on the recording or the pixels: the last
    :data:`_FLAT_LIGHT_KEPT` are kept (read-only) for the next reconstruction through the same calibration.
    """
    view = None if cell_map is None else (np.asarray(cell_map.matrix, np.float64).tobytes(), float(cell_map.k1),
                                          tuple(int(v) for v in cell_map.sensor_size))
    ks = (int(kernel_shape[0]), int(kernel_shape[1]))
    fs = (int(features_shape[0]), int(features_shape[1]))
    key = (bench, ks, fs, None if origin_px is None else tuple(float(v) for v in origin_px), view,
           tuple(int(v) for v in region))
    with _flat_lights_lock:
        got = _flat_lights.get(key)
        if got is not None:
            _flat_lights.move_to_end(key)
            return got
    k, f = np.ones(ks, np.int8), np.ones(fs, np.int8)
    origin = origin_px
    if origin is None:  # the bench geometry's
        origin = response_origin_px(bench, ks, fs)
    light = None
    if cell_map is not None:  # a fitted map: a scale and shift is an origin, anything else is seen through
        full = (k.shape[0] + f.shape[0] - 1, k.shape[1] + f.shape[1] - 1)
        aligned = cell_map.axis_aligned(full)
        if aligned is None:  # turned, tilted or distorted
            light = _flat_through_map(k, f, bench, cell_map, tuple(region))
        else:
            origin = aligned[0]
    if light is None:  # where the plan places the response (a calibration's origin, or the bench's own)
        light = screen_response(k, f, bench.replace(origin_px=tuple(origin)), tuple(region))
    light = np.array(light)  # its own copy, kept read-only
    light.flags.writeable = False
    with _flat_lights_lock:
        _flat_lights[key] = light
        while len(_flat_lights) > _FLAT_LIGHT_KEPT:
            _flat_lights.popitem(last=False)
    return light


def _log_step(plan, light):
    """Log-light step over the dark level of a pixel receiving ``light`` (response units), by ``plan``'s pixels."""
    px = plan.pixels
    rate = px.gain_e_per_s_per_unit * light + px.sensor.dark_current_e_per_s
    return np.log(np.maximum(rate, 1e-300) / px.blank_rate_e_per_s)


def _flat_through_map(kernel, features, bench, cell_map, region):
    """The light each pixel of ``region`` sees of one pass when cells land where ``cell_map`` puts them: each
    footprint point's cell (through the map's inverse) on a nominal grid of the bench's step, 8 px in
    (:func:`evtk.optics.camera.footprint_light`)."""
    step = bench.kernel_step_cells / bench.pixel_cells
    pad = 8.0
    rows, cols = (features.shape[0] + kernel.shape[0] - 1), (features.shape[1] + kernel.shape[1] - 1)
    nw, nh = int(np.ceil(2 * pad + step * cols)), int(np.ceil(2 * pad + step * rows))
    nominal = bench.replace(origin_px=(pad, pad), sensor_width=max(nw, 1), sensor_height=max(nh, 1))
    return footprint_light(kernel, features, nominal, region, lambda pts: pad + step * cell_map.to_cells(pts))


def _expected_flat_counts(sim, bench, region, curve, theta_on, u=None):
    """Net count a nominal pixel gives in a flat-field window, per pixel of ``region`` (y, x).

    The light is the optics' own (every mirror on, borders included); with
    a count curve the count is the curve read continuously, else
    ``log-step / theta_on``. ``u``: :func:`_flat_log_step`'s result, when the caller has it already.
    """
    if u is None:
        u = _flat_log_step(sim, bench, region)
    if curve is None:
        return u / theta_on
    levels, mid = _count_steps(curve)
    return np.interp(u, mid, levels)


def _count_steps(curve):
    """Whole counts 0..top of a :func:`count_curve` and the log-light step each stands for (its middle)."""
    levels, lo, hi = _count_bands(curve)
    mid = 0.5 * (lo + hi)
    mid[0] = 0.0
    return levels, mid


def _count_bands(curve):
    """Whole counts 0..top of a :func:`count_curve` and the band ``[lo, hi)`` of log-light steps giving each."""
    u, n_of_u = curve
    top = int(n_of_u[-1])
    levels = np.arange(top + 2)
    first = np.searchsorted(n_of_u, levels, side="left")  # first grid index reaching each count
    lo = u[np.minimum(first[:-1], u.size - 1)]
    hi = np.where(first[1:] < u.size, u[np.minimum(first[1:], u.size - 1)], u[-1])
    return levels[:-1], lo, hi


def flat_field_gain(flat_counts: npt.ArrayLike, expected_counts: npt.ArrayLike, min_counts: float = 3,
                    limits: tuple[float, float] = (0.5, 2.0)) -> np.ndarray:
    """Per-pixel count gain from flat-field captures: ``expected / observed``.

    A pixel with threshold ``theta`` counts a log-light step ``u`` as about
    ``u / theta`` events, so its threshold mismatch is a gain on all its
    counts. ``flat_counts`` (captures, ...) are net counts of windows whose
    light is known up to that gain (every mirror on); ``expected_counts``
    (...) is what a pixel with nominal thresholds counts there (the pixel
    model's :func:`count_curve` at the light the optics give each pixel, or
    the region's median on a bench without a model). Multiplying a pixel's
    counts by its gain puts them on the nominal threshold's scale.

    Pixels expecting fewer than ``min_counts`` events, or observing none,
    keep a gain of 1; gains are clipped to ``limits``.

    Parameters
    ----------
    flat_counts : array_like (captures, ...)
        Net counts of the flat-field windows.
    expected_counts : array_like (...)
        What a pixel with nominal thresholds counts there.
    min_counts : float
        Fewest expected events for a gain other than 1.
    limits : tuple of float
        ``(low, high)`` the gains are clipped to.

    Returns
    -------
    ndarray (...)
        Each pixel's gain.

    Examples
    --------
    >>> flat_field_gain(np.array([[30, 25, 0]]), np.array([27.5, 27.5, 27.5])).tolist()
    [0.9166666666666666, 1.1, 1.0]
    """
    obs = np.asarray(flat_counts, dtype=np.float64)
    exp_ = np.asarray(expected_counts, dtype=np.float64)
    if obs.ndim < 1 or obs.shape[0] == 0:
        raise EvtkError("flat-field calibration needs at least one flat-field capture")
    if obs.shape[1:] != exp_.shape:
        raise EvtkError(f"flat-field counts {obs.shape[1:]} and expected counts {exp_.shape} differ in shape")
    obs = obs.mean(axis=0)
    ok = (exp_ >= min_counts) & (obs > 0) & np.isfinite(exp_)
    gain = np.ones(exp_.shape)
    gain[ok] = exp_[ok] / obs[ok]
    return np.clip(gain, *limits)


def isotonic(y: npt.ArrayLike, weights: npt.ArrayLike | None = None) -> np.ndarray:
    """The non-decreasing sequence nearest ``y`` in weighted least squares (pool adjacent violators).

    Parameters
    ----------
    y : array_like, shape (n,)
        The sequence.
    weights : array_like, shape (n,), optional
        Positive weights (default all 1).

    Returns
    -------
    ndarray, shape (n,)
        Each run of violators replaced by its weighted mean.

    Examples
    --------
    >>> isotonic([1.0, 3.0, 2.0, 4.0]).tolist()
    [1.0, 2.5, 2.5, 4.0]
    """
    y = np.asarray(y, dtype=np.float64)
    w = np.ones_like(y) if weights is None else np.asarray(weights, dtype=np.float64)
    means, sizes, counts = [], [], []
    for v, wv in zip(y, w):
        means.append(v)
        sizes.append(wv)
        counts.append(1)
        while len(means) > 1 and means[-2] > means[-1]:
            m2, s2, c2 = means.pop(), sizes.pop(), counts.pop()
            tot = sizes[-1] + s2
            means[-1] = (means[-1] * sizes[-1] + m2 * s2) / tot
            sizes[-1] = tot
            counts[-1] += c2
    return np.repeat(np.asarray(means), counts)


def level_table_values(net_counts: npt.ArrayLike, level_counts: npt.ArrayLike,
                       level_light: npt.ArrayLike) -> np.ndarray:
    """Light behind each net count, read from the level captures without a pixel model.

    The level captures (known light ``level_light``, response units above
    the dark level) give the mean net counts ``level_counts`` a pixel
    makes at each light; with (0 counts, 0 light) added and the counts made
    non-decreasing in light (:func:`isotonic`), the table is read by linear
    interpolation, and beyond its ends along its first and last segments.

    Parameters
    ----------
    net_counts : array_like
        ON minus OFF counts (any shape; flat-field calibrated or not).
    level_counts, level_light : array_like, shape (levels,)
        The level captures' mean net counts and their light.

    Returns
    -------
    ndarray
        Light in the units of ``level_light``, the shape of ``net_counts``.

    Examples
    --------
    >>> level_table_values(np.array([0.0, 5.0, 15.0]), [10.0, 20.0], [1.0, 2.0]).tolist()
    [0.0, 0.5, 1.5]
    """
    light = np.asarray(level_light, dtype=np.float64).ravel()
    counts = np.asarray(level_counts, dtype=np.float64).ravel()
    if light.size != counts.size or light.size == 0:
        raise EvtkError("a level table needs one mean count per level capture, and at least one capture")
    if not (np.all(np.isfinite(light)) and np.all(np.isfinite(counts))):
        raise EvtkError("the level captures' light and counts must be finite")
    order = np.argsort(light, kind="stable")
    light = np.concatenate([[0.0], light[order]])
    counts = isotonic(np.concatenate([[0.0], counts[order]]))
    # equal counts (a saturated or flat stretch) stand for the mean of their lights
    xs, inverse = np.unique(counts, return_inverse=True)
    ys = np.bincount(inverse, weights=light) / np.bincount(inverse)
    n = np.asarray(net_counts, dtype=np.float64)
    if xs.size < 2:
        raise EvtkError("the level captures' counts do not grow with their light: no table can be read from them")
    out = np.interp(n, xs, ys)
    lo_slope = (ys[1] - ys[0]) / (xs[1] - xs[0])
    hi_slope = (ys[-1] - ys[-2]) / (xs[-1] - xs[-2])
    out = np.where(n < xs[0], ys[0] + (n - xs[0]) * lo_slope, out)
    return np.where(n > xs[-1], ys[-1] + (n - xs[-1]) * hi_slope, out)


def level_curve(level_light: npt.ArrayLike, level_counts: npt.ArrayLike, blank_units: float,
                points: int = 4000) -> tuple[np.ndarray, np.ndarray]:
    """A count curve (:func:`count_curve`'s form) read from level captures instead of simulated by a model.

    The level captures' mean net counts against their known light
    (:func:`level_table_values`' monotone table) give the count at each
    log-light step ``u = log(1 + light / blank_units)``; rounded to whole
    counts, a count ``n`` stands for the steps whose mean count rounds to
    it, so :func:`linearize_by_model` reads ``n`` back as the light whose
    mean count is ``n``. Up to 1.5 times the brightest level's step, along
    the table's last segment beyond it.

    Parameters
    ----------
    level_light : array_like, shape (levels,)
        Each level capture's light (response units above the dark level).
    level_counts : array_like, shape (levels,)
        Their mean net counts (flat-field calibrated).
    blank_units : float
        The dark level in response units: ``u`` is the light's log step over it.
    points : int
        Grid of ``u``.

    Returns
    -------
    (u, counts)
        ``u`` from 0 upwards and whole counts non-decreasing in it.
    """
    light = np.asarray(level_light, dtype=np.float64).ravel()
    if not (np.isfinite(blank_units) and blank_units > 0):
        raise EvtkError(f"the dark level must be a positive number of response units, not {blank_units}")
    if light.size == 0 or not np.all(np.isfinite(light)) or light.max() <= 0:
        raise EvtkError("a level curve needs level captures of some light")
    u = np.linspace(0.0, 1.5 * np.log1p(light.max() / blank_units), int(points))
    counts_of_light = np.asarray(level_counts, dtype=np.float64).ravel()
    order = np.argsort(light, kind="stable")
    lx = np.concatenate([[0.0], light[order]])
    cy = isotonic(np.concatenate([[0.0], counts_of_light[order]]))
    target = np.expm1(u) * blank_units
    n = np.interp(target, lx, cy)
    slope = (cy[-1] - cy[-2]) / (lx[-1] - lx[-2])
    n = np.where(target > lx[-1], cy[-1] + (target - lx[-1]) * max(slope, 0.0), n)
    counts = np.maximum.accumulate(np.maximum(np.floor(n + 0.5), 0.0))
    u.flags.writeable = counts.flags.writeable = False
    return u, counts
