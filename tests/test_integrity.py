"""Checksums a file carries are verified by default: a damaged file gives its exact events or a FormatError
naming the file and the byte, never other events; the opt-out reads what the checksums would refuse."""

from __future__ import annotations

import os

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


# -- reconstruction files: the HDF5 policy and the memory budget ---------------------------------------------

def _reconstruction(n=3, size=8, windows=3):
    """A small, valid reconstruction (hand-made: no recording needed)."""
    from evtk.reconstruct import Reconstruction, WindowCounts, Windows

    rng = np.random.default_rng(7)
    responses = rng.normal(size=(n, size, size))
    counts = WindowCounts(rng.integers(0, 5, (windows, 4, 4)).astype(np.int32),
                          rng.integers(0, 5, (windows, 4, 4)).astype(np.int32),
                          Windows(np.arange(windows) * 100, np.arange(windows) * 100 + 50, np.arange(windows), "period"),
                          (0, 4, 0, 4), 10)
    return Reconstruction(responses, np.where(responses > 0, 1, -1).astype(np.int8), None,
                          rng.normal(size=(n, 3, 3)), None, counts, {"window_source": "period"})


@pytest.fixture
def recon_h5(tmp_path):
    """A valid reconstruction in evtk HDF5 (its path)."""
    from evtk.io.reconstruction import save_reconstruction

    path = tmp_path / "recon.h5"
    save_reconstruction(path, _reconstruction(), (32, 32))
    return path


def _replace(path, name, make):
    """Replace ``/reconstruction/name`` in ``path`` by what ``make(group, name, data)`` creates."""
    import h5py

    with h5py.File(path, "a") as f:
        g = f["reconstruction"]
        data = g[name][()] if name in g else None
        if data is not None:
            del g[name]
        make(g, name, data)


def _cli(*args, env=None):
    return CliRunner().invoke(main, list(map(str, args)), env=env)


def test_reconstruction_external_link_refused(recon_h5, tmp_path):
    """/reconstruction/responses as an external link to another file's dataset: info, enob and
    load_reconstruction refuse it without --trust-external (before: the other file's bytes came back)."""
    import h5py

    from evtk.reconstruct import load_reconstruction

    other = tmp_path / "secret.h5"
    with h5py.File(other, "w") as f:
        f["data"] = np.full((3, 8, 8), 42.0)
    _replace(recon_h5, "responses", lambda g, n, d: g.__setitem__(n, h5py.ExternalLink(str(other), "/data")))
    with pytest.raises(evtk.FormatError, match="external link"):
        load_reconstruction(recon_h5)
    for args in (["info", recon_h5], ["enob", recon_h5]):
        res = _cli(*args)
        assert res.exit_code == 1 and "external link" in res.output and res.output.count("\n") == 1, res.output
    assert load_reconstruction(recon_h5, trust_external=True).responses[0, 0, 0] == 42.0
    assert _cli("--trust-external", "info", recon_h5).exit_code == 0


def test_reconstruction_group_as_external_link_refused(recon_h5, tmp_path):
    """The whole /reconstruction group an external link: refused, not followed."""
    import h5py

    from evtk.reconstruct import load_reconstruction

    other = tmp_path / "other.h5"
    with h5py.File(recon_h5, "r") as src, h5py.File(other, "w") as dst:
        src.copy("reconstruction", dst)
    with h5py.File(recon_h5, "a") as f:
        del f["reconstruction"]
        f["reconstruction"] = h5py.ExternalLink(str(other), "/reconstruction")
    with pytest.raises(evtk.FormatError, match="external link"):
        load_reconstruction(recon_h5)
    res = _cli("info", recon_h5)
    assert res.exit_code == 1 and "external link" in res.output, res.output


def test_reconstruction_external_storage_refused(recon_h5, tmp_path):
    """A dataset whose bytes live in a raw file beside it: refused unless trusted."""
    from evtk.reconstruct import load_reconstruction

    raw = tmp_path / "raw.bin"
    raw.write_bytes(np.full((3, 8, 8), 7.0).tobytes())

    def external(g, name, data):
        g.create_dataset(name, shape=data.shape, dtype=data.dtype, external=[(str(raw), 0, raw.stat().st_size)])

    _replace(recon_h5, "responses", external)
    with pytest.raises(evtk.FormatError, match="external file"):
        load_reconstruction(recon_h5)
    res = _cli("enob", recon_h5)
    assert res.exit_code == 1 and "external file" in res.output, res.output
    assert load_reconstruction(recon_h5, trust_external=True).responses[1, 2, 3] == 7.0


