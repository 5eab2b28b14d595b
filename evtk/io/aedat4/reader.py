"""Reading an AEDAT4 file: streams, packet bodies, events and triggers by time window, salvage."""

from __future__ import annotations

import os
import struct
from collections.abc import Iterator
from typing import TYPE_CHECKING

import numpy as np

from ..._native import decode_lz4_batch as native_decode_lz4_batch
from ..._native import decode_lz4_range as native_decode_lz4_range
from ..._native import enabled as native_enabled
from ..._threads import MEMORY_SHARE, helpers, workers_within
from ...errors import EvtkError, FormatError
from ...events import Events, Triggers
from .. import _compression as cz
from .. import _fbpy
from ..base import BaseRecording, StreamInfo, load_json
from .common import _STRUCT_SIZE, _TYPE_NAMES, _VECTOR_TYPES, _status
from .index import _CountMismatch, _FileIndex, _Stop

if TYPE_CHECKING:
    import numpy.typing as npt

#: Events a decode thread takes from the file at a time (1 MiB of FlatBuffers events, which stay in a core's
#: cache for the column copies): see ``Recording._batcher``.
BATCH_EVENTS = 1 << 16
#: The least events of a batch in a read of fewer than ``16 * BATCH_EVENTS`` events, whose batches hold a
#: sixteenth of it (at most :data:`BATCH_EVENTS`): a batch's compressed bytes and staging buffer are memory a
#: fresh process touches for the first time, a page fault per 4 KiB (24 bytes an event of a batch), and a
#: recording of 100 k events read in 64 k-event batches touched 1.2 MB more of it than in 8 k-event ones
#: (600 page faults, 1-1.5 ms of a 3-4 ms decode here), while a large read keeps its batches' calls few.
SMALL_BATCH_EVENTS = 1 << 13
#: The most bytes one read of packet headers covers when a stream's first read checks the data table's stream ids
#: against the headers of the packets it gives to other streams (``Recording._first_header_naming``), into one
#: buffer kept for the check.
HEADER_STRETCH_BYTES = 1 << 18
#: Bytes a read of headers may cover for each header in it: about what a read call costs here (1-1.5 us) at the
#: page cache's 10 GB/s; headers farther apart are read one by one.
HEADER_READ_BYTES = 1 << 14
# room in a thread's staging buffer for packet headers and the bytes after a packet's events
_BATCH_SLACK = 1 << 16
# a decode thread's buffers with batches of BATCH_EVENTS: the staging buffer (16 bytes an event and the slack), the
# batch's compressed bytes, its allocator arena's share (about 2.5 MiB); in proportion for a small read's batches
_THREAD_BYTES = 40 * BATCH_EVENTS

#: The share of a chunk's memory its decoding threads may add in a chunked read (``iter_events``): its memory is
#: a chunk's whatever the file's size, and :data:`evtk._threads.MEMORY_SHARE` (a whole read's rule) of a 1 M-event
#: chunk pays for one thread, which left the chunk-by-chunk counting of fixed windows decoding on one core.
_CHUNK_SHARE = 1.0
#: Most threads decoding a prefetched chunk (the prefetching thread among them; the consumer helps once it has
#: counted its own). Set on a 16-core machine in issue 32's tenth round, when the consumer counted with numpy and
#: kept the GIL most of the time: more threads only took turns for it, with no time saved and 10-20 % more CPU
#: time. The counting and the decoding now release the GIL (compiled), so on many cores the cap may hold the
#: chunked commands back against a read that decodes on every core; on two cores it never binds. Not remeasured
#: since (``benchmarks/device_run.sh caps`` does).
PREFETCH_THREADS = 3


