"""What a run shows and when: patterns, their +/- passes, the capture schedule, flat fields and calibration dots."""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from ..errors import EvtkError
from ..settings import (
    MAX_COUNT,
    MAX_SCHEDULE_BYTES,
    MAX_SETTINGS_BYTES,
    MAX_SIDE,
    MAX_US,
    Spec,
    check_array,
    check_table,
    check_value,
    read_table,
)
from . import METADATA_KEY  # (defined in the package: a recording's route is known without this module)

if TYPE_CHECKING:
    import numpy.typing as npt

    from .core import Plan

__all__ = [
    "split_passes", "Schedule", "CaptureCounts", "load_patterns", "dot_grid", "FLAT_ID",
    "DOTS_ID", "LEVEL_ID", "level_kernel", "level_steps", "default_features", "METADATA_KEY", "check_schedule",
    "check_patterns", "read_schedule", "SCHEDULE_SPECS", "sign_pass",
]


_T_LIMIT = np.iinfo(np.int64).max



def split_passes(kernel: npt.ArrayLike, features: npt.ArrayLike) -> list[tuple[int, int, np.ndarray, np.ndarray]]:
    """Non-negative passes of a signed (kernel, features) pair.

    Parameters
    ----------
    kernel, features : array_like of -1, 0, 1
        The signed patterns.

    Returns
    -------
    list of tuple
        ``(kernel_sign, features_sign, kernel_pass, features_pass)`` with passes in {0, 1}; pairs where either
        pass is all zero are left out. The signed response is ``sum(ks * fs * response(kp, fp))``.

    Examples
    --------
    >>> k = np.array([[1, -1]]); f = np.array([[1, 1, 0]])
    >>> [(ks, fs) for ks, fs, _, _ in split_passes(k, f)]
    [(1, 1), (-1, 1)]
    """
    out = []
    for ks in (1, -1):
        kp = sign_pass(kernel, ks)
        if not kp.any():
            continue
        for fs in (1, -1):
            fp = sign_pass(features, fs)
            if fp.any():
                out.append((ks, fs, kp, fp))
    return out


def sign_pass(pattern: npt.ArrayLike, sign: int) -> np.ndarray:
    """The 0/1 pattern a DMD shows for one sign of a signed pattern.

    Parameters
    ----------
    pattern : array_like of -1, 0, 1
        The signed pattern.
    sign : {1, -1}
        The pass: the elements equal to ``sign`` are on.

    Returns
    -------
    ndarray of int8
        1 where ``pattern * sign > 0``, else 0.
    """
    return (np.asarray(pattern) * sign > 0).astype(np.int8)


