"""Every FlatBuffers read of an AEDAT4 file, in plain Python and numpy: the header, the data table and the
event and trigger packets.

Reading loads no compiler. The header is one table; the data table's entries
and a trigger packet's tables are read all at once with numpy; an event
packet's vector of 16-byte structs is viewed as :data:`EVENT_DTYPE` records
and its columns copied out. Every offset is checked against the buffer: a
lying one yields a negative status (``ST_*``, turned into
:class:`~evtk.FormatError` messages by :mod:`evtk.io.aedat4`), never a read
outside it. The layouts are in ``docs/formats/aedat4.md``; the encoders are
:mod:`evtk.io._fb`'s.
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
    """Position of the root table (size-prefixed or plain buffer, told apart by the identifier).

    Parameters
    ----------
    b : numpy.ndarray or bytes
        The buffer.
    ident : bytes
        The four-byte identifier (or the uint8 array of them).

    Returns
    -------
    int
        The root table's position, or a negative status.
    """
    n = len(b)
    ident = bytes(ident)  # bytes, or the uint8 array of them
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


def fb_vector(b, table: int, slot: int, elem_size: int):
    """``(start, length)`` of the vector in field ``slot`` of ``table``.

    Parameters
    ----------
    b : numpy.ndarray or bytes
        The buffer.
    table : int
        Position of the table.
    slot : int
        The field's index in the table's vtable.
    elem_size : int
        Bytes of one element: ``length`` of them must lie inside the buffer.

    Returns
    -------
    start, length : int, int
        ``(0, 0)`` when the field is absent; ``(status, 0)`` when the field, the offset to the vector or its
        elements lie outside the buffer.
    """
    f = fb_field(b, table, slot, 1)
    if f <= 0:
        return f, 0
    v = fb_deref(b, f)
    if v < 0:
        return v, 0
    count = u32(b, v)
    if v + 4 + count * elem_size > len(b):
        return ST_BAD_OFFSET, 0
    return v + 4, count


def _root_vector(b, ident: bytes, struct_size: int):
    """``(start, length)`` of the vector in field 0 of the root table, or ``(status, 0)``; a vector of
    ``struct_size``-byte structs (``struct_size`` > 0) must end the buffer, as writers lay it out."""
    return _root_vector_at(b, 0, len(b), bytes(ident), struct_size)


_HEAD = struct.Struct("<I4s")
_I32 = struct.Struct("<i")
_U16X2 = struct.Struct("<HH")
_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")


def _root_vector_at(buf, at: int, n: int, ident: bytes, struct_size: int):
    """:func:`_root_vector` of the ``n`` bytes of ``buf`` from ``at`` (positions returned from ``at``), read in
    place: :func:`fb_root`, :func:`fb_field` and :func:`fb_vector`'s checks, every one, in one call (the
    AEDAT4 reader's batches parse a packet's header with it, 4-5 us a packet less than through them).

    Parameters
    ----------
    buf : numpy.ndarray or bytes
        The buffer holding the FlatBuffer.
    at : int
        Where the FlatBuffer starts in ``buf``.
    n : int
        Its length; nothing past ``at + n`` is read.
    ident : bytes
        The four-byte identifier.
    struct_size : int
        As :func:`_root_vector`'s.

    Returns
    -------
    start, length : int, int
        The vector's start (from ``at``) and length, or ``(status, 0)``.
    """
    # the root: a size-prefixed buffer (identifier at 8) or a plain one (at 4)
    if n >= 12 and _HEAD.unpack_from(buf, at + 4)[1] == ident:
        root = 4 + _U32.unpack_from(buf, at + 4)[0]
    elif n >= 8 and _HEAD.unpack_from(buf, at)[1] == ident:
        root = _U32.unpack_from(buf, at)[0]
    else:
        return ST_BAD_IDENT, 0
    if root + 4 > n:
        return ST_BAD_OFFSET, 0
    # field 0 of the root table (fb_field), whose value is the offset to the vector
    vt = root - _I32.unpack_from(buf, at + root)[0]
    if vt < 0 or vt + 4 > n:
        return ST_BAD_OFFSET, 0
    vt_size, tb_size = _U16X2.unpack_from(buf, at + vt)
    if vt_size < 4 or vt + vt_size > n or root + tb_size > n:
        return ST_BAD_OFFSET, 0
    off = _U16.unpack_from(buf, at + vt + 4)[0] if vt_size >= 6 else 0
    if off == 0:  # absent: an empty vector at 0
        start = count = 0
    else:
        field = root + off
        if off + 1 > tb_size or field + 4 > n:  # (fb_field's bounds, then fb_deref's)
            return ST_BAD_OFFSET, 0
        v = field + _U32.unpack_from(buf, at + field)[0]
        if v + 4 > n:
            return ST_BAD_OFFSET, 0
        count = _U32.unpack_from(buf, at + v)[0]
        if v + 4 + count * max(1, struct_size) > n:
            return ST_BAD_OFFSET, 0
        start = v + 4
    # writers build a vector of structs first, so it ends the buffer (FlatBuffers fills from the back): room
    # for another element after it means a length that shrank, whose elements would vanish without a word
    if struct_size > 0 and n - (start + struct_size * count) >= struct_size:
        return ST_SLACK, 0
    return start, count


def vector_length(b, ident: bytes, struct_size: int) -> int:
    """Length of the vector in field 0 of the root table (the element count of EVTS, TRIG and IMUS packets).

    Parameters
    ----------
    b : numpy.ndarray or bytes
        The packet body.
    ident : bytes
        The four-byte FlatBuffers identifier the body must carry.
    struct_size : int
        Bytes of one element when the vector holds structs (16 for events), which must then end the body
        (else ``ST_SLACK``); 0 for a vector of offsets.

    Returns
    -------
    int
        The length, or a negative status.
    """
    start, count = _root_vector(b, ident, struct_size)
    return start if start < 0 else count


# one event of an EVTS packet's vector, as FlatBuffers lays the struct out (little-endian, 16 bytes)
EVENT_DTYPE = np.dtype({"names": ["t", "x", "y", "p"], "formats": ["<i8", "<u2", "<u2", "u1"],
                        "offsets": [0, 8, 10, 12], "itemsize": EVENT_STRUCT})


def decode_events(b, ident: bytes, t, x, y, p, offset: int, capacity: int, width: int, height: int):
    """Decode an EVTS packet body into the columns ``t, x, y, p`` from index ``offset``, with numpy.

    The event vector is viewed as :data:`EVENT_DTYPE` records (at any alignment) and each column copied out
    at once; numpy releases the GIL for the copies, so packets decode in parallel threads, and nothing is
    compiled at run time.

    Parameters
    ----------
    b : numpy.ndarray or bytes
        The decompressed packet body (uint8).
    ident : bytes
        ``b"EVTS"``.
    t, x, y, p : numpy.ndarray
        The output columns (int64, uint16, uint16, uint8).
    offset : int
        Where the packet's first event goes.
    capacity : int
        The most events the packet may hold (room in the columns).
    width, height : int
        The sensor: every event must lie on it.

    Returns
    -------
    count, status : int, int
        ``(events, ST_OK)``; with ``ST_COORD`` the count is the index of the first event outside the sensor
        (x and y are int16 on disk: a negative one reads as 32768 or more and fails too; the events before it
        are written), with ``ST_CAPACITY`` the vector's length; any other status says where the FlatBuffer is
        damaged (nothing written).
    """
    if not isinstance(b, np.ndarray):
        b = np.frombuffer(b, np.uint8)
    start, count = _root_vector(b, ident, EVENT_STRUCT)
    if start < 0:
        return 0, start
    if count > capacity:
        return count, ST_CAPACITY
    ev = b[start:start + EVENT_STRUCT * count].view(EVENT_DTYPE)
    end = offset + count
    xs, ys = x[offset:end], y[offset:end]
    xs[...] = ev["x"]
    ys[...] = ev["y"]
    if count and (int(xs.max()) >= width or int(ys.max()) >= height):
        first = int(np.argmax((xs >= width) | (ys >= height)))
        t[offset:offset + first] = ev["t"][:first]
        np.not_equal(ev["p"][:first], 0, out=p[offset:offset + first].view(np.bool_))
        return first, ST_COORD
    t[offset:end] = ev["t"]
    ps = p[offset:end]
    ps[...] = ev["p"]  # a bool on disk: 0 or 1 but for a damaged file, where any other byte means ON
    if count and int(ps.max()) > 1:
        np.not_equal(ps, 0, out=ps.view(np.bool_))
    return count, ST_OK


def _gather(b, pos, width, signed):
    """Little-endian integers of ``width`` (2, 4 or 8) bytes at the positions ``pos`` (all already checked), as
    int64: each one's bytes gathered into a row and the rows read as one integer each (a pass per byte cost a
    small file's open 0.3 ms in numpy calls)."""
    rows = b[np.asarray(pos, np.int64)[:, None] + np.arange(width)]  # C-ordered: row k holds integer k's bytes
    return rows.view(f"<{'i' if signed else 'u'}{width}").reshape(-1).astype(np.int64)