def test_reconstruction_virtual_dataset_refused(recon_h5, tmp_path):
    import h5py

    from evtk.reconstruct import load_reconstruction

    other = tmp_path / "src.h5"
    with h5py.File(other, "w") as f:
        f["data"] = np.ones((3, 8, 8))

    def virtual(g, name, data):
        layout = h5py.VirtualLayout(shape=data.shape, dtype=data.dtype)
        layout[:] = h5py.VirtualSource(str(other), "data", shape=data.shape)
        g.create_virtual_dataset(name, layout)

    _replace(recon_h5, "responses", virtual)
    with pytest.raises(evtk.FormatError, match="virtual dataset"):
        load_reconstruction(recon_h5)


def test_reconstruction_hdf5_bomb_refused(recon_h5, monkeypatch):
    """A few-KB file whose gzip chunks of zeros declare gigabytes: refused from the declared shape, before
    anything is allocated (before: 3.7-4.8 GB)."""
    import tracemalloc

    from evtk.reconstruct import load_reconstruction

    def bomb(g, name, data):  # 2 GiB of float64 zeros, in 16 MiB chunks of which only one is written
        ds = g.create_dataset(name, shape=(4096, 256, 256), dtype=np.float64, chunks=(32, 256, 256),
                              compression="gzip", fillvalue=0.0)
        ds[0] = 0.0

    _replace(recon_h5, "responses", bomb)
    _replace(recon_h5, "binary", bomb)
    assert recon_h5.stat().st_size < 200_000
    tracemalloc.start()
    with pytest.raises((evtk.FormatError, evtk.EvtkError), match="claims|chunks|memory|allowed|written"):
        load_reconstruction(recon_h5)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 64 << 20
    res = _cli("info", recon_h5)
    assert res.exit_code == 1 and res.output.count("\n") == 1, res.output


def test_reconstruction_hdf5_over_the_memory_budget(recon_h5):
    """Arrays that the file does hold but that need more than --memory-limit-mb: refused before reading."""
    from evtk.reconstruct import load_reconstruction

    def big(g, name, data):  # 24 MiB of random float64 (incompressible), stored
        g.create_dataset(name, data=np.random.default_rng(0).normal(size=(3, 1024, 1024)))

    _replace(recon_h5, "responses", big)
    res = _cli("--memory-limit-mb", "16", "info", recon_h5)
    assert res.exit_code == 1 and "memory-limit-mb" in res.output, res.output
    with pytest.raises(evtk.FormatError, match="binary and responses differ"):
        load_reconstruction(recon_h5)  # within the default budget: read, and its shapes then refused


def test_reconstruction_non_numeric_dataset_refused(recon_h5):
    import h5py

    from evtk.reconstruct import load_reconstruction

    def strings(g, name, data):
        g.create_dataset(name, data=np.array([b"a", b"b", b"c"], dtype=h5py.string_dtype()))

    _replace(recon_h5, "pairs", strings)
    with pytest.raises(evtk.FormatError, match="pairs has dtype"):
        load_reconstruction(recon_h5)


def _npz_members(path):
    import zipfile

    with zipfile.ZipFile(path) as z:
        return {i.filename: z.read(i) for i in z.infolist()}


