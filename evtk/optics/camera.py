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
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter, map_coordinates

from ..errors import EvtkError
from .screen import response_origin_px, screen_response

#: Largest deviation (pixels) over the response at which a map is still taken as a scale and shift.
AXIS_TOLERANCE_PX = 0.05

__all__ = ["Camera", "CellMap", "radial_distort", "radial_undistort", "render_nominal", "footprint_light",
           "footprint_points"]


def radial_distort(xy, centre, norm, k1):
    """``c + (1 + k1 r^2) (p - c)`` with ``r = |p - c| / norm``."""
    xy = np.asarray(xy, np.float64)
    d = xy - centre
    r2 = np.sum(d * d, axis=-1, keepdims=True) / (norm * norm)
    return centre + d * (1.0 + k1 * r2)


def radial_undistort(xy, centre, norm, k1, iterations=20):
    """The inverse of :func:`radial_distort` (fixed-point iteration; exact to 1e-9 px for |k1| < 0.3)."""
    xy = np.asarray(xy, np.float64)
    if k1 == 0:
        return xy.copy()
    d = xy - centre
    u = d.copy()
    for _ in range(iterations):
        r2 = np.sum(u * u, axis=-1, keepdims=True) / (norm * norm)
        u = d / (1.0 + k1 * r2)
    return centre + u


def _apply_h(h, xy):
    xy = np.asarray(xy, np.float64)
    ph = np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], axis=-1) @ np.asarray(h).T
    return ph[..., :2] / ph[..., 2:3]


@dataclass(frozen=True)
class Camera:
    """Pose and lens of the event camera (defaults: the ideal, nominal view).

    Attributes
    ----------
    rotation_deg : float
        Rotation about the sensor centre.
    tilt : (float, float)
        Projective terms (per 1000 px) of a sensor not parallel to the screen.
    offset_px : (float, float)
        Shift on the sensor.
    scale : float
        Magnification against the nominal one.
    k1 : float
        Radial distortion (barrel < 0 < pincushion), at the half diagonal.
    vignetting : float
        Light lost at the sensor's corners (0 to 1), quadratic in the radius.
    defocus_px : float
        Standard deviation of the defocus blur.
    mirror : bool
        The view mirrored left to right about the sensor's centre before the
        rotation (a camera that sees the screen from behind, through the
        diffuser); with ``rotation_deg=180`` it is mirrored top to bottom.
        A camera turned upside down is ``rotation_deg=180`` alone.
    """

    rotation_deg: float = 0.0
    tilt: tuple = (0.0, 0.0)
    offset_px: tuple = (0.0, 0.0)
    scale: float = 1.0
    k1: float = 0.0
    vignetting: float = 0.0
    defocus_px: float = 0.0
    mirror: bool = False

    def __post_init__(self):
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
        return self == Camera()

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["tilt"], d["offset_px"] = list(self.tilt), list(self.offset_px)
        return d

    @classmethod
    def from_dict(cls, d) -> Camera:
        if isinstance(d, cls):
            return d
        try:
            return cls(**dict(d))
        except TypeError as exc:
            raise EvtkError(f"a camera takes {', '.join(f.name for f in dataclasses.fields(cls))}: {exc}") from None

    def _frame(self, sensor_size):
        w, h = (float(v) for v in sensor_size)
        centre = np.array([(w - 1) / 2, (h - 1) / 2])
        return centre, 0.5 * math.hypot(w, h)

    def homography(self, sensor_size) -> np.ndarray:
        """The projective part ``P`` (3x3, nominal pixel -> undistorted sensor pixel)."""
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

    def to_sensor(self, xy, sensor_size):
        """Sensor pixels (x, y) where nominal pixels ``xy`` land."""
        c, norm = self._frame(sensor_size)
        return radial_distort(_apply_h(self.homography(sensor_size), xy), c, norm, self.k1)

    def to_nominal(self, xy, sensor_size):
        """Nominal pixels (x, y) seen at sensor pixels ``xy`` (the inverse of :meth:`to_sensor`)."""
        c, norm = self._frame(sensor_size)
        return _apply_h(np.linalg.inv(self.homography(sensor_size)), radial_undistort(xy, c, norm, self.k1))

    def sensor_region(self, nominal_region, sensor_size):
        """The sensor pixels ``(x0, x1, y0, y1)`` a nominal region's light can reach (blur included)."""
        x0, x1, y0, y1 = nominal_region
        xs, ys = np.linspace(x0 - 0.5, x1 - 0.5, 9), np.linspace(y0 - 0.5, y1 - 0.5, 9)
        edge = np.concatenate([np.stack([xs, np.full(9, v)], 1) for v in (ys[0], ys[-1])]
                              + [np.stack([np.full(9, v), ys], 1) for v in (xs[0], xs[-1])])
        q = self.to_sensor(edge, sensor_size)
        pad = 3.0 * self.defocus_px + 2.0
        w, h = sensor_size
        return (int(max(0, math.floor(q[:, 0].min() - pad))), int(min(w, math.ceil(q[:, 0].max() + pad) + 1)),
                int(max(0, math.floor(q[:, 1].min() - pad))), int(min(h, math.ceil(q[:, 1].max() + pad) + 1)))

    def view(self, kernel, features, bench, region, supersample=4):
        """The light (response units) each sensor pixel of ``region`` sees of one displayed pass.

        Each sensor pixel's footprint is sampled at ``supersample`` squared
        points, each mapped back onto the nominal grid, where the screen is
        rendered ``supersample`` times finer (:func:`render_nominal`); their
        mean is the pixel's light, which is then vignetted and blurred by the
        defocus.
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
            out = gaussian_filter(out, self.defocus_px, mode="nearest")
        return out[pad:pad + (y1 - y0), pad:pad + (x1 - x0)]


def footprint_light(kernel, features, bench, region, to_nominal, supersample=4):
    """The light each sensor pixel of ``region`` collects of one pass, seen through any map.

    Each pixel's footprint is sampled at ``supersample`` squared points,
    ``to_nominal`` takes them (x, y) to the nominal grid of ``bench``, where
    the pass is rendered ``supersample`` times finer (:func:`render_nominal`)
    and looked up bilinearly; the pixel's light is the mean.
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
        img = render_nominal(kernel, features, bench, (fx0, fx1, fy0, fy1), s)
        light = map_coordinates(img, [fine[:, 1] - fy0, fine[:, 0] - fx0], order=1, mode="nearest")
    return light.reshape((y1 - y0, x1 - x0, s * s)).mean(axis=-1)


