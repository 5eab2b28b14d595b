"""Hostile files and careless hands (issue 19): each case as an attacker or an unlucky user would make it.

Every test builds the bad input itself and checks the one thing that must hold: a clear evtk error naming
what and where, or the exact events, never another file's bytes, a huge allocation, a traceback or a
silently short read.
"""

import json
import os
import struct
import subprocess
import sys
import textwrap

import h5py
import numpy as np
import pytest
from click.testing import CliRunner
from conftest import random_events

import evtk
from evtk.cli import main
from evtk.io import _compression as cz
from evtk.io import _fb
from evtk.io import aedat4 as a4

SECRET = b"TOP-SECRET-" * 100


def _evtk_h5(path, make_t):
    """An evtk-layout HDF5 file whose /events/t is made by ``make_t(group)``; x, y, p hold 4 events."""
    with h5py.File(path, "w") as f:
        f.attrs["evtk_format"] = np.bytes_("evtk.events")
        f.attrs["sensor_size"] = np.array([320, 240])
        g = f.create_group("events")
        make_t(g)
        for name, dt in (("x", np.uint16), ("y", np.uint16), ("p", np.uint8)):
            g.create_dataset(name, data=np.zeros(4, dt))


def _cli(*args):
    r = CliRunner().invoke(main, list(map(str, args)))
    return r.exit_code, r.output


# -- HDF5 files that reach outside themselves -----------------------------------------------------------------


@pytest.fixture
def secret(tmp_path):
    p = tmp_path / "secret.bin"
    p.write_bytes(np.arange(4, dtype=np.int64).tobytes() + SECRET)  # read as time stamps 0..3 when trusted
    return p


def _external_link(path, secret_h5):
    with h5py.File(secret_h5, "w") as f:
        f.create_dataset("data", data=np.arange(4, dtype=np.int64))
    _evtk_h5(path, lambda g: g.__setitem__("t", h5py.ExternalLink(str(secret_h5), "/data")))


def _external_storage(path, secret):
    _evtk_h5(path, lambda g: g.create_dataset("t", shape=(4,), dtype=np.int64, external=[(str(secret), 0, 32)]))


def _virtual(path, source, missing=False):
    with h5py.File(source, "w") as f:
        f.create_dataset("data", data=np.arange(4, dtype=np.int64))
    layout = h5py.VirtualLayout(shape=(4,), dtype=np.int64)
    layout[:] = h5py.VirtualSource(str(source), "data", shape=(4,))
    _evtk_h5(path, lambda g: g.create_virtual_dataset("t", layout, fillvalue=0))
    if missing:
        os.unlink(source)


@pytest.mark.parametrize("kind", ["external link", "external storage", "virtual dataset"])
def test_hdf5_that_reads_other_files_is_refused_unless_trusted(tmp_path, secret, kind):
    path = tmp_path / "evil.h5"
    target = tmp_path / "other.h5"
    if kind == "external link":
        _external_link(path, target)
        named = "external link to .*other.h5"
    elif kind == "external storage":
        _external_storage(path, secret)
        named = "external file.*secret.bin"
    else:
        _virtual(path, target)
        named = "virtual dataset reading .*other.h5"
    with pytest.raises(evtk.FormatError, match=f"/events/t .*{named}.*trust"):
        evtk.open(path).events()
    # convert copies nothing and says why on one line
    code, out = _cli("convert", path, tmp_path / "out.parquet")
    assert code == 1 and "trust" in out and len(out.strip().splitlines()) == 1
    assert not (tmp_path / "out.parquet").exists()
    # with the user's explicit trust it reads what the link points at
    with evtk.open(path, trust_external=True) as rec:
        got = rec.events()
    assert np.array_equal(got.t, np.arange(4))
    code, _ = _cli("--trust-external", "info", path)
    assert code == 0


def test_virtual_dataset_whose_source_is_missing_never_reads_as_fill_values(tmp_path):
    path = tmp_path / "vds.h5"
    _virtual(path, tmp_path / "gone.h5", missing=True)
    for trust in (False, True):
        with pytest.raises(evtk.FormatError, match="gone.h5"):
            evtk.open(path, trust_external=trust).events()


def test_soft_link_to_an_external_link_is_refused(tmp_path):
    target = tmp_path / "other.h5"
    with h5py.File(target, "w") as f:
        f.create_dataset("data", data=np.arange(4, dtype=np.int64))
    path = tmp_path / "soft.h5"
    _evtk_h5(path, lambda g: (g.file.__setitem__("ext", h5py.ExternalLink(str(target), "/data")),
                              g.__setitem__("t", h5py.SoftLink("/ext"))))
    with pytest.raises(evtk.FormatError, match="/ext is an external link"):
        evtk.open(path).events()


# -- sizes claimed, not held ------------------------------------------------------------------------------------


def test_hdf5_columns_claiming_2_to_50_unwritten_elements_are_an_error_at_once(tmp_path):
    path = tmp_path / "huge.h5"
    with h5py.File(path, "w") as f:
        f.attrs["evtk_format"] = np.bytes_("evtk.events")
        f.attrs["sensor_size"] = np.array([320, 240])
        g = f.create_group("events")
        for name, dt in (("t", np.int64), ("x", np.uint16), ("y", np.uint16), ("p", np.uint8)):
            g.create_dataset(name, shape=(2**50,), maxshape=(None,), chunks=(65536,), dtype=dt)
    assert path.stat().st_size < 20_000
    for args in (["info", "--check", path], ["convert", path, tmp_path / "o.parquet"], ["info", path]):
        code, out = _cli(*args)
        assert code == 1 and ("far more than" in out or "chunks written" in out), out
    assert not (tmp_path / "o.parquet").exists()


