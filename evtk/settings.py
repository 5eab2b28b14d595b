"""Reading, checking and writing the small TOML/JSON settings files evtk uses (job, bench, schedule, calibration).

Every value a user can write in one of these files passes through this
module where it is read: :func:`read_table` reads the file (a regular file
of at most :data:`MAX_SETTINGS_BYTES`, TOML or strict JSON), and
:class:`Spec` with :func:`check_value`, :func:`check_table` and
:func:`check_array` check each value's type, finiteness and range, so that
a bad value is one :class:`~evtk.EvtkError` naming the file, the key and
what is allowed (``schedule.json: dot_spacing = -3 must be a whole number
from 2 to 16384 (features elements)``) instead of a traceback, a NaN or a
silently wrong run.
"""

from __future__ import annotations

import math
import os
import stat
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from .errors import EvtkError
from .limits import require_memory

if TYPE_CHECKING:
    import numpy.typing as npt

__all__ = ["read_table", "toml_text", "Spec", "check_value", "check_table", "check_array", "check_matrix",
           "check_origin", "check_region", "MAX_SETTINGS_BYTES", "MAX_SCHEDULE_BYTES", "MAX_BLUR_PX", "MAX_US",
           "MAX_COUNT", "MAX_SIDE"]

#: Largest settings file evtk reads (bytes): a job, bench or calibration is a few KiB.
MAX_SETTINGS_BYTES = 16 << 20
#: Largest ``schedule.json`` evtk reads (bytes): about 300 bytes a capture.
MAX_SCHEDULE_BYTES = 1 << 30
#: Longest time a setting may give (µs): 2^52, where float64 still holds every microsecond.
MAX_US = 2 ** 52
#: Largest count (captures, repeats, dots) a setting may give.
MAX_COUNT = 10 ** 7
#: Most elements along one side of a pattern, a DMD or a sensor.
MAX_SIDE = 32767
#: Widest camera defocus a calibration may state (Gaussian standard deviation, pixels): ``evtk calibrate``
#: measures 0 to 3 px from its dots (wider blurs merge neighbouring dots), so a larger value was not measured
#: and the deblur would invent detail the sensor never showed.
MAX_BLUR_PX = 4.0


def read_table(path: str | os.PathLike[str], what: str, max_bytes: int = MAX_SETTINGS_BYTES,
               parse_factor: float | None = None) -> dict[str, Any]:
    """The top-level table of a TOML (``.toml``) or JSON (anything else) settings file.

    Parameters
    ----------
    path : str or os.PathLike
        The file; it must be a regular file (not a device or a pipe, which
        could be endless) of at most ``max_bytes``.
    what : str
        What the file is ("job", "bench", "calibration"), for messages.
    max_bytes : int
        Size cap (default :data:`MAX_SETTINGS_BYTES`).
    parse_factor : float, optional
        Bytes of Python objects the parsed file takes per byte of it, for a
        large file (a schedule): its size times this is checked against the
        memory budget (:func:`evtk.limits.require_memory`) before it is read.

    Returns
    -------
    dict
        The table (JSON's ``NaN`` and ``Infinity`` read as floats, which the checks refuse by key).
    """
    path = os.fspath(path)
    try:
        with open(path, "rb") as f:
            st = os.fstat(f.fileno())
            if not stat.S_ISREG(st.st_mode):
                raise EvtkError(f"{path}: a {what} file must be a regular file, not a device, pipe or folder")
            if st.st_size > max_bytes:
                raise EvtkError(f"{path}: {st.st_size:,} bytes is too large for a {what} file "
                                f"(at most {max_bytes:,})")
            if parse_factor is not None:
                require_memory(st.st_size * parse_factor, f"reading the {st.st_size:,}-byte {what} file {path}")
            raw = f.read(min(max_bytes, st.st_size) + 1)  # read(n) reserves n bytes first: ask for what is there
    except OSError as exc:
        raise EvtkError(f"{path}: cannot read {what} file: {exc.strerror or exc}") from None
    if len(raw) > max_bytes:  # grew while read
        raise EvtkError(f"{path}: too large for a {what} file (at most {max_bytes:,} bytes)")
    try:
        if path.lower().endswith(".toml"):
            try:
                import tomllib
            except ModuleNotFoundError:  # Python 3.10
                import tomli as tomllib
            data = tomllib.loads(raw.decode("utf-8"))
        else:
            import json  # here: a run without a settings file does not load it

            data = json.loads(raw.decode("utf-8"))  # NaN and Infinity are read, for the checks to name their key
    except Exception as exc:  # noqa: BLE001 - any parse failure is the user's file
        raise EvtkError(f"{path}: not a valid {what} file: {exc}") from None
    if not isinstance(data, dict):
        raise EvtkError(f"{path}: not an evtk {what} (a {what} file holds a table of parameters)")
    return data


