"""evtk's compiled batches of LZ4 event packets (``evtk._native.decode_lz4_range``, a thread's batches read and
decoded in one call, and ``evtk._native.decode_lz4_batch``, one batch a call): used for every batch of a
healthy LZ4 file, the same events as the Python loop, and for anything else (damage, a header that disagrees with
the data table, checksums to leave unread, a body too large for its room) a decline that leaves the batch to
the Python loop, never a crash or a different answer."""

from __future__ import annotations

import struct
from pathlib import Path

import lz4.frame
import numpy as np
import pytest
from conftest import random_events
from test_aedat4_batches import _body
from test_hostile import _aedat4

import evtk
from evtk import _native
from evtk.io import _compression as cz
from evtk.io import _fbpy
from evtk.io.aedat4 import reader as a4r

pytestmark = pytest.mark.skipif(not _native.BUILT, reason="evtk._ckernels was not built (no C compiler)")

SENSOR = (320, 240)


class _Spy:
    """Counts the kernels' answers while a test runs, a batch at a time: True for each batch the range kernel or
    the one-batch kernel decoded, False for each one it left to the Python loop; ``codecs`` holds each range
    call's codec (0 LZ4, 1 Zstandard)."""

    def __init__(self, monkeypatch):
        self.answers: list[bool] = []
        self.codecs: list[int] = []
        real = _native._kernel_decode_lz4_batch
        ranged = _native._kernel_decode_lz4_range

        def spy(*args):
            got = real(*args)
            self.answers.append(got)
            return got

        def spy_range(*args):
            got = ranged(*args)
            self.codecs.append(args[26] if len(args) > 26 else 0)  # (the optional codec after the sensor)
            k, need_raw, need_stage, batches, _ = got
            self.answers.extend([True] * batches)
            if k < args[7] and not need_raw and not need_stage:  # (args[7]: k1) a batch declined
                self.answers.append(False)
            return got

        monkeypatch.setattr(_native, "_kernel_decode_lz4_batch", spy)
        monkeypatch.setattr(_native, "_kernel_decode_lz4_range", spy_range)


def _read_both(monkeypatch, path, **kw):
    out = {}
    for value in ("1", "0"):
        monkeypatch.setenv("EVTK_NATIVE", value)
        with evtk.open(path, **kw) as rec:
            out[value] = rec.events()
    return out["1"], out["0"]


def _same(a, b):
    for c in "txyp":
        np.testing.assert_array_equal(getattr(a, c), getattr(b, c))


@pytest.mark.parametrize("threads", ["1", "2"])
def test_every_batch_of_a_healthy_lz4_file_goes_through_the_kernel_with_the_same_events(tmp_path, monkeypatch,
                                                                                       threads):
    monkeypatch.setenv("EVTK_THREADS", threads)
    ev = random_events(300_000, seed=4)
    path = tmp_path / "a.aedat4"
    evtk.write_events(path, ev, compression="lz4")
    spy = _Spy(monkeypatch)
    compiled, python = _read_both(monkeypatch, path)
    assert spy.answers and all(spy.answers)
    _same(compiled, python)
    _same(compiled, ev)