def test_dsec_ms_to_idx_never_written_is_an_error_not_gigabytes(tmp_path):
    path = tmp_path / "dsec.h5"
    with h5py.File(path, "w") as f:
        g = f.create_group("events")
        for name in "txyp":
            g.create_dataset(name, data=np.zeros(4, np.uint32 if name == "t" else np.uint16))
        f.create_dataset("ms_to_idx", shape=(2**29,), dtype=np.uint64, chunks=(2**16,))
    assert path.stat().st_size < 10_000
    with pytest.raises(evtk.FormatError, match="ms_to_idx"):
        evtk.open(path)


def test_salvage_reads_the_chunks_written_before_the_first_unwritten_one(tmp_path):
    ev = random_events(5000, seed=1)
    path = tmp_path / "sparse.h5"
    with h5py.File(path, "w") as f:
        f.attrs["evtk_format"] = np.bytes_("evtk.events")
        f.attrs["sensor_size"] = np.array([320, 240])
        g = f.create_group("events")
        for name in "txyp":
            col = getattr(ev, name)
            ds = g.create_dataset(name, shape=(8000,), chunks=(1000,), dtype=col.dtype)
            ds[:3000] = col[:3000]  # chunks 3.. never written
    with pytest.raises(evtk.FormatError, match="3 of its 8 chunks written"):
        evtk.open(path)
    with evtk.open(path, salvage=True) as rec:
        got = rec.events()
        assert "unwritten" in rec.damage.reason
    assert got == ev[:3000]


def test_hdf5_chunk_larger_than_evtk_decodes_is_refused(tmp_path):
    path = tmp_path / "bigchunk.h5"
    _evtk_h5(path, lambda g: g.create_dataset("t", shape=(2**24,), chunks=(2**24,), dtype=np.int64,
                                              compression="gzip"))
    with h5py.File(path, "a") as f:
        f["events/t"][:4] = np.arange(4)  # written, so it is the chunk size that is refused
    with pytest.raises(evtk.FormatError, match="chunks of 134217728 bytes"):
        evtk.open(path)


