"""Exception hierarchy shared by every evtk module."""

from __future__ import annotations

import os
from collections.abc import Mapping

__all__ = ["EvtkError", "FormatError", "check_parameters"]


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
