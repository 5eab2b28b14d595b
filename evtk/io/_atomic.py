"""Atomic file replacement: write beside the target, then rename over it."""

from __future__ import annotations

import io
import os
import tempfile

from ..errors import EvtkError

PARTIAL_SUFFIX = ".evtk-partial"


class AtomicFile:
    """A binary file that appears under ``path`` only when :meth:`commit` runs.

    Until then the data lives in ``<name>.<random>.evtk-partial`` in the same
    directory, so a crash leaves the previous file untouched and the partial
    one recognisable.  :meth:`discard` removes the partial file.
    """

    def __init__(self, path, keep_open=True):
        self.path = os.fspath(path)
        directory = os.path.dirname(os.path.abspath(self.path))
        if not os.path.isdir(directory):
            raise EvtkError(f"cannot write {self.path}: there is no folder {directory}")
        fd, self.tmp_path = tempfile.mkstemp(
            prefix=os.path.basename(self.path) + ".", suffix=PARTIAL_SUFFIX, dir=directory
        )
        # mkstemp creates 0600 files; give the result the mode a plain open()
        # would (or keep the mode of the file being replaced)
        try:
            mode = os.stat(self.path).st_mode & 0o7777
        except OSError:
            umask = os.umask(0)
            os.umask(umask)
            mode = 0o666 & ~umask
        try:
            os.fchmod(fd, mode)
        except OSError:  # pragma: no cover - filesystems without modes
            pass
        self.file = os.fdopen(fd, "w+b")
        if not keep_open:  # another library (h5py, pyarrow) writes the path itself
            self.file.close()

    def commit(self):
        """Flush to disk and move the file under its final name."""
        if not self.file.closed:
            self.file.flush()
            os.fsync(self.file.fileno())
            self.file.close()
        else:
            fd = os.open(self.tmp_path, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        os.replace(self.tmp_path, self.path)
        try:  # make the rename itself durable
            dfd = os.open(os.path.dirname(os.path.abspath(self.path)), os.O_RDONLY)
        except OSError:  # pragma: no cover - platform without directory fds
            return
        try:
            os.fsync(dfd)
        except OSError:  # pragma: no cover
            pass
        finally:
            os.close(dfd)

    def discard(self):
        try:
            self.file.close()
        finally:
            try:
                os.unlink(self.tmp_path)
            except FileNotFoundError:
                pass

    def write(self, data):
        return self.file.write(data)

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            self.commit()
        else:
            self.discard()
        return False


def refuse_overwriting_inputs(targets, sources):
    """Raise :class:`~evtk.EvtkError` when one of ``targets`` (a path or several) is one of ``sources`` (the
    same file by any name, compared by device and inode): writing it would replace a recording being read."""
    if isinstance(targets, (str, os.PathLike)):
        targets = [targets]
    inodes = {}
    for src in sources:
        try:
            st = os.stat(src)
        except OSError:
            continue
        inodes.setdefault((st.st_dev, st.st_ino), src)
    for target in targets:
        try:
            st = os.stat(target)
        except OSError:
            continue
        src = inodes.get((st.st_dev, st.st_ino))
        if src is not None:
            raise EvtkError(f"the output {os.fspath(target)} is the input {os.fspath(src)}; writing it would replace "
                            "the recording (choose another output name or folder)")


class FailSafeFile(io.RawIOBase):
    """A file object for a library that writes through it (h5py) and must be able to close after the disk
    fails: the first failed write raises, and from then on writes, reads and truncation go nowhere, so the
    library's own clean-up succeeds (libhdf5 otherwise crashes the process at exit after a failed flush).
    :attr:`failure` keeps the first error. The file itself is about to be discarded."""

    def __init__(self, raw):
        super().__init__()
        self._f = raw
        self.failure = None
        self._pos = 0
        self._size = 0

    def readable(self):
        return True

    def writable(self):
        return True

    def seekable(self):
        return True

    def seek(self, offset, whence=0):
        if self.failure is None:
            self._pos = self._f.seek(offset, whence)
        else:
            self._pos = (offset, self._pos + offset, self._size + offset)[whence]
        return self._pos

    def tell(self):
        return self._pos

    def write(self, data):
        n = memoryview(data).nbytes
        if self.failure is None:
            try:
                n = self._f.write(data)
            except OSError as exc:
                self.failure = exc
                raise
        self._pos += n
        self._size = max(self._size, self._pos)
        return n

    def readinto(self, buf):
        if self.failure is None:
            n = self._f.readinto(buf) or 0
        else:
            n = len(buf)
            memoryview(buf).cast("B")[:] = bytes(n)
        self._pos += n
        return n

    def truncate(self, size=None):
        size = self._pos if size is None else size
        if self.failure is None:
            try:
                self._f.truncate(size)
            except OSError as exc:
                self.failure = exc
                raise
        self._size = size
        return size

    def flush(self):
        if self.failure is None:
            try:
                self._f.flush()
            except OSError as exc:
                self.failure = exc
                raise
