"""Where the response lies on the sensor, measured from the device's own calibration captures.

A job with ``calibration = N`` shows, after its flat fields, N captures of a
dot grid on the feature DMD (:func:`evtk.simulate.dot_grid`) under the
kernel's centre element alone. Each dot lights one response cell, known in
cell coordinates. :func:`calibrate` finds
the blobs in the ON events of those windows, pairs them with the dots, and
fits the map from response cells to sensor pixels: a projective transform,
by RANSAC (scikit-image's ``measure.ransac`` with ``transform.ProjectiveTransform``),
with its residuals in pixels. From the map follow the response's origin
(the pixel that sees cell (0, 0)), its step (pixels per cell) and the
region to count. Nothing here reads a simulation record: the schedule
(``schedule.json`` from ``evtk patterns``) and the events are enough.

When the map is not a scale and shift a radial lens distortion is fitted
too. The dots' profiles give the camera's defocus (:func:`dot_blur_px`),
the run's level captures the pixel model
(:func:`evtk.reconstruct.fit.fit_pixel_model`), and the pixels outside the
response in the dark the background rate (:func:`background_rate_hz`).
"""

from __future__ import annotations

import dataclasses
import json
import os
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from ._atomic import AtomicFile
from .errors import EvtkError
from .optics.camera import CellMap
from .plan import DOTS_ID, FLAT_ID, LEVEL_ID, Plan, as_plan, dot_grid
from .reconstruct import PixelFit, accumulate, match_windows
from .reconstruct.bench import refuse_synchronous
from .reconstruct.calibrated import fit_on_edges, refuse_pixel_fit
from .reconstruct.deblur import sampling_matrix
from .reconstruct.fit import describe_pixels, hot_pixels
from .reconstruct.windows import Windows
from .settings import (
    MAX_BLUR_PX,
    MAX_COUNT,
    MAX_SIDE,
    Spec,
    check_array,
    check_matrix,
    check_origin,
    check_region,
    check_table,
    check_value,
    read_table,
    toml_text,
)

if TYPE_CHECKING:
    import numpy.typing as npt

    from .io.base import BaseRecording
    from .optics import Bench

__all__ = ["Calibration", "calibrate", "background_rate_hz", "dot_blur_px", "load_calibration", "save_calibration",
           "plot_calibration", "MIN_DOTS"]

#: Fewest ON events at a dot's brightest pixel, over the calibration captures, for it to count as seen.
MIN_DOT_EVENTS = 3

#: Fewest dots a calibration needs (a projective map has 8 unknowns; RANSAC wants more).
MIN_DOTS = 8


@dataclass
class Calibration:
    """What :func:`calibrate` measured.

    Parameters
    ----------
    matrix : list of 3 lists of 3 floats
        Projective map from response cells (column, row) to sensor pixels (x, y), homogeneous, before
        the lens's radial distortion.
    k1 : float
        Radial distortion about the sensor centre, at the half diagonal (0: none fitted);
        :class:`evtk.optics.camera.CellMap` applies both.
    origin_px : [x, y]
        Sensor pixel that sees cell (0, 0) of the full response.
    step_px : float
        Sensor pixels per response cell (mean of the map's two axes at the response's centre).
    region : [x0, x1, y0, y1]
        Sensor pixels covering the full response plus a pixel of margin (half-open), clipped to the sensor.
    residual_rms_px : float
        RMS distance between the dots found and the fitted map, over the inliers, pixels.
    residual_max_px : float
        The largest such distance, pixels.
    dots_expected : int
        Dots the calibration captures showed (the marker's places dark).
    dots_found : int
        Blobs found in the ON events.
    inliers : int
        Dots the fitted map agrees with (within a pixel).
    sensor_size : [width, height]
        The sensor, pixels.
    response_shape : [rows, cols]
        Cells of the full response (features + kernel - 1).
    pixel_model : dict or None
        The pixel model fitted to the run's level captures
        (:meth:`evtk.reconstruct.PixelFit.to_dict`: thresholds, the dark
        level's light, time constants, the statistics fitted), when it has
        any; ``evtk reconstruct --calibration`` uses it for runs without
        level captures of their own.
    background_rate_hz : float or None
        Background activity per pixel, from the pixels outside the response
        while the DMDs are dark and the pixels settled (:func:`background_rate_hz`).
    blur_px : float
        The camera's defocus, a Gaussian's standard deviation in pixels, beyond the footprint the bench
        geometry predicts (:func:`dot_blur_px`); the reconstruction deblurs it. Below about 0.3 px it is
        not told apart from none.
    orientation : str or None
        How the camera sees the screen (a key of :data:`ORIENTATIONS`: upright, mirrored, rotated), measured
        from the dot grid's marker; None where the grid carries none (then upright was assumed, and said).
    warnings : list of str
        What the calibration assumed or left out (hot pixels, a refused pixel model, an assumed orientation).
    """

    matrix: list
    origin_px: list
    step_px: float
    region: list
    residual_rms_px: float
    residual_max_px: float
    dots_expected: int
    dots_found: int
    inliers: int
    sensor_size: list
    response_shape: list
    pixel_model: dict | None = None
    k1: float = 0.0
    background_rate_hz: float | None = None
    blur_px: float = 0.0
    orientation: str | None = None
    warnings: list = field(default_factory=list)

    def to_dict(self) -> dict:
        """The calibration as a plain dict (what :func:`save_calibration` writes).

        Returns
        -------
        dict
            Field name to value.
        """
        return asdict(self)

    def cell_map(self) -> CellMap:
        """The fitted map as a :class:`evtk.optics.camera.CellMap` (projective, then radial ``k1``).

        Returns
        -------
        CellMap
            The map from response cells to sensor pixels.
        """
        return CellMap(np.asarray(self.matrix, dtype=np.float64), float(self.k1), tuple(self.sensor_size))

    def to_pixels(self, cells_xy: npt.ArrayLike) -> np.ndarray:
        """Sensor pixels (x, y) of response cells (column, row).

        Parameters
        ----------
        cells_xy : array_like
            Cells as (column, row), shape ``(2,)`` or ``(n, 2)``; fractional cells allowed.

        Returns
        -------
        numpy.ndarray
            float64, shape ``(n, 2)``, sensor pixels.
        """
        return self.cell_map().to_pixels(cells_xy)

    def place(self, plan: Plan | dict | str | os.PathLike, own_levels: bool = True) -> Plan:
        """The run's plan with the camera part this calibration measured: region, origin, map, defocus and
        (when it kept one) the pixel model.

        Parameters
        ----------
        plan : Plan, dict, str or os.PathLike
            The run's plan, a schedule's dict form or its ``schedule.json`` (:func:`evtk.plan.as_plan`).
        own_levels : bool
            Let the reconstruction fit the pixel model to the run's own level captures when it has any (else
            it uses this calibration's).

        Returns
        -------
        Plan
            The plan :func:`evtk.reconstruct.reconstruct` takes.
        """
        return as_plan(plan).replace(region=tuple(self.region), origin_px=tuple(self.origin_px),
                                     cell_map=self.cell_map(), blur_px=self.blur_px, pixel_model=self.pixel_model,
                                     own_levels=own_levels)


