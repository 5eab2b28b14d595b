"""Fixed windows with numpy alone (evtk.reconstruct.fixed) against the whole-run path, and what it leaves out.

The whole-run path (every window's counts by ``accumulate``, then ``reconstruct_counts``) is the reference: the
numpy route must give the same responses (to 1e-9), the same binary responses and the same summary, for net
counts and for ``exp(n theta)``, and must not load numba or scipy (``evtk reconstruct --window period:US``).
"""

from __future__ import annotations

import importlib
import json
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

import evtk
from evtk.errors import EvtkError
from evtk.reconstruct import Windows, accumulate, reconstruct, reconstruct_counts, windows_periodic
from evtk.reconstruct.fixed import fixed_responses

# every test twice: with evtk's compiled kernels and without them (tests/conftest.py)
pytestmark = pytest.mark.usefixtures("compiled")

ROOT = Path(__file__).resolve().parents[1]
SENSOR = (40, 30)
PERIOD_US = 1_000


def _events(seed: int = 7) -> evtk.Events:
    """Both polarities; a bright pixel with hundreds of events a window (huge counts); many events stamped
    exactly on window boundaries; and an empty stretch (windows 20-24 hold no event)."""
    rng = np.random.default_rng(seed)
    n = 40_000
    t = rng.integers(0, 40_000, n)
    t = np.where(rng.random(n) < 0.1, (t // PERIOD_US) * PERIOD_US, t)  # on a boundary
    t = np.where((t >= 20_000) & (t < 25_000), t + 5_000, t)  # nothing in windows 20-24
    x = rng.integers(0, SENSOR[0], n)
    y = rng.integers(0, SENSOR[1], n)
    hot = rng.random(n) < 0.05  # one pixel with ~50 events a window, mostly ON
    x[hot], y[hot] = 3, 4
    p = np.where(hot, rng.random(n) < 0.8, rng.random(n) < 0.5)
    order = np.argsort(t, kind="stable")
    return evtk.Events(t[order], x[order].astype(np.uint16), y[order].astype(np.uint16),
                       p[order].astype(np.uint8), SENSOR)


def _whole_run(source, win, region, **options):
    return reconstruct_counts(accumulate(source, win, region), None, **options)


def _same(got, ref) -> None:
    assert got.responses.shape == ref.responses.shape
    scale = max(1.0, float(np.abs(ref.responses).max()))
    np.testing.assert_allclose(got.responses, ref.responses, rtol=0, atol=1e-9 * scale)
    np.testing.assert_array_equal(got.binary, ref.binary)
    assert got.summary == ref.summary
    assert got.counts.events_used == ref.counts.events_used
    assert got.counts.on.size == 0 and got.cells.shape == got.responses.shape  # no windows x pixels kept


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    path = tmp_path_factory.mktemp("fixed") / "rec.aedat4"
    evtk.write_events(path, _events())
    return path


@pytest.mark.parametrize("linear", [False, True])
@pytest.mark.parametrize("region, size", [((0, 40, 0, 30), (15, 20)),  # whole factors: straight to the cells
                                          ((0, 40, 0, 30), (7, 9)),  # area-weighted resizing
                                          ((2, 38, 1, 29), (4, 4)),  # pixels outside the region
                                          ((3, 4, 4, 5), (1, 1))])  # the hot pixel alone
@pytest.mark.parametrize("batch", [None, 3])
def test_equals_the_whole_run(linear, region, size, batch):
    ev = _events()
    win = windows_periodic(0, 40_000, PERIOD_US)
    options = dict(linear=linear, size=size, theta=0.05 if linear else None)
    _same(fixed_responses(ev, win, region, batch_windows=batch, **options), _whole_run(ev, win, region, **options))


@pytest.mark.parametrize("linear", [False, True])
def test_a_recording_read_in_small_chunks_equals_the_whole_run(recording, linear):
    # windows span chunks, chunks span windows; skip and length leave gaps between the windows
    with evtk.open(recording) as rec:
        win = windows_periodic(0, 40_000, PERIOD_US, skip_us=100, length_us=700)
        options = dict(linear=linear, theta=0.05 if linear else None, skip_us=100, length_us=700)
        ref = _whole_run(rec, win, (0, 40, 0, 30), **options)
        got = fixed_responses(rec, win, (0, 40, 0, 30), chunk_events=777, batch_windows=4, **options)
    _same(got, ref)
    assert ref.summary["events_used"] < 40_000  # the gaps left events out


@pytest.mark.parametrize("span", [(0, 40_000), (5_000, 60_000), (-3_000, 20_000)])
def test_windows_over_part_of_a_recording_or_beyond_it_equal_the_whole_run(recording, span):
    # windows starting after the first event (a time-window read), running past the last (empty windows at the
    # end), or starting before the recording
    with evtk.open(recording) as rec:
        win = windows_periodic(span[0], span[1], 1_500)
        for linear in (False, True):
            options = dict(linear=linear, theta=0.05 if linear else None, size=(5, 4))
            _same(fixed_responses(rec, win, (0, 40, 0, 30), chunk_events=5_000, batch_windows=3, **options),
                  _whole_run(rec, win, (0, 40, 0, 30), **options))


def test_sliding_windows_equal_the_whole_run(recording):
    # windows in time order overlapping their neighbours (and so the next batch's)
    starts = np.arange(0, 38_000, 500)
    win = Windows(starts, starts + 1_700, np.arange(starts.size), "test")
    with evtk.open(recording) as rec:
        for linear in (False, True):
            options = dict(linear=linear, theta=0.05 if linear else None, size=(3, 4))
            _same(fixed_responses(rec, win, (0, 40, 0, 30), chunk_events=3_000, batch_windows=4, **options),
                  _whole_run(rec, win, (0, 40, 0, 30), **options))


def test_windows_in_any_order_and_overlapping_equal_the_whole_run():
    ev = _events()
    rng = np.random.default_rng(2)
    starts = rng.integers(0, 38_000, 31)
    win = Windows(starts, starts + rng.integers(1, 3_000, 31), np.arange(31), "test")
    for linear in (False, True):
        options = dict(linear=linear, theta=0.05 if linear else None, size=(3, 4))
        _same(fixed_responses(ev, win, (0, 40, 0, 30), batch_windows=5, **options),
              _whole_run(ev, win, (0, 40, 0, 30), **options))


def test_counts_too_many_for_the_value_table_equal_the_whole_run():
    # one pixel with 1100 ON and 1000 OFF events: (ON + 1) x (OFF + 1) beyond the look-up table
    n_on, n_off = 1100, 1000
    p = np.r_[np.ones(n_on), np.zeros(n_off)].astype(np.uint8)
    np.random.default_rng(0).shuffle(p)
    extra = 5000  # every other pixel a few events, so that the whole run's table applies to its arrays
    rng = np.random.default_rng(1)
    t = np.sort(np.r_[np.arange(p.size), rng.integers(0, p.size, extra)])
    x = np.r_[np.full(p.size, 2), rng.integers(0, 64, extra)].astype(np.uint16)
    y = np.r_[np.full(p.size, 2), rng.integers(0, 64, extra)].astype(np.uint16)
    order = np.argsort(np.r_[np.arange(p.size), rng.integers(0, p.size, extra)], kind="stable")
    ev = evtk.Events(t, x[order], y[order], np.r_[p, rng.integers(0, 2, extra)].astype(np.uint8)[order], (64, 64))
    win = Windows([0], [p.size], [0], "test")
    for options in (dict(theta=0.2), dict(linear=False)):
        _same(fixed_responses(ev, win, (0, 64, 0, 64), **options), _whole_run(ev, win, (0, 64, 0, 64), **options))


def test_bad_settings_are_refused():
    ev = _events()
    win = windows_periodic(0, 40_000, PERIOD_US)
    with pytest.raises(EvtkError, match="size must be positive"):
        fixed_responses(ev, win, (0, 40, 0, 30), size=(0, 4))
    with pytest.raises(EvtkError, match="not a non-empty part"):
        fixed_responses(ev, win, (0, 40, 0, 31))
    with pytest.raises(EvtkError, match="no windows"):
        fixed_responses(ev, win[:0], (0, 40, 0, 30))


def test_reconstruct_takes_the_numpy_route_for_responses_alone(recording):
    with evtk.open(recording) as rec:
        for linear in (False, True):
            full = reconstruct(rec, window=("period", PERIOD_US), linear=linear)
            lean = reconstruct(rec, window=("period", PERIOD_US), linear=linear, keep_pixels=False)
            np.testing.assert_allclose(lean.responses, full.responses, rtol=0,
                                       atol=1e-9 * max(1.0, np.abs(full.responses).max()))
            np.testing.assert_array_equal(lean.binary, full.binary)
            assert lean.summary == full.summary
            assert lean.counts.on.shape == (len(lean.responses), 0, 0)


_PROBE = """
import sys
from evtk.cli import main

try:
    main({args!r})
except SystemExit as exc:
    assert not exc.code, exc.code
heavy = sorted({{m.split(".")[0] for m in sys.modules}} & {{"numba", "scipy", "llvmlite", "matplotlib", "skimage"}})
# and two a command's start paid for without using them: numpy.typing (annotations only, 1 ms parsing numpy's
# docstrings) and tempfile (with shutil, bz2, lzma and random, 2-3 ms; enob's simulated sweeps only)
heavy += sorted({{"numpy.typing", "tempfile"}} & set(sys.modules))
print("HEAVY", heavy)
"""


def _cli(args):
    done = subprocess.run([sys.executable, "-c", _PROBE.format(args=[str(a) for a in args])], capture_output=True,
                          text=True, cwd=ROOT, env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"}, check=False)
    assert done.returncode == 0, done.stderr
    return done.stdout


def test_the_cli_on_fixed_windows_loads_no_compiler_and_stores_responses_only(recording, tmp_path):
    out = tmp_path / "r.npz"
    printed = _cli(["reconstruct", recording, "--window", f"period:{PERIOD_US}", "-o", out])
    assert "HEAVY []" in printed  # neither numba nor scipy (nor plotting) for fixed windows
    with zipfile.ZipFile(out) as z:
        names = set(n[:-4] for n in z.namelist())
    got = evtk.reconstruct.load_reconstruction(out)
    with evtk.open(recording) as rec:
        ref = reconstruct(rec, window=("period", PERIOD_US))
    n = len(ref.responses)
    assert {"responses", "binary", "on", "off"} <= names
    assert got.counts.on.shape == (n, 0, 0) and got.cells.shape == got.responses.shape == (n, 16, 16)
    np.testing.assert_allclose(got.responses, ref.responses, rtol=0, atol=1e-9 * max(1.0, np.abs(ref.responses).max()))
    np.testing.assert_array_equal(got.binary, ref.binary)
    # --keep-pixels stores every window's counts, as before
    full = tmp_path / "full.npz"
    _cli(["reconstruct", recording, "--window", f"period:{PERIOD_US}", "--keep-pixels", "-o", full])
    kept = evtk.reconstruct.load_reconstruction(full)
    np.testing.assert_array_equal(kept.counts.on, ref.counts.on)
    assert kept.cells.shape == (n, 30, 40)
    # the responses alone: no array grows with windows x pixels (the pixels' file holds several times more)
    with np.load(out) as a, np.load(full) as b:
        assert sum(a[k].size for k in a.files) * 3 < sum(b[k].size for k in b.files)
    assert json.loads(json.dumps(dict(got.summary)))["events_used"] == ref.summary["events_used"]


def test_enob_on_fixed_windows_loads_no_compiler(recording):
    printed = _cli(["enob", recording, "--window", f"period:{PERIOD_US}"])
    assert "HEAVY []" in printed


@pytest.mark.parametrize("df", [1, 2, 3, 4, 7, 10, 31, 63, 200])
def test_the_jackknife_t_quantile_equals_scipys(df):
    # enob's interval takes Student's t quantile without importing scipy (half a second of a fresh process)
    from scipy import stats

    from evtk.metrics.sinad import _t_quantile_two_sided

    for confidence in (0.5, 0.9, 0.95, 0.99):
        assert _t_quantile_two_sided(confidence, df) == pytest.approx(stats.t.ppf(0.5 + confidence / 2, df),
                                                                      rel=1e-11)


def test_small_npz_outputs_are_stored_and_large_ones_deflated(recording, tmp_path, monkeypatch):
    # responses alone are stored as they are (deflating them cost a fresh evtk reconstruct more than its counting);
    # outputs beyond NPZ_STORE_BYTES are deflated; either reads back the same
    from evtk.io import reconstruction as recio

    with evtk.open(recording) as rec:
        result = reconstruct(rec, window=("period", PERIOD_US), keep_pixels=False)
    small, large = tmp_path / "small.npz", tmp_path / "large.npz"
    recio.save_reconstruction(small, result, SENSOR, {"source": "x"})
    with zipfile.ZipFile(small) as z:
        assert {i.compress_type for i in z.infolist()} == {zipfile.ZIP_STORED}
    monkeypatch.setattr(recio, "NPZ_STORE_BYTES", 1000)  # every output is now "large"
    recio.save_reconstruction(large, result, SENSOR, {"source": "x"})
    with zipfile.ZipFile(large) as z:
        assert {i.compress_type for i in z.infolist()} == {zipfile.ZIP_DEFLATED}
    a, b = evtk.reconstruct.load_reconstruction(small), evtk.reconstruct.load_reconstruction(large)
    np.testing.assert_array_equal(a.responses, result.responses)
    np.testing.assert_array_equal(b.responses, result.responses)
    np.testing.assert_array_equal(a.binary, b.binary)
    assert dict(a.summary) == dict(b.summary)


def test_writing_the_responses_loads_no_hash_socket_zip_or_tempfile_module(recording, tmp_path):
    # the output's partial-file host tag comes from os.uname and zlib (hashlib and socket: 6 ms of every fresh
    # evtk reconstruct), its partial file from os.open (tempfile, shutil), and a stored NPZ is written without
    # zipfile (pathlib): the file is still a valid zip (checked by zipfile's CRC test) that np.load reads
    code = (f"import sys, evtk\nfrom evtk.reconstruct import reconstruct, save_reconstruction\n"
            f"with evtk.open({str(recording)!r}) as rec:\n"
            f"    r = reconstruct(rec, window=('period', {PERIOD_US}), keep_pixels=False)\n"
            f"save_reconstruction({str(tmp_path / 'r.npz')!r}, r, rec.sensor_size)\n"
            "from evtk._atomic import _host_tag\n"
            "print(sorted({'hashlib', 'socket', 'zipfile', 'tempfile', 'shutil'} & set(sys.modules)), _host_tag())")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT,
                          env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"}, check=False)
    assert done.returncode == 0, done.stderr
    loaded, tag = done.stdout.split("] ")
    assert loaded == "[" and len(tag.strip()) == 8 and int(tag, 16) >= 0
    assert evtk.reconstruct.load_reconstruction(tmp_path / "r.npz").responses.shape[1:] == (16, 16)
    with zipfile.ZipFile(tmp_path / "r.npz") as z:
        assert z.testzip() is None and all(i.compress_type == zipfile.ZIP_STORED for i in z.infolist())


def test_a_recording_is_read_in_chunks_of_at_most_read_events(recording, monkeypatch):
    # whatever chunk_events the caller gives (reconstruct passes 4 M), the numpy route reads at most READ_EVENTS
    # at a time (4 M-event chunks were mapped and faulted in afresh, 133 MB peak for responses of 4 MB); chunks
    # of 999 events end inside the file's packets and inside windows, and the numbers stay the whole run's
    from evtk.reconstruct import fixed

    monkeypatch.setattr(fixed, "READ_EVENTS", 999)
    sizes: list[int] = []
    with evtk.open(recording) as rec:
        win = windows_periodic(0, 40_000, PERIOD_US)
        for linear in (False, True):
            options = dict(linear=linear, theta=0.05 if linear else None, size=(5, 4))
            got = fixed_responses(rec, win, (0, 40, 0, 30), chunk_events=4_000_000, progress=sizes.append,
                                  **options)
            _same(got, _whole_run(rec, win, (0, 40, 0, 30), **options))
    assert max(sizes) == 999 and sum(sizes) == 2 * 40_000


@pytest.mark.parametrize("x,y", [(320, 0), (0, 240), (65535, 3)])
@pytest.mark.parametrize("net", [True, False])
def test_in_memory_events_off_their_sensor_are_refused(x, y, net):
    """``Events`` does not check coordinates against its sensor size (the readers do): the fixed route refuses
    such events by name instead of counting them in another pixel's bin (net counts over the whole sensor key by
    ``y * width + x``) or failing on a table look-up with an IndexError."""
    from evtk.reconstruct.fixed import fixed_responses, net_count_batches
    from evtk.reconstruct.windows import Windows

    n = 3000
    xs, ys = np.full(n, 5), np.full(n, 7)
    xs[1234], ys[1234] = x, y
    ev = evtk.Events(np.arange(n) * 10, xs, ys, np.arange(n) % 2, (320, 240))
    win = Windows(np.arange(0, 30_000, 1000), np.arange(1000, 31_000, 1000), np.arange(30), "period")
    with pytest.raises(EvtkError, match=r"outside their 320x240 sensor"):
        if net:
            list(net_count_batches(ev, win, (0, 320, 0, 240), [0]))
        else:
            fixed_responses(ev, win, (0, 320, 0, 240), linear=False)


def test_reconstruct_refuses_what_is_not_an_open_recording():
    """``reconstruct(events)`` failed with an AttributeError ('Events' object has no attribute 'metadata'); it
    says what it takes instead."""
    from evtk.reconstruct import reconstruct

    ev = evtk.Events(np.arange(100) * 10, np.zeros(100), np.zeros(100), np.ones(100), (32, 32))
    for bad in (ev, "path.aedat4", None):
        with pytest.raises(EvtkError, match="takes an open recording"):
            reconstruct(bad, window=("period", 100), keep_pixels=False)


def _block_counts(ev: evtk.Events, win, region, cells) -> tuple[np.ndarray, np.ndarray, int]:
    """ON and OFF counts of each window's blocks (``cells`` rows x cols of whole pixels; a remainder that does
    not fill a block left out), one window at a time with plain indexing, and the events they hold."""
    x0, x1, y0, y1 = region
    fy, fx = ((y1 - y0) // cells[0], (x1 - x0) // cells[1]) if cells else (1, 1)
    rows, cols = (y1 - y0) // fy, (x1 - x0) // fx
    on = np.zeros((len(win), rows, cols), np.int64)
    off = np.zeros_like(on)
    x, y = ev.x.astype(np.int64), ev.y.astype(np.int64)
    for w in range(len(win)):
        m = (ev.t >= win.t_start_us[w]) & (ev.t < win.t_end_us[w]) & (x >= x0) & (x < x1) & (y >= y0) & (y < y1)
        r, c = (y - y0) // fy, (x - x0) // fx
        m &= (r < rows) & (c < cols)
        np.add.at(on[w], (r[m & (ev.p == 1)], c[m & (ev.p == 1)]), 1)
        np.add.at(off[w], (r[m & (ev.p == 0)], c[m & (ev.p == 0)]), 1)
    return on, off, int(on.sum() + off.sum())


@pytest.mark.parametrize("sensor, region, cells", [
    ((320, 240), (0, 320, 0, 240), (16, 16)),  # the CLI's default: whole sensor, whole factors, 2-byte keys
    ((320, 240), (1, 319, 2, 239), (5, 7)),  # blocks that leave a remainder, pixels outside on every side
    ((32_768, 3), (1, 32_768, 0, 3), None),  # the widest sensor with 2-byte keys: coordinates wrap below x0
    ((32_769, 3), (32_000, 32_769, 1, 2), (1, 7)),  # one wider: 4-byte keys
    ((300, 200), (0, 300, 0, 200), None),  # a window's pixels past 2**16 bins: 4-byte keys, scattered adds
])
def test_block_counts_by_arithmetic_match_plain_indexing(sensor, region, cells):
    # each event's bin is found by unsigned arithmetic (coordinates below the region wrap past it, to the dump
    # place): every sensor edge, every key width and a remainder of pixels that fill no block
    rng = np.random.default_rng(17)
    n = 60_000
    xs = np.concatenate([rng.integers(0, sensor[0], n - 8), [0, sensor[0] - 1] * 4])
    ys = np.concatenate([rng.integers(0, sensor[1], n - 8), [0, sensor[1] - 1, sensor[1] - 1, 0] * 2])
    t = np.sort(rng.integers(0, 20_000, n))
    ev = evtk.Events(t, xs.astype(np.uint16), ys.astype(np.uint16), rng.integers(0, 2, n).astype(np.uint8), sensor)
    from evtk.reconstruct.fixed import count_batches

    win = Windows(np.array([0, 1_000, 5_000, 4_000, 19_000], np.int64), np.array([1_000, 6_000, 9_000, 4_500,
                  25_000], np.int64), np.arange(5), "test")  # overlapping and out of order too
    got = list(count_batches(ev, win, region, cells, batch_windows=2, chunk_events=7_001))
    on, off, used = _block_counts(ev, win, region, cells)
    np.testing.assert_array_equal(np.concatenate([b[1] for b in got]), on)
    np.testing.assert_array_equal(np.concatenate([b[2] for b in got]), off)
    assert sum(b[3] for b in got) == used


class _OffSensorChunks:
    """A recording whose reader let events off its 32x24 sensor through (the readers refuse them): x = 40 and
    y = 30 on an event each."""

    sensor_size = (32, 24)

    def __init__(self, ev):
        self.ev = ev

    def info(self):
        return {"t_start_us": int(self.ev.t[0]), "t_end_us": int(self.ev.t[-1]), "events": len(self.ev)}

    def iter_events(self, chunk_events=1_000_000, t_start_us=None, t_end_us=None, **kw):
        yield self.ev


@pytest.mark.parametrize("cells", [None, (4, 4)])
def test_an_event_off_the_sensor_never_lands_in_another_pixels_bin(cells):
    # the bins are found by arithmetic on the coordinates; on a whole-sensor region an x past the width landed in
    # the next row's pixel (a row of 32 pixels: x = 40 is row + 1, x = 8), silently
    from evtk.reconstruct.fixed import count_batches

    t = np.array([10, 20, 30], np.int64)
    x = np.array([40, 3, 5], np.uint16)
    y = np.array([2, 30, 6], np.uint16)
    ev = evtk.Events._trusted(t, x, y, np.ones(3, np.uint8), (32, 24))
    win = Windows(np.array([0], np.int64), np.array([100], np.int64), np.arange(1), "test")
    (_, on, off, used), = list(count_batches(_OffSensorChunks(ev), win, (0, 32, 0, 24), cells))
    assert used == 1 and int(on.sum()) == 1 and int(off.sum()) == 0
    if cells is None:
        assert on[0, 6, 5] == 1  # the one event on the sensor, where it is
    else:
        assert on[0, 6 // 6, 5 // 8] == 1


@pytest.mark.parametrize("linear, size, overlapped", [(False, (15, 20), False),  # straight to the cells
                                                      (True, (15, 20), True),  # linearised: work a batch
                                                      (False, (7, 9), True)])  # resized: work a batch
def test_only_responses_with_work_of_their_own_decode_the_next_chunk_meanwhile(recording, monkeypatch, linear, size,
                                                                               overlapped, compiled):
    # straight to the cells numpy's counting is all the work, and it holds the GIL: a thread decoding the next
    # chunk beside it only competes with the reader's own threads, so each chunk is decoded, then counted. The
    # compiled counting releases the GIL, so there the next chunk decodes meanwhile. The same responses
    overlapped = overlapped or compiled == "compiled"
    acc_module = importlib.import_module("evtk.reconstruct.accumulate")  # (the package's name is the function)
    prefetched = []
    real = acc_module._prefetched

    def spy(chunks):
        prefetched.append(1)
        return real(chunks)

    monkeypatch.setattr(acc_module, "_prefetched", spy)
    win = windows_periodic(0, 40_000, PERIOD_US)
    options = dict(linear=linear, size=size, theta=0.05 if linear else None)
    with evtk.open(recording) as rec:
        got = fixed_responses(rec, win, (0, 40, 0, 30), chunk_events=5_000, batch_windows=4, **options)
    assert bool(prefetched) == overlapped
    _same(got, _whole_run(_events(), win, (0, 40, 0, 30), **options))


@pytest.mark.parametrize("dtype", [np.int16, np.int32])
def test_a_run_of_windows_clears_the_frames_it_is_given_with_or_without_events(dtype):
    # the shared frames hold a batch's leftovers: a run clears the windows of its clear range before it counts
    # (the compiled kernel as it reaches each, numpy first), whether its windows hold events in this chunk or not,
    # and leaves the others' counts as they were
    from evtk.reconstruct.fixed import _net_count_run

    ev = evtk.Events(np.arange(6, dtype=np.int64), np.array([0, 1, 2, 0, 1, 2], np.uint16),
                     np.zeros(6, np.uint16), np.array([1, 1, 0, 1, 0, 1], np.uint8), (3, 1))
    frame, n_w = 3, 4
    by_y, by_x = np.zeros(1, np.int64), np.arange(3, dtype=np.int64)
    tables = (evtk._native.padded_table(by_y, n_w * frame), evtk._native.padded_table(by_x, n_w * frame))
    for at, want_counted in ((np.array([0, 3, 3, 6, 6]), [[1, 1, -1], [0, 0, 0], [1, -1, 1], [0, 0, 0]]),
                             (np.array([0, 0, 0, 0, 0]), [[0] * 3] * 4)):
        out = np.full(n_w * frame + 1, 7, dtype)
        _net_count_run(ev, slice(0, 6), at, 0, n_w, 0, n_w, frame, 3, True, by_y, by_x, np.int64, out,
                       tables if evtk._native.enabled() else None, (1, 3))
        want = np.array(want_counted, dtype).reshape(-1) + np.repeat([7, 0, 0, 7], 3).astype(dtype)
        np.testing.assert_array_equal(out[:n_w * frame], want)