def test_doubly_deflated_bomb_is_refused_before_it_inflates(tmp_path):
    import zlib

    n = 2**27  # 1 GiB of int64 in 16 chunks of 64 MiB
    chunk = 2**23
    once = zlib.compress(bytes(chunk * 8), 1)
    twice = zlib.compress(once, 9)
    path = tmp_path / "bomb.h5"

    def make(g):
        ds = g.create_dataset("t", shape=(n,), chunks=(chunk,), dtype=np.int64, compression="gzip")
        ds.id.set_extent((n,))

    _evtk_h5(path, make)
    with h5py.File(path, "a") as f:  # a pipeline of two deflate filters, each chunk written pre-compressed
        del f["events/t"]
        dcpl = h5py.h5p.create(h5py.h5p.DATASET_CREATE)
        dcpl.set_chunk((chunk,))
        dcpl.set_deflate(1)
        dcpl.set_deflate(9)
        space = h5py.h5s.create_simple((n,), (n,))
        dsid = h5py.h5d.create(f["events"].id, b"t", h5py.h5t.NATIVE_INT64, space, dcpl=dcpl)
        for k in range(n // chunk):
            dsid.write_direct_chunk((k * chunk,), twice)
    assert path.stat().st_size < 200_000
    with pytest.raises(evtk.FormatError, match="far more than a file"):
        evtk.open(path)


def _zstd_frame_claiming(content_size, payload=b"\0" * 64):
    """A ZSTD frame whose header says ``content_size`` bytes (8-byte field) around one raw block."""
    fhd = 0b11100000  # 8-byte content size, single segment, no checksum, no dictionary
    block = struct.pack("<I", (len(payload) << 3) | 1)[:3] + payload
    return b"\x28\xb5\x2f\xfd" + bytes([fhd]) + struct.pack("<Q", content_size) + block


def _zstd_rle_frame(total_bytes):
    """A ZSTD frame without a content size, of RLE blocks: 4 bytes for every 128 KiB it inflates to."""
    header = b"\x28\xb5\x2f\xfd" + bytes([0b00000000, 7 << 3])  # no content size; window 128 KiB
    blocks = []
    left = total_bytes
    while left:
        size = min(left, 128 << 10)
        left -= size
        blocks.append(struct.pack("<I", (size << 3) | (1 << 1) | (left == 0))[:3] + b"\0")
    return header + b"".join(blocks)


def _aedat4(path, code, bodies, table=None):
    """An AEDAT4 file of raw packet bodies (stream 0: events) and an optional raw data-table blob."""
    xml = a4._header_xml([("events", "EVTS", {"sizeX": ("int", 320), "sizeY": ("int", 240)})], code)
    head = a4.MAGIC + a4._io_header(code, -1, xml)
    out = bytearray(head)
    for body in bodies:
        out += struct.pack("<ii", 0, len(body)) + body
    if table is not None:
        struct.pack_into("<q", out, a4._DTP_FIELD, len(out))
        out += table
    path.write_bytes(bytes(out))


def test_zstd_frame_declaring_gigabytes_is_refused_without_allocating(tmp_path):
    path = tmp_path / "claim.aedat4"
    _aedat4(path, cz.ZSTD, [_zstd_frame_claiming(1_900_000_000)])
    with pytest.raises(evtk.FormatError, match="announces 1900000000 bytes"):
        evtk.read_events(path)


def test_zstd_frame_without_size_that_inflates_past_the_bound_stops_at_the_bound(tmp_path):
    body = _zstd_rle_frame(256 << 20)
    assert len(body) < 10_000
    path = tmp_path / "rle.aedat4"
    _aedat4(path, cz.ZSTD, [body])
    with pytest.raises(evtk.FormatError, match="more than"):
        evtk.read_events(path)
    # the same in the data table: plain info does not inflate it, it walks the packets
    _aedat4(path, cz.ZSTD, [cz.compress(cz.ZSTD, _event_body(random_events(10, seed=2)))], table=body)
    with evtk.open(path) as rec:
        assert rec.info()["events"] == 10
        assert any("data table is unreadable" in w for w in rec.warnings)


def test_lz4_frame_without_size_is_bounded_and_read_when_honest(tmp_path):
    import lz4.frame

    ev = random_events(3000, seed=3)
    honest = lz4.frame.compress(_event_body(ev), store_size=False)
    bomb = lz4.frame.compress(bytes(256 << 20), store_size=False)
    assert cz.decompress(cz.LZ4, honest, cz.output_limit(len(honest))) == _event_body(ev)
    with pytest.raises(cz.CodecError, match="more than"):
        cz.decompress(cz.LZ4, bomb, cz.output_limit(len(bomb)))
    with pytest.raises(cz.CodecError, match="truncated"):
        cz.decompress(cz.LZ4, honest[:-20], cz.output_limit(len(honest)))


def _event_body(ev):
    buf = np.zeros(_fb.EVENT_PACKET_HEADER + 16 * len(ev) + 8 + 8, np.uint8)
    _fb.encode_event_packets(ev.t, ev.x, ev.y, ev.p, np.array([0, len(ev)]), 0, buf)
    return buf[8 : 8 + 32 + 16 * len(ev)].tobytes()


def test_memory_of_a_hostile_aedat4_stays_within_the_bound(tmp_path):
    """Four bombs of 256 MiB each: peak memory of reading them stays far below what they claim."""
    path = tmp_path / "four.aedat4"
    _aedat4(path, cz.ZSTD, [_zstd_rle_frame(256 << 20)] * 4)
    script = textwrap.dedent(f"""
        import resource, evtk
        try:
            evtk.read_events({str(path)!r})
        except evtk.FormatError:
            pass
        print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
    """)
    base = subprocess.run([sys.executable, "-c", "import resource, evtk; evtk.Events([], [], [], [], (2, 2));"
                           "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)"],
                          capture_output=True, text=True, check=True)
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
    grown_mib = (int(run.stdout.split()[-1]) - int(base.stdout.split()[-1])) / 1024
    assert grown_mib < 256, grown_mib


# -- nothing lost, nothing silently wrong ------------------------------------------------------------------------


def _zero_vector_length(path, packet):
    """Zero the event-vector length of packet ``packet`` of an uncompressed evtk AEDAT4 file."""
    with evtk.open(path) as rec:
        off = int(rec._index.offset[rec._index.stream == 0][packet])
    data = bytearray(path.read_bytes())
    struct.pack_into("<I", data, off + 28, 0)
    path.write_bytes(bytes(data))


@pytest.mark.parametrize("table", [True, False])
def test_strict_aedat4_read_never_drops_a_packet_whose_length_was_zeroed(tmp_path, table):
    ev = random_events(5000, seed=4)
    path = tmp_path / "z.aedat4"
    evtk.write_events(path, ev, compression="none", packet_events=1000, packet_us=None)
    if not table:  # no data table: the packets are found by walking them
        with evtk.open(path) as rec:
            dtp = rec._data_table_pos
        data = bytearray(path.read_bytes()[:dtp])
        struct.pack_into("<q", data, a4._DTP_FIELD, -1)
        path.write_bytes(bytes(data))
    _zero_vector_length(path, 2)
    with pytest.raises(evtk.FormatError, match="vector length is damaged"):
        evtk.read_events(path)
    with pytest.raises(evtk.FormatError):
        list(evtk.open(path).iter_events(chunk_events=700))
    code, out = _cli("convert", path, tmp_path / "o.h5")
    assert code == 1 and not (tmp_path / "o.h5").exists()
    with evtk.open(path, salvage=True) as rec:
        assert rec.events() == ev[:2000] and rec.damage is not None


def test_lying_hdf5_index_still_gives_exact_windows(tmp_path):
    ev = random_events(50_000, seed=5)
    path = tmp_path / "i.h5"
    evtk.write_events(path, ev, chunk_events=1000)
    with h5py.File(path, "a") as f:
        idx = f["events/index_t_us"]
        idx[...] = idx[...] + 40_000  # every block claims to start 40 ms later
    with evtk.open(path) as rec:
        for lo, hi in [(100_000, 130_000), (0, 5000), (990_000, 2_000_000)]:
            assert rec.events(lo, hi) == ev.between(lo, hi)
            assert list(rec.iter_events(t_start_us=lo, t_end_us=hi))[0] == ev.between(lo, hi)
        assert any("index disagrees" in w for w in rec.warnings)


def test_lying_parquet_statistics_still_give_exact_windows(tmp_path):
    import pyarrow.parquet as pq

    ev = random_events(4000, seed=6, span_us=40_000)
    path = tmp_path / "s.parquet"
    evtk.write_events(path, ev, row_group_events=1000)
    md = pq.ParquetFile(path).metadata
    data = bytearray(path.read_bytes())
    footer_at = len(data) - 8 - struct.unpack("<i", data[-8:-4])[0]
    # move row group 1's t statistics (min and max, written as 8-byte values in the footer) 1 s later
    st = md.row_group(1).column(0).statistics
    for v in (st.min, st.max):
        raw = struct.pack("<q", v)
        at = data.index(raw, footer_at)
        while at >= 0:
            data[at:at + 8] = struct.pack("<q", v + 1_000_000)
            at = data.find(raw, at + 8)
    path.write_bytes(bytes(data))
    assert pq.ParquetFile(path).metadata.row_group(1).column(0).statistics.min == st.min + 1_000_000
    lo, hi = int(ev.t[1000]), int(ev.t[1999]) + 1
    with evtk.open(path) as rec:
        assert rec.events(lo, hi) == ev.between(lo, hi)
        assert len(rec.events(lo, hi)) == 1000


def test_lying_aedat4_table_times_still_give_exact_windows(tmp_path):
    ev = random_events(20_000, seed=7, span_us=200_000)
    path = tmp_path / "t.aedat4"
    evtk.write_events(path, ev, compression="none", packet_events=1000, packet_us=None)
    with evtk.open(path) as rec:
        idx = rec._index
        dtp = rec._data_table_pos
        cols = [idx.offset, idx.stream, idx.size, idx.count, idx.t0.copy(), idx.t1.copy()]
    cols[4][5:] += 10_000_000  # packets 5.. claim to lie 10 s later
    cols[5][5:] += 10_000_000
    buf = np.empty(_fb.data_table_size(len(cols[0])), np.uint8)
    size = _fb.encode_data_table(*cols, buf)
    data = bytearray(path.read_bytes())
    data[dtp:dtp + size] = buf[:size].tobytes()
    path.write_bytes(bytes(data))
    lo, hi = int(ev.t[6000]), int(ev.t[7000])
    with evtk.open(path) as rec:
        assert rec.events(lo, hi) == ev.between(lo, hi)
        assert len(ev.between(lo, hi)) >= 1000
        assert any("disagree" in w for w in rec.warnings)


def _prophesee(path, t, dtype="<u8"):
    dt = np.dtype([("x", "<u2"), ("y", "<u2"), ("p", "<i2"), ("t", dtype)])
    a = np.zeros(len(t), dt)
    a["t"] = t
    with h5py.File(path, "w") as f:
        f.attrs["width"], f.attrs["height"] = 320, 240
        f.create_dataset("CD/events", data=a, chunks=(2,))


def test_uint64_times_at_or_above_2_to_63_are_a_format_error(tmp_path):
    path = tmp_path / "p.h5"
    _prophesee(path, np.array([1, 2, 2**63, 2**64 - 1], np.uint64))
    with pytest.raises(evtk.FormatError, match="beyond int64"):
        evtk.read_events(path)
    dsec = tmp_path / "d.h5"
    with h5py.File(dsec, "w") as f:
        for name in "xyp":
            f.create_dataset(f"events/{name}", data=np.zeros(3, np.uint16))
        f.create_dataset("events/t", data=np.array([0, 1, 2], np.uint64))
        f.create_dataset("ms_to_idx", data=np.zeros(1, np.uint64))
        f.create_dataset("t_offset", data=np.uint64(2**64 - 1))
    with pytest.raises(evtk.FormatError, match="t_offset"):
        evtk.read_events(dsec)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf, 1e20])
