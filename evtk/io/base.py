"""What every opened recording offers, whatever its file format."""

from __future__ import annotations

import os
import re
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import numpy as np

from ..errors import MAX_SENSOR_SIDE, EvtkError, FormatError, load_json, sensor_dims  # noqa: F401  (part of this module's API)
from ..events import Events, Triggers

__all__ = ["BaseRecording", "BaseWriter", "StreamInfo", "Damage", "time_chunks", "window_blocks", "sensor_dims", "load_json",
           "text_header"]


def _event_columns(n: int):
    """Empty event columns (t, x, y, p: int64, uint16, uint16, uint8) for ``n`` events, for readers that decode
    a file piece by piece into one set of arrays."""
    return np.empty(n, np.int64), np.empty(n, np.uint16), np.empty(n, np.uint16), np.empty(n, np.uint8)


def _put_events(cols, n: int, ev):
    """Copy the events ``ev`` into the columns ``cols`` (:func:`_event_columns`) after their first ``n``; columns
    too short are replaced by ones twice as long (or as long as needed). Returns ``(cols, n + len(ev))``."""
    k = len(ev)
    if n + k > len(cols[0]):
        grown = _event_columns(max(2 * len(cols[0]), n + k))
        for dst, src in zip(grown, cols):
            dst[:n] = src[:n]
        cols = grown
    for dst, src in zip(cols, (ev.t, ev.x, ev.y, ev.p)):
        dst[n:n + k] = src
    return cols, n + k


def _header_end(buf: bytes, cut: bool, prefix: int, last_line) -> tuple[int, bool]:
    """Where the text header at the start of ``buf`` ends, and whether it may go on past ``buf`` (``cut``: the
    file does); see :func:`text_header`."""
    import numpy as np

    a = np.frombuffer(buf, np.uint8)
    text = ((a >= 0x20) & (a <= 0x7E)) | (a == 0x09)
    feeds = a == 0x0A
    text[:-1] |= (a[:-1] == 0x0D) & feeds[1:]  # a carriage return only right before a line feed
    text |= feeds
    first_binary = int(np.argmin(text)) if not text.all() else len(a)
    ends = np.flatnonzero(feeds[:first_binary])  # complete lines before any binary byte
    starts = np.concatenate(([0], ends[:-1] + 1)).astype(np.int64) if len(ends) else np.zeros(0, np.int64)
    not_header = np.flatnonzero(a[starts] != prefix) if len(starts) else np.zeros(0, np.int64)
    n_lines = int(not_header[0]) if len(not_header) else len(starts)
    end = int(ends[n_lines - 1]) + 1 if n_lines else 0
    if last_line is not None and n_lines and (m := last_line.search(buf, 0, end)) is not None:
        return buf.index(b"\n", m.start()) + 1, False
    # every byte read is header text, a line perhaps cut: the header may go on
    more = cut and n_lines == len(starts) and first_binary == len(a) and (end == len(a) or a[end] == prefix)
    return end, more