@dataclass
class Schedule:
    """One row per capture: which patterns, which pass, when (µs).

    Parameters
    ----------
    capture : ndarray of int
        Capture numbers 0, 1, 2, ...
    kernel_id, features_id : ndarray of int
        The patterns each capture shows (or a setup capture's :data:`FLAT_ID`, :data:`DOTS_ID`, :data:`LEVEL_ID`).
    kernel_sign, features_sign : ndarray of int
        The pass of each pattern, +1 or -1.
    t_on_us, t_off_us : ndarray of int
        When the patterns appear and go (µs).
    repeat : ndarray of int
        Which repeat of its pair each capture is.
    level : ndarray of int, optional
        Mirrors on in the kernel of a level capture, 0 for the others (zeros when None).
    """

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
        """The schedule's dict form, column name to a list of whole numbers (what a record stores).

        Returns
        -------
        dict
            One list per column.
        """
        return {c: getattr(self, c).tolist() for c in self._COLUMNS}

    def take(self, rows: npt.ArrayLike) -> Schedule:
        """The schedule of some captures, in the order given.

        Parameters
        ----------
        rows : array_like
            Capture indices, or a boolean mask over the captures.

        Returns
        -------
        Schedule
            Their rows (their capture numbers kept).
        """
        return Schedule(**{c: getattr(self, c)[rows] for c in self._COLUMNS})

    @classmethod
    def from_dict(cls, d: dict, where: str = "the capture schedule", n_kernels: int | None = None,
                  n_features: int | None = None, kernel_elements: int | None = None) -> Schedule:
        """The schedule of its dict form (:meth:`to_dict`), every column checked (:func:`check_schedule`).

        Parameters
        ----------
        d : dict
            Column name to a list of whole numbers, one per capture.
        where : str
            The file or record it was read from, for messages.
        n_kernels, n_features, kernel_elements : int, optional
            Patterns the run holds and elements of one kernel: the ids and
            levels the captures may name (unchecked when None).

        Returns
        -------
        Schedule
        """
        if not isinstance(d, dict):
            raise EvtkError(f"{where}: the capture schedule must be a table of columns")
        missing = [c for c in cls._COLUMNS if c not in d and c not in cls._OPTIONAL]
        if missing:
            raise EvtkError(f"{where}: the capture schedule lacks {', '.join(missing)}")
        cols = {c: check_array(where, c, d[c], 1, -_T_LIMIT, _T_LIMIT, max_elements=MAX_COUNT)
                for c in cls._COLUMNS if c in d}
        if len({v.shape for v in cols.values()}) != 1:
            raise EvtkError(f"{where}: the capture schedule's columns must be of equal length")
        sched = cls(**cols)
        check_schedule(where, sched, n_kernels, n_features, kernel_elements)
        return sched


def check_schedule(where: str, s: Schedule, n_kernels: int | None = None, n_features: int | None = None,
                   kernel_elements: int | None = None) -> None:
    """Raise :class:`~evtk.EvtkError` naming the first capture of ``s`` that no run of evtk could have.

    Capture numbers 0, 1, 2, ... in order; times within the int64 range,
    each window at least 1 µs long and after the one before it; ids of
    patterns the run holds (or a setup capture's :data:`FLAT_ID`,
    :data:`DOTS_ID`, :data:`LEVEL_ID` in both); signs +1 or -1 (+1 for setup
    captures); repeats 0 or more; a level from 1 to ``kernel_elements`` on a
    level capture and 0 elsewhere.

    Parameters
    ----------
    where : str
        The file or record, for messages.
    s : Schedule
        The schedule.
    n_kernels, n_features, kernel_elements : int, optional
        What the run holds (unchecked when None).
    """
    n = len(s)
    if n == 0:
        raise EvtkError(f"{where}: the capture schedule holds no capture")

    def first(bad, what):
        i = int(np.flatnonzero(bad)[0])
        raise EvtkError(f"{where}: capture {i}: {what}")

    if np.any(s.capture != np.arange(n)):
        first(s.capture != np.arange(n), f"capture = {int(s.capture[np.flatnonzero(s.capture != np.arange(n))[0]])}"
              "; captures are numbered 0, 1, 2, ... in order")
    if np.any(s.t_off_us <= s.t_on_us):
        first(s.t_off_us <= s.t_on_us, "t_off_us must come after t_on_us")
    if n > 1 and np.any(s.t_on_us[1:] < s.t_off_us[:-1]):
        first(np.r_[False, s.t_on_us[1:] < s.t_off_us[:-1]], "t_on_us comes before the previous capture's t_off_us")
    for col, count in (("kernel_id", n_kernels), ("features_id", n_features)):
        ids = getattr(s, col)
        bad = ~np.isin(ids, _SETUP_IDS) & ((ids < 0) | (ids >= (count if count is not None else _T_LIMIT)))
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            held = f"ids 0 to {count - 1}" if count is not None else "ids from 0"
            raise EvtkError(f"{where}: capture {i}: {col} = {int(ids[i])} names no pattern; the run holds "
                            f"{held}, or -1, -2, -3 for setup captures")
    setup = np.isin(s.kernel_id, _SETUP_IDS)
    if np.any(setup != np.isin(s.features_id, _SETUP_IDS)) or np.any(setup & (s.kernel_id != s.features_id)):
        first((setup != np.isin(s.features_id, _SETUP_IDS)) | (setup & (s.kernel_id != s.features_id)),
              "a flat-field (-1), dot (-2) or level (-3) capture has that id as both kernel_id and features_id")
    for col in ("kernel_sign", "features_sign"):
        sign = getattr(s, col)
        if np.any((sign != 1) & (sign != -1)) or np.any(setup & (sign != 1)):
            first((sign != 1) & (sign != -1) | (setup & (sign != 1)), f"{col} must be 1 or -1 (1 for setup captures)")
    if np.any(s.repeat < 0) or np.any(s.repeat > MAX_COUNT):
        first((s.repeat < 0) | (s.repeat > MAX_COUNT), f"repeat must be from 0 to {MAX_COUNT}")
    is_level = s.kernel_id == LEVEL_ID
    top: int = kernel_elements if kernel_elements is not None else MAX_SIDE ** 2
    level = s.level if s.level is not None else np.zeros(len(s.kernel_id), np.int64)
    if np.any(is_level & ((level < 1) | (level > top))) or np.any(~is_level & (level != 0)):
        first(is_level & ((level < 1) | (level > top)) | (~is_level & (level != 0)),
              f"level must be from 1 to {top} (kernel elements on) on a level capture and 0 elsewhere")


