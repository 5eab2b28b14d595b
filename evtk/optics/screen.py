"""Light on the screen and the sensor: penumbral shadows of the diffused kernel through the features."""

from __future__ import annotations

import functools
import math
from typing import TYPE_CHECKING

import numpy as np

from ..errors import EvtkError
from .bench import Bench
from .geometry import shadow_magnification

if TYPE_CHECKING:
    import numpy.typing as npt

__all__ = [
    "screen_response", "ideal_response", "glow_response", "brightest_response", "response_region",
    "response_origin_px", "response_to_sensor_grid",
]


def _phi1(x):
    """First antiderivative of the normal CDF: x*Phi(x) + phi(x)."""
    from scipy import special  # (scipy loads where a footprint is modelled, not with the module)

    return x * special.ndtr(x) + np.exp(-0.5 * x * x) / math.sqrt(2 * math.pi)


def _phi2(x):
    """Second antiderivative of the normal CDF: ((x^2+1)*Phi(x) + x*phi(x)) / 2."""
    from scipy import special

    return 0.5 * ((x * x + 1.0) * special.ndtr(x) + x * np.exp(-0.5 * x * x) / math.sqrt(2 * math.pi))


def footprint_cdf(t: np.ndarray | float, a: float, b: float, s: float) -> np.ndarray:
    """CDF at ``t`` of U(0,a) + U(0,b) + N(0,s^2); ``b`` and ``s`` may be 0.

    Closed forms only, so the ideal case is exact. The deblur
    (:mod:`evtk.reconstruct.deblur`) builds its weights from the same function.

    Parameters
    ----------
    t : numpy.ndarray or float
        Where to evaluate, in feature elements.
    a : float
        The pixel footprint, in feature elements (> 0).
    b : float
        The source extent, in feature elements (0: a point source).
    s : float
        The blur's standard deviation, in feature elements (0: none).

    Returns
    -------
    numpy.ndarray
        The probability, in [0, 1], shaped like ``t``.
    """
    t = np.asarray(t, dtype=np.float64)
    tiny = 1e-4 * a
    if s <= tiny:
        if b <= 0:
            return np.clip(t / a, 0.0, 1.0)
        r = lambda v: np.maximum(v, 0.0) ** 2  # noqa: E731
        return np.clip((r(t) - r(t - a) - r(t - b) + r(t - a - b)) / (2 * a * b), 0.0, 1.0)
    if b <= 0:
        return np.clip(s / a * (_phi1(t / s) - _phi1((t - a) / s)), 0.0, 1.0)
    return np.clip(s * s / (a * b) * (_phi2(t / s) - _phi2((t - a) / s) - _phi2((t - b) / s)
                                      + _phi2((t - a - b) / s)), 0.0, 1.0)


def axis_weights(
    pixels: npt.ArrayLike, n_cells: int, k: int, bench: Bench, origin: float, psf_cells: float
) -> np.ndarray:
    """W[j, i, n]: share of pixel ``pixels[i]``'s view of kernel element ``j``'s shadow in cell ``n``.

    One axis of the separable footprint model (:func:`footprint_cdf`); :func:`screen_response` and the
    reconstruction's deblurring both use it.

    Parameters
    ----------
    pixels : array_like of int
        Sensor pixel indices along the axis.
    n_cells : int
        Feature elements along the axis.
    k : int
        Kernel elements along the axis.
    bench : Bench
        The bench (pixel footprint, kernel step, source extent, flip).
    origin : float
        Sensor pixel that sees cell 0 of the full response (:func:`response_origin_px`, one coordinate).
    psf_cells : float
        Standard deviation of the shadow blur, in feature elements.

    Returns
    -------
    numpy.ndarray
        float64, shape ``(k, len(pixels), n_cells)``, each entry in [0, 1]; read-only for a run of consecutive
        pixels (a cached array).
    """
    pixels = np.asarray(pixels)
    if pixels.size and np.array_equal(pixels, np.arange(pixels[0], pixels[0] + pixels.size)):
        # the usual call: a run of pixels; the same geometry recurs for every capture of a run
        return _axis_weights_run(int(pixels[0]), int(pixels.size), int(n_cells), int(k), bench.pixel_cells,
                                 bench.kernel_step_cells, bench.source_extent, bool(bench.kernel_flipped),
                                 float(origin), float(psf_cells))
    return _axis_weights_of(pixels, n_cells, k, bench.pixel_cells, bench.kernel_step_cells, bench.source_extent,
                            bench.kernel_flipped, origin, psf_cells)


