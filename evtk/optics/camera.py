"""The camera's view of the screen: pose (rotation, tilt, offset, scale), radial lens distortion, vignetting, defocus.

The bench geometry (:mod:`evtk.optics.screen`) puts the response on an
ideal, axis-aligned *nominal* sensor grid. :class:`Camera` says how the real
camera sees that grid: a nominal point ``p`` lands on the sensor at

    ``q = c + d(r) (P(p) - c)``,   ``d(r) = 1 + k1 r^2``,

where ``c`` is the sensor centre, ``P`` a projective map about ``c``
(scale, rotation, tilt, offset) and ``r`` the distance of ``P(p)`` from
``c`` over the half diagonal. Vignetting multiplies the light by
``1 - vignetting (r_q)^2`` (``r_q`` of the sensor point, the corners losing
``vignetting``), and defocus blurs it with a Gaussian of ``defocus_px``.
:class:`CellMap` is the same kind of map from response cells to sensor
pixels, as :func:`evtk.calibrate.calibrate` fits it.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import EvtkError
from .bench import Bench
from .screen import response_origin_px, screen_response

if TYPE_CHECKING:
    import numpy.typing as npt

#: Largest deviation (pixels) over the response at which a map is still taken as a scale and shift.
AXIS_TOLERANCE_PX = 0.05

__all__ = ["Camera", "CellMap", "radial_distort", "radial_undistort", "render_nominal", "footprint_light",
           "footprint_points"]


def radial_distort(xy: npt.ArrayLike, centre: npt.ArrayLike, norm: float, k1: float) -> np.ndarray:
    """``c + (1 + k1 r^2) (p - c)`` with ``r = |p - c| / norm``.

    Parameters
    ----------
    xy : array_like
        Points ``p``, shape ``(..., 2)`` as (x, y), pixels.
    centre : array_like
        Centre of distortion ``c``, shape ``(2,)``, pixels.
    norm : float
        Radius (pixels) at which ``r = 1``: the sensor's half diagonal in evtk's maps.
    k1 : float
        Radial coefficient (barrel < 0 < pincushion).

    Returns
    -------
    numpy.ndarray
        float64, the distorted points, shaped like ``xy``.
    """
    xy = np.asarray(xy, np.float64)
    d = xy - centre
    r2 = np.sum(d * d, axis=-1, keepdims=True) / (norm * norm)
    return centre + d * (1.0 + k1 * r2)


def radial_undistort(
    xy: npt.ArrayLike, centre: npt.ArrayLike, norm: float, k1: float, iterations: int = 20
) -> np.ndarray:
    """The inverse of :func:`radial_distort` (fixed-point iteration; exact to 1e-9 px for |k1| < 0.3).

    Parameters
    ----------
    xy : array_like
        Distorted points, shape ``(..., 2)`` as (x, y), pixels.
    centre : array_like
        Centre of distortion, shape ``(2,)``, pixels.
    norm : float
        Radius (pixels) at which ``r = 1``.
    k1 : float
        Radial coefficient, as given to :func:`radial_distort`.
    iterations : int, optional
        Fixed-point iterations.

    Returns
    -------
    numpy.ndarray
        float64, the undistorted points, shaped like ``xy`` (a copy when ``k1 == 0``).
    """
    xy = np.asarray(xy, np.float64)
    if k1 == 0:
        return xy.copy()
    d = xy - centre
    u = d.copy()
    for _ in range(iterations):
        r2 = np.sum(u * u, axis=-1, keepdims=True) / (norm * norm)
        u = d / (1.0 + k1 * r2)
    return centre + u


def _apply_h(h: npt.ArrayLike, xy: npt.ArrayLike) -> np.ndarray:
    xy = np.asarray(xy, np.float64)
    ph = np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], axis=-1) @ np.asarray(h).T
    return ph[..., :2] / ph[..., 2:3]


@dataclass(frozen=True)
class Camera:
    """Pose and lens of the event camera (defaults: the ideal, nominal view).

    Parameters
    ----------
    rotation_deg : float
        Rotation about the sensor centre, degrees (within +-360).
    tilt : (float, float)
        Projective terms (per 1000 px) of a sensor not parallel to the screen (within +-1).
    offset_px : (float, float)
        Shift on the sensor, pixels.
    scale : float
        Magnification against the nominal one (0.5 to 2).
    k1 : float
        Radial distortion (barrel < 0 < pincushion), at the half diagonal (within +-0.3).
    vignetting : float
        Light lost at the sensor's corners (0 to 1), quadratic in the radius.
    defocus_px : float
        Standard deviation of the defocus blur, pixels (0 to 100).
    mirror : bool
        The view mirrored left to right about the sensor's centre before the
        rotation (a camera that sees the screen from behind, through the
        diffuser); with ``rotation_deg=180`` it is mirrored top to bottom.
        A camera turned upside down is ``rotation_deg=180`` alone.

    Raises
    ------
    EvtkError
        If a value is not finite, of the wrong kind, or outside the ranges above.
    """

    rotation_deg: float = 0.0
    tilt: tuple = (0.0, 0.0)
    offset_px: tuple = (0.0, 0.0)
    scale: float = 1.0
    k1: float = 0.0
    vignetting: float = 0.0
    defocus_px: float = 0.0
    mirror: bool = False

    def __post_init__(self) -> None:
        if not isinstance(self.mirror, bool):
            raise EvtkError(f"camera mirror must be true or false, not {self.mirror!r}")
        for name in ("rotation_deg", "scale", "k1", "vignetting", "defocus_px"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise EvtkError(f"camera {name} must be a finite number, not {v!r}")
            object.__setattr__(self, name, float(v))
        for name in ("tilt", "offset_px"):
            v = tuple(getattr(self, name))
            if len(v) != 2 or not all(isinstance(x, (int, float)) and math.isfinite(x) for x in v):
                raise EvtkError(f"camera {name} must be two finite numbers, not {getattr(self, name)!r}")
            object.__setattr__(self, name, (float(v[0]), float(v[1])))
        if not 0.5 <= self.scale <= 2.0:
            raise EvtkError(f"camera scale must be within 0.5 and 2, not {self.scale}")
        if not (-0.3 < self.k1 < 0.3 and 0 <= self.vignetting < 1 and self.defocus_px >= 0):
            raise EvtkError("camera k1 must be within -0.3 and 0.3, vignetting within 0 and 1, defocus_px >= 0")
        # a view still on the sensor: beyond these the projected region overflows or leaves every sensor behind
        if not (self.defocus_px <= 100 and abs(self.rotation_deg) <= 360 and max(map(abs, self.tilt)) <= 1
                and max(map(abs, self.offset_px)) <= 32767):
            raise EvtkError("camera defocus_px must be at most 100, rotation_deg within +-360, tilt within +-1 "
                            "(per 1000 px) and offset_px within +-32767 px")

    @property
    def is_ideal(self) -> bool:
        """True when every setting is its default (the nominal view)."""
        return self == Camera()

    def to_dict(self) -> dict:
        """The settings as a plain dict (tuples as lists), for TOML/JSON.

        Returns
        -------
        dict
            Field name to value; :meth:`from_dict` reads it back.
        """
        d = dataclasses.asdict(self)
        d["tilt"], d["offset_px"] = list(self.tilt), list(self.offset_px)
        return d

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | Camera) -> Camera:
        """A camera from a dict of settings (missing ones take their defaults), or the camera itself.

        Parameters
        ----------
        d : Mapping or Camera
            Field name to value, as :meth:`to_dict` writes; a :class:`Camera` is returned as it is.

        Returns
        -------
        Camera
            The checked camera.

        Raises
        ------
        EvtkError
            If a key is not a setting or a value is out of range.
        """
        if isinstance(d, Camera):
            return d
        try:
            return cls(**dict(d))
        except TypeError as exc:
            raise EvtkError(f"a camera takes {', '.join(f.name for f in dataclasses.fields(cls))}: {exc}") from None

    def _frame(self, sensor_size: tuple[int, int]) -> tuple[np.ndarray, float]:
        w, h = (float(v) for v in sensor_size)
        centre = np.array([(w - 1) / 2, (h - 1) / 2])
        return centre, 0.5 * math.hypot(w, h)

    def homography(self, sensor_size: tuple[int, int]) -> np.ndarray:
        """The projective part ``P`` (3x3, nominal pixel -> undistorted sensor pixel).

        Parameters
        ----------
        sensor_size : tuple of int
            ``(width, height)`` of the sensor, pixels; rotation, scale and tilt act about its centre.

        Returns
        -------
        numpy.ndarray
            float64, shape ``(3, 3)``, acting on homogeneous ``(x, y, 1)`` columns.
        """
        c, _ = self._frame(sensor_size)
        a = math.radians(self.rotation_deg)
        rs = self.scale * np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
        if self.mirror:  # x -> -x about the centre, then the rotation
            rs = rs @ np.diag([-1.0, 1.0])
        m = np.eye(3)
        m[:2, :2] = rs
        m[:2, 2] = c + np.asarray(self.offset_px) - rs @ c
        tilt = np.eye(3)
        tilt[2, :2] = np.asarray(self.tilt) / 1000.0
        tilt[2, 2] = 1.0 - tilt[2, :2] @ c  # about the centre: the centre stays put
        return m @ tilt

    def to_sensor(self, xy: npt.ArrayLike, sensor_size: tuple[int, int]) -> np.ndarray:
        """Sensor pixels (x, y) where nominal pixels ``xy`` land.

        Parameters
        ----------
        xy : array_like
            Nominal points, shape ``(..., 2)`` as (x, y), pixels.
        sensor_size : tuple of int
            ``(width, height)`` of the sensor, pixels.

        Returns
        -------
        numpy.ndarray
            float64, sensor points shaped like ``xy``.
        """
        c, norm = self._frame(sensor_size)
        return radial_distort(_apply_h(self.homography(sensor_size), xy), c, norm, self.k1)

    def to_nominal(self, xy: npt.ArrayLike, sensor_size: tuple[int, int]) -> np.ndarray:
        """Nominal pixels (x, y) seen at sensor pixels ``xy`` (the inverse of :meth:`to_sensor`).

        Parameters
        ----------
        xy : array_like
            Sensor points, shape ``(..., 2)`` as (x, y), pixels.
        sensor_size : tuple of int
            ``(width, height)`` of the sensor, pixels.

        Returns
        -------
        numpy.ndarray
            float64, nominal points shaped like ``xy``.
        """
        c, norm = self._frame(sensor_size)
        return _apply_h(np.linalg.inv(self.homography(sensor_size)), radial_undistort(xy, c, norm, self.k1))

    def sensor_region(
        self, nominal_region: tuple[int, int, int, int], sensor_size: tuple[int, int]
    ) -> tuple[int, int, int, int]:
        """The sensor pixels ``(x0, x1, y0, y1)`` a nominal region's light can reach (blur included).

        Parameters
        ----------
        nominal_region : tuple of int
            ``(x0, x1, y0, y1)`` on the nominal grid, half-open, pixels.
        sensor_size : tuple of int
            ``(width, height)`` of the sensor, pixels.

        Returns
        -------
        tuple of int
            ``(x0, x1, y0, y1)`` on the sensor, half-open, clipped to it; padded by three defocus
            standard deviations and two pixels.
        """
        x0, x1, y0, y1 = nominal_region
        xs, ys = np.linspace(x0 - 0.5, x1 - 0.5, 9), np.linspace(y0 - 0.5, y1 - 0.5, 9)
        edge = np.concatenate([np.stack([xs, np.full(9, v)], 1) for v in (ys[0], ys[-1])]
                              + [np.stack([np.full(9, v), ys], 1) for v in (xs[0], xs[-1])])
        q = self.to_sensor(edge, sensor_size)
        pad = 3.0 * self.defocus_px + 2.0
        w, h = sensor_size
        return (int(max(0, math.floor(q[:, 0].min() - pad))), int(min(w, math.ceil(q[:, 0].max() + pad) + 1)),
                int(max(0, math.floor(q[:, 1].min() - pad))), int(min(h, math.ceil(q[:, 1].max() + pad) + 1)))

    def view(
        self,
        kernel: npt.ArrayLike,
        features: npt.ArrayLike,
        bench: Bench,
        region: tuple[int, int, int, int],
        supersample: int = 4,
    ) -> np.ndarray:
        """The light (response units) each sensor pixel of ``region`` sees of one displayed pass.

        Each sensor pixel's footprint is sampled at ``supersample`` squared
        points, each mapped back onto the nominal grid, where the screen is
        rendered ``supersample`` times finer (:func:`render_nominal`); their
        mean is the pixel's light, which is then vignetted and blurred by the
        defocus.

        Parameters
        ----------
        kernel : array_like of {0, 1}
            The kernel pattern shown (one pass), 2-D.
        features : array_like of {0, 1}
            The feature pattern shown, 2-D.
        bench : Bench
            The bench; its sensor size is the sensor's.
        region : tuple of int
            ``(x0, x1, y0, y1)`` sensor pixels to compute, half-open.
        supersample : int, optional
            Samples per pixel along each axis.

        Returns
        -------
        numpy.ndarray
            float64, shape ``(y1 - y0, x1 - x0)``, in the units of :func:`~evtk.optics.screen_response`.
        """
        size = (bench.sensor_width, bench.sensor_height)
        x0, x1, y0, y1 = region
        pad = int(math.ceil(3.0 * self.defocus_px)) if self.defocus_px > 0 else 0
        out = footprint_light(kernel, features, bench, (x0 - pad, x1 + pad, y0 - pad, y1 + pad),
                              lambda pts: self.to_nominal(pts, size), supersample)
        yy, xx = np.mgrid[y0 - pad:y1 + pad, x0 - pad:x1 + pad]
        if self.vignetting:
            c, norm = self._frame(size)
            out = out * (1.0 - self.vignetting * ((xx - c[0]) ** 2 + (yy - c[1]) ** 2) / (norm * norm))
        if self.defocus_px > 0:
            from scipy.ndimage import gaussian_filter  # scipy loads where a camera renders, not with the module

            out = gaussian_filter(out, self.defocus_px, mode="nearest")
        return out[pad:pad + (y1 - y0), pad:pad + (x1 - x0)]


def footprint_light(
    kernel: npt.ArrayLike,
    features: npt.ArrayLike,
    bench: Bench,
    region: tuple[int, int, int, int],
    to_nominal: Callable[[np.ndarray], np.ndarray],
    supersample: int = 4,
) -> np.ndarray:
    """The light each sensor pixel of ``region`` collects of one pass, seen through any map.

    Each pixel's footprint is sampled at ``supersample`` squared points,
    ``to_nominal`` takes them (x, y) to the nominal grid of ``bench``, where
    the pass is rendered ``supersample`` times finer (:func:`render_nominal`)
    and looked up bilinearly; the pixel's light is the mean.

    Parameters
    ----------
    kernel : array_like of {0, 1}
        The kernel pattern shown (one pass), 2-D.
    features : array_like of {0, 1}
        The feature pattern shown, 2-D.
    bench : Bench
        The bench whose nominal grid the pass is rendered on.
    region : tuple of int
        ``(x0, x1, y0, y1)`` sensor pixels, half-open.
    to_nominal : callable
        Takes sensor points, shape ``(n, 2)`` as (x, y), to nominal points of the same shape.
    supersample : int, optional
        Samples per pixel along each axis (and the fineness of the rendering).

    Returns
    -------
    numpy.ndarray
        float64, shape ``(y1 - y0, x1 - x0)``, in response units. A view that misses the nominal grid sees only
        the glow.
    """
    x0, x1, y0, y1 = region
    s = int(supersample)
    pts = footprint_points(region, s)
    fine = (to_nominal(pts) + 0.5) * s - 0.5  # nominal pixels on the fine grid
    fw, fh = bench.sensor_width * s, bench.sensor_height * s
    fx0, fx1 = int(max(0, math.floor(fine[:, 0].min()) - 1)), int(min(fw, math.ceil(fine[:, 0].max()) + 2))
    fy0, fy1 = int(max(0, math.floor(fine[:, 1].min()) - 1)), int(min(fh, math.ceil(fine[:, 1].max()) + 2))
    if fx1 <= fx0 or fy1 <= fy0:  # the view misses the nominal grid: only the glow
        light = np.full(pts.shape[0], float(render_nominal(kernel, features, bench, (0, 1, 0, 1), s).mean()))
    else:
        from scipy.ndimage import map_coordinates

        img = render_nominal(kernel, features, bench, (fx0, fx1, fy0, fy1), s)
        light = map_coordinates(img, [fine[:, 1] - fy0, fine[:, 0] - fx0], order=1, mode="nearest")
    return light.reshape((y1 - y0, x1 - x0, s * s)).mean(axis=-1)


def footprint_points(region: tuple[int, int, int, int], supersample: int) -> np.ndarray:
    """Sensor points (x, y) sampling each pixel of a region on a ``supersample`` squared grid over its footprint.

    Parameters
    ----------
    region : tuple of int
        ``(x0, x1, y0, y1)`` sensor pixels, half-open.
    supersample : int
        Samples per pixel along each axis, at the centres of a regular sub-grid.

    Returns
    -------
    numpy.ndarray
        float64, shape ``((y1 - y0) * (x1 - x0) * supersample**2, 2)``, pixel by pixel in row-major order.
    """
    x0, x1, y0, y1 = (int(v) for v in region)
    s = int(supersample)
    yy, xx = np.mgrid[y0:y1, x0:x1]
    sub = (np.arange(s) + 0.5) / s - 0.5
    sy, sx = np.meshgrid(sub, sub, indexing="ij")
    return np.stack([(xx[..., None, None] + sx).ravel(), (yy[..., None, None] + sy).ravel()], 1).astype(np.float64)


def render_nominal(
    kernel: npt.ArrayLike,
    features: npt.ArrayLike,
    bench: Bench,
    fine_region: tuple[int, int, int, int],
    supersample: int,
) -> np.ndarray:
    """:func:`~evtk.optics.screen_response` on a nominal sensor ``supersample`` times finer.

    The fine sensor keeps the response origin; its pixels are a ``supersample``-th of the size.

    Parameters
    ----------
    kernel : array_like of {0, 1}
        The kernel pattern shown (one pass), 2-D.
    features : array_like of {0, 1}
        The feature pattern shown, 2-D.
    bench : Bench
        The bench at nominal resolution.
    fine_region : tuple of int
        ``(x0, x1, y0, y1)`` in fine pixels, half-open.
    supersample : int
        How many times finer.

    Returns
    -------
    numpy.ndarray
        float64, shape ``(y1 - y0, x1 - x0)`` of ``fine_region``, in response units.
    """
    s = int(supersample)
    ox, oy = response_origin_px(bench, np.shape(kernel), np.shape(features))
    fine = bench.replace(sensor_pitch_um=bench.sensor_pitch_um / s, sensor_width=bench.sensor_width * s,
                         sensor_height=bench.sensor_height * s, origin_px=((ox + 0.5) * s - 0.5, (oy + 0.5) * s - 0.5))
    return screen_response(kernel, features, fine, fine_region)


@dataclass(frozen=True)
class CellMap:
    """Response cells (column, row) to sensor pixels (x, y): a projective map then radial distortion.

    The distortion acts about the sensor centre, normalised by its half diagonal (as :class:`Camera`'s);
    :func:`evtk.calibrate.calibrate` fits it. The camera's pose and lens in one.

    Parameters
    ----------
    matrix : numpy.ndarray
        float64, shape ``(3, 3)``: homogeneous cell ``(column, row, 1)`` to undistorted sensor pixel.
    k1 : float
        Radial distortion coefficient at the half diagonal.
    sensor_size : tuple of int
        ``(width, height)`` of the sensor, pixels.
    """

    matrix: np.ndarray
    k1: float
    sensor_size: tuple

    @classmethod
    def scale_shift(
        cls, origin_px: tuple[float, float], step_px: float, sensor_size: tuple[int, int]
    ) -> CellMap:
        """The map of a square view: cell ``(j, i)`` on pixel ``origin_px + (j, i) * step_px``.

        Parameters
        ----------
        origin_px : tuple of float
            Sensor pixel ``(x, y)`` of cell (0, 0).
        step_px : float
            Pixels per cell along both axes.
        sensor_size : tuple of int
            ``(width, height)`` of the sensor, pixels.

        Returns
        -------
        CellMap
            The map, without distortion.
        """
        ox, oy = (float(v) for v in origin_px)
        step = float(step_px)
        return cls(np.array([[step, 0.0, ox], [0.0, step, oy], [0.0, 0.0, 1.0]]), 0.0, tuple(sensor_size))

    def _frame(self) -> tuple[np.ndarray, float]:
        w, h = (float(v) for v in self.sensor_size)
        return np.array([(w - 1) / 2, (h - 1) / 2]), 0.5 * math.hypot(w, h)

    def to_pixels(self, cells_xy: npt.ArrayLike) -> np.ndarray:
        """Sensor pixels (x, y) of response cells (column, row).

        Parameters
        ----------
        cells_xy : array_like
            Cells as (column, row), shape ``(2,)`` or ``(n, 2)``; fractional cells allowed.

        Returns
        -------
        numpy.ndarray
            float64, shape ``(n, 2)`` (a single cell comes back as one row).
        """
        c, norm = self._frame()
        return radial_distort(_apply_h(self.matrix, np.atleast_2d(cells_xy)), c, norm, self.k1)

    def to_cells(self, pixels_xy: npt.ArrayLike) -> np.ndarray:
        """Response cells (column, row) seen at sensor pixels (x, y): the inverse of :meth:`to_pixels`.

        Parameters
        ----------
        pixels_xy : array_like
            Sensor points as (x, y), shape ``(2,)`` or ``(n, 2)``.

        Returns
        -------
        numpy.ndarray
            float64, shape ``(n, 2)``, fractional cells.
        """
        c, norm = self._frame()
        return _apply_h(np.linalg.inv(self.matrix), radial_undistort(np.atleast_2d(pixels_xy), c, norm, self.k1))

    def axis_aligned(
        self, shape: tuple[int, int], tolerance_px: float = AXIS_TOLERANCE_PX
    ) -> tuple[tuple[float, float], float] | None:
        """The upright scale-and-shift map that matches this one over a response, if any.

        One step for both axes and an origin per axis are fitted by least squares to the map's pixels of
        every cell of the response. A negative step (a view turned half a turn) is not upright: callers take
        the result for an origin and a pixel pitch along the sensor's axes, so such a map is seen through.

        Parameters
        ----------
        shape : tuple of int
            ``(rows, cols)`` of the response, cells.
        tolerance_px : float, optional
            Largest deviation, pixels, at which the fit still counts as matching.

        Returns
        -------
        tuple or None
            ``((origin_x_px, origin_y_px), step_px)`` with ``step_px > 0``, as :meth:`scale_shift` takes them,
            or None when no upright scale and shift matches (rotation, a half turn, tilt, distortion).
        """
        rows, cols = (int(v) for v in shape)
        jj, ii = np.meshgrid(np.arange(cols, dtype=np.float64), np.arange(rows, dtype=np.float64))
        cells = np.stack([jj.ravel(), ii.ravel()], 1)
        px = self.to_pixels(cells)
        a = np.stack([np.ones(len(cells)), cells[:, 0], cells[:, 1]], 1)
        # one step for both axes, an origin per axis: x = ox + s j, y = oy + s i
        lhs = np.zeros((2 * len(cells), 3))
        lhs[0::2, 0], lhs[1::2, 1] = 1.0, 1.0
        lhs[0::2, 2], lhs[1::2, 2] = a[:, 1], a[:, 2]
        sol, *_ = np.linalg.lstsq(lhs, px.ravel(), rcond=None)
        if sol[2] <= 0 or np.max(np.abs(lhs @ sol - px.ravel())) > tolerance_px:
            return None
        return (float(sol[0]), float(sol[1])), float(sol[2])
