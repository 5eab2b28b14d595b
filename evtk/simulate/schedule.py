"""What a run shows and when: patterns, their +/- passes, the capture schedule, flat fields and calibration dots."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import EvtkError

__all__ = [
    "split_passes", "Schedule", "CaptureCounts", "load_patterns", "dot_grid", "FLAT_ID",
    "DOTS_ID", "LEVEL_ID", "level_kernel", "level_steps", "default_features", "METADATA_KEY",
]


#: Key of the simulation record in a recording's evtk metadata.
METADATA_KEY = "simulation"


_T_LIMIT = np.iinfo(np.int64).max



def _as_patterns(name, a):
    """A stack (n, h, w) of patterns with values in {-1, 0, 1}."""
    a = np.asarray(a)
    if a.dtype == bool:
        a = a.astype(np.int8)
    if a.ndim == 2:
        a = a[None]
    if a.ndim != 3 or 0 in a.shape:
        raise EvtkError(f"{name} must be a 2-D pattern or a stack of them (n, h, w), got shape {a.shape}")
    if not np.issubdtype(a.dtype, np.number):
        raise EvtkError(f"{name} must be numeric, got {a.dtype}")
    if not np.all(np.isfinite(a)) or not np.all((a == -1) | (a == 0) | (a == 1)):
        raise EvtkError(f"{name} must hold only -1, 0 and 1 (binary DMD patterns, optionally signed)")
    return a.astype(np.int8)


def split_passes(kernel, features):
    """Non-negative passes of a signed (kernel, features) pair.

    Returns a list of ``(kernel_sign, features_sign, kernel_pass, features_pass)``
    with passes in {0, 1}; pairs where either pass is all zero are left out.
    The signed response is ``sum(ks * fs * response(kp, fp))``.

    Examples
    --------
    >>> k = np.array([[1, -1]]); f = np.array([[1, 1, 0]])
    >>> [(ks, fs) for ks, fs, _, _ in split_passes(k, f)]
    [(1, 1), (-1, 1)]
    """
    out = []
    for ks in (1, -1):
        kp = _pass(kernel, ks)
        if not kp.any():
            continue
        for fs in (1, -1):
            fp = _pass(features, fs)
            if fp.any():
                out.append((ks, fs, kp, fp))
    return out


def _pass(pattern, sign):
    """The 0/1 pattern a DMD shows for one sign of a signed pattern."""
    return (np.asarray(pattern) * sign > 0).astype(np.int8)


@dataclass
class Schedule:
    """One row per capture: which patterns, which pass, when (us)."""

    capture: np.ndarray
    kernel_id: np.ndarray
    features_id: np.ndarray
    kernel_sign: np.ndarray
    features_sign: np.ndarray
    t_on_us: np.ndarray
    t_off_us: np.ndarray
    repeat: np.ndarray
    #: mirrors on in the kernel of a level capture (:data:`LEVEL_ID`), 0 for the others
    level: np.ndarray | None = None

    _COLUMNS = ("capture", "kernel_id", "features_id", "kernel_sign", "features_sign", "t_on_us", "t_off_us",
                "repeat", "level")
    _OPTIONAL = ("level",)  # columns older schedules do not have (read as zeros)

    def __post_init__(self):
        if self.level is None:
            self.level = np.zeros(np.shape(self.capture), np.int64)

    def __len__(self):
        return int(self.capture.size)

    def to_dict(self) -> dict:
        return {c: getattr(self, c).tolist() for c in self._COLUMNS}

    def take(self, rows) -> Schedule:
        """The schedule of the captures ``rows`` (indices or a boolean mask), in that order."""
        return Schedule(**{c: getattr(self, c)[rows] for c in self._COLUMNS})

    @classmethod
    def from_dict(cls, d: dict) -> Schedule:
        try:
            cols = {c: np.asarray(d[c], dtype=np.int64) for c in cls._COLUMNS if c in d or c not in cls._OPTIONAL}
        except (KeyError, TypeError, ValueError) as exc:
            raise EvtkError(f"capture schedule is malformed: {exc}") from None
        n = {v.shape for v in cols.values()}
        if len(n) != 1 or next(iter(n)).__len__() != 1:
            raise EvtkError("capture schedule columns must be 1-D and of equal length")
        return cls(**cols)


@dataclass
class CaptureCounts:
    """Per-capture event counts inside each capture window, over a sensor region.

    ``on`` and ``off`` have shape (n_captures, y1 - y0, x1 - x0); ``region`` is
    (x0, x1, y0, y1) on the sensor.
    """

    on: np.ndarray
    off: np.ndarray
    region: tuple
    schedule: Schedule


def _int_param(name, v, low):
    if isinstance(v, bool) or not isinstance(v, (int, np.integer, float)) or (isinstance(v, float) and not v.is_integer()):
        raise EvtkError(f"{name} must be a whole number, not {v!r}")
    v = int(v)
    if v < low:
        raise EvtkError(f"{name} must be at least {low}, not {v}")
    return v


def default_features(side=16):
    """The embedded default input: scikit-image's camera picture, ``side`` x ``side``, binarised at its mean (0/1)."""
    from skimage import data, transform

    img = transform.resize(data.camera().astype(np.float64), (side, side), anti_aliasing=True)
    return (img > img.mean()).astype(np.int8)