@dataclass(frozen=True)
class Spec:
    """What one setting may hold.

    Parameters
    ----------
    kind : {"int", "float", "bool", "str"}
        A whole number (an integral float such as ``2.0`` too), any finite
        number, true/false, or text.
    lo, hi : float or None
        Inclusive bounds of a number (None: unbounded on that side).
    lo_open : bool
        The lower bound itself is excluded (``> lo``).
    unit : str
        What the number counts, for messages ("µs", "pixels").
    choices : tuple or None
        The values text (or a number) may take.
    optional : bool
        None (JSON ``null``) is allowed.
    """

    kind: str
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    unit: str = ""
    choices: tuple | None = None
    optional: bool = False

    def describe(self) -> str:
        """The allowed values in words.

        Returns
        -------
        str
            For messages, e.g. "a whole number from 2 to 16384 (features elements)" or "one of 'a', 'b'".
        """
        if self.choices is not None:
            return "one of " + ", ".join(repr(c) for c in self.choices)
        if self.kind == "bool":
            return "true or false"
        if self.kind == "str":
            return "text"
        noun = "a whole number" if self.kind == "int" else "a finite number"
        lo = None if self.lo is None else f"{self.lo:g}" if self.kind == "float" else f"{int(self.lo)}"
        hi = None if self.hi is None else f"{self.hi:g}" if self.kind == "float" else f"{int(self.hi)}"
        if self.lo == 0 and self.lo_open:
            noun = "a positive " + noun[2:]
            rng = "" if hi is None else f" up to {hi}"
        elif lo is not None and hi is not None:
            rng = f" above {lo} and at most {hi}" if self.lo_open else f" from {lo} to {hi}"
        elif lo is not None:
            rng = f" above {lo}" if self.lo_open else f" of at least {lo}"
        elif hi is not None:
            rng = f" of at most {hi}"
        else:
            rng = ""
        return noun + rng + (f" ({self.unit})" if self.unit else "") + (" or null" if self.optional else "")


def _is_number(v) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))


def check_value(where: str, key: str, value: Any, spec: Spec) -> int | float | bool | str | None:
    """``value`` checked against ``spec``, as the Python type the spec names.

    Parameters
    ----------
    where : str
        The file (or record) the value was read from, for the message.
    key : str
        The setting's name.
    value : object
        What the file holds.
    spec : Spec
        What it may hold.

    Returns
    -------
    int, float, bool, str or None
        The value (an integral float as an int for ``kind="int"``).

    Raises
    ------
    EvtkError
        Naming ``where``, ``key``, the value and what is allowed, when it does not fit.
    """
    bad = EvtkError(f"{where}: {key} = {_show(value)} must be {spec.describe()}")
    if value is None:
        if spec.optional:
            return None
        raise bad
    if spec.kind == "bool":
        if not isinstance(value, (bool, np.bool_)):
            raise bad
        return bool(value)
    if spec.kind == "str":
        if not isinstance(value, str) or (spec.choices is not None and value not in spec.choices):
            raise bad
        return value
    if not _is_number(value):
        raise bad
    if spec.kind == "int":
        if isinstance(value, (float, np.floating)):
            if not (math.isfinite(value) and float(value).is_integer()):
                raise bad
        value = int(value)
    else:
        value = float(value)
        if not math.isfinite(value):
            raise bad
    if spec.lo is not None and (value <= spec.lo if spec.lo_open else value < spec.lo):
        raise bad
    if spec.hi is not None and value > spec.hi:
        raise bad
    if spec.choices is not None and value not in spec.choices:
        raise bad
    return value