def _tables(b, slots):
    """The tables that the offsets stored at ``slots`` (a vector of offsets, checked) point to.

    Returns ``(tables, vtables, vt_size, tb_size, bad)``: ``bad`` marks each table that, or whose vtable,
    lies outside the buffer (their other entries are then 0, safe to gather at).
    """
    n = len(b)
    tables = slots + _gather(b, slots, 4, False)
    bad = tables + 4 > n
    tables = np.where(bad, 0, tables)
    vts = tables - _gather(b, tables, 4, True)
    bad |= (vts < 0) | (vts + 4 > n)
    vts = np.where(bad, 0, vts)
    vt_size = _gather(b, vts, 2, False)
    tb_size = _gather(b, vts + 2, 2, False)
    bad |= (vt_size < 4) | (vts + vt_size > n) | (tables + tb_size > n)
    zero = np.zeros_like(tables)
    return (np.where(bad, zero, tables), vts, np.where(bad, zero, vt_size), np.where(bad, zero, tb_size), bad)


def _fields(b, tables, vts, vt_size, tb_size, slot, size):
    """Position of field ``slot`` of each table (0 when absent) and where ``size`` bytes of it would leave
    the table or the buffer."""
    entry = 4 + 2 * slot
    present = entry + 2 <= vt_size
    off = np.where(present, _gather(b, np.where(present, vts + entry, 0), 2, False), 0)
    bad = (off > 0) & ((off + size > tb_size) | (tables + off + size > len(b)))
    return np.where((off > 0) & ~bad, tables + off, 0), bad


