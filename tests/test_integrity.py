"""Checksums a file carries are verified by default: a damaged file gives its exact events or a FormatError
naming the file and the byte, never other events; the opt-out reads what the checksums would refuse."""

from __future__ import annotations

import numpy as np
import peers
import pytest
from click.testing import CliRunner
from conftest import random_events

import evtk
from evtk.cli import main
from evtk.io import _compression as cz

pytest.importorskip("faery")


def _frame_structure(body: bytes) -> list[int]:
    """Offsets in an LZ4 frame of its magic, descriptor, block sizes, block checksums, end mark and content
    checksum (the bytes a flip in which changes how the frame is read rather than what it holds)."""
    flg = body[4]
    pos = 4 + 2 + (8 if flg & 0x08 else 0) + (4 if flg & 0x01 else 0) + 1
    marks = list(range(pos))
    block_sum = 4 if flg & 0x10 else 0
    while pos + 4 <= len(body):
        size = int.from_bytes(body[pos:pos + 4], "little")
        marks += range(pos, pos + 4)
        if size == 0:
            marks += range(pos + 4, min(len(body), pos + 8))
            break
        end = pos + 4 + (size & 0x7FFFFFFF)
        marks += range(end, end + block_sum)
        pos = end + block_sum
    return marks


@pytest.fixture(scope="module")
def faery_file(tmp_path_factory):
    """A faery-written LZ4 AEDAT4 file (three packets, block and content checksums), its events, and the
    bytes of its packets and data table."""
    ev = random_events(9000, seed=3, t0=5)
    path = tmp_path_factory.mktemp("integrity") / "faery.aedat4"
    peers.faery_write(path, ev, "lz4")
    with evtk.open(path) as rec:
        idx = rec._index
        offsets, sizes = idx.offset.astype(int), idx.size.astype(int)
        table_at = int(rec._data_table_pos)
    data = path.read_bytes()
    assert table_at == int(offsets[-1] + sizes[-1])  # the data table follows the packets
    return path, ev, data, offsets, sizes, table_at


def _flips(data, offsets, sizes, table_at, sampled=600, seed=0):
    """Bits to flip: every bit of the packet headers, of each frame's structure and of the data table, and
    ``sampled`` more bits drawn from the rest of the packets."""
    structural = set()
    for off, size in zip(offsets, sizes):
        structural.update(range(off - 8, off))  # the packet header: stream id, body size
        structural.update(off + m for m in _frame_structure(data[off:off + size]))
    structural.update(range(table_at, len(data)))
    bits = [8 * b + k for b in sorted(structural) for k in range(8)]
    rest = np.setdiff1d(np.arange(8 * int(offsets[0] - 8), 8 * table_at), bits)
    rng = np.random.default_rng(seed)
    return bits + sorted(rng.choice(rest, sampled, replace=False).tolist())


def _read(path, verify=None):
    """The events read from ``path``, or the FormatError that refused it."""
    try:
        with evtk.open(path, verify_checksums=verify) as rec:
            return rec.events()
    except evtk.FormatError as exc:
        return exc