def test_npz_bomb_refused(tmp_path):
    """A zero-filled NPZ of a few MB declaring gigabytes is refused from its members' declared sizes
    (before: 2.8 MB became 3.8 GB); a header that claims more than its member holds likewise."""
    import tracemalloc
    import zipfile

    from evtk.reconstruct import load_reconstruction, save_reconstruction

    good = tmp_path / "good.npz"
    save_reconstruction(good, _reconstruction(), (32, 32))
    members = _npz_members(good)
    bomb = tmp_path / "bomb.npz"
    header = {"descr": "<f8", "fortran_order": False, "shape": (64, 1024, 1024)}  # 512 MiB of zeros
    with zipfile.ZipFile(bomb, "w", zipfile.ZIP_DEFLATED) as z:
        for name, data in members.items():
            if name != "responses.npy":
                z.writestr(name, data)
        with z.open("responses.npy", "w", force_zip64=True) as f:
            np.lib.format.write_array_header_1_0(f, header)
            chunk = bytes(1 << 24)
            for _ in range(32):
                f.write(chunk)
    assert bomb.stat().st_size < 1_000_000
    tracemalloc.start()
    with pytest.raises(evtk.FormatError, match="claim"):
        load_reconstruction(bomb)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 64 << 20
    res = _cli("enob", bomb)
    assert res.exit_code == 1 and "claim" in res.output, res.output

    liar = tmp_path / "liar.npz"  # a header claiming 1 GiB in a member of a few hundred bytes
    with zipfile.ZipFile(liar, "w", zipfile.ZIP_DEFLATED) as z:
        for name, data in members.items():
            if name == "responses.npy":
                buf = __import__("io").BytesIO()
                np.lib.format.write_array_header_1_0(buf, {**header, "shape": (128, 1024, 1024)})
                data = buf.getvalue() + data[-3 * 8 * 8 * 8:]
            z.writestr(name, data)
    tracemalloc.start()
    with pytest.raises(evtk.FormatError, match="header gives"):
        load_reconstruction(liar)
    assert tracemalloc.get_traced_memory()[1] < 64 << 20
    tracemalloc.stop()


def test_npz_object_array_refused(tmp_path):
    """An NPZ member holding Python objects (a pickle) is refused from its header, never unpickled."""
    import zipfile

    from evtk.reconstruct import load_reconstruction, save_reconstruction

    good = tmp_path / "good.npz"
    save_reconstruction(good, _reconstruction(), (32, 32))
    members = _npz_members(good)
    buf = __import__("io").BytesIO()
    np.save(buf, np.array([1, "x"], dtype=object), allow_pickle=True)
    members["pairs.npy"] = buf.getvalue()
    bad = tmp_path / "objects.npz"
    with zipfile.ZipFile(bad, "w") as z:
        for name, data in members.items():
            z.writestr(name, data)
    with pytest.raises(evtk.FormatError, match="Python objects"):
        load_reconstruction(bad)


def test_recording_with_reconstruction_group_is_a_recording(tmp_path):
    """A recording that also holds /reconstruction: every command reads its events (info and enob too, where
    they used to measure the group), info says so in a warning, and load_reconstruction reads the group
    when asked by name."""
    import h5py

    from evtk.io.reconstruction import is_reconstruction
    from evtk.reconstruct import load_reconstruction, save_reconstruction

    ev = random_events(5000, seed=8, sensor_size=(32, 32))
    rec = tmp_path / "both.h5"
    evtk.write_events(rec, ev)
    recon = tmp_path / "recon.h5"
    save_reconstruction(recon, _reconstruction(), (32, 32))
    with h5py.File(recon, "r") as src, h5py.File(rec, "a") as dst:
        src.copy("reconstruction", dst)
    assert is_reconstruction(recon) and not is_reconstruction(rec)
    res = _cli("info", rec)
    assert res.exit_code == 0 and "events       5,000" in res.output, res.output
    assert "warning: the file also holds a /reconstruction group" in res.output
    assert "load_reconstruction" in res.output
    res = _cli("enob", rec, "--window", "period:100000", "--json")
    assert res.exit_code == 0, res.output
    assert load_reconstruction(rec).responses.shape == (3, 8, 8)


# -- external storage, when trusted: regular files holding what the dataset declares ---------------------------

def _external_t(path, target, offset=0, size=None, n=4, columns="t"):
    """An evtk HDF5 file of ``n`` events whose ``columns`` live in ``target`` (segment at ``offset`` of
    ``size`` bytes; None: to the end of the file), the others zeros in the file."""
    import h5py

    with h5py.File(path, "w") as f:
        f.attrs["evtk_format"] = np.bytes_("evtk.events")
        f.attrs["sensor_size"] = np.array([320, 240])
        g = f.create_group("events")
        for name, dt in (("t", np.int64), ("x", np.uint16), ("y", np.uint16), ("p", np.uint8)):
            if name in columns:
                g.create_dataset(name, shape=(n,), dtype=dt,
                                 external=[(str(target), offset, h5py.h5f.UNLIMITED if size is None else size)])
            else:
                g.create_dataset(name, data=np.zeros(n, dt))


