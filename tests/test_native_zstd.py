"""The AEDAT4 reader's compiled range for Zstandard packets (``evtk._native.decode_lz4_range`` with the system's
libzstd, :func:`evtk.io._compression.zstd_addresses`): every batch of a healthy file through it with the events the
Python loop (zstandard) gives; a frame without a stated size, two frames in one body, damaged frames and a missing
library left to the Python loop or read the same, never a different answer."""

from __future__ import annotations

import numpy as np
import pytest
import zstandard
from conftest import random_events
from test_aedat4_batches import _body
from test_hostile import _aedat4
from test_native_batches import _flipped_copies_read_alike, _outcome, _read_both, _same, _Spy

import evtk
from evtk import _native
from evtk.io import _compression as cz

pytestmark = pytest.mark.skipif(not _native.BUILT or not _native.RANGE_ZSTD or not cz._zstd(),
                                reason="evtk._ckernels without Zstandard batches, or no system libzstd")


@pytest.mark.parametrize("threads", ["1", "2"])
def test_every_batch_of_a_healthy_zstd_file_goes_through_the_kernel_with_the_same_events(tmp_path, monkeypatch,
                                                                                        threads):
    monkeypatch.setenv("EVTK_THREADS", threads)
    ev = random_events(300_000, seed=5)
    path = tmp_path / "z.aedat4"
    evtk.write_events(path, ev, compression="zstd")
    spy = _Spy(monkeypatch)
    compiled, python = _read_both(monkeypatch, path)
    assert spy.answers and all(spy.answers) and spy.codecs and set(spy.codecs) == {1}
    _same(compiled, python)
    _same(compiled, ev)


def test_frames_that_state_no_size_are_decoded_by_the_kernel_too(tmp_path, monkeypatch):
    # a streaming compressor's frames: no content size in their headers (dv-processing 2's state one; a writer
    # that streams its packets' bytes would not)
    ev = random_events(60_000, seed=6)
    bodies = [_body(ev[i:i + 5_000], 0) for i in range(0, len(ev), 5_000)]
    frames = [zstandard.ZstdCompressor(write_content_size=False, write_checksum=True).compress(b) for b in bodies]
    assert all(zstandard.frame_content_size(f) == -1 for f in frames)
    path = tmp_path / "nosize.aedat4"
    _aedat4(path, cz.ZSTD, frames)
    spy = _Spy(monkeypatch)
    compiled, python = _read_both(monkeypatch, path)
    assert spy.answers and all(spy.answers)
    _same(compiled, python)
    _same(compiled, ev)


def test_without_the_library_every_batch_goes_to_the_python_loop_and_reads_the_same(tmp_path, monkeypatch):
    ev = random_events(50_000, seed=7)
    path = tmp_path / "z.aedat4"
    evtk.write_events(path, ev, compression="zstd")
    spy = _Spy(monkeypatch)
    monkeypatch.setattr(cz, "_zstd_lib", False)
    compiled, python = _read_both(monkeypatch, path)
    assert not spy.answers
    _same(compiled, ev)
    _same(python, ev)


@pytest.mark.parametrize("sized", [True, False])
def test_two_frames_in_one_body_are_left_to_the_python_loop(tmp_path, monkeypatch, sized):
    # a body of two frames, the first stating its size or not: the kernel takes exactly one frame a body (libzstd
    # would decompress both), so the batch goes to the Python loop, which decides (the same events or the same error
    # either way)
    ev = random_events(20_000, seed=8)
    bodies = [_body(ev[i:i + 5_000], 0) for i in range(0, len(ev), 5_000)]
    frames = [zstandard.ZstdCompressor(write_content_size=sized).compress(b) for b in bodies]
    frames[1] = frames[1] + cz.compress(cz.ZSTD, b"more")
    path = tmp_path / "two.aedat4"
    _aedat4(path, cz.ZSTD, frames)
    spy = _Spy(monkeypatch)
    outcomes = []
    for value in ("1", "0"):
        monkeypatch.setenv("EVTK_NATIVE", value)
        outcomes.append(_outcome(path, False))
    assert False in spy.answers
    assert outcomes[0] == outcomes[1]


def test_damaged_frames_give_the_same_events_or_the_same_error_with_the_kernel_and_without(tmp_path, monkeypatch):
    # bits flipped in the packets' bodies (the frames' headers, blocks and checksums): with salvage and without,
    # the compiled range and the Python loop give the same events, warnings and errors
    source = tmp_path / "z.aedat4"
    evtk.write_events(source, random_events(120_000, seed=9), compression="zstd", packet_events=5_000)
    spy = _Spy(monkeypatch)
    _flipped_copies_read_alike(monkeypatch, source.read_bytes(), tmp_path / "flipped.aedat4", 23)
    assert True in spy.answers and False in spy.answers  # both routes met: intact batches and damaged ones


@pytest.mark.parametrize("change", ["magic", "end", "middle"])
def test_a_frame_the_kernel_declines_is_named_by_the_python_loop(tmp_path, monkeypatch, change):
    # one packet's frame damaged in place (the file's data table intact, so nothing is decompressed when it opens):
    # its magic, its last byte (its checksum), a byte of its blocks; the kernel declines that batch and the Python
    # loop raises the error it raises without the kernel
    path = tmp_path / "bad.aedat4"
    evtk.write_events(path, random_events(40_000, seed=10), compression="zstd", packet_events=5_000)
    with evtk.open(path) as rec:
        off, size = int(rec._index.offset[3]), int(rec._index.size[3])
    data = bytearray(path.read_bytes())
    assert bytes(data[off:off + 4]) == b"\x28\xb5\x2f\xfd"
    data[{"magic": off, "end": off + size - 1, "middle": off + size // 2}[change]] ^= 0x10
    path.write_bytes(bytes(data))
    outcomes = []
    spy = _Spy(monkeypatch)
    for value in ("1", "0"):
        monkeypatch.setenv("EVTK_NATIVE", value)
        outcomes.append(_outcome(path, False))
    assert False in spy.answers
    assert outcomes[0] == outcomes[1] and outcomes[0][0] == "error"


def test_the_raw_kernel_refuses_a_zstd_call_without_its_functions():
    # codec 1 needs libzstd's three functions, a context and ZSTD_getFrameContentSize; codec 2 does not exist
    ev = random_events(10, seed=1)
    n = len(ev)
    cols = (np.zeros(n, np.int64), np.zeros(n, np.uint16), np.zeros(n, np.uint16), np.zeros(n, np.uint8))
    z = np.zeros(1, np.int64)
    args = [0, z, z, z, z, np.zeros(2, np.int64), 0, 0, 1, 0, np.zeros(8, np.uint8), True, 1, 1, 1, 1,
            np.zeros(8, np.uint8), 0, 0, 0, *cols, 320, 240]
    assert _native._kernel_decode_lz4_range(*args) == (0, 0, 0, 0, 0)  # no rows: nothing to do (LZ4, addresses set)
    for codec, size_at in ((1, 0), (2, 1)):
        with pytest.raises(ValueError):
            _native._kernel_decode_lz4_range(*args, codec, size_at)
