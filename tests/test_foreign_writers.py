"""Writers of the formats other tools read (EVT 2.0, EVT 3.0, DAT, Event Stream, CSV) and the readers of text events
and N-MNIST binaries (issue 33): each file evtk writes is read back exactly by the public readers."""

import os
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from conftest import random_events

import evtk
from evtk.cli import main
from evtk.errors import EvtkError, FormatError

faery = pytest.importorskip("faery")
expelliarmus = pytest.importorskip("expelliarmus")

REAL = Path(__file__).resolve().parent.parent.parent / "shared" / "real-files"


def _events(n=20_000, seed=3, size=(640, 480), t0=1_000, span=5_000_000):
    return random_events(n, seed=seed, sensor_size=size, t0=t0, span_us=span)


def _triggers(seed=5, n=40, t0=1_000, span=5_000_000, channels=1):
    rng = np.random.default_rng(seed)
    return evtk.Triggers(np.sort(rng.integers(t0, t0 + span, n)), rng.choice([1, 2], n), rng.integers(0, channels, n))


def _same(got, ev):
    return all(np.array_equal(np.asarray(getattr(got, c), np.int64), np.asarray(getattr(ev, c), np.int64))
               for c in "txyp")


def _faery(path):
    a = faery.events_stream_from_file(str(path)).to_array()
    return a["t"].astype(np.int64), a["x"], a["y"], a["on"].astype(np.uint8)


@pytest.mark.parametrize("fmt,ext", [("evt2", ".raw"), ("evt3", ".raw"), ("dat", ".dat"), ("es", ".es"),
                                     ("csv", ".csv")])
def test_each_written_file_reads_back_exactly_with_evtk_and_faery(fmt, ext, tmp_path):
    ev = _events()
    path = tmp_path / f"rec{ext}"
    evtk.write_events(path, ev, fmt=fmt)
    with evtk.open(path) as rec:
        assert rec.sensor_size == ev.sensor_size
        assert _same(rec.events(), ev)
        w = rec.events(2_000_000, 3_000_000)
        assert _same(w, ev.between(2_000_000, 3_000_000))
        assert _same(evtk.Events.concatenate(list(rec.iter_events(3_000)), sensor_size=ev.sensor_size), ev)
    t, x, y, p = _faery(path)
    assert np.array_equal(x, ev.x) and np.array_equal(y, ev.y) and np.array_equal(p, ev.p)
    assert np.array_equal(t, ev.t)


@pytest.mark.parametrize("fmt,enc,ext", [("evt2", "evt2", "raw"), ("dat", "dat", "dat")])
def test_expelliarmus_reads_evtk_s_raw_and_dat_files_exactly(fmt, enc, ext, tmp_path):
    ev = _events(seed=8)
    path = tmp_path / f"rec.{ext}"
    evtk.write_events(path, ev, fmt=fmt)
    a = expelliarmus.Wizard(encoding=enc).read(str(path))
    for c in "txyp":
        assert np.array_equal(np.asarray(a[c], np.int64), np.asarray(getattr(ev, c), np.int64)), c


def test_evt3_events_and_trigger_channels_read_back_by_the_evt3_package(tmp_path):
    evt3 = pytest.importorskip("evt3")
    ev = _events(seed=9)
    tr = _triggers(channels=16)
    path = tmp_path / "rec.raw"
    evtk.write_events(path, ev, tr)
    e, trig = evt3.decode_file_with_triggers(str(path))
    assert np.array_equal(np.asarray(e.timestamp, np.int64), ev.t)
    assert np.array_equal(e.x, ev.x) and np.array_equal(e.y, ev.y) and np.array_equal(e.polarity, ev.p.astype(bool))
    assert (int(e.sensor_width), int(e.sensor_height)) == ev.sensor_size
    assert np.array_equal(np.asarray(trig.timestamp, np.int64), tr.t)
    assert np.array_equal(np.asarray(trig.value).astype(bool), tr.kind == 1)
    assert np.array_equal(np.asarray(trig.id), tr.channel) and len(tr.channels) > 8
    with evtk.open(path) as rec:
        assert rec.triggers() == tr  # times, edges and channels