def test_event_utils_times_that_are_not_times_are_a_format_error(tmp_path, bad):
    path = tmp_path / "eu.h5"
    with h5py.File(path, "w") as f:
        f.create_dataset("events/ts", data=np.array([0.0, 0.5, bad]))
        for name in ("xs", "ys", "ps"):
            f.create_dataset(f"events/{name}", data=np.zeros(3, np.int16))
        f.attrs["sensor_resolution"] = (240, 320)
    with pytest.raises(evtk.FormatError, match=r"ts\[2\]"):
        evtk.read_events(path)


def test_parquet_writer_refuses_what_its_reader_refuses_and_sorts_when_asked(tmp_path):
    ev = random_events(100, seed=8, sort=False)
    assert not ev.is_sorted
    with pytest.raises(evtk.EvtkError, match="time order"):
        evtk.write_events(tmp_path / "u.parquet", ev)
    assert not (tmp_path / "u.parquet").exists()
    evtk.write_events(tmp_path / "s.parquet", ev, sort=True)
    order = np.argsort(ev.t, kind="stable")
    assert np.array_equal(evtk.read_events(tmp_path / "s.parquet").t, ev.t[order])
    with evtk.io.open_writer(tmp_path / "w.parquet", (320, 240)) as w:
        w.write_events(evtk.Events([5, 6], [0, 1], [0, 0], [1, 1], (320, 240)))
        with pytest.raises(evtk.EvtkError, match="backwards at event 2"):
            w.write_events(evtk.Events([4], [0], [0], [1], (320, 240)))
    off = evtk.Events._trusted(np.array([1, 2]), np.array([0, 400], np.uint16), np.array([0, 0], np.uint16),
                               np.array([1, 1], np.uint8), (320, 240))
    with pytest.raises(evtk.EvtkError, match="outside"):
        evtk.write_events(tmp_path / "o.parquet", off)


