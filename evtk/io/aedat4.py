"""AEDAT4 reading and writing, byte-compatible with iniVation's dv-processing.

The layout evtk relies on is written down in ``docs/formats/aedat4.md``.  In
short: a magic line, a size-prefixed ``IOHeader`` FlatBuffer holding the
compression, the position of the data table and an XML description of the
streams, then packets (stream id, body size, compressed size-prefixed
FlatBuffer), then an optional ``FileDataTable`` indexing every packet.
"""

from __future__ import annotations

import json
import os
import struct
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from xml.sax.saxutils import escape

import numpy as np

from .._version import __version__
from ..errors import EvtkError, FormatError
from ..events import Events, Triggers
from . import _compression as cz
from . import _fbpy
from ._atomic import AtomicFile
from .base import BaseRecording, BaseWriter, Damage, StreamInfo, load_json, sensor_dims, time_chunks, window_blocks

__all__ = ["Recording", "Aedat4Writer", "write_aedat4", "MAGIC"]

MAGIC = b"#!AER-DAT4.0\r\n"
_HEADER_START = len(MAGIC)
_IDENT = {name: np.frombuffer(name.encode(), np.uint8) for name in ("EVTS", "TRIG", "IMUS", "FRME", "FTAB", "IOHE")}


def _jit():
    """The compiled FlatBuffers decoders and encoders (numba loads on first use: opening and describing a file
    with a data table needs none of them)."""
    from . import _fb

    return _fb
# types whose element count is the length of the root table's first vector
_VECTOR_TYPES = {"EVTS", "TRIG", "IMUS"}
# ... and the element size of those whose vector holds structs (which then ends the packet)
_STRUCT_SIZE = {"EVTS": _fbpy.EVENT_STRUCT}
_TYPE_NAMES = StreamInfo.KINDS

DEFAULT_PACKET_EVENTS = 8192
DEFAULT_PACKET_US = 10_000


class _Stop(Exception):
    def __init__(self, offset, reason):
        self.offset = offset
        self.reason = reason


class _CountMismatch(Exception):
    """A packet holds another number of elements than the data table says."""


class _PacketIndex:
    """Per-packet columns: body offset and size, stream, element count, time range."""

    def __init__(self, offset, size, stream, count, t0, t1, from_table):
        self.offset = np.asarray(offset, np.int64)
        self.size = np.asarray(size, np.int64)
        self.stream = np.asarray(stream, np.int64)
        self.count = np.asarray(count, np.int64)  # -1: unknown until decoded
        self.t0 = np.asarray(t0, np.int64)
        self.t1 = np.asarray(t1, np.int64)
        self.from_table = from_table

    def __len__(self):
        return len(self.offset)

    def take(self, mask):
        return _PacketIndex(
            self.offset[mask], self.size[mask], self.stream[mask], self.count[mask], self.t0[mask], self.t1[mask],
            self.from_table,
        )


def _parse_xml(text: str, path) -> dict:
    """Streams described by the header XML: ``{id: (attrs, info_attrs)}``."""
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise FormatError(path, _HEADER_START, f"the header's XML is malformed ({exc})") from None

    def attrs(node):
        out = {}
        for a in node.findall("attr"):
            key, typ, val = a.get("key"), a.get("type"), a.text or ""
            if key is None:
                continue
            try:
                if typ in ("int", "long", "short", "byte"):
                    out[key] = int(val)
                elif typ in ("float", "double"):
                    out[key] = float(val)
                elif typ == "bool":
                    out[key] = val.strip().lower() == "true"
                else:
                    out[key] = val
            except ValueError:
                raise FormatError(path, _HEADER_START, f"header attribute {key!r} is not a valid {typ}: {val!r}") from None
        return out

    streams = {}
    outinfo = None
    for node in root.iter("node"):
        if node.get("name") == "outInfo":
            outinfo = node
            break
    if outinfo is None:
        raise FormatError(path, _HEADER_START, "the header's XML has no 'outInfo' node describing the streams")
    for node in outinfo.findall("node"):
        try:
            sid = int(node.get("name"))
        except (TypeError, ValueError):
            continue
        info = node.find("node[@name='info']")
        streams[sid] = (attrs(node), attrs(info) if info is not None else {})
    return streams