def decode_triggers(b, ident: bytes, t, kind, offset: int, capacity: int):
    """Decode a TRIG packet body (a vector of ``Trigger`` tables) into ``t`` and ``kind`` from ``offset``.

    Parameters
    ----------
    b : numpy.ndarray
        The decompressed packet body (uint8).
    ident : bytes
        ``b"TRIG"``.
    t, kind : numpy.ndarray
        The output columns (int64 time stamps in us, uint8 kinds).
    offset : int
        Where the packet's first trigger goes.
    capacity : int
        The most triggers the packet may hold.

    Returns
    -------
    count, status : int, int
        ``(triggers, ST_OK)``; else the index of the first damaged trigger (those before it are written) and
        the status, or ``ST_CAPACITY`` with the vector's length.
    """
    b = np.frombuffer(b, np.uint8)
    root = fb_root(b, ident)
    if root < 0:
        return 0, root
    start, count = fb_vector(b, root, 0, 4)
    if start < 0:
        return 0, start
    if count > capacity:
        return count, ST_CAPACITY
    tables, vts, vt_size, tb_size, bad = _tables(b, start + 4 * np.arange(count, dtype=np.int64))
    f_t, bad_t = _fields(b, tables, vts, vt_size, tb_size, 0, 1)
    f_k, bad_k = _fields(b, tables, vts, vt_size, tb_size, 1, 1)
    bad |= bad_t | bad_k | (f_t + 8 > len(b))  # the stamp's 8 bytes must lie in the buffer
    done = int(np.argmax(bad)) if bad.any() else count
    f_t, f_k = f_t[:done], f_k[:done]
    t[offset:offset + done] = np.where(f_t > 0, _gather(b, f_t, 8, True), 0)
    kind[offset:offset + done] = np.where(f_k > 0, b[f_k], 0)
    return (count, ST_OK) if done == count else (done, ST_BAD_OFFSET)