@functools.lru_cache(maxsize=64)
def _axis_weights_run(p0, n, n_cells, k, s1, kappa, source_extent, flipped, origin, psf_cells):
    w = _axis_weights_of(np.arange(p0, p0 + n), n_cells, k, s1, kappa, source_extent, flipped, origin, psf_cells)
    w.setflags(write=False)
    return w


def _axis_weights_of(pixels, n_cells, k, s1, kappa, source_extent, flipped, origin, psf_cells):
    b = kappa if source_extent == "area" else 0.0
    j = np.arange(k, dtype=np.float64)
    if flipped:
        j = j[::-1].copy()
    # footprint centre of pixel x for element j: (x - origin) * s1 + (j - (k - 1)) * kappa + 1/2
    centre = (np.asarray(pixels, np.float64)[None, :] - origin) * s1 + (j[:, None] - (k - 1)) * kappa + 0.5
    low = centre - 0.5 * (s1 + b)  # start of U(0, s1) + U(0, b)
    edges = np.arange(n_cells + 1, dtype=np.float64)
    cdf = footprint_cdf(edges[None, None, :] - low[:, :, None], s1, b, psf_cells)
    # rounding in the blurred closed form can make the CDF dip by ~1e-15: keep light non-negative
    return np.diff(np.maximum.accumulate(cdf, axis=2), axis=2)


def response_origin_px(
    bench: Bench, kernel_shape: tuple[int, int], features_shape: tuple[int, int]
) -> tuple[float, float]:
    """Sensor pixel (x, y) whose footprint sees cell (0, 0) of the full response.

    ``bench.origin_px`` when set, else the position that centres the full
    response on the sensor.

    Parameters
    ----------
    bench : Bench
        The bench (its ``origin_px``, geometry and sensor size).
    kernel_shape : tuple of int
        ``(rows, cols)`` of the kernel, in elements.
    features_shape : tuple of int
        ``(rows, cols)`` of the features, in elements.

    Returns
    -------
    tuple of float
        ``(x, y)`` in sensor pixels (whole numbers when centred, as set when ``bench.origin_px`` is given).
    """
    if bench.origin_px is not None:
        return bench.origin_px
    kh, kw = kernel_shape
    fh, fw = features_shape
    # centre the full response: it spans (f + k - 1) * kappa... in cells, i.e. that / s1 pixels
    span_x = (fw + (kw - 1) * bench.kernel_step_cells) / bench.pixel_cells
    span_y = (fh + (kh - 1) * bench.kernel_step_cells) / bench.pixel_cells
    return (math.floor((bench.sensor_width - span_x) / 2), math.floor((bench.sensor_height - span_y) / 2))


def response_region(
    bench: Bench, kernel_shape: tuple[int, int], features_shape: tuple[int, int]
) -> tuple[int, int, int, int]:
    """Sensor pixels the pattern's shadow can reach: ``(x0, x1, y0, y1)``, half-open, clipped.

    The reach includes half a pixel footprint, half a source element (area sources) and six standard
    deviations of the shadow blur on each side.

    Parameters
    ----------
    bench : Bench
        The bench.
    kernel_shape : tuple of int
        ``(rows, cols)`` of the kernel, in elements.
    features_shape : tuple of int
        ``(rows, cols)`` of the features, in elements.

    Returns
    -------
    tuple of int
        ``(x0, x1, y0, y1)`` in sensor pixels, clipped to the sensor (possibly empty: ``x1 == x0``).
    """
    kh, kw = kernel_shape
    fh, fw = features_shape
    ox, oy = response_origin_px(bench, kernel_shape, features_shape)
    s1 = bench.pixel_cells
    kappa = bench.kernel_step_cells
    # the footprint of a pixel spreads half a pixel and half a source element each way, plus blur
    spread = 0.5 * s1 + (0.5 * kappa if bench.source_extent == "area" else 0.0)
    spread += 6.0 * bench.shadow_sigma_um / (shadow_magnification(bench.u_mm, bench.z_mm) * bench.feature_pitch_um)

    def span(origin: float, k: int, f: int, n: int) -> tuple[int, int]:
        # pixel x sees cells (x - origin) * s1 + (j - (k-1)) * kappa + 1/2 +- spread, j in [0, k)
        lo = origin + (-(spread + 0.5)) / s1
        hi = origin + (f - 0.5 + (k - 1) * kappa + spread) / s1
        return max(0, math.floor(lo)), min(n, math.floor(hi) + 1)

    x0, x1 = span(ox, kw, fw, bench.sensor_width)
    y0, y1 = span(oy, kh, fh, bench.sensor_height)
    return x0, max(x0, x1), y0, max(y0, y1)