class Recording(BaseRecording):
    """An AEDAT4 file opened for reading.

    Use :func:`evtk.open` rather than this class directly.  The file is
    indexed on open (through its data table when it has a usable one, else
    by walking the packet headers); packet bodies are read only when asked.

    Parameters
    ----------
    path : str or os.PathLike
    salvage : bool
        Return what is intact before the first damage instead of raising
        :class:`~evtk.FormatError`; :attr:`damage` then says where it stopped.
    """

    format = "aedat4"

    def __init__(self, path, salvage: bool = False, verify_checksums: bool = False):
        super().__init__(path, salvage)
        self._fd = -1
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

    def _pread(self, n, offset):
        if self._fd < 0:
            raise EvtkError(f"{self.path}: the recording is closed")
        data = os.pread(self._fd, n, offset)
        return data

    def _fail(self, offset, reason):
        """Raise in strict mode; in salvage mode record the damage and stop."""
        if not self.salvage:
            raise FormatError(self.path, offset, reason)
        if self.damage is None or offset < self.damage.offset:
            self.damage = Damage(int(offset), reason)
        raise _Stop(offset, reason)

    # -- header ---------------------------------------------------------------
    def _read_header(self):
        head = self._pread(_HEADER_START + 4, 0)
        if head[: len(MAGIC)] != MAGIC:
            if head.startswith(b"#!AER-DAT"):
                version = head[9:12].decode("ascii", "replace")
                raise FormatError(self.path, 0, f"AEDAT version {version} is not supported; evtk reads AEDAT 4.0")
            raise FormatError(self.path, 0, "not an AEDAT4 file (the magic line '#!AER-DAT4.0' is missing)")
        if len(head) < _HEADER_START + 4:
            raise FormatError(self.path, _HEADER_START, "file ends inside the header (no header length)")
        (hlen,) = struct.unpack_from("<I", head, _HEADER_START)
        self._data_start = _HEADER_START + 4 + hlen
        if self._data_start > self._size:
            raise FormatError(
                self.path, _HEADER_START,
                f"the header claims {hlen} bytes but the file has only {self._size - _HEADER_START - 4} after it",
            )
        # IOHeader is stored like a plain (not size-prefixed) buffer after its length
        buf = struct.pack("<I", hlen) + self._pread(hlen, _HEADER_START + 4)
        root = _fbpy.fb_root(buf, b"IOHE")
        if root < 0:
            raise FormatError(self.path, _HEADER_START + 4, "the IOHeader FlatBuffer is damaged (" + _status(root) + ")")
        # each field's whole value must lie inside the header (a field at the table's end read past it once)
        f_comp = _fbpy.fb_field(buf, root, 0, 4)
        f_dtp = _fbpy.fb_field(buf, root, 1, 8)
        f_xml = _fbpy.fb_field(buf, root, 2, 4)
        if f_comp < 0 or f_dtp < 0 or f_xml < 0:
            raise FormatError(self.path, _HEADER_START + 4, "the IOHeader FlatBuffer has offsets outside the header")
        code = _fbpy.i32(buf, f_comp) if f_comp else 0
        if not 0 <= code < len(cz.CODE_NAMES):
            raise FormatError(self.path, _HEADER_START + f_comp, f"unknown compression code {code} in the header")
        self._code = int(code)
        self._data_table_pos = int(_fbpy.i64(buf, f_dtp)) if f_dtp else -1
        if f_xml == 0:
            raise FormatError(self.path, _HEADER_START + 4, "the header has no stream description (infoNode)")
        s = _fbpy.fb_deref(buf, f_xml)
        if s < 0:
            raise FormatError(self.path, _HEADER_START + f_xml, "the header's infoNode string lies outside the header")
        slen = _fbpy.u32(buf, s)
        if s + 4 + slen > len(buf):
            raise FormatError(self.path, _HEADER_START + s, "the header's infoNode string runs past the header")
        self.header_xml = buf[s + 4 : s + 4 + slen].decode("utf-8", "replace").rstrip("\x00")
        described = _parse_xml(self.header_xml, self.path)
        self._streams: dict[int, StreamInfo] = {}
        for sid, (attrs, info) in sorted(described.items()):
            typ = str(attrs.get("typeIdentifier", "")).strip()
            name = str(attrs.get("originalOutputName", f"stream{sid}"))
            size = None
            if "sizeX" in info and "sizeY" in info:
                size = sensor_dims(info["sizeX"], info["sizeY"], self.path, f"the header of stream {sid}")
            elif typ == "EVTS":
                raise FormatError(self.path, _HEADER_START, f"event stream {sid} ({name}) has no sizeX/sizeY in its header")
            merged = dict(attrs)
            merged.update(info)
            self._streams[sid] = StreamInfo(sid, name, typ, sensor_size=size, attributes=merged)
        if not self._streams:
            raise FormatError(self.path, _HEADER_START, "the header describes no streams")

    # -- index ------------------------------------------------------------------
    def _build_index(self) -> _PacketIndex:
        dtp = self._data_table_pos
        if dtp >= 0:
            if dtp < self._data_start or dtp > self._size:
                if not self.salvage:
                    raise FormatError(
                        self.path, _HEADER_START,
                        f"the data table is said to start at byte {dtp}, outside the file of {self._size} bytes "
                        "(truncated file?)",
                    )
                self.damage = Damage(self._size, "file truncated: the data table lies past the end")
            else:
                table = self._read_data_table(dtp)
                if table is not None:
                    return table
        end = dtp if self._data_start <= dtp <= self._size else self._size
        return self._walk(end)

    def _read_data_table(self, dtp):
        body = self._pread(self._size - dtp, dtp)
        if not body:
            self.warnings.append("the data table is empty; packets were indexed by walking the file")
            return None
        try:
            raw = cz.decompress(self._code, body, cz.output_limit(len(body)), self.verify_checksums)
        except cz.CodecError as exc:
            self.warnings.append(f"the data table is unreadable ({exc}); packets were indexed by walking the file")
            return None
        cols, st = _fbpy.decode_data_table(raw, b"FTAB")
        if st != _fbpy.ST_OK:
            self.warnings.append(
                f"the data table is damaged ({_status(st)}); packets were indexed by walking the file"
            )
            return None
        offset, stream, size, count, t0, t1 = cols
        n = len(offset)
        ok = (
            (offset - 8 >= self._data_start)
            & (size >= 0)
            & (offset + size <= dtp)
            & np.isin(stream, list(self._streams))
            & (count >= 0)
        )
        if n and not ok.all():
            self.warnings.append("the data table points outside the packets; packets were indexed by walking the file")
            return None
        # an element count the packet's size cannot hold would make the reader
        # allocate for it: such a table is not trusted
        # (an event packet's body grows at most BODY_RATIO times when decompressed: the fixed allowance
        # the decompressor grants frames of pixels is no licence for event counts)
        evts = np.isin(stream, [sid for sid, st in self._streams.items() if st.type == "EVTS"])
        per_element = np.where(evts, _fbpy.EVENT_STRUCT, 1)
        room = np.where(evts, cz.BODY_RATIO * size + 4096,
                        np.array([cz.output_limit(z) for z in size], np.int64))
        plausible = count <= room // per_element
        if n and not plausible.all():
            self.warnings.append("the data table claims more elements than its packets can hold; "
                                 "packets were indexed by walking the file")
            return None
        order = np.argsort(offset, kind="stable")
        if n and np.any(offset[order][1:] < (offset + size)[order][:-1] + 8):
            self.warnings.append("the data table lists overlapping packets; packets were indexed by walking the file")
            return None
        idx = _PacketIndex(offset[order], size[order], stream[order], count[order], t0[order], t1[order], True)
        return idx

    def _walk(self, end) -> _PacketIndex:
        offs, sizes, sids = [], [], []
        pos = self._data_start
        while pos < end:
            if pos + 8 > end:
                self._note(pos, f"file ends inside a packet header ({end - pos} of 8 bytes)")
                break
            sid, size = struct.unpack("<ii", self._pread(8, pos))
            if sid not in self._streams:
                self._note(pos, f"packet names stream {sid}, which the header does not describe")
                break
            if size < 0 or pos + 8 + size > end:
                self._note(pos, f"packet of stream {sid} claims {size} bytes but only {end - pos - 8} remain")
                break
            offs.append(pos + 8)
            sizes.append(size)
            sids.append(sid)
            pos += 8 + size
        n = len(offs)
        unknown = np.full(n, -1, np.int64)
        return _PacketIndex(offs, sizes, sids, unknown, np.full(n, np.iinfo(np.int64).min),
                            np.full(n, np.iinfo(np.int64).max), False)

    def _note(self, offset, reason):
        if not self.salvage:
            raise FormatError(self.path, offset, reason)
        if self.damage is None or offset < self.damage.offset:
            self.damage = Damage(int(offset), reason)

    # -- streams ------------------------------------------------------------------
    @property
    def compression(self) -> str:
        return cz.CODE_NAMES[self._code].lower()

    def _stream(self, stream, typ) -> StreamInfo | None:
        if stream is None:
            candidates = [s for s in self._streams.values() if s.type == typ]
            preferred = [s for s in candidates if s.name == _TYPE_NAMES[typ]]
            return (preferred or candidates or [None])[0]
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
                nz = counts > 0 if counts is not None else np.ones(s.packets, bool)
                s.t_start_us = int(idx.t0[sel][nz].min()) if nz.any() else None
                s.t_end_us = int(idx.t1[sel][nz].max()) if nz.any() else None
        if not idx.from_table:
            self._fill_times()
        return list(self._streams.values())

    def _count_elements(self, rows, typ):
        if typ not in _VECTOR_TYPES:
            return None
        out = np.zeros(len(rows), np.int64)
        for k, i in enumerate(rows):
            try:
                b = self._body(i)
            except _Stop:
                return out[:k]
            n = _jit().vector_length(b, _IDENT[typ], _STRUCT_SIZE.get(typ, 0))
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
    def _body(self, i):
        """Decompressed body of packet ``i`` as a uint8 array (or raise/stop)."""
        idx = self._index
        off, size = int(idx.offset[i]), int(idx.size[i])
        data = self._pread(size + 8, off - 8)
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
            raw = cz.decompress(self._code, body, cz.output_limit(size), self.verify_checksums)
        except cz.CodecError as exc:
            self._fail(off, f"packet body cannot be decompressed: {exc}")
        return np.frombuffer(raw, np.uint8)

    def _select(self, typ, stream, t_start_us, t_end_us):
        s = self._stream(stream, typ)
        if s is None:
            return None, np.zeros(0, np.int64)
        idx = self._index
        rows = np.flatnonzero(idx.stream == s.id)
        if idx.from_table and (t_start_us is not None or t_end_us is not None):
            span = window_blocks(idx.t0[rows], idx.t1[rows], t_start_us, t_end_us,
                                 lambda k: self._packet_span(s, rows[k]))
            if span is None:
                self._warn_once("the data table's packet times disagree with the packets or are out of order; "
                                "windows read every packet", s.name)
            else:
                rows = rows[span[0]:span[1]]
        return s, rows

    def _packet_span(self, s, row):
        """(first, last) time stamp of packet ``row``, or None when it is empty or unreadable."""
        if s.type == "TRIG":
            t = self._decode_triggers(s, [row]).t
        else:
            t = next(self._event_packets(s, [row]), Events.empty(s.sensor_size)).t
        return (int(t[0]), int(t[-1])) if len(t) else None

    # -- events -------------------------------------------------------------------
    def events(self, t_start_us=None, t_end_us=None, stream=None) -> Events:
        """Events with ``t_start_us <= t < t_end_us`` (None: no bound).

        With a data table only the packets that overlap the window are
        decoded; both cores decompress.
        """
        try:
            return self._events(t_start_us, t_end_us, stream)
        except _CountMismatch:
            # the data table lied about a packet's size: count from the packets
            self.warnings.append("the data table's element counts are wrong; counted from the packets instead")
            self._index.count[:] = -1
            return self._events(t_start_us, t_end_us, stream)

    def _events(self, t_start_us, t_end_us, stream) -> Events:
        s, rows = self._select("EVTS", stream, t_start_us, t_end_us)
        if s is None:
            raise FormatError(self.path, None, f"no event stream; the streams are {self._stream_names()}")
        counts = self._index.count[rows]
        if np.any(counts < 0):
            counts = self._count_elements(rows, "EVTS")
            rows = rows[: len(counts)]
        ev, _ = self._decode_rows(s, rows, counts)
        if t_start_us is not None or t_end_us is not None:
            ev = ev.between(t_start_us, t_end_us)
        return ev

    def _decode_rows(self, s, rows, counts):
        """Decode the event packets ``rows`` (element counts known) on both cores.

        Returns ``(events, complete)``; with salvage, ``events`` is the intact
        prefix and ``complete`` False when damage stopped the decoding.
        """
        total = int(np.sum(counts))
        t = np.empty(total, np.int64)
        x = np.empty(total, np.uint16)
        y = np.empty(total, np.uint16)
        p = np.empty(total, np.uint8)
        end, complete = self._decode_into(s, rows, counts, (t, x, y, p), 0)
        return Events._trusted(t[:end], x[:end], y[:end], p[:end], s.sensor_size), complete

    def _decode_into(self, s, rows, counts, out, offset):
        """Decode the packets ``rows`` into the columns ``out`` from ``offset``, on both cores.

        Returns ``(events written, complete)``.
        """
        width, height = s.sensor_size
        t, x, y, p = out
        starts = np.full(len(rows) + 1, offset, np.int64)
        np.cumsum(counts, out=starts[1:])
        starts[1:] += offset
        ident = _IDENT["EVTS"]
        decode = _jit().decode_events

        def work(k0, k1):
            for k in range(k0, k1):
                i = rows[k]
                try:
                    b = self._body(i)
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

        stopped = _run_split(work, len(rows), counts)
        return int(starts[stopped]) - offset, stopped == len(rows)

    def iter_events(self, chunk_events: int = 1_000_000, t_start_us=None, t_end_us=None, stream=None) -> Iterator[Events]:
        """Yield the events in order, at most ``chunk_events`` at a time.

        Memory stays bounded by the chunk (plus one packet), whatever the
        size of the file.
        """
        chunk_events = int(chunk_events)
        if chunk_events < 1:
            raise EvtkError(f"chunk_events must be at least 1, got {chunk_events}")
        s, rows = self._select("EVTS", stream, t_start_us, t_end_us)
        if s is None:
            raise FormatError(self.path, None, f"no event stream; the streams are {self._stream_names()}")
        counts = self._index.count[rows]
        if len(rows) and np.all(counts >= 0):
            stopped_at = yield from self._chunks_from_table(s, rows, counts, chunk_events, t_start_us, t_end_us)
            if stopped_at is None:
                return
            rows = rows[stopped_at:]
        yield from self._chunks_from_packets(s, rows, chunk_events, t_start_us, t_end_us)

    def _chunks_from_table(self, s, rows, counts, chunk_events, t_start_us, t_end_us):
        """Chunks of exactly ``chunk_events`` (the last one shorter), packets decoded on both cores
        straight into each chunk's arrays. Returns None when done, or the row to go on from packet
        by packet when the data table's counts prove wrong."""
        bounded = t_start_us is not None or t_end_us is not None
        cum = np.zeros(len(rows) + 1, np.int64)
        np.cumsum(counts, out=cum[1:])
        buf = None
        fill = 0

        def chunk(n):
            ev = Events._trusted(buf[0][:n], buf[1][:n], buf[2][:n], buf[3][:n], s.sensor_size)
            return ev.between(t_start_us, t_end_us) if bounded else ev

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
                    n, complete = self._decode_into(s, rows[k:j], counts[k:j], buf, fill)
                    fill += n
                    k = j
                else:  # one packet larger than the room left: decode it alone and split it
                    ev1, complete = self._decode_rows(s, rows[k:k + 1], counts[k:k + 1])
                    pos = 0
                    while pos < len(ev1):
                        if buf is None:
                            buf, fill = new_buffer(), 0
                        take = min(chunk_events - fill, len(ev1) - pos)
                        for dst, src in zip(buf, (ev1.t, ev1.x, ev1.y, ev1.p)):
                            dst[fill:fill + take] = src[pos:pos + take]
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
        ident = _IDENT["EVTS"]
        fb = _jit()
        for i in rows:
            try:
                b = self._body(i)
            except _Stop:
                break
            n = fb.vector_length(b, ident, _fbpy.EVENT_STRUCT)
            if n < 0:
                try:
                    self._fail(int(self._index.offset[i]), f"event packet: {_status(n)}")
                except _Stop:
                    break
            cols = (np.empty(n, np.int64), np.empty(n, np.uint16), np.empty(n, np.uint16), np.empty(n, np.uint8))
            got, st = fb.decode_events(b, ident, *cols, 0, n, width, height)
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
    def triggers(self, t_start_us=None, t_end_us=None, stream=None) -> Triggers:
        """Trigger time stamps and kinds (empty when the file has no trigger stream)."""
        s, rows = self._select("TRIG", stream, t_start_us, t_end_us)
        if s is None:
            return Triggers()
        trig = self._decode_triggers(s, rows)
        if t_start_us is not None or t_end_us is not None:
            trig = trig.between(t_start_us, t_end_us)
        return trig

    def _decode_triggers(self, s, rows) -> Triggers:
        parts = []
        ident = _IDENT["TRIG"]
        for i in rows:
            try:
                b = self._body(i)
            except _Stop:
                break
            n = _jit().vector_length(b, ident)
            if n < 0:
                try:
                    self._fail(int(self._index.offset[i]), f"trigger packet: {_status(n)}")
                except _Stop:
                    break
            t = np.empty(n, np.int64)
            k = np.empty(n, np.uint8)
            got, st = _jit().decode_triggers(b, ident, t, k, 0, n)
            if st != _fbpy.ST_OK:
                try:
                    self._fail(int(self._index.offset[i]), f"trigger packet: {_status(st)}")
                except _Stop:
                    break
            parts.append(Triggers(t, k))
        return Triggers.concatenate(parts)

    def other_streams(self) -> list[StreamInfo]:
        """Streams that are neither events nor triggers (frames, IMU, ...), which evtk copies but does not decode."""
        return [st for st in self._streams.values() if st.type not in ("EVTS", "TRIG")]

    def packets(self, stream):
        """Yield ``(body, count, t_start_us, t_end_us)`` for every packet of ``stream`` (name or id), the body
        decompressed and as the file holds it; counts from the data table or the packets, times from the data
        table (None without one)."""
        s = next((st for st in self._streams.values() if stream in (st.id, st.name)), None)
        if s is None:
            raise EvtkError(f"{self.path}: no stream {stream!r}")
        idx = self._index
        rows = np.flatnonzero(idx.stream == s.id)
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


