"""The FlatBuffers encoders of the AEDAT4 packet bodies, data table and trigger packets evtk writes (numpy).

Reading needs none of them: :mod:`evtk.io._fbpy` reads the header, the data
table and the event and trigger packets with plain Python and numpy, every
offset bounds-checked. The layouts are specified in ``docs/formats/aedat4.md``
and ``docs/formats/aedat4.fbs``. Every field is stored through a little-endian
view of the output at its own alignment (the layouts keep every 8-byte scalar
8-byte aligned from the size prefix, as the FlatBuffers builders of
dv-processing and aedat do), so writing loads no compiler.
"""

from __future__ import annotations

import numpy as np

# constants and status codes of the plain-Python reader, for the callers that build packets
from ._fbpy import (  # noqa: F401
    EVENT_PACKET_HEADER,
    EVENT_STRUCT,
    ST_BAD_IDENT,
    ST_BAD_OFFSET,
    ST_CAPACITY,
    ST_COORD,
    ST_MISSING,
    ST_OK,
    ST_SLACK,
    STATUS_TEXT,
)

#: Events a pass of :func:`encode_event_packets` takes over small packets: its index temporaries stay at 16 MiB.
_EVENTS_PER_PASS = 1 << 20
#: Packets of at least this many events on average are written one at a time with strided copies (about 10 µs a
#: packet); smaller ones all at once through computed positions (about 70 ns an event).
_PACKET_EVENTS_LOOPED = 128


def _words(out: np.ndarray, dtype: str) -> np.ndarray:
    """``out`` (uint8) seen as little-endian words of ``dtype``, as far as whole words reach."""
    size = np.dtype(dtype).itemsize
    return out[:len(out) - len(out) % size].view(dtype)


def _ident(name: bytes) -> int:
    return int.from_bytes(name, "little")


def _root(out: np.ndarray, name: bytes, n: int) -> None:
    """The 32 bytes every packet evtk writes begins with (size prefix left to the caller): root table offset,
    identifier, a root vtable of one field and the root table pointing at a vector of ``n`` elements."""
    w32 = out[:32].view("<u4")
    w32[1:] = (16, _ident(name), 6 << 16, 8 | (4 << 16), 6, 4, n)


def encode_event_packets(t: np.ndarray, x: np.ndarray, y: np.ndarray, p: np.ndarray, bounds: np.ndarray,
                         stream_id: int, out: np.ndarray) -> None:
    """Serialise events ``bounds[i]:bounds[i+1]`` as AEDAT4 packets.

    Each packet is an 8-byte packet header (stream id, body size) followed by
    the size-prefixed EVTS FlatBuffer (32 + 16 n bytes), so an uncompressed
    file can be written from ``out`` in one call. Packet ``i`` starts at
    ``16 * bounds[i] + 40 * i``.

    Parameters
    ----------
    t, x, y, p : np.ndarray
        The events' columns (µs, pixels, polarity).
    bounds : np.ndarray
        Packet boundaries, indices into the columns.
    stream_id : int
        The packets' stream.
    out : np.ndarray
        uint8 output, its length a multiple of 8 and at least ``16 * bounds[-1] + 40 * (len(bounds) - 1)``.
    """
    bounds = np.asarray(bounds, np.int64)
    npk = len(bounds) - 1
    if npk < 1:
        return
    count = np.diff(bounds)
    w32 = _words(out, "<u4")
    h = (bounds[:-1] * 16 + 40 * np.arange(npk)) // 4  # each packet's first word
    for k, value in enumerate((stream_id, 32 + 16 * count, 28 + 16 * count, 16, _ident(b"EVTS"), 6 << 16,
                               8 | (4 << 16), 6, 4, count)):
        w32[h + k] = value
    # event j's 16-byte struct: t, then x, y (16 bits each) and p in the next 8 bytes, at word 2 j + 5 (i + 1)
    w64 = _words(out, "<i8")
    if npk * _PACKET_EVENTS_LOOPED <= bounds[-1] - bounds[0]:  # packets of many events: strided copies each
        w16 = _words(out, "<u2")
        for i in range(npk):
            lo, n = int(bounds[i]), int(count[i])
            s = 2 * lo + 5 * (i + 1)
            w64[s:s + 2 * n:2] = t[lo:lo + n]
            rest = w16[4 * s:4 * s + 8 * n].reshape(n, 8)
            rest[:, 4], rest[:, 5], rest[:, 6], rest[:, 7] = x[lo:lo + n], y[lo:lo + n], p[lo:lo + n], 0
        return
    first = int(bounds[0])
    pk = np.repeat(np.arange(npk, dtype=np.int64), count)
    for a in range(0, len(pk), _EVENTS_PER_PASS):
        j = slice(first + a, first + min(a + _EVENTS_PER_PASS, len(pk)))
        idx = 5 * (pk[a:a + _EVENTS_PER_PASS] + 1)
        idx += 2 * np.arange(j.start, j.stop)
        w64[idx] = t[j]
        idx += 1
        w64[idx] = x[j].astype(np.int64) | (y[j].astype(np.int64) << 16) | (p[j].astype(np.int64) << 32)