def _blobs(image, spacing_px=None, radius=2):
    """Centroids (x, y) of the bright spots of ``image``.

    Spots are the local maxima above Otsu's threshold, at least half a dot
    spacing apart (``spacing_px``; blurred dots seen through the pixels'
    log response are flat-topped and touch, so connected areas would merge
    them). Each spot's centre is then the count-weighted mean over the
    (2 radius + 1)^2 pixels around its maximum (radius at most a third of the
    spacing), background (the window's lowest count) taken off, so that the
    faint pixels a sub-pixel position spreads light into count too.
    """
    from scipy.ndimage import gaussian_filter  # scipy and scikit-image load when calibrating only: a
    from skimage.feature import peak_local_max  # reconstruction that loads a calibration does not need them
    from skimage.filters import threshold_otsu

    img = np.asarray(image, dtype=np.float64)
    if not np.any(img > 0):
        return np.zeros((0, 2))
    thr = threshold_otsu(img) if np.ptp(img) > 0 else 0.0
    sep = max(1, int(spacing_px // 2)) if spacing_px else 2
    if spacing_px:
        radius = int(max(1, min(radius, spacing_px // 3)))
    # a plateau's pixels are all maxima: smooth a little first so each spot has one summit
    peaks = peak_local_max(gaussian_filter(img, 0.7), min_distance=sep, threshold_abs=thr, exclude_border=False)
    # a dot is a few events at least: a lone background event is not one
    peaks = peaks[img[peaks[:, 0], peaks[:, 1]] >= max(thr, MIN_DOT_EVENTS)] if len(peaks) else peaks
    out = []
    h, w = img.shape
    for py, px in peaks:
        y0, y1 = max(0, py - radius), min(h, py + radius + 1)
        x0, x1 = max(0, px - radius), min(w, px + radius + 1)
        win = img[y0:y1, x0:x1]
        win = win - win.min()
        total = win.sum()
        if total <= 0:
            continue
        yy, xx = np.mgrid[y0:y1, x0:x1]
        out.append((float((win * xx).sum() / total), float((win * yy).sum() / total)))
    return np.asarray(out, dtype=np.float64).reshape(-1, 2)


def calibrate(rec: BaseRecording, schedule: Plan | str | os.PathLike[str] | dict, tolerance_us: int | None = None,
              pixel_model: bool = True) -> Calibration:
    """Fit the map from response cells to sensor pixels from a recording's calibration captures.

    ``schedule`` is a ``schedule.json`` path or :func:`evtk.reconstruct.load_schedule`'s
    dict; windows come from the recording's trigger edges, matched to the
    schedule (:func:`evtk.reconstruct.match_windows`). Raises
    :class:`~evtk.EvtkError` when the schedule has no calibration captures,
    none was recorded, fewer than :data:`MIN_DOTS` dots are seen, or the
    dots do not fit one map. Dots are located on the ON-event counts (a
    pixel counts the log of its light, which pulls centres up to 0.08 px
    towards the pixel boundaries; linearising first amplified the noise
    more than it removed). The map is projective; when an affine map fits
    the inliers as well (RMS within 10 %), the affine one is kept, as its
    fewer parameters extrapolate better to the response's corners. With
    ``pixel_model`` and level captures in the run, the pixel model is fitted
    too (:attr:`Calibration.pixel_model`), and the defocus measured through it
    (:attr:`Calibration.blur_px`; without a model, through a logarithmic
    response, which reads it low: 0.6 and 1.0 px as 0.44 and 0.92).

    Parameters
    ----------
    rec : Recording
        The open recording of the run, with its trigger edges.
    schedule : Plan, str, os.PathLike or dict
        The run's plan, its ``schedule.json``, or the dict form of it (:func:`evtk.plan.as_plan`).
    tolerance_us : int or None
        How far a trigger edge may sit from the schedule's time, us
        (:func:`evtk.reconstruct.match_windows`; None: its default).
    pixel_model : bool
        Fit the pixel model to the run's level captures when it has any.

    Returns
    -------
    Calibration
        The map, its residuals, the region, and (when measured) the pixel model, the background rate and the
        defocus; ``warnings`` says what was assumed or left out.

    Raises
    ------
    EvtkError
        As above: no calibration captures scheduled or recorded, too few dots seen or paired, or no single map.
    """
    sched = as_plan(schedule)
    s, kernels, features = sched.schedule, sched.kernels, sched.features
    if not np.any(s.kernel_id == DOTS_ID):
        raise EvtkError("the schedule has no calibration captures: add calibration = N to the job")
    win, report = match_windows(rec.triggers(), s, tolerance_us)
    dots_win = s.kernel_id[win.capture] == DOTS_ID
    if not dots_win.any():
        raise EvtkError(f"none of the schedule's calibration captures has a trigger window (missing: "
                        f"{report['missing'][:10]})")
    w, h = rec.sensor_size  # type: ignore[misc]  # an open recording knows its size (None only on the base class)
    sub = Windows(win.t_start_us[dots_win], win.t_end_us[dots_win], win.capture[dots_win], win.source)
    dot_counts = accumulate(rec, sub, (0, w, 0, h))
    # pixels that fire in the dark would be dots of their own: each takes its neighbours' median
    hot = hot_pixels(rec, win.t_start_us, win.t_end_us)
    image = _without(dot_counts.on.sum(axis=0).astype(np.float64), hot)
    bench = sched.bench
    found = _blobs(image, sched.dot_spacing * bench.kernel_step_cells / bench.pixel_cells)
    kh, kw = kernels.shape[1:]
    fh, fw = features.shape[1:]
    grid = np.argwhere(dot_grid((fh, fw), sched.dot_spacing, marker=False) > 0)  # (row, col) of every grid place
    lit = dot_grid((fh, fw), sched.dot_spacing)[grid[:, 0], grid[:, 1]] > 0  # the marker's places are dark
    # the kernel's centre element (ck) and a dot at features (r, c) light full-response cell (r + kh-1 - ck, ...)
    ck_r, ck_c = (kh - 1) // 2, (kw - 1) // 2
    places = np.stack([grid[:, 1] + (kw - 1) - ck_c, grid[:, 0] + (kh - 1) - ck_r], axis=1).astype(np.float64)
    expected = places[lit]
    if len(found) < MIN_DOTS:
        raise EvtkError(f"only {len(found)} calibration dots were seen ({len(expected)} shown); at least {MIN_DOTS} "
                        "are needed: more light, a longer window, or a coarser dot spacing")
    pairs, orientation, note = _orient(found, places, lit)
    warnings = [] if note is None else [note]
    if hot.any():
        warnings.append(f"left {describe_pixels(hot)} out of the dot search and the pixel model's fit: they fire "
                        "in the dark far more than the rest (hot pixels)")
    if len(pairs) < MIN_DOTS:
        raise EvtkError(f"only {len(pairs)} of the {len(found)} dots seen could be paired with the "
                        f"{len(expected)} shown: is the schedule that of this recording?")
    src = places[[j for _, j in pairs]]
    dst = found[[i for i, _ in pairs]]
    from skimage.measure import ransac
    from skimage.transform import ProjectiveTransform

    model, inliers = ransac((src, dst), ProjectiveTransform, min_samples=4, residual_threshold=1.0,
                            max_trials=500, rng=0)
    if model is None or inliers is None or inliers.sum() < MIN_DOTS:
        raise EvtkError("the calibration dots do not fit one projective map (fewer than "
                        f"{MIN_DOTS} agree within a pixel)")
    res = np.linalg.norm(model(src[inliers]) - dst[inliers], axis=1)
    affine = _affine(src[inliers], dst[inliers])
    if affine is not None:
        res_a = np.linalg.norm(affine(src[inliers]) - dst[inliers], axis=1)
        if np.sqrt(np.mean(res_a ** 2)) <= 1.1 * np.sqrt(np.mean(res ** 2)):
            model, res = ProjectiveTransform(affine.params), res_a
    cmap, res = _with_distortion(CellMap(np.asarray(model.params, np.float64), 0.0, (w, h)), src[inliers],
                                 dst[inliers], res)
    model = cmap.to_pixels
    rows, cols = fh + kh - 1, fw + kw - 1
    origin = model(np.array([[0.0, 0.0]]))[0]
    centre = np.array([[(cols - 1) / 2, (rows - 1) / 2]])
    dx = np.linalg.norm(model(centre + [0.5, 0]) - model(centre - [0.5, 0]))
    dy = np.linalg.norm(model(centre + [0, 0.5]) - model(centre - [0, 0.5]))
    corners = model(np.array([[-0.5, -0.5], [cols - 0.5, -0.5], [-0.5, rows - 0.5], [cols - 0.5, rows - 0.5]]))
    x0 = int(max(0, np.floor(corners[:, 0].min()) - 1))
    x1 = int(min(w, np.ceil(corners[:, 0].max()) + 2))
    y0 = int(max(0, np.floor(corners[:, 1].min()) - 1))
    y1 = int(min(h, np.ceil(corners[:, 1].max()) + 2))
    cal = Calibration(np.asarray(cmap.matrix).tolist(), [float(origin[0]), float(origin[1])], float((dx + dy) / 2),
                      [x0, x1, y0, y1], float(np.sqrt(np.mean(res ** 2))), float(res.max()), len(expected),
                      len(found), int(inliers.sum()), [int(w), int(h)], [int(rows), int(cols)], None, cmap.k1,
                      orientation=orientation, warnings=warnings)
    cal._evidence = (image, found, expected)  # type: ignore[attr-defined]  # for plot_calibration; not saved
    levels = s.kernel_id[win.capture] == LEVEL_ID
    use = levels | (s.kernel_id[win.capture] == FLAT_ID)
    if pixel_model and levels.any():  # a synchronous readout's counts fall in bright light: no model fits them
        try:
            refuse_synchronous(rec, win.t_start_us[use], win.t_end_us[use])
        except EvtkError as exc:
            cal.warnings.append(f"no pixel model: {exc}")
            pixel_model = False
    if pixel_model and levels.any():  # and the pixels' model, from the level captures (with the flat fields' spread)
        fit = fit_on_edges(rec, win.t_start_us[use], win.t_end_us[use], s.take(win.capture[use]), sched, cal.region,
                           cal.origin_px, cell_map=cal.cell_map(), hot=hot)
        refused = refuse_pixel_fit(fit)  # a model no camera has is neither used nor saved
        cal.pixel_model = fit.to_dict() if refused is None else None
        if refused is not None:
            cal.warnings.append(refused)
    x0, x1, y0, y1 = cal.region
    net = _without((dot_counts.on.astype(np.float64) - dot_counts.off).mean(axis=0), hot)[y0:y1, x0:x1]
    cal.blur_px = dot_blur_px(net, cal.region, cal.cell_map(), bench, np.rint(expected).astype(np.int64), (rows, cols),
                              model=PixelFit.from_dict(cal.pixel_model) if cal.pixel_model else None)
    cal.background_rate_hz = background_rate_hz(rec, win.t_end_us, sched.settle_us, cal.region)
    return cal


def dot_blur_px(net: npt.ArrayLike, region: tuple[int, int, int, int] | list[int], cell_map: CellMap, bench: Bench,
                dot_cells: npt.ArrayLike, shape: tuple[int, int], model: PixelFit | None = None,
                radius_px: float = 3, max_px: float = 3.0) -> float:
    """The camera's defocus (Gaussian standard deviation, pixels) that best explains the dots' counts.

    Each dot lights one response cell, all of them at once. Through the
    fitted map, the bench's footprint (pixel area, source extent, shadow
    blur) and a trial defocus, :func:`~evtk.reconstruct.deblur.sampling_matrix`
    predicts the light each pixel gets from all the dots ``dot_cells``
    (column, row) together; the pixels' response turns it into counts, by the
    fitted pixel model (``model``, a :class:`~evtk.reconstruct.PixelFit`: its
    mean count at each light) or, without one, ``log(1 + a L) / theta`` with
    ``a`` and ``theta`` free. The defocus is searched on a grid of 0.05 px
    from 0 to ``max_px`` (then refined by a parabola), the light's scale
    fitted at each step by least squares; the mean net counts ``net`` (over
    the region, per dot capture) are the data, over the pixels within
    ``radius_px`` of a dot.

    Parameters
    ----------
    net : array_like
        Mean net (ON minus OFF) counts per dot capture, shape ``(y1 - y0, x1 - x0)`` of ``region``.
    region : tuple of int
        ``(x0, x1, y0, y1)`` sensor pixels, half-open.
    cell_map : CellMap
        The fitted map from response cells to sensor pixels.
    bench : Bench
        The bench whose footprint (pixel area, source extent, shadow blur) is predicted.
    dot_cells : array_like
        int, shape ``(n, 2)``: the response cells (column, row) the dots light.
    shape : tuple of int
        ``(rows, cols)`` of the full response, cells.
    model : PixelFit or None
        The fitted pixel model; None fits a logarithmic response instead.
    radius_px : float
        Pixels within this distance of a dot's centre are the data.
    max_px : float
        Largest defocus searched, pixels.

    Returns
    -------
    float
        The defocus, a Gaussian's standard deviation in pixels, in ``[0, max_px]``.

    Raises
    ------
    EvtkError
        When fewer than three pixels near the dots, or none with counts above zero, are left to fit.
    """
    x0, x1, y0, y1 = (int(v) for v in region)
    net = np.asarray(net, np.float64)
    rows, cols = (int(v) for v in shape)
    cells = np.asarray(dot_cells, np.int64)  # (column, row)
    lit = np.zeros(rows * cols)
    lit[cells[:, 1] * cols + cells[:, 0]] = 1.0
    a0 = (sampling_matrix(bench, cell_map.to_cells, region, shape) @ lit).reshape(y1 - y0, x1 - x0)
    centres = cell_map.to_pixels(cells.astype(np.float64)) - [x0, y0]
    yy, xx = np.mgrid[0:y1 - y0, 0:x1 - x0]
    use = np.zeros(a0.shape, bool)
    for cx, cy in centres:
        use |= (xx - cx) ** 2 + (yy - cy) ** 2 <= radius_px ** 2
    data = net[use]
    if data.size < 3 or not np.any(data > 0):
        raise EvtkError("no counts near the calibration dots to measure the camera's blur from")
    if model is not None:
        grid = np.linspace(0.0, 4.0, 81)
        curve = np.maximum.accumulate(np.nan_to_num(model.mean_counts(grid)))

        def counts(light, p):
            return np.interp(p[0] * light, grid, curve)
        start, lo, hi = [1.0], [0.05], [4.0]
    else:
        def counts(light, p):
            return np.log1p(p[0] * light) / p[1]
        start, lo, hi = [1.0, 0.2], [1e-3, 1e-3], [1e3, 10.0]

    from scipy.ndimage import gaussian_filter
    from scipy.optimize import least_squares

    def misfit(sigma):
        light = (gaussian_filter(a0, sigma, mode="constant") if sigma > 0 else a0)[use]
        fit = least_squares(lambda p: counts(light, p) - data, start, bounds=(lo, hi))
        return float(np.sum(fit.fun ** 2))

    sigmas = np.arange(0.0, max_px + 1e-9, 0.05)
    cost = np.array([misfit(v) for v in sigmas])
    i = int(np.argmin(cost))
    if 0 < i < sigmas.size - 1:  # the parabola's vertex through the best step and its neighbours
        c0, c1, c2 = cost[i - 1:i + 2]
        curv = c0 - 2 * c1 + c2
        if curv > 0:
            return float(sigmas[i] + 0.05 * 0.5 * (c0 - c2) / curv)
    return float(sigmas[i])


def background_rate_hz(rec: BaseRecording, t_off_us: np.ndarray, settle_us: int,
                       region: tuple[int, int, int, int] | list[int], margin_px: int = 3,
                       max_windows: int = 64) -> float | None:
    """Background activity: events a pixel fires per second with nothing changing.

    Counted on the pixels outside the response (``region`` grown by ``margin_px``) in the second half of the
    darkness after each pattern (settled), over at most ``max_windows`` of them.

    Parameters
    ----------
    rec : Recording
        The open recording.
    t_off_us : numpy.ndarray
        Where each pattern's darkness begins (the windows' ends), us.
    settle_us : int
        Length of the darkness after each pattern, us.
    region : tuple of int
        ``(x0, x1, y0, y1)``: the response's sensor pixels, half-open.
    margin_px : int
        Pixels around ``region`` left out too.
    max_windows : int
        Most dark intervals read.

    Returns
    -------
    float or None
        Events per pixel per second, or None when there is no such time or pixel.
    """
    w, h = rec.sensor_size  # type: ignore[misc]  # an open recording knows its size (None only on the base class)
    x0, x1, y0, y1 = region
    x0, x1, y0, y1 = max(0, x0 - margin_px), min(w, x1 + margin_px), max(0, y0 - margin_px), min(h, y1 + margin_px)
    pixels = w * h - (x1 - x0) * (y1 - y0)
    half = int(settle_us) // 2
    if pixels <= 0 or half <= 0 or len(t_off_us) == 0:
        return None
    n = 0
    ends = np.asarray(t_off_us)[:max_windows].tolist()
    for t in ends:
        ev = rec.events(int(t) + half, int(t) + int(settle_us))
        inside = (ev.x >= x0) & (ev.x < x1) & (ev.y >= y0) & (ev.y < y1)
        n += int(np.count_nonzero(~inside))
    return float(n / (pixels * len(ends) * (int(settle_us) - half) * 1e-6))


def _without(image, mask):
    """``image`` with the pixels of ``mask`` replaced by the median of their 3x3 neighbourhood."""
    if not np.any(mask):
        return image
    from scipy.ndimage import median_filter

    out = image.copy()
    out[mask] = median_filter(image, size=3, mode="nearest")[mask]
    return out


def _with_distortion(cmap, src, dst, res):
    """``cmap`` (a :class:`CellMap` without distortion) refined with radial distortion about the sensor centre,
    when that fits the dots better (RMS down by more than 10 %): ``(map, residuals)``."""
    if len(src) < 10:
        return cmap, res
    from scipy.optimize import least_squares

    h0 = np.asarray(cmap.matrix, np.float64) / cmap.matrix[2, 2]

    def residuals(p):
        m = np.append(p[:8], 1.0).reshape(3, 3)
        return (CellMap(m, p[8], cmap.sensor_size).to_pixels(src) - dst).ravel()

    fit = least_squares(residuals, np.append(h0.ravel()[:8], 0.0), x_scale="jac")
    res_d = np.linalg.norm(fit.fun.reshape(-1, 2), axis=1)
    if not (fit.success and abs(fit.x[8]) < 0.3) or np.sqrt(np.mean(res_d ** 2)) > 0.9 * np.sqrt(np.mean(res ** 2)):
        return cmap, res
    return CellMap(np.append(fit.x[:8], 1.0).reshape(3, 3), float(fit.x[8]), cmap.sensor_size), res_d


def _affine(src, dst):
    """The least-squares affine map ``src -> dst`` (scikit-image's, through whichever API it has), or None."""
    from skimage.transform import AffineTransform

    if hasattr(AffineTransform, "from_estimate"):  # scikit-image >= 0.26
        model = AffineTransform.from_estimate(src, dst)
        return model if model else None
    model = AffineTransform()
    return model if model.estimate(src, dst) else None


#: The eight ways a camera can see the dot grid (cell axes to sensor axes, up to scale), by name: 2x2 matrices
#: applied to cell offsets (column, row) about the grid's centre.
ORIENTATIONS = {
    "upright": ((1, 0), (0, 1)),
    "mirrored left-right": ((-1, 0), (0, 1)),
    "mirrored top-bottom": ((1, 0), (0, -1)),
    "rotated 180 degrees": ((-1, 0), (0, -1)),
    "transposed (mirrored and rotated 90 degrees)": ((0, 1), (1, 0)),
    "rotated 90 degrees": ((0, -1), (1, 0)),
    "rotated 270 degrees": ((0, 1), (-1, 0)),
    "anti-transposed (mirrored and rotated 270 degrees)": ((0, -1), (-1, 0)),
}


def _orient(found, places, lit):
    """Pair the blobs ``found`` with the grid's ``places`` (cells, column and row) in whichever of the
    :data:`ORIENTATIONS` the marker (the grid places not ``lit``, :func:`evtk.simulate.dot_grid`) says.

    Each orientation turns the grid about its centre before :func:`_pair` lays its bounding box on the blobs';
    its misfit is the lit places no blob pairs with plus the dark places one does. The best must be alone: a
    tie, or a dot on every marker place whichever way (a pattern without the marker), cannot tell a mirrored
    camera from an upright one.

    Returns
    -------
    pairs : list of (int, int)
        (blob index, place index) of the lit places paired.
    orientation : str or None
        The name of the orientation found; None when the grid carries no marker.
    warning : str or None
        Why the orientation was assumed rather than measured.
    """
    lit = np.asarray(lit, bool)
    centre = places.mean(axis=0)
    if lit.all():
        return ([(i, j) for i, j in _pair(found, places)], None,
                f"the dot grid ({len(places)} dots) is too small to carry the orientation marker (at least 10 dots, 3 "
                "rows and 4 columns or 4 and 3): the camera was taken to see the screen upright, not mirrored or rotated")
    scores = {}
    for name, m in ORIENTATIONS.items():
        turned = (places - centre) @ np.asarray(m, np.float64).T + centre
        pairs = _pair(found, turned)
        got = np.zeros(len(places), bool)
        got[[j for _, j in pairs]] = True
        scores[name] = (int(np.sum(lit & ~got)) + int(np.sum(~lit & got)), int(np.sum(~lit & got)),
                        [(i, j) for i, j in pairs if lit[j]])
    if all(v[1] == int(np.sum(~lit)) for v in scores.values()):  # the marker's places lit whichever way
        pairs = [(i, j) for i, j in _pair(found, places)]
        return (pairs, None, "a dot shows on every place of the grid, the orientation marker's too (patterns written "
                "before evtk drew the marker?): the camera was taken to see the screen upright; write the patterns again")
    ranked = sorted(scores, key=lambda k: scores[k][0])
    best, second = ranked[0], ranked[1]
    if scores[second][0] <= scores[best][0]:
        raise EvtkError(f"the calibration dots do not tell the camera's orientation: '{best}' and '{second}' both "
                        f"leave {scores[best][0]} dots unexplained (the marker is the dot missing next to the grid's "
                        "first corner; a dot lost at the grid's edge or a hot pixel can hide it): more light or "
                        "a longer window for the calibration captures")
    return scores[best][2], best, None


def _pair(found, expected):
    """Pairs (found index, expected index): the grid's bounding box mapped onto the blobs' (scale and shift
    per axis), then each expected dot takes its nearest blob within half a dot spacing, one blob each."""
    lo_f, hi_f = found.min(axis=0), found.max(axis=0)
    lo_e, hi_e = expected.min(axis=0), expected.max(axis=0)
    scale = np.where(hi_e > lo_e, (hi_f - lo_f) / np.maximum(hi_e - lo_e, 1e-9), 1.0)
    guess = (expected - lo_e) * scale + lo_f
    spacing = np.min([np.min(np.diff(np.unique(np.round(expected[:, a], 6)))) if len(np.unique(expected[:, a])) > 1
                      else 1.0 for a in (0, 1)]) * float(np.mean(scale))
    pairs, used = [], set()
    for j, g in enumerate(guess):
        d = np.linalg.norm(found - g, axis=1)
        i = int(np.argmin(d))
        if d[i] <= 0.5 * spacing and i not in used:
            pairs.append((i, j))
            used.add(i)
    return pairs


def _plot_pixel_model(ax, fit):
    """The level captures' mean counts against their light, and the fitted model's (noise-free) curve."""
    st = fit.statistics
    light = np.linspace(0.25, float(st.light.max()) * 1.05, 60)
    ax.plot(light, fit.mean_counts(light), "-", color="C0", label="fitted pixel model")
    ax.plot(st.light, st.counts, "o", color="C1", label="level captures (mean)")
    ax.set_xlabel("light (kernel elements on flat features)")
    ax.set_ylabel("net events per pixel and window")
    ax.set_title(f"pixel model: theta {fit.sensor.theta_on:.3f}, tau {fit.sensor.tau_min_us:.0f}"
                 f"-{fit.tau_dark_us:.0f} µs", fontsize=10)
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.14), ncols=2, frameon=False)  # off the data


def _nan_free(x):
    """A list element TOML can hold: a missing time (None, NaN) as -1."""
    return -1.0 if x is None or (isinstance(x, float) and not np.isfinite(x)) else x


def save_calibration(path: str | os.PathLike[str], cal: Calibration) -> None:
    """Write a calibration as TOML (``.toml``) or JSON, atomically.

    Parameters
    ----------
    path : str or os.PathLike
        Where to write; a name ending ``.toml`` writes TOML (the pixel model as a ``[pixel_model]`` table,
        missing times as -1), anything else JSON.
    cal : Calibration
        What to write.
    """

    path = os.fspath(path)
    d = cal.to_dict()
    if path.lower().endswith(".toml"):
        model = d.pop("pixel_model")
        table = {k: v for k, v in d.items() if v is not None}
        if model:
            table["pixel_model"] = {k: [_nan_free(x) for x in v] if isinstance(v, list) else v
                                    for k, v in model.items() if v is not None}
        comment = "evtk calibration (evtk calibrate): response cells -> sensor pixels"
        if model:
            comment += "\nthe pixel_model table: fitted to the level captures"
        text = toml_text(table, "calibration", comment=comment)
    else:
        text = json.dumps(d, indent=1)
    with AtomicFile(path) as out:
        out.file.write(text.encode())


#: The range of each number a calibration file holds (the map, pixels and region are checked on their own).
CALIBRATION_SPECS = {
    "step_px": Spec("float", 0, MAX_SIDE, lo_open=True, unit="sensor pixels per response cell"),
    "residual_rms_px": Spec("float", 0, MAX_SIDE, unit="px"),
    "residual_max_px": Spec("float", 0, MAX_SIDE, unit="px"),
    "dots_expected": Spec("int", 0, MAX_COUNT),
    "dots_found": Spec("int", 0, MAX_COUNT),
    "inliers": Spec("int", 0, MAX_COUNT),
    "k1": Spec("float", -0.3, 0.3, unit="radial distortion at the half diagonal"),
    "background_rate_hz": Spec("float", 0, 1e9, unit="events per pixel and second", optional=True),
    "blur_px": Spec("float", 0, MAX_BLUR_PX, unit="px, the camera's defocus; evtk calibrate measures 0 to 3"),
}


def load_calibration(path: str | os.PathLike[str]) -> Calibration:
    """Read :func:`save_calibration`'s file, every value checked.

    Parameters
    ----------
    path : str or os.PathLike
        A ``.toml`` or JSON calibration.

    Returns
    -------
    Calibration
        The calibration as saved (without the evidence :func:`plot_calibration` draws).

    Raises
    ------
    EvtkError
        A bad value is one :class:`~evtk.EvtkError` naming the file, the key
        and what is allowed: numbers finite and within :data:`CALIBRATION_SPECS`,
        a non-singular map whose horizon misses the response, the origin
        where the map puts cell (0, 0), the region on the sensor.
    """
    path = os.fspath(path)
    d = read_table(path, "calibration")
    fields = {f.name for f in dataclasses.fields(Calibration)}
    unknown = sorted(set(d) - fields)
    if unknown:
        raise EvtkError(f"{path}: not an evtk calibration (unknown keys {', '.join(unknown)})")
    missing = sorted(f.name for f in dataclasses.fields(Calibration)
                     if f.default is dataclasses.MISSING and f.name not in d)
    if missing:
        raise EvtkError(f"{path}: not an evtk calibration (it lacks {', '.join(missing)})")
    kw = check_table(path, d, CALIBRATION_SPECS, unknown="keep")
    size = check_array(path, "sensor_size", d["sensor_size"], 1, 1, MAX_SIDE, shape=(2,))
    shape = check_array(path, "response_shape", d["response_shape"], 1, 1, MAX_SIDE, shape=(2,))
    rows, cols = (int(v) for v in shape)
    m = check_matrix(path, "matrix", d["matrix"], [(0, 0), (cols, 0), (0, rows), (cols, rows)])
    kw.update(sensor_size=[int(v) for v in size], response_shape=[rows, cols], matrix=m.tolist(),
              origin_px=list(check_origin(path, "origin_px", d["origin_px"], size)),
              region=list(check_region(path, "region", d["region"], size)))
    notes = d.get("warnings", [])
    if not (isinstance(notes, list) and all(isinstance(n, str) for n in notes)):
        raise EvtkError(f"{path}: warnings must be a list of text lines, not {notes!r:.60}")
    if d.get("orientation") is not None and not isinstance(d["orientation"], str):
        raise EvtkError(f"{path}: orientation must be text (how the camera sees the grid), not {d['orientation']!r:.60}")
    cal = Calibration(**kw)
    at = cal.to_pixels(np.zeros((1, 2)))[0]
    if not np.all(np.abs(at - cal.origin_px) <= 0.5):
        raise EvtkError(f"{path}: origin_px = {cal.origin_px} is not where the matrix puts cell (0, 0) "
                        f"({at[0]:.2f}, {at[1]:.2f}); the file was edited by hand?")
    if cal.pixel_model is not None:
        if not isinstance(cal.pixel_model, dict):
            raise EvtkError(f"{path}: pixel_model must be a table")
        for k, v in cal.pixel_model.items():  # numbers finite and of sane size; lists of them
            if isinstance(v, list):
                check_array(path, f"pixel_model.{k}", [-1.0 if x is None else x for x in v], 1, -1e12, 1e12,
                            kind="float", max_elements=MAX_COUNT, allow_empty=True)
            elif not isinstance(v, bool) and v is not None:
                check_value(path, f"pixel_model.{k}", v, Spec("float", -1e12, 1e12))
        try:
            PixelFit.from_dict(cal.pixel_model)
        except EvtkError as exc:
            raise EvtkError(f"{path}: pixel_model: {exc}") from None
        except (TypeError, ValueError) as exc:  # a list where a number belongs, or the reverse
            raise EvtkError(f"{path}: pixel_model is malformed ({exc})") from None
    return cal


def plot_calibration(path: str | os.PathLike[str], cal: Calibration) -> None:
    """PNG report of a calibration.

    The calibration captures' ON events with the dots found and the fitted map's prediction of every dot,
    and the residual of each dot (pixels); with a pixel model, its curve against the level captures.

    Parameters
    ----------
    path : str or os.PathLike
        The PNG to write.
    cal : Calibration
        A calibration just made by :func:`calibrate` (it carries the evidence drawn).

    Raises
    ------
    EvtkError
        For a calibration read from a file, which holds no evidence.
    """

    evidence = getattr(cal, "_evidence", None)
    if evidence is None:
        raise EvtkError("a calibration read from a file holds no evidence to draw; calibrate the recording again")
    image, found, expected = evidence
    from .plots import pyplot, save_png  # plotting only: a reconstruction that loads a calibration skips it

    plt = pyplot()
    model = PixelFit.from_dict(cal.pixel_model) if cal.pixel_model else None
    if model is None:
        fig, (ax, ax_r) = plt.subplots(1, 2, figsize=(10.0, 4.8), gridspec_kw={"width_ratios": [3, 2]},
                                       layout="constrained")
    else:
        fig, (ax, ax_r, ax_m) = plt.subplots(1, 3, figsize=(15.0, 4.8), gridspec_kw={"width_ratios": [3, 2, 2]},
                                             layout="constrained")
        _plot_pixel_model(ax_m, model)
    x0, x1, y0, y1 = cal.region
    pad = 4
    xs = slice(max(0, x0 - pad), min(image.shape[1], x1 + pad))
    ys = slice(max(0, y0 - pad), min(image.shape[0], y1 + pad))
    im = ax.imshow(image[ys, xs], cmap="gray", interpolation="nearest",
                   extent=(xs.start - 0.5, xs.stop - 0.5, ys.stop - 0.5, ys.start - 0.5))
    fig.colorbar(im, ax=ax, label="ON events per pixel (dot captures)")
    pred = cal.to_pixels(expected)
    ax.plot(found[:, 0], found[:, 1], "o", mfc="none", color="C1", label="dots found")
    ax.plot(pred[:, 0], pred[:, 1], "+", color="C0", label="fitted map")
    ax.set_xlabel("sensor x (pixels)")
    ax.set_ylabel("sensor y (pixels)")
    ax.set_title(f"calibration dots: {cal.dots_found} found of {cal.dots_expected}", fontsize=10)
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.14), ncols=2, frameon=False)  # off the image
    d = np.linalg.norm(found[:, None, :] - pred[None, :, :], axis=2).min(axis=1)
    ax_r.bar(np.arange(len(d)), d, color="C0")
    ax_r.xaxis.get_major_locator().set_params(integer=True)  # dots are numbered
    ax_r.set_xlabel("dot (index)")
    ax_r.set_ylabel("distance to the fitted map (pixels)")
    ax_r.set_title(f"residual RMS {cal.residual_rms_px:.3f} px; defocus {cal.blur_px:.2f} px", fontsize=10)
    save_png(fig, path)