def _status(code) -> str:
    return _fbpy.STATUS_TEXT.get(int(code), f"status {int(code)}")


def _run_split(work, n_rows, counts) -> int:
    """Run ``work(k0, k1)`` over contiguous row ranges on the I/O pool.

    Each call returns the first row it did not finish (``k1`` on success);
    the result is the length of the intact prefix.
    """
    if n_rows == 0:
        return 0
    nw = cz.workers()
    total = int(np.sum(counts))
    if nw == 1 or n_rows < 4 or total < 200_000:
        return work(0, n_rows)
    # balance by elements: 4 ranges per worker keeps both cores busy to the end
    parts = nw * 4
    cum = np.cumsum(counts)
    cuts = np.searchsorted(cum, np.linspace(0, total, parts + 1)[1:-1], side="left")
    bounds = np.unique(np.concatenate([[0], cuts, [n_rows]]))
    futures = [cz.pool().submit(work, int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:])]
    done = n_rows
    for b, fut in zip(bounds[1:], futures):
        got = fut.result()
        if got < b:
            done = min(done, got)
    return done


# =============================================================================
# Writing
# =============================================================================

_TYPE_DESCRIPTIONS = {"EVTS": "Array of events (polarity ON/OFF).", "TRIG": "Array of triggers."}


def _header_xml(streams, code) -> str:
    lines = ['<dv version="2.0">', '    <node name="outInfo" path="/outInfo/">']
    for sid, (name, typ, info) in enumerate(streams):
        base = f"/outInfo/{sid}/"
        lines.append(f'        <node name="{sid}" path="{base}">')
        for key, val in (
            ("compression", cz.CODE_NAMES[code]),
            ("originalModuleName", "evtk"),
            ("originalOutputName", name),
            ("typeDescription", _TYPE_DESCRIPTIONS.get(typ, "")),
            ("typeIdentifier", typ),
        ):
            lines.append(f'            <attr key="{key}" type="string">{escape(val)}</attr>')
        lines.append(f'            <node name="info" path="{base}info/">')
        for key, (typ_name, val) in info.items():
            text = str(val).lower() if isinstance(val, bool) else str(val)
            lines.append(f'                <attr key="{escape(key)}" type="{typ_name}">{escape(text)}</attr>')
        lines.append("            </node>")
        lines.append("        </node>")
    lines.append("    </node>")
    lines.append("</dv>")
    return "\n".join(lines) + "\n"