def test_event_stream_files_read_back_by_event_stream_with_y_from_the_bottom_row(tmp_path):
    event_stream = pytest.importorskip("event_stream")
    ev = _events(seed=10, size=(346, 260))
    path = tmp_path / "rec.es"
    evtk.write_events(path, ev)
    d = event_stream.Decoder(str(path))
    assert d.type == "dvs" and (d.width, d.height) == (346, 260)
    a = np.concatenate(list(d))
    assert np.array_equal(a["t"].astype(np.int64), ev.t) and np.array_equal(a["x"], ev.x)
    assert np.array_equal(a["y"], 259 - ev.y.astype(np.int64)) and np.array_equal(a["p"], ev.p.astype(bool))


@pytest.mark.parametrize("fmt,period_us", [("evt2", 1 << 34), ("evt3", 1 << 24), ("es", None), ("dat", 1 << 32)])
def test_time_counters_wrap_unambiguously_across_long_gaps(fmt, period_us, tmp_path):
    """Times past the format's counter and gaps longer than half its period: written so that every reader
    counts the wraps (extra time-high words), or refused (DAT has none)."""
    ev = _events(n=3_000, seed=11, t0=0, span=2_000_000)
    t = ev.t.copy()
    if period_us:
        t[1000:] += period_us - 1_000_000   # across one wrap
        t[2000:] += 3 * period_us // 4       # a gap of three quarters of a period
    else:
        t[1000:] += 50_000_000
    ev2 = evtk.Events(t, ev.x, ev.y, ev.p, ev.sensor_size)
    path = tmp_path / f"rec.{fmt}"
    if fmt == "dat":
        with pytest.raises(EvtkError, match="gap"):
            evtk.write_events(path, ev2, fmt=fmt)
        assert not path.exists()
        return
    evtk.write_events(path, ev2, fmt=fmt)
    assert _same(evtk.read_events(path), ev2)
    if fmt == "evt3":
        evt3 = pytest.importorskip("evt3")
        e, _ = evt3.decode_file_with_triggers(str(path))
        assert np.array_equal(np.asarray(e.timestamp, np.int64), t)


@pytest.mark.parametrize("bad,match", [("negative", "from 0"), ("unsorted", "time order"), ("wide", "below 2048")])
def test_writers_refuse_what_the_format_cannot_hold_and_leave_no_file(bad, match, tmp_path):
    ev = _events(n=100)
    if bad == "negative":
        ev = evtk.Events(ev.t - int(ev.t[50]), ev.x, ev.y, ev.p, ev.sensor_size)
    elif bad == "unsorted":
        ev = evtk.Events(ev.t[::-1].copy(), ev.x, ev.y, ev.p, ev.sensor_size)
    else:
        ev = evtk.Events(ev.t, ev.x, ev.y, ev.p, (4096, 480))
    path = tmp_path / "rec.raw"
    with pytest.raises(EvtkError, match=match):
        evtk.write_events(path, ev)
    assert not path.exists() and not list(tmp_path.iterdir())


def test_triggers_into_formats_without_them_are_an_error_and_convert_names_them(tmp_path):
    ev, tr = _events(n=2_000), _triggers()
    with pytest.raises(EvtkError, match="trigger"):
        evtk.write_events(tmp_path / "a.dat", ev, tr)
    src = tmp_path / "src.aedat4"
    evtk.write_events(src, ev, tr)
    res = CliRunner().invoke(main, ["convert", str(src), str(tmp_path / "b.dat")])
    assert res.exit_code == 0, res.output
    assert "trigger edges (40)" in res.output
    assert _same(evtk.read_events(tmp_path / "b.dat"), ev)
    res = CliRunner().invoke(main, ["convert", str(src), str(tmp_path / "b.raw"), "--format", "evt2"])
    assert res.exit_code == 0, res.output and "warning" not in res.output
    with evtk.open(tmp_path / "b.raw") as rec:
        assert rec.encoding == "evt2" and _same(rec.events(), ev) and rec.triggers() == tr


@pytest.mark.parametrize("source_fmt", ["evt2", "evt3", "dat", "es", "csv", "aedat4", "hdf5", "parquet"])
@pytest.mark.parametrize("target_fmt", ["evt2", "evt3", "dat", "es", "csv", "aedat4"])
def test_convert_between_any_two_formats_keeps_every_event(source_fmt, target_fmt, tmp_path):
    ev = _events(n=3_000, seed=12, size=(320, 240))
    ext = {"aedat4": ".aedat4", "hdf5": ".h5", "parquet": ".parquet"}.get(source_fmt, ".x")
    src = tmp_path / f"src{ext}"
    evtk.write_events(src, ev, fmt=source_fmt)
    dst = tmp_path / f"dst.{target_fmt}"
    res = CliRunner().invoke(main, ["convert", str(src), str(dst), "--format", target_fmt])
    assert res.exit_code == 0, res.output
    assert _same(evtk.read_events(dst), ev)


