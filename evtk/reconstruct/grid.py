"""The sensor region onto the response's cells, the signed passes combined, and resampling to a target size."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ..errors import EvtkError

if TYPE_CHECKING:
    import numpy.typing as npt

    from ..plan.schedule import Schedule

if TYPE_CHECKING:  # (the optics and scipy load where a function needs them: resizing needs neither)
    from ..optics import Bench
    from ..optics.camera import CellMap

__all__ = ["combine_passes", "to_response_grid", "sample_response_grid", "downsample", "footprint_matrix",
           "overlap_matrix"]


def combine_passes(values: npt.ArrayLike, schedule: Schedule | dict,
                   signed: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Signed responses: ``sum(kernel_sign * features_sign * values[c])`` over each pair's captures
    (``signed=False``: the plain sum).

    Parameters
    ----------
    values : ndarray, shape (captures, ...)
        One response per capture, in schedule order.
    schedule : evtk.plan.Schedule or dict
        The capture schedule (``kernel_id``, ``features_id``, signs, ``repeat``).
    signed : bool
        Weigh each capture by its passes' signs (else the plain sum).

    Returns
    -------
    tuple
        ``combined`` has shape (pairs, ...); ``pairs`` is an int array of
        (kernel_id, features_id, repeat) rows, sorted. Flat-field captures
        (ids -1) are not responses and are left out.
    """

    if isinstance(schedule, dict):
        from ..plan.schedule import Schedule  # (here: fixed windows' block means load no schedule)

        schedule = Schedule.from_dict(schedule)
    values = np.asarray(values)
    if values.shape[0] != len(schedule):
        raise EvtkError(f"{values.shape[0]} responses for a schedule of {len(schedule)} captures")
    use = (schedule.kernel_id >= 0) & (schedule.features_id >= 0)
    if not use.any():
        raise EvtkError("the schedule holds no (kernel, features) captures, only flat fields")
    keys = np.stack([schedule.kernel_id, schedule.features_id, schedule.repeat], axis=1)[use]
    pairs, which = np.unique(keys, axis=0, return_inverse=True)
    which = np.asarray(which).reshape(-1)
    sign = (schedule.kernel_sign * schedule.features_sign).astype(np.float64)[use] if signed else np.ones(int(use.sum()))
    # each capture belongs to one pair: sum the pairs' runs in one sorted pass (np.add.at is ten times slower)
    order = np.argsort(which, kind="stable")
    terms = values[use][order] * sign[order].reshape((-1,) + (1,) * (values.ndim - 1))
    starts = np.flatnonzero(np.r_[True, np.diff(which[order]) != 0])
    return np.add.reduceat(terms.astype(np.float64, copy=False), starts, axis=0), pairs


def overlap_matrix(n_cells: int, first_edge: float, step: float, n_pixels: int) -> np.ndarray:
    """How much of each cell each pixel covers, along one axis.

    Parameters
    ----------
    n_cells : int
        Cells; cell c is an interval of ``step`` pixels from ``first_edge + c * step``.
    first_edge : float
        Where cell 0 starts (pixels; pixel x spans ``[x, x + 1)``).
    step : float
        Pixels per cell.
    n_pixels : int
        Pixels.

    Returns
    -------
    ndarray (n_cells, n_pixels)
        ``W[c, x]``: the share of cell c covered by pixel x.
    """
    lo = first_edge + step * np.arange(n_cells)[:, None]
    hi = lo + step
    px = np.arange(n_pixels)[None, :]
    return np.clip(np.minimum(hi, px + 1) - np.maximum(lo, px), 0, None) / step


def sample_response_grid(values: npt.ArrayLike, region: tuple, cell_map: CellMap,
                         shape: tuple[int, int]) -> np.ndarray:
    """Responses over a sensor region on the response's cell grid through a general map (rotation, tilt,
    distortion): each cell takes the bilinear interpolation of the pixels around where its centre lands
    (:class:`evtk.optics.camera.CellMap`); cells landing outside the region count as zero light.

    Parameters
    ----------
    values : ndarray, shape (..., y1 - y0, x1 - x0)
        Responses over the region's pixels.
    region : (x0, x1, y0, y1)
        The sensor pixels ``values`` cover.
    cell_map : CellMap
        From cells to sensor pixels.
    shape : (rows, cols)
        Cells wanted.

    Returns
    -------
    ndarray (..., rows, cols)
        The responses on the cell grid.
    """
    values = np.asarray(values, dtype=np.float64)
    x0, x1, y0, y1 = (int(v) for v in region)
    rows, cols = (int(v) for v in shape)
    jj, ii = np.meshgrid(np.arange(cols, dtype=np.float64), np.arange(rows, dtype=np.float64))
    px = cell_map.to_pixels(np.stack([jj.ravel(), ii.ravel()], 1))
    coords = [px[:, 1] - y0, px[:, 0] - x0]
    lead = values.shape[:-2]
    flat = values.reshape((-1,) + values.shape[-2:])
    from scipy.ndimage import map_coordinates

    out = np.stack([map_coordinates(v, coords, order=1, mode="constant", cval=0.0) for v in flat])
    return out.reshape(lead + (rows, cols))