def check_table(where: str, data: object, specs: Mapping[str, Spec], required: Iterable[str] = (),
                unknown: str = "refuse") -> dict[str, Any]:
    """The values of ``data`` that ``specs`` names, each checked by :func:`check_value`.

    Parameters
    ----------
    where : str
        The file, for messages.
    data : dict
        The table read.
    specs : dict of str to Spec
        The settings the table may hold.
    required : iterable of str
        Settings it must hold.
    unknown : {"refuse", "keep"}
        Whether a key ``specs`` does not name is an error or passed through unchecked
        (for tables checked further by their own reader).

    Returns
    -------
    dict
        The checked values (keys absent from ``data`` stay absent).
    """
    if not isinstance(data, dict):
        raise EvtkError(f"{where}: expected a table of settings, not {type(data).__name__}")
    missing = [k for k in required if k not in data]
    if missing:
        raise EvtkError(f"{where}: lacks {', '.join(missing)}")
    out = {}
    for k, v in data.items():
        if k in specs:
            out[k] = check_value(where, k, v, specs[k])
        elif unknown == "refuse":
            raise EvtkError(f"{where}: unknown setting {k!r}; it may hold {', '.join(specs)}")
        else:
            out[k] = v
    return out


def check_array(where: str, key: str, value: object, ndim: int | Iterable[int], lo: float | None = None,
                hi: float | None = None, kind: str = "int", shape: tuple[int | None, ...] | None = None,
                max_elements: int | None = None, allow_empty: bool = False) -> np.ndarray:
    """A nested list (or array) of numbers, checked before it is used.

    Parameters
    ----------
    where, key : str
        File and setting, for messages.
    value : list or ndarray
        What the file holds.
    ndim : int or tuple of int
        Dimensions allowed.
    lo, hi : float, optional
        Inclusive bounds of every element.
    kind : {"int", "float"}
        Whole numbers (int64) or finite numbers (float64).
    shape : tuple, optional
        The exact shape required (``None`` entries match any length).
    max_elements : int, optional
        Most elements allowed.
    allow_empty : bool
        Whether an array with no elements is allowed.

    Returns
    -------
    ndarray
        int64 (``kind="int"``) or float64, of the shape given.

    Raises
    ------
    EvtkError
        Naming ``where`` and ``key`` when the value is not such an array: text, ragged rows, another
        dimension or shape, too many or no elements, NaN or infinity, a fraction for ``kind="int"``, a
        number outside ``[lo, hi]`` or beyond the int64 range.
    """
    ndims = (ndim,) if isinstance(ndim, int) else tuple(ndim)
    what = f"{'whole' if kind == 'int' else 'finite'} numbers"
    rng = "" if lo is None and hi is None else f" from {lo:g} to {hi:g}" if lo is not None and hi is not None \
        else f" of at least {lo:g}" if lo is not None else f" of at most {hi:g}"
    want = f"{' or '.join(f'{d}-D' for d in ndims)} array of {what}{rng}"
    if isinstance(value, (str, bytes, dict)) or value is None or _is_number(value) or isinstance(value, bool):
        raise EvtkError(f"{where}: {key} = {_show(value)} must be a {want}")
    try:
        arr = np.asarray(value)
    except (ValueError, TypeError, OverflowError):
        raise EvtkError(f"{where}: {key} must be a {want} (rows of equal length)") from None
    if arr.ndim not in ndims:
        raise EvtkError(f"{where}: {key} must be a {want}, not of shape {arr.shape}")
    if arr.dtype.kind not in ("iufb" if kind == "int" else "iuf"):
        holds = "text" if arr.dtype.kind in "US" else "other values (or numbers beyond the int64 range)"
        raise EvtkError(f"{where}: {key} must be a {want}: it holds {holds}")
    if shape is not None and (len(shape) != arr.ndim or any(s is not None and s != n for s, n in zip(shape, arr.shape))):
        raise EvtkError(f"{where}: {key} must have shape {tuple('*' if s is None else s for s in shape)}, "
                        f"not {arr.shape}")
    if arr.size == 0 and not allow_empty:
        raise EvtkError(f"{where}: {key} must not be empty")
    if max_elements is not None and arr.size > max_elements:
        raise EvtkError(f"{where}: {key} holds {arr.size:,} elements, more than the {max_elements:,} allowed")
    if arr.dtype.kind == "f":
        if not np.all(np.isfinite(arr)):
            raise EvtkError(f"{where}: {key} must be a {want}: it holds infinity or NaN")
        if kind == "int" and not np.all(arr == np.round(arr)):
            raise EvtkError(f"{where}: {key} must be a {want}: it holds a fraction")
        if kind == "int" and arr.size and np.max(np.abs(arr)) > 2.0 ** 62:
            raise EvtkError(f"{where}: {key} holds a number beyond the int64 range")
    if arr.size and ((lo is not None and np.min(arr) < lo) or (hi is not None and np.max(arr) > hi)):
        bad = arr[(arr < lo) if lo is not None and np.min(arr) < lo else (arr > hi)].flat[0]
        raise EvtkError(f"{where}: {key} holds {_show(bad.item())}; it must be a {want}")
    if kind == "int":
        if arr.dtype.kind == "u" and arr.size and np.max(arr) > np.iinfo(np.int64).max:
            raise EvtkError(f"{where}: {key} holds a number beyond the int64 range")
        return arr.astype(np.int64)
    return arr.astype(np.float64)


