"""Atomic file replacement, and the one guard on what evtk writes.

Every file evtk writes goes through :class:`AtomicFile`: the data goes to a
partial file beside the target (``<name>.<host>-<pid>.<random>.evtk-partial``)
and is renamed over the target only when complete. Partial files are removed
when the process is interrupted (SIGINT, SIGTERM, SIGHUP: the handler removes
them, then the signal takes its usual course) and, when a process died
without that chance (SIGKILL, power loss), by the next write of the same
target on the same machine once the process named in the partial file is gone.

:func:`guard_outputs` is the one check of a command's outputs against its
inputs: up front (an output that is an input, or two outputs that are one
file, is refused before anything runs), and again at every commit inside it,
so a file written under a computed name (a contact sheet's later page, a
batch output) can replace neither an input nor another output of the command.
"""

from __future__ import annotations

import _thread
import contextlib
import contextvars
import io
import os

from .errors import EvtkError

PARTIAL_SUFFIX = ".evtk-partial"

_HOST_TAG: str | None = None


def _host_tag() -> str:
    """A short tag of this machine in partial-file names: stale partial files are only removed by the host that
    made them. Found on the first write, from ``os.uname`` and zlib's CRC-32 (hashlib and socket cost a fresh
    process 6 ms, a sixtieth of a 20 M-event read)."""
    global _HOST_TAG
    if _HOST_TAG is None:
        import zlib

        try:
            name = os.uname().nodename
        except AttributeError:  # pragma: no cover - Windows
            import socket

            name = socket.gethostname()
        _HOST_TAG = f"{zlib.crc32(name.encode('utf-8', 'replace')):08x}"
    return _HOST_TAG


# partial files being written, by the process that writes them (a forked child must not remove its parent's)
_LIVE: dict = {}
_LIVE_LOCK = _thread.RLock()  # re-entrant: the signal handler may run while the main thread holds it
_PREVIOUS_HANDLERS: dict = {}
#: The signals whose handlers remove the partial files (names: the signal module loads with the first write, not
#: with every command that might write: 0.4-0.5 ms of a fresh process)
_SIGNAL_NAMES = ("SIGINT", "SIGTERM", "SIGHUP")


def _remove_live_partials():
    """Remove this process's partial files (they are incomplete by definition)."""
    pid = os.getpid()
    with _LIVE_LOCK:
        mine = [p for p, owner in _LIVE.items() if owner == pid]
        for p in mine:
            _LIVE.pop(p, None)
    for p in mine:
        try:
            os.unlink(p)
        except OSError:
            pass


def _on_signal(signum, frame):
    """Remove the partial files, then let the signal do what it did before (raise, exit, or nothing)."""
    import signal

    _remove_live_partials()
    previous = _PREVIOUS_HANDLERS.get(signum, signal.SIG_DFL)
    if callable(previous):
        return previous(signum, frame)
    if previous == signal.SIG_IGN:
        return None
    signal.signal(signum, signal.SIG_DFL)  # die of the signal, as without evtk
    os.kill(os.getpid(), signum)
    return None