# -- text events ---------------------------------------------------------------------------------------------------

def test_text_events_in_microseconds_with_a_height_width_line(tmp_path):
    """As the DVS toolkit writes them: a 'rows cols' first line, then 't x y p' with runs of spaces."""
    ev = _events(n=500, size=(240, 180), t0=1_645_793_388_095_964, span=1_000_000)
    lines = ["180 240"] + [f"{t} {x:3d} {y:3d} {p}" for t, x, y, p in zip(ev.t, ev.x, ev.y, ev.p)]
    path = tmp_path / "events.txt"
    path.write_text("\n".join(lines) + "\n")
    assert evtk.io.detect_format(path) == "text"
    with evtk.open(path) as rec:
        assert rec.sensor_size == (240, 180) and _same(rec.events(), ev)
        info = rec.info()
        assert info["events"] == 500 and info["format"] == "text"


def test_one_stray_decimal_point_does_not_read_a_microsecond_file_as_seconds(tmp_path):
    """A separator changed to '.' on one line ("1234. 56 7 1") left four numbers there, and the first dot in
    the file made every stamp seconds: a million times every time written, silently (fuzz campaign, t.txt)."""
    ev = _events(n=400, size=(240, 180), t0=5_000, span=100_000)
    lines = ["180 240"] + [f"{t}  {x:3d} {y:3d} {p}" for t, x, y, p in zip(ev.t, ev.x, ev.y, ev.p)]
    lines[20] = lines[20].replace("  ", ". ", 1)
    path = tmp_path / "events.txt"
    path.write_text("\n".join(lines) + "\n")
    with evtk.open(path) as rec:
        assert _same(rec.events(), ev)


def test_text_events_in_seconds_with_column_names_and_minus_one_polarity(tmp_path):
    ev = _events(n=300, size=(346, 260), t0=10_000, span=2_000_000)
    lines = ["timestamp,x,y,polarity"] + [f"{t / 1e6:.6f},{x},{y},{1 if p else -1}"
                                          for t, x, y, p in zip(ev.t, ev.x, ev.y, ev.p)]
    path = tmp_path / "ev.csv"
    path.write_text("\n".join(lines))
    with evtk.open(path, sensor_size=(346, 260)) as rec:
        assert _same(rec.events(), ev)


def test_faery_csv_is_read_with_its_sensor_size(tmp_path):
    ev = _events(n=1_000, size=(128, 96))
    arr = np.zeros(len(ev), faery.EVENTS_DTYPE)
    arr["t"], arr["x"], arr["y"], arr["on"] = ev.t, ev.x, ev.y, ev.p.astype(bool)
    path = tmp_path / "f.csv"
    faery.events_stream_from_array(arr, (128, 96)).to_file(str(path))
    with evtk.open(path) as rec:
        assert rec.sensor_size == (128, 96) and _same(rec.events(), ev)


def test_a_bad_text_line_is_a_format_error_naming_it_and_salvage_keeps_the_lines_before(tmp_path):
    path = tmp_path / "ev.txt"
    path.write_text("1 2 3 1\n5 6 7 0\n9 10 oops 1\n12 1 1 1\n")
    with pytest.raises(FormatError, match="line 3"):
        evtk.read_events(path)
    with evtk.open(path, salvage=True, sensor_size=(20, 20)) as rec:
        got = rec.events()
        assert list(got.t) == [1, 5] and rec.damage is not None and rec.damage.offset == 16
    path.write_text("1 2 3 1\n5 6 7\n")
    with pytest.raises(FormatError, match="line 2"):
        evtk.read_events(path)


def test_text_events_off_the_given_sensor_are_refused(tmp_path):
    path = tmp_path / "ev.txt"
    path.write_text("10 20\n1 25 3 1\n")
    with pytest.raises(FormatError, match="sensor"):
        evtk.read_events(path)


# -- N-MNIST ------------------------------------------------------------------------------------------------------

def _nmnist_bytes(x, y, p, t):
    raw = np.zeros((len(x), 5), np.uint8)
    raw[:, 0], raw[:, 1] = x, y
    raw[:, 2] = (np.asarray(p, np.int64) << 7) | ((np.asarray(t) >> 16) & 0x7F)
    raw[:, 3] = (np.asarray(t) >> 8) & 0xFF
    raw[:, 4] = np.asarray(t) & 0xFF
    return raw.tobytes()


