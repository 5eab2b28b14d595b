"""The FlatBuffers reads of an AEDAT4 file's header and data table, in plain Python and numpy.

Opening a file and describing it (``evtk info``) needs only these, so they
load no compiler: the header is one table, and the data table's entries are
read all at once with numpy (every offset checked, as :mod:`evtk.io._fb` does
in its compiled loops for packet bodies). Status codes are :mod:`evtk.io._fb`'s.
"""

from __future__ import annotations

import struct

import numpy as np

EVENT_PACKET_HEADER = 32  # bytes before the first event struct (as evtk writes them)
EVENT_STRUCT = 16  # bytes of one event: int64 time, int16 x, int16 y, bool polarity, padding

ST_OK = 0
ST_BAD_OFFSET = -1  # an offset points outside the buffer
ST_BAD_IDENT = -2  # the file identifier is not the expected one
ST_CAPACITY = -3  # more elements than the caller said there would be
ST_COORD = -4  # an event lies outside the sensor
ST_MISSING = -5  # a required field is absent
ST_SLACK = -6  # the body has room for more events after the vector than its length says

STATUS_TEXT = {
    ST_BAD_OFFSET: "a FlatBuffers offset points outside the packet",
    ST_BAD_IDENT: "the packet's FlatBuffers identifier does not match its stream type",
    ST_CAPACITY: "the packet holds more elements than the data table says",
    ST_COORD: "an event lies outside the sensor",
    ST_MISSING: "a required FlatBuffers field is missing",
    ST_SLACK: "the packet's body holds more bytes after its event vector than one event (its vector length is damaged)",
}


def u16(b, pos):
    return struct.unpack_from("<H", b, pos)[0]


def u32(b, pos):
    return struct.unpack_from("<I", b, pos)[0]


def i32(b, pos):
    return struct.unpack_from("<i", b, pos)[0]


def i64(b, pos):
    return struct.unpack_from("<q", b, pos)[0]


def fb_root(b, ident: bytes) -> int:
    """Position of the root table (size-prefixed or plain buffer, told apart by the identifier), or a status."""
    n = len(b)
    for base in (4, 0):
        if base + 8 <= n and bytes(b[base + 4:base + 8]) == ident:
            root = base + u32(b, base)
            return root if root + 4 <= n else ST_BAD_OFFSET
    return ST_BAD_IDENT


def fb_field(b, table: int, slot: int, size: int) -> int:
    """Absolute position of a ``size``-byte field: 0 when absent, a status when any of it lies outside."""
    n = len(b)
    if table < 0 or table + 4 > n:
        return ST_BAD_OFFSET
    vt = table - i32(b, table)
    if vt < 0 or vt + 4 > n:
        return ST_BAD_OFFSET
    vt_size, tb_size = u16(b, vt), u16(b, vt + 2)
    if vt_size < 4 or vt + vt_size > n or table + tb_size > n:
        return ST_BAD_OFFSET
    entry = 4 + 2 * slot
    if entry + 2 > vt_size:
        return 0
    off = u16(b, vt + entry)
    if off == 0:
        return 0
    if off + size > tb_size or table + off + size > n:
        return ST_BAD_OFFSET
    return table + off


def fb_deref(b, pos: int) -> int:
    """Follow the unsigned offset stored at ``pos``."""
    if pos < 0 or pos + 4 > len(b):
        return ST_BAD_OFFSET
    target = pos + u32(b, pos)
    return target if target + 4 <= len(b) else ST_BAD_OFFSET


def _gather(b, pos, width, signed):
    """Little-endian integers of ``width`` bytes at the positions ``pos`` (all already checked)."""
    out = np.zeros(len(pos), np.uint64)
    for k in range(width):
        out |= b[pos + k].astype(np.uint64) << np.uint64(8 * k)
    if signed:
        return out.view(np.int64) if width == 8 else (out.astype(np.int64) ^ (1 << (8 * width - 1))) - (1 << (8 * width - 1))
    return out.astype(np.int64)


def decode_data_table(b, ident: bytes):
    """A FileDataTable (FTAB): ``(columns, status)`` with columns (offset, stream, size, count, t0, t1)."""
    b = np.frombuffer(b, np.uint8)
    n = len(b)
    root = fb_root(b, ident)
    if root < 0:
        return None, root
    field = fb_field(b, root, 0, 4)
    if field <= 0:
        return None, ST_MISSING if field == 0 else field
    vec = fb_deref(b, field)
    if vec < 0:
        return None, vec
    count = u32(b, vec)
    start = vec + 4
    if start + 4 * count > n:
        return None, ST_BAD_OFFSET
    slots = start + 4 * np.arange(count, dtype=np.int64)
    tables = slots + _gather(b, slots, 4, False)
    if np.any(tables + 4 > n):
        return None, ST_BAD_OFFSET
    vts = tables - _gather(b, tables, 4, True)
    if np.any(vts < 0) or np.any(vts + 4 > n):
        return None, ST_BAD_OFFSET
    vt_size = _gather(b, vts, 2, False)
    tb_size = _gather(b, vts + 2, 2, False)
    if np.any(vt_size < 4) or np.any(vts + vt_size > n) or np.any(tables + tb_size > n):
        return None, ST_BAD_OFFSET

    def column(slot, size, signed, required):
        entry = 4 + 2 * slot
        present = entry + 2 <= vt_size
        off = np.where(present, _gather(b, np.where(present, vts + entry, 0), 2, False), 0)
        if required and np.any(off == 0):
            return None, ST_MISSING
        if np.any((off > 0) & ((off + size > tb_size) | (tables + off + size > n))):
            return None, ST_BAD_OFFSET
        pos = np.where(off > 0, tables + off, 0)
        return np.where(off > 0, _gather(b, pos, size, signed), 0), ST_OK

    out = []
    for slot, size, signed, required in ((0, 8, True, True), (1, 8, False, True), (2, 8, True, False),
                                         (3, 8, True, False), (4, 8, True, False)):
        col, st = column(slot, size, signed, required)
        if st != ST_OK:
            return None, st
        out.append(col)
    offset, header, cnt, t0, t1 = out
    stream = (header & 0xFFFFFFFF).astype(np.int64)
    stream = np.where(stream >= 2**31, stream - 2**32, stream)
    size = (header >> 32).astype(np.int64)
    size = np.where(size >= 2**31, size - 2**32, size)
    return (offset, stream, size, cnt, t0, t1), ST_OK