def text_header(path: str | os.PathLike[str], prefix: bytes, max_bytes: int,
                last_line: re.Pattern | None = None) -> tuple[list[str], int]:
    """The text header at the start of a file: its lines and the offset where the data begins.

    A header line is text: it starts with ``prefix``, holds printable ASCII
    or tabs, and ends with a line feed (a carriage return may precede it).
    The header ends at the first line that is not one (so a data word that
    happens to start with the prefix byte but holds binary is data), or after
    the line ``last_line`` matches, which then belongs to the header. The
    work is linear in the header's length, whatever the lines hold:
    vectorised passes over the file's start, read again four times longer
    while the header goes on (64 KiB first), up to ``max_bytes + 1`` bytes.

    Parameters
    ----------
    path : str or os.PathLike
        The file.
    prefix : bytes
        The single byte every header line starts with (``b"#"``, ``b"%"``).
    max_bytes : int
        The longest header accepted; a longer one raises.
    last_line : re.Pattern, optional
        A bytes pattern, compiled with ``re.MULTILINE`` and anchored with
        ``^``, matching the line that closes the header.

    Returns
    -------
    lines : list of str
        The header lines, each stripped of surrounding white space (the prefix kept).
    offset : int
        The byte where the data begins.

    Raises
    ------
    FormatError
        The header runs past ``max_bytes``.
    """
    want = min(1 << 16, max_bytes)  # most headers are a few KB: read more only while the header goes on
    with open(path, "rb") as f:
        while True:
            f.seek(0)
            buf = f.read(want + 1)
            end, more = _header_end(buf, len(buf) > want, prefix[0], last_line)
            if not more:
                break
            if want >= max_bytes:
                raise FormatError(path, 0, f"the text header runs past {max_bytes >> 20} MiB")
            want = min(4 * want, max_bytes)
    if end > max_bytes:
        raise FormatError(path, 0, f"the text header runs past {max_bytes >> 20} MiB")
    lines = buf[:end].decode("ascii").split("\n")[:-1]
    return [line.strip() for line in lines], end


class _Record:
    """Equality and a repr by the fields ``_FIELDS``, as a dataclass has them (without the ``dataclasses``
    module and the code it generates: 1.5-2 ms of a fresh process's start)."""

    _FIELDS: tuple[str, ...] = ()
    __hash__ = None  # type: ignore[assignment]  # compared by value, and changeable

    def __eq__(self, other: object) -> bool:
        if other.__class__ is not self.__class__:
            return NotImplemented
        return tuple(getattr(self, f) for f in self._FIELDS) == tuple(getattr(other, f) for f in self._FIELDS)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({', '.join(f'{f}={getattr(self, f)!r}' for f in self._FIELDS)})"


class StreamInfo(_Record):
    """One stream of a recording: name, type, element count and time range.

    Parameters
    ----------
    id : int
        The stream's number in the file (AEDAT4 stream id; 0 for formats of one stream).
    name : str
        Its name ("events", "triggers", or the AEDAT4 stream's name).
    type : str
        AEDAT4 type identifier: ``EVTS`` (events), ``TRIG`` (triggers), ``IMUS``, ``FRME``, ...
    packets : int
        Packets (AEDAT4), chunks (HDF5) or row groups (Parquet) holding it.
    count : int or None
        Elements (events, triggers), as the file's index states it; None when it does not say.
    t_start_us, t_end_us : int or None
        First and last time stamp (µs) as the index states them; None when unknown or empty.
    sensor_size : tuple of (int, int) or None
        ``(width, height)`` in pixels, for an event or frame stream.
    attributes : dict, optional
        Anything else the file says of the stream (compression, source, ...); None: empty.
    """

    _FIELDS = ("id", "name", "type", "packets", "count", "t_start_us", "t_end_us", "sensor_size", "attributes")

    def __init__(self, id: int, name: str, type: str, packets: int = 0, count: int | None = None,
                 t_start_us: int | None = None, t_end_us: int | None = None,
                 sensor_size: tuple[int, int] | None = None, attributes: dict | None = None) -> None:
        self.id = id
        self.name = name
        self.type = type  # AEDAT4 identifier: EVTS, TRIG, IMUS, FRME, ...
        self.packets = packets
        self.count = count
        self.t_start_us = t_start_us
        self.t_end_us = t_end_us
        self.sensor_size = sensor_size
        self.attributes = {} if attributes is None else attributes

    KINDS = {"EVTS": "events", "TRIG": "triggers", "IMUS": "imu", "FRME": "frame"}

    def as_dict(self) -> dict[str, Any]:
        """The stream as ``evtk info --json`` prints it.

        Returns
        -------
        dict
            ``id``, ``name``, ``type``, ``kind`` ("events", "triggers", "imu", "frame" or "other"),
            ``packets``, ``count``, ``t_start_us``, ``t_end_us`` and ``sensor_size`` (a list, or None);
            not the attributes.
        """
        return {
            "id": self.id,
            "name": self.name,
            "type": self.type,
            "kind": self.KINDS.get(self.type, "other"),
            "packets": self.packets,
            "count": self.count,
            "t_start_us": self.t_start_us,
            "t_end_us": self.t_end_us,
            "sensor_size": list(self.sensor_size) if self.sensor_size else None,
        }


