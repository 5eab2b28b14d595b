"""Exception hierarchy shared by every evtk module."""

from __future__ import annotations

import os

__all__ = ["EvtkError", "FormatError"]


class EvtkError(Exception):
    """Base class of every error evtk raises on purpose.

    The command line prints such errors as one line and exits non-zero.
    """


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

    def __init__(self, path, offset, reason):
        self.path = None if path is None else os.fspath(path)
        self.offset = None if offset is None else int(offset)
        self.reason = str(reason)
        where = self.path if self.path is not None else "<data>"
        if self.offset is not None:
            where = f"{where} at byte {self.offset}"
        super().__init__(f"{where}: {self.reason}")


def one_line(exc) -> str:
    """A library's error message on one line (pyarrow's and libhdf5's span several)."""
    return " ".join(str(exc).split())