def test_output_that_is_the_input_is_an_error_and_the_recording_stays(tmp_path):
    rec = tmp_path / "rec.h5"
    _trig_recording(rec, 9)
    before = rec.read_bytes()
    for args in (["reconstruct", rec, "-o", rec, "--window", "triggers"],
                 ["reconstruct", rec, "-o", tmp_path / "." / "rec.h5", "--window", "triggers"],
                 ["convert", rec, rec],
                 ["batch", "reconstruct", tmp_path, "-o", tmp_path, "--force", "--window", "triggers",
                  "--scheduler", "serial"]):
        code, out = _cli(*args)
        assert code == 1 and "input" in out, (args, out)
        assert rec.read_bytes() == before


# -- one line, never a traceback ----------------------------------------------------------------------------------


def _aedat4_with_size(path, size_x, typ="int"):
    ev = random_events(10, seed=1)
    evtk.write_events(path, ev, compression="none")
    data = path.read_bytes()
    data = data.replace(b'<attr key="sizeX" type="int">320</attr>',
                        f'<attr key="sizeX" type="{typ}">{size_x}</attr>'.encode())
    # keep the header's length: the XML string sits at its end, padded, before the packets
    path.write_bytes(data)


@pytest.mark.parametrize("value,typ", [("inf", "float"), ("nan", "double"), ("abc", "string"), ("1e400", "double"),
                                       ("-5", "int")])
def test_aedat4_impossible_sizes_are_one_line(tmp_path, value, typ):
    path = tmp_path / "s.aedat4"
    ev = random_events(10, seed=1)
    xml = a4._header_xml([("events", "EVTS", {"sizeX": (typ, value), "sizeY": ("int", 240)})], cz.NONE)
    body = _event_body(ev)
    path.write_bytes(a4.MAGIC + a4._io_header(cz.NONE, -1, xml) + struct.pack("<ii", 0, len(body)) + body)
    code, out = _cli("info", "--json", path)
    assert code == 1 and "sensor size" in out and len(out.strip().splitlines()) == 1, out


def test_deeply_nested_metadata_is_one_line(tmp_path):
    ev = random_events(10, seed=1)
    path = tmp_path / "n.parquet"
    evtk.write_events(path, ev, metadata={"a": 1})
    import pyarrow.parquet as pq

    table = pq.read_table(path)
    meta = dict(table.schema.metadata)
    meta[b"evtk.metadata"] = b"[" * 100_000 + b"]" * 100_000
    pq.write_table(table.replace_schema_metadata(meta), path)
    code, out = _cli("info", path)
    assert code == 1 and "nests too deeply" in out, out


@pytest.mark.parametrize("size", [b"[1e400, 240]", b"[-5, 0]", b'["a", 2]', b"[NaN, 2]", b"{}"])
def test_parquet_impossible_sensor_size_is_one_line(tmp_path, size):
    import pyarrow.parquet as pq

    path = tmp_path / "s.parquet"
    evtk.write_events(path, random_events(10, seed=1))
    table = pq.read_table(path)
    meta = dict(table.schema.metadata)
    meta[b"evtk.sensor_size"] = size
    pq.write_table(table.replace_schema_metadata(meta), path)
    code, out = _cli("info", "--json", path)
    assert code == 1 and "sensor_size" in out and len(out.strip().splitlines()) == 1, out


def test_info_json_is_strict_json_whatever_the_metadata(tmp_path):
    path = tmp_path / "m.aedat4"
    evtk.write_events(path, random_events(10, seed=1), metadata={"gain": 1.5})
    data = path.read_bytes().replace(b'"gain":1.5', b'"gain":NaN')
    path.write_bytes(data)
    code, out = _cli("info", "--json", path)
    # NaN in the file's metadata is the file's fault: an error, never bare NaN on stdout
    assert code == 1 and "NaN" in out and "not valid JSON" in out
    from evtk.cli import _dumps

    assert json.loads(_dumps({"a": float("nan"), "b": [np.float64("inf"), 1.0]})) == {"a": None, "b": [None, 1.0]}


@pytest.mark.parametrize("value", ['"abc"', "NaN", "Infinity", "1e400", "true"])
def test_bench_values_that_are_not_numbers_are_one_line(tmp_path, value):
    bench = tmp_path / "b.json"
    bench.write_text(f'{{"power_mw": {value}}}')
    code, out = _cli("simulate", "--bench", bench, "-o", tmp_path / "s.aedat4")
    assert code == 1 and "power_mw" in out and len(out.strip().splitlines()) == 1, out


@pytest.mark.parametrize("args,needle", [
    (["simulate", "--power-mw", "1e300"], "power_mw"),
    (["simulate", "--repeat", "1000000000"], "MiB"),
    (["simulate", "--flat-field", "1000000000"], "MiB"),
    (["--memory-limit-mb", "1", "simulate", "--repeat", "10000"], "MiB"),
])
def test_parameters_whose_cost_is_absurd_are_refused_before_work(tmp_path, args, needle):
    code, out = _cli(*args, "-o", tmp_path / "s.aedat4")
    assert code == 1 and needle in out and len(out.strip().splitlines()) == 1, out
    assert not list(tmp_path.iterdir())