def test_nmnist_binary_agrees_with_tonic_including_the_overflow_marker(tmp_path):
    tio = pytest.importorskip("tonic.io")
    rng = np.random.default_rng(2)
    n = 2_000
    t = np.sort(rng.integers(0, 300_000, n))
    x, y, p = rng.integers(0, 34, n), rng.integers(0, 34, n), rng.integers(0, 2, n)
    data = _nmnist_bytes(x, y, p, t)
    marker = _nmnist_bytes([0], [240], [0], [t[1500]])  # adds 2**13 us to every later event
    path = tmp_path / "00001.bin"
    path.write_bytes(data[:5 * 1500] + marker + data[5 * 1500:])
    assert evtk.io.detect_format(path) == "nmnist"
    ref = tio.read_mnist_file(str(path), dtype=np.dtype([("x", int), ("y", int), ("t", int), ("p", int)]))
    with evtk.open(path) as rec:
        got = rec.events()
        assert rec.sensor_size == (34, 34) and len(got) == n
    assert np.array_equal(got.t, ref["t"]) and np.array_equal(got.x, ref["x"]) and np.array_equal(got.y, ref["y"])
    assert np.array_equal(got.p, ref["p"])
    assert np.array_equal(got.t[1500:], t[1500:] + 8192)


def test_a_cut_nmnist_file_is_an_error_and_salvage_keeps_the_whole_events(tmp_path):
    data = _nmnist_bytes([1, 2, 3], [4, 5, 6], [1, 0, 1], [10, 20, 30])
    path = tmp_path / "cut.bin"
    path.write_bytes(data[:-2])
    with pytest.raises(FormatError, match="ends inside an event"):
        evtk.read_events(path)
    from evtk.io.decoded import NmnistRecording

    with NmnistRecording(path, salvage=True) as rec:
        assert list(rec.events().t) == [10, 20] and rec.damage.offset == 10


@pytest.mark.skipif(not (REAL / "tonic__sample_nmnist.bin").exists(), reason="../shared/real-files is not here")
def test_the_real_nmnist_sample_reads_as_tonic_reads_it():
    tio = pytest.importorskip("tonic.io")
    path = REAL / "tonic__sample_nmnist.bin"
    ref = tio.read_mnist_file(str(path), dtype=np.dtype([("x", int), ("y", int), ("t", int), ("p", int)]))
    got = evtk.read_events(path)
    assert len(got) == len(ref) > 0
    assert np.array_equal(got.t, ref["t"]) and np.array_equal(got.x, ref["x"]) and np.array_equal(got.y, ref["y"])


@pytest.mark.skipif(not (REAL / "taro-dvstoolkit__test-02.txt").exists(), reason="../shared/real-files is not here")
def test_the_real_text_file_reads_line_for_line():
    path = REAL / "taro-dvstoolkit__test-02.txt"
    rows = np.loadtxt(path, skiprows=1, dtype=np.int64)
    with evtk.open(path) as rec:
        got = rec.events()
        assert rec.sensor_size == (240, 180)
    assert np.array_equal(got.t, rows[:, 0]) and np.array_equal(got.x, rows[:, 1])
    assert np.array_equal(got.y, rows[:, 2]) and np.array_equal(got.p, rows[:, 3])


def test_no_file_is_left_when_a_foreign_write_fails_midway(tmp_path):
    ev = _events(n=1_000)
    path = tmp_path / "x.es"
    with pytest.raises(EvtkError):
        with evtk.io.open_writer(path, ev.sensor_size) as w:
            w.write_events(ev)
            w.write_events(ev)  # goes back in time
    assert not os.path.exists(path) and not list(tmp_path.iterdir())


def test_csv_lines_equal_python_s_own_formatting():
    """The numpy-only integer formatting of the CSV writer, against str() on every width and sign."""
    from evtk.io.decoded import csv_lines

    rng = np.random.default_rng(13)
    cols = [np.concatenate([[0, -1, 9, 10, -10, 2**62, -(2**62)], rng.integers(-(10**12), 10**15, 500)]),
            rng.integers(0, 65536, 507), np.zeros(507, np.int64), rng.integers(0, 2, 507)]
    want = "".join(",".join(str(int(c[i])) for c in cols) + "\n" for i in range(507)).encode()
    assert csv_lines(cols) == want


