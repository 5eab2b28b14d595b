"""Atomic file replacement: write beside the target, then rename over it."""

from __future__ import annotations

import os
import tempfile

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