def decode_data_table(b, ident: bytes):
    """Read a FileDataTable (FTAB), every entry at once.

    Parameters
    ----------
    b : bytes or numpy.ndarray
        The decompressed table.
    ident : bytes
        ``b"FTAB"``.

    Returns
    -------
    columns, status : tuple or None, int
        int64 columns (offset, stream, size, count, t0, t1) and ``ST_OK``, or None and the status.
    """
    b = np.frombuffer(b, np.uint8)
    root = fb_root(b, ident)
    if root < 0:
        return None, root
    field = fb_field(b, root, 0, 4)
    if field <= 0:
        return None, ST_MISSING if field == 0 else field
    start, count = fb_vector(b, root, 0, 4)
    if start < 0:
        return None, start
    out = _table_entries_alike(b, start, count, _FTAB_FIELDS)
    if out is None:
        out = _table_entries(b, start, count, _FTAB_FIELDS)
        if not isinstance(out, list):
            return None, out
    offset, header, cnt, t0, t1 = out
    low = (header & 0xFFFFFFFF).astype(np.int64)
    stream = np.where(low >= 2**31, low - 2**32, low)
    high = (header >> 32).astype(np.int64)
    sizes = np.where(high >= 2**31, high - 2**32, high)
    return (offset, stream, sizes, cnt, t0, t1), ST_OK


# the data table entry's fields (PacketInfo): slot, bytes, signed, required
_FTAB_FIELDS = ((0, 8, True, True), (1, 8, False, True), (2, 8, True, False), (3, 8, True, False), (4, 8, True, False))


def _table_entries(b, start: int, count: int, fields):
    """The ``fields`` (``(slot, bytes, signed, required)`` each) of every table of the vector of ``count``
    offsets at ``start``, as int64 columns (0 where an optional field is absent), or a negative status."""
    tables, vts, vt_size, tb_size, bad = _tables(b, start + 4 * np.arange(count, dtype=np.int64))
    if np.any(bad):
        return ST_BAD_OFFSET
    out = []
    for slot, size, signed, required in fields:
        pos, bad = _fields(b, tables, vts, vt_size, tb_size, slot, size)
        if required and np.any((pos == 0) & ~bad):
            return ST_MISSING
        if np.any(bad):
            return ST_BAD_OFFSET
        out.append(np.where(pos > 0, _gather(b, pos, size, signed), 0))
    return out


def _table_entries_alike(b, start: int, count: int, fields):
    """:func:`_table_entries` of a vector whose tables' vtables all hold the same field offsets (as writers lay
    a data table out; only the tables' sizes may differ) and whose tables, vtables and fields lie on their own
    sizes' multiples, or None where that or anything else does not hold (the general route then reads it, or
    names what is wrong). Every bound the general route checks is checked and the columns are the same; each
    is one look-up in a view of the buffer as words of its size instead of a dozen numpy passes over rows of
    gathered bytes (0.55-0.7 ms of a fresh process's open of a recording, and its memory's first touch).

    Returns
    -------
    list of numpy.ndarray or None
        The int64 columns, one per field, or None.
    """
    n = len(b)
    if count == 0 or start % 4 or any(size != 8 for _, size, _, _ in fields):
        return None
    w32 = b[:n - n % 4].view("<u4")
    tables = w32[start // 4:start // 4 + count] + (start + 4 * np.arange(count, dtype=np.int64))
    if int(tables.max()) + 4 > n or np.any(tables & 3):
        return None
    vts = tables - w32[tables // 4].view("<i4")
    v0 = int(vts[0])
    if int(vts.min()) < 0 or np.any(vts & 1) or v0 + 4 > n:
        return None
    vt_size = u16(b, v0)
    if vt_size < 4 or vt_size % 2 or int(vts.max()) + vt_size > n:
        return None
    w16 = b[:n - n % 2].view("<u2")
    half = vts // 2
    for j in range(vt_size // 2):  # entry 1 is the table's own size (padding), which may differ
        if j != 1 and np.any(w16[half + j] != w16[v0 // 2 + j]):
            return None
    tb_size = w16[half + 1]
    if int((tables + tb_size).max()) > n:
        return None
    room = int(tb_size.min())
    offs = [u16(b, v0 + 4 + 2 * slot) if 4 + 2 * slot + 2 <= vt_size else 0 for slot, _, _, _ in fields]
    if any((off == 0 and required) or off + 8 > room for off, (_, _, _, required) in zip(offs, fields)):
        return None
    w64 = b[:n - n % 8].view("<i8")
    out = []
    for off in offs:
        if not off:
            out.append(np.zeros(count, np.int64))
            continue
        pos = tables + off
        if np.any(pos & 7):
            return None
        out.append(w64[pos // 8])
    return out