def check_matrix(where: str, key: str, value: object, corners: npt.ArrayLike | None = None) -> np.ndarray:
    """A projective map (3x3, finite, non-singular) from cells to pixels.

    Parameters
    ----------
    where, key : str
        File and setting, for messages.
    value : list or ndarray
        The matrix as the file holds it.
    corners : array_like (n, 2), optional
        Points (cells) the map must carry to finite pixels on one side of
        its horizon (the response's corners): a map that sends part of the
        response to infinity is no camera's view.

    Returns
    -------
    ndarray
        float64 (3, 3), as given (not normalised).

    Raises
    ------
    EvtkError
        When it is not a finite 3x3 array, is singular (or nearly so: condition number above 1e12), or
        its horizon crosses ``corners``.
    """
    m = check_array(where, key, value, 2, kind="float", shape=(3, 3))
    scale = float(np.max(np.abs(m)))
    if scale == 0 or abs(np.linalg.det(m / scale)) < 1e-12 or np.linalg.cond(m) > 1e12:
        raise EvtkError(f"{where}: {key} is singular: it maps the response onto a line or a point, not onto pixels")
    if corners is not None:
        pts = np.asarray(corners, np.float64)
        w = pts @ m[2, :2] + m[2, 2]
        if not (np.all(w > 1e-9) or np.all(w < -1e-9)):
            raise EvtkError(f"{where}: {key} sends part of the response to infinity (its horizon crosses it)")
    return m


def check_origin(where: str, key: str, value: object, sensor_size: Sequence[int] | np.ndarray) -> tuple[float, float]:
    """A sensor pixel (x, y) where a response begins: two finite numbers within one sensor size of the sensor.

    Parameters
    ----------
    where, key : str
        File and setting, for messages.
    value : list or tuple
        What it holds.
    sensor_size : sequence of two int
        The sensor (width, height) in pixels.

    Returns
    -------
    tuple of (float, float)
        The pixel (x, y); x within ``[-width, 2 width]``, y within ``[-height, 2 height]``.
    """
    try:
        o = check_array(where, key, value, 1, kind="float", shape=(2,))
    except EvtkError:
        raise EvtkError(f"{where}: {key} = {_show(value)} must be two finite numbers, a pixel (x, y)") from None
    w, h = (int(v) for v in sensor_size)
    if not (-w <= o[0] <= 2 * w and -h <= o[1] <= 2 * h):
        raise EvtkError(f"{where}: {key} = {_show(value)} must be a pixel (x, y) within one sensor size of the "
                        f"{w}x{h} sensor (x from {-w} to {2 * w}, y from {-h} to {2 * h})")
    return float(o[0]), float(o[1])