@pytest.mark.parametrize("fmt", ["evt2", "evt3", "dat", "es", "csv"])
def test_writes_across_encoding_blocks_from_a_structured_array_read_back_exactly(fmt, tmp_path):
    """The writers encode 65,536 events at a time: a time-high change, a long gap, a repeated time and a repeated
    row fall exactly on the block edges; columns that are a structured array's (unaligned) fields, contiguous
    columns and uneven chunks give the same bytes, which evtk and faery read back exactly."""
    from evtk.io.foreign import _BLOCK

    n = 3 * _BLOCK + 123
    rng = np.random.default_rng(21)
    t = np.cumsum(rng.integers(0, 3, n)).astype(np.int64)
    # long: the longest DAT holds; EVT 2.0 / 3.0 gaps that need intermediate time-high words; 0xFF bytes in ES
    long_gap = {"dat": 1 << 30, "evt2": (1 << 35) + 7, "evt3": (1 << 23) + 7, "es": (1 << 20) + 7}.get(fmt, 1 << 40)
    t[_BLOCK:] += long_gap  # the second block opens after a long gap
    t[2 * _BLOCK:] += 4096 - t[2 * _BLOCK] % 4096  # the third opens on a new EVT 3.0 time high ...
    t[2 * _BLOCK - 1] = t[2 * _BLOCK - 2]  # ... after a repeated time
    arr = np.zeros(n, [("t", "<i8"), ("x", "<u2"), ("y", "<u2"), ("p", "u1")])  # 13-byte records: unaligned fields
    arr["t"], arr["x"], arr["y"], arr["p"] = t, rng.integers(0, 1280, n), rng.integers(0, 720, n), rng.integers(0, 2, n)
    arr["y"][_BLOCK - 1:_BLOCK + 1] = 5  # a row repeated across the first edge
    strided = evtk.Events(arr["t"], arr["x"], arr["y"], arr["p"], (1280, 720))
    plain = evtk.Events(t, arr["x"].copy(), arr["y"].copy(), arr["p"].copy(), (1280, 720))
    assert not strided.x.flags.aligned or not strided.x.flags.c_contiguous
    ext = {"evt2": "raw", "evt3": "raw"}.get(fmt, fmt)
    paths = [tmp_path / f"{k}.{ext}" for k in range(3)]
    evtk.write_events(paths[0], strided, fmt=fmt)
    evtk.write_events(paths[1], plain, fmt=fmt)
    with evtk.io.open_writer(paths[2], plain.sensor_size, fmt=fmt) as w:
        for a, b in [(0, 1000), (1000, _BLOCK + 5), (_BLOCK + 5, n)]:
            w.write_events(plain[a:b])

    def body(p):  # the bytes after the header (its date line differs from file to file)
        data = p.read_bytes()
        return data[data.index(b"% end\n") + 6:] if fmt in ("evt2", "evt3") else data.split(b"\n", 5)[-1] \
            if fmt == "dat" else data

    assert body(paths[0]) == body(paths[1]) == body(paths[2])
    assert _same(evtk.read_events(paths[0]), plain)
    ft, fx, fy, fp = _faery(paths[0])
    assert np.array_equal(ft, t) and np.array_equal(fx, plain.x) and np.array_equal(fy, plain.y)
    assert np.array_equal(fp, plain.p)


def test_csv_lines_any_mix_of_narrow_and_wide_columns():
    """Narrow columns (below 65,536) are read from a table as 8-byte words and may share the line's first bytes;
    wide and negative ones are formatted digit by digit: every order and mix, against str()."""
    from evtk.io.decoded import csv_lines

    rng = np.random.default_rng(17)
    n = 700
    pool = [rng.integers(-(10**15), 10**17, n), rng.integers(0, 65536, n).astype(np.uint16),
            rng.integers(0, 2, n).astype(np.uint8), rng.integers(0, 70_000, n), rng.integers(0, 2, n).astype(bool),
            rng.integers(0, 10, n), rng.integers(0, 10**7, n), rng.integers(0, 2**63 - 1, n, dtype=np.int64),
            np.full(n, -(2**63), np.int64)]
    for trial in range(40):
        cols = [pool[i] for i in rng.permutation(len(pool))[:rng.integers(1, len(pool) + 1)]]
        want = "".join(",".join(str(int(c[i])) for c in cols) + "\n" for i in range(n)).encode()
        assert csv_lines(cols) == want, trial