def test_window_period_is_sized_before_it_is_allocated(tmp_path):
    two = tmp_path / "two.h5"
    evtk.write_events(two, evtk.Events([0, 10**12], [0, 1], [0, 0], [1, 0], (32, 24)))
    code, out = _cli("reconstruct", two, "-o", tmp_path / "r.h5", "--window", "period:1000")
    assert code == 1 and "1,000,000,000 windows" in out and "--memory-limit-mb" in out
    empty = tmp_path / "empty.aedat4"
    evtk.write_events(empty, evtk.Events([], [], [], [], (32, 24)))
    code, out = _cli("reconstruct", empty, "-o", tmp_path / "r.h5", "--window", "period:1000")
    assert code == 1 and "no events" in out and "Traceback" not in out


@pytest.mark.parametrize("spec,needle", [("tcp://", "HOST:PORT"), ("tcp://host:abc", "port"),
                                         ("tcp://127.0.0.1:99999", "port"), ("local:100000", "EVTK_MAX_LOCAL_WORKERS")])
def test_malformed_scheduler_addresses_are_one_line(tmp_path, spec, needle):
    rec = tmp_path / "r.h5"
    evtk.write_events(rec, random_events(10, seed=1))
    code, out = _cli("batch", "reconstruct", rec, "-o", tmp_path / "out", "--scheduler", spec)
    assert code == 1 and needle in out and len(out.strip().splitlines()) == 1, out


def test_unreachable_scheduler_fails_before_the_client_waits(monkeypatch):
    import distributed

    from evtk.cluster import scheduler

    def never(*a, **k):  # the refused connection must be reported without the client's time-out
        raise AssertionError("Client() was reached")

    monkeypatch.setattr(distributed, "Client", never)
    with pytest.raises(evtk.EvtkError, match="Connection refused|no Dask scheduler"):
        with scheduler("tcp://127.0.0.1:1"):
            pass


# -- batch: every input recorded, nothing lost ----------------------------------------------------------------


def _trig_recording(path, seed):
    """2,000 events over 0.1 s and 5 windows between rising (1) and falling (2) trigger edges."""
    ev = random_events(2000, seed=seed, span_us=100_000)
    evtk.write_events(path, ev, evtk.Triggers(np.arange(0, 100_000, 10_000), np.tile([1, 2], 5)))


def test_batch_with_a_bad_input_records_it_and_does_the_rest(tmp_path, monkeypatch):
    import evtk.batch as rc

    good, bad = tmp_path / "good.h5", tmp_path / "bad.h5"
    _trig_recording(good, 1)
    _trig_recording(bad, 2)
    real = rc.reconstruct_recording

    def flaky(rec, **kw):  # an unexpected library error on one input only
        if rec.path.endswith("bad.h5"):
            raise ZeroDivisionError("division by zero")
        return real(rec, **kw)

    monkeypatch.setattr(rc, "reconstruct_recording", flaky)  # the name the batch module calls
    from evtk.batch import batch_reconstruct

    m = batch_reconstruct([good, bad, str(tmp_path / "none*.aedat4")], tmp_path / "out",
                          {"window": "triggers", "size": (4, 4)})
    by = {os.path.basename(e["input"]): e for e in m["inputs"]}
    assert by["good.h5"]["status"] == "ok" and (tmp_path / "out" / "good.h5").exists()
    assert by["bad.h5"]["status"] == "error" and "ZeroDivisionError" in by["bad.h5"]["error"]
    assert by["none*.aedat4"]["status"] == "error" and "matches no file" in by["none*.aedat4"]["error"]


def test_two_batch_runs_into_one_folder_keep_each_others_entries_and_names_do_not_collide(tmp_path):
    from evtk.batch import batch_reconstruct

    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir()
    b.mkdir()
    _trig_recording(a / "one.h5", 1)
    _trig_recording(a / "two.h5", 2)
    _trig_recording(b / "one.h5", 3)
    out = tmp_path / "out"
    opts = {"window": "triggers", "size": (4, 4)}
    batch_reconstruct([a / "one.h5"], out, opts)
    batch_reconstruct([a / "two.h5"], out, opts)
    manifest = json.loads((out / "batch.json").read_text())
    assert {os.path.basename(e["input"]) for e in manifest["inputs"]} == {"one.h5", "two.h5"}
    # a later, different input with the same name is not skipped as if it were done
    m = batch_reconstruct([b / "one.h5"], out, opts)
    assert m["inputs"][0]["status"] == "error" and "another input" in m["inputs"][0]["error"]
    # the same input again is skipped
    m = batch_reconstruct([a / "one.h5"], out, opts)
    assert m["inputs"][0]["status"] == "skipped"


def test_batch_manifest_that_is_a_list_is_rebuilt(tmp_path):
    rec = tmp_path / "r.h5"
    _trig_recording(rec, 1)
    out = tmp_path / "out"
    out.mkdir()
    (out / "batch.json").write_text("[1, 2]")
    code, text = _cli("batch", "reconstruct", rec, "-o", out, "--window", "triggers", "--size", "4x4",
                      "--scheduler", "serial")
    assert code == 0, text
    assert json.loads((out / "batch.json").read_text())["counts"]["ok"] == 1