#: ``kernel_id``/``features_id`` of a flat-field capture (every mirror on) in a schedule.
FLAT_ID = -1


#: ``kernel_id``/``features_id`` of a calibration capture (kernel all on, a dot grid of features).
DOTS_ID = -2


#: ``kernel_id``/``features_id`` of a level capture: features all on, ``level`` kernel mirrors on
#: (:func:`level_kernel`), so the flat response's interior is ``level`` units of light.
LEVEL_ID = -3


def level_kernel(shape, on):
    """The kernel of a level capture: its first ``on`` elements in row-major order on, the rest off (int8).

    Under features that are all on, every cell of the response's interior
    sees exactly ``on`` units of light, whichever elements are on: a
    staircase of these captures measures the pixels' transfer from light to
    counts, to which :func:`evtk.reconstruct.fit_pixel_model` fits the pixel model.

    Examples
    --------
    >>> level_kernel((2, 3), 4).tolist()
    [[1, 1, 1], [1, 0, 0]]
    """
    h, w = (int(v) for v in shape)
    on = int(on)
    if not 1 <= on <= h * w:
        raise EvtkError(f"a level capture turns on 1 to {h * w} kernel elements, not {on}")
    out = np.zeros(h * w, np.int8)
    out[:on] = 1
    return out.reshape(h, w)


def level_steps(n_elements, levels):
    """The ``levels`` kernel element counts a staircase shows: evenly spread from 1 to ``n_elements``, distinct."""
    n, k = int(n_elements), int(levels)
    if k <= 0:
        return np.zeros(0, np.int64)
    return np.unique(np.round(np.linspace(1, n, min(k, n))).astype(np.int64))


def dot_grid(shape, spacing, marker=True):
    """The calibration pattern: 1 at every ``spacing``-th features element along each axis, starting
    ``spacing // 2`` in, 0 elsewhere (int8).

    With ``marker`` (default) one dot is left out when the grid has at least 10 dots
    (:data:`DOT_MARKER_MIN`) and 3 rows and 4 columns (or 4 and 3): the second of the first row (on a taller
    grid the first of the second row). That place lies on no axis of the grid's symmetry, so no rotation or
    reflection maps the gap onto itself and :func:`evtk.calibrate.calibrate` tells a mirrored or rotated camera
    apart from an upright one; the corners stay, for the map's extrapolation. ``marker=False`` gives the whole
    grid.

    Examples
    --------
    >>> dot_grid((6, 6), 3).nonzero()
    (array([1, 1, 4, 4]), array([1, 4, 1, 4]))
    >>> int(dot_grid((16, 16), 4).sum()), int(dot_grid((16, 16), 4, marker=False).sum())
    (15, 16)
    """
    h, w = (int(v) for v in shape)
    s = int(spacing)
    out = np.zeros((h, w), np.int8)
    out[s // 2::s, s // 2::s] = 1
    rows, cols = len(range(s // 2, h, s)), len(range(s // 2, w, s))
    if marker and rows * cols >= DOT_MARKER_MIN:
        r0 = c0 = s // 2
        if cols >= 4 and rows >= 3:  # grid place (0, 1): on no axis of symmetry, and not a corner
            out[r0, c0 + s] = 0
        elif rows >= 4 and cols >= 3:  # a tall grid: (1, 0)
            out[r0 + s, c0] = 0
    return out


#: Fewest dots a grid needs before :func:`dot_grid` leaves one out as an orientation marker.
DOT_MARKER_MIN = 10


def load_patterns(path_or_bits, name, side=None):
    """Patterns from a ``.npy`` file, an image (PNG etc.) or a bit string like ``101010101``.

    Images are binarised at half their range; a bit string fills a square
    pattern row by row.
    """
    s = str(path_or_bits)
    if set(s) <= {"0", "1"} and s:
        n = len(s)
        k = int(round(math.sqrt(n)))
        if k * k != n:
            raise EvtkError(f"{name} bits {s!r}: {n} bits do not make a square pattern")
        return np.array([int(c) for c in s], dtype=np.int8).reshape(k, k)
    from .._loaders import read_image, read_npy

    if s.lower().endswith(".npy"):
        return read_npy(s, name)
    img = np.asarray(read_image(s, f"{name} image"), dtype=np.float64)
    if img.ndim == 3:
        img = img[..., :3].mean(axis=2)
    lo, hi = float(img.min()), float(img.max())
    return (img > (lo + hi) / 2).astype(np.int8) if hi > lo else np.zeros(img.shape, np.int8)