class Recording(_FileIndex, BaseRecording):
    """An AEDAT4 file opened for reading.

    Use :func:`evtk.open` rather than this class directly.  The file is
    indexed on open (through its data table when it has a usable one, else
    by walking the packet headers); packet bodies are read only when asked.

    Parameters
    ----------
    path : str or os.PathLike
        The ``.aedat4`` file.
    salvage : bool
        Return what is intact before the first damage instead of raising
        :class:`~evtk.FormatError`; :attr:`damage` then says where it stopped.
    verify_checksums : bool
        Check the checksums packet bodies carry (on by default; see :func:`evtk.open`).
    """

    format = "aedat4"

    def __init__(self, path: str | os.PathLike[str], salvage: bool = False, verify_checksums: bool = True) -> None:
        super().__init__(path, salvage)
        self._fd = -1
        self._spans: dict = {}  # stream id -> each packet's (earliest, latest) stamp, read on the first window
        self._hidden: dict[int, int | None] = {}  # stream id -> row of a packet the data table gives another stream
        self.verify_checksums = bool(verify_checksums)
        try:
            self._fd = os.open(self.path, os.O_RDONLY)
        except OSError as exc:
            raise EvtkError(f"cannot open {self.path}: {exc.strerror}") from None
        try:
            self._size = os.fstat(self._fd).st_size
            self._read_header()
            self._index = self._build_index()
        except BaseException:
            os.close(self._fd)
            self._fd = -1
            raise

    def _close(self):
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1

    def __repr__(self):
        return f"Recording({self.path!r}, format='aedat4', streams={[s.name for s in self._streams.values()]})"

    def _stream_names(self):
        return [(s.name, s.type) for s in self._streams.values()]

    # -- streams ------------------------------------------------------------------
    @property
    def compression(self) -> str:
        return cz.CODE_NAMES[self._code].lower()

    def _stream(self, stream, typ) -> StreamInfo | None:
        if stream is None:
            candidates = [s for s in self._streams.values() if s.type == typ]
            preferred = [s for s in candidates if s.name == _TYPE_NAMES[typ]]
            return (preferred or candidates)[0] if (preferred or candidates) else None
        for s in self._streams.values():
            if stream == s.id or stream == s.name:
                if s.type != typ:
                    raise EvtkError(f"{self.path}: stream {stream!r} holds {s.type} packets, not {typ}")
                return s
        raise EvtkError(f"{self.path}: no stream {stream!r}; streams are {[s.name for s in self._streams.values()]}")

    @property
    def sensor_size(self):
        """``(width, height)`` of the main event stream, or None without one."""
        s = self._stream(None, "EVTS")
        if s is None:
            s = next((s for s in self._streams.values() if s.sensor_size), None)
        return s.sensor_size if s is not None else None

    @property
    def streams(self) -> list[StreamInfo]:
        """Every stream with its packet and element counts and time range."""
        idx = self._index
        for s in self._streams.values():
            sel = idx.stream == s.id
            s.packets = int(sel.sum())
            counts = idx.count[sel]
            if s.type == "FRME":
                counts = np.ones(s.packets, np.int64)
            elif np.any(counts < 0):
                counts = self._count_elements(np.flatnonzero(sel), s.type)
            s.count = int(counts.sum()) if counts is not None else None
            if s.packets and idx.from_table:
                # (salvage: the packets counted, those before the damage)
                nz = counts > 0 if counts is not None else np.ones(s.packets, bool)
                rows = np.flatnonzero(sel)[:len(nz)]
                s.t_start_us = int(idx.t0[rows][nz].min()) if nz.any() else None
                s.t_end_us = int(idx.t1[rows][nz].max()) if nz.any() else None
        if not idx.from_table:
            self._fill_times()
        return list(self._streams.values())

    def _count_elements(self, rows, typ):
        if typ not in _VECTOR_TYPES:
            return None
        out = np.zeros(len(rows), np.int64)
        scratch = cz.Scratch()
        for k, i in enumerate(rows):
            try:
                b = self._body(i, scratch)
            except _Stop:
                return out[:k]
            n = _fbpy.vector_length(b, typ.encode(), _STRUCT_SIZE.get(typ, 0))
            if n < 0:
                try:
                    self._fail(int(self._index.offset[i]), f"{typ} packet: {_status(n)}")
                except _Stop:
                    return out[:k]
            out[k] = n
            self._index.count[i] = n
        return out

    def _fill_times(self):
        ev = self._stream(None, "EVTS")
        if ev is not None and ev.count:
            events = self.events()
            ev.t_start_us, ev.t_end_us = events.t_start_us, events.t_end_us
        tr = self._stream(None, "TRIG")
        if tr is not None and tr.count:
            trig = self.triggers()
            if len(trig):
                tr.t_start_us, tr.t_end_us = int(trig.t.min()), int(trig.t.max())

    @property
    def metadata(self) -> dict:
        """evtk metadata stored with the event stream (``evtkMetadata``), else {}."""
        s = self._stream(None, "EVTS")
        text = s.attributes.get("evtkMetadata") if s is not None else None
        if not text:
            return {}
        value = load_json(text, self.path, "the evtkMetadata attribute")
        return value if isinstance(value, dict) else {"value": value}

    # -- packet bodies ------------------------------------------------------------
    def _body(self, i, scratch: cz.Scratch | None = None):
        """Decompressed body of packet ``i`` as a uint8 array (or raise/stop).

        With ``scratch`` (one per thread, see :class:`~evtk.io._compression.Scratch`) the packet is read and
        decompressed into its buffers and the array returned is a view of them, valid until the next call
        with it: a loop over packets then allocates nothing per packet. Without, it is a new buffer.
        """
        idx = self._index
        off, size = int(idx.offset[i]), int(idx.size[i])
        data = self._pread(size + 8, off - 8) if scratch is None else self._pread_into(scratch.room(size + 8), off - 8)
        if len(data) < size + 8:
            self._fail(off - 8, "file ends inside a packet")
        sid, sz = struct.unpack_from("<ii", data, 0)
        if sid != idx.stream[i] or sz != size:
            self._fail(off - 8, f"packet header says stream {sid}, {sz} bytes; "
                                f"the data table says stream {idx.stream[i]}, {size} bytes")
        body = memoryview(data)[8:]
        if self._code == cz.NONE and cz.sniff(body):
            self._fail(off, f"the header declares no compression but the body is a {cz.sniff(body)} frame")
        try:
            if scratch is None:
                return np.frombuffer(cz.decompress(self._code, body, cz.output_limit(size), self.verify_checksums),
                                     np.uint8)
            return cz.decompress_into(self._code, body, cz.output_limit(size), self.verify_checksums, scratch)
        except cz.CodecError as exc:
            self._fail(off, f"packet body cannot be decompressed: {exc}")
            raise  # pragma: no cover - _fail always raises

    def _pread_into(self, buf, offset: int):
        """Read ``len(buf)`` bytes at ``offset`` into ``buf`` (fewer at the end of the file).

        Returns
        -------
        numpy.ndarray
            The part of ``buf`` read.
        """
        return buf[:os.preadv(self._open_fd(), [buf], offset)]

    def _open_fd(self) -> int:
        """The file's descriptor; an :class:`~evtk.errors.EvtkError` once the recording is closed."""
        if self._fd < 0:
            raise EvtkError(f"{self.path}: the recording is closed")
        return self._fd

    def _select(self, typ, stream, t_start_us, t_end_us):
        """The stream of ``typ`` and the rows of its packets that can hold stamps in the window.

        Returns
        -------
        s : StreamInfo or None
            The stream (None when the file has none of ``typ``).
        rows : numpy.ndarray
            Its packets' rows in the index, in file order: with a data table and a window, those whose stamps
            (:meth:`_packet_spans`) meet the window; else all.
        edge : numpy.ndarray or None
            Per row of ``rows``, whether the packet may hold stamps outside the window (True: its events
            are to be filtered; False: it lies inside the window, kept whole); None without a window.
        """
        s = self._stream(stream, typ)
        if s is None:
            return None, np.zeros(0, np.int64), None
        idx = self._index
        rows = self._stream_rows(s)
        if t_start_us is None and t_end_us is None:
            return s, rows, None
        if not idx.from_table:
            return s, rows, np.ones(len(rows), bool)
        lo, hi = self._packet_spans(s, rows)
        keep = np.ones(len(rows), bool)
        inside = np.ones(len(rows), bool)
        if t_start_us is not None:
            keep &= hi >= int(t_start_us)
            inside &= lo >= int(t_start_us)
        if t_end_us is not None:
            keep &= lo < int(t_end_us)
            inside &= hi < int(t_end_us)
        return s, rows[keep], ~inside[keep]

    def _stream_rows(self, s: StreamInfo) -> np.ndarray:
        """The rows of stream ``s``'s packets in the index, in file order.

        The data table's stream ids are checked against the packets' headers (once per stream, and only the
        packets the table gives to other streams, which a read of ``s`` never opens): a damaged id that gave
        one of ``s``'s packets to another stream would drop its elements without a word. Such a packet is
        damage at its header: :class:`~evtk.FormatError`, or with salvage the rows before it.

        Parameters
        ----------
        s : StreamInfo
            The stream.

        Returns
        -------
        numpy.ndarray
            int64 rows (with salvage, those before a hidden packet).
        """
        idx = self._index
        rows = np.flatnonzero(idx.stream == s.id)
        if not idx.from_table:
            return rows
        if s.id not in self._hidden:
            self._hidden[s.id] = self._first_header_naming(s.id, np.flatnonzero(idx.stream != s.id))
        i = self._hidden[s.id]
        if i is None:
            return rows
        off = int(idx.offset[i])
        self._note(off - 8, f"packet header says stream {s.id}; the data table says stream {int(idx.stream[i])}")
        return rows[idx.offset[rows] < off]

    def _first_header_naming(self, sid: int, others: np.ndarray) -> int | None:
        """The first of the index rows ``others`` (in file order) whose packet header names stream ``sid``, or None.

        The 8-byte headers are read a stretch of the file at a time: one read covers the headers of a stretch of
        at most :data:`HEADER_STRETCH_BYTES` where they lie closer than :data:`HEADER_READ_BYTES` apart on
        average (a DAVIS recording's IMU packets between its event packets: one read for dozens), each header
        alone elsewhere (a frame's megabytes are not read for its header).

        Parameters
        ----------
        sid : int
            The stream id looked for.
        others : numpy.ndarray
            Rows of packets the data table gives to other streams, increasing.

        Returns
        -------
        int or None
            The first such row whose header says ``sid``.
        """
        if not len(others):
            return None
        at = self._index.offset[others] - 8  # the headers' positions, increasing
        stretch = (at - at[0]) // HEADER_STRETCH_BYTES  # which stretch of the file each header lies in
        cuts = [0, *(np.flatnonzero(stretch[1:] != stretch[:-1]) + 1).tolist(), len(at)]
        four = np.arange(4)
        buf = None  # one buffer for every stretch (a fresh megabyte a read cost more in page faults than the reads)
        for a, z in zip(cuts[:-1], cuts[1:]):
            lo, hi = int(at[a]), int(at[z - 1]) + 8
            if (z - a) * HEADER_READ_BYTES >= hi - lo:  # close together: one read
                if buf is None:
                    buf = np.empty(HEADER_STRETCH_BYTES + 8, np.uint8)
                b = self._pread_into(buf[:hi - lo], lo)
                rel = at[a:z] - lo
                whole = rel + 4 <= b.size  # (a short read at the end: those headers are not there)
                ids = b[rel[whole, None] + four].view("<i4")[:, 0]
                hit = np.flatnonzero(ids == sid)
                if hit.size:
                    return int(others[a + int(np.flatnonzero(whole)[hit[0]])])
                continue
            for k in range(a, z):  # far apart: each header alone
                head = self._pread(4, int(at[k]))
                if len(head) == 4 and struct.unpack_from("<i", head)[0] == sid:
                    return int(others[k])
        return None

    def _packet_spans(self, s, rows):
        """The earliest and latest time stamp of each packet of ``rows`` (stream ``s``), as the packets hold
        them: read once, on the first window, and kept.

        The data table's times are each packet's first and last stamp; a packet whose stamps are out of
        order can hold events outside them, so a window chosen by them could miss events that reading
        everything and filtering finds. Windows go by what the packets hold instead (an empty packet meets
        no window; packets after damage that stopped salvage meet every window). A table whose times differ
        from them gets a warning.

        Parameters
        ----------
        s : StreamInfo
            The event or trigger stream.
        rows : numpy.ndarray
            Its packets' rows in the index, in file order.

        Returns
        -------
        lo, hi : numpy.ndarray
            int64 per row: the earliest and latest stamp.
        """
        spans = self._spans.get(s.id)
        if spans is None:
            if s.type == "TRIG":
                n = len(rows)
                lo = np.full(n, np.iinfo(np.int64).min)
                hi = np.full(n, np.iinfo(np.int64).max)
                for k, got in enumerate(self._trigger_packets(s, rows)):  # where salvage stops, the packets
                    t = got.t                                              # left stay in every window
                    lo[k], hi[k] = (t.min(), t.max()) if len(t) else (np.iinfo(np.int64).max,
                                                                      np.iinfo(np.int64).min)
            else:
                lo, hi = self._event_spans(s, rows)
            spans = self._keep_spans(s, rows, lo, hi)
        return spans

    def _keep_spans(self, s, rows, lo, hi):
        """Keep each packet's earliest and latest stamp (``lo``, ``hi``: int64 per row of ``rows``, all of
        stream ``s``'s packets; ``lo > hi`` for an empty one) for the windows to come, warning once where the
        data table's times differ from them. Returns ``(lo, hi)``."""
        spans = self._spans[s.id] = (lo, hi)
        idx = self._index
        table = (idx.t0[rows], idx.t1[rows])
        read = lo <= hi
        if np.any(read & ((table[0] != lo) | (table[1] != hi))):
            self._warn_once("the data table's packet times disagree with the packets or are out of order; "
                            "windows go by the times the packets hold", s.name)
        return spans

    def _learning_spans(self, s, rows, counts, chunks):
        """Pass the chunks of a read of all of stream ``s``'s packets (``rows``, ``counts`` events each, decoded
        whole and in order: :meth:`_chunks_from_table`'s) through, taking each packet's earliest and latest stamp
        from them; once the read has gone through every packet, keep them (:meth:`_keep_spans`) as the windowed
        reads' scan would have, so that later windowed reads of this open recording skip packets without that
        scan. Returns what ``chunks`` returns."""
        cum = np.zeros(len(rows) + 1, np.int64)
        np.cumsum(counts, out=cum[1:])
        lo = np.full(len(rows), np.iinfo(np.int64).max)
        hi = np.full(len(rows), np.iinfo(np.int64).min)
        pos = 0
        while True:
            try:
                ev = next(chunks)
            except StopIteration as stop:
                result = stop.value
                break
            n = len(ev)
            a = int(np.searchsorted(cum, pos, side="right")) - 1  # the packets this chunk's events belong to
            b = int(np.searchsorted(cum, pos + n, side="left"))
            seg = np.clip(cum[a:b + 1], pos, pos + n) - pos
            full = np.flatnonzero(seg[1:] > seg[:-1])
            if full.size:
                t = ev.t
                lo[a + full] = np.minimum(lo[a + full], np.minimum.reduceat(t, seg[full]))
                hi[a + full] = np.maximum(hi[a + full], np.maximum.reduceat(t, seg[full]))
            pos += n
            yield ev
        if result is None and pos == cum[-1]:
            self._keep_spans(s, rows, lo, hi)
        return result

    def _event_spans(self, s, rows):
        """The earliest and latest stamp of each event packet of ``rows``, on the I/O threads.

        Each packet is read and decompressed into its thread's scratch buffers and checked as
        :meth:`_event_packets` checks it (its FlatBuffer, every event on the sensor), and its stamps' least
        and greatest taken where they lie, nothing copied out. Damage stops the scan where the one-thread
        scan would stop it: the earliest damaged packet raises (strict) or ends what is scanned (salvage),
        and the packets from there on keep the widest span, meeting every window.

        Parameters
        ----------
        s : StreamInfo
            The event stream.
        rows : numpy.ndarray
            Its packets' rows in the index, in file order.

        Returns
        -------
        lo, hi : numpy.ndarray
            int64 per row: the earliest and latest stamp (``lo > hi`` for an empty packet).
        """
        n = len(rows)
        lo = np.full(n, np.iinfo(np.int64).min)
        hi = np.full(n, np.iinfo(np.int64).max)
        width, height = s.sensor_size
        ident = b"EVTS"

        def work(k0, k1):
            scratch = cz.Scratch()
            for k in range(k0, k1):
                i = rows[k]
                try:
                    b = self._body(i, scratch)
                    reason = None
                    start, count = _fbpy._root_vector(b, ident, _fbpy.EVENT_STRUCT)
                    if start < 0:
                        reason = f"event packet: {_status(start)}"
                    elif count == 0:
                        lo[k], hi[k] = np.iinfo(np.int64).max, np.iinfo(np.int64).min
                    else:
                        ev = b[start:start + _fbpy.EVENT_STRUCT * count].view(_fbpy.EVENT_DTYPE)
                        xs, ys = ev["x"], ev["y"]
                        if int(xs.max()) >= width or int(ys.max()) >= height:
                            first = int(np.argmax((xs >= width) | (ys >= height)))
                            reason = f"event {first} of the packet lies outside the {width}x{height} sensor"
                        else:
                            ts = ev["t"]
                            lo[k], hi[k] = ts.min(), ts.max()
                    if reason is not None:
                        self._fail(int(self._index.offset[i]), reason)
                except _Stop:
                    return k
            return k1

        stopped = _run_split(work, n, np.maximum(self._index.count[rows], 0))
        lo[stopped:] = np.iinfo(np.int64).min  # where salvage stopped: the packets left meet every window
        hi[stopped:] = np.iinfo(np.int64).max
        return lo, hi

    # -- events -------------------------------------------------------------------
    def events(self, t_start_us: int | None = None, t_end_us: int | None = None,
               stream: int | str | None = None) -> Events:
        """Events with ``t_start_us <= t < t_end_us`` (None: no bound).

        With a data table only the packets that overlap the window are
        decoded; both cores decompress.

        Parameters
        ----------
        t_start_us : int, optional
            First time kept (µs, inclusive); None: from the start.
        t_end_us : int, optional
            End of the window (µs, exclusive); None: to the end.
        stream : int or str, optional
            The event stream (id or name) of a file with several; None: the first.

        Returns
        -------
        Events
            The events, in file order.

        Raises
        ------
        FormatError
            When the file has no event stream, or at damage (without salvage), a failed checksum included.
        EvtkError
            When the events would not fit the memory budget.
        """
        try:
            return self._events(t_start_us, t_end_us, stream)
        except _CountMismatch:
            # the data table lied about a packet's size: count from the packets
            self.warnings.append("the data table's element counts are wrong; counted from the packets instead")
            self._index.count[:] = -1
            return self._events(t_start_us, t_end_us, stream)

    def _events(self, t_start_us, t_end_us, stream) -> Events:
        s, rows, edge = self._select("EVTS", stream, t_start_us, t_end_us)
        if s is None:
            raise FormatError(self.path, None, f"no event stream; the streams are {self._stream_names()}")
        counts = self._index.count[rows]
        if np.any(counts < 0):
            counts = self._count_elements(rows, "EVTS")
            rows = rows[: len(counts)]
        ev, _ = self._decode_rows(s, rows, counts)
        if edge is not None:
            ends = np.cumsum(counts)
            cut = edge[: len(rows)]
            ev = _cut(ev, (ends - counts)[cut], ends[cut], t_start_us, t_end_us)
        return ev

    def _decode_rows(self, s, rows, counts):
        """Decode the event packets ``rows`` (element counts known) on both cores.

        Returns ``(events, complete)``; with salvage, ``events`` is the intact
        prefix and ``complete`` False when damage stopped the decoding. The events know whether they are in time
        order where the decoding found out (:meth:`_decode_into`).
        """
        total = int(np.sum(counts))
        t = np.empty(total, np.int64)
        x = np.empty(total, np.uint16)
        y = np.empty(total, np.uint16)
        p = np.empty(total, np.uint8)
        end, complete, ordered = self._decode_into(s, rows, counts, (t, x, y, p), 0)
        return Events._trusted(t[:end], x[:end], y[:end], p[:end], s.sensor_size, ordered), complete

    def _decode_into(self, s, rows, counts, out, offset, share=MEMORY_SHARE):
        """Decode the packets ``rows`` into the columns ``out`` from ``offset``, on the threads that ``share`` of
        the events' memory pays for (:func:`evtk._threads.workers_within`).

        Returns ``(events written, complete, ordered)``. ``ordered`` is whether the stamps written never
        decrease, the first of them included against the stamp before it in ``out`` (where ``offset`` is not 0),
        where the decoding can tell: the compiled range compares each stamp with the one before it in its packet
        as it splits the events (no pass of its own over the stamps), and each packet's first stamp is compared
        here with the stamp before it. None (not known: :attr:`evtk.Events.is_sorted` checks when asked) where a
        packet went another way (the Python loop, the one-batch kernel) or the decoding stopped early.
        """
        width, height = s.sensor_size
        t, x, y, p = out
        starts = np.full(len(rows) + 1, offset, np.int64)
        np.cumsum(counts, out=starts[1:])
        starts[1:] += offset
        ident = b"EVTS"
        decode = _fbpy.decode_events
        order = [False, False]  # [a packet decoded another way than the compiled range, a packet's stamps go back]
        batch = self._batcher(rows, counts, starts, out, width, height, order)

        free: list[cz.Scratch] = []  # the read's buffers: a range takes a set, gives it back for the next range

        def work(k0, k1):
            scratch = free.pop() if free else cz.Scratch()  # reused packet after packet (list ops: atomic)
            try:
                if batch is None:
                    return packets(k0, k1, scratch)
                return batch(k0, k1, scratch, packets)
            finally:
                free.append(scratch)

        def packets(k0, k1, scratch):
            order[0] = True  # (stamps not compared on the way)
            for k in range(k0, k1):
                i = rows[k]
                try:
                    b = self._body(i, scratch)
                except _Stop:
                    return k
                cap = int(counts[k])
                n, st = decode(b, ident, t, x, y, p, int(starts[k]), cap, width, height)
                if (st == _fbpy.ST_OK and n != cap) or st == _fbpy.ST_CAPACITY:
                    raise _CountMismatch
                if st != _fbpy.ST_OK:
                    off = int(self._index.offset[i])
                    if st == _fbpy.ST_COORD:
                        reason = f"event {n} of the packet lies outside the {width}x{height} sensor"
                    else:
                        reason = f"event packet: {_status(st)}"
                    try:
                        self._fail(off, reason)
                    except _Stop:
                        return k
            return k1

        # a thread's buffers scale with its batches, which a small read (a chunk) keeps small
        thread_bytes = max(1, _THREAD_BYTES * _batch_events(int(starts[-1] - starts[0])) // BATCH_EVENTS)
        stopped = _run_split(work, len(rows), counts, 0 if batch is None else thread_bytes, share)
        complete = stopped == len(rows)
        ordered = None
        if complete and order[1]:  # (a whole batch's stamps, all of them kept: out of order for certain)
            ordered = False
        elif complete and not order[0]:
            ordered = _edges_in_order(t, starts)
        return int(starts[stopped]) - offset, complete, ordered

    def _batcher(self, rows, counts, starts, out, width: int, height: int, order: list[bool]):
        """The batched decode of :meth:`_decode_into`'s packet ranges, or None where it does not apply.

        A thread's packets go a batch at a time (about :data:`BATCH_EVENTS` events, fewer in a small read: see
        :data:`SMALL_BATCH_EVENTS`): the batch's bytes come
        from the file in one read, each body is decompressed into the thread's staging buffer so that its
        events follow the previous packet's (the packet is put where its FlatBuffer header overlaps the end
        of the events before it, which are kept aside and put back), and the columns are copied out of the
        batch's events at once. Each packet then costs one call that releases the GIL (its decompression)
        instead of eight (its read, its decompression, four column copies and two range checks): with many
        threads, taking the GIL back after each such call is what kept more cores from reading faster.

        Where evtk's compiled kernels were built, a thread's whole range of LZ4 batches goes through one call that
        holds no GIL (:func:`evtk._native.decode_lz4_range`): each batch cut by the same rule and read with
        ``pread``, each body decompressed into the staging buffer and its events split straight into the columns,
        with every check below. A loop over the batches in Python held the GIL for about a tenth of a one-thread
        read: the part that runs one thread at a time however many cores read. A batch the range declines goes to the
        Python loop; where the range cannot run (a build before it), each batch goes through
        :func:`evtk._native.decode_lz4_batch` (one call a batch) first. Without the kernels the Python loop takes
        every batch.

        ``order`` is :meth:`_decode_into`'s: the compiled range sets ``order[1]`` where a packet's stamps go back
        in time within it; a batch decoded any other way sets ``order[0]`` (its stamps were not compared).

        The batch reports success only; at anything unexpected (packets far apart in the file, a header that
        disagrees with the data table, a body that fails to decompress or to parse, a count not the
        table's, an event off the sensor) it returns False and the caller decodes the batch packet by
        packet, which names the fault exactly as before.

        Returns
        -------
        callable or None
            ``batch(k0, k1, scratch, packets)``: decode rows ``k0:k1``, returning the first row not done;
            ``packets(a, b, scratch)`` is the packet-by-packet decode of rows ``a:b``.
        """
        if len(rows) == 0 or self._code not in (cz.NONE, cz.LZ4, cz.LZ4_HIGH, cz.ZSTD, cz.ZSTD_HIGH):
            return None
        idx = self._index
        offs_a, sizes_a = idx.offset[rows].astype(np.int64), idx.size[rows].astype(np.int64)
        sids_a, cnt_a = idx.stream[rows].astype(np.int64), np.ascontiguousarray(counts, np.int64)
        offs = offs_a.tolist()
        sizes = sizes_a.tolist()
        sids = sids_a.tolist()
        at = starts.tolist()
        cnt = cnt_a.tolist()
        code, verify, ident = self._code, self.verify_checksums, b"EVTS"
        lz4 = code in (cz.LZ4, cz.LZ4_HIGH)
        zstd = code in (cz.ZSTD, cz.ZSTD_HIGH)
        compiled = lz4 and native_enabled()  # evtk's compiled batches (the GIL released), where built
        t, x, y, p = out
        unpack_from = struct.unpack_from
        root_vector_at = _fbpy._root_vector_at
        searchsorted = np.searchsorted
        pread_into = self._pread_into
        slack = _BATCH_SLACK
        batch_events = _batch_events(at[-1] - at[0])

        def one(k, kb, scratch, kernel) -> bool:
            order[0] = True  # (stamps not compared on the way)
            o0 = offs[k] - 8
            span = offs[kb - 1] + sizes[kb - 1] - o0
            if span > 2 * (sum(sizes[k:kb]) + 8 * (kb - k)) + slack:
                return False  # other streams' packets between them: packet by packet
            raw = pread_into(scratch.room(span), o0)
            if len(raw) < span:
                return False
            raw_at = raw.ctypes.data
            n_ev = at[kb] - at[k]
            stage = scratch.stage(16 * n_ev + 3 * slack)
            if kernel:  # (not for a batch the range declined: the one-batch kernel checks the same, and declines too)
                lz4f = cz.lz4f_addresses(scratch)
                o, e = at[k], at[kb]
                if lz4f is not None and native_decode_lz4_batch(
                        raw, offs_a[k:kb] - (o0 + 8), sids_a[k:kb], sizes_a[k:kb], cnt_a[k:kb], verify, lz4f, stage,
                        cz.BODY_FLOOR_BYTES, cz.BODY_RATIO, cz.MAX_PACKET_BYTES, (t[o:e], x[o:e], y[o:e], p[o:e]),
                        (width, height)):
                    return True
            stage_at, room = stage.ctypes.data, len(stage)
            h = scratch.header_hint  # the last packet's header length: the first packet placed so that its
            base = rec = -1  # events start on a multiple of 16 bytes if its header is as long
            for j in range(k, kb):
                pos = offs[j] - 8 - o0
                sid, sz = unpack_from("<ii", raw, pos)
                if sid != sids[j] or sz != sizes[j]:
                    return False
                body = raw[pos + 8:pos + 8 + sz]
                # where the body goes: its header over the end of the events before it (kept aside), so that
                # its events follow them if its header is as long as the previous packet's
                dst = -h % 16 if base < 0 else max(0, rec - h)
                saved = None if base < 0 else stage[dst:rec].copy()
                limit = cz.output_limit(sz)
                if lz4:
                    n = cz.lz4_into_at(body, raw_at + pos + 8, limit, verify, scratch, stage_at + dst, room - dst)
                    if n < 0:
                        return False
                else:
                    if code == cz.NONE:
                        if cz.sniff(body):
                            return False
                        dec = body
                    else:
                        try:
                            dec = np.frombuffer(cz.decompress(code, body, limit, verify), np.uint8)
                        except cz.CodecError:
                            return False
                    n = len(dec)
                    if n > room - dst:
                        return False
                    stage[dst:dst + n] = dec
                st, c = root_vector_at(stage, dst, n, ident, 16)
                if st < 0 or c != cnt[j]:
                    return False
                if base < 0:
                    base = rec = dst + st
                elif dst + st != rec:  # a header of another length: its events moved to follow the others
                    stage[rec:rec + 16 * c] = stage[dst + st:dst + st + 16 * c]
                if saved is not None:
                    stage[dst:rec] = saved
                h = st
                rec += 16 * c
            scratch.header_hint = h
            o, e = at[k], at[kb]
            ev = stage[base:rec].view(_fbpy.EVENT_DTYPE)
            xs, ys = x[o:e], y[o:e]
            xs[...] = ev["x"]
            ys[...] = ev["y"]
            if e > o and (int(xs.max()) >= width or int(ys.max()) >= height):
                return False
            t[o:e] = ev["t"]
            ps = p[o:e]
            ps[...] = ev["p"]  # a bool on disk: 0 or 1 but for a damaged file, where any other byte means ON
            if e > o and int(ps.max()) > 1:
                np.not_equal(ps, 0, out=ps.view(np.bool_))
            return True

        # the range kernel until it cannot run (a build before it, no LZ4 library, no Zstandard library)
        ranged = [compiled or (zstd and native_enabled())]

        def through_range(k, k1, scratch, fd) -> int:
            """Rows ``k ..`` through the compiled range, growing its buffers as it asks: the first row not done."""
            while k < k1:
                lz4f: tuple[int, int, int, int] | None = (0, 0, 0, 0)  # (unused for Zstandard)
                zfns = None
                if zstd:  # the system's libzstd (zstandard exports none of its functions), or the Python loop
                    zfns = cz.zstd_addresses(scratch)
                else:
                    lz4f = cz.lz4f_addresses(scratch)
                got = None if lz4f is None or (zstd and zfns is None) else native_decode_lz4_range(
                    fd, offs_a, sids_a, sizes_a, cnt_a, starts, k, k1, batch_events, slack, scratch.read_room(0),
                    verify, lz4f, scratch.stage(0), cz.BODY_FLOOR_BYTES, cz.BODY_RATIO, cz.MAX_PACKET_BYTES, out,
                    (width, height), zfns)
                if got is None:
                    ranged[0] = False
                    return k
                k, need_raw, need_stage, _, back = got
                if back:
                    order[1] = True
                if not need_raw and not need_stage:
                    return k
                scratch.read_room(need_raw)
                scratch.stage(need_stage)
            return k

        def batch(k0, k1, scratch, packets) -> int:
            fd = self._open_fd()  # (closed meanwhile: said, not read from a descriptor another file may hold now)
            k = k0
            while k < k1:
                if ranged[0]:
                    k = through_range(k, k1, scratch, fd)
                    if k >= k1:
                        break
                # the first row past the batch (numpy's search: _bisect is a shared library more for a fresh
                # read to load, 0.2-0.7 ms; the starts are non-decreasing, so it is past k)
                past = min(k1 + 1, int(searchsorted(starts, at[k] + batch_events, "right")))
                kb = min(k1, max(k + 1, past - 1))
                if not one(k, kb, scratch, compiled and not ranged[0]):
                    got = packets(k, kb, scratch)
                    if got < kb:
                        return got
                k = kb
            return k1

        return batch

    def iter_events(self, chunk_events: int = 1_000_000, t_start_us: int | None = None, t_end_us: int | None = None,
                    stream: int | str | None = None) -> Iterator[Events]:
        """Yield the events in order, at most ``chunk_events`` at a time.

        Memory stays bounded by the chunk (plus one packet), whatever the
        size of the file.

        Parameters
        ----------
        chunk_events : int
            Most events a chunk holds (at least 1).
        t_start_us : int, optional
            First time kept (µs, inclusive); None: from the start.
        t_end_us : int, optional
            End of the window (µs, exclusive); None: to the end.
        stream : int or str, optional
            The event stream (id or name); None: the first.

        Yields
        ------
        Events
            The next chunk; together, what :meth:`events` returns.

        Raises
        ------
        FormatError
            When the file has no event stream, or at damage (without salvage).
        EvtkError
            When ``chunk_events`` is below 1.
        """
        chunk_events = int(chunk_events)
        if chunk_events < 1:
            raise EvtkError(f"chunk_events must be at least 1, got {chunk_events}")
        s, rows, edge = self._select("EVTS", stream, t_start_us, t_end_us)
        if s is None:
            raise FormatError(self.path, None, f"no event stream; the streams are {self._stream_names()}")
        counts = self._index.count[rows]
        if len(rows) and np.all(counts >= 0):
            stopped_at = yield from self._chunks_from_table(s, rows, counts, chunk_events, t_start_us, t_end_us,
                                                            edge)
            if stopped_at is None:
                return
            rows = rows[stopped_at:]
        yield from self._chunks_from_packets(s, rows, chunk_events, t_start_us, t_end_us)

    def iter_events_meeting(self, t_start_us: npt.ArrayLike, t_end_us: npt.ArrayLike, chunk_events: int = 1_000_000,
                            stream: int | str | None = None) -> Iterator[Events]:
        """Yield the events of the packets that may hold a stamp in any of the windows ``[t_start_us, t_end_us)``,
        in file order, at most ``chunk_events`` at a time, each packet whole (events outside the windows
        included: the caller keeps what it wants; a packet that meets no window is neither decoded nor yielded).

        The packets' spans are those a windowed read scans once per open recording (:meth:`_packet_spans`): when
        they are not known yet, or without a data table, or with salvage, every packet is read (the scan costs
        more than the decoding it would save), and a read that goes through all of them with a data table and
        without salvage keeps their spans for the next call.

        Parameters
        ----------
        t_start_us, t_end_us : array_like of int
            The windows' starts (inclusive) and ends (exclusive), µs, one each, in any order.
        chunk_events : int
            Most events a chunk holds (at least 1).
        stream : int or str, optional
            The event stream (id or name); None: the first.

        Yields
        ------
        Events
            The next chunk.

        Raises
        ------
        FormatError
            When the file has no event stream, or at damage (without salvage).
        EvtkError
            When ``chunk_events`` is below 1 or the starts and ends differ in number.
        """
        chunk_events = int(chunk_events)
        if chunk_events < 1:
            raise EvtkError(f"chunk_events must be at least 1, got {chunk_events}")
        starts = np.asarray(t_start_us, np.int64).ravel()
        ends = np.asarray(t_end_us, np.int64).ravel()
        if starts.shape != ends.shape:
            raise EvtkError(f"{starts.size} window starts for {ends.size} ends")
        s, rows, _ = self._select("EVTS", stream, None, None)
        if s is None:
            raise FormatError(self.path, None, f"no event stream; the streams are {self._stream_names()}")
        spans = self._spans.get(s.id)
        if spans is not None and self._index.from_table and not self.salvage and len(rows) == len(spans[0]):
            lo, hi = spans
            order = np.argsort(starts, kind="stable")
            first, reach = starts[order], np.maximum.accumulate(ends[order])
            # the first window (by start) that some window up to it ends after the packet's earliest stamp: the
            # packet meets a window exactly when that one starts by its latest stamp (an empty packet: none)
            j = np.searchsorted(reach, lo, side="right")
            keep = j < first.size
            keep[keep] = first[j[keep]] <= hi[keep]
            rows = rows[keep]
        counts = self._index.count[rows]
        if len(rows) and np.all(counts >= 0):
            chunks = self._chunks_from_table(s, rows, counts, chunk_events, None, None)
            if spans is None and self._index.from_table and not self.salvage:  # every packet read: learn their spans
                chunks = self._learning_spans(s, rows, counts, chunks)
            stopped_at = yield from chunks
            if stopped_at is None:
                return
            rows = rows[stopped_at:]
        yield from self._chunks_from_packets(s, rows, chunk_events, None, None)

    def _chunks_from_table(self, s, rows, counts, chunk_events, t_start_us, t_end_us, edge=None):
        """Chunks of at most ``chunk_events``, packets decoded on every core straight into each chunk's
        arrays (a window's: those of the packets that meet it, then the events of those that cross its
        edges (``edge``) outside it left out). Returns None when done, or the row to go on from packet
        by packet when the data table's counts prove wrong."""
        cum = np.zeros(len(rows) + 1, np.int64)
        np.cumsum(counts, out=cum[1:])
        buf = None
        fill = 0
        seg_lo: list[np.ndarray] = []  # where the current chunk's packets that cross the window's edges lie
        seg_hi: list[np.ndarray] = []
        ordered = [True]  # (bool or None) the chunk's stamps in order so far (None: not known)

        def part_ordered(in_order):  # a part of the chunk: out of order stays so, not known stays so unless out
            if in_order is not True and ordered[0] is not False:
                ordered[0] = in_order

        def chunk(n):
            ev = Events._trusted(buf[0][:n], buf[1][:n], buf[2][:n], buf[3][:n], s.sensor_size, ordered[0])
            ordered[0] = True
            if edge is None:
                return ev
            cut = (np.concatenate(seg_lo), np.concatenate(seg_hi)) if seg_lo else (np.zeros(0, np.int64),) * 2
            seg_lo.clear()
            seg_hi.clear()
            return _cut(ev, cut[0], cut[1], t_start_us, t_end_us)

        def new_buffer():
            return (np.empty(chunk_events, np.int64), np.empty(chunk_events, np.uint16),
                    np.empty(chunk_events, np.uint16), np.empty(chunk_events, np.uint8))

        k = 0
        while k < len(rows):
            if buf is None:
                buf, fill = new_buffer(), 0
            # the packets that fit whole in what is left of the chunk
            j = int(np.searchsorted(cum, cum[k] + (chunk_events - fill), side="right")) - 1
            try:
                if j > k:
                    n, complete, in_order = self._decode_into(s, rows[k:j], counts[k:j], buf, fill, _CHUNK_SHARE)
                    part_ordered(in_order)  # (each part compared with the chunk's stamps before it too)
                    if edge is not None:
                        e = k + np.flatnonzero(edge[k:j])
                        seg_lo.append(fill + cum[e] - cum[k])
                        seg_hi.append(fill + cum[e + 1] - cum[k])
                    fill += n
                    k = j
                else:  # one packet larger than the room left: decode it alone and split it
                    ev1, complete = self._decode_rows(s, rows[k:k + 1], counts[k:k + 1])
                    pos = 0
                    while pos < len(ev1):
                        if buf is None:
                            buf, fill = new_buffer(), 0
                        take = min(chunk_events - fill, len(ev1) - pos)
                        part = ev1[pos:pos + take]  # (in order where the packet is; else its own check)
                        for dst, src in zip(buf, (part.t, part.x, part.y, part.p)):
                            dst[fill:fill + take] = src
                        # the part in order and its first stamp no earlier than the chunk's last before it (a
                        # packet's order not known: not known)
                        part_ordered(None if ev1._sorted is None else
                                     part.is_sorted and (fill == 0 or bool(buf[0][fill] >= buf[0][fill - 1])))
                        if edge is not None and edge[k]:
                            seg_lo.append(np.array([fill], np.int64))
                            seg_hi.append(np.array([fill + take], np.int64))
                        fill += take
                        pos += take
                        if fill == chunk_events:
                            ev = chunk(fill)
                            if len(ev):
                                yield ev
                            buf = None
                    k += 1
            except _CountMismatch:  # the table lied: hand over what is complete, go on packet by packet
                self.warnings.append("the data table's element counts are wrong; counted from the packets instead")
                if buf is not None and fill:
                    ev = chunk(fill)
                    if len(ev):
                        yield ev
                return k
            if not complete:
                break
            if buf is not None and fill == chunk_events:
                ev = chunk(fill)
                if len(ev):
                    yield ev
                buf = None
        if buf is not None and fill:
            ev = chunk(fill)
            if len(ev):
                yield ev
        return None

    def _chunks_from_packets(self, s, rows, chunk_events, t_start_us, t_end_us):
        pending: list[Events] = []
        held = 0
        for ev in self._event_packets(s, rows):
            if t_start_us is not None or t_end_us is not None:
                ev = ev.between(t_start_us, t_end_us)
            if not len(ev):
                continue
            pending.append(ev)
            held += len(ev)
            while held >= chunk_events:
                joined = Events.concatenate(pending)
                yield joined[:chunk_events]
                rest = joined[chunk_events:]
                pending = [rest] if len(rest) else []
                held = len(rest)
        if held:
            yield Events.concatenate(pending)

    def _event_packets(self, s, rows):
        width, height = s.sensor_size
        ident = b"EVTS"
        scratch = cz.Scratch()
        for i in rows:
            try:
                b = self._body(i, scratch)
            except _Stop:
                break
            n = _fbpy.vector_length(b, ident, _fbpy.EVENT_STRUCT)
            if n < 0:
                try:
                    self._fail(int(self._index.offset[i]), f"event packet: {_status(n)}")
                except _Stop:
                    break
            cols = (np.empty(n, np.int64), np.empty(n, np.uint16), np.empty(n, np.uint16), np.empty(n, np.uint8))
            got, st = _fbpy.decode_events(b, ident, *cols, 0, n, width, height)
            if st != _fbpy.ST_OK:
                reason = (
                    f"event {got} of the packet lies outside the {width}x{height} sensor"
                    if st == _fbpy.ST_COORD else f"event packet: {_status(st)}"
                )
                try:
                    self._fail(int(self._index.offset[i]), reason)
                except _Stop:
                    break
            yield Events._trusted(*cols, s.sensor_size)

    # -- triggers -------------------------------------------------------------------
    def triggers(self, t_start_us: int | None = None, t_end_us: int | None = None,
                 stream: int | str | None = None) -> Triggers:
        """Trigger time stamps and kinds (empty when the file has no trigger stream).

        Parameters
        ----------
        t_start_us : int, optional
            First time kept (µs, inclusive); None: from the start.
        t_end_us : int, optional
            End of the window (µs, exclusive); None: to the end.
        stream : int or str, optional
            The trigger stream (id or name); None: the first.

        Returns
        -------
        Triggers
            In file order; all of channel 0 (AEDAT4 has no channels).

        Raises
        ------
        FormatError
            At damage in a trigger packet (without salvage).
        """
        s, rows, _ = self._select("TRIG", stream, t_start_us, t_end_us)
        if s is None:
            return Triggers()
        trig = self._decode_triggers(s, rows)
        if t_start_us is not None or t_end_us is not None:
            trig = trig.between(t_start_us, t_end_us)
        return trig

    def _decode_triggers(self, s, rows) -> Triggers:
        return Triggers.concatenate(self._trigger_packets(s, rows))

    def _trigger_packets(self, s, rows):
        """Yield the triggers of each packet of ``rows``, stopping where salvage stops."""
        ident = b"TRIG"
        scratch = cz.Scratch()
        for i in rows:
            try:
                b = self._body(i, scratch)
            except _Stop:
                return
            n = _fbpy.vector_length(b, ident, 0)
            if n < 0:
                try:
                    self._fail(int(self._index.offset[i]), f"trigger packet: {_status(n)}")
                except _Stop:
                    return
            t = np.empty(n, np.int64)
            k = np.empty(n, np.uint8)
            got, st = _fbpy.decode_triggers(b, ident, t, k, 0, n)
            if st != _fbpy.ST_OK:
                try:
                    self._fail(int(self._index.offset[i]), f"trigger packet: {_status(st)}")
                except _Stop:
                    return
            yield Triggers(t, k)

    def other_streams(self) -> list[StreamInfo]:
        """Streams that are neither events nor triggers (frames, IMU, ...), which evtk copies but does not decode.

        Returns
        -------
        list of StreamInfo
            Those streams, in the header's order.
        """
        return [st for st in self._streams.values() if st.type not in ("EVTS", "TRIG")]

    def packets(self, stream: int | str) -> Iterator[tuple[bytes, int, int | None, int | None]]:
        """Every packet of one stream, decompressed, as the file holds it (for copying the stream as it is).

        Parameters
        ----------
        stream : int or str
            The stream's id or name.

        Yields
        ------
        tuple of (bytes, int, int or None, int or None)
            ``(body, count, t_start_us, t_end_us)``: the decompressed FlatBuffer body, the elements it holds
            (from the data table or the packets; a frame packet counts 1), and its first and last time (µs)
            from the data table (None without one).

        Raises
        ------
        EvtkError
            When there is no such stream.
        FormatError
            At damage (without salvage: with it, the packets end there).
        """
        s = next((st for st in self._streams.values() if stream in (st.id, st.name)), None)
        if s is None:
            raise EvtkError(f"{self.path}: no stream {stream!r}")
        idx = self._index
        rows = self._stream_rows(s)
        if np.any(idx.count[rows] < 0):  # no data table: count what the packets hold (frames: one each)
            counted = self._count_elements(rows, s.type)
            if counted is None:
                idx.count[rows] = 1 if s.type == "FRME" else 0
        known = idx.from_table
        for i in rows:
            try:
                body = self._body(i)
            except _Stop:
                return
            yield (body.tobytes(), max(0, int(idx.count[i])), int(idx.t0[i]) if known else None,
                   int(idx.t1[i]) if known else None)

    @property
    def header(self) -> dict:
        """Every stream's attributes from the header XML, by stream name
        (``source``, ``sizeX``, ``tsOffset``, ``compression``, ...)."""
        return {s.name: dict(s.attributes) for s in self._streams.values()}

    def _extra_info(self) -> dict:
        return {"data_table": bool(self._index.from_table), "header": self.header}






def _cut(ev: Events, seg_lo: np.ndarray, seg_hi: np.ndarray, t_start_us: int | None,
         t_end_us: int | None) -> Events:
    """``ev`` with ``t_start_us <= t < t_end_us`` (None: no bound), as ``ev.between`` gives it, where only the
    events at ``seg_lo[i]:seg_hi[i]`` can lie outside the window (the packets that cross its edges).

    Parameters
    ----------
    ev : Events
        Decoded packets, in file order.
    seg_lo, seg_hi : numpy.ndarray
        int64 start and end (exclusive) of each stretch of ``ev`` to filter; clipped to ``ev``.
    t_start_us : int, optional
        First time kept (µs, inclusive); None: from the start.
    t_end_us : int, optional
        End of the window (µs, exclusive); None: to the end.

    Returns
    -------
    Events
        A slice of ``ev`` (no copy) when what is kept is contiguous, else a copy of the events kept.
    """
    n = len(ev)
    seg_hi = np.minimum(seg_hi, n)
    live = seg_lo < seg_hi
    seg_lo, seg_hi = seg_lo[live], seg_hi[live]
    if not len(seg_lo):
        return ev
    if len(seg_lo) > 16:  # many packets cross the edges (stamps out of order): filter every event at once
        return ev.between(t_start_us, t_end_us)
    keep = np.ones(n, bool)
    kept = n
    for u, v in zip(seg_lo.tolist(), seg_hi.tolist()):
        t, m = ev.t[u:v], keep[u:v]
        if t_start_us is not None:
            np.greater_equal(t, int(t_start_us), out=m)
        if t_end_us is not None:
            if t_start_us is not None:
                m &= t < int(t_end_us)
            else:
                np.less(t, int(t_end_us), out=m)
        kept -= (v - u) - int(np.count_nonzero(m))
    if kept == n:
        return ev
    if kept == 0:
        return ev[0:0]
    first = int(np.argmax(keep))
    end = n - int(np.argmax(keep[::-1]))
    if end - first == kept:
        return ev[first:end]
    return Events._trusted(ev.t[keep], ev.x[keep], ev.y[keep], ev.p[keep], ev.sensor_size, ev._sorted or None)


def _edges_in_order(t: np.ndarray, starts: np.ndarray) -> bool:
    """Whether each packet's first stamp in ``t`` (packet ``k``'s events at ``starts[k]:starts[k + 1]``) is no
    earlier than the stamp before it in the column, the last of the packets before (one comparison a packet: the
    compiled range has compared the stamps within each)."""
    at = starts[:-1]
    at = at[(at > 0) & (at < starts[-1])]
    return bool(np.all(t[at] >= t[at - 1]))


def _batch_events(n_events: int) -> int:
    """Events of a batch in a read of ``n_events``: :data:`BATCH_EVENTS`, or a sixteenth of a smaller read (at
    least :data:`SMALL_BATCH_EVENTS`)."""
    return min(BATCH_EVENTS, max(SMALL_BATCH_EVENTS, n_events >> 4))


def _run_split(work, n_rows, counts, thread_bytes: int = 0, share: float = MEMORY_SHARE) -> int:
    """Run ``work(k0, k1)`` over contiguous row ranges on the I/O pool.

    Each call returns the first row it did not finish (``k1`` on success);
    the result is the length of the intact prefix. With ``thread_bytes`` (one thread's buffers), no more
    threads work than ``share`` of the events' memory pays for (:func:`evtk._threads.workers_within`). On a
    prefetching thread (:func:`evtk._threads.helpers`) the calling thread takes ranges too, and the ranges are
    offered to the consumer of the chunk, which takes them once it would otherwise wait.
    """
    if n_rows == 0:
        return 0
    total = int(np.sum(counts))
    # no more threads than the events' memory pays for (each holds a batch's buffers): on 16 cores a 20 M-event
    # read peaked at 1.13-1.15x its arrays with one per core, and ran no faster than on 8
    nw = workers_within(13 * total, thread_bytes, share) if thread_bytes else cz.workers()
    if nw == 1 or n_rows < 4 or total < 200_000:
        return work(0, n_rows)
    # balance by elements, each range a (2 nw)-th of the events not yet given out, down to a (16 nw)-th of all:
    # long ranges first (few calls), short ones last, so that no thread is left decoding a long range alone at
    # the end (equal ranges, four a thread, left one core idle for up to a range: 30-40 ms of a 20 M-event read)
    marks: list[int] = []
    given, floor = 0, max(1, total // (16 * nw))
    while (given := given + max(floor, (total - given) // (2 * nw))) < total:
        marks.append(given)
    parts = len(marks) + 1
    cum = np.cumsum(counts)
    cuts = np.searchsorted(cum, marks, side="left")
    bounds = sorted({0, n_rows, *cuts.tolist()})  # (np.unique would import numpy.ma, 7-8 ms of a first read)
    ranges = iter(list(zip(bounds[:-1], bounds[1:])))  # taken in order by nw runners (next() holds the GIL)
    got: dict[int, tuple[int, int]] = {}
    failed: dict[int, BaseException] = {}

    def runner() -> None:
        for a, b in ranges:
            if failed:  # a range failed: the ranges after it are not needed (those before it are under way)
                return
            try:
                got[a] = (b, work(a, b))
            except BaseException as exc:  # noqa: BLE001 - raised below, the earliest range's first
                failed[a] = exc

    busy = min(nw, parts)
    offer = helpers()  # a prefetching thread decodes too, on one core fewer than it may use (the consumer counts
    # on that one), and the consumer joins once it would wait (:class:`evtk._threads.Helpers`)
    if offer is not None:
        busy = min(busy, max(1, cz.workers() - 1), PREFETCH_THREADS)
    futures = [cz.pool().submit(runner) for _ in range(busy - (offer is not None))]
    if offer is not None:
        offer.share(runner)
    for fut in futures:
        fut.result()
    if failed:  # the fault a read packet by packet would meet first, whichever thread met which
        raise failed[min(failed)]
    return min((stop for b, stop in got.values() if stop < b), default=n_rows)