def check_region(where: str, key: str, value: object,
                 sensor_size: Sequence[int] | np.ndarray) -> tuple[int, int, int, int]:
    """A sensor region ``(x0, x1, y0, y1)``, half-open, non-empty and on the sensor.

    Parameters
    ----------
    where, key : str
        File and setting, for messages.
    value : list or tuple
        What it holds.
    sensor_size : sequence of two int
        The sensor (width, height) in pixels.

    Returns
    -------
    tuple of (int, int, int, int)
        ``(x0, x1, y0, y1)`` with ``0 <= x0 < x1 <= width`` and ``0 <= y0 < y1 <= height``.
    """
    r = check_array(where, key, value, 1, shape=(4,))
    x0, x1, y0, y1 = (int(v) for v in r)
    w, h = (int(v) for v in sensor_size)
    if not (0 <= x0 < x1 <= w and 0 <= y0 < y1 <= h):
        raise EvtkError(f"{where}: {key} = {_show(value)} must be pixels [x0, x1, y0, y1] with 0 <= x0 < x1 <= {w} "
                        f"and 0 <= y0 < y1 <= {h} (the sensor)")
    return x0, x1, y0, y1


def _show(v) -> str:
    """A value for a message, cut short when long."""
    text = repr(v)
    return text if len(text) <= 60 else text[:57] + "..."


def toml_text(table: Mapping[str, Any], what: str = "settings", comment: str | None = None) -> str:
    """``table`` as the text of a TOML file, written by ``tomli-w`` so that reading it back gives ``table`` again.

    A value that is itself a table becomes a ``[name]`` section. Values are booleans, whole numbers, finite
    floats (written exactly: read back, they are the same float64), strings, and lists or tables of them;
    numpy scalars are taken as the Python number they hold.

    Parameters
    ----------
    table : Mapping of str to object
        The settings, by name (callers leave out unset, ``None``, values: TOML has no null).
    what : str
        The file kind ("bench", "calibration"), for the message when a value cannot be stored.
    comment : str, optional
        Text put first, each of its lines as a ``#`` comment.

    Returns
    -------
    str
        The TOML text, ending in a newline.

    Raises
    ------
    EvtkError
        When a value cannot be stored in TOML: ``None``, NaN or infinity (which evtk's readers refuse), or an
        object that is not one of the types above. The message names the key.
    """
    import tomli_w  # writing only: a run that reads its settings does not load it

    text = tomli_w.dumps(_toml_ready(table, what, ""))
    head = "".join(f"# {line}".rstrip() + "\n" for line in comment.splitlines()) if comment else ""
    return head + text


def _toml_ready(v: Any, what: str, key: str) -> Any:
    """``v`` with numpy scalars as Python numbers, or an EvtkError naming ``key`` if TOML cannot hold it."""
    if isinstance(v, Mapping):
        out = {}
        for k, x in v.items():
            if not isinstance(k, str):
                raise EvtkError(f"cannot store the key {k!r} in a {what} file (keys are text)")
            out[k] = _toml_ready(x, what, f"{key}.{k}" if key else k)
        return out
    if isinstance(v, (list, tuple)):
        return [_toml_ready(x, what, f"{key}[{i}]") for i, x in enumerate(v)]
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        if not math.isfinite(v):
            raise EvtkError(f"cannot store {key} = {float(v)!r} in a {what} file (only finite numbers)")
        return float(v)
    if isinstance(v, str):
        return v
    raise EvtkError(f"cannot store {key} = {_show(v)} in a {what} file "
                    f"(a {type(v).__name__}: TOML holds true/false, numbers, text, and lists or tables of them)")
