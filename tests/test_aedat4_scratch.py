"""Packet bodies read and decompressed into buffers reused from packet to packet (issue 32): a read returns
exactly what reading every packet into fresh memory returns, whatever the order of packet sizes."""

from __future__ import annotations

import lz4.frame
import numpy as np
import pytest
from conftest import random_events
from test_hostile import _aedat4, _event_body

import evtk
from evtk.io import _compression as cz

# large before small, so a reused buffer holds a larger packet's bytes when a smaller one lands in it
SIZES = (20_000, 3, 7_000, 1, 0, 12_000, 2, 20_001, 5)


def _frames(code, bodies, sized):
    """Each body compressed as ``code``; LZ4 frames with or without their content size (dv-processing writes
    none) and, every other one, with block and content checksums (as faery writes them)."""
    if code == cz.NONE:
        return list(bodies)
    if code == cz.ZSTD:
        return [cz.compress(cz.ZSTD, b) for b in bodies]
    return [lz4.frame.compress(b, store_size=sized, block_size=lz4.frame.BLOCKSIZE_MAX64KB,
                               content_checksum=bool(k % 2), block_checksum=bool(k % 2))
            for k, b in enumerate(bodies)]


def _packets(seed):
    evs = [random_events(n, seed=seed + k) for k, n in enumerate(SIZES)]
    return evs, [_event_body(ev) for ev in evs]


def _fresh(rec):
    """The events read with every packet in a new buffer (the reader's path before buffers were reused)."""
    body = rec._body
    rec._body = lambda i, *scratch: body(i)
    try:
        return rec.events()
    finally:
        del rec._body


@pytest.mark.parametrize("code,sized", [(cz.NONE, True), (cz.LZ4, True), (cz.LZ4, False), (cz.ZSTD, True)])
@pytest.mark.parametrize("threads,into_min", [("1", cz.INTO_MIN_BYTES), ("2", cz.INTO_MIN_BYTES), ("2", 0)])
def test_reused_buffers_read_what_fresh_buffers_read(tmp_path, monkeypatch, code, sized, threads, into_min):
    """(``into_min`` 0: every LZ4 body, the smallest included, decompressed into the reused buffer.)"""
    monkeypatch.setenv("EVTK_THREADS", threads)
    monkeypatch.setattr(cz, "INTO_MIN_BYTES", into_min)
    evs, bodies = _packets(seed=40)
    path = tmp_path / "sizes.aedat4"
    _aedat4(path, code, _frames(code, bodies, sized))
    expected = evtk.Events.concatenate(evs)
    with evtk.open(path) as rec:
        got = rec.events()
        assert got == expected
        assert _fresh(rec) == expected
        assert evtk.Events.concatenate(list(rec.iter_events(chunk_events=4_000))) == expected
        # packet by packet through one scratch: each body exactly as decompressed alone
        scratch = cz.Scratch()
        for i, raw in enumerate(bodies):
            assert rec._body(i, scratch).tobytes() == raw