FULL_DISK = textwrap.dedent("""
    import resource, signal, sys
    import numpy as np, evtk
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)   # writes past the limit fail with EFBIG, as on a full disk
    ev = evtk.Events(np.arange(2_000_000), np.zeros(2_000_000, np.uint16), np.zeros(2_000_000, np.uint16),
                     np.ones(2_000_000, np.uint8), (320, 240))
    resource.setrlimit(resource.RLIMIT_FSIZE, (200_000, 200_000))
    from evtk.cli import main
    sys.exit(main(sys.argv[1:]))
""")


@pytest.mark.parametrize("ext", [".h5", ".aedat4", ".parquet"])
def test_writing_onto_a_full_disk_is_one_error_and_the_old_file_stays(tmp_path, ext):
    src = tmp_path / "src.aedat4"
    evtk.write_events(src, random_events(300_000, seed=3))
    target = tmp_path / f"out{ext}"
    target.write_bytes(b"previous contents")
    run = subprocess.run([sys.executable, "-c", FULL_DISK, "convert", str(src), str(target), "--compression",
                          "none"], capture_output=True, text=True, timeout=120)
    assert run.returncode == 1, run.stderr
    assert len(run.stderr.strip().splitlines()) == 1 and "Traceback" not in run.stderr, run.stderr
    assert "Segmentation" not in run.stderr and run.returncode != -11
    assert target.read_bytes() == b"previous contents"
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".evtk-partial")]


def test_batch_onto_a_full_disk_writes_its_manifest(tmp_path):
    ins = tmp_path / "in"
    ins.mkdir()
    for k in range(2):
        _trig_recording(ins / f"r{k}.h5", k)
    out = tmp_path / "out"
    run = subprocess.run([sys.executable, "-c", FULL_DISK.replace("200_000", "3_000"), "batch", "reconstruct",
                          str(ins), "-o", str(out), "--window", "triggers", "--size", "64x64", "--format", "npz",
                          "--scheduler", "serial"], capture_output=True, text=True, timeout=120)
    assert run.returncode == 1 and "Traceback" not in run.stderr, run.stderr
    manifest = json.loads((out / "batch.json").read_text())
    assert [e["status"] for e in manifest["inputs"]] == ["error", "error"]
    assert not [p for p in out.iterdir() if p.name.endswith(".evtk-partial")]


# -- bounds of the FlatBuffers decoders -------------------------------------------------------------------------


def test_ioheader_field_at_the_end_of_the_buffer_is_the_same_error_every_time(tmp_path):
    """A field whose offset lies inside its table but whose value would run past the header: reading it
    read beyond the buffer (errors changed from run to run and could print heap addresses)."""
    buf = bytearray(32)
    struct.pack_into("<I", buf, 0, 28)  # size prefix
    struct.pack_into("<I", buf, 4, 20)  # root table at 4 + 20 = 24
    buf[8:12] = b"IOHE"
    struct.pack_into("<HHHHH", buf, 12, 10, 8, 7, 0, 0)  # vtable: table of 8 bytes, compression at +7
    struct.pack_into("<i", buf, 24, 12)  # table -> vtable at 12
    path = tmp_path / "h.aedat4"
    path.write_bytes(a4.MAGIC + bytes(buf))
    messages = set()
    for _ in range(20):
        with pytest.raises(evtk.FormatError) as err:
            evtk.open(path)
        messages.add(str(err.value))
    assert len(messages) == 1 and "offsets outside the header" in messages.pop()


def test_data_table_claiming_billions_of_events_is_not_trusted(tmp_path):
    ev = random_events(3000, seed=11)
    path = tmp_path / "c.aedat4"
    evtk.write_events(path, ev, compression="none", packet_events=1000, packet_us=None)
    with evtk.open(path) as rec:
        idx, dtp = rec._index, rec._data_table_pos
        cols = [idx.offset, idx.stream, idx.size, idx.count.copy(), idx.t0, idx.t1]
    cols[3][0] = 3_280_000_000
    buf = np.empty(_fb.data_table_size(len(cols[0])), np.uint8)
    size = _fb.encode_data_table(*cols, buf)
    data = bytearray(path.read_bytes())
    data[dtp:dtp + size] = buf[:size].tobytes()
    path.write_bytes(bytes(data))
    with evtk.open(path) as rec:
        assert rec.info()["events"] == 3000
        assert any("more elements than its packets can hold" in w for w in rec.warnings)
        assert rec.events() == ev


@pytest.mark.parametrize("size", [[-5, 0], [0, 240], [70000, 1], [1.5, 2]])
def test_hdf5_impossible_sensor_size_is_an_error_not_printed(tmp_path, size):
    path = tmp_path / "s.h5"
    evtk.write_events(path, random_events(10, seed=1))
    with h5py.File(path, "a") as f:
        f.attrs["sensor_size"] = np.array(size)
    code, out = _cli("info", path)
    assert code == 1 and "impossible sensor size" in out and "x0" not in out.split("size")[0], out


