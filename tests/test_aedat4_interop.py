"""AEDAT4 interoperability: dv-processing, aedat and faery as oracles, both directions."""

from pathlib import Path

import numpy as np
import peers
import pytest
from conftest import random_events

import evtk
from evtk.io import aedat4

pytest.importorskip("dv_processing")
pytest.importorskip("aedat")
pytest.importorskip("faery")

COMPRESSIONS = ["lz4", "zstd", "none"]


@pytest.fixture(scope="module")
def scene():
    ev = random_events(3000, seed=11, span_us=200_000, t0=1_000_000)
    tr = evtk.Triggers(
        [1_000_100, 1_050_000, 1_100_000, 1_150_000],
        [
            evtk.TriggerKind.EXTERNAL_SIGNAL_RISING_EDGE,
            evtk.TriggerKind.EXTERNAL_SIGNAL_FALLING_EDGE,
            evtk.TriggerKind.EXTERNAL_SIGNAL_RISING_EDGE,
            evtk.TriggerKind.TIMESTAMP_RESET,  # default-valued field: may be left out of the table
        ],
    )
    return ev, tr


# -- peer writes, evtk reads -----------------------------------------------------------

@pytest.mark.parametrize("compression", COMPRESSIONS + ["lz4_high", "zstd_high"])
def test_evtk_reads_dv_processing_files(tmp_path, scene, compression):
    ev, tr = scene
    path = tmp_path / "dv.aedat4"
    peers.dv_write(path, ev, tr, compression, chunk=700, imu=True, frame=True)
    with evtk.open(path) as rec:
        assert rec.compression == compression
        assert rec.events() == ev
        assert rec.triggers() == tr
        kinds = {s.type: s for s in rec.streams}
        assert kinds["EVTS"].count == len(ev) and kinds["EVTS"].packets == 5
        assert kinds["TRIG"].count == len(tr)
        assert kinds["IMUS"].count == 1 and kinds["FRME"].count == 1
        assert rec.sensor_size == (320, 240)
    # and what evtk reads is what dv-processing itself reads back
    dv_ev, dv_tr = peers.dv_read(path)
    assert dv_ev == ev and dv_tr == tr


@pytest.mark.parametrize("compression", COMPRESSIONS)
def test_evtk_reads_faery_files(tmp_path, compression):
    ev = random_events(10_000, seed=12, t0=5)
    path = tmp_path / "faery.aedat4"
    peers.faery_write(path, ev, compression)
    assert evtk.read_events(path) == ev


@pytest.mark.parametrize("name", ["dvxplorer_lz4.aedat4", "dvxplorer_zstd.aedat4"])
def test_committed_fixtures_agree_with_dv_processing(fixtures_dir, name):
    dv_ev, dv_tr = peers.dv_read(fixtures_dir / name)
    with evtk.open(fixtures_dir / name) as rec:
        assert rec.events() == dv_ev
        assert rec.triggers() == dv_tr
    assert len(dv_ev) == 4000 and len(dv_tr) == 20


# -- evtk writes, peers read -----------------------------------------------------------

@pytest.mark.parametrize("compression", COMPRESSIONS + ["lz4_high", "zstd_high"])
def test_dv_processing_reads_evtk_files(tmp_path, scene, compression):
    ev, tr = scene
    path = tmp_path / "evtk.aedat4"
    evtk.write_events(path, ev, tr, compression=compression, packet_events=512)
    dv_ev, dv_tr = peers.dv_read(path)
    assert dv_ev == ev
    assert dv_tr == tr


@pytest.mark.parametrize("compression", COMPRESSIONS)
def test_aedat_reads_evtk_files(tmp_path, scene, compression):
    ev, tr = scene
    path = tmp_path / "evtk.aedat4"
    evtk.write_events(path, ev, tr, compression=compression, packet_events=512)
    arr, trig, streams = peers.aedat_read(path)
    assert np.array_equal(arr["t"], ev.t.astype(np.uint64))
    assert np.array_equal(arr["x"], ev.x) and np.array_equal(arr["y"], ev.y)
    assert np.array_equal(arr["on"], ev.p.astype(bool))
    assert np.array_equal(trig["t"], tr.t.astype(np.uint64))
    assert np.array_equal(trig["source"], tr.kind)
    assert streams[0] == {"type": "events", "width": 320, "height": 240}
    assert streams[1]["type"] == "triggers"


