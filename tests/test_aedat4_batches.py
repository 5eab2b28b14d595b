"""The AEDAT4 reader's batches (issue 32, every core): a thread decompresses a batch of packets into one staging
buffer, each packet's FlatBuffer header laid over the end of the events before it, and copies the columns out
once. Whatever the packets' header lengths, sizes and codecs, a read returns what the packet-by-packet decode
returns, and damage anywhere in a batch is named exactly as packet by packet."""

from __future__ import annotations

import struct

import lz4.frame
import numpy as np
import pytest
from conftest import random_events
from test_hostile import _aedat4

import evtk
from evtk import _native
from evtk.io import _compression as cz
from evtk.io.aedat4 import reader as a4r

# every test twice: with evtk's compiled kernels and without them (tests/conftest.py)
pytestmark = pytest.mark.usefixtures("compiled")

# events per packet and the padding between each packet's table and its vector: headers of 28 bytes up to
# 28 + 70,000, longer and shorter than the packet before, odd lengths, empty packets between
SIZES = (900, 0, 1, 2_500, 7, 3_000, 0, 640, 1_200, 33, 4_000, 5)
PADS = (0, 4, 1, 0, 100, 3, 70_000, 8, 0, 13, 5, 0)


def _body(ev, pad: int) -> bytes:
    """An EVTS packet body laid out by hand: root offset, identifier, vtable, table, ``pad`` bytes, then the
    event vector, which ends the buffer (a header of ``28 + pad`` bytes)."""
    recs = np.zeros(len(ev), np.dtype({"names": ["t", "x", "y", "p"], "formats": ["<i8", "<u2", "<u2", "u1"],
                                       "offsets": [0, 8, 10, 12], "itemsize": 16}))
    recs["t"], recs["x"], recs["y"], recs["p"] = ev.t, ev.x, ev.y, ev.p
    head = struct.pack("<I4sHHH2xiI", 16, b"EVTS", 6, 8, 4, 8, 4 + pad)
    return head + (bytes(range(256)) * (pad // 256 + 1))[:pad] + struct.pack("<I", len(ev)) + recs.tobytes()


def _frames(code, bodies):
    if code == cz.NONE:
        return list(bodies)
    if code == cz.ZSTD:
        return [cz.compress(cz.ZSTD, b) for b in bodies]
    # with and without a content size (dv-processing writes none), every third one checksummed (faery)
    return [lz4.frame.compress(b, store_size=bool(k % 2), content_checksum=k % 3 == 0, block_checksum=k % 3 == 0)
            for k, b in enumerate(bodies)]


def _packet_by_packet(rec, **kw):
    """What the reader returns without batches (the decode before them)."""
    rec._batcher = lambda *a: None
    try:
        return rec.events(**kw)
    finally:
        del rec._batcher


@pytest.mark.parametrize("code", [cz.NONE, cz.LZ4, cz.ZSTD])
@pytest.mark.parametrize("threads", ["1", "2"])
@pytest.mark.parametrize("batch_events", [1, 1_000, 5_000, 1 << 18])
def test_batches_read_what_packet_by_packet_reads(tmp_path, monkeypatch, code, threads, batch_events):
    monkeypatch.setenv("EVTK_THREADS", threads)
    monkeypatch.setattr(a4r, "BATCH_EVENTS", batch_events)
    evs = [random_events(n, seed=60 + k) for k, n in enumerate(SIZES)]
    path = tmp_path / "pads.aedat4"
    _aedat4(path, code, _frames(code, [_body(ev, pad) for ev, pad in zip(evs, PADS)]))
    expected = evtk.Events.concatenate(evs)
    with evtk.open(path) as rec:
        assert rec.events() == expected
        assert _packet_by_packet(rec) == expected
        assert rec.events(1_000, 400_000) == expected.between(1_000, 400_000)


def test_batches_are_used(tmp_path, monkeypatch):
    """The batched route really carries the read (not the packet-by-packet one it falls back to)."""
    monkeypatch.setattr(a4r, "BATCH_EVENTS", 5_000)
    evs = [random_events(n, seed=80 + k) for k, n in enumerate(SIZES)]
    path = tmp_path / "used.aedat4"
    _aedat4(path, cz.LZ4, _frames(cz.LZ4, [_body(ev, pad) for ev, pad in zip(evs, PADS)]))
    calls = []
    decode = a4r._fbpy.decode_events  # the packet-by-packet decode of one body
    monkeypatch.setattr(a4r._fbpy, "decode_events", lambda *a: calls.append(1) or decode(*a))
    with evtk.open(path) as rec:
        assert rec.events() == evtk.Events.concatenate(evs)
        assert calls == []
        monkeypatch.setattr(rec, "_batcher", lambda *a: None)
        assert rec.events() == evtk.Events.concatenate(evs)
        assert len(calls) == len(SIZES)


@pytest.mark.parametrize("small", [1_000, 1 << 20])
def test_a_small_read_takes_small_batches(tmp_path, monkeypatch, compiled, small):
    """A read of fewer than 16 batches' events takes batches of a sixteenth of it, at least
    ``SMALL_BATCH_EVENTS`` (the memory a fresh process touches first costs page faults), and reads the same; the
    compiled range cuts its batches as the Python loop does."""
    monkeypatch.setattr(a4r, "SMALL_BATCH_EVENTS", small)
    evs = [random_events(n, seed=70 + k) for k, n in enumerate(SIZES)]
    path = tmp_path / "small.aedat4"
    _aedat4(path, cz.LZ4, _frames(cz.LZ4, [_body(ev, pad) for ev, pad in zip(evs, PADS)]))
    with evtk.open(path) as rec:
        assert rec.events() == evtk.Events.concatenate(evs)  # (this file's packets counted: no data table)
        reads = []  # one a batch: the Python loop's reads, or the batches the range kernel says it decoded
        pread = rec._pread_into
        monkeypatch.setattr(rec, "_pread_into", lambda buf, off: reads.append(off) or pread(buf, off))
        ranged = _native._kernel_decode_lz4_range

        def counted(*args):
            got = ranged(*args)
            reads.extend([None] * got[3])
            return got

        monkeypatch.setattr(_native, "_kernel_decode_lz4_range", counted)
        assert rec.events() == evtk.Events.concatenate(evs)
    # 1,000-event batches: the packets of 900 to 4,000 events one or two at a time; else the file in one read
    assert len(reads) == (9 if small == 1_000 else 1), reads
    assert (None in reads) == (compiled == "compiled")


def _damage(kind, bodies, evs):
    """The bodies with one packet in the middle damaged as ``kind`` says."""
    bodies = list(bodies)
    k = 5
    if kind == "off sensor":
        ev = evs[k]
        x = np.array(ev.x)
        x[1000] = 320
        bodies[k] = _body(evtk.Events(ev.t, x, ev.y, ev.p, (400, 240)), PADS[k])
    elif kind == "bad flatbuffer":
        b = bytearray(bodies[k])
        b[4:8] = b"XXXX"
        bodies[k] = bytes(b)
    elif kind == "polarity byte":
        b = bytearray(bodies[k])
        b[len(b) - 16 * 10 + 12] = 7  # event 10 from the end: a damaged bool, which reads as ON
        bodies[k] = bytes(b)
    return bodies


@pytest.mark.parametrize("kind", ["off sensor", "bad flatbuffer", "polarity byte", "bad frame"])
@pytest.mark.parametrize("salvage", [False, True])
def test_damage_inside_a_batch_is_named_as_packet_by_packet(tmp_path, monkeypatch, kind, salvage):
    monkeypatch.setattr(a4r, "BATCH_EVENTS", 20_000)  # the whole file one batch on one thread
    monkeypatch.setattr(a4r, "SMALL_BATCH_EVENTS", 20_000)
    monkeypatch.setenv("EVTK_THREADS", "1")
    evs = [random_events(n, seed=90 + k) for k, n in enumerate(SIZES)]
    bodies = _damage(kind, [_body(ev, pad) for ev, pad in zip(evs, PADS)], evs)
    frames = _frames(cz.LZ4, bodies)
    if kind == "bad frame":
        frames[5] = frames[5][:-4]  # its end mark cut off
    path = tmp_path / "bad.aedat4"
    _aedat4(path, cz.LZ4, frames)
    outcomes = []
    for batched in (True, False):
        with evtk.open(path, salvage=salvage) as rec:
            try:
                got = rec.events() if batched else _packet_by_packet(rec)
                outcomes.append(("ok", got, str(rec.damage) if salvage else None))
            except evtk.FormatError as exc:
                outcomes.append(("error", str(exc), None))
    assert outcomes[0][0] == outcomes[1][0]
    if outcomes[0][0] == "ok":
        assert outcomes[0][1] == outcomes[1][1] and outcomes[0][2] == outcomes[1][2]
    else:
        assert outcomes[0][1] == outcomes[1][1]
    if kind == "polarity byte":  # not damage: the byte is read as ON, in both routes
        assert outcomes[0][0] == "ok" and len(outcomes[0][1]) == sum(SIZES)
    elif not salvage:
        assert outcomes[0][0] == "error"
    else:  # salvage: the packets before the damaged one, whole
        assert outcomes[0][1] == evtk.Events.concatenate(evs[:5])


def move_off_sensor(path, packets, events_each: int) -> list[int]:
    """Move the first event of each of ``packets`` (uncompressed EVTS packets of ``events_each`` events) to x =
    400, off a sensor narrower than that, in place; returns every packet's byte offset."""
    from evtk.io import _fbpy

    data = bytearray(path.read_bytes())
    with evtk.open(path) as rec:
        offsets = [int(v) for v in rec._index.offset]
        sizes = [int(v) for v in rec._index.size]
    for k in packets:
        body = np.frombuffer(bytes(data[offsets[k]:offsets[k] + sizes[k]]), np.uint8)
        start, count = _fbpy._root_vector(body, b"EVTS", 16)
        assert count == events_each
        data[offsets[k] + start + 8:offsets[k] + start + 10] = (400).to_bytes(2, "little")
    path.write_bytes(bytes(data))
    return offsets


def test_of_two_damaged_packets_the_first_is_named_whichever_thread_meets_it(tmp_path, monkeypatch):
    """Strict reads on several threads raise the fault of the earliest damaged packet, as one thread reading
    packet by packet would, even when a later range fails first (here the ranges before the first damage are
    slowed down, so the later damage is met first)."""
    import time as _time
    monkeypatch.setenv("EVTK_THREADS", "3")
    monkeypatch.setattr(a4r, "_THREAD_BYTES", 1)
    ev = random_events(270_000, seed=210)
    path = tmp_path / "two.aedat4"
    evtk.write_events(path, ev, compression="none", packet_events=3_000, packet_us=None)
    offsets = move_off_sensor(path, (20, 80), 3_000)
    with evtk.open(path) as rec:
        body = rec._body
        slow = set(offsets[10:21])

        def late(i, *s):  # the packets before the first damage take longer
            if int(rec._index.offset[i]) in slow:
                _time.sleep(0.02)
            return body(i, *s)

        monkeypatch.setattr(rec, "_body", late)
        monkeypatch.setattr(rec, "_batcher", lambda *a: None)
        with pytest.raises(evtk.FormatError) as err:
            rec.events()
    assert f"at byte {offsets[20]}" in str(err.value), str(err.value)


def test_a_chunked_read_decodes_each_chunk_on_more_than_one_thread(tmp_path, monkeypatch):
    """A whole read keeps its decoding threads' memory within 8 % of its arrays, but a chunked read's memory is a
    chunk's whatever the file: its chunks are decoded on the threads the chunk's own memory pays for (one thread
    for 8 % of a 1 M-event chunk left fixed windows' counting decoding on one core), and give the same events."""
    monkeypatch.setenv("EVTK_THREADS", "2")
    rng = np.random.default_rng(3)
    n = 600_000
    ev = evtk.Events(np.sort(rng.integers(0, 10**6, n)), rng.integers(0, 320, n).astype(np.uint16),
                     rng.integers(0, 240, n).astype(np.uint16), rng.integers(0, 2, n).astype(np.uint8), (320, 240))
    path = tmp_path / "chunked.aedat4"
    evtk.write_events(path, ev)
    threads: list[int] = []
    real = a4r.workers_within

    def counted(*args):
        threads.append(real(*args))
        return threads[-1]

    monkeypatch.setattr(a4r, "workers_within", counted)
    with evtk.open(path) as rec:
        whole = rec.events()
        assert threads and max(threads) == 1  # 8 % of 7.8 MB of arrays: one thread's buffers
        threads.clear()
        chunks = list(rec.iter_events(chunk_events=n))
    assert threads and max(threads) == 2
    for got in (whole, evtk.Events(*(np.concatenate([getattr(c, k) for c in chunks]) for k in "txyp"), (320, 240))):
        assert all(np.array_equal(getattr(got, k), getattr(ev, k)) for k in "txyp")


def _root_vector_by_parts(b, ident, struct_size):
    """The root vector found through fb_root, fb_vector and the slack rule, one step at a time (the reference
    :func:`_fbpy._root_vector_at` must agree with)."""
    from evtk.io import _fbpy

    root = _fbpy.fb_root(b, ident)
    if root < 0:
        return root, 0
    start, count = _fbpy.fb_vector(b, root, 0, max(1, struct_size))
    if start < 0:
        return start, 0
    if struct_size > 0 and len(b) - (start + struct_size * count) >= struct_size:
        return _fbpy.ST_SLACK, 0
    return start, count


def test_a_packet_header_read_in_place_is_read_as_step_by_step():
    """The batches' one-call parse of a packet's FlatBuffer header, in place in the staging buffer, gives what
    the step-by-step parse of the body alone gives, on intact, cut, bit-flipped and random headers."""
    from evtk.io import _fbpy

    rng = np.random.default_rng(7)
    bodies = [_body(random_events(n, seed=n), pad) for n, pad in ((0, 0), (1, 0), (3, 5), (40, 64), (2, 300))]
    bodies.append(struct.pack("<I4sHHi", 12, b"EVTS", 4, 4, 4) + bytes(8))  # root tables without field 0
    bodies.append(struct.pack("<I4sHHHxxi", 16, b"EVTS", 6, 4, 0, 8) + bytes(4))
    bodies.append(bodies[2][4:])  # not size-prefixed
    seen = set()
    for k in range(6000):
        b = bytearray(bodies[k % len(bodies)])
        kind = k % 4
        if kind == 1 and len(b):  # cut
            b = b[:int(rng.integers(0, len(b)))]
        elif kind == 2:  # a few bytes of the header changed
            for _ in range(int(rng.integers(1, 4))):
                b[int(rng.integers(0, min(len(b), 48)))] = int(rng.integers(0, 256))
        elif kind == 3:  # random
            b = bytearray(rng.integers(0, 256, int(rng.integers(0, 80)), dtype=np.uint8).tobytes())
            if len(b) >= 12 and k % 8 == 3:
                b[8:12] = b"EVTS"
        pad = int(rng.integers(0, 9))
        buf = np.frombuffer(bytes(rng.integers(0, 256, pad, dtype=np.uint8)) + bytes(b) + b"\xff" * 32, np.uint8)
        for size in (16, 0):
            want = _root_vector_by_parts(np.frombuffer(bytes(b), np.uint8), b"EVTS", size)
            assert _fbpy._root_vector_at(buf, pad, len(b), b"EVTS", size) == want, (k, bytes(b).hex())
            seen.add(want[0] if want[0] < 0 else "ok")
    assert seen >= {"ok", _fbpy.ST_BAD_IDENT, _fbpy.ST_BAD_OFFSET, _fbpy.ST_SLACK}, seen


@pytest.mark.parametrize("threads", [2, 5, 16])
def test_the_threads_ranges_shrink_to_the_end_and_cover_every_packet_once(monkeypatch, threads):
    # packets of uneven sizes over the threads: the ranges run back to back over every row, the long ones first,
    # and the last ones short (no thread left alone with a long range at the end); a range that stops early
    # ends the intact prefix there
    monkeypatch.setenv("EVTK_THREADS", str(threads))
    rng = np.random.default_rng(threads)
    counts = rng.integers(1_000, 20_000, 2_000)
    total = int(counts.sum())
    seen: list[tuple[int, int]] = []

    def work(a, b):
        seen.append((a, b))
        return b

    assert a4r._run_split(work, len(counts), counts) == len(counts)
    seen.sort()
    assert seen[0][0] == 0 and seen[-1][1] == len(counts)
    assert all(b == c for (_, b), (c, _) in zip(seen, seen[1:])) and all(a < b for a, b in seen)
    sizes = [int(counts[a:b].sum()) for a, b in seen]
    assert sizes[0] > 4 * sizes[-2]  # guided: the first range is several of the last ones
    assert max(sizes[-3:]) <= total // (16 * threads) + int(counts.max())  # the last ones at the floor
    assert len(seen) <= 8 * threads  # few ranges, however many packets

    stop = seen[len(seen) // 2]
    assert a4r._run_split(lambda a, b: a if (a, b) == stop else b, len(counts), counts) == stop[0]