class Damage(_Record):
    """Where salvage stopped: the byte offset (or dataset) and what was wrong there.

    Parameters
    ----------
    offset : int or None
        Byte offset in the file of the first damaged byte (None where the format has no such offset, as an
        HDF5 dataset).
    reason : str
        What was wrong there, in words.
    """

    _FIELDS = ("offset", "reason")

    def __init__(self, offset: int | None, reason: str) -> None:
        self.offset = offset
        self.reason = reason


class BaseWriter:
    """What every writer shares: one ``close`` that finishes and moves the file into place, one ``abort``.

    A writer is a context manager: leaving the block normally closes it,
    leaving it on an exception aborts it (the temporary file is removed and
    any previous file under the name is untouched). Either happens once;
    writing after it is an :class:`~evtk.EvtkError`. Subclasses set
    ``path`` and ``_closed = False`` and provide ``_finish()`` (write what is
    buffered and the file's trailer), ``_commit()`` (move the file into
    place) and ``_discard()`` (remove the temporary file, never raising for
    a writer already broken).
    """

    path: str
    _closed: bool = True

    def _finish(self):  # pragma: no cover - overridden
        raise NotImplementedError

    def _commit(self):  # pragma: no cover - overridden
        raise NotImplementedError

    def _discard(self):  # pragma: no cover - overridden
        raise NotImplementedError

    def _check_open(self):
        if self._closed:
            raise EvtkError(f"{self.path}: writer is closed")

    def write_events(self, events: Events) -> None:  # pragma: no cover - overridden
        """Append events to the file.

        Parameters
        ----------
        events : Events
            The next events, of the writer's sensor size (in time order for the formats that need it:
            HDF5, Prophesee RAW and DAT, Event Stream, CSV).

        Raises
        ------
        EvtkError
            When the writer is closed, or the events do not fit the format (coordinates beyond the sensor or
            the format's range, time going backwards where it may not).
        """
        raise NotImplementedError

    def close(self) -> None:
        """Finish the file and move it into place (atomically); a second call does nothing.

        On an error while finishing, the temporary file is removed (any previous file under the name is
        untouched) and the error raised.
        """
        if self._closed:
            return
        self._closed = True
        try:
            self._finish()
            self._commit()
        except BaseException:
            self._discard()
            raise

    def abort(self) -> None:
        """Give up: remove the temporary file and leave any previous file alone."""
        if not self._closed:
            self._closed = True
            self._discard()

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            self.close()
        else:
            self.abort()