@pytest.mark.parametrize("compression", COMPRESSIONS)
def test_faery_reads_evtk_files(tmp_path, compression):
    ev = random_events(5000, seed=13, t0=10)
    path = tmp_path / "evtk.aedat4"
    evtk.write_events(path, ev, compression=compression)
    arr = peers.faery_read(path)
    assert evtk.Events.from_structured(arr, (320, 240)) == ev


def test_evtk_file_has_a_data_table_peers_agree_on(tmp_path, scene):
    ev, tr = scene
    path = tmp_path / "evtk.aedat4"
    evtk.write_events(path, ev, tr, packet_events=1000)
    import dv_processing as dv

    rec = dv.io.MonoCameraRecording(str(path))
    # dv-processing answers time ranges from the data table without decoding
    assert rec.getTimeRange() == (min(ev.t[0], tr.t[0]), max(ev.t[-1], tr.t[-1]))
    with evtk.open(path) as r:
        assert r._index.from_table
        assert r.t_start_us == ev.t[0] and r.t_end_us == ev.t[-1]


def test_metadata_round_trip_and_dv_sees_the_attribute(tmp_path, scene):
    ev, _ = scene
    meta = {"bench": "A", "schedule": [[0, 1, 2], [3, 4, 5]], "window_us": 5000, "note": "<&>\""}
    path = tmp_path / "meta.aedat4"
    evtk.write_events(path, ev, metadata=meta)
    with evtk.open(path) as rec:
        assert rec.metadata == meta
    import dv_processing as dv

    rec = dv.io.MonoCameraRecording(str(path))
    assert "evtkMetadata" in rec.getStreamMetadata("events")


# -- windows, chunks, no data table -----------------------------------------------------

def test_windowed_read_decodes_only_overlapping_packets(tmp_path, monkeypatch):
    ev = random_events(50_000, seed=14, span_us=1_000_000)
    path = tmp_path / "w.aedat4"
    evtk.write_events(path, ev, packet_events=1000, packet_us=None)
    with evtk.open(path) as rec:
        calls = []
        original, decode_into = rec._body, rec._decode_into
        monkeypatch.setattr(rec, "_body", lambda i, *scratch: calls.append(i) or original(i, *scratch))
        # whole batches of packets decode without _body (Recording._batcher): their rows count too
        monkeypatch.setattr(rec, "_decode_into", lambda s, rows, *a: calls.extend(rows.tolist())
                            or decode_into(s, rows, *a))
        # the first window reads every packet once for the times it holds (a packet's stamps can be out of
        # order, so the data table's first and last stamp do not bound it); then only the packets a window meets
        rec.events(0, 1)
        assert sorted(set(calls)) == list(range(len(rec._index.offset)))
        for lo, hi in [(0, 10), (500_000, 510_000), (123_456, 654_321), (999_990, 2_000_000), (-5, 0)]:
            calls.clear()
            got = rec.events(lo, hi)
            assert got == ev.between(lo, hi)
            overlapping = int(np.sum((rec._index.t1 >= lo) & (rec._index.t0 < hi)))
            assert len(calls) == overlapping and overlapping <= len(got) // 1000 + 2


def test_iter_events_chunks_are_bounded_and_complete(tmp_path):
    ev = random_events(20_000, seed=15)
    path = tmp_path / "it.aedat4"
    evtk.write_events(path, ev, packet_events=777)
    with evtk.open(path) as rec:
        chunks = list(rec.iter_events(chunk_events=3000))
        assert all(len(c) <= 3000 for c in chunks) and all(len(c) == 3000 for c in chunks[:-1])
        assert evtk.Events.concatenate(chunks) == ev
        small = list(rec.iter_events(chunk_events=100))  # packets (777) split across chunks
        assert all(len(c) == 100 for c in small) and evtk.Events.concatenate(small) == ev
        window = list(rec.iter_events(chunk_events=1000, t_start_us=250_000, t_end_us=260_000))
        assert evtk.Events.concatenate(window, sensor_size=(320, 240)) == ev.between(250_000, 260_000)
        with pytest.raises(evtk.EvtkError):
            next(rec.iter_events(chunk_events=0))


def _strip_data_table(src, dst):
    """Copy of ``src`` as an interrupted recording: no data table, position -1."""
    with evtk.open(src) as rec:
        dtp = rec._data_table_pos
    data = bytearray(Path(src).read_bytes()[:dtp])
    data[aedat4._DTP_FIELD : aedat4._DTP_FIELD + 8] = np.int64(-1).tobytes()
    Path(dst).write_bytes(data)


