"""HDF5 (evtk's layout and the foreign ones) and Arrow/Parquet."""

import json
import os
import struct
import subprocess
import sys
from pathlib import Path

import h5py
import hdf5plugin
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from conftest import random_events
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import evtk

WINDOWS = [(None, None), (0, 10), (250_000, 260_000), (123_457, 654_321), (999_000, 5_000_000), (-10, 0), (7, 3)]


def check_windows(rec, ev):
    for lo, hi in WINDOWS:
        assert rec.events(lo, hi) == ev.between(lo, hi), (lo, hi)


# -- evtk's own layout -------------------------------------------------------------------

@pytest.mark.parametrize("compression", ["lz4", "zstd", "gzip", "none", "lz4_high"])
def test_hdf5_round_trip_and_layout(tmp_path, compression):
    ev = random_events(200_000, seed=1)
    tr = evtk.Triggers([10, 20, 5], [1, 2, 1])
    path = tmp_path / "r.h5"
    evtk.write_events(path, ev, tr, compression=compression, metadata={"bench": "B", "n": [1, 2]}, chunk_events=4096)
    with evtk.open(path) as rec:
        assert rec.format == "hdf5" and rec.layout == "evtk"
        assert rec.sensor_size == (320, 240)
        assert rec.events() == ev
        assert rec.triggers() == evtk.Triggers([5, 10, 20], [1, 1, 2])
        assert rec.metadata == {"bench": "B", "n": [1, 2]}
        check_windows(rec, ev)
        chunks = list(rec.iter_events(chunk_events=30_000, t_start_us=100_000))
        assert all(len(c) <= 30_000 for c in chunks)
        assert evtk.Events.concatenate(chunks) == ev.between(100_000, None)
    # the layout as docs/formats/hdf5.md promises it, read with plain h5py
    with h5py.File(path, "r") as f:
        assert f.attrs["evtk_format"] == b"evtk.events" and list(f.attrs["sensor_size"]) == [320, 240]
        assert f["events/t"].dtype == np.int64 and f["events/x"].dtype == np.uint16 and f["events/p"].dtype == np.uint8
        assert f["events/t"].chunks == (4096,)
        idx = f["events/index_t_us"][...]
        assert f["events/index_t_us"].attrs["stride"] == 4096
        assert np.array_equal(idx, ev.t[::4096])
        assert json.loads(f["metadata"][...].tobytes()) == {"bench": "B", "n": [1, 2]}
        assert f.attrs.get_id("evtk_format").dtype.kind == "S"  # fixed-length: no global heap


def test_hdf5_reader_keeps_a_small_chunk_cache(tmp_path):
    """HDF5 2.0 keeps 8 MiB of decoded chunks per open dataset: a whole read of the four event columns held
    32 MiB on top of the events (1.26x a 10 M-event read); the reader opens files with a 1 MiB cache, and
    the values read are those written (whole, windowed and streamed, the cache cut inside chunks)."""
    from evtk.io.hdf5.common import READ_CHUNK_CACHE_BYTES

    ev = random_events(100_000, seed=31)
    path = tmp_path / "c.h5"
    evtk.write_events(path, ev, chunk_events=4096)
    with evtk.open(path) as rec:
        lay = rec._layout
        for ds in (lay.t, lay.x, lay.y, lay.p):
            assert ds.id.get_access_plist().get_chunk_cache()[1] <= READ_CHUNK_CACHE_BYTES
        assert rec.events() == ev
        check_windows(rec, ev)
        assert evtk.Events.concatenate(list(rec.iter_events(chunk_events=3000))) == ev


def test_hdf5_window_reads_only_overlapping_chunks(tmp_path, monkeypatch):
    ev = random_events(300_000, seed=2)
    path = tmp_path / "w.h5"
    evtk.write_events(path, ev, chunk_events=8192)
    with evtk.open(path) as rec:
        lay = rec._layout
        reads = []
        orig_t, orig = lay.read_t, lay.read
        monkeypatch.setattr(lay, "read_t", lambda a, b: reads.append(b - a) or orig_t(a, b))
        monkeypatch.setattr(lay, "read", lambda a, b: reads.append(b - a) or orig(a, b))
        got = rec.events(500_000, 510_000)
        assert got == ev.between(500_000, 510_000)
        # two index look-ups of at most one block each, plus the window itself
        assert sum(reads) <= 2 * 8192 + len(got) + 8


def test_hdf5_streaming_writer_and_extra_arrays(tmp_path):
    from evtk.io.hdf5 import Hdf5Writer

    ev = random_events(50_000, seed=3)
    path = tmp_path / "s.h5"
    with Hdf5Writer(path, (320, 240), chunk_events=1000) as w:
        for a in range(0, len(ev), 7777):
            w.write_events(ev[a : a + 7777])
        w.write_array("responses/raw", np.arange(12.0).reshape(3, 4), {"unit": "counts"})
        with pytest.raises(evtk.EvtkError, match="time order"):
            w.write_events(ev[:10])
    with evtk.open(path) as rec:
        assert rec.events() == ev
        assert np.array_equal(rec.read_array("responses/raw"), np.arange(12.0).reshape(3, 4))
        assert np.array_equal(rec._layout.index_t, ev.t[::1000])