def test_no_bit_flip_gives_other_events(faery_file, tmp_path):
    """Every bit of the frames' structure, packet headers and data table, and 600 sampled bits of the frames'
    contents: each flipped alone, a read gives the exact events or a FormatError naming the file and a byte
    offset. Unchecked (the old default) some of the same flips give other events, silently."""
    path, ev, data, offsets, sizes, table_at = faery_file
    bad = tmp_path / "flipped.aedat4"
    refused = silent_unchecked = 0
    for bit in _flips(data, offsets, sizes, table_at):
        flipped = bytearray(data)
        flipped[bit // 8] ^= 1 << (bit % 8)
        bad.write_bytes(flipped)
        got = _read(bad)
        if isinstance(got, evtk.FormatError):
            assert got.path == str(bad) and got.offset is not None, (bit, got)
            assert 0 <= got.offset < len(data), (bit, got)
            refused += 1
        else:
            assert got == ev, f"flipping bit {bit % 8} of byte {bit // 8} gave other events"
        unchecked = _read(bad, verify=False)
        silent_unchecked += isinstance(unchecked, evtk.Events) and not unchecked == ev
    assert refused > 600
    assert silent_unchecked > 100  # what checking by default catches


def _flip_content(data, offsets, sizes):
    """``data`` with one bit flipped inside the first packet's first block, the first such flip past its
    start that still decodes unchecked, to other bytes."""
    off, size = int(offsets[0]), int(sizes[0])
    body = data[off:off + size]
    good = cz.decompress(cz.LZ4, body, 1 << 24)
    for at in range(200, size):
        bad = bytearray(body)
        bad[at] ^= 0x10
        try:
            if cz.decompress(cz.LZ4, bytes(bad), 1 << 24, verify=False) != good:
                return data[:off + at] + bytes([bad[at]]) + data[off + at + 1:]
        except cz.CodecError:
            continue
    raise AssertionError("no flip decodes")


def _flip_content_checksum(data, offsets, sizes):
    """``data`` with one bit flipped in the first packet's content checksum (its events are intact)."""
    flipped = bytearray(data)
    flipped[int(offsets[0] + sizes[0]) - 1] ^= 0x01
    return bytes(flipped)


@pytest.mark.parametrize("damage", [_flip_content, _flip_content_checksum])
def test_cli_refuses_flipped_file_unless_opted_out(faery_file, tmp_path, damage):
    """`evtk info --check` and `evtk convert` exit 1 with one line naming the file, byte and checksum;
    --no-verify-checksums and EVTK_VERIFY_CHECKSUMS=0 read the file (exact events when only a checksum
    was hit)."""
    path, ev, data, offsets, sizes, _ = faery_file
    bad = tmp_path / "bad.aedat4"
    bad.write_bytes(damage(data, offsets, sizes))
    out = tmp_path / "out.h5"
    run = CliRunner().invoke
    for args in (["info", "--check", str(bad)], ["convert", str(bad), str(out)]):
        res = run(main, args)
        assert res.exit_code == 1, res.output
        assert f"{bad} at byte {int(offsets[0])}" in res.output and "checksum" in res.output, res.output
        assert res.output.count("\n") == 1 and "Traceback" not in res.output
        res = run(main, ["--verify-checksums", *args])
        assert res.exit_code == 1, res.output
    assert not out.exists()
    res = run(main, ["--no-verify-checksums", "convert", str(bad), str(out)])
    assert res.exit_code == 0, res.output
    res = run(main, ["info", "--check", str(bad)], env={"EVTK_VERIFY_CHECKSUMS": "0"})
    assert res.exit_code == 0, res.output
    if damage is _flip_content_checksum:
        assert evtk.read_events(out) == ev
    else:
        assert evtk.read_events(out) != ev  # what the opt-out risks


def test_zstd_content_checksum_verified():
    """A Zstandard frame that carries a content checksum (no AEDAT4 writer known here writes one) is
    refused when its checksum does not match, checked or not: zstandard always verifies it."""
    import zstandard

    raw = np.random.default_rng(1).integers(0, 8, 100_000, np.uint8).tobytes()
    frame = bytearray(zstandard.ZstdCompressor(write_checksum=True).compress(raw))
    assert cz.decompress(cz.ZSTD, bytes(frame), 1 << 20) == raw
    frame[-1] ^= 0x01
    for verify in (True, False):
        with pytest.raises(cz.CodecError, match="content checksum"):
            cz.decompress(cz.ZSTD, bytes(frame), 1 << 20, verify=verify)
    streamed = bytearray(zstandard.ZstdCompressor(write_checksum=True, write_content_size=False).compress(raw))
    streamed[-2] ^= 0x01
    with pytest.raises(cz.CodecError, match="content checksum"):
        cz.decompress(cz.ZSTD, bytes(streamed), 1 << 20)


def test_lz4_checksums_named():
    """Each of an LZ4 frame's three checksums, damaged, is named in the error (header, block, content)."""
    import lz4.frame

    raw = np.random.default_rng(2).integers(0, 8, 200_000, np.uint8).tobytes()
    frame = lz4.frame.compress(raw, block_checksum=True, content_checksum=True, store_size=False,
                               block_size=lz4.frame.BLOCKSIZE_MAX64KB)
    marks = _frame_structure(frame)
    header_check = 6
    first_size = int.from_bytes(frame[7:11], "little") & 0x7FFFFFFF
    block_check = 11 + first_size
    assert block_check in marks and frame[-4:] != b"\0\0\0\0"
    for at, what in ((header_check, "header"), (block_check, "block"), (len(frame) - 1, "content")):
        bad = bytearray(frame)
        bad[at] ^= 0x04
        with pytest.raises(cz.CodecError, match=f"{what} checksum"):
            cz.decompress(cz.LZ4, bytes(bad), 1 << 20)
        if what != "header":  # unchecked, the frame is read (the descriptor's own check byte is rewritten)
            assert cz.decompress(cz.LZ4, bytes(bad), 1 << 20, verify=False) == raw


def _flip_inside(path, data_at, bit=0x01):
    """Flip one bit of ``path`` at byte ``data_at``."""
    data = bytearray(path.read_bytes())
    data[data_at] ^= bit
    path.write_bytes(bytes(data))


def test_parquet_page_checksums_verified(tmp_path):
    """A Parquet file whose data pages carry CRC-32s (pyarrow's write_page_checksum) is refused when one
    fails, as a FormatError naming the file and row group; verify_checksums=False reads it unchecked."""
    pa = pytest.importorskip("pyarrow")
    pq = pytest.importorskip("pyarrow.parquet")
    ev = random_events(50_000, seed=4)
    table = pa.table({"t": ev.t, "x": ev.x, "y": ev.y, "p": ev.p})
    path = tmp_path / "crc.parquet"
    pq.write_table(table, path, write_page_checksum=True, compression="none", use_dictionary=False)
    assert evtk.open(path, sensor_size=(320, 240)).events() == ev
    _flip_inside(path, 4 + 8 * 20_000 + 3)  # inside the t column's page (time stamp 20,000's third byte)
    with pytest.raises(evtk.FormatError, match="row group 0") as err:
        evtk.open(path, sensor_size=(320, 240)).events()
    assert err.value.path == str(path) and "CRC" in str(err.value)
    got = evtk.open(path, sensor_size=(320, 240), verify_checksums=False).events()
    assert not got == ev


def test_hdf5_fletcher32_verified(tmp_path):
    """An HDF5 event file written with the Fletcher-32 filter is refused when a chunk fails it."""
    h5py = pytest.importorskip("h5py")
    ev = random_events(20_000, seed=5)
    path = tmp_path / "f32.h5"
    evtk.write_events(path, ev)
    with h5py.File(path, "r") as f:
        root, attrs = dict(f.attrs), dict(f["events"].attrs)
    with h5py.File(path, "w") as f:
        f.attrs.update(root)
        g = f.create_group("events")
        g.attrs.update(attrs)
        for name in ("t", "x", "y", "p"):
            g.create_dataset(name, data=getattr(ev, name), chunks=(4096,), fletcher32=True)
        at = g["t"].id.get_chunk_info(0).byte_offset
    assert evtk.read_events(path) == ev
    _flip_inside(path, at + 100)
    with pytest.raises(evtk.FormatError) as err:
        evtk.read_events(path)
    assert err.value.path == str(path)
