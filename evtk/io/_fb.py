"""The FlatBuffers encoders of the AEDAT4 packet bodies, data table and trigger packets evtk writes (numba).

Reading needs none of them: :mod:`evtk.io._fbpy` reads the header, the data
table and the event and trigger packets with plain Python and numpy, every
offset bounds-checked, so opening and reading a file loads no compiler. The
layouts are specified in ``docs/formats/aedat4.md`` and
``docs/formats/aedat4.fbs``.

Callers pass every argument: a compiled function called with an argument
left to its default makes numba type every later call of every compiled
function in Python, about ten times slower, so none of them has defaults.
"""

from __future__ import annotations

import numpy as np
from numba import njit

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

# ---------------------------------------------------------------------------
# Writing.  Layouts are fixed and aligned so that every 8-byte scalar sits at
# an 8-byte boundary counted from the start of the size prefix, as the
# FlatBuffers builders of dv-processing and aedat produce them.
# ---------------------------------------------------------------------------


@njit(cache=True, nogil=True)
def _put_u16(b, pos, v):
    b[pos] = v & 0xFF
    b[pos + 1] = (v >> 8) & 0xFF


@njit(cache=True, nogil=True)
def _put_u32(b, pos, v):
    for k in range(4):
        b[pos + k] = (v >> (8 * k)) & 0xFF


@njit(cache=True, nogil=True)
def _put_i64(b, pos, v):
    u = np.uint64(v)
    for k in range(8):
        b[pos + k] = np.uint8((u >> np.uint64(8 * k)) & np.uint64(0xFF))


@njit(cache=True, nogil=True)
def _encode_event_packets(t, x, y, p, bounds, stream_id, out, out16, out64):
    for i in range(len(bounds) - 1):
        lo = bounds[i]
        hi = bounds[i + 1]
        n = hi - lo
        head = lo * 16 + 40 * i
        _put_u32(out, head, stream_id)
        _put_u32(out, head + 4, 32 + 16 * n)
        base = head + 8
        _put_u32(out, base + 0, 28 + 16 * n)  # size prefix
        _put_u32(out, base + 4, 16)  # root table at 4 + 16 = 20
        out[base + 8] = 69  # 'E'
        out[base + 9] = 86  # 'V'
        out[base + 10] = 84  # 'T'
        out[base + 11] = 83  # 'S'
        _put_u16(out, base + 12, 0)  # padding
        _put_u16(out, base + 14, 6)  # vtable: 6 bytes
        _put_u16(out, base + 16, 8)  # table: 8 bytes
        _put_u16(out, base + 18, 4)  # field 0 at table + 4
        _put_u32(out, base + 20, 6)  # table -> vtable at 20 - 6 = 14
        _put_u32(out, base + 24, 4)  # vector at 24 + 4 = 28
        _put_u32(out, base + 28, n)
        # the structs start 8-byte aligned (16 lo + 40 (i + 1)): store by word
        w = (base + 32) // 8
        for k in range(n):
            j = lo + k
            out64[w + 2 * k] = t[j]
            out64[w + 2 * k + 1] = 0
            h = 4 * (w + 2 * k + 1)
            out16[h] = x[j]
            out16[h + 1] = y[j]
            out[2 * h + 4] = p[j]


def encode_event_packets(t, x, y, p, bounds, stream_id, out):
    """Serialise events ``bounds[i]:bounds[i+1]`` as AEDAT4 packets.

    Each packet is an 8-byte packet header (stream id, body size) followed by
    the size-prefixed EVTS FlatBuffer (32 + 16 n bytes), so an uncompressed
    file can be written from ``out`` in one call.  Packet ``i`` starts at
    ``16 * bounds[i] + 40 * i``; ``out`` must be a uint8 array whose length
    is a multiple of 8.
    """
    _encode_event_packets(t, x, y, p, bounds, stream_id, out, out.view(np.uint16), out.view(np.int64))


@njit(cache=True, nogil=True)
def encode_trigger_packet(t, kind, out):
    """Serialise triggers as one size-prefixed TRIG packet; returns its length."""
    n = len(t)
    out[:] = 0
    # root vtable at 12 (6 bytes), root table at 20, vector at 28, offsets at 32
    _put_u32(out, 4, 16)
    out[8] = 84  # 'T'
    out[9] = 82  # 'R'
    out[10] = 73  # 'I'
    out[11] = 71  # 'G'
    _put_u16(out, 14, 6)
    _put_u16(out, 16, 8)
    _put_u16(out, 18, 4)
    _put_u32(out, 20, 6)
    _put_u32(out, 24, 4)
    _put_u32(out, 28, n)
    vt = 32 + 4 * n  # shared vtable of the Trigger tables
    _put_u16(out, vt, 8)
    _put_u16(out, vt + 2, 13)
    _put_u16(out, vt + 4, 4)
    _put_u16(out, vt + 6, 12)
    first = vt + 8
    if first % 8 != 4:
        first += 4
    for i in range(n):
        tb = first + 16 * i
        _put_u32(out, 32 + 4 * i, tb - (32 + 4 * i))
        _put_u32(out, tb, tb - vt)
        _put_i64(out, tb + 4, t[i])
        out[tb + 12] = kind[i]
    total = first + 16 * n
    _put_u32(out, 0, total - 4)
    return total


def trigger_packet_size(n: int) -> int:
    first = 32 + 4 * n + 8
    if first % 8 != 4:
        first += 4
    return first + 16 * n


@njit(cache=True, nogil=True)
def encode_data_table(offset, stream, size, count, t0, t1, out):
    """Serialise the FileDataTable (FTAB); returns its length."""
    n = len(offset)
    out[:] = 0
    _put_u32(out, 4, 16)
    out[8] = 70  # 'F'
    out[9] = 84  # 'T'
    out[10] = 65  # 'A'
    out[11] = 66  # 'B'
    _put_u16(out, 14, 6)
    _put_u16(out, 16, 8)
    _put_u16(out, 18, 4)
    _put_u32(out, 20, 6)
    _put_u32(out, 24, 4)
    _put_u32(out, 28, n)
    vt = 32 + 4 * n
    # vtable: ByteOffset, PacketInfo (struct), NumElements, TimestampStart, TimestampEnd
    _put_u16(out, vt, 14)
    _put_u16(out, vt + 2, 44)
    _put_u16(out, vt + 4, 12)
    _put_u16(out, vt + 6, 4)
    _put_u16(out, vt + 8, 20)
    _put_u16(out, vt + 10, 28)
    _put_u16(out, vt + 12, 36)
    first = vt + 14
    while first % 8 != 4:
        first += 1
    for i in range(n):
        tb = first + 48 * i
        _put_u32(out, 32 + 4 * i, tb - (32 + 4 * i))
        _put_u32(out, tb, tb - vt)
        _put_u32(out, tb + 4, np.int64(stream[i]) & 0xFFFFFFFF)
        _put_u32(out, tb + 8, np.int64(size[i]) & 0xFFFFFFFF)
        _put_i64(out, tb + 12, offset[i])
        _put_i64(out, tb + 20, count[i])
        _put_i64(out, tb + 28, t0[i])
        _put_i64(out, tb + 36, t1[i])
    total = first + 48 * n
    _put_u32(out, 0, total - 4)
    return total


def data_table_size(n: int) -> int:
    first = 32 + 4 * n + 14
    while first % 8 != 4:
        first += 1
    return first + 48 * n
