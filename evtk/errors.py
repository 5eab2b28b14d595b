"""Exception hierarchy shared by every evtk module, and the checks of a file's header values that raise them
(:func:`sensor_dims`, :func:`load_json`: every reader uses them, so they load with the errors and not with the Arrow
table code, which a read of an AEDAT4 or Event Stream file does not need)."""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Any

__all__ = ["EvtkError", "FormatError", "check_parameters", "check_positive", "sensor_dims", "load_json",
           "MAX_SENSOR_SIDE"]


class EvtkError(Exception):
    """Base class of every error evtk raises on purpose.

    The command line prints such errors as one line and exits non-zero.

    Parameters
    ----------
    *args : object
        The message (one string, as a rule), as for :class:`Exception`.
    """

    def __init__(self, *args: object) -> None:
        super().__init__(*args)


class FormatError(EvtkError):
    """A file does not follow the format it claims to be in.

    Parameters
    ----------
    path : str or os.PathLike or None
        The file that was being read or written.
    offset : int or None
        Byte offset in the file where the problem was found.
    reason : str
        What was wrong, in words a user can act on.
    """

    def __init__(self, path: str | os.PathLike[str] | None, offset: int | None, reason: str) -> None:
        self.path = None if path is None else os.fspath(path)
        self.offset = None if offset is None else int(offset)
        self.reason = str(reason)
        where = self.path if self.path is not None else "<data>"
        if self.offset is not None:
            where = f"{where} at byte {self.offset}"
        super().__init__(f"{where}: {self.reason}")


def one_line(exc: BaseException | str) -> str:
    """A library's error message on one line (pyarrow's and libhdf5's span several).

    Parameters
    ----------
    exc : BaseException or str
        The error (or its message).

    Returns
    -------
    str
        Its message with every run of whitespace, line breaks included, made one space.
    """
    return " ".join(str(exc).split())


def check_parameters(kind: str, cls: type, values: Mapping[str, object]) -> None:
    """Check settings against the fields of a dataclass before it is built from them.

    Each of ``values`` must be a field of ``cls`` and fit its default's type: a finite number where the
    default is a number, text where it is text, true/false where it is a flag (a field whose default is
    None or missing takes anything here; its own checks follow).

    Parameters
    ----------
    kind : str
        What the parameters are ("bench", "sensor"), for the message.
    cls : type
        The dataclass.
    values : Mapping of str to object
        The settings, by field name.

    Raises
    ------
    EvtkError
        Naming the first unknown parameter, or the first value that does not fit its field.
    """
    import dataclasses
    import math

    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - set(fields))
    if unknown:
        raise EvtkError(f"unknown {kind} parameter(s): {', '.join(unknown)}")
    for name, v in values.items():
        default = fields[name].default
        if default is dataclasses.MISSING or default is None:
            continue
        if isinstance(default, bool):
            ok, want = isinstance(v, bool), "true or false"
        elif isinstance(default, (int, float)):
            ok, want = isinstance(v, (int, float)) and not isinstance(v, bool), "a number"
            if ok and isinstance(v, float) and not math.isfinite(v):
                raise EvtkError(f"{kind} parameter {name} must be a finite number, not {v!r}")
        elif isinstance(default, str):
            ok, want = isinstance(v, str), "text"
        else:
            ok, want = True, ""
        if not ok:
            raise EvtkError(f"{kind} parameter {name} must be {want}, not {v!r}")


def check_positive(**values: Any) -> None:
    """Check that every value is a positive finite number.

    Parameters
    ----------
    **values : Any
        The values, by the name the error gives them (numbers, or anything ``float`` takes).

    Raises
    ------
    EvtkError
        Naming the first value that is not a number above 0 and below infinity (NaN, infinity, 0, negative, text).
    """
    import math

    for name, v in values.items():
        try:
            ok = math.isfinite(float(v)) and float(v) > 0
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise EvtkError(f"{name} must be a positive finite number, not {v!r}")


#: Largest sensor side evtk reads (coordinates are 16-bit).
MAX_SENSOR_SIDE = 65536


def sensor_dims(width: Any, height: Any, path: str | os.PathLike[str] | None, where: str) -> tuple[int, int]:
    """``(width, height)`` from a file's header values (numbers, or their text), checked.

    Parameters
    ----------
    width, height : Any
        The values as the header holds them: numbers, text or bytes of a number, or one-element arrays.
    path : str or os.PathLike or None
        The file, for the error.
    where : str
        Which header entry they came from, for the error.

    Returns
    -------
    tuple of (int, int)
        ``(width, height)`` in pixels.

    Raises
    ------
    FormatError
        Naming ``where``, when either is not a whole number from 1 to :data:`MAX_SENSOR_SIDE` (65536).
    """
    import numpy as np  # (loaded by every reader by now; ``import evtk`` itself does not load numpy)

    out = []
    for v in (width, height):
        if isinstance(v, (bytes, np.bytes_)):
            v = bytes(v).decode("utf-8", "replace")
        if isinstance(v, np.ndarray) and v.size == 1:
            v = v.reshape(-1)[0]
        try:
            f = float(v)
            ok = f.is_integer() and 1 <= f <= MAX_SENSOR_SIDE
        except (TypeError, ValueError, OverflowError):
            ok = False
        if not ok:
            raise FormatError(path, None, f"{where} gives an impossible sensor size {width!r} x {height!r} "
                                          f"(whole numbers from 1 to {MAX_SENSOR_SIDE} expected)")
        out.append(int(f))
    return out[0], out[1]


def _no_constant(name):
    raise ValueError(f"{name} is not a JSON number")


def load_json(text: str | bytes | bytearray | memoryview, path: str | os.PathLike[str] | None, what: str) -> Any:
    """JSON metadata a file carries, parsed and checked.

    Parameters
    ----------
    text : str or bytes-like
        The JSON (bytes as UTF-8).
    path : str or os.PathLike or None
        The file, for the error.
    what : str
        Which entry of the file it is, for the error.

    Returns
    -------
    object
        The parsed value (dict, list, str, number, bool or None).

    Raises
    ------
    FormatError
        Naming ``what`` when it is not valid JSON or UTF-8, nests too deeply to read, or holds NaN or
        infinities (which would make evtk's own JSON output invalid).
    """
    import json  # here: a fresh process reading a file without JSON in it does not load the module (1-1.5 ms)

    try:
        if isinstance(text, (bytes, bytearray, memoryview)):
            text = bytes(text).decode("utf-8")
        return json.loads(text, parse_constant=_no_constant)
    except (ValueError, UnicodeDecodeError) as exc:
        raise FormatError(path, None, f"{what} is not valid JSON ({' '.join(str(exc).split())[:200]})") from None
    except RecursionError:
        raise FormatError(path, None, f"{what} nests too deeply to read") from None