def _xml_type(value) -> str:
    """The header XML type of a stream attribute read back from another file."""
    if isinstance(value, bool):
        return "bool"
    if isinstance(value, int):
        return "int" if -(2**31) <= value < 2**31 else "long"
    if isinstance(value, float):
        return "double"
    return "string"


def _io_header(code, data_table_pos, xml) -> bytes:
    """Size-prefixed IOHeader FlatBuffer; the data-table position sits at byte 40."""
    text = xml.encode("utf-8")
    out = bytearray(48)
    struct.pack_into("<I", out, 4, 24)  # root table at 4 + 24 = 28
    out[8:12] = b"IOHE"
    struct.pack_into("<HHHHH", out, 12, 10, 20, 4, 12, 8)  # vtable at 12
    struct.pack_into("<i", out, 28, 16)  # table -> vtable
    struct.pack_into("<i", out, 32, code)
    struct.pack_into("<I", out, 36, 48 - 36)  # string at 48
    struct.pack_into("<q", out, 40, data_table_pos)
    out += struct.pack("<I", len(text)) + text + b"\x00"
    out += b"\x00" * (-len(out) % 8)
    struct.pack_into("<I", out, 0, len(out) - 4)
    return bytes(out)


_DTP_FIELD = _HEADER_START + 40  # file offset of IOHeader.dataTablePosition


