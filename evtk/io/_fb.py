"""Bounds-checked FlatBuffers access for the AEDAT4 packet bodies evtk decodes and encodes (numba).

The header and the data table are read by :mod:`evtk.io._fbpy` (plain Python and numpy, no compiler).

Every function takes the packet body as a uint8 array and never reads outside
it: a lying offset yields a negative status instead of a crash.  The layouts
are specified in ``docs/formats/aedat4.md`` and ``docs/formats/aedat4.fbs``.

Callers pass every argument: a compiled function called with an argument
left to its default makes numba type every later call of every compiled
function in Python, about ten times slower (measured: 11 to 120 us a
packet), so none of them has defaults.

Status codes (``ST_*``) are shared with :mod:`evtk.io.aedat4`, which turns
them into :class:`~evtk.FormatError` messages.
"""

from __future__ import annotations

import sys

import numpy as np
from numba import njit

# the word-wise event decoder reinterprets little-endian bytes as native words
_LITTLE_ENDIAN = sys.byteorder == "little"

# constants and status codes shared with the plain-Python header reader
from ._fbpy import (  # noqa: E402,F401
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


@njit(cache=True, nogil=True)
def _u16(b, pos):
    return np.int64(b[pos]) | (np.int64(b[pos + 1]) << 8)


@njit(cache=True, nogil=True)
def _u32(b, pos):
    return np.int64(b[pos]) | (np.int64(b[pos + 1]) << 8) | (np.int64(b[pos + 2]) << 16) | (np.int64(b[pos + 3]) << 24)


@njit(cache=True, nogil=True)
def _i32(b, pos):
    v = _u32(b, pos)
    if v >= 2147483648:
        v -= 4294967296
    return v


@njit(cache=True, nogil=True)
def _i64(b, pos):
    v = np.uint64(0)
    for k in range(8):
        v |= np.uint64(b[pos + k]) << np.uint64(8 * k)
    return np.int64(v)


@njit(cache=True, nogil=True)
def fb_root(b, ident):
    """Position of the root table, or a negative status.

    Accepts both the size-prefixed form AEDAT4 writers use and a plain buffer;
    the four identifier bytes decide which one it is.
    """
    n = len(b)
    for base in (4, 0):
        if base + 8 > n:
            continue
        ok = True
        for k in range(4):
            if b[base + 4 + k] != ident[k]:
                ok = False
                break
        if ok:
            root = base + _u32(b, base)
            if root + 4 > n:
                return ST_BAD_OFFSET
            return root
    return ST_BAD_IDENT


@njit(cache=True, nogil=True)
def fb_field(b, table, slot):
    """Absolute position of field ``slot`` of ``table``; 0 if absent, <0 if corrupt."""
    n = len(b)
    if table < 0 or table + 4 > n:
        return ST_BAD_OFFSET
    vt = table - _i32(b, table)
    if vt < 0 or vt + 4 > n:
        return ST_BAD_OFFSET
    vt_size = _u16(b, vt)
    tb_size = _u16(b, vt + 2)
    if vt_size < 4 or vt + vt_size > n or table + tb_size > n:
        return ST_BAD_OFFSET
    entry = 4 + 2 * slot
    if entry + 2 > vt_size:
        return 0
    off = _u16(b, vt + entry)
    if off == 0:
        return 0
    if off + 1 > tb_size:
        return ST_BAD_OFFSET
    # (only the field's first byte is known to lie in the buffer: callers check the rest for its size)
    return table + off


@njit(cache=True, nogil=True)
def fb_deref(b, pos):
    """Follow the unsigned offset stored at ``pos``."""
    if pos < 0 or pos + 4 > len(b):
        return ST_BAD_OFFSET
    target = pos + _u32(b, pos)
    if target + 4 > len(b):
        return ST_BAD_OFFSET
    return target


@njit(cache=True, nogil=True)
def fb_vector(b, table, slot, elem_size):
    """(start, length) of the vector in field ``slot``; length 0 if the field is absent."""
    f = fb_field(b, table, slot)
    if f < 0:
        return f, 0
    if f == 0:
        return 0, 0
    v = fb_deref(b, f)
    if v < 0:
        return v, 0
    count = _u32(b, v)
    if v + 4 + count * elem_size > len(b):
        return ST_BAD_OFFSET, 0
    return v + 4, count


@njit(cache=True, nogil=True)
def decode_events(b, ident, t, x, y, p, offset, capacity, width, height, address_mod8):
    """Decode an EVTS packet body into the columns, starting at ``offset``.

    Returns ``(count, status)``; with ``ST_COORD`` the count is the index of
    the first event outside ``width`` x ``height``. ``address_mod8`` is the
    body's memory address modulo 8 (:func:`address_mod8`; -2: found here): when the event
    vector is 8-byte aligned, as FlatBuffers lays it out, each 16-byte event
    is read as two little-endian words; otherwise (a damaged file, or -1)
    byte by byte.
    """
    root = fb_root(b, ident)
    if root < 0:
        return 0, root
    start, count = fb_vector(b, root, 0, 16)
    if start < 0:
        return 0, start
    # writers build the event vector first, so it ends the buffer (FlatBuffers fills from the back): room
    # for another event after it means a length that shrank, whose events would vanish without a word
    if len(b) - (start + EVENT_STRUCT * count) >= EVENT_STRUCT:
        return 0, ST_SLACK
    if count > capacity:
        return count, ST_CAPACITY
    if address_mod8 == -2:  # the body's own address: no Python call per packet to find it
        address_mod8 = b.ctypes.data % 8
    if address_mod8 >= 0 and (address_mod8 + start) % 8 == 0 and _LITTLE_ENDIAN:
        w = b[start : start + 16 * count].view(np.uint64)
        for i in range(count):
            hi = w[2 * i + 1]
            xi = np.int64(hi & np.uint64(0xFFFF))
            yi = np.int64((hi >> np.uint64(16)) & np.uint64(0xFFFF))
            if xi >= width or yi >= height:  # int16 on disk: negative values appear as >= 32768
                return i, ST_COORD
            j = offset + i
            t[j] = np.int64(w[2 * i])
            x[j] = xi
            y[j] = yi
            p[j] = 1 if (hi >> np.uint64(32)) & np.uint64(0xFF) else 0
        return count, ST_OK
    for i in range(count):
        pos = start + 16 * i
        xi = _u16(b, pos + 8)
        yi = _u16(b, pos + 10)
        # int16 on disk: negative values appear as >= 32768 and fail the test
        if xi >= width or yi >= height:
            return i, ST_COORD
        j = offset + i
        t[j] = _i64(b, pos)
        x[j] = xi
        y[j] = yi
        p[j] = 1 if b[pos + 12] != 0 else 0
    return count, ST_OK


def address_mod8(b) -> int:
    """Memory address of a numpy buffer modulo 8 (for :func:`decode_events`)."""
    return b.__array_interface__["data"][0] % 8


@njit(cache=True, nogil=True)
def decode_triggers(b, ident, t, kind, offset, capacity):
    """Decode a TRIG packet (a vector of ``Trigger`` tables)."""
    root = fb_root(b, ident)
    if root < 0:
        return 0, root
    start, count = fb_vector(b, root, 0, 4)
    if start < 0:
        return 0, start
    if count > capacity:
        return count, ST_CAPACITY
    for i in range(count):
        tb = fb_deref(b, start + 4 * i)
        if tb < 0:
            return i, tb
        ft = fb_field(b, tb, 0)
        fk = fb_field(b, tb, 1)
        if ft < 0 or fk < 0:
            return i, ST_BAD_OFFSET
        if ft + 8 > len(b):
            return i, ST_BAD_OFFSET
        t[offset + i] = _i64(b, ft) if ft > 0 else 0
        kind[offset + i] = b[fk] if fk > 0 else 0
    return count, ST_OK


@njit(cache=True, nogil=True)
def vector_length(b, ident, struct_size):
    """Length of the vector in field 0 of the root table (IMU and other packets).

    With ``struct_size`` (16 for events), a vector of structs must end the buffer as writers lay it out
    (less than one element after it), else ``ST_SLACK``.
    """
    root = fb_root(b, ident)
    if root < 0:
        return root
    start, count = fb_vector(b, root, 0, max(1, struct_size))
    if start < 0:
        return start
    if struct_size > 0 and len(b) - (start + struct_size * count) >= struct_size:
        return ST_SLACK
    return count


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