#: What each top-level number of a ``schedule.json`` may be.
SCHEDULE_SPECS = {
    "window_us": Spec("int", 1, MAX_US, unit="µs"),
    "settle_us": Spec("int", 1, MAX_US, unit="µs"),
    "start_us": Spec("int", -MAX_US, MAX_US, unit="µs"),
    "repeat": Spec("int", 0, MAX_COUNT),
    "flat_field": Spec("int", 0, MAX_COUNT),
}
#: What the ``calibration`` table of a ``schedule.json`` may hold.
SCHEDULE_CALIBRATION_SPECS = {
    "captures": Spec("int", 0, MAX_COUNT),
    "dot_spacing": Spec("int", 2, MAX_SIDE, unit="features elements between dots"),
    "levels": Spec("int", 0, MAX_COUNT),
}


def check_patterns(where: str, key: str, value: Any) -> np.ndarray:
    """A stack (n, h, w) of patterns, -1, 0 or 1, read from a settings file or record.

    Parameters
    ----------
    where, key : str
        File and setting, for messages.
    value : list or ndarray
        What it holds.

    Returns
    -------
    ndarray
        int64 (n, h, w).
    """
    a = check_array(where, key, value, 3, -1, 1, max_elements=MAX_SETTINGS_BYTES)
    if a.shape[1] > MAX_SIDE or a.shape[2] > MAX_SIDE:
        raise EvtkError(f"{where}: {key} are {a.shape[1]}x{a.shape[2]}, beyond {MAX_SIDE} a side")
    return a


