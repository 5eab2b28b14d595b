"""The AEDAT4 data table read at once where every entry's vtable holds the same field offsets (issue 32, a fresh
process's open): the columns and the faults are those of the entry-by-entry route, whatever the layout."""

from __future__ import annotations

import struct

import numpy as np
import pytest

import evtk
from evtk.io import _fbpy

# PacketInfo's fields at these table offsets (after the 4-byte vtable offset): ByteOffset, PacketInfo, NumElements,
# TimestampStart, TimestampEnd
USUAL = (4, 12, 20, 28, 36)


def _table(entries, offsets=lambda k: USUAL, pad=lambda k: 0, shared=False, at=4) -> bytes:
    """A size-prefixed FileDataTable laid out by hand: each entry ``(offset, stream, size, count, t0, t1)`` a table
    with its fields at ``offsets(k)`` (0: absent) and ``pad(k)`` bytes more room, each with its own vtable before
    it (as dv-processing writes them) or, with ``shared``, all pointing to the first one's; each table at ``at``
    modulo 8 (FlatBuffers puts it at 4, so that its 8-byte fields lie on multiples of 8)."""
    n = len(entries)
    buf = bytearray(4 + 4 + 4)  # size prefix, root offset, identifier
    buf[8:12] = b"FTAB"
    buf += struct.pack("<HHH2x", 6, 8, 4)  # root vtable at 12
    root = len(buf)
    buf += struct.pack("<iI", root - 12, 4)  # root table: vtable offset, offset to the vector (just after)
    vec = len(buf)
    buf += struct.pack("<I", n) + bytes(4 * n)
    first_vt = None
    for k, (offset, stream, size, count, t0, t1) in enumerate(entries):
        offs = offsets(k)
        tb_size = max(offs) + 8 + pad(k)
        if not shared or first_vt is None:
            while len(buf) % 4:
                buf += b"\0"
            vt = len(buf)
            buf += struct.pack("<HH5H", 14, tb_size, *offs) + b"\0\0"
            first_vt = first_vt if first_vt is not None else vt
        else:
            vt = first_vt
        while len(buf) % 8 != at:
            buf += b"\0"
        table = len(buf)
        body = bytearray(max(tb_size, max(offs) + 8))  # (a table size cut short in its vtable: the bytes are there)
        struct.pack_into("<i", body, 0, table - vt)
        values = (offset, (stream & 0xFFFFFFFF) | (size << 32), count, t0, t1)
        for off, value in zip(offs, values):
            if off:
                struct.pack_into("<q" if value < 2**63 else "<Q", body, off, value)
        buf += body
        struct.pack_into("<I", buf, vec + 4 + 4 * k, table - (vec + 4 + 4 * k))
    struct.pack_into("<I", buf, 0, len(buf) - 4)
    struct.pack_into("<I", buf, 4, root - 4)
    return bytes(buf)


def _entries(n, seed=0):
    rng = np.random.default_rng(seed)
    return [(int(rng.integers(0, 2**40)), int(rng.integers(-3, 5)), int(rng.integers(0, 2**31)),
             int(rng.integers(0, 10**6)), int(rng.integers(-2**62, 2**62)), int(rng.integers(-2**62, 2**62)))
            for _ in range(n)]


def _general(b, monkeypatch):
    with monkeypatch.context() as m:
        m.setattr(_fbpy, "_table_entries_alike", lambda *a: None)
        return _fbpy.decode_data_table(b, b"FTAB")


def _same(a, b):
    (ca, sa), (cb, sb) = a, b
    assert sa == sb
    assert (ca is None) == (cb is None)
    if ca is not None:
        for x, y in zip(ca, cb):
            assert x.dtype == y.dtype == np.int64 and np.array_equal(x, y)


LAYOUTS = {
    "own vtables, sizes differ": {"pad": lambda k: (k % 3) * 2},
    "one shared vtable": {"shared": True},
    "fields in another order": {"offsets": lambda k: (36, 4, 12, 20, 28)},
    "optional fields absent": {"offsets": lambda k: (4, 12, 0, 0, 20)},
}