def test_two_batch_runs_at_once_into_one_folder_lose_no_entry(tmp_path):
    """Two runs writing their manifests at the same moment (threads here; processes share the same lock)."""
    import threading

    from evtk.batch import batch_reconstruct

    names = [f"r{k}.h5" for k in range(6)]
    for k, name in enumerate(names):
        _trig_recording(tmp_path / name, k)
    out = tmp_path / "out"
    opts = {"window": "triggers", "size": (4, 4)}
    runs = [[tmp_path / n for n in names[:3]], [tmp_path / n for n in names[3:]]]
    errors = []

    def go(inputs):
        try:
            batch_reconstruct(inputs, out, opts)
        except Exception as exc:  # noqa: BLE001
            errors.append(exc)

    threads = [threading.Thread(target=go, args=(r,)) for r in runs]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    manifest = json.loads((out / "batch.json").read_text())
    assert sorted(os.path.basename(e["input"]) for e in manifest["inputs"]) == names
    assert manifest["counts"]["ok"] == 6


def test_an_unfiltered_chunk_shorter_than_a_chunk_is_an_error_not_uninitialised_memory(tmp_path):
    """Fuzz case 52382 (seed 29): a bit flip removed the Blosc filter from a DSEC column, leaving a 1,536-byte chunk
    where an unfiltered chunk holds 2,400; libhdf5 filled the rest of each read from uninitialised memory, so two
    reads of the file disagreed. A chunk stored without filters must hold exactly its chunk's bytes."""
    from evtk.io.hdf5.checks import _storage_problem

    n = 1200
    path = tmp_path / "dsec.h5"
    with h5py.File(path, "w") as f:
        g = f.create_group("events")
        g.create_dataset("t", data=np.arange(n, dtype=np.uint32))
        g.create_dataset("p", data=np.ones(n, np.uint8))
        g.create_dataset("x", data=np.full(n, 3, np.uint16))
        y = g.create_dataset("y", shape=(n,), dtype=np.uint16, chunks=(n,))
        y.id.write_direct_chunk((0,), np.full(n, 7, np.uint16).tobytes()[:1536])  # short, as the flip left it
        f.create_dataset("ms_to_idx", data=np.array([0, n], np.uint64))
        f.create_dataset("t_offset", data=np.int64(0))
    with pytest.raises(evtk.FormatError, match=r"/events/y.*unfiltered in 1536 bytes, but a chunk holds 2400"):
        with evtk.open(path, sensor_size=(16, 16)) as rec:
            rec.events()
    with h5py.File(path) as f:  # the check looks at the chunk index only; a sound chunk passes
        g = f["events"]
        assert _storage_problem(g["x"], _Policy())[0] is None
        assert "unfiltered" in _storage_problem(g["y"], _Policy())[0]


class _Policy:
    trust_external = False
    file_bytes = None


def test_window_counts_of_a_recording_out_of_time_order_are_an_error_not_misplaced(tmp_path):
    """An AEDAT4 file may hold stamps out of order (its reader returns events in file order); counting windows
    finds each window's events by binary search in every chunk and hands a batch on once a chunk passes its end,
    so such a file gave other counts than its sorted events, with no word (here 25 counts instead of 571 through
    ``accumulate``, and other counts on four more of these six routes). Every route that counts a recording's
    windows now refuses it, naming the file; the same file sorted counts as its events in memory do."""
    from evtk.reconstruct.accumulate import accumulate, accumulate_batches
    from evtk.reconstruct.fixed import count_batches, net_count_batches
    from evtk.reconstruct.windows import Windows, windows_periodic

    ev = random_events(60_000, seed=5, span_us=600_000)
    t = ev.t.copy()
    t[::50] = t[::50][::-1]  # every 50th stamp is one of the far end's (2% of the events out of order)
    bad = tmp_path / "unsorted.aedat4"
    evtk.write_events(bad, evtk.Events(t, ev.x, ev.y, ev.p, ev.sensor_size), packet_events=1000, packet_us=None)
    good = tmp_path / "sorted.aedat4"
    evtk.write_events(good, evtk.Events(t, ev.x, ev.y, ev.p, ev.sensor_size).sorted(), packet_events=1000,
                      packet_us=None)
    region = (0, 32, 0, 24)
    periodic = windows_periodic(0, 600_000, 20_000)
    overlapping = Windows(np.array([0, 10_000, 200_000], np.int64), np.array([300_000, 310_000, 500_000], np.int64),
                          np.arange(3), "test")

    def counts(source, route):
        if route == "accumulate":
            c = accumulate(source, periodic, region)
            return [c.on, c.off]
        if route == "accumulate_batches":
            return [x for _, c in accumulate_batches(source, overlapping, region, batch_windows=1)
                    for x in (c.on, c.off)]
        if route == "net":
            return [np.array(b[1]) for b in net_count_batches(source, periodic, region)]
        windows = overlapping if route == "overlapping" else periodic
        return [np.array(x) for b in count_batches(source, windows, region, overlap=route != "plain")
                for x in b[1:3]]

    for route in ("accumulate", "accumulate_batches", "net", "overlapping", "plain", "no-overlap"):
        with evtk.open(bad) as rec, pytest.raises(evtk.EvtkError, match="unsorted.aedat4: its events are not in"):
            counts(rec, route)
        with evtk.open(good) as rec:
            got = counts(rec, route)
        with evtk.open(bad) as rec:
            want = counts(rec.events(), route)  # in memory: sorted first
        assert len(got) == len(want) and all(np.array_equal(a, b) for a, b in zip(got, want)), route