class BaseRecording:
    """Common interface of :class:`evtk.io.aedat4.Recording` and the HDF5 and
    Parquet recordings.

    Subclasses provide ``sensor_size``, ``streams``, ``metadata``,
    ``events()``, ``triggers()``, ``iter_events()`` and ``_close()``.
    A recording is a context manager: leaving the ``with`` block closes it.

    Parameters
    ----------
    path : str or os.PathLike
        The file.
    salvage : bool
        Read what precedes damage instead of raising :class:`~evtk.FormatError` at it; where reading stopped
        is kept in ``damage`` (a :class:`Damage`) and said in ``warnings``.
    """

    format = "?"

    def __init__(self, path: str | os.PathLike[str], salvage: bool = False) -> None:
        self.path = os.fspath(path)
        self.salvage = bool(salvage)
        self.damage: Damage | None = None
        self.warnings: list[str] = []
        self._closed = False

    # -- lifetime -------------------------------------------------------------
    def close(self) -> None:
        """Release the file (and its decoder threads); a second call does nothing."""
        if not self._closed:
            self._closed = True
            self._close()

    def _close(self):  # pragma: no cover - overridden
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def __del__(self):
        try:
            self.close()
        except Exception:
            pass

    def __repr__(self):
        return f"{type(self).__name__}({self.path!r}, format={self.format!r})"

    def _check_open(self):
        if self._closed:
            raise EvtkError(f"{self.path}: the recording is closed")

    # -- interface -------------------------------------------------------------
    sensor_size: tuple[int, int] | None = None
    _salvage_cache: Events | None = None

    @property
    def streams(self) -> list[StreamInfo]:  # pragma: no cover - overridden
        raise NotImplementedError

    @property
    def metadata(self) -> dict:
        return {}

    def events(self, t_start_us: int | None = None, t_end_us: int | None = None) -> Events:  # pragma: no cover
        """The events with ``t_start_us <= t < t_end_us``, read at once.

        Readers with an index (AEDAT4's data table, the HDF5 time index, Parquet row-group statistics) read
        only the blocks the window needs, after checking the index against the data at its edges.

        Parameters
        ----------
        t_start_us : int, optional
            First time kept (µs, inclusive); None: from the start.
        t_end_us : int, optional
            End of the window (µs, exclusive); None: to the end.

        Returns
        -------
        Events
            The events in file order, with the recording's sensor size.

        Raises
        ------
        FormatError
            Damage met while reading (not with ``salvage=True``: the events before it are returned).
        EvtkError
            When the events would not fit the memory budget (:func:`evtk.limits.require_memory`), or the
            recording is closed.
        """
        raise NotImplementedError

    def triggers(self, t_start_us: int | None = None, t_end_us: int | None = None) -> Triggers:
        """The trigger edges with ``t_start_us <= t < t_end_us``.

        Parameters
        ----------
        t_start_us : int, optional
            First time kept (µs, inclusive); None: from the start.
        t_end_us : int, optional
            End of the window (µs, exclusive); None: to the end.

        Returns
        -------
        Triggers
            Their times, kinds and channels, in file order (none for a format without triggers).

        Raises
        ------
        FormatError
            Damage met while reading them (not with ``salvage=True``).
        """
        return Triggers()

    def iter_events(self, chunk_events: int = 1_000_000, t_start_us: int | None = None,
                    t_end_us: int | None = None) -> Iterator[Events]:
        """The events with ``t_start_us <= t < t_end_us`` in chunks, in file order, never all in memory at once.

        Parameters
        ----------
        chunk_events : int
            Events a chunk holds, about (a reader may give chunks of its blocks' sizes).
        t_start_us : int, optional
            First time kept (µs, inclusive); None: from the start.
        t_end_us : int, optional
            End of the window (µs, exclusive); None: to the end.

        Yields
        ------
        Events
            One chunk after another; together, what :meth:`events` returns.

        Raises
        ------
        FormatError
            Damage met while reading (not with ``salvage=True``: the iteration ends at it).
        """
        raise NotImplementedError  # pragma: no cover

    @property
    def compression(self) -> str | None:
        return None

    # -- derived -----------------------------------------------------------------
    def _main(self, typ):
        return next((s for s in self.streams if s.type == typ), None)

    @property
    def t_start_us(self):
        s = self._main("EVTS")
        return s.t_start_us if s else None

    @property
    def t_end_us(self):
        s = self._main("EVTS")
        return s.t_end_us if s else None

    def info(self) -> dict[str, Any]:
        """A JSON-ready summary (what ``evtk info --json`` prints).

        Counts and times are as the file's headers and indexes give them, without reading the events
        (:meth:`scan` reads them).

        Returns
        -------
        dict
            ``path``, ``format``, ``compression``, ``events`` and ``triggers`` (counts), ``sensor_size``
            (``[width, height]`` or None), ``t_start_us`` and ``t_end_us`` (µs, or None), ``streams``
            (:meth:`StreamInfo.as_dict` each), ``metadata``, the format's own entries, and ``warnings`` and
            (with salvage) ``damage`` where there are any.
        """
        streams = self.streams
        ev = next((s for s in streams if s.type == "EVTS"), None)
        tr = next((s for s in streams if s.type == "TRIG"), None)
        out = {
            "path": self.path,
            "format": self.format,
            "compression": self.compression,
            "events": ev.count if ev else 0,
            "triggers": tr.count if tr else 0,
            "sensor_size": list(self.sensor_size) if self.sensor_size else None,
            "t_start_us": ev.t_start_us if ev else None,
            "t_end_us": ev.t_end_us if ev else None,
            "streams": [s.as_dict() for s in streams],
            "metadata": self.metadata,
        }
        out.update(self._extra_info())
        out.update(self._damage_info())
        return out

    def _damage_info(self) -> dict:
        out: dict = {}
        if self.warnings:
            out["warnings"] = list(self.warnings)
        if self.salvage:
            out["damage"] = None if self.damage is None else {"offset": self.damage.offset, "reason": self.damage.reason}
        return out

    def _warn_once(self, topic: str, detail: str):
        """A warning ``topic (detail)``, unless one on ``topic`` is there already."""
        if not any(w.startswith(topic) for w in self.warnings):
            self.warnings.append(f"{topic} ({detail})")

    def _read_span(self, chunk_events: int = 1_000_000):
        """``(count, first t, last t)`` of the events :meth:`iter_events` gives, in one pass."""
        n, first, last = 0, None, None
        for ev in self.iter_events(chunk_events=chunk_events):
            if len(ev):
                first = int(ev.t[0]) if first is None else first
                n, last = n + len(ev), int(ev.t[-1])
        return n, first, last

    def scan(self, chunk_events: int = 1_000_000) -> dict[str, Any]:
        """Read every event and trigger once and report what reads.

        :meth:`info` reports what the file's headers and indexes say; with
        ``salvage=True`` this reports what :meth:`events` recovers, which
        damage found only by reading can make fewer. In strict mode it
        raises :class:`~evtk.FormatError` at the first damage instead.

        Parameters
        ----------
        chunk_events : int
            Events read at a time (:meth:`iter_events`).

        Returns
        -------
        dict
            ``events`` (count), ``t_start_us``, ``t_end_us`` (first and last stamp read, µs, or None),
            ``triggers`` (count), ``scanned`` (True), with ``warnings`` and (salvage) ``damage`` as they
            stand after the pass.

        Raises
        ------
        FormatError
            At the first damage, without salvage.
        """
        n, first, last = self._read_span(chunk_events)
        try:
            triggers = len(self.triggers())
        except FormatError as exc:
            if not self.salvage:
                raise
            triggers = 0
            self._warn_once("the triggers cannot be read; none counted", str(exc))
        return {"events": n, "t_start_us": first, "t_end_us": last, "triggers": triggers, "scanned": True,
                **self._damage_info()}

    def _extra_info(self) -> dict:
        return {}

    def _salvaged_window(self, t_start_us, t_end_us) -> Events:
        """With salvage, a time window is cut from what the whole read recovers (read once, then kept): a window
        must never hold events from beyond the damage that ends the full read. Readers whose index could reach
        past the damage call this for windowed reads in salvage mode."""
        if self._salvage_cache is None:
            self._salvage_cache = self.events()
        return self._salvage_cache.between(t_start_us, t_end_us)