def _install_signal_handlers():
    """Chain :func:`_on_signal` before the handlers in place (once; only the main thread may)."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        return
    for signum in (getattr(signal, name) for name in _SIGNAL_NAMES if hasattr(signal, name)):
        current = signal.getsignal(signum)
        if current is _on_signal or current is None:  # ours already, or set outside Python: leave it
            continue
        if signum != signal.SIGINT and current == signal.SIG_IGN:  # nohup: the signal does nothing, so do we
            continue
        try:
            signal.signal(signum, _on_signal)
        except (ValueError, OSError):  # pragma: no cover - not the main interpreter
            continue
        _PREVIOUS_HANDLERS[signum] = current


def _pid_alive(pid) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process
        return True
    except (OSError, OverflowError, ValueError):
        return True
    return True


# the partial files of this host found in each folder when this process first wrote there: a folder is listed
# once, so writing many files into one folder (evtk patterns' frames) stays linear
_PARTIALS_SEEN: dict = {}


def _partials_in(directory) -> set:
    with _LIVE_LOCK:
        names = _PARTIALS_SEEN.get(directory)
    if names is None:
        try:
            names = {n for n in os.listdir(directory) if n.endswith(PARTIAL_SUFFIX) and f".{_host_tag()}-" in n}
        except OSError:
            names = set()
        with _LIVE_LOCK:
            names = _PARTIALS_SEEN.setdefault(directory, names)
    return names


def remove_stale_partials(path) -> list:
    """Remove the partial files of ``path`` left by processes of this machine that are gone; return them.

    Parameters
    ----------
    path : str or os.PathLike
        The target whose partial files (``<name>.<host>-<pid>.<random>.evtk-partial``) are looked for.

    Returns
    -------
    list of str
        The partial files removed.
    """
    path = os.fspath(path)
    directory = os.path.dirname(os.path.abspath(path))
    prefix = os.path.basename(path) + f".{_host_tag()}-"
    removed = []
    names = _partials_in(directory)
    for name in [n for n in names if n.startswith(prefix)]:
        names.discard(name)
        pid_text = name[len(prefix):-len(PARTIAL_SUFFIX)].split(".", 1)[0]
        if not pid_text.isdigit() or _pid_alive(int(pid_text)):
            continue
        try:
            os.unlink(os.path.join(directory, name))
            removed.append(os.path.join(directory, name))
        except OSError:
            pass
    return removed


def _new_partial(directory: str, prefix: str) -> tuple[int, str]:
    """Create ``<prefix><random>.evtk-partial`` in ``directory`` as :func:`tempfile.mkstemp` does (exclusively,
    mode 0600, never through a link), without importing tempfile and shutil (2-8 ms of a fresh process).

    Returns
    -------
    tuple of (int, str)
        The open descriptor (read and write) and the path.
    """
    flags = os.O_RDWR | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0) \
        | getattr(os, "O_BINARY", 0)
    for _ in range(100):
        path = os.path.join(directory, f"{prefix}{os.urandom(6).hex()}{PARTIAL_SUFFIX}")
        try:
            return os.open(path, flags, 0o600), path
        except FileExistsError:
            continue
    raise FileExistsError(f"no free partial-file name for {prefix} in {directory}")  # pragma: no cover


class AtomicFile:
    """A binary file that appears under ``path`` only when :meth:`commit` runs.

    Until then the data lives in ``<name>.<host>-<pid>.<random>.evtk-partial``
    in the same directory, so a crash leaves the previous file untouched and
    the partial one recognisable; it is removed on SIGINT/SIGTERM/SIGHUP, and
    by the next write of ``path`` once its process is gone. :meth:`discard`
    removes it. Inside :func:`guard_outputs` the commit refuses to replace an
    input of the command or a file the command already wrote.
    """

    def __init__(self, path, keep_open=True):
        self.path = os.fspath(path)
        directory = os.path.dirname(os.path.abspath(self.path))
        if not os.path.isdir(directory):
            raise EvtkError(f"cannot write {self.path}: there is no folder {directory}")
        _check_target(self.path)  # before the work of writing it
        remove_stale_partials(self.path)
        _install_signal_handlers()
        fd, self.tmp_path = _new_partial(directory, f"{os.path.basename(self.path)}.{_host_tag()}-{os.getpid()}.")
        with _LIVE_LOCK:
            _LIVE[self.tmp_path] = os.getpid()
        # the partial file is created 0600; give the result the mode a plain open()
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
        """Flush to disk and move the file under its final name (the partial file is removed if that fails)."""
        try:
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
            _check_target(self.path)
            expected = (_EXPECTED.get() or {}).get(os.path.abspath(self.path), _ANY)
            if expected is _ANY:
                os.replace(self.tmp_path, self.path)
            elif expected is None:
                self._create_exclusively()
            else:
                if _identity(self.path) != expected:
                    raise EvtkError(_replaced_meanwhile(self.path))
                os.replace(self.tmp_path, self.path)
        except BaseException:
            self.discard()
            raise
        with _LIVE_LOCK:
            _LIVE.pop(self.tmp_path, None)
        _note_written(self.path)
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

    def _create_exclusively(self):
        """Put the partial file under its name only if nothing is there (a hard link fails on an existing name)."""
        try:
            os.link(self.tmp_path, self.path)
        except FileExistsError:
            raise EvtkError(_replaced_meanwhile(self.path)) from None
        except OSError:  # a file system without hard links: check, then rename (a narrow window remains)
            if os.path.lexists(self.path):
                raise EvtkError(_replaced_meanwhile(self.path)) from None
            os.replace(self.tmp_path, self.path)
            return
        os.unlink(self.tmp_path)

    def discard(self):
        """Close and remove the partial file."""
        try:
            self.file.close()
        finally:
            with _LIVE_LOCK:
                _LIVE.pop(self.tmp_path, None)
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


# -- targets another process may write at the same time ---------------------------------------------

_ANY = object()
_EXPECTED: contextvars.ContextVar = contextvars.ContextVar("evtk_expected_targets", default=None)


def _replaced_meanwhile(path):
    return (f"{path} was written by another process while this result was computed (another batch into the "
            "same folder?); it was left as that process wrote it and this result was not saved")


def file_identity(path):
    """(device, inode) of the file at ``path``, or None where there is none.

    Parameters
    ----------
    path : str or os.PathLike
        The file.

    Returns
    -------
    tuple of int or None
        What :func:`expect_target` compares.
    """
    return _identity(path)


@contextlib.contextmanager
def expect_target(path, identity):
    """Inside the block, an :class:`AtomicFile` commit to ``path`` replaces only the file seen before the work
    began: ``identity`` (from :func:`file_identity`), or, when None, no file at all (the result is then created
    exclusively). A file another process put there meanwhile is left alone and the commit raises
    :class:`~evtk.EvtkError` saying so.

    Parameters
    ----------
    path : str or os.PathLike
        The target.
    identity : tuple of int or None
        Its :func:`file_identity` when the work began.

    Yields
    ------
    None
    """
    expected = dict(_EXPECTED.get() or {})
    expected[os.path.abspath(os.fspath(path))] = identity
    token = _EXPECTED.set(expected)
    try:
        yield
    finally:
        _EXPECTED.reset(token)


# -- the guard on outputs ----------------------------------------------------------------------

class _Guard:
    """The inputs of a running command and the files it has written, by (device, inode)."""

    def __init__(self, inputs):
        self.inputs = {}
        for label, src in inputs:
            key = _identity(src)
            if key is not None:
                self.inputs.setdefault(key, (label, os.fspath(src)))
        self.written = {}


_GUARDS: list = []


def _identity(path):
    try:
        st = os.stat(path)
    except (OSError, ValueError):
        return None
    return (st.st_dev, st.st_ino)


def _labelled(items, default):
    """``items`` (a path, paths, or (label, path) pairs) as (label, path) pairs, empty paths left out."""
    if items is None:
        return []
    if isinstance(items, (str, bytes, os.PathLike)):
        items = [items]
    out = []
    for item in items:
        label, p = item if isinstance(item, tuple) and len(item) == 2 else (default, item)
        if p is not None and os.fspath(p) != "":
            out.append((label, os.fspath(p)))
    return out


def _describe(label, path):
    return f"{path} ({label})" if label else path


def _check_target(path):
    """Refuse, inside a guard, a target that is an input of the command or a file it already wrote."""
    if not _GUARDS:
        return
    key = _identity(path)
    if key is None:
        return
    for guard in _GUARDS:
        if key in guard.inputs:
            label, src = guard.inputs[key]
            raise EvtkError(f"the output {path} is the input {_describe(label, src)}; writing it would replace "
                            "it (choose another output name or folder)")
        if key in guard.written:
            raise EvtkError(f"the output {path} is {guard.written[key]}, which this command has just written; "
                            "writing it would replace that output (choose distinct output names)")


def _note_written(path):
    if not _GUARDS:
        return
    key = _identity(path)
    if key is not None:
        for guard in _GUARDS:
            guard.written.setdefault(key, os.fspath(path))


def check_outputs(outputs, inputs=()):
    """Raise :class:`~evtk.EvtkError` when an output is an input or two outputs are one file.

    A file is the same by any name: device and inode where it exists
    (hard and symbolic links included), else its resolved path.

    Parameters
    ----------
    outputs : path, paths, or (label, path) pairs
        What is about to be written; a label ("--png") names the option in messages.
    inputs : path, paths, or (label, path) pairs
        What the work reads.
    """
    outs = _labelled(outputs, "")
    ins = _labelled(inputs, "")
    by_key = {}
    for label, src in ins:
        key = _identity(src)
        if key is not None:
            by_key.setdefault(key, (label, src))
        by_key.setdefault(os.path.realpath(src), (label, src))
    seen = {}
    for label, target in outs:
        keys = [os.path.realpath(target)]
        ident = _identity(target)
        if ident is not None:
            keys.append(ident)
        for key in keys:
            if key in by_key:
                src_label, src = by_key[key]
                raise EvtkError(f"the output {_describe(label, target)} is the input {_describe(src_label, src)}; "
                                "writing it would replace it (choose another output name or folder)")
        for key in keys:
            if key in seen:
                other_label, other = seen[key]
                raise EvtkError(f"the outputs {_describe(other_label, other)} and {_describe(label, target)} are "
                                "the same file; one would replace the other (choose distinct output names)")
        for key in keys:
            seen[key] = (label, target)


def refuse_overwriting_inputs(targets, sources):
    """Raise :class:`~evtk.EvtkError` when one of ``targets`` is one of ``sources`` or two targets are one file
    (:func:`check_outputs`)."""
    check_outputs(targets, sources)


@contextlib.contextmanager
def guard_outputs(outputs=(), inputs=()):
    """Check ``outputs`` against ``inputs`` now (:func:`check_outputs`), and every :class:`AtomicFile` commit
    inside the block against the inputs and against what the block has already written.

    Parameters
    ----------
    outputs : path, paths, or (label, path) pairs
        The outputs known up front (option values); directories are left out of the check.
    inputs : path, paths, or (label, path) pairs
        The files the work reads.

    Yields
    ------
    None
    """
    files = [(label, p) for label, p in _labelled(outputs, "") if not os.path.isdir(p)]
    check_outputs(files, inputs)
    guard = _Guard(_labelled(inputs, ""))
    _GUARDS.append(guard)
    try:
        yield
    finally:
        _GUARDS.remove(guard)


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