@pytest.mark.parametrize("compression", COMPRESSIONS)
def test_file_without_data_table_is_read_by_walking(tmp_path, scene, compression):
    ev, tr = scene
    full, cut = tmp_path / "full.aedat4", tmp_path / "cut.aedat4"
    peers.dv_write(full, ev, tr, compression, chunk=500)
    _strip_data_table(full, cut)
    with evtk.open(cut) as rec:
        assert not rec._index.from_table
        assert rec.events() == ev and rec.triggers() == tr
        assert rec.events(1_050_000, 1_060_000) == ev.between(1_050_000, 1_060_000)
        info = rec.info()
        assert info["events"] == len(ev) and info["t_start_us"] == ev.t[0] and info["t_end_us"] == ev.t[-1]
    # dv-processing agrees that it is still a readable recording
    dv_ev, _ = peers.dv_read(cut)
    assert dv_ev == ev


def test_writer_is_atomic_and_keeps_previous_file(tmp_path):
    path = tmp_path / "keep.aedat4"
    first = random_events(100, seed=16)
    evtk.write_events(path, first)
    before = path.read_bytes()

    class Boom(Exception):
        pass

    with pytest.raises(Boom):
        with aedat4.Aedat4Writer(path, (320, 240)) as w:
            w.write_events(random_events(1000, seed=17))
            raise Boom
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["keep.aedat4"]


def test_streaming_writer_many_calls(tmp_path):
    ev = random_events(10_000, seed=18)
    path = tmp_path / "stream.aedat4"
    with aedat4.Aedat4Writer(path, (320, 240), compression="zstd") as w:
        for lo in range(0, len(ev), 1234):
            w.write_events(ev[lo : lo + 1234])
        w.write_triggers(evtk.Triggers([5], [1]))
    dv_ev, dv_tr = peers.dv_read(path)
    assert dv_ev == ev and dv_tr.t.tolist() == [5]


def test_header_attributes_are_exposed(fixtures_dir):
    with evtk.open(fixtures_dir / "dvxplorer_lz4.aedat4") as rec:
        header = rec.header
        assert header["events"]["source"] == "DVXplorer_fixture"
        assert header["events"]["sizeX"] == 320 and header["events"]["typeIdentifier"] == "EVTS"
        assert header["triggers"]["compression"] == "LZ4"
        assert rec.info()["header"]["frames"]["sizeY"] == 240


def _dv_frames_and_imu(path):
    import dv_processing as dv

    rec = dv.io.MonoCameraRecording(str(path))
    frames, imu = [], []
    while rec.isFrameStreamAvailable():
        f = rec.getNextFrame()
        if f is None:
            break
        frames.append((f.timestamp, f.image.copy()))
    while rec.isImuStreamAvailable():
        batch = rec.getNextImuBatch()
        if batch is None:
            break
        imu += [(m.timestamp, m.accelerometerX, m.accelerometerY, m.accelerometerZ, m.temperature) for m in batch]
    return rec.getCameraName(), frames, imu


def test_convert_aedat4_to_aedat4_keeps_frames_imu_and_the_camera(tmp_path):
    from click.testing import CliRunner
    from peers import dv_read

    from evtk.cli import main

    src = Path(__file__).resolve().parent.parent / "fixtures" / "dvxplorer_lz4.aedat4"
    out = tmp_path / "copy.aedat4"
    r = CliRunner().invoke(main, ["convert", str(src), str(out), "--compression", "zstd"])
    assert r.exit_code == 0 and "frames" in r.output and "warning" not in r.output, r.output
    name0, frames0, imu0 = _dv_frames_and_imu(src)
    name1, frames1, imu1 = _dv_frames_and_imu(out)
    assert name1 == name0 == "DVXplorer_fixture"
    assert len(frames1) == len(frames0) >= 1 and imu1 == imu0 and len(imu0) >= 1
    assert all(t0 == t1 and np.array_equal(a, b) for (t0, a), (t1, b) in zip(frames0, frames1))
    e0, t0 = dv_read(src)
    e1, t1 = dv_read(out)
    assert e0 == e1 and np.array_equal(t0.t, t1.t)
    # a target that cannot hold them: one warning naming them, or none with --events-only
    r = CliRunner().invoke(main, ["convert", str(src), str(tmp_path / "c.parquet")])
    assert r.exit_code == 0 and "warning: left out frames (1 packets), imu (1 packets)" in r.output
    assert evtk.open(tmp_path / "c.parquet").metadata["source"] == "DVXplorer_fixture"
    r = CliRunner().invoke(main, ["convert", str(src), str(tmp_path / "d.h5"), "--events-only"])
    assert r.exit_code == 0 and "warning" not in r.output