def read_schedule(path: str | os.PathLike) -> Plan:
    """Read and check a ``schedule.json`` (:func:`evtk.patterns.write_patterns`; ``docs/formats/schedule.md``).

    Parameters
    ----------
    path : str or os.PathLike
        The file.

    Returns
    -------
    Plan
        Its ``schedule`` (:class:`Schedule`), ``kernels``, ``features`` (int
        arrays (n, h, w)), ``bench`` (:class:`evtk.optics.Bench`),
        ``window_us``, ``settle_us`` and ``dot_spacing``; no placement, no
        pixel model. Every value is checked; a bad one is an
        :class:`~evtk.EvtkError` naming the file, the key and what is allowed.
    """
    from ..optics import Bench
    from .core import Plan

    path = os.fspath(path)
    doc = read_table(path, "schedule", MAX_SCHEDULE_BYTES, parse_factor=40)  # JSON's lists of ints: ~40x
    if doc.get("evtk_schedule_version") != 1 or isinstance(doc.get("evtk_schedule_version"), bool):
        raise EvtkError(f"{path}: not an evtk schedule (evtk_schedule_version 1); write one with evtk patterns")
    missing = [k for k in ("captures", "kernels", "features", "bench", "window_us", "settle_us") if k not in doc]
    if missing:
        raise EvtkError(f"{path}: the schedule is malformed: it lacks {', '.join(missing)}")
    top = {k: check_value(path, k, doc[k], spec) for k, spec in SCHEDULE_SPECS.items() if k in doc}
    cal = doc.get("calibration") or {}
    if not isinstance(cal, dict):
        raise EvtkError(f"{path}: calibration must be a table (captures, dot_spacing, levels)")
    cal = check_table(f"{path}: calibration", cal, SCHEDULE_CALIBRATION_SPECS, unknown="keep")
    kernels = check_patterns(path, "kernels", doc["kernels"])
    features = check_patterns(path, "features", doc["features"])
    if not isinstance(doc["bench"], dict):
        raise EvtkError(f"{path}: bench must be a table of bench parameters")
    try:
        bench = Bench.from_dict(doc["bench"])
    except EvtkError as exc:
        raise EvtkError(f"{path}: {exc}") from None
    caps = doc["captures"]
    if not isinstance(caps, list) or not caps or not all(isinstance(c, dict) for c in caps):
        raise EvtkError(f"{path}: captures must be a non-empty list of tables, one per capture")
    cols = {}
    for c in Schedule._COLUMNS:
        if c in Schedule._OPTIONAL and not any(c in cap for cap in caps):
            continue
        cols[c] = [cap.get(c, 0 if c in Schedule._OPTIONAL else None) for cap in caps]
        if any(v is None for v in cols[c]):
            i = next(i for i, v in enumerate(cols[c]) if v is None)
            raise EvtkError(f"{path}: capture {i} lacks {c}")
    schedule = Schedule.from_dict(cols, path, len(kernels), len(features), kernels.shape[1] * kernels.shape[2])
    if np.any(schedule.t_off_us - schedule.t_on_us != top["window_us"]):
        i = int(np.flatnonzero(schedule.t_off_us - schedule.t_on_us != top["window_us"])[0])
        raise EvtkError(f"{path}: capture {i} lasts {int(schedule.t_off_us[i] - schedule.t_on_us[i])} us, "
                        f"not the schedule's window_us = {top['window_us']}")
    bench.check_pattern(kernels.shape[1:], features.shape[1:])
    if (schedule.kernel_id == DOTS_ID).any() and not dot_grid(features.shape[1:],
                                                               cal.get("dot_spacing", 4)).any():
        raise EvtkError(f"{path}: calibration dot_spacing = {cal.get('dot_spacing', 4)} leaves no dot on "
                        f"{features.shape[1]}x{features.shape[2]} features")
    return Plan(schedule, kernels, features, bench, cast(int, top["window_us"]), cast(int, top["settle_us"]),
                dot_spacing=int(cal.get("dot_spacing", 4)))


@dataclass
class CaptureCounts:
    """Per-capture event counts inside each capture window, over a sensor region.

    Parameters
    ----------
    on, off : ndarray of int
        ON and OFF counts, ``(n_captures, y1 - y0, x1 - x0)``.
    region : tuple
        ``(x0, x1, y0, y1)`` on the sensor.
    schedule : Schedule
        The captures counted.
    """

    on: np.ndarray
    off: np.ndarray
    region: tuple
    schedule: Schedule


def default_features(side: int = 16) -> np.ndarray:
    """The embedded default input: scikit-image's camera picture, ``side`` x ``side``, binarised at its mean.

    Parameters
    ----------
    side : int
        Elements a side.

    Returns
    -------
    ndarray of int8
        0/1, ``(side, side)``.
    """
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

#: The ids a setup capture has in both ``kernel_id`` and ``features_id``.
_SETUP_IDS = (FLAT_ID, DOTS_ID, LEVEL_ID)


