"""A read-only file spliced from the intact start of a damaged file and bytes evtk supplies."""

from __future__ import annotations

import atexit
import io
import os
import weakref

__all__ = ["SplicedFile", "close_at_exit"]


class SplicedFile(io.RawIOBase):
    """The first ``end`` bytes of ``path``, then ``tail``, then zeros up to ``size`` bytes.

    A truncated HDF5 file opens when its missing end reads as zeros up to the
    size its superblock records; a Parquet file without a footer opens with a
    rebuilt footer in place of its torn end.
    """

    def __init__(self, path, end: int, tail: bytes = b"", size: int | None = None):
        super().__init__()
        self._f = open(path, "rb")
        self._end, self._tail = int(end), bytes(tail)
        self._size = max(self._end + len(self._tail), int(size or 0))
        self._pos = 0

    def readable(self):
        return True

    def seekable(self):
        return True

    def seek(self, offset, whence=os.SEEK_SET):
        base = {os.SEEK_SET: 0, os.SEEK_CUR: self._pos, os.SEEK_END: self._size}[whence]
        self._pos = max(0, base + int(offset))
        return self._pos

    def tell(self):
        return self._pos

    def size(self):
        return self._size

    def readinto(self, buf):
        n = min(len(buf), max(0, self._size - self._pos))
        view = memoryview(buf).cast("B")
        done = 0
        if self._pos < self._end and n:
            self._f.seek(self._pos)
            done = self._f.readinto(view[: min(n, self._end - self._pos)]) or 0
        if done < n:
            start = self._pos + done - self._end
            piece = self._tail[max(0, start) : max(0, start) + n - done]
            view[done : done + len(piece)] = piece
            done += len(piece)
        if done < n:
            view[done:n] = bytes(n - done)
            done = n
        self._pos += done
        return done

    def close(self):
        try:
            self._f.close()
        finally:
            super().close()


_OPEN: weakref.WeakSet = weakref.WeakSet()


def close_at_exit(recording):
    """Close ``recording`` before the interpreter shuts down, if its user did not.

    A library reading through a Python file object (h5py's ``fileobj``
    driver) calls back into Python when it closes; left to the library's own
    exit handler that happens during interpreter shutdown and crashes it.
    """
    _OPEN.add(recording)


@atexit.register
def _close_all():
    for rec in list(_OPEN):
        try:
            rec.close()
        except Exception:  # noqa: BLE001 - shutting down: nothing left to report to
            pass
