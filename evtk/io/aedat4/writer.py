"""Writing AEDAT4 as dv-processing does: LZ4/ZSTD packets, a data table, atomically."""

from __future__ import annotations

import json
import os
import struct
from collections.abc import Iterable, Mapping
from html import escape as _html_escape
from typing import Any

import numpy as np

from ..._atomic import AtomicFile
from ..._version import __version__
from ...errors import EvtkError
from ...events import Events, Triggers
from .. import _compression as cz
from ..base import BaseWriter, time_chunks
from .common import _HEADER_START, DEFAULT_PACKET_EVENTS, DEFAULT_PACKET_US, MAGIC, _jit


def escape(text: str) -> str:
    """``&``, ``<`` and ``>`` as XML entities (what ``xml.sax.saxutils.escape`` does, without importing it:
    it pulls in ``urllib.request``, 10-30 ms of every read, since reading imports this module too).

    Parameters
    ----------
    text : str
        An attribute's key or value.

    Returns
    -------
    str
        The text, safe inside the header's XML.
    """
    return _html_escape(text, quote=False)


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
        The target (``.aedat4``).
    sensor_size : tuple of (int, int)
        Width and height in pixels, each at most 32768 (AEDAT4 stores int16 coordinates).
    compression : {'lz4', 'zstd', 'none', 'lz4_high', 'zstd_high'}
        The packets' codec, as DV names them.
    triggers : bool
        Declare a trigger stream.
    metadata : Mapping of str to object, optional
        JSON-serialisable; stored in the event stream's ``evtkMetadata``.
    packet_events, packet_us : int
        A packet closes after this many events or this many microseconds (``packet_us`` None: by count
        only); with the data table, a short window then decodes few packets.
    source : str
        The streams' ``source`` attribute: the camera's name (``"evtk"`` for what evtk made).
    extra_streams : iterable of (str, str, Mapping)
        Other streams to declare, as ``(name, type identifier, attributes)`` (frames ``FRME``, IMU
        ``IMUS``, ...), whose packets :meth:`write_packet` then copies.

    Raises
    ------
    EvtkError
        For an unknown compression, a sensor size that does not fit int16, packet limits below 1, or
        metadata that is not JSON-serialisable.
    """

    def __init__(self, path: str | os.PathLike[str], sensor_size: tuple[int, int], compression: str = "lz4",
                 triggers: bool = True, metadata: Mapping[str, Any] | None = None,
                 packet_events: int = DEFAULT_PACKET_EVENTS, packet_us: int | None = DEFAULT_PACKET_US,
                 source: str = "evtk", extra_streams: Iterable[tuple[str, str, Mapping[str, Any]]] = ()) -> None:
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
        self._table: list[list[np.ndarray]] = [[] for _ in range(6)]  # offset, stream, size, count, t0, t1
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

    def write_events(self, events: Events) -> None:
        """Append events (one or more packets).

        Parameters
        ----------
        events : Events
            Of the writer's sensor size; any order (each packet's first and last time in the data table are
            its smallest and largest stamp).

        Raises
        ------
        EvtkError
            When the writer is closed, the sensor sizes differ, or an event lies outside the sensor.
        """
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
        staging: list[np.ndarray | None] = [None, None]
        pending = None
        for k, b0 in enumerate(range(0, len(bounds) - 1, rows)):
            b = bounds[b0 : b0 + rows + 1]
            lo, hi = int(b[0]), int(b[-1])
            local = b - lo
            npk = len(local) - 1
            need = (hi - lo) * 16 + 40 * npk
            buf = staging[k % 2]
            if buf is None or len(buf) < need:
                buf = np.empty(need + (-need % 8), np.uint8)
                staging[k % 2] = buf
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
                self._f.write(buf[:need].data)
                self._pos += need
                continue
            mv = buf.data
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

    def write_packet(self, stream: str, body: bytes | bytearray | memoryview | np.ndarray, count: int,
                     t_start_us: int, t_end_us: int) -> None:
        """Append one packet of a stream declared in ``extra_streams`` (frames, IMU samples, ...).

        Parameters
        ----------
        stream : str
            The stream's name, as declared.
        body : bytes-like
            The packet's decompressed FlatBuffer, written as it is under this file's compression.
        count : int
            Elements it holds, for the data table.
        t_start_us, t_end_us : int
            Its first and last time (µs), for the data table.

        Raises
        ------
        EvtkError
            When the writer is closed or the stream was not declared.
        """
        self._check_open()
        if stream not in self._extra:
            raise EvtkError(f"no stream {stream!r} was declared; declared: {sorted(self._extra)}")
        self._emit(self._extra[stream], cz.compress(self.code, body), int(count), int(t_start_us), int(t_end_us))

    def write_triggers(self, triggers: Triggers) -> None:
        """Append triggers (one packet per 8192).

        Parameters
        ----------
        triggers : Triggers
            Their times and kinds (AEDAT4 holds no channels: those are not written).

        Raises
        ------
        EvtkError
            When the writer is closed or was made with ``triggers=False``.
        """
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


def write_aedat4(path: str | os.PathLike[str], events: Events, triggers: Triggers | None = None,
                 compression: str = "lz4", metadata: Mapping[str, Any] | None = None, **kwargs: Any) -> None:
    """Write a whole recording to ``path`` (atomically); see :class:`Aedat4Writer`.

    Trigger packets are interleaved with the event packets by time (when the events are sorted), as a
    camera writes them.

    Parameters
    ----------
    path : str or os.PathLike
        The target (``.aedat4``).
    events : Events
        The events.
    triggers : Triggers, optional
        Trigger edges (sorted by time here); their channels are not kept.
    compression : str
        The codec (:class:`Aedat4Writer`).
    metadata : Mapping of str to object, optional
        JSON-serialisable; stored in the event stream's ``evtkMetadata``.
    **kwargs : Any
        :class:`Aedat4Writer`'s other options (``packet_events``, ``packet_us``, ``source``).

    Raises
    ------
    EvtkError
        As :class:`Aedat4Writer` and its ``write_events``; no file is left under ``path`` then.
    """
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