class Aedat4Writer(BaseWriter):
    """Stream events and triggers into an AEDAT4 file, atomically.

    Data goes to a temporary file beside ``path``; :meth:`close` writes the
    data table and renames it into place.  If the process dies first, the
    temporary ``*.evtk-partial`` file is a valid recording without a data
    table (read it with ``salvage=True``).

    Parameters
    ----------
    path : str or os.PathLike
    sensor_size : (int, int)
    compression : {'lz4', 'zstd', 'none', 'lz4_high', 'zstd_high'}
    triggers : bool
        Declare a trigger stream.
    metadata : dict, optional
        JSON-serialisable; stored in the event stream's ``evtkMetadata``.
    packet_events, packet_us : int
        A packet closes after this many events or this many microseconds.
    """

    def __init__(self, path, sensor_size, compression="lz4", triggers=True, metadata=None,
                 packet_events=DEFAULT_PACKET_EVENTS, packet_us=DEFAULT_PACKET_US, source="evtk",
                 extra_streams=()):
        name = str(compression).lower()
        if name not in cz.BY_NAME:
            raise EvtkError(f"unknown compression {compression!r}; choose one of {sorted(cz.BY_NAME)}")
        self.code = cz.BY_NAME[name]
        w, h = (int(v) for v in sensor_size)
        if not (0 < w <= 32768 and 0 < h <= 32768):
            raise EvtkError(f"AEDAT4 stores int16 coordinates: sensor size {(w, h)} does not fit")
        self.sensor_size = (w, h)
        self.packet_events = int(packet_events)
        self.packet_us = None if packet_us is None else int(packet_us)
        if self.packet_events < 1 or (self.packet_us is not None and self.packet_us < 1):
            raise EvtkError("packet_events and packet_us must be positive")
        info = {"sizeX": ("int", w), "sizeY": ("int", h), "source": ("string", source)}
        if metadata:
            try:
                info["evtkMetadata"] = ("string", json.dumps(metadata, sort_keys=True, separators=(",", ":")))
            except (TypeError, ValueError) as exc:
                raise EvtkError(f"metadata must be JSON-serialisable: {exc}") from None
        info["evtkVersion"] = ("string", __version__)
        streams = [("events", "EVTS", info)]
        self._trigger_sid = None
        if triggers:
            self._trigger_sid = 1
            streams.append(("triggers", "TRIG", {"source": ("string", source)}))
        # other streams (frames, IMU, ...) copied from another recording: (name, type, {key: value})
        self._extra = {}
        for name, typ, attrs in extra_streams:
            self._extra[name] = len(streams)
            streams.append((name, typ, {k: (_xml_type(v), v) for k, v in attrs.items()}))
        self._file = AtomicFile(path)
        self.path = self._file.path
        self._table = [[] for _ in range(6)]  # offset, stream, size, count, t0, t1
        self._closed = False
        try:
            header = _io_header(self.code, -1, _header_xml(streams, self.code))
            self._f = self._file.file
            self._f.write(MAGIC)
            self._f.write(header)
            self._f.flush()  # a writer killed from here on leaves a partial file whose header is readable
            self._pos = len(MAGIC) + len(header)
        except BaseException:
            self._file.discard()
            raise

    # -- packets ----------------------------------------------------------------------
    def _emit(self, sid, body, count, t0, t1):
        self._f.write(struct.pack("<ii", sid, len(body)))
        self._f.write(body)
        self._record_many(sid, [self._pos + 8], [len(body)], [count], [t0], [t1])
        self._pos += 8 + len(body)

    def _record_many(self, sid, offsets, sizes, counts, t0, t1):
        """Remember packets for the data table."""
        n = len(offsets)
        for col, v in zip(self._table, (offsets, np.full(n, sid), sizes, counts, t0, t1)):
            col.append(np.asarray(v, np.int64))

    def write_events(self, events: Events):
        """Append events (one or more packets)."""
        self._check_open()
        if tuple(events.sensor_size) != self.sensor_size:
            raise EvtkError(f"events are for a {events.sensor_size} sensor, the file for {self.sensor_size}")
        n = len(events)
        if n == 0:
            return
        w, h = self.sensor_size
        if int(events.x.max()) >= w or int(events.y.max()) >= h:
            raise EvtkError(f"{events.out_of_bounds()} events lie outside the {w}x{h} sensor")
        bounds = time_chunks(events.t, self.packet_events, self.packet_us, events.is_sorted)
        # Serialise batches of about 2 M events into two staging buffers used in
        # turn: the next batch is encoded while the pool compresses this one.
        rows = max(1, (1 << 21) // self.packet_events)
        staging = [None, None]
        pending = None
        for k, b0 in enumerate(range(0, len(bounds) - 1, rows)):
            b = bounds[b0 : b0 + rows + 1]
            lo, hi = int(b[0]), int(b[-1])
            local = b - lo
            npk = len(local) - 1
            need = (hi - lo) * 16 + 40 * npk
            buf = staging[k % 2]
            if buf is None or len(buf) < need:
                buf = staging[k % 2] = np.empty(need + (-need % 8), np.uint8)
            tt = events.t[lo:hi]
            _jit().encode_event_packets(tt, events.x[lo:hi], events.y[lo:hi], events.p[lo:hi], local, 0, buf)
            heads = local[:-1] * 16 + 40 * np.arange(npk)
            ends = local[1:] * 16 + 40 * np.arange(1, npk + 1)
            if events.is_sorted:
                t0, t1 = tt[local[:-1]], tt[local[1:] - 1]
            else:
                t0, t1 = np.minimum.reduceat(tt, local[:-1]), np.maximum.reduceat(tt, local[:-1])
            counts = np.diff(local)
            if self.code == cz.NONE:  # packet headers are already in place: one write
                self._record_many(0, heads + 8 + self._pos, ends - heads - 8, counts, t0, t1)
                self._f.write(memoryview(buf)[:need])
                self._pos += need
                continue
            mv = memoryview(buf)
            code = self.code
            futures = [cz.pool().submit(cz.compress, code, mv[a:z]) for a, z in zip(heads + 8, ends)]
            if pending is not None:
                self._emit_all(*pending)
            pending = (futures, counts, t0, t1)
        if pending is not None:
            self._emit_all(*pending)

    def _emit_all(self, futures, counts, t0, t1):
        """Write compressed event packets in order as they become ready."""
        for k, fut in enumerate(futures):
            self._emit(0, fut.result(), int(counts[k]), int(t0[k]), int(t1[k]))

    def write_packet(self, stream: str, body, count: int, t_start_us: int, t_end_us: int):
        """Append one packet of a stream declared in ``extra_streams``: ``body`` is its (decompressed)
        FlatBuffer, written as it is under this file's compression (frames, IMU samples, ...)."""
        self._check_open()
        if stream not in self._extra:
            raise EvtkError(f"no stream {stream!r} was declared; declared: {sorted(self._extra)}")
        self._emit(self._extra[stream], cz.compress(self.code, body), int(count), int(t_start_us), int(t_end_us))

    def write_triggers(self, triggers: Triggers):
        """Append triggers (one packet per 8192)."""
        self._check_open()
        if self._trigger_sid is None:
            raise EvtkError("this writer was opened without a trigger stream (triggers=False)")
        for lo in range(0, len(triggers), 8192):
            t = triggers.t[lo : lo + 8192]
            k = triggers.kind[lo : lo + 8192]
            buf = np.empty(_jit().trigger_packet_size(len(t)), np.uint8)
            size = _jit().encode_trigger_packet(t, k, buf)
            body = cz.compress(self.code, buf[:size])
            self._emit(self._trigger_sid, body, len(t), int(t.min()), int(t.max()))

    # -- finishing (BaseWriter's close and abort) --------------------------------------
    def _finish(self):
        """Write the data table and patch the header's pointer to it."""
        cols = [np.concatenate(c) if c else np.zeros(0, np.int64) for c in self._table]
        buf = np.empty(_jit().data_table_size(len(cols[0])), np.uint8)
        size = _jit().encode_data_table(*cols, buf)
        blob = cz.compress(self.code, buf[:size])
        dtp = self._pos
        self._f.write(blob)
        self._f.seek(_DTP_FIELD)
        self._f.write(struct.pack("<q", dtp))

    def _commit(self):
        self._file.commit()

    def _discard(self):
        self._file.discard()


def write_aedat4(path, events: Events, triggers: Triggers | None = None, compression="lz4", metadata=None, **kwargs):
    """Write a whole recording to ``path`` (atomically); see :class:`Aedat4Writer`."""
    with Aedat4Writer(path, events.sensor_size, compression, triggers=triggers is not None, metadata=metadata, **kwargs) as w:
        if triggers is not None and len(triggers):
            # interleave by time: each trigger packet follows the events before it
            order = np.argsort(triggers.t, kind="stable")
            trig = Triggers(triggers.t[order], triggers.kind[order])
            done = 0
            for lo in range(0, len(trig), 8192):
                part = trig[lo : lo + 8192]
                if events.is_sorted:
                    cut = int(np.searchsorted(events.t, part.t[-1], side="right"))
                    w.write_events(events[done:cut])
                    done = max(done, cut)
                w.write_triggers(part)
            w.write_events(events[done:])
        else:
            w.write_events(events)