def footprint_points(region, supersample):
    """Sensor points (x, y) sampling each pixel of ``region`` (x0, x1, y0, y1) on a ``supersample`` squared grid
    over its footprint: ``((y1 - y0) * (x1 - x0) * supersample**2, 2)``, pixel by pixel in row-major order."""
    x0, x1, y0, y1 = (int(v) for v in region)
    s = int(supersample)
    yy, xx = np.mgrid[y0:y1, x0:x1]
    sub = (np.arange(s) + 0.5) / s - 0.5
    sy, sx = np.meshgrid(sub, sub, indexing="ij")
    return np.stack([(xx[..., None, None] + sx).ravel(), (yy[..., None, None] + sy).ravel()], 1).astype(np.float64)


def render_nominal(kernel, features, bench, fine_region, supersample):
    """:func:`~evtk.optics.screen_response` on a nominal sensor ``supersample`` times finer (the same response
    origin, pixels a ``supersample``-th of the size); ``fine_region`` in fine pixels."""
    s = int(supersample)
    ox, oy = response_origin_px(bench, np.shape(kernel), np.shape(features))
    fine = bench.replace(sensor_pitch_um=bench.sensor_pitch_um / s, sensor_width=bench.sensor_width * s,
                         sensor_height=bench.sensor_height * s, origin_px=((ox + 0.5) * s - 0.5, (oy + 0.5) * s - 0.5))
    return screen_response(kernel, features, fine, fine_region)


@dataclass(frozen=True)
class CellMap:
    """Response cells (column, row) to sensor pixels (x, y): a projective map then radial distortion about the
    sensor centre (what :func:`evtk.calibrate.calibrate` fits; the camera's pose and lens in one)."""

    matrix: np.ndarray
    k1: float
    sensor_size: tuple

    @classmethod
    def scale_shift(cls, origin_px, step_px, sensor_size) -> CellMap:
        """The map of a square view: cell ``(j, i)`` on pixel ``origin_px + (j, i) * step_px``."""
        ox, oy = (float(v) for v in origin_px)
        step = float(step_px)
        return cls(np.array([[step, 0.0, ox], [0.0, step, oy], [0.0, 0.0, 1.0]]), 0.0, tuple(sensor_size))

    def _frame(self):
        w, h = (float(v) for v in self.sensor_size)
        return np.array([(w - 1) / 2, (h - 1) / 2]), 0.5 * math.hypot(w, h)

    def to_pixels(self, cells_xy):
        c, norm = self._frame()
        return radial_distort(_apply_h(self.matrix, np.atleast_2d(cells_xy)), c, norm, self.k1)

    def to_cells(self, pixels_xy):
        c, norm = self._frame()
        return _apply_h(np.linalg.inv(self.matrix), radial_undistort(np.atleast_2d(pixels_xy), c, norm, self.k1))

    def axis_aligned(self, shape, tolerance_px=AXIS_TOLERANCE_PX):
        """``(origin_px, step_px)`` of the scale-and-shift map that matches this one within ``tolerance_px``
        over a response of ``shape`` (rows, cols) cells, or None when none does (rotation, tilt, distortion)."""
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
        if np.max(np.abs(lhs @ sol - px.ravel())) > tolerance_px:
            return None
        return (float(sol[0]), float(sol[1])), float(sol[2])