def to_response_grid(values: npt.ArrayLike, region: tuple, origin_px: tuple, step_px: float,
                     shape: tuple[int, int]) -> np.ndarray:
    """Resample responses over a sensor region onto the response's cell grid.

    Pixel ``x`` is centred on ``x`` and cell ``(i, j)`` on
    ``origin + (j, i) * step_px`` (the optics' convention), each ``step_px``
    pixels wide; a cell's value is the area-weighted mean of the pixels it
    overlaps. Cells larger
    than pixels (effective stride below 1) average whole and partial pixels;
    cells smaller than pixels (stride above 1) take the value of the pixel
    they lie in, as the sensor cannot resolve them. Parts of a cell outside
    the region count as zero light.

    Parameters
    ----------
    values : ndarray, shape (..., y1 - y0, x1 - x0)
        Responses over the region's pixels.
    region : (x0, x1, y0, y1)
        The sensor pixels ``values`` cover.
    origin_px : (x, y)
        Sensor pixel that sees cell (0, 0) (``response_origin_px`` in the metadata).
    step_px : float
        Sensor pixels per cell: ``decimation / effective stride``.
    shape : (rows, cols)
        Cells wanted (the full response is ``features + kernel - 1``).

    Returns
    -------
    ndarray (..., rows, cols)
        The responses on the cell grid.
    """
    values = np.asarray(values, dtype=np.float64)
    x0, x1, y0, y1 = (int(v) for v in region)
    if values.shape[-2:] != (y1 - y0, x1 - x0):
        raise EvtkError(f"values of shape {values.shape[-2:]} do not cover the region {tuple(region)}")
    if not (np.isfinite(step_px) and step_px > 0):
        raise EvtkError(f"step_px must be positive, not {step_px}")
    rows, cols = (int(v) for v in shape)
    ox, oy = (float(v) for v in origin_px)
    # in edge units (pixel x spans [x, x + 1)) cell c starts at origin + 1/2 - step/2 + c * step
    wy = overlap_matrix(rows, oy + 0.5 - 0.5 * step_px - y0, step_px, y1 - y0)
    wx = overlap_matrix(cols, ox + 0.5 - 0.5 * step_px - x0, step_px, x1 - x0)
    return wy @ values @ wx.T


def downsample(values: npt.ArrayLike, size: tuple[int, int] = (16, 16)) -> np.ndarray:
    """Resize the last two axes to ``size``: block means for whole factors, else area-weighted.

    Area weighting treats each input element as a unit square and each output
    element as the mean over the squares it covers, which conserves the mean
    for any ratio (up or down).

    Parameters
    ----------
    values : array_like (..., rows, cols)
        The responses.
    size : tuple of int
        ``(rows, cols)`` wanted.

    Returns
    -------
    ndarray (..., size[0], size[1])
        The resized responses.

    Examples
    --------
    >>> downsample(np.arange(16.0).reshape(4, 4), (2, 2)).tolist()
    [[2.5, 4.5], [10.5, 12.5]]
    """
    values = np.asarray(values, dtype=np.float64)
    h, w = values.shape[-2:]
    oh, ow = (int(v) for v in size)
    if oh < 1 or ow < 1:
        raise EvtkError(f"size must be positive, not {size}")
    if h % oh == 0 and w % ow == 0:
        fy, fx = h // oh, w // ow
        return values.reshape(values.shape[:-2] + (oh, fy, ow, fx)).mean(axis=(-3, -1))
    wy = overlap_matrix(oh, 0.0, h / oh, h)
    wx = overlap_matrix(ow, 0.0, w / ow, w)
    return wy @ values @ wx.T


def footprint_matrix(bench: Bench, origin: float, p0: int, p1: int, n_cells: int, step: float) -> np.ndarray:
    """M[c, i]: what a unit response at full-response cell i puts into cell c after sampling (one axis).

    The optics' footprint (pixel width, source extent, diffuser blur) followed
    by :func:`to_response_grid`'s area overlap; valid for matched scaling.

    Parameters
    ----------
    bench : Bench
        The bench: its pixel footprint, kernel step, source extent and the shadow blur
        (``shadow_sigma_um``, scaled to feature elements by the shadow's magnification).
    origin : float
        Sensor pixel (one coordinate) that sees cell 0 of the full response (``response_origin_px``).
    p0, p1 : int
        The sensor pixels sampled along the axis, ``[p0, p1)`` (one axis of the region).
    n_cells : int
        Cells of the full response along the axis (``features + kernel - 1``).
    step : float
        Sensor pixels per cell (:func:`to_response_grid`'s ``step_px``).

    Returns
    -------
    numpy.ndarray
        float64, shape ``(n_cells, n_cells)``: column i is the sampled image of a unit response in cell i.
    """

    from ..optics import axis_weights, shadow_magnification

    psf_cells = bench.shadow_sigma_um / (shadow_magnification(bench.u_mm, bench.z_mm) * bench.feature_pitch_um)
    w = axis_weights(np.arange(p0, p1), n_cells, 1, bench, origin, psf_cells)[0]  # (pixels, cells)
    t = overlap_matrix(n_cells, origin + 0.5 - 0.5 * step - p0, step, p1 - p0)  # (cells, pixels)
    return t @ w