def test_hdf5_writer_refuses_unsorted_unless_asked(tmp_path):
    ev = random_events(1000, seed=4, sort=False)
    with pytest.raises(evtk.EvtkError, match="time order"):
        evtk.write_events(tmp_path / "u.h5", ev)
    assert not (tmp_path / "u.h5").exists() and not list(tmp_path.iterdir())
    evtk.write_events(tmp_path / "u.h5", ev, sort=True)
    got = evtk.read_events(tmp_path / "u.h5")
    order = np.argsort(ev.t, kind="stable")
    assert np.array_equal(got.t, ev.t[order]) and np.array_equal(got.x, ev.x[order])


# -- foreign layouts, built exactly as those projects lay them out -----------------------------

def make_dsec(path, ev, t_offset):
    rel = ev.t - t_offset
    with h5py.File(path, "w") as f:
        g = f.create_group("events")
        g.create_dataset("p", data=ev.p, **hdf5plugin.Blosc(cname="zstd"))
        g.create_dataset("t", data=rel.astype(np.uint32), **hdf5plugin.Blosc(cname="zstd"))
        g.create_dataset("x", data=ev.x, **hdf5plugin.Blosc(cname="zstd"))
        g.create_dataset("y", data=ev.y, **hdf5plugin.Blosc(cname="zstd"))
        ms = np.searchsorted(rel, np.arange(0, int(rel[-1]) // 1000 + 2) * 1000, side="left").astype(np.uint64)
        f.create_dataset("ms_to_idx", data=ms)
        f.create_dataset("t_offset", data=np.int64(t_offset))


def test_dsec_layout(tmp_path):
    ev = random_events(100_000, seed=5, sensor_size=(640, 480), t0=5_000_000)
    path = tmp_path / "dsec.h5"
    make_dsec(path, ev, t_offset=4_990_000)
    with evtk.open(path, sensor_size=(640, 480)) as rec:
        assert rec.layout == "dsec" and rec.sensor_size == (640, 480)
        assert rec.events() == ev
        for lo, hi in [(5_100_000, 5_100_500), (5_000_000, 5_000_001), (0, 5_000_000), (5_999_000, None)]:
            assert rec.events(lo, hi) == ev.between(lo, hi)
        assert not rec.warnings
    with evtk.open(path) as rec:  # no size given: inferred, with a warning
        w, h = rec.sensor_size
        assert w == int(ev.x.max()) + 1 and h == int(ev.y.max()) + 1
        assert any("inferred" in m for m in rec.warnings)


def test_prophesee_layout(tmp_path):
    ev = random_events(50_000, seed=6, sensor_size=(1280, 720))
    path = tmp_path / "prophesee.hdf5"
    dt = np.dtype([("x", "<u2"), ("y", "<u2"), ("p", "<i2"), ("t", "<i8")])
    cd = np.zeros(len(ev), dt)
    cd["x"], cd["y"], cd["p"], cd["t"] = ev.x, ev.y, ev.p, ev.t
    ts = np.arange(0, int(ev.t[-1]) + 2000, 2000, dtype=np.int64)
    idx = np.zeros(len(ts), np.dtype([("id", "<u8"), ("ts", "<i8")]))
    idx["ts"], idx["id"] = ts, np.searchsorted(ev.t, ts, side="left")
    trig = np.zeros(2, np.dtype([("p", "<i2"), ("id", "<i2"), ("t", "<i8")]))
    trig["p"], trig["t"] = [1, 0], [100, 900]
    with h5py.File(path, "w") as f:
        f.attrs["geometry"] = "1280x720"
        f.attrs["format"] = "EVT3"
        f.create_dataset("CD/events", data=cd, chunks=(16384,), compression="gzip")
        f.create_dataset("CD/indexes", data=idx)
        f.create_dataset("EXT_TRIGGER/events", data=trig)
    with evtk.open(path) as rec:
        assert rec.layout == "prophesee" and rec.sensor_size == (1280, 720)
        assert rec.events() == ev
        check_windows(rec, ev)
        assert rec.triggers() == evtk.Triggers([100, 900], [1, 2])


def test_prophesee_layout_reads_into_contiguous_columns(tmp_path, monkeypatch):
    """/CD/events is read a block of records at a time into contiguous columns: the fields of one read of the
    records were strided views that kept every record (16 bytes an event here) alive beside the int16 polarity's
    copy, 1.31x the events at 10 M of them. A polarity other than 0 or 1 is still named by the events' check."""
    from evtk.io.hdf5 import layouts

    monkeypatch.setattr(layouts, "RECORD_BLOCK", 1000, raising=False)  # several blocks, cut inside the file's chunks
    ev = random_events(5500, seed=33, sensor_size=(1280, 720))
    dt = np.dtype([("x", "<u2"), ("y", "<u2"), ("p", "<i2"), ("t", "<i8")])
    cd = np.zeros(len(ev), dt)
    cd["x"], cd["y"], cd["p"], cd["t"] = ev.x, ev.y, ev.p, ev.t
    path = tmp_path / "blocks.hdf5"
    with h5py.File(path, "w") as f:
        f.attrs["width"], f.attrs["height"] = 1280, 720
        f.create_dataset("CD/events", data=cd, chunks=(768,), compression="gzip")
    with evtk.open(path) as rec:
        got = rec.events()
        assert got == ev
        for col in (got.t, got.x, got.y, got.p):
            assert col.flags.c_contiguous and (col.base is None or col.base.dtype.names is None)
        assert got.p.dtype == np.uint8
        assert rec.events(1000, 600_000) == ev.between(1000, 600_000)
    cd["p"][4321] = 2  # in the fifth block
    with h5py.File(path, "w") as f:
        f.attrs["width"], f.attrs["height"] = 1280, 720
        f.create_dataset("CD/events", data=cd, chunks=(768,), compression="gzip")
    with evtk.open(path) as rec, pytest.raises(evtk.FormatError, match=r"'p' has values outside \[0, 1\] \(min 0, max 2\)"):
        rec.events()


def test_prophesee_ecf_without_plugin_is_named(tmp_path):
    from h5py import h5p, h5z

    if h5z.filter_avail(36559):
        pytest.skip("an ECF plugin is installed here")
    path = tmp_path / "ecf.hdf5"
    dt = np.dtype([("x", "<u2"), ("y", "<u2"), ("p", "<i2"), ("t", "<i8")])
    with h5py.File(path, "w") as f:
        dcpl = h5p.create(h5p.DATASET_CREATE)
        dcpl.set_chunk((1024,))
        dcpl.set_filter(36559, h5z.FLAG_OPTIONAL, ())
        space = h5py.h5s.create_simple((10,), (h5py.h5s.UNLIMITED,))
        f.create_group("CD")
        h5py.h5d.create(f["CD"].id, b"events", h5py.h5t.py_create(dt), space, dcpl=dcpl)
    with pytest.raises(evtk.FormatError, match="ECF codec .*36559.* not installed"):
        evtk.open(path)


@pytest.mark.parametrize("polarity", ["bool", "signed"])
def test_event_utils_layout(tmp_path, polarity):
    ev = random_events(20_000, seed=7, sensor_size=(346, 260), t0=1_000_000)
    path = tmp_path / "eu.h5"
    with h5py.File(path, "w") as f:
        f.create_dataset("events/xs", data=ev.x.astype(np.int16))
        f.create_dataset("events/ys", data=ev.y.astype(np.int16))
        f.create_dataset("events/ts", data=ev.t / 1e6)
        ps = ev.p.astype(bool) if polarity == "bool" else np.where(ev.p > 0, 1, -1).astype(np.int8)
        f.create_dataset("events/ps", data=ps)
        f.attrs["sensor_resolution"] = (260, 346)
        f.attrs["num_events"] = len(ev)
    with evtk.open(path) as rec:
        assert rec.layout == "event_utils" and rec.sensor_size == (346, 260)
        assert rec.events() == ev
        assert rec.events(1_200_000, 1_300_000) == ev.between(1_200_000, 1_300_000)


def test_unknown_layout_lists_what_was_found(tmp_path):
    path = tmp_path / "other.h5"
    with h5py.File(path, "w") as f:
        f.create_dataset("images/frame0", data=np.zeros((2, 2)))
    with pytest.raises(evtk.FormatError, match=r"found \['/images/', '/images/frame0'\]; expected evtk .* DSEC"):
        evtk.open(path)


# -- bad HDF5 input ----------------------------------------------------------------------------

def evtk_file(path, ev, edit):
    evtk.write_events(path, ev, chunk_events=1024)
    with h5py.File(path, "r+") as f:
        edit(f)
    return path


@pytest.mark.parametrize(
    "edit, match",
    [
        (lambda f: (f["events/x"].resize((10,))), "differ in length"),
        (lambda f: f.__delitem__("events/p"), r"/p missing"),
        (lambda f: (f.__delitem__("events/x"), f.create_dataset("events/x", data=np.zeros(2000))), "dtype float64"),
        (lambda f: f["events/t"].__setitem__(slice(1500, 1501), [0]), "backwards at event index 1500"),
        (lambda f: f["events/x"].__setitem__(slice(1700, 1701), [999]), "outside the 320x240 sensor at event index 1700"),
        (lambda f: f.attrs.__delitem__("sensor_size"), "sensor_size"),
    ],
)
def test_bad_hdf5(tmp_path, edit, match):
    ev = random_events(2000, seed=8)
    path = evtk_file(tmp_path / "bad.h5", ev, edit)
    with pytest.raises(evtk.FormatError, match=match) as info:
        with evtk.open(path) as rec:
            rec.events()
    assert info.value.path == str(path)


def test_hdf5_backwards_time_sort_and_salvage(tmp_path):
    ev = random_events(2000, seed=9)
    path = evtk_file(tmp_path / "b.h5", ev, lambda f: f["events/t"].__setitem__(slice(1500, 1501), [0]))
    with evtk.open(path, sort=True) as rec:
        got = rec.events()
        assert got.is_sorted and len(got) == 2000 and got.t[0] == 0
    with evtk.open(path, salvage=True) as rec:
        assert rec.events() == ev[:1500]
        assert "backwards at event index 1500" in rec.damage.reason


def test_truncated_and_empty_hdf5(tmp_path):
    ev = random_events(100_000, seed=10)
    good = tmp_path / "g.h5"
    evtk.write_events(good, ev, compression="none")
    cut = tmp_path / "cut.h5"
    cut.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(evtk.FormatError):
        with evtk.open(cut) as rec:
            rec.events()
    empty = tmp_path / "empty.h5"
    with h5py.File(empty, "w"):
        pass
    with pytest.raises(evtk.FormatError, match="no datasets"):
        evtk.open(empty)


# -- Arrow and Parquet --------------------------------------------------------------------------

def test_arrow_round_trip():
    ev = random_events(1000, seed=11)
    table = ev.to_arrow()
    assert table.schema.names == ["t", "x", "y", "p"]
    assert table.schema.field("t").type == pa.int64() and table.schema.field("x").type == pa.uint16()
    assert evtk.Events.from_arrow(table) == ev
    plain = pa.table({"t": ev.t, "x": ev.x.astype(np.int32), "y": ev.y, "p": ev.p.astype(bool)})
    assert evtk.Events.from_arrow(plain, sensor_size=(320, 240)) == ev
    with pytest.raises(evtk.EvtkError, match="sensor_size"):
        evtk.Events.from_arrow(plain)


@pytest.mark.parametrize("compression", ["lz4", "zstd", "none"])
def test_parquet_round_trip_windows_and_row_groups(tmp_path, compression):
    ev = random_events(100_000, seed=12)
    tr = evtk.Triggers([3, 4], [1, 2])
    path = tmp_path / "e.parquet"
    evtk.write_events(path, ev, tr, compression=compression, metadata={"k": 1}, row_group_events=10_000, row_group_us=50_000)
    pf = pq.ParquetFile(path)
    assert pf.metadata.num_row_groups >= 20
    with evtk.open(path) as rec:
        assert rec.format == "parquet" and rec.events() == ev and rec.triggers() == tr and rec.metadata == {"k": 1}
        check_windows(rec, ev)
        # a window reads only the row groups its time range overlaps
        assert len(rec._rows(500_000, 510_000)) <= 2
    # pandas/polars users read it with plain pyarrow
    table = pq.read_table(path)
    assert np.array_equal(table.column("t").to_numpy(), ev.t)


def test_parquet_whole_read_gives_arrow_memory_back_as_it_goes(tmp_path, monkeypatch):
    """A whole read decodes the row groups on its own thread and hands what Arrow's allocator freed back to the
    system every RELEASE_EVENTS events: mimalloc (pyarrow's default) otherwise kept 15-20 MiB of freed pages
    through a 10 M-event read, 1.17x the events it returned. The events are those written."""
    import types

    from evtk.io import arrow

    ev = random_events(50_000, seed=32)
    path = tmp_path / "m.parquet"
    evtk.write_events(path, ev, row_group_events=1000, row_group_us=None)
    released, threads = [], []
    pool = pa.default_memory_pool()
    spy = types.SimpleNamespace(release_unused=lambda: released.append(pool.release_unused()))
    monkeypatch.setattr(arrow, "pyarrow_module", lambda: types.SimpleNamespace(default_memory_pool=lambda: spy))
    monkeypatch.setattr(arrow, "RELEASE_EVENTS", 10_000)
    with evtk.open(path) as rec:
        read_group = rec._pf.read_row_group
        rec._pf.read_row_group = lambda g, **kw: threads.append(kw.get("use_threads", True)) or read_group(g, **kw)
        assert rec.events() == ev
    assert len(released) >= len(ev) // 10_000 - 1
    assert threads and not any(threads)


def test_bad_parquet(tmp_path):
    path = tmp_path / "bad.parquet"
    pq.write_table(pa.table({"t": [1, 2], "x": [0, 1]}), path)
    with pytest.raises(evtk.FormatError, match=r"columns \['y', 'p'\] missing"):
        evtk.open(path)
    pq.write_table(pa.table({"t": [1.5], "x": [0], "y": [0], "p": [1]}), path)
    with pytest.raises(evtk.FormatError, match="type double"):
        evtk.open(path)
    pq.write_table(pa.table({"t": [5, 1], "x": [0, 1], "y": [0, 0], "p": [1, 0]}), path)
    with pytest.raises(evtk.FormatError, match="backwards at event index 1"):
        evtk.open(path, sensor_size=(4, 4)).events()
    good = tmp_path / "g.parquet"
    evtk.write_events(good, random_events(1000, seed=13))
    cut = tmp_path / "cut.parquet"
    cut.write_bytes(good.read_bytes()[:-100])
    with pytest.raises(evtk.FormatError, match="Parquet"):
        evtk.open(cut)


def test_parquet_without_a_sensor_size_and_a_damaged_row_group(tmp_path):
    """A foreign file (no evtk metadata) whose third row group's page header is zeroed: inferring the sensor
    size reads the row groups, so it meets the damage first. A FormatError naming the row group; salvage infers
    the size from the intact row groups and keeps their events (found by the fuzz campaign, seed 29)."""
    ev = random_events(3000, seed=21, sensor_size=(64, 48))
    path = tmp_path / "foreign.parquet"
    pq.write_table(pa.table({"t": ev.t, "x": ev.x, "y": ev.y, "p": ev.p}), path, row_group_size=1000,
                   compression="none")
    off = pq.ParquetFile(path).metadata.row_group(2).column(1).data_page_offset
    data = bytearray(path.read_bytes())
    data[off:off + 8] = bytes(8)
    path.write_bytes(bytes(data))
    with pytest.raises(evtk.FormatError, match="row group 2 cannot be read") as err:
        evtk.open(path)
    assert "\n" not in str(err.value)
    with evtk.open(path, salvage=True) as rec:
        assert rec.sensor_size == (int(ev.x[:2000].max()) + 1, int(ev.y[:2000].max()) + 1)
        got = rec.events()
        for col in "txyp":
            np.testing.assert_array_equal(getattr(got, col), getattr(ev, col)[:2000])
        assert "row group 2" in rec.damage.reason


# -- every pair of formats ------------------------------------------------------------------------

FORMATS = [".aedat4", ".h5", ".parquet"]


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(n=st.integers(0, 400), seed=st.integers(0, 10**6), src=st.sampled_from(FORMATS), dst=st.sampled_from(FORMATS),
       equal_t=st.booleans())
def test_convert_every_pair(tmp_path, n, seed, src, dst, equal_t):
    ev = random_events(n, seed=seed, span_us=1 if equal_t else 10**7)
    tr = evtk.Triggers(np.arange(min(n, 3)), np.ones(min(n, 3)))
    a = tmp_path / ("a" + src)
    b = tmp_path / ("b" + dst)
    evtk.write_events(a, ev, tr, metadata={"seed": seed})
    from click.testing import CliRunner

    from evtk.cli import main

    r = CliRunner().invoke(main, ["convert", str(a), str(b)])
    assert r.exit_code == 0, r.output
    with evtk.open(b) as rec:
        assert rec.events() == ev
        assert rec.triggers() == tr
        assert rec.metadata == {"seed": seed}
        info = rec.info()
        assert info["events"] == n and info["sensor_size"] == [320, 240]


def test_parquet_footer_with_a_bad_column_type_is_an_error_not_an_abort(tmp_path):
    """A footer whose column chunk type is damaged made pyarrow abort the process (fuzzing, seed 99).

    The reader checks the chunk types against the schema first. Run in a child
    process: a regression would kill the interpreter, not fail an assert.
    """
    import struct
    import subprocess
    import sys

    ev = random_events(5000, seed=3)
    good = tmp_path / "good.parquet"
    evtk.write_events(good, ev, row_group_events=1000)
    data = bytearray(good.read_bytes())
    footer_len = struct.unpack("<I", data[-8:-4])[0]
    # Thrift compact: ColumnMetaData field 1 (type, i32) = INT64 (2, zigzag 4), then field 2 (a list)
    i = data.rfind(b"\x15\x04\x19", len(data) - 8 - footer_len)
    assert i > 0
    data[i + 1] = 0x1E  # type 15: no such physical type
    bad = tmp_path / "bad.parquet"
    bad.write_bytes(bytes(data))
    code = (
        "import evtk\n"
        f"p = {str(bad)!r}\n"
        "try:\n    evtk.open(p)\nexcept evtk.FormatError as e:\n    print('error:', e)\n"
        "with evtk.open(p, salvage=True) as r:\n    print('salvaged', len(r.events()), r.damage is not None)\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    md = pq.ParquetFile(good).metadata
    last = md.num_row_groups - 1  # rfind: the last row group's t column was damaged
    assert "error:" in r.stdout and f"row group {last} " in r.stdout and "footer is damaged" in r.stdout
    assert f"salvaged {len(ev) - md.row_group(last).num_rows} True" in r.stdout


class _FakeColumn:
    physical_type = "INT64"
    statistics = None
    compression = "LZ4"


class _FakeMetadata:
    """Row group ``fatal`` aborts the process when touched, as pyarrow does on some damaged footers."""

    def __init__(self, n, fatal):
        self.num_row_groups, self.num_columns, self._fatal = n, 1, fatal
        self.schema = self

    def column(self, j):
        return _FakeColumn()

    def row_group(self, g):
        if g == self._fatal:
            import os

            os.abort()
        return self

    @property
    def num_rows(self):
        return 0


class _FakeFile:
    def __init__(self, n, fatal):
        self.metadata = _FakeMetadata(n, fatal)


@pytest.mark.skipif(not hasattr(__import__("os"), "fork"), reason="needs fork")
def test_parquet_footer_probe_finds_the_row_group_that_aborts():
    """A footer entry pyarrow cannot parse (it aborts; found by fuzzing, seed 102) is probed in a child."""
    from evtk.io.arrow import _first_fatal_row_group

    assert _first_fatal_row_group(_FakeFile(5, fatal=2), 0) == 2
    assert _first_fatal_row_group(_FakeFile(5, fatal=0), 0) == 0
    assert _first_fatal_row_group(_FakeFile(5, fatal=None), 0) == 5
    assert _first_fatal_row_group(_FakeFile(0, fatal=None), 0) is None


def test_hdf5_salvage_keeps_everything_before_a_damaged_chunk(tmp_path):
    """events() and iter_events() agree on the intact prefix, to the HDF5 chunk (fuzzing, seed 7)."""
    ev = random_events(10_000, seed=12)
    path = tmp_path / "c.h5"
    evtk.write_events(path, ev, compression="lz4", chunk_events=1000)
    with h5py.File(path) as f:
        info = f["events/x"].id.get_chunk_info(6)  # events 6000..6999 of the x column
        offset, size = info.byte_offset, info.size
    data = bytearray(path.read_bytes())
    data[offset:offset + size] = bytes(size)
    path.write_bytes(bytes(data))
    with evtk.open(path) as rec:
        with pytest.raises(evtk.FormatError, match="cannot be read"):
            rec.events()
    with evtk.open(path, salvage=True) as rec:
        got = rec.events()
        assert rec.damage is not None and "6000" in rec.damage.reason
    assert got == ev[:6000]
    for chunk in (333, 1000, 4096):
        with evtk.open(path, salvage=True) as rec:
            assert evtk.Events.concatenate(list(rec.iter_events(chunk_events=chunk))) == ev[:6000]


@pytest.mark.parametrize("column", ["t", "x"])
def test_hdf5_salvage_info_when_the_last_events_cannot_be_read(tmp_path, column):
    """info() (``evtk info --salvage``) of a file whose last chunk of a column is damaged: the events
    salvage recovers and their time span, with the damage; strict mode refuses (fuzzing, seed 7). Before,
    a damaged ``t`` chunk made info() raise, and a damaged ``x`` chunk left it counting all 10,000."""
    ev = random_events(10_000, seed=13)
    path = tmp_path / "t.h5"
    evtk.write_events(path, ev, compression="lz4", chunk_events=1000)
    with h5py.File(path) as f:
        chunk = f[f"events/{column}"].id.get_chunk_info(9)  # events 9000..9999 of the column
    data = bytearray(path.read_bytes())
    data[chunk.byte_offset:chunk.byte_offset + chunk.size] = bytes(chunk.size)
    path.write_bytes(bytes(data))
    if column == "t":
        with evtk.open(path) as rec:
            with pytest.raises(evtk.FormatError, match="damaged HDF5 data"):
                rec.info()
    with evtk.open(path, salvage=True) as rec:
        info = rec.info()
        got = rec.events()
    assert got == ev[:9000]
    assert (info["events"], info["t_start_us"], info["t_end_us"]) == (9000, int(ev.t[0]), int(ev.t[8999]))
    assert info["damage"] is not None and "9000" in info["damage"]["reason"]
    from click.testing import CliRunner

    from evtk.cli import main

    r = CliRunner().invoke(main, ["info", "--salvage", str(path)])
    assert r.exit_code == 0 and "9,000" in r.output and "salvaged: stopped: events from index 9000" in r.output


def test_hdf5_salvage_info_agrees_with_salvaged_events_whatever_structure_is_damaged(tmp_path):
    """Each HDF5 structure of an evtk file (B-trees, symbol-table nodes, local heaps) damaged in turn:
    wherever salvage reads events, info() in salvage mode works and counts exactly those events. The
    triggers group's own structures are among them (its damage is a warning, the events stay readable)."""
    import re

    ev = random_events(10_000, seed=14)
    path = tmp_path / "s.h5"
    evtk.write_events(path, ev, evtk.Triggers([10, 20], [1, 2]), compression="lz4", chunk_events=1000)
    original = path.read_bytes()
    spots = [m.start() for sig in (b"TREE", b"SNOD", b"HEAP") for m in re.finditer(sig, original)]
    assert len(spots) >= 8
    checked = warned = 0
    for at in spots:
        data = bytearray(original)
        data[at:at + 4] = bytes(4)
        path.write_bytes(bytes(data))
        try:
            with evtk.open(path, salvage=True) as rec:
                n = len(rec.events())
        except evtk.FormatError:
            continue  # nothing to salvage: the events group itself is unreachable
        with evtk.open(path, salvage=True) as rec:
            info = rec.info()
        assert info["events"] == n, at
        checked += 1
        warned += any("triggers cannot be read" in w for w in info.get("warnings", []))
    assert checked >= 4 and warned >= 1


# -- Blosc (v1) chunks are checked before c-blosc sees them -----------------------------------

@pytest.mark.parametrize("cname", ["lz4", "zstd", "blosclz", "snappy", "zlib"])
def test_sound_blosc1_chunks_pass_the_check(tmp_path, cname):
    """No false alarms: every chunk HDF5's Blosc filter writes (several types, the three shuffles, a chunk
    of several blocks with a leftover, chunks the filter stored raw) passes blosc1_chunk_damage."""
    from evtk.io.hdf5 import blosc1_chunk_damage

    rng = np.random.default_rng(1)
    n = 300_001
    prophesee = np.zeros(n, [("x", "<u2"), ("y", "<u2"), ("p", "<i2"), ("t", "<i8")])
    prophesee["t"] = np.cumsum(rng.integers(0, 40, n))
    prophesee["x"] = rng.integers(0, 1280, n)
    columns = [np.cumsum(rng.integers(0, 3, n)).astype(np.int64), rng.integers(0, 640, n).astype(np.uint16),
               rng.integers(0, 2, n).astype(np.uint8), rng.random(n).astype(np.float32), prophesee]
    checked = 0
    with h5py.File(tmp_path / "b.h5", "w") as f:
        for k, data in enumerate(columns):
            for shuffle in (hdf5plugin.Blosc.NOSHUFFLE, hdf5plugin.Blosc.SHUFFLE, hdf5plugin.Blosc.BITSHUFFLE):
                for chunk in (1000, 150_001):
                    f.create_dataset(f"d{k}_{shuffle}_{chunk}", data=data, chunks=(chunk,),
                                     **hdf5plugin.Blosc(cname=cname, clevel=5, shuffle=shuffle))
    with h5py.File(tmp_path / "b.h5", "r") as f:
        for name, ds in f.items():
            nbytes = ds.chunks[0] * ds.dtype.itemsize
            for i in range(ds.id.get_num_chunks()):
                mask, raw = ds.id.read_direct_chunk(ds.id.get_chunk_info(i).chunk_offset)
                if not mask & 1:
                    assert blosc1_chunk_damage(memoryview(raw), nbytes) is None, (name, i)
                    checked += 1
    assert checked > 500


def test_blosc1_check_names_each_lie():
    from evtk.io.hdf5 import blosc1_chunk_damage

    data = np.arange(20_000, dtype=np.int64)
    import io

    buf = io.BytesIO()
    with h5py.File(buf, "w") as f:
        f.create_dataset("t", data=data, chunks=(20_000,), **hdf5plugin.Blosc(cname="lz4"))
    with h5py.File(buf, "r") as f:
        raw = bytearray(f["t"].id.read_direct_chunk((0,))[1])
    assert blosc1_chunk_damage(raw, data.nbytes) is None

    def lie(pos, fmt, value):
        bad = bytearray(raw)
        struct.pack_into(fmt, bad, pos, value)
        return blosc1_chunk_damage(bad, data.nbytes)

    assert "compressed bytes" in lie(12, "<i", len(raw) + 1000)
    assert "uncompressed" in lie(4, "<i", 2**31 - 1)
    assert "block size" in lie(8, "<i", -5)
    assert "block 0 starts" in lie(16, "<i", 2**30)
    first_stream = struct.unpack_from("<i", raw, 16)[0]
    assert "claims" in lie(first_stream, "<i", 2**30)
    assert "claims" in lie(first_stream, "<i", -1)
    assert "shorter" in blosc1_chunk_damage(raw[:10], data.nbytes)


READ_IN_A_CHILD = """
import sys, json, evtk
out = {}
for salvage in (False, True):
    try:
        with evtk.open(sys.argv[1], salvage=salvage) as rec:
            ev = rec.events()
        out[str(salvage)] = ["ok", len(ev), [int(v) for v in ev.t[:3]], [int(v) for v in ev.t[-1:]]]
    except evtk.FormatError as exc:
        out[str(salvage)] = ["FormatError", str(exc)]
print(json.dumps(out))
"""


@pytest.mark.parametrize("pos,value", [(12, 2**31 - 1), (16, 2**30), (15, 0x7F7F7F7F), (4, 2**31 - 1)])
def test_damaged_dsec_blosc1_chunk_is_an_error_not_a_crash(tmp_path, pos, value):
    """A DSEC file (Blosc v1, as DSEC ships) whose second chunk of /events/t has a lying header field:
    read in a child process (c-blosc 1 would take the whole process down), it gives a FormatError naming
    the chunk, and salvage returns exactly the events before that chunk."""
    import json
    import subprocess
    import sys

    ev = random_events(60_000, seed=9, sensor_size=(640, 480), t0=1_000_000)
    path = tmp_path / "dsec.h5"
    rel = ev.t - 1_000_000
    with h5py.File(path, "w") as f:
        g = f.create_group("events")
        for name, data in (("t", rel.astype(np.uint32)), ("x", ev.x), ("y", ev.y), ("p", ev.p)):
            g.create_dataset(name, data=data, chunks=(20_000,), **hdf5plugin.Blosc(cname="lz4"))
        ms = np.searchsorted(rel, np.arange(0, int(rel[-1]) // 1000 + 2) * 1000).astype(np.uint64)
        f.create_dataset("ms_to_idx", data=ms)
        f.create_dataset("t_offset", data=np.int64(1_000_000))
    with h5py.File(path, "r") as f:
        offset = f["events/t"].id.get_chunk_info(1).byte_offset
    data = bytearray(path.read_bytes())
    struct.pack_into("<I", data, offset + pos, value)
    path.write_bytes(bytes(data))
    r = subprocess.run([sys.executable, "-c", READ_IN_A_CHILD, str(path)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, (r.returncode, r.stderr[-500:])
    out = json.loads(r.stdout)
    assert out["False"][0] == "FormatError" and "Blosc chunk 1 of /events/t" in out["False"][1]
    status, n, head, tail = out["True"]
    assert status == "ok" and n == 20_000
    assert head == [int(v) for v in ev.t[:3]] and tail == [int(ev.t[19_999])]


def test_damaged_blosc_filter_parameters_are_an_error_not_a_crash(tmp_path):
    """The Blosc filter reads its parameters 2 and 3 unchecked; a pipeline message whose parameter count
    was zeroed (found by the fuzz campaign, seed 23) crashed the process. Now it is a FormatError naming
    the dataset (read in a child process)."""
    import subprocess
    import sys

    ev = random_events(5000, seed=4, sensor_size=(640, 480), t0=1000)
    path = tmp_path / "dsec.h5"
    make_dsec(path, ev, t_offset=500)
    data = bytes(path.read_bytes())
    message = struct.pack("<HHHH", 32001, 8, 1, 7) + b"blosc"  # filter id, name length, flags, parameters
    assert data.count(message) == 4
    data = data.replace(message, struct.pack("<HHHH", 32001, 8, 0, 0) + b"blosc")
    path.write_bytes(data)
    r = subprocess.run([sys.executable, "-c", READ_IN_A_CHILD, str(path)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, (r.returncode, r.stderr[-500:])
    out = json.loads(r.stdout)
    for mode in ("False", "True"):
        assert out[mode][0] == "FormatError" and "filter pipeline is damaged" in out[mode][1]


def test_chunk_claiming_more_than_the_file_is_refused_before_allocating(tmp_path):
    """A chunk index entry that claims a 4 GB chunk in a 30 kB file (found by the fuzz campaign: h5py
    allocated the claimed size before libhdf5 compared it with the file) is a FormatError naming the chunk,
    with nothing large allocated."""
    import struct
    import tracemalloc

    ev = random_events(5000, seed=4, sensor_size=(640, 480), span_us=50_000, t0=1000)
    path = tmp_path / "d.h5"
    make_dsec(path, ev, t_offset=500)
    with h5py.File(path, "r") as f:
        info = f["events/t"].id.get_chunk_info(0)
    data = bytearray(path.read_bytes())
    # v1 B-tree key of chunk 0: its size, the filter mask, then its offsets (0, and 0 for the element)
    key = struct.pack("<II", info.size, 0) + bytes(16)
    at = data.find(key)
    assert at > 0 and data.find(key, at + 1) < 0
    data[at : at + 4] = struct.pack("<I", 0xFFFF0000)
    path.write_bytes(bytes(data))
    tracemalloc.start()
    try:
        with pytest.raises(evtk.FormatError, match="chunk 0 of /events/t claims 4294901760 bytes"):
            evtk.read_events(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 64 * 2**20


def test_a_finished_or_abandoned_hdf5_writer_leaves_no_file_object_to_fail(tmp_path):
    """The HDF5 writer's file object for libhdf5 stayed open after the file was committed (or removed): the
    garbage collector's close then flushed a closed file, an error Python reports in its development mode
    (``-X dev``: "Exception ignored in ... flush of closed file", 262 times in the suite)."""
    code = f"""
import gc, numpy as np, evtk
from evtk.errors import EvtkError
ev = evtk.Events(np.arange(5000), np.zeros(5000), np.zeros(5000), np.ones(5000), (4, 4))
evtk.write_events({str(tmp_path / 'a.h5')!r}, ev)
try:
    evtk.write_events({str(tmp_path / 'b.h5')!r}, evtk.Events(np.arange(3)[::-1], [0, 0, 0], [0, 0, 0], [1, 1, 1], (4, 4)))
except EvtkError:
    pass
gc.collect()
print(len(evtk.read_events({str(tmp_path / 'a.h5')!r})))
"""
    done = subprocess.run([sys.executable, "-X", "dev", "-c", code], capture_output=True, text=True,
                          env=dict(os.environ, PYTHONPATH=str(Path(evtk.__file__).parents[1])))
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["5000"]
    assert "Exception ignored" not in done.stderr, done.stderr