def test_writing_the_foreign_formats_imports_no_compiler_nor_other_format_s_library(tmp_path):
    """A fresh process pays for every import: writing EVT 2.0/3.0, DAT, Event Stream and CSV needs numpy alone
    (no numba, h5py, pyarrow, scipy)."""
    import subprocess
    import sys

    code = ("import sys, numpy as np, evtk\n"
            "ev = evtk.Events(np.arange(100), np.arange(100) % 7, np.arange(100) % 5, np.arange(100) % 2, (8, 8))\n"
            "for fmt in ('evt2', 'evt3', 'dat', 'es', 'csv'):\n"
            f"    evtk.write_events({str(tmp_path)!r} + '/rec.' + fmt, ev, fmt=fmt)\n"
            "print(sorted(m for m in ('numba', 'h5py', 'pyarrow', 'scipy', 'llvmlite') if m in sys.modules))\n")
    env = {**os.environ, "PYTHONPATH": str(Path(evtk.__file__).resolve().parent.parent)}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    assert out.stdout.strip() == "[]"
    assert len(list(tmp_path.iterdir())) == 5


def test_event_stream_memory_for_long_gaps_is_a_few_times_the_bytes_written(tmp_path):
    """Each whole 127 us of a gap is one 0xFF byte in an Event Stream file: a sparse recording's file is mostly
    those bytes, and writing it takes a few bytes of memory for each (it took 40: an 8-byte index a byte, sorted)."""
    import tracemalloc

    n = 1_000
    ev = evtk.Events(np.arange(n, dtype=np.int64) * 127 * 4_000, np.zeros(n), np.zeros(n), np.ones(n), (8, 8))
    path = tmp_path / "sparse.es"
    tracemalloc.start()
    try:
        evtk.write_events(path, ev)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    size = path.stat().st_size
    assert size > 4_000_000 and peak < 5 * size
    assert _same(evtk.read_events(path), ev)


def test_a_chunk_refused_part_way_is_taken_back_whole_and_the_writer_goes_on(tmp_path, monkeypatch):
    """The writers encode a chunk a block at a time: a chunk whose later block is refused (here an Event Stream
    gap whose 0xFF bytes exceed the memory budget) leaves nothing of its earlier blocks in the file, and the next
    chunk continues from the one before it."""
    from evtk.io.foreign import _BLOCK

    monkeypatch.setenv("EVTK_MEMORY_LIMIT_MB", "16")

    def chunk(t):
        t = np.asarray(t, np.int64)
        return evtk.Events(t, np.arange(len(t)) % 8, np.arange(len(t)) % 8, np.arange(len(t)) % 2, (8, 8))

    first, last = chunk(np.arange(100) * 3), chunk(np.arange(100) * 3 + 400)
    t_bad = np.arange(2 * _BLOCK) + 300
    t_bad[_BLOCK + 10:] += 127 * (8 << 20)  # the second block needs 8 MiB of 0xFF bytes, three times that to make
    path = tmp_path / "rec.es"
    with evtk.io.open_writer(path, (8, 8), fmt="es") as w:
        w.write_events(first)
        with pytest.raises(EvtkError, match="memory|MiB"):
            w.write_events(chunk(t_bad))
        w.write_events(last)
    assert _same(evtk.read_events(path), evtk.Events.concatenate([first, last]))


@pytest.mark.parametrize("fmt,period", [("evt3", 1 << 24), ("evt2", 1 << 34), ("evt21", 1 << 34)])
def test_a_first_time_in_the_counter_s_first_period_reads_back_and_one_past_it_is_refused(fmt, period, tmp_path):
    """Readers take a RAW file's first time for one of the counter's first period (2**24 us in EVT 3.0, 2**34 in
    EVT 2.0 and 2.1): a later first event read back modulo the period (a DV recording stamped in Unix
    microseconds lost its hours and days, with no warning). Events starting just inside it read back exactly, in
    evtk and in the evt3 package; one microsecond later the write is refused and leaves no file."""
    ev = _events(n=3_000, seed=12, t0=period - 1_000, span=3_000_000)
    tr = _triggers(t0=period - 500, span=3_000_000)
    path = tmp_path / "late.raw"
    evtk.write_events(path, ev, tr, fmt=fmt)
    with evtk.open(path) as rec:
        assert _same(rec.events(), ev) and np.array_equal(rec.triggers().t, tr.t)
    if fmt == "evt3":
        evt3 = pytest.importorskip("evt3")
        e, _ = evt3.decode_file_with_triggers(str(path))
        assert np.array_equal(np.asarray(e.timestamp, np.int64), ev.t)
    path.unlink()
    later = evtk.Events(ev.t - int(ev.t[0]) + period, ev.x, ev.y, ev.p, ev.sensor_size)
    with pytest.raises(EvtkError, match=f"modulo {period:,} us"):
        evtk.write_events(path, later, fmt=fmt)
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("fmt,ext,t0", [("evt3", ".raw", 1_761_176_369_642_276), ("dat", ".dat", 2**32),
                                        ("evt2", ".raw", 2**62), ("es", ".es", 127 * 2**30 + 127)])