def time_chunks(t: np.ndarray, max_events: int, max_us: int | None, is_sorted: bool) -> np.ndarray:
    """Indices where consecutive chunks of ``t`` start, plus ``len(t)``.

    A chunk holds at most ``max_events`` events and, for a sorted stream, spans
    less than ``max_us`` microseconds.  Used for AEDAT4 packets and Parquet
    row groups alike, so a short time window touches few of them.

    Parameters
    ----------
    t : numpy.ndarray
        Time stamps (int64, µs).
    max_events : int
        Most events in a chunk (at least 1).
    max_us : int or None
        Longest span of a chunk (µs), for a sorted stream; None: by count only.
    is_sorted : bool
        Whether ``t`` never decreases (an unsorted stream is cut by count only).

    Returns
    -------
    numpy.ndarray
        int64 boundaries ``[0, ..., len(t)]``: chunk ``k`` is ``t[b[k]:b[k + 1]]`` (just ``[0]`` for no
        events when cut by time).
    """
    n = len(t)
    if max_us is None or not is_sorted:
        return np.append(np.arange(0, n, max_events, dtype=np.int64), n)
    cuts = [0]
    i = 0
    t_max = int(np.iinfo(np.int64).max)
    while i < n:
        limit = int(t[i]) + max_us
        j = int(np.searchsorted(t, limit, side="left")) if limit <= t_max else n
        i = min(max(j, i + 1), i + max_events)
        cuts.append(i)
    return np.asarray(cuts, np.int64)