@pytest.mark.parametrize("sized", [True, False])
def test_decompress_into_one_scratch_matches_lz4_frame_by_frame(sized, monkeypatch):
    """Small after large, empty, checksummed, high compression: each frame's bytes, no more and no fewer,
    and a damaged frame in between neither stops nor spoils the next (the context is reset)."""
    monkeypatch.setattr(cz, "INTO_MIN_BYTES", 0)
    rng = np.random.default_rng(7)
    raws = [rng.integers(0, 4, n, dtype=np.uint8).tobytes() for n in (300_000, 10, 0, 150_000, 64 << 10, 1)]
    scratch = cz.Scratch()
    for k, raw in enumerate(raws):
        frame = lz4.frame.compress(raw, store_size=sized, compression_level=9 * (k % 2),
                                   content_checksum=bool(k % 2), block_checksum=bool(k % 3 == 0))
        for verify in (True, False):  # False: a checksummed frame is rebuilt without them (read-only bytes)
            got = cz.decompress_into(cz.LZ4, frame, cz.output_limit(len(frame)), verify, scratch)
            assert got.tobytes() == raw == cz.decompress(cz.LZ4, frame, cz.output_limit(len(frame)), verify)
        bad = bytearray(frame)
        bad[len(bad) // 2] ^= 0x55
        cut = frame[: len(frame) - 6]
        for damaged in (bytes(bad), cut):
            try:
                cz.decompress(cz.LZ4, damaged, cz.output_limit(len(damaged)))
            except cz.CodecError as exc:
                with pytest.raises(cz.CodecError) as caught:
                    cz.decompress_into(cz.LZ4, damaged, cz.output_limit(len(damaged)), True, scratch)
                assert str(caught.value) == str(exc)


def test_decompress_into_keeps_the_bounds(monkeypatch):
    """A frame without a size that inflates past the limit is refused (as decompress refuses it), one that
    states more than the limit is refused before decoding, and a frame holding more than it states fails."""
    monkeypatch.setattr(cz, "INTO_MIN_BYTES", 0)
    scratch = cz.Scratch()
    bomb = lz4.frame.compress(bytes(64 << 20), store_size=False)
    with pytest.raises(cz.CodecError, match="more than"):
        cz.decompress_into(cz.LZ4, bomb, cz.output_limit(len(bomb)), True, scratch)
    assert len(scratch._out) <= cz.output_limit(len(bomb)) + 1
    sized = lz4.frame.compress(bytes(1 << 20))
    with pytest.raises(cz.CodecError, match="announces"):
        cz.decompress_into(cz.LZ4, sized, 1000, True, scratch)
    raw = bytes(range(256)) * 64
    liar = bytearray(lz4.frame.compress(raw, content_checksum=False))
    liar[6:14] = (len(raw) // 2).to_bytes(8, "little")  # the stated size halved, the check byte redone
    liar = bytearray(cz.lz4_without_checksums(bytes(liar)))  # (the descriptor's check byte recomputed)
    with pytest.raises(cz.CodecError):
        cz.decompress(cz.LZ4, bytes(liar), 1 << 20)
    with pytest.raises(cz.CodecError):
        cz.decompress_into(cz.LZ4, bytes(liar), 1 << 20, True, scratch)


def test_without_the_lz4_library_the_read_falls_back_to_python_lz4(tmp_path, monkeypatch):
    """Where python-lz4's LZ4 frame functions cannot be reached (another build), decompress_into is
    decompress: the same events, a new buffer per packet."""
    evs, bodies = _packets(seed=60)
    path = tmp_path / "fallback.aedat4"
    _aedat4(path, cz.LZ4, _frames(cz.LZ4, bodies, False))
    monkeypatch.setattr(cz, "_lz4f_lib", False)
    with evtk.open(path) as rec:
        assert rec.events() == evtk.Events.concatenate(evs)
    frame = lz4.frame.compress(bodies[0])
    assert len(frame) >= cz.INTO_MIN_BYTES
    scratch = cz.Scratch()
    got = cz.decompress_into(cz.LZ4, frame, cz.output_limit(len(frame)), True, scratch)
    assert got.tobytes() == bodies[0] and len(scratch._out) == 0


def test_lz4_into_at_gives_decompress_intos_bytes_or_hands_the_frame_back():
    """The batches' LZ4 call (one LZ4F_decompress for a whole frame, steps otherwise) writes exactly what
    decompress_into returns, or returns -1 for decompress_into to name the fault: over frames with and without
    a content size, with checksums (checked, or left to decompress_into when not verified), cut, damaged,
    with bytes after them, and with too little room."""
    import lz4.frame

    rng = np.random.default_rng(11)
    data = [bytes(rng.integers(0, 4, n, dtype=np.uint8)) for n in (0, 1, 100, 70_000, 300_000)]
    cases = []
    for raw in data:
        for sized in (False, True):
            for summed in (False, True):
                frame = lz4.frame.compress(raw, store_size=sized, content_checksum=summed, block_checksum=summed,
                                           block_size=lz4.frame.BLOCKSIZE_MAX64KB)
                cases += [(raw, frame, len(raw) + 64), (raw, frame, max(0, len(raw) - 1)),  # room short by one
                          (raw, frame[:-3], len(raw) + 64), (raw, frame + b"tail", len(raw) + 64)]
                bad = bytearray(frame)
                bad[len(bad) // 2] ^= 0x5A  # (unchecked, it may decode to other bytes: decompress_into's too)
                cases.append((None, bytes(bad), len(raw) + 64))
    cases.append((b"", lz4.frame.compress(b"")[:5], 64))  # too short for its descriptor
    whole = 0
    for raw, frame, room in cases:
        for verify in (True, False):
            src = np.frombuffer(frame, np.uint8).copy()
            out = np.full(room + 16, 0xEE, np.uint8)
            scratch = cz.Scratch()
            n = cz.lz4_into_at(src, src.ctypes.data, cz.output_limit(len(frame)), verify, scratch, out.ctypes.data,
                               room)
            try:
                want = bytes(cz.decompress_into(cz.LZ4, memoryview(src), cz.output_limit(len(frame)), verify,
                                                cz.Scratch()))
            except cz.CodecError:
                want = None
            if n < 0:
                continue
            assert want is not None and bytes(out[:n]) == want and n <= room and out[room] == 0xEE
            if raw is not None:
                whole += 1
                assert want == raw
    # every intact frame with room for it read in the quick call (checksummed ones when verified)
    assert whole >= 2 * len(data) * 2 * 2 - len(data), whole
