"""Writing evtk's HDF5 layout: chunked columns, a time index, atomic and fail-safe."""

from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from ..._atomic import AtomicFile, FailSafeFile
from ..._version import __version__
from ...errors import EvtkError
from ...events import Events, Triggers
from .._checks import require_readable, sorted_for_writing
from ..base import BaseWriter
from .common import _FILL, DEFAULT_CHUNK, EVTK_FORMAT, FORMAT_VERSION, INTERRUPTED, _filter, _h5

if TYPE_CHECKING:
    import numpy.typing as npt


def _superblock_eoa(path):
    """The end-of-file address an HDF5 superblock records (absolute), or None when none is found.

    The superblock sits at byte 0 or after a user block of 512, 1024, 2048, ... bytes.  Versions 0 and 1
    keep the address after four fixed fields; versions 2 and 3 right after the base and extension addresses.
    """
    with open(path, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        at = 0
        while at + 64 <= size:
            f.seek(at)
            head = f.read(64)
            if head[:8] == b"\x89HDF\r\n\x1a\n":
                version = head[8]
                if version in (0, 1):
                    width = head[13]
                    start = 24 if version == 0 else 28
                else:
                    width = head[9]
                    start = 12
                if width not in (2, 4, 8):
                    return None
                base = int.from_bytes(head[start : start + width], "little")
                eoa = int.from_bytes(head[start + 2 * width : start + 3 * width], "little")
                return base + eoa if base + eoa < 1 << 62 else None
            at = 512 if at == 0 else at * 2
    return None


def _copy(ev: Events) -> Events:
    return Events._trusted(ev.t.copy(), ev.x.copy(), ev.y.copy(), ev.p.copy(), ev.sensor_size, True)


class Hdf5Writer(BaseWriter):
    """Stream events into evtk's HDF5 layout, atomically.

    Events must arrive in time order (call :meth:`write_events` as often as
    needed); the block index is built on the way.  Nothing appears under
    ``path`` until :meth:`close`.

    Parameters
    ----------
    path : str or os.PathLike
        The target (``.h5`` / ``.hdf5``).
    sensor_size : sequence of two int
        Width and height in pixels, stored in the root attribute ``sensor_size``.
    compression : str
        One of :data:`COMPRESSIONS`; default Blosc2-LZ4 with byte shuffle
        (chosen by measurement and robustness, see ``docs/formats/hdf5.md``).
    metadata : Mapping of str to object, optional
        JSON-serialisable, stored in the root attribute ``metadata``.
    chunk_events : int
        HDF5 chunk length, and the stride of the time index.

    Raises
    ------
    EvtkError
        For an unknown compression, ``chunk_events`` below 1, or metadata that is not JSON-serialisable.
    """

    def __init__(self, path: str | os.PathLike[str], sensor_size: Sequence[int], compression: str = "lz4",
                 metadata: Mapping[str, Any] | None = None, chunk_events: int = DEFAULT_CHUNK) -> None:
        h5py = _h5()
        self.sensor_size = (int(sensor_size[0]), int(sensor_size[1]))
        self.chunk = int(chunk_events)
        if self.chunk < 1:
            raise EvtkError("chunk_events must be positive")
        kw = _filter(str(compression).lower())
        try:
            meta_text = json.dumps(metadata or {}, sort_keys=True)
        except (TypeError, ValueError) as exc:
            raise EvtkError(f"metadata must be JSON-serialisable: {exc}") from None
        self._atomic = AtomicFile(path)
        self.path = self._atomic.path
        # libhdf5 writes through a Python file object that turns into a sink once the disk fails: a failed
        # write is then one error, and the library still closes (it crashed the process at exit otherwise)
        self._sink = FailSafeFile(self._atomic.file)
        try:
            self._f = h5py.File(self._sink, "w")
            f = self._f
            f.attrs["evtk_format"] = np.bytes_(EVTK_FORMAT)
            f.attrs["evtk_format_version"] = FORMAT_VERSION
            f.attrs["evtk_version"] = np.bytes_(__version__)
            f.attrs["sensor_size"] = np.asarray(self.sensor_size, np.int64)
            f.attrs["time_unit"] = np.bytes_("us")
            f.attrs[INTERRUPTED] = np.uint8(1)
            f.create_dataset("metadata", data=np.frombuffer(meta_text.encode("utf-8"), np.uint8))
            g = f.create_group("events")
            self._cols = {}
            for name, dtype in (("t", np.int64), ("x", np.uint16), ("y", np.uint16), ("p", np.uint8)):
                self._cols[name] = g.create_dataset(name, shape=(0,), maxshape=(None,), dtype=dtype, chunks=(self.chunk,),
                                                    fillvalue=_FILL[name], **kw)
            self._cols["t"].attrs["unit"] = np.bytes_("us")
            self._index: list[np.ndarray] = []
            self._n = 0  # events accepted ...
            self._stored = 0  # ... of which in the datasets (whole chunks until close)
            self._tail: list[Events] = []  # the rest, fewer than a chunk
            self._last_t: int | None = None
            self._trig: list[Triggers] = []
            self._closed = False
            f.flush()  # from here on the partial file opens (and salvages) as an interrupted evtk file
        except BaseException:
            self._discard()
            raise

    def write_events(self, events: Events) -> None:
        """Append time-ordered events.

        Whole chunks go to the datasets as they fill; the rest waits for the next call or :meth:`close`.

        Parameters
        ----------
        events : Events
            Of the writer's sensor size, continuing the time order of those before.

        Raises
        ------
        EvtkError
            When the writer is closed, the sensor sizes differ, time goes backwards, an event lies off the
            sensor, or the disk refuses the write (no file is left then).
        """
        self._check_open()
        if tuple(events.sensor_size) != self.sensor_size:
            raise EvtkError(f"events are for a {events.sensor_size} sensor, the file for {self.sensor_size}")
        n = len(events)
        if n == 0:
            return
        require_readable(events, self.sensor_size, self._last_t, self._n, "HDF5")
        a, b = self._n, self._n + n
        first_block = -(-a // self.chunk)
        starts = np.arange(first_block * self.chunk, b, self.chunk)
        if len(starts):
            self._index.append(events.t[starts - a])
        self._n = b
        self._last_t = int(events.t[-1])
        self._tail.append(events)
        whole = (b // self.chunk) * self.chunk
        if whole > self._stored:
            with self._disk():
                self._store(whole)
                self._f.flush()  # the file on disk is complete up to here: a kill loses at most the events since
        else:  # keep our own copy: the caller may reuse its arrays
            self._tail[-1] = _copy(events)

    def _store(self, upto):
        """Move the buffered events up to index ``upto`` into the datasets.

        Only whole chunks are stored before :meth:`close`, so a stored chunk is never rewritten: after a kill
        every chunk the last flush recorded is still where it was.
        """
        pending = Events.concatenate(self._tail, sensor_size=self.sensor_size) if len(self._tail) > 1 else self._tail[0]
        a, k = self._stored, upto - self._stored
        for name in ("t", "x", "y", "p"):
            ds = self._cols[name]
            ds.resize((upto,))
            ds[a:upto] = getattr(pending, name)[:k]
        self._tail = [_copy(pending[k:])] if k < len(pending) else []
        self._stored = upto

    def write_triggers(self, triggers: Triggers) -> None:
        """Add trigger edges, stored (sorted by time, with their channels) when the file is closed.

        Parameters
        ----------
        triggers : Triggers
            The edges; may be called several times.

        Raises
        ------
        EvtkError
            When the writer is closed.
        """
        self._check_open()
        self._trig.append(triggers)

    def write_array(self, name: str, data: npt.ArrayLike, attrs: Mapping[str, Any] | None = None) -> None:
        """Store an extra dataset (responses, schedule, parameters) in the same file.

        Parameters
        ----------
        name : str
            Its path in the file (groups made as needed), outside ``/events`` and ``/triggers``.
        data : array_like
            Its values, stored uncompressed as NumPy makes them an array.
        attrs : Mapping of str to object, optional
            HDF5 attributes of the dataset.

        Raises
        ------
        EvtkError
            When the writer is closed, ``name`` is in evtk's event layout, or the disk refuses the write.
        """
        self._check_open()
        if name.strip("/").split("/")[0] in ("events", "triggers"):
            raise EvtkError(f"{name!r} is reserved for evtk's event layout")
        with self._disk():
            ds = self._f.create_dataset(name, data=np.asarray(data))
            for k, v in (attrs or {}).items():
                ds.attrs[k] = v

    @contextlib.contextmanager
    def _disk(self):
        """A write that the disk refused (full, over quota, too large) becomes one EvtkError, with the partial
        file removed; any previous file under the name is untouched."""
        try:
            yield
        except EvtkError:
            raise
        except Exception:
            failure = self._sink.failure
            if failure is None:
                raise
            self._closed = True
            self._discard()
            raise EvtkError(f"cannot write {self.path}: {failure.strerror or failure} (nothing was written "
                            "under that name)") from None

    # -- finishing (BaseWriter's close and abort) --------------------------------------
    def _finish(self):
        with self._disk():
            self._finish_file()

    def _commit(self):
        self._atomic.commit()

    def _finish_file(self):
        """Store what is buffered, the time index and the triggers, and close the HDF5 file."""
        if self._stored < self._n:
            self._store(self._n)
        g = self._f["events"]
        index = np.concatenate(self._index) if self._index else np.zeros(0, np.int64)
        ds = g.create_dataset("index_t_us", data=index.astype(np.int64))
        ds.attrs["stride"] = self.chunk
        if self._trig:
            tr = Triggers.concatenate(self._trig)
            order = np.argsort(tr.t, kind="stable")
            tg = self._f.create_group("triggers")
            tg.create_dataset("t", data=tr.t[order])
            tg.create_dataset("kind", data=tr.kind[order])
            if tr.channel.any():  # channel 0 throughout: no dataset, as files before channels were kept
                tg.create_dataset("channel", data=tr.channel[order])
        del self._f.attrs[INTERRUPTED]
        self._f.close()
        self._sink.close()  # (left open, the collector closed it after the commit: a flush of a closed file)

    def _discard(self):
        for close in ("_f", "_sink"):  # (either may be missing or fail: the file is removed next)
            try:
                getattr(self, close).close()
            except Exception:
                pass
        self._atomic.discard()


def write_hdf5(path: str | os.PathLike[str], events: Events, triggers: Triggers | None = None,
               compression: str = "lz4", metadata: Mapping[str, Any] | None = None, sort: bool = False,
               **kwargs: Any) -> None:
    """Write a whole recording in evtk's HDF5 layout (atomically).

    Parameters
    ----------
    path : str or os.PathLike
        The target (``.h5`` / ``.hdf5``); it appears only once complete.
    events : Events
        The events, in time order (or any order with ``sort``).
    triggers : Triggers, optional
        Trigger edges, with their channels.
    compression : str
        One of :data:`COMPRESSIONS` (:class:`Hdf5Writer`).
    metadata : Mapping of str to object, optional
        JSON-serialisable, stored in the root attribute ``metadata``.
    sort : bool
        Sort the events by time (stably) first, instead of refusing them out of order.
    **kwargs : Any
        :class:`Hdf5Writer`'s other options (``chunk_events``).

    Raises
    ------
    EvtkError
        As :class:`Hdf5Writer` and its ``write_events``; no file is left under ``path`` then.
    """
    events = sorted_for_writing(events, sort, "HDF5")
    with Hdf5Writer(path, events.sensor_size, compression, metadata, **kwargs) as w:
        for a in range(0, len(events), 1 << 22):
            w.write_events(events[a : a + (1 << 22)])
        if triggers is not None:
            w.write_triggers(triggers)