def test_a_first_time_no_file_of_the_format_can_reach_is_refused_and_convert_shifts_it(fmt, ext, t0, tmp_path):
    """A first time past the counter's first period (Unix microseconds in EVT 3.0; 2**32 us in DAT; 2**62 us in
    EVT 2.0) is refused, naming the remedy, and leaves no file; ``convert --time-from-zero`` writes the times less
    the earliest, and keeps that in the header (HDF5: in the metadata)."""
    ev = _events(n=2_000, seed=13, t0=t0, span=2_000_000)
    tr = None
    if fmt not in ("dat", "es"):  # the earliest time a trigger's, 500 us before the first event
        tr = _triggers(t0=t0, span=2_000_000)
        tr = evtk.Triggers(np.concatenate(([int(ev.t[0]) - 500], tr.t)), np.concatenate(([1], tr.kind)),
                           np.concatenate(([0], tr.channel)))
    target = tmp_path / f"late{ext}"
    with pytest.raises(EvtkError, match="--time-from-zero"):
        evtk.write_events(target, ev, tr, fmt=fmt)
    assert not list(tmp_path.iterdir())
    source = tmp_path / "src.h5"
    evtk.write_events(source, ev, tr)
    r = CliRunner().invoke(main, ["convert", str(source), str(target), "--format", fmt])
    assert r.exit_code != 0 and "--time-from-zero" in r.output and not target.exists()
    r = CliRunner().invoke(main, ["convert", str(source), str(target), "--format", fmt, "--time-from-zero"])
    start = int(ev.t[0]) if tr is None else min(int(ev.t[0]), int(tr.t[0]))
    assert r.exit_code == 0, r.output
    assert f"shifted by -{start:,} us" in r.output
    with evtk.open(target) as rec:
        assert np.array_equal(rec.events().t, ev.t - start) and _same(rec.events(), evtk.Events(
            ev.t - start, ev.x, ev.y, ev.p, ev.sensor_size))
        if tr is not None:
            assert np.array_equal(rec.triggers().t, tr.t - start)
        if fmt != "es":  # (Event Stream holds no metadata)
            assert f"time_offset_us {start}" in rec.metadata["header"]
    done = evtk.io.convert(source, tmp_path / "again.h5", time_from_zero=True)
    assert done["time_offset_us"] == start
    with evtk.open(tmp_path / "again.h5") as rec:
        assert str(rec.metadata.get("time_offset_us")) == str(start)
        assert np.array_equal(rec.events().t, ev.t - start)


def test_time_from_zero_refuses_to_leave_an_aedat4_target_s_other_streams_unshifted(tmp_path):
    """AEDAT4 to AEDAT4 copies the other streams' packets as they are: shifting only the events would misalign
    them, so --time-from-zero asks for --events-only there."""
    src = REAL / "hetk987__dvSave-2025_10_22_18_39_29.aedat4"  # events and 698 IMU packets
    if not src.exists():
        pytest.skip("../shared/real-files is not beside the checkout")
    r = CliRunner().invoke(main, ["convert", str(src), str(tmp_path / "o.aedat4"), "--time-from-zero"])
    assert r.exit_code != 0 and "--events-only" in r.output and not (tmp_path / "o.aedat4").exists()
    r = CliRunner().invoke(main, ["convert", str(src), str(tmp_path / "o.aedat4"), "--time-from-zero",
                                  "--events-only"])
    assert r.exit_code == 0, r.output
    a, b = evtk.read_events(src), evtk.read_events(tmp_path / "o.aedat4")
    assert np.array_equal(b.t, a.t - a.t.min()) and np.array_equal(b.x, a.x)