def _binary(name, a):
    a = np.asarray(a)
    if a.ndim != 2 or a.size == 0:
        raise EvtkError(f"{name} must be a non-empty 2-D array, got shape {a.shape}")
    if not np.all(np.isfinite(a)) or not np.all((a == 0) | (a == 1)):
        raise EvtkError(f"{name} must be a binary DMD pattern (0/1); split signed patterns into passes first")
    return a.astype(np.float64)


def screen_response(
    kernel: npt.ArrayLike,
    features: npt.ArrayLike,
    bench: Bench,
    region: tuple[int, int, int, int] | None = None,
    *,
    leak: bool = True,
) -> np.ndarray:
    """Light collected by each sensor pixel for one displayed (kernel, features) pair.

    Parameters
    ----------
    kernel, features : array_like of {0, 1}
        The binary patterns shown on the two DMDs (one pass), 2-D.
    bench : Bench
        The bench: geometry, blur, leakage and stray light.
    region : (x0, x1, y0, y1), optional
        Sensor pixels to compute (half-open); default the whole sensor.
    leak : bool
        Include off-mirror leakage and stray light (True for a real bench).

    Returns
    -------
    ndarray, shape (y1 - y0, x1 - x0), float64
        In units of one lit kernel element seen through one open feature
        element, averaged over the pixel's footprint. Pixels away from the
        pattern see the uniform glow of leaking mirrors plus stray light.

    Raises
    ------
    EvtkError
        If a pattern is not a non-empty 2-D array of 0/1, or does not fit its DMD.
    """
    k = _binary("kernel", kernel)
    f = _binary("features", features)
    bench.check_pattern(k.shape, f.shape)
    if region is None:
        region = (0, bench.sensor_width, 0, bench.sensor_height)
    x0, x1, y0, y1 = region
    lk = bench.leak if leak else 0.0
    k_eff = k + lk * (1.0 - k)  # off kernel mirrors in the lit footprint leak
    out = np.zeros((y1 - y0, x1 - x0))
    if leak:  # the whole feature DMD glows where it is off ...
        out += glow_response(k, bench)
    # ... and the pattern adds (1 - lk) where its elements are on
    rx0, rx1, ry0, ry1 = response_region(bench, k.shape, f.shape)
    ax0, ax1, ay0, ay1 = max(x0, rx0), min(x1, rx1), max(y0, ry0), min(y1, ry1)
    if ax1 <= ax0 or ay1 <= ay0 or not f.any():
        return out
    ox, oy = response_origin_px(bench, k.shape, f.shape)
    psf_cells = bench.shadow_sigma_um / (shadow_magnification(bench.u_mm, bench.z_mm) * bench.feature_pitch_um)
    wx = axis_weights(np.arange(ax0, ax1), f.shape[1], k.shape[1], bench, ox, psf_cells)  # (kw, nx, fw)
    wy = axis_weights(np.arange(ay0, ay1), f.shape[0], k.shape[0], bench, oy, psf_cells)  # (kh, ny, fh)
    patch = np.zeros((ay1 - ay0, ax1 - ax0))
    for r in range(k.shape[0]):
        a = wy[r] @ f  # (ny, fw)
        for c in range(k.shape[1]):
            if k_eff[r, c] != 0:
                patch += k_eff[r, c] * (a @ wx[c].T)
    out[ay0 - y0:ay1 - y0, ax0 - x0:ax1 - x0] += (1.0 - lk) * patch
    return out


def glow_response(kernel: npt.ArrayLike, bench: Bench) -> float:
    """Light every pixel gets whatever the features show: off feature mirrors leak.

    ``leak * sum(K')`` with ``K' = K + leak * (1 - K)`` (off kernel mirrors
    leak too), plus stray light, in the units of :func:`screen_response`.
    With both DMDs dark (``kernel`` all zero) it is the blank level.

    Parameters
    ----------
    kernel : array_like
        The kernel pattern shown (0/1 per element).
    bench : Bench
        The bench (its ``leak`` and ``stray_light``).

    Returns
    -------
    float
        The glow, in response units.
    """
    k = np.asarray(kernel, dtype=np.float64)
    lk = bench.leak
    return float(lk * (k + lk * (1.0 - k)).sum() + bench.stray_light)