def level_kernel(shape: tuple[int, int], on: int) -> np.ndarray:
    """The kernel of a level capture: its first ``on`` elements in row-major order on, the rest off (int8).

    Under features that are all on, every cell of the response's interior
    sees exactly ``on`` units of light, whichever elements are on: a
    staircase of these captures measures the pixels' transfer from light to
    counts, to which :func:`evtk.reconstruct.fit_pixel_model` fits the pixel model.

    Parameters
    ----------
    shape : tuple of int
        The kernel's ``(rows, cols)``.
    on : int
        Elements on, 1 to rows x cols.

    Returns
    -------
    ndarray of int8
        The kernel.

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


def level_steps(n_elements: int, levels: int) -> np.ndarray:
    """The kernel element counts a staircase of level captures shows: evenly spread from 1 up, distinct.

    Parameters
    ----------
    n_elements : int
        Elements of the kernel (the brightest step).
    levels : int
        Steps asked for (fewer when the kernel has fewer elements).

    Returns
    -------
    ndarray of int64
        The steps, ascending; empty for ``levels <= 0``.
    """
    n, k = int(n_elements), int(levels)
    if k <= 0:
        return np.zeros(0, np.int64)
    return np.unique(np.round(np.linspace(1, n, min(k, n))).astype(np.int64))


def dot_grid(shape: tuple[int, int], spacing: int, marker: bool = True) -> np.ndarray:
    """The calibration pattern: 1 at every ``spacing``-th features element along each axis, starting
    ``spacing // 2`` in, 0 elsewhere (int8).

    With ``marker`` (default) one dot is left out when the grid has at least 10 dots
    (:data:`DOT_MARKER_MIN`) and 3 rows and 4 columns (or 4 and 3): the second of the first row (on a taller
    grid the first of the second row). That place lies on no axis of the grid's symmetry, so no rotation or
    reflection maps the gap onto itself and :func:`evtk.calibrate.calibrate` tells a mirrored or rotated camera
    apart from an upright one; the corners stay, for the map's extrapolation. ``marker=False`` gives the whole
    grid.

    Parameters
    ----------
    shape : tuple of int
        The features' ``(rows, cols)``.
    spacing : int
        Elements between dots.
    marker : bool
        Leave the orientation marker's dot out.

    Returns
    -------
    ndarray of int8
        The pattern.

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


def load_patterns(path_or_bits: str | os.PathLike, name: str, side: int | None = None) -> np.ndarray:
    """Patterns from a ``.npy`` file, an image (PNG etc.) or a bit string like ``101010101``.

    Images are binarised at half their range; a bit string fills a square
    pattern row by row. A file's size is read from its header and checked
    (at most :data:`evtk.settings.MAX_SIDE` a side, within the memory budget)
    before its data are.

    Parameters
    ----------
    path_or_bits : str or os.PathLike
        A ``.npy`` path, an image path or a string of 0s and 1s.
    name : str
        What the patterns are ("kernel", "features"), for messages.
    side : int, optional
        Unused; kept for callers that pass it.

    Returns
    -------
    ndarray
        The pattern(s), as the file holds them (an image as int8 0/1).
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
        arr = read_npy(s, name)
        if arr.ndim not in (2, 3) or max(arr.shape[-2:], default=0) > MAX_SIDE:
            raise EvtkError(f"{s}: a {name} array is (h, w) or (n, h, w) of at most {MAX_SIDE} a side, "
                            f"not {arr.shape}")
        return arr
    img = np.asarray(read_image(s, f"{name} image"), dtype=np.float64)
    if max(img.shape[:2]) > MAX_SIDE:
        raise EvtkError(f"{s}: a {img.shape[1]}x{img.shape[0]} {name} image is larger than {MAX_SIDE} pixels a side")
    if img.ndim == 3:
        img = img[..., :3].mean(axis=2)
    lo, hi = float(img.min()), float(img.max())
    return (img > (lo + hi) / 2).astype(np.int8) if hi > lo else np.zeros(img.shape, np.int8)