@pytest.mark.parametrize("layout", LAYOUTS)
def test_alike_entries_read_at_once_as_one_by_one(monkeypatch, layout):
    entries = _entries(50, seed=len(layout))
    b = _table(entries, **LAYOUTS[layout])
    body = np.frombuffer(b, np.uint8)
    root = _fbpy.fb_root(body, b"FTAB")
    start, count = _fbpy.fb_vector(body, root, 0, 4)
    assert _fbpy._table_entries_alike(body, start, count, _fbpy._FTAB_FIELDS) is not None  # the quick route
    got = _fbpy.decode_data_table(b, b"FTAB")
    _same(got, _general(b, monkeypatch))
    cols, _ = got
    absent = [k for k, off in enumerate(LAYOUTS[layout].get("offsets", lambda k: USUAL)(0)) if not off]
    for k, e in enumerate(entries):
        want = list(e)
        for f in absent:  # NumElements, TimestampStart absent: 0
            want[{2: 3, 3: 4}[f]] = 0
        assert [int(c[k]) for c in cols] == want


HOSTILE = {
    # one entry's vtable names other offsets: the general route reads it
    "one vtable differs": ({"offsets": lambda k: (36, 4, 12, 20, 28) if k == 7 else USUAL}, True),
    # a table too short for a field (its vtable's table size cut): damaged
    "a table too short": ({"pad": lambda k: -8 if k == 30 else 0}, False),
    # tables off the alignment FlatBuffers gives them (readable, not by whole words)
    "tables not on multiples of 4": ({"at": 2}, True),
    "fields not on multiples of 8": ({"at": 0}, True),
    # the required PacketInfo absent everywhere: missing
    "a required field absent": ({"offsets": lambda k: (4, 0, 12, 20, 28)}, False),
}


@pytest.mark.parametrize("case", HOSTILE)
def test_unlike_or_damaged_entries_fall_to_the_general_route(monkeypatch, case):
    kw, readable = HOSTILE[case]
    b = _table(_entries(40, seed=5), **kw)
    got = _fbpy.decode_data_table(b, b"FTAB")
    _same(got, _general(b, monkeypatch))
    assert (got[1] == _fbpy.ST_OK) == readable
    if case == "a required field absent":
        assert got[1] == _fbpy.ST_MISSING


def test_vtable_or_table_past_the_end_is_damage_not_a_read_outside(monkeypatch):
    """Offsets pointing past the buffer (from any entry) give the general route's status."""
    b = bytearray(_table(_entries(20, seed=9)))
    body = np.frombuffer(bytes(b), np.uint8)
    start, count = _fbpy.fb_vector(body, _fbpy.fb_root(body, b"FTAB"), 0, 4)
    for k, value in ((3, 10**6), (19, len(b))):  # an entry's table offset past the end; at the end exactly
        bad = bytearray(b)
        struct.pack_into("<I", bad, start + 4 * k, value)
        got = _fbpy.decode_data_table(bytes(bad), b"FTAB")
        _same(got, _general(bytes(bad), monkeypatch))
        assert got[1] == _fbpy.ST_BAD_OFFSET
    bad = bytearray(b)  # the last table's vtable offset pointing before the buffer
    table = start + 4 * (count - 1) + struct.unpack_from("<I", b, start + 4 * (count - 1))[0]
    struct.pack_into("<i", bad, table, table + 50)
    got = _fbpy.decode_data_table(bytes(bad), b"FTAB")
    _same(got, _general(bytes(bad), monkeypatch))
    assert got[1] == _fbpy.ST_BAD_OFFSET


def test_files_evtk_writes_open_through_the_quick_route(tmp_path, monkeypatch):
    from conftest import random_events

    ev = random_events(30_000, seed=4)
    path = tmp_path / "t.aedat4"
    evtk.write_events(path, ev, packet_events=1_000, packet_us=None)
    calls = []
    real = _fbpy._table_entries_alike
    monkeypatch.setattr(_fbpy, "_table_entries_alike", lambda *a: calls.append(1) or real(*a))
    with evtk.open(path) as rec:
        assert rec._index.from_table and len(rec._index) == 30
        quick = (rec._index.offset.copy(), rec._index.count.copy())
        assert rec.events() == ev
    assert calls
    monkeypatch.setattr(_fbpy, "_table_entries_alike", lambda *a: None)
    with evtk.open(path) as rec:
        assert np.array_equal(rec._index.offset, quick[0]) and np.array_equal(rec._index.count, quick[1])