def test_frames_with_checksums_are_verified_by_the_kernel_and_left_to_python_when_unread(tmp_path, monkeypatch):
    # faery's frames carry block and content checksums: verified as they decompress; with verification off
    # the Python route rebuilds each frame without them, so the kernel declines those batches
    ev = random_events(40_000, seed=6)
    bodies = [_body(ev[i:i + 4_096], 0) for i in range(0, len(ev), 4_096)]
    frames = [lz4.frame.compress(b, content_checksum=True, block_checksum=True) for b in bodies]
    path = tmp_path / "sums.aedat4"
    _aedat4(path, cz.LZ4, frames)
    spy = _Spy(monkeypatch)
    compiled, python = _read_both(monkeypatch, path)
    assert spy.answers and all(spy.answers)
    _same(compiled, python)
    spy.answers.clear()
    compiled, python = _read_both(monkeypatch, path, verify_checksums=False)
    assert spy.answers and not any(spy.answers)
    _same(compiled, python)
    # a flipped bit in one frame's compressed data: the kernel declines, and the Python route names it
    damaged = bytearray(frames[3])
    damaged[len(damaged) // 2] ^= 0x40
    _aedat4(path, cz.LZ4, frames[:3] + [bytes(damaged)] + frames[4:])
    for value in ("1", "0"):
        monkeypatch.setenv("EVTK_NATIVE", value)
        with pytest.raises(evtk.FormatError, match="checksum"):
            evtk.read_events(path)


def _one_packet(body: bytes, frame: bytes | None = None, *, sid=0, size=None, count=None, stage_bytes=None,
                verify=True, sensor=SENSOR):
    """The kernel on one packet: ``(answer, columns)``."""
    frame = lz4.frame.compress(body) if frame is None else frame
    raw = np.frombuffer(struct.pack("<ii", 0, len(frame)) + frame, np.uint8).copy()
    n = count if count is not None else max(0, (len(body) - 28) // 16)
    columns = (np.zeros(n, np.int64), np.zeros(n, np.uint16), np.zeros(n, np.uint16), np.zeros(n, np.uint8))
    stage = np.zeros(stage_bytes or len(body) + 4096, np.uint8)
    scratch = cz.Scratch()
    got = _native.decode_lz4_batch(raw, np.array([0], np.int64), np.array([sid], np.int64),
                                   np.array([len(frame) if size is None else size], np.int64), np.array([n], np.int64),
                                   verify, cz.lz4f_addresses(scratch), stage, cz.BODY_FLOOR_BYTES, cz.BODY_RATIO,
                                   cz.MAX_PACKET_BYTES, columns, sensor)
    return got, columns


def _python_rule(body: bytes, n: int, sensor=SENSOR):
    """What the Python loop accepts of a decompressed body that should hold ``n`` events: the events, or None."""
    buf = np.frombuffer(body, np.uint8)
    start, count = _fbpy._root_vector_at(buf, 0, len(buf), b"EVTS", 16)
    if start < 0 or count != n:
        return None
    ev = buf[start:start + 16 * count].view(_fbpy.EVENT_DTYPE)
    if count and (int(ev["x"].max()) >= sensor[0] or int(ev["y"].max()) >= sensor[1]):
        return None
    return ev


def test_a_healthy_packet_and_the_faults_the_kernel_declines():
    ev = random_events(500, seed=1)
    body = _body(ev, 12)
    got, (t, x, y, p) = _one_packet(body)
    assert got
    np.testing.assert_array_equal(t, ev.t)
    np.testing.assert_array_equal(x, ev.x)
    np.testing.assert_array_equal(p, ev.p)
    assert not _one_packet(body, sid=1)[0]  # the header's stream is not the table's
    assert not _one_packet(body, size=17)[0]  # nor its size
    assert not _one_packet(body, count=499)[0]  # the table's count is not the packet's
    assert not _one_packet(body, stage_bytes=1_000)[0]  # the body does not fit its room
    assert not _one_packet(body, sensor=(int(ev.x.max()), 240))[0]  # an event off the sensor
    assert not _one_packet(body, frame=cz.compress(cz.ZSTD, body))[0]  # not an LZ4 frame
    assert not _one_packet(body, frame=lz4.frame.compress(body)[:-9])[0]  # a frame cut short
    checked = lz4.frame.compress(body, content_checksum=True)
    assert _one_packet(body, frame=checked)[0] and not _one_packet(body, frame=checked, verify=False)[0]
    sized = lz4.frame.compress(body, store_size=True)
    wrong = bytearray(sized)
    wrong[6:14] = struct.pack("<Q", len(body) - 16)  # a stated size the content does not meet
    assert _one_packet(body, frame=sized)[0] and not _one_packet(body, frame=bytes(wrong))[0]
    polar = bytearray(body)
    polar[-4] = 7  # the last event's polarity byte: not 0, so ON
    got, (_, _, _, p) = _one_packet(bytes(polar))
    assert got and p[-1] == 1


@pytest.mark.parametrize("n", [1, 7, 8, 9, 16, 23, 500])
def test_the_column_split_of_any_event_bytes_is_the_structs_and_checks_every_event(n):
    """The events' split into columns (eight at a time with SSE2, the rest one by one): every time stamp (any
    int64), x and y (any uint16, 32,768 and above included) and polarity byte (any value: 1 where not 0) as the
    FlatBuffer's structs hold them, for counts around the eight; and an x equal to the sensor's width or a y equal
    to its height, at any event, declines the packet where one less is taken."""
    rng = np.random.default_rng(n)
    ev = random_events(n, seed=n)
    body = bytearray(_body(ev, 12))
    start, count = _fbpy._root_vector_at(np.frombuffer(bytes(body), np.uint8), 0, len(body), b"EVTS", 16)
    assert count == n
    structs = np.frombuffer(body, np.uint8, 16 * n, start).copy()
    structs[:] = rng.integers(0, 256, structs.size, dtype=np.uint8)  # every byte random, padding too
    body[start:start + 16 * n] = structs.tobytes()
    want = np.frombuffer(structs.tobytes(), _fbpy.EVENT_DTYPE)
    wide = (int(want["x"].max()) + 1, int(want["y"].max()) + 1)
    got, (t, x, y, p) = _one_packet(bytes(body), sensor=wide)
    assert got
    np.testing.assert_array_equal(t, want["t"])
    np.testing.assert_array_equal(x, want["x"])
    np.testing.assert_array_equal(y, want["y"])
    np.testing.assert_array_equal(p, (structs.reshape(n, 16)[:, 12] != 0).astype(np.uint8))
    for i in sorted({0, n // 2, n - 1}):
        for field in (8, 10):
            edge = bytearray(body)
            small = bytearray(body)
            for b in (edge, small):  # every event well inside a 1000 x 1000 sensor, the other coordinate too
                arr = np.frombuffer(b, np.uint8, 16 * n, start).reshape(n, 16).copy()
                arr[:, 8:12] = np.frombuffer(np.full(2 * n, 3, "<u2").tobytes(), np.uint8).reshape(n, 4)
                arr[i, field:field + 2] = np.frombuffer(struct.pack("<H", 1000 if b is edge else 999), np.uint8)
                b[start:start + 16 * n] = arr.tobytes()
            assert not _one_packet(bytes(edge), sensor=(1000, 1000))[0], (n, i, field)
            assert _one_packet(bytes(small), sensor=(1000, 1000))[0], (n, i, field)


def test_hostile_headers_never_crash_the_kernel_and_it_accepts_only_what_python_accepts():
    # 3,000 bodies with random bytes of the FlatBuffer's header (root offset, identifier, vtable, table, vector
    # offset and length) overwritten: the kernel's answer must be the Python rule's, its events the same
    rng = np.random.default_rng(11)
    ev = random_events(64, seed=2)
    base = bytearray(_body(ev, 8))
    agreed = {True: 0, False: 0}
    for _ in range(3_000):
        body = bytearray(base)
        for _ in range(int(rng.integers(1, 4))):
            at = int(rng.integers(0, 44))  # the 36-byte header and the vector's length field
            body[at] = int(rng.integers(0, 256))
        if rng.random() < 0.2:
            del body[len(body) - int(rng.integers(1, 40)):]  # and sometimes its end cut off
        elif rng.random() < 0.2:
            body += bytes(int(rng.integers(1, 40)))  # or bytes after the vector (room for another event: refused)
        body = bytes(body)
        want = _python_rule(body, len(ev))
        got, (t, x, y, p) = _one_packet(body, count=len(ev))
        assert got == (want is not None)
        if got:
            np.testing.assert_array_equal(t, want["t"])
            np.testing.assert_array_equal(x, want["x"])
            np.testing.assert_array_equal(p, want["p"] != 0)
        agreed[got] += 1
    assert agreed[True] > 50 and agreed[False] > 500  # both kinds of answer were reached


def test_corrupt_compressed_data_never_crashes_the_kernel():
    # random bytes of the LZ4 frame overwritten (no checksums to catch it): the kernel declines or gives what
    # python-lz4 decompresses, never something else
    rng = np.random.default_rng(5)
    ev = random_events(300, seed=3)
    body = _body(ev, 0)
    frame = lz4.frame.compress(body)
    for _ in range(1_000):
        bad = bytearray(frame)
        for _ in range(int(rng.integers(1, 6))):
            bad[int(rng.integers(0, len(bad)))] = int(rng.integers(0, 256))
        got, (t, x, y, p) = _one_packet(body, frame=bytes(bad), count=len(ev))
        if got:
            want = _python_rule(lz4.frame.decompress(bytes(bad)), len(ev))
            assert want is not None
            np.testing.assert_array_equal(t, want["t"])
            np.testing.assert_array_equal(y, want["y"])


def test_arguments_outside_the_batch_are_declined(monkeypatch):
    body = _body(random_events(10, seed=1), 0)
    frame = lz4.frame.compress(body)
    raw = np.frombuffer(struct.pack("<ii", 0, len(frame)) + frame, np.uint8).copy()
    cols = (np.zeros(10, np.int64), np.zeros(10, np.uint16), np.zeros(10, np.uint16), np.zeros(10, np.uint8))
    one = np.array([0], np.int64)
    scratch = cz.Scratch()

    def call(heads=one, sizes=None, cols=cols, raw=raw, stage=None):
        sizes = np.array([len(frame)], np.int64) if sizes is None else sizes
        stage = np.zeros(4096, np.uint8) if stage is None else stage
        return _native.decode_lz4_batch(raw, heads, np.zeros(len(heads), np.int64), sizes,
                                        np.full(len(heads), 10, np.int64), True, cz.lz4f_addresses(scratch), stage,
                                        cz.BODY_FLOOR_BYTES, cz.BODY_RATIO, cz.MAX_PACKET_BYTES, cols, SENSOR)

    assert call()
    assert not call(heads=np.array([len(raw) - 4], np.int64))  # a header past the bytes read
    assert not call(heads=np.array([-1], np.int64))
    assert not call(sizes=np.array([len(frame) + 1], np.int64), raw=raw[:-1].copy())  # a body past them
    assert not call(heads=np.array([0, 0], np.int64))  # more events than the columns hold
    assert not call(cols=tuple(c[:9] for c in cols))
    # output limits whose sum or product would wrap: the room stays the stage's, never more
    top = (1 << 63) - 1
    for floor, ratio, most in ((1 << 62, 1 << 62, top), (0, 1 << 62, top), (top, 0, top), (top, 1 << 40, 1 << 20)):
        args = dict(floor_bytes=floor, ratio=ratio, most_bytes=most)
        assert _native.decode_lz4_batch(raw, one, np.zeros(1, np.int64), np.array([len(frame)], np.int64),
                                        np.full(1, 10, np.int64), True, cz.lz4f_addresses(scratch),
                                        np.zeros(100, np.uint8), columns=cols, sensor_size=SENSOR, **args) is False
    assert not call(heads=one.astype(np.int32))  # the wrapper's checks: types, contiguity, writable
    assert not call(raw=np.frombuffer(raw.tobytes(), np.uint8)[::1][:len(raw)].astype(np.int8))
    assert not call(stage=np.zeros(8192, np.uint8)[::2])
    monkeypatch.setenv("EVTK_NATIVE", "0")
    assert not call()


REAL = Path(__file__).resolve().parent.parent.parent / "shared" / "real-files"


def _outcome(path, salvage):
    try:
        with evtk.open(path, salvage=salvage) as rec:
            ev = rec.events()
            return "events", ev.t.tobytes(), ev.x.tobytes(), ev.y.tobytes(), ev.p.tobytes(), tuple(rec.warnings)
    except evtk.EvtkError as exc:
        return "error", type(exc).__name__, str(exc)


@pytest.mark.parametrize("name", ["evtk", "tonic__sample.aedat4", "hetk987__dvSave-2025_10_22_18_39_29.aedat4"])
def test_flipped_bits_give_the_same_events_or_the_same_error_with_the_kernel_and_without(tmp_path, monkeypatch,
                                                                                         name):
    # hostile copies: bits flipped anywhere past the file's header; with salvage and without, the compiled
    # batches and the Python loop give the same events, warnings and errors
    if name == "evtk":
        source = tmp_path / "evtk.aedat4"
        evtk.write_events(source, random_events(120_000, seed=8), compression="lz4", packet_events=5_000)
    else:
        source = REAL / name
        if not source.exists():
            pytest.skip("../shared/real-files is not beside the checkout")
    _flipped_copies_read_alike(monkeypatch, source.read_bytes(), tmp_path / "flipped.aedat4", 21)


def _flipped_copies_read_alike(monkeypatch, data, path, seed):
    """40 copies of the file ``data`` with 1-3 bits flipped past its first fiftieth, written to ``path``: with
    salvage and without, the compiled batches and the Python loop give the same events, warnings and errors."""
    rng = np.random.default_rng(seed)
    for _ in range(40):
        flipped = bytearray(data)
        for _ in range(int(rng.integers(1, 4))):
            flipped[int(rng.integers(len(data) // 50, len(data)))] ^= 1 << int(rng.integers(0, 8))
        path.write_bytes(bytes(flipped))
        for salvage in (False, True):
            monkeypatch.setenv("EVTK_NATIVE", "1")
            compiled = _outcome(path, salvage)
            monkeypatch.setenv("EVTK_NATIVE", "0")
            assert _outcome(path, salvage) == compiled


def _two_streams(path, bodies, other_at, other_bytes):
    """An LZ4 AEDAT4 file of event packets (stream 0) with one packet of another stream (1, ``other_bytes`` of
    LZ4 noise) after the ``other_at``-th: no data table, so the reader counts the packets."""
    from evtk.io.aedat4 import writer as a4w

    xml = a4w._header_xml([("events", "EVTS", {"sizeX": ("int", 320), "sizeY": ("int", 240)}),
                           ("imu", "IMUS", {})], cz.LZ4)
    out = bytearray(a4w.MAGIC + a4w._io_header(cz.LZ4, -1, xml))
    other = lz4.frame.compress(np.random.default_rng(1).integers(0, 256, other_bytes, dtype=np.uint8).tobytes())
    for k, body in enumerate(bodies):
        frame = lz4.frame.compress(body)
        out += struct.pack("<ii", 0, len(frame)) + frame
        if k == other_at:
            out += struct.pack("<ii", 1, len(other)) + other
    path.write_bytes(bytes(out))


def test_a_batch_around_another_streams_large_packet_is_left_to_python_and_reads_the_same(tmp_path, monkeypatch):
    # the range kernel reads a batch's bytes at once only when they are mostly its own packets: a megabyte of
    # another stream between two event packets sends that batch to the Python loop, packet by packet
    ev = random_events(40_000, seed=8)
    bodies = [_body(ev[i:i + 4_000], 0) for i in range(0, len(ev), 4_000)]
    path = tmp_path / "imu.aedat4"
    _two_streams(path, bodies, 4, 1 << 20)
    spy = _Spy(monkeypatch)
    compiled, python = _read_both(monkeypatch, path)
    assert False in spy.answers and True in spy.answers
    _same(compiled, python)
    _same(compiled, ev)
    # the same packets without it: every batch through the kernel
    _two_streams(path, bodies, -1, 0)
    spy.answers.clear()
    compiled, python = _read_both(monkeypatch, path)
    assert spy.answers and all(spy.answers)
    _same(compiled, ev)


@pytest.mark.parametrize("native", ["1", "0"])
def test_a_file_cut_short_after_it_was_opened_is_an_error_not_stale_events(tmp_path, monkeypatch, native):
    # the packets were indexed when the file opened; its end then goes missing: the read that comes back short
    # is named, whichever route reads it (the range kernel hands that batch to the Python loop)
    monkeypatch.setenv("EVTK_NATIVE", native)
    monkeypatch.setenv("EVTK_THREADS", "1")
    ev = random_events(200_000, seed=9)
    path = tmp_path / "cut.aedat4"
    evtk.write_events(path, ev, compression="lz4")
    with evtk.open(path) as rec:
        rec.info()
        size = path.stat().st_size
        with open(path, "r+b") as f:
            f.truncate(size * 3 // 4)
        with pytest.raises(evtk.EvtkError) as err:
            rec.events()
    assert "cut.aedat4" in str(err.value)


def test_a_batch_read_short_is_never_decoded_from_the_bytes_of_the_batch_before(tmp_path, monkeypatch):
    # eight identical packets, two a batch: a read that comes back empty leaves the previous batch's bytes in the
    # buffer, exactly where this batch's would be; they must not pass for this batch's events
    monkeypatch.setenv("EVTK_THREADS", "1")
    monkeypatch.setattr(a4r, "SMALL_BATCH_EVENTS", 2_000)
    ev = random_events(1_000, seed=10)
    frame = lz4.frame.compress(_body(ev, 0))
    path = tmp_path / "same.aedat4"
    _aedat4(path, cz.LZ4, [frame] * 8)
    spy = _Spy(monkeypatch)
    with evtk.open(path) as rec:
        rec.info()
        size = path.stat().st_size
        with open(path, "r+b") as f:  # the last two batches' packets gone
            f.truncate(size - 4 * (8 + len(frame)))
        with pytest.raises(evtk.EvtkError):
            rec.events()
    assert spy.answers[:2] == [True, True]  # the first two batches decoded, the third left to the Python loop


def test_without_the_range_kernel_every_batch_goes_through_the_one_batch_kernel(tmp_path, monkeypatch):
    # an install built before the range kernel: the reader asks for it once, then calls the one-batch kernel
    ev = random_events(300_000, seed=11)
    path = tmp_path / "a.aedat4"
    evtk.write_events(path, ev, compression="lz4")
    spy = _Spy(monkeypatch)
    monkeypatch.setattr(_native, "_kernel_decode_lz4_range", None)
    batches = _native._kernel_decode_lz4_batch
    calls = []
    monkeypatch.setattr(_native, "_kernel_decode_lz4_batch", lambda *a: calls.append(1) or batches(*a))
    compiled, python = _read_both(monkeypatch, path)
    assert calls and spy.answers and all(spy.answers)
    _same(compiled, python)
    _same(compiled, ev)