def test_faery_checksums_checked_unless_opted_out(tmp_path):
    """faery's LZ4 bodies carry xxHash block and content checksums: checked by default, skipped (the frame is
    rebuilt without them) with verify_checksums=False, --no-verify-checksums or EVTK_VERIFY_CHECKSUMS=0; a
    damaged checksum is fatal to the first, invisible to the second."""
    ev = random_events(20_000, seed=13, t0=5)
    path = tmp_path / "faery.aedat4"
    peers.faery_write(path, ev, "lz4")
    with evtk.open(path) as rec:
        body_at = int(rec._index.offset[rec._index.stream == 0][0])
    data = bytearray(path.read_bytes())
    flg = data[body_at + 4]
    assert flg & 0x10 and flg & 0x04  # block and content checksums, as faery writes them
    head = body_at + 4 + 2 + (8 if flg & 0x08 else 0) + 1
    size = int.from_bytes(data[head:head + 4], "little") & 0x7FFFFFFF
    data[head + 4 + size] ^= 0xFF  # the first block's checksum
    bad = tmp_path / "bad_checksum.aedat4"
    bad.write_bytes(bytes(data))
    assert evtk.read_events(path) == ev
    with pytest.raises(evtk.FormatError, match="block checksum"):
        evtk.read_events(bad)
    for verify in (True, None):
        with evtk.open(path, verify_checksums=verify) as rec:
            assert rec.events() == ev
        with evtk.open(bad, verify_checksums=verify) as rec, pytest.raises(evtk.FormatError, match="LZ4"):
            rec.events()
    with evtk.open(bad, verify_checksums=False) as rec:
        assert rec.events() == ev
    from click.testing import CliRunner

    from evtk.cli import main

    for flags in ([], ["--verify-checksums"]):
        res = CliRunner().invoke(main, [*flags, "convert", str(bad), str(tmp_path / "out.h5")])
        assert res.exit_code == 1 and "checksum" in res.output, res.output
    res = CliRunner().invoke(main, ["--no-verify-checksums", "convert", str(bad), str(tmp_path / "out.h5")])
    assert res.exit_code == 0, res.output
    res = CliRunner().invoke(main, ["info", "--check", str(bad)], env={"EVTK_VERIFY_CHECKSUMS": "0"})
    assert res.exit_code == 0, res.output


def test_lz4_checksum_stripping_matches_lz4(tmp_path):
    """Every frame layout lz4 writes decompresses to the same bytes without its checksums (and the check byte
    evtk recomputes for the new descriptor is lz4's own); a truncated frame is left for the decompressor to
    refuse."""
    import lz4.frame

    from evtk.io import _compression as cz

    data = np.random.default_rng(0).integers(0, 4, 300_000, np.uint8).tobytes()
    for linked in (True, False):
        for store_size in (True, False):
            for block_sum in (True, False):
                f = lz4.frame.compress(data, content_checksum=True, block_checksum=block_sum, store_size=store_size,
                                       block_linked=linked, block_size=lz4.frame.BLOCKSIZE_MAX64KB)
                g = cz.lz4_without_checksums(f)
                # the same from a numpy view of the bytes (numpy 2 refused the negative mask on a uint8)
                assert cz.lz4_without_checksums(np.frombuffer(f, np.uint8)) == g
                info = lz4.frame.get_frame_info(g)
                assert not info["content_checksum"] and not info["block_checksum"]
                assert cz.decompress(cz.LZ4, f, 1 << 22, verify=False) == data == lz4.frame.decompress(g)
                assert cz.decompress(cz.LZ4, f, 1 << 22) == data
                desc_end = 6 + (8 if store_size else 0)
                assert cz._lz4_header_checksum(bytes(f[4:desc_end]))[0] == f[desc_end]
    cut = f[: len(f) // 2]
    assert cz.lz4_without_checksums(cut) is cut
    with pytest.raises(cz.CodecError):
        cz.decompress(cz.LZ4, cut, 1 << 22)