def _tables(out: np.ndarray, vt: int, n: int, size: int) -> int:
    """The offsets vector of ``n`` tables of ``size`` bytes placed after the vtable at ``vt`` (each table's first
    scalar after its 4-byte vtable offset 8-byte aligned); returns where the first table starts."""
    first = vt + int(out[vt]) + (int(out[vt + 1]) << 8)  # past the vtable (its size in its first 16 bits)
    while first % 8 != 4:
        first += 1
    tb = first + size * np.arange(n)
    slot = 32 + 4 * np.arange(n)
    w32 = _words(out, "<u4")
    w32[slot // 4] = tb - slot
    w32[tb // 4] = tb - vt
    return first


def encode_trigger_packet(t: np.ndarray, kind: np.ndarray, out: np.ndarray) -> int:
    """Serialise triggers as one size-prefixed TRIG packet.

    Parameters
    ----------
    t : np.ndarray
        Trigger times (µs).
    kind : np.ndarray
        Their kinds (uint8).
    out : np.ndarray
        uint8 output of :func:`trigger_packet_size` bytes (a multiple of 4).

    Returns
    -------
    int
        The packet's length in bytes.
    """
    n = len(t)
    out[:] = 0
    _root(out, b"TRIG", n)
    vt = 32 + 4 * n  # shared vtable of the Trigger tables: 8 bytes, tables of 13, timestamp at 4, kind at 12
    out[vt:vt + 8].view("<u2")[:] = (8, 13, 4, 12)
    first = _tables(out, vt, n, 16)
    tb = first + 16 * np.arange(n)
    _words(out, "<i8")[(tb + 4) // 8] = t
    out[tb + 12] = kind
    total = first + 16 * n
    out[:4].view("<u4")[0] = total - 4
    return total


def trigger_packet_size(n: int) -> int:
    """Bytes of a TRIG packet of ``n`` triggers.

    Parameters
    ----------
    n : int
        Triggers.

    Returns
    -------
    int
        The size.
    """
    first = 32 + 4 * n + 8
    if first % 8 != 4:
        first += 4
    return first + 16 * n


def encode_data_table(offset: np.ndarray, stream: np.ndarray, size: np.ndarray, count: np.ndarray, t0: np.ndarray,
                      t1: np.ndarray, out: np.ndarray) -> int:
    """Serialise the FileDataTable (FTAB).

    Parameters
    ----------
    offset, stream, size, count, t0, t1 : np.ndarray
        Per packet: byte offset, stream id, body size, elements, first and last time stamp (µs).
    out : np.ndarray
        uint8 output of :func:`data_table_size` bytes.

    Returns
    -------
    int
        The table's length in bytes.
    """
    n = len(offset)
    out[:] = 0
    _root(out, b"FTAB", n)
    vt = 32 + 4 * n
    # vtable: ByteOffset, PacketInfo (struct), NumElements, TimestampStart, TimestampEnd
    out[vt:vt + 14].view("<u2")[:] = (14, 44, 12, 4, 20, 28, 36)
    first = _tables(out, vt, n, 48)
    tb = first + 48 * np.arange(n)
    w32 = _words(out, "<u4")
    w32[(tb + 4) // 4] = np.asarray(stream, np.int64) & 0xFFFFFFFF
    w32[(tb + 8) // 4] = np.asarray(size, np.int64) & 0xFFFFFFFF
    w64 = _words(out, "<i8")
    for k, col in enumerate((offset, count, t0, t1)):
        w64[(tb + 12 + 8 * k) // 8] = col
    total = first + 48 * n
    w32[0] = total - 4
    return total


def data_table_size(n: int) -> int:
    """Bytes of a data table of ``n`` packets.

    Parameters
    ----------
    n : int
        Packets.

    Returns
    -------
    int
        The size.
    """
    first = 32 + 4 * n + 14
    while first % 8 != 4:
        first += 1
    return first + 48 * n