def brightest_response(kernel_shape: tuple[int, int], bench: Bench) -> float:
    """The most light a pixel can get: every kernel element through open features, plus stray light.

    Parameters
    ----------
    kernel_shape : tuple of int
        ``(rows, cols)`` of the kernel, in elements.
    bench : Bench
        The bench (its ``stray_light``).

    Returns
    -------
    float
        ``rows * cols + stray_light``, in response units.
    """
    kh, kw = kernel_shape
    return float(kh * kw + bench.stray_light)


def ideal_response(kernel: npt.ArrayLike, features: npt.ArrayLike, bench: Bench | None = None) -> np.ndarray:
    """The digital response the device approximates: full 2-D correlation (or convolution).

    ``scipy.signal.correlate2d(features, kernel, mode="full")``, or
    ``convolve2d`` when ``bench.kernel_flipped``. Accepts signed patterns.

    Parameters
    ----------
    kernel : array_like
        2-D kernel, any real values.
    features : array_like
        2-D features, any real values.
    bench : Bench or None, optional
        Only its ``kernel_flipped`` is read; None correlates.

    Returns
    -------
    numpy.ndarray
        float64, shape ``(fh + kh - 1, fw + kw - 1)``.
    """
    k = np.asarray(kernel, dtype=np.float64)
    f = np.asarray(features, dtype=np.float64)
    flipped = bench is not None and bench.kernel_flipped
    if k.ndim == 2 and f.ndim == 2 and _exact_in_any_order(k, f):
        return _correlate_full(f, k[::-1, ::-1] if flipped else k)
    from scipy import signal  # real-valued patterns: scipy's sums (importing scipy.signal is ~0.5 s of a process)

    if flipped:
        return signal.convolve2d(f, k, mode="full")
    return signal.correlate2d(f, k, mode="full")


def _exact_in_any_order(k: np.ndarray, f: np.ndarray) -> bool:
    """Whether every product and partial sum of the correlation of ``f`` with ``k`` is an exact float64 integer.

    True for integer-valued patterns whose largest possible sum, max|f| * sum|k|, is below 2**53: then the
    correlation is the same floats whatever the order of its sums (scipy's or :func:`_correlate_full`'s).
    """
    if k.size == 0 or f.size == 0 or not (np.all(np.isfinite(k)) and np.all(np.isfinite(f))):
        return False
    if not (np.array_equal(k, np.round(k)) and np.array_equal(f, np.round(f))):
        return False
    return float(np.abs(f).max()) * float(np.abs(k).sum()) < 2.0 ** 53


def _correlate_full(f: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Full 2-D correlation ``out[i, j] = sum_ab f[i + a - kh + 1, j + b - kw + 1] * k[a, b]`` (zero outside
    ``f``): one shifted, scaled copy of ``f`` added per kernel element."""
    (fh, fw), (kh, kw) = f.shape, k.shape
    out = np.zeros((fh + kh - 1, fw + kw - 1))
    for a in range(kh):
        for b in range(kw):
            if k[a, b] != 0:
                out[kh - 1 - a:kh - 1 - a + fh, kw - 1 - b:kw - 1 - b + fw] += k[a, b] * f
    return out


def response_to_sensor_grid(
    bench: Bench, kernel_shape: tuple[int, int], features_shape: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """Sensor pixel centres (x, y) of each cell of the full ideal response, in pixel units.

    Cell ``(i, j)`` of :func:`ideal_response` is centred on sensor coordinate
    ``origin + i * kappa / s1`` (kappa the kernel step, s1 the pixel footprint,
    both in feature elements; pixel ``x`` is centred on ``x``). At stride 1
    that cell is exactly pixel ``origin + i``'s footprint.

    Parameters
    ----------
    bench : Bench
        The bench.
    kernel_shape : tuple of int
        ``(rows, cols)`` of the kernel, in elements.
    features_shape : tuple of int
        ``(rows, cols)`` of the features, in elements.

    Returns
    -------
    xs : numpy.ndarray
        float64, shape ``(fw + kw - 1,)``: the x centre of each response column, sensor pixels.
    ys : numpy.ndarray
        float64, shape ``(fh + kh - 1,)``: the y centre of each response row, sensor pixels.
    """
    kh, kw = kernel_shape
    fh, fw = features_shape
    ox, oy = response_origin_px(bench, kernel_shape, features_shape)
    step = bench.kernel_step_cells / bench.pixel_cells
    # full-response cell i sits where element (k-1) of pixel x sees cell i - (k-1) -> x = origin + i*kappa/s1
    xs = ox + np.arange(fw + kw - 1) * step
    ys = oy + np.arange(fh + kh - 1) * step
    return xs, ys