def window_blocks(t_lo: Sequence[int | None], t_hi: Sequence[int | None], t_start_us: int | None,
                  t_end_us: int | None, actual: Callable[[int], tuple[int, int] | None]) -> tuple[int, int] | None:
    """The blocks (packets, row groups) a time window needs, by a file's index, checked against the data.

    ``t_lo[k]``/``t_hi[k]`` are the first and last time an index gives block ``k`` (None when it gives
    none); ``actual(k)`` reads block ``k`` and returns its ``(first, last)`` time stamp, or None when it is
    empty or cannot be read. Returns ``(a, b)``: blocks ``a..b-1`` hold every event of the window, checked
    by reading the nearest non-empty block on each side of the range (exact for time-ordered data, which
    the readers verify as they read). Returns None when the index cannot be used: some block without
    times, times out of order, or an edge block whose stamps contradict it (an index that lies); the caller
    then reads every block.

    Parameters
    ----------
    t_lo, t_hi : sequence of int or None
        First and last time stamp (µs) of each block, as the file's index states them.
    t_start_us, t_end_us : int or None
        The window, ``t_start_us <= t < t_end_us`` (None: open on that side).
    actual : callable
        ``actual(k)``: block ``k``'s true ``(first, last)`` stamps, read from it, or None.

    Returns
    -------
    tuple of (int, int) or None
        ``(a, b)``, the blocks ``a..b-1`` to read, or None when the index cannot be trusted.
    """
    n = len(t_lo)
    if any(v is None for v in t_lo) or any(v is None for v in t_hi):
        return None
    lo = np.asarray(t_lo, np.int64)
    hi = np.asarray(t_hi, np.int64)
    if n and (np.any(lo > hi) or np.any(np.diff(lo) < 0) or np.any(np.diff(hi) < 0)):
        return None
    a = 0 if t_start_us is None else int(np.searchsorted(hi, int(t_start_us), side="left"))
    b = n if t_end_us is None else max(a, int(np.searchsorted(lo, int(t_end_us), side="left")))
    if t_start_us is not None:
        k = a - 1
        while k >= 0:  # the last events before the range must come before the window
            got = actual(k)
            if got is not None:
                if got[1] >= int(t_start_us) or got[0] != lo[k] or got[1] != hi[k]:
                    return None
                break
            k -= 1
    if t_end_us is not None:
        k = b
        while k < n:  # ... and the first events after it at or after its end
            got = actual(k)
            if got is not None:
                if got[0] < int(t_end_us) or got[0] != lo[k] or got[1] != hi[k]:
                    return None
                break
            k += 1
    return a, b