@pytest.mark.parametrize("device", ["/dev/zero", "link"])
def test_trusted_external_storage_on_a_device_refused(tmp_path, device):
    """External storage on /dev/zero (or a link to it) is refused even when trusted: a device is no file
    of data, and one declared unlimited never ends (before: 4 zeros read, or 2**34 events read forever)."""
    if not os.path.exists("/dev/zero"):
        pytest.skip("no /dev/zero")
    target = "/dev/zero"
    if device == "link":
        target = tmp_path / "zeros"
        os.symlink("/dev/zero", target)
    for n in (4, 2**34):
        path = tmp_path / f"dev{n}.h5"
        _external_t(path, target, n=n, columns="txyp")
        with pytest.raises(evtk.FormatError, match="not a regular file"):
            evtk.open(path, trust_external=True).events()
        res = _cli("--trust-external", "info", "--check", path)
        assert res.exit_code == 1 and "not a regular file" in res.output, res.output


def test_trusted_external_storage_shorter_than_declared_refused(tmp_path):
    """A trusted external file that ends before the bytes the dataset reads from it: refused, naming the
    file and the sizes; one that holds them (longer is fine: only the segment is read) reads."""
    raw = tmp_path / "t.bin"
    raw.write_bytes(np.arange(2, dtype=np.int64).tobytes())  # 16 bytes for 4 time stamps (32)
    short = tmp_path / "short.h5"
    _external_t(short, raw, size=32)
    with pytest.raises(evtk.FormatError, match="reads 32 bytes at byte 0 of external file .*t.bin, which holds 16"):
        evtk.open(short, trust_external=True).events()
    unlimited = tmp_path / "unlimited.h5"
    _external_t(unlimited, raw, offset=8)
    with pytest.raises(evtk.FormatError, match="which holds 16"):
        evtk.open(unlimited, trust_external=True).events()
    raw.write_bytes(np.arange(4, dtype=np.int64).tobytes() + b"more bytes the segment leaves out")
    with evtk.open(short, trust_external=True) as rec:
        assert rec.events().t.tolist() == [0, 1, 2, 3]


@pytest.mark.parametrize("key, value, match", [
    ("on", lambda a: a.astype(np.int64) + 2**40, "on holds values outside"),
    ("off", lambda a: a.astype(np.float64) + 0.5, "off must hold integers"),
    ("binary", lambda a: a.astype(np.int16) * 300, "binary holds values outside"),
    # window times cast to int64 silently (fuzz campaign, 2026-11-26: NaN and fractions from a float column)
    ("window_end_us", lambda a: a.astype(np.float64) + 0.5, "window_end_us must hold whole microseconds"),
    ("window_start_us", lambda a: a.astype(np.uint64) + np.uint64(2**63), "beyond int64 microseconds"),
])
def test_reconstruction_values_that_would_wrap_refused(tmp_path, key, value, match):
    """Counts beyond int32 and binary values beyond int8 would wrap silently when converted: refused."""
    from evtk.reconstruct import load_reconstruction, save_reconstruction

    good = tmp_path / "good.npz"
    save_reconstruction(good, _reconstruction(), (32, 32))
    arrays = dict(np.load(good))
    arrays[key] = value(arrays[key])
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(evtk.FormatError, match=match):
        load_reconstruction(tmp_path / "bad.npz")


def test_reconstruction_summary_region_not_integers_refused(tmp_path):
    import json

    from evtk.io.reconstruction import save_reconstruction

    good = tmp_path / "good.npz"
    save_reconstruction(good, _reconstruction(), (32, 32))
    arrays = dict(np.load(good))
    summary = json.loads(str(arrays["summary"]))
    for region in (["a", "b", 0, 1], [0, 1]):
        summary["reconstruction"]["region"] = region
        arrays["summary"] = np.array(json.dumps(summary))
        np.savez(tmp_path / "bad.npz", **arrays)
        res = _cli("info", tmp_path / "bad.npz")
        assert res.exit_code == 1 and "region" in res.output and res.output.count("\n") == 1, res.output
