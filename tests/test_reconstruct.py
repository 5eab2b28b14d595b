"""Reconstruction stages 1-2: capture windows and per-window accumulation."""

import json

import numpy as np
import pytest
from conftest import random_events

import evtk
from evtk import EvtkError, TriggerKind, Triggers
from evtk.reconstruct import Windows, accumulate, windows_from_schedule, windows_from_triggers, windows_periodic

R, F = TriggerKind.EXTERNAL_SIGNAL_RISING_EDGE, TriggerKind.EXTERNAL_SIGNAL_FALLING_EDGE


def _oracle(ev, windows, region):
    """np.add.at, window by window: the independent reference."""
    x0, x1, y0, y1 = region
    on = np.zeros((len(windows), y1 - y0, x1 - x0), np.int64)
    off = np.zeros_like(on)
    for w, (a, b) in enumerate(zip(windows.t_start_us, windows.t_end_us)):
        sel = (ev.t >= a) & (ev.t < b) & (ev.x >= x0) & (ev.x < x1) & (ev.y >= y0) & (ev.y < y1)
        for arr, pol in ((on, 1), (off, 0)):
            s = sel & (ev.p == pol)
            np.add.at(arr[w], (ev.y[s].astype(int) - y0, ev.x[s].astype(int) - x0), 1)
    return on, off


def _time_oracle(ev, windows, region):
    """First and last ON-event time per window and pixel from the window's start, -1 where none."""
    x0, x1, y0, y1 = region
    first = np.full((len(windows), y1 - y0, x1 - x0), -1, np.int64)
    last = first.copy()
    for w, (a, b) in enumerate(zip(windows.t_start_us, windows.t_end_us)):
        sel = (ev.t >= a) & (ev.t < b) & (ev.x >= x0) & (ev.x < x1) & (ev.y >= y0) & (ev.y < y1) & (ev.p == 1)
        for t, x, y in zip(ev.t[sel] - a, ev.x[sel].astype(int) - x0, ev.y[sel].astype(int) - y0):
            if first[w, y, x] < 0:
                first[w, y, x] = t
            last[w, y, x] = t
    return first, last


def _random_windows(rng, n, t0, t1, overlap=False):
    if overlap:
        a = rng.integers(t0, t1 - 1, n)
        b = a + rng.integers(1, (t1 - t0) // 4, n)
    else:
        edges = np.sort(rng.choice(np.arange(t0, t1), 2 * n, replace=False))
        a, b = edges[0::2], edges[1::2]
    return Windows(a, b, np.arange(n), "test")


@pytest.mark.parametrize("overlap", [False, True])
@pytest.mark.parametrize("region", [None, (10, 50, 5, 40)])
def test_accumulate_matches_add_at(overlap, region):
    rng = np.random.default_rng(1 + overlap)
    ev = random_events(50_000, seed=2, sensor_size=(64, 48), span_us=100_000)
    win = _random_windows(rng, 40, -1000, 101_000, overlap)
    got = accumulate(ev, win, region)
    reg = region or (0, 64, 0, 48)
    on, off = _oracle(ev, win, reg)
    np.testing.assert_array_equal(got.on, on)
    np.testing.assert_array_equal(got.off, off)
    assert got.events_used == on.sum() + off.sum()
    assert got.on.dtype == np.int32
    assert got.on_first_us is None and got.on_last_us is None
    timed = accumulate(ev, win, region, times=True)
    np.testing.assert_array_equal(timed.on, on)
    np.testing.assert_array_equal(timed.off, off)
    first, last = _time_oracle(ev, win, reg)
    np.testing.assert_array_equal(timed.on_first_us, first)
    np.testing.assert_array_equal(timed.on_last_us, last)
    assert timed.on_first_us.dtype == np.int32


def test_accumulate_streams_a_recording_across_chunks(tmp_path):
    ev = random_events(30_000, seed=4, sensor_size=(32, 24), span_us=60_000)
    path = tmp_path / "r.aedat4"
    evtk.write_events(path, ev)
    rng = np.random.default_rng(5)
    win = _random_windows(rng, 25, 0, 60_000)
    # unsorted windows too: the result keeps the caller's order
    perm = rng.permutation(len(win))
    win = Windows(win.t_start_us[perm], win.t_end_us[perm], win.capture[perm], "test")
    on, off = _oracle(ev, win, (0, 32, 0, 24))
    for fmt in ("r.aedat4", "r.h5", "r.parquet"):
        p = tmp_path / fmt
        if not p.exists():
            evtk.write_events(p, ev)
        with evtk.open(p) as rec:
            got = accumulate(rec, win, chunk_events=997)  # many chunks, windows straddle them
            timed = accumulate(rec, win, chunk_events=997, times=True)
        np.testing.assert_array_equal(got.on, on)
        np.testing.assert_array_equal(got.off, off)
        np.testing.assert_array_equal(timed.on, on)
        first, last = _time_oracle(ev, win, (0, 32, 0, 24))
        np.testing.assert_array_equal(timed.on_first_us, first)  # in the caller's window order
        np.testing.assert_array_equal(timed.on_last_us, last)


def test_unsorted_events_empty_windows_and_no_events():
    ev = random_events(5000, seed=6, sensor_size=(16, 16), span_us=10_000, sort=False)
    win = Windows([0, 20_000, 5_000], [5_000, 30_000, 10_000], [0, 1, 2], "test")
    got = accumulate(ev, win)
    on, off = _oracle(ev, win, (0, 16, 0, 16))
    np.testing.assert_array_equal(got.on, on)
    assert got.on[1].sum() == got.off[1].sum() == 0  # a window after the last event
    empty = evtk.Events.empty((16, 16))
    assert accumulate(empty, win).on.sum() == 0
    none = accumulate(ev, Windows([], [], [], "none"))
    assert none.on.shape == (0, 16, 16)
    timed = accumulate(ev, win, times=True)
    assert np.all(timed.on_first_us[1] == -1) and np.all(timed.on_last_us[1] == -1)
    assert accumulate(ev, Windows([], [], [], "none"), times=True).on_first_us.shape == (0, 16, 16)
    assert np.all(accumulate(empty, win, times=True).on_last_us == -1)
    with pytest.raises(EvtkError, match="shorter than 2\\*\\*31"):
        accumulate(ev, Windows([0], [2**31], [0], "long"), times=True)


def test_bad_windows_and_regions():
    with pytest.raises(EvtkError, match="empty or reversed"):
        Windows([10], [10], [0], "x")
    with pytest.raises(EvtkError, match="equal length"):
        Windows([1, 2], [3], [0], "x")
    ev = random_events(100, seed=1, sensor_size=(8, 8))
    with pytest.raises(EvtkError, match="region"):
        accumulate(ev, Windows([0], [10], [0], "x"), region=(0, 9, 0, 8))


def test_windows_from_triggers_edge_cases():
    t = [100, 200, 300, 350, 500, 600, 650, 800, 900, 900, 1000]
    k = [R, F, R, R, F, F, 0, R, R, F, R]
    w = windows_from_triggers(Triggers(t, k))
    # [100,200); rising at 300 lost its falling edge; [350,500); falling at 600 has no rising edge;
    # the timestamp reset (kind 0) is not an edge; 800 lost its falling edge; 900/900 is zero-length;
    # 1000 is still open at the end
    assert w.t_start_us.tolist() == [100, 350] and w.t_end_us.tolist() == [200, 500]
    assert w.dropped == {"missing falling edge": 2, "falling edge without rising edge": 1,
                         "recording ends mid-window": 1, "zero-length window": 1}
    trimmed = windows_from_triggers(Triggers(t, k), skip_us=20, length_us=50)
    assert trimmed.t_start_us.tolist() == [120, 370] and trimmed.t_end_us.tolist() == [170, 420]
    with pytest.raises(EvtkError, match="leaves nothing"):
        windows_from_triggers(Triggers(t, k), skip_us=100)
    with pytest.raises(EvtkError, match="no complete window"):
        windows_from_triggers(Triggers([5, 6], [F, R]))


def test_windows_periodic():
    w = windows_periodic(1000, 1950, 100, skip_us=10, length_us=50)
    assert len(w) == 9 and w.t_start_us[0] == 1010 and w.t_end_us[0] == 1060
    assert w.dropped == {"partial last period": 1}
    with pytest.raises(EvtkError, match="shorter than one period"):
        windows_periodic(0, 50, 100)
    with pytest.raises(EvtkError, match="period_us"):
        windows_periodic(0, 50, 0)


def test_simulated_recording_schedule_and_triggers_agree(tmp_path):
    from evtk.sensor import SensorModel
    from evtk.simulate import Simulation

    k = np.array([[1, -1, 1], [0, 1, 0], [1, 0, -1]])
    f = np.random.default_rng(3).choice([-1, 1], (16, 16))
    sim = Simulation(k, f, repeat=2, seed=2, sensor=SensorModel(shot_noise=False, background_rate_hz=0.0))
    path = tmp_path / "sim.aedat4"
    sim.write(path)
    with evtk.open(path) as rec:
        by_schedule = windows_from_schedule(rec.metadata)
        by_triggers = windows_from_triggers(rec.triggers())
        np.testing.assert_array_equal(by_schedule.t_start_us, by_triggers.t_start_us)
        np.testing.assert_array_equal(by_schedule.t_end_us, by_triggers.t_end_us)
        assert by_triggers.dropped == {}
        counts = accumulate(rec, by_schedule, region=sim.region, chunk_events=5000)
    exact = sim.responses(method="exact")
    np.testing.assert_array_equal(counts.on, exact.on)
    np.testing.assert_array_equal(counts.off, exact.off)
    with pytest.raises(EvtkError, match="no capture schedule"):
        windows_from_schedule({"something": 1})


def test_windows_from_triggers_of_a_dv_processing_recording(tmp_path):
    """A bench recording without a schedule: dv-processing writes events and the DMD triggers."""
    pytest.importorskip("dv_processing")
    from peers import dv_read, dv_write

    ev = random_events(20_000, seed=8, sensor_size=(320, 240), span_us=40_000)
    on_t = np.arange(2_000, 38_000, 4_000)
    t = np.empty(2 * on_t.size, np.int64)
    t[0::2], t[1::2] = on_t, on_t + 1_500
    kinds = np.tile([int(R), int(F)], on_t.size)
    path = tmp_path / "bench.aedat4"
    dv_write(path, ev, Triggers(t, kinds))
    _, dv_tr = dv_read(path)
    with evtk.open(path) as rec:
        assert rec.triggers() == dv_tr
        win = windows_from_triggers(rec.triggers(), skip_us=100)
        got = accumulate(rec, win)
    assert win.t_start_us.tolist() == (on_t + 100).tolist()
    on, off = _oracle(ev, win, (0, 320, 0, 240))
    np.testing.assert_array_equal(got.on, on)
    np.testing.assert_array_equal(got.off, off)


def test_accumulate_into_a_reused_dirty_buffer():
    ev = random_events(20_000, seed=9, sensor_size=(40, 30), span_us=50_000)
    win = Windows([0, 60_000, 10_000, 30_000], [10_000, 70_000, 20_000, 30_500], np.arange(4), "test")
    buf = np.full((2, 4, 30, 40), 7, np.int32)
    got = accumulate(ev, win, out=buf)
    on, off = _oracle(ev, win, (0, 40, 0, 30))
    np.testing.assert_array_equal(got.on, on)  # the window after the last event is zeroed too
    np.testing.assert_array_equal(got.off, off)
    assert np.shares_memory(got.on, buf)
    with pytest.raises(EvtkError, match="out must be"):
        accumulate(ev, win, out=np.zeros((2, 4, 30, 40), np.int64))


def test_linearize_inverts_the_count_model():
    from evtk.reconstruct import linearize

    theta = 0.2
    ratio = np.array([1.0, 2.0, 10.0, 1e6])
    n = np.floor(np.log(ratio) / theta + 1e-12)  # a noise-free slow pixel's ON count
    rel = linearize(n, theta_on=theta)
    # within one threshold below the true change, never above
    assert np.all(rel <= ratio - 1 + 1e-12) and np.all((rel + 1) * np.exp(theta) >= ratio)
    np.testing.assert_allclose(linearize([3], [3], theta_on=0.2), [0.0], atol=1e-15)
    per_pixel = linearize(np.array([5, 5]), theta_on=np.array([0.1, 0.2]))
    np.testing.assert_allclose(per_pixel, np.expm1([0.5, 1.0]))
    with pytest.raises(EvtkError, match="theta_on"):
        linearize([1], theta_on=0)
    with pytest.raises(EvtkError, match="beyond"):
        linearize([10_000], theta_on=0.2)


def test_combine_passes_against_the_signed_correlation():
    from scipy import signal

    from evtk.reconstruct import combine_passes
    from evtk.simulate import Simulation

    rng = np.random.default_rng(11)
    k = np.stack([rng.choice([-1, 0, 1], (3, 3)) for _ in range(2)])
    k[:, 1, 1] = 1
    f = np.stack([rng.choice([-1, 1], (8, 8)) for _ in range(3)])
    sim = Simulation(k, f, repeat=2, seed=1)
    per_capture = np.stack([sim.ideal(c) for c in range(len(sim.schedule))])
    combined, pairs = combine_passes(per_capture, sim.schedule)
    assert len(pairs) == 2 * 3 * 2
    for (ki, fi, _r), got in zip(pairs, combined):
        np.testing.assert_array_equal(got, signal.correlate2d(f[fi], k[ki], "full"))
    with pytest.raises(EvtkError, match="responses for a schedule"):
        combine_passes(per_capture[:-1], sim.schedule)


@pytest.mark.parametrize("stride", [1.0, 0.5, 0.25, 2.0])
def test_to_response_grid_recovers_the_ideal_response(stride):
    """Ideal optics (point sources, no leak): sensor light mapped back onto cells is the correlation."""
    from scipy import signal

    from evtk.optics import Bench, response_origin_px, response_region, screen_response
    from evtk.reconstruct import to_response_grid

    base = Bench(source_extent="point")
    # an origin that puts pixel edges on cell edges: pixel 100's footprint starts at cell 0
    o = 100 + (0.5 - stride / 2) / stride
    bench = base.replace(sensor_pitch_um=base.sensor_pitch_um * stride, origin_px=(o, o))
    rng = np.random.default_rng(3)
    k = rng.integers(0, 2, (3, 3))
    f = rng.integers(0, 2, (16, 16))
    region = response_region(bench, k.shape, f.shape)
    x0, x1, y0, y1 = region
    light = screen_response(k, f, bench, region, leak=False)
    origin = response_origin_px(bench, k.shape, f.shape)
    cells = to_response_grid(light, region, origin, 1 / bench.stride_eff, (18, 18))
    ideal = signal.correlate2d(f, k, "full")
    if stride <= 1:  # every cell is covered by pixels that see only it
        np.testing.assert_allclose(cells, ideal, atol=1e-9)
    else:  # each pixel sees 2x2 cells: every cell takes its pixel's mean of them
        padded = np.zeros((18, 18))
        padded[:18, :18] = ideal
        blocks = padded.reshape(9, 2, 9, 2).mean(axis=(1, 3))
        np.testing.assert_allclose(cells, np.kron(blocks, np.ones((2, 2))), atol=1e-9)


def test_downsample_block_and_area():
    from skimage.measure import block_reduce

    from evtk.reconstruct import downsample

    rng = np.random.default_rng(4)
    a = rng.random((3, 32, 48))
    np.testing.assert_allclose(downsample(a, (16, 16)), block_reduce(a, (1, 2, 3), np.mean))
    b = rng.random((14, 14))
    up = downsample(b, (16, 16))
    assert up.shape == (16, 16) and up.mean() == pytest.approx(b.mean())
    down = downsample(rng.random((50, 70)), (16, 16))
    assert down.shape == (16, 16)
    const = downsample(np.full((21, 13), 2.5), (16, 16))
    np.testing.assert_allclose(const, 2.5)
    with pytest.raises(EvtkError, match="size"):
        downsample(b, (0, 4))


def test_binarize_methods():
    from skimage.filters import threshold_otsu

    from evtk.reconstruct import binarize

    rng = np.random.default_rng(5)
    r = np.concatenate([rng.normal(0, 1, (2, 8, 8)), rng.normal(5, 1, (2, 8, 8))], axis=1)
    assert binarize(r, "sign").dtype == np.int8
    np.testing.assert_array_equal(binarize(r, "sign"), np.where(r >= 0, 1, -1))
    np.testing.assert_array_equal(binarize(r, 2.0), np.where(r >= 2.0, 1, -1))
    for i in range(2):
        np.testing.assert_array_equal(binarize(r, "mean")[i], np.where(r[i] >= r[i].mean(), 1, -1))
        np.testing.assert_array_equal(binarize(r, "otsu")[i], np.where(r[i] > threshold_otsu(r[i]), 1, -1))
    flat = np.zeros((4, 4))
    assert np.all(binarize(flat, "otsu") == 1) and np.all(binarize(flat, "mean") == 1)
    with pytest.raises(EvtkError, match="method"):
        binarize(r, "median")
    with pytest.raises(EvtkError, match="NaN"):
        binarize(np.full((2, 2), np.nan))


def test_binarize_splits_a_tie_the_same_way_whatever_the_rounding():
    """A value at its threshold goes to +1 (sign, mean, a number), and so does one a rounding off it either side."""
    from evtk.reconstruct import binarize

    below, above = np.nextafter(1.0, 0.0), np.nextafter(1.0, 2.0)
    for tie in (1.0, below, above):  # a response [[0, 2], [1, 1]]: its mean is 1, two values at it
        r = np.array([[[0.0, 2.0], [tie, 2.0 - tie]]])
        assert binarize(r, "mean").tolist() == [[[-1, 1], [1, 1]]], tie
        assert binarize(r, 1.0).tolist() == [[[-1, 1], [1, 1]]], tie
        # the same response shifted to a mean of 0: a zero summed in another order is +-1e-16
        assert binarize(r - 1.0, "sign").tolist() == [[[-1, 1], [1, 1]]], tie
    # a real difference, however small against the threshold's 1e-9 band, is not a tie
    assert binarize(np.array([[-1e-6, 1.0]]), "sign").tolist() == [[-1, 1]]
    assert binarize(np.array([[0.0, 0.0], [0.0, 0.0]]), "sign").tolist() == [[1, 1], [1, 1]]


def test_reconstruct_end_to_end_on_an_ideal_simulation(tmp_path):
    """Point sources, no shot noise, no threshold mismatch: the pipeline finds the correlation.

    The accuracy the device reaches with its default (realistic) optics and
    pixels is reported by the pipeline, not asserted here: see summary["error"].
    """
    from evtk.optics import Bench
    from evtk.reconstruct import reconstruct
    from evtk.sensor import SensorModel
    from evtk.simulate import Simulation

    rng = np.random.default_rng(0)
    k = rng.choice([-1, 1], (3, 3))
    f = rng.choice([-1, 1], (16, 16))
    ideal_sensor = SensorModel(shot_noise=False, background_rate_hz=0.0, theta_mismatch=0.0)
    sim = Simulation(k, f, bench=Bench(source_extent="point"), sensor=ideal_sensor, repeat=2, seed=1)
    path = tmp_path / "ideal.aedat4"
    sim.write(path)
    with evtk.open(path) as rec:
        r = reconstruct(rec, size=(16, 16))
        by_triggers = reconstruct(rec, window="triggers")
    # two flat fields, then two repeats of four passes
    assert r.summary["captures"] == 10 and r.summary["windows"] == 10 and r.pairs.tolist() == [[0, 0, 0], [0, 0, 1]]
    assert r.summary["flat_field_captures"] == 2
    assert r.cells.shape == (2, 14, 14) and r.responses.shape == (2, 16, 16) and r.binary.dtype == np.int8
    assert r.summary["error"]["correlation"] > 0.99
    np.testing.assert_array_equal(by_triggers.cells, r.cells)
    # the binary response agrees with the sign of the ideal wherever the ideal is clearly non-zero
    clear = np.abs(r.ideal) >= 2
    assert np.mean(np.sign(r.cells[clear]) == np.sign(r.ideal[clear])) > 0.98


def test_cli_reconstruct_outputs(tmp_path):
    import json

    from click.testing import CliRunner

    from evtk.cli import main
    from evtk.sensor import SensorModel
    from evtk.simulate import Simulation

    rng = np.random.default_rng(2)
    sim = Simulation(rng.choice([-1, 1], (3, 3)), rng.choice([-1, 1], (16, 16)), repeat=2, seed=3,
                     sensor=SensorModel(shot_noise=False))
    src = tmp_path / "sim.aedat4"
    sim.write(src)
    with evtk.open(src) as rec:
        from evtk.reconstruct import reconstruct

        lib = reconstruct(rec, size=(8, 8), binarize_method="mean")
    for out in ("r.npz", "r.h5"):
        res = CliRunner().invoke(main, ["reconstruct", str(src), "-o", str(tmp_path / out), "--size", "8x8",
                                        "--binarize", "mean", "--json", "--png", str(tmp_path / "sheet.png"), "--oracle"])
        assert res.exit_code == 0, res.output
        summary = json.loads(res.output)
        assert summary["responses"] == 2 and summary["size"] == [8, 8]
        assert summary["events_used"] + summary["events_dropped"] == summary["events_in_recording"]
        assert summary["error"]["correlation"] == pytest.approx(lib.summary["error"]["correlation"])
    from skimage import io as skio

    sheet = skio.imread(tmp_path / "sheet.png")
    assert sheet.ndim == 3 and sheet.shape[0] > 100 and sheet.shape[1] > 3 * 100  # 2 rows x 3 columns of panels
    z = np.load(tmp_path / "r.npz")
    np.testing.assert_array_equal(z["binary"], lib.binary)
    np.testing.assert_allclose(z["responses"], lib.responses)
    assert json.loads(str(z["summary"]))["reconstruction"]["windows"] == 10
    import h5py

    with h5py.File(tmp_path / "r.h5") as f:
        np.testing.assert_allclose(f["reconstruction/responses"][...], lib.responses)
        np.testing.assert_array_equal(f["reconstruction/pairs"][...], lib.pairs)
    # a bench recording without a schedule: triggers or a period, never the schedule
    bench = tmp_path / "bench.h5"
    evtk.write_events(bench, random_events(5000, seed=1, span_us=20_000), evtk.Triggers([100, 900], [R, F]))
    res = CliRunner().invoke(main, ["reconstruct", str(bench), "-o", str(tmp_path / "b.npz")])
    assert res.exit_code == 1 and "no schedule was given" in res.output and "--schedule S" in res.output
    res = CliRunner().invoke(main, ["reconstruct", str(bench), "-o", str(tmp_path / "b.npz"), "--window", "triggers",
                                    "--size", "4x4", "--json"])
    assert res.exit_code == 0, res.output
    assert json.loads(res.output)["windows"] == 1
    res = CliRunner().invoke(main, ["reconstruct", str(bench), "-o", str(tmp_path / "p.npz"), "--window",
                                    "period:5000", "--counts", "--json"])
    assert res.exit_code == 0, res.output
    assert json.loads(res.output)["windows"] == 3
    for bad, msg in ((["--window", "period:x"], "period:US"), (["--binarize", "median"], "--binarize"),
                     (["--size", "4by4"], "--size")):
        res = CliRunner().invoke(main, ["reconstruct", str(bench), "-o", str(tmp_path / "x.npz"), *bad])
        assert res.exit_code == 2 and msg in res.output  # malformed values are usage errors
    res = CliRunner().invoke(main, ["reconstruct", str(bench), "-o", str(tmp_path / "x.txt"), "--window", "triggers"])
    assert res.exit_code == 1 and ".npz" in res.output


def _fixed_window_events(period_us=1_000, n_w=6, seed=4):
    """Events over a 24x16 sensor spanning exactly ``n_w`` periods from t = 0, and their ON and OFF counts per
    period and pixel, counted here with numpy alone."""
    rng = np.random.default_rng(seed)
    n = 9_000
    t = np.sort(np.r_[0, rng.integers(0, n_w * period_us, n - 2), n_w * period_us - 1])
    x = rng.integers(0, 24, n)
    y = rng.integers(0, 16, n)
    p = (rng.random(n) < 0.55).astype(np.uint8)
    k = t // period_us
    on = np.zeros((n_w, 16, 24))
    off = np.zeros((n_w, 16, 24))
    np.add.at(on, (k[p == 1], y[p == 1], x[p == 1]), 1)
    np.add.at(off, (k[p == 0], y[p == 0], x[p == 0]), 1)
    ev = evtk.Events(t, x.astype(np.uint16), y.astype(np.uint16), p, (24, 16))
    return ev, on, off


def _block_means(v):
    """(windows, 16, 24) -> (windows, 4, 6): means of 4x4 blocks."""
    return v.reshape(len(v), 4, 4, 6, 4).mean(axis=(2, 4))


def test_fixed_windows_without_a_plan_are_net_counts(tmp_path):
    """Issue 30: nothing in the plan (fixed windows of a recording without a record) says how counts map to light:
    the responses are net counts ON - OFF, not exp(n theta) at a made-up theta = 0.2."""
    from click.testing import CliRunner

    from evtk.cli import main
    from evtk.reconstruct import reconstruct

    ev, on, off = _fixed_window_events()
    path = tmp_path / "fixed.h5"
    evtk.write_events(path, ev)
    want = _block_means(on - off)
    with evtk.open(path) as rec:
        for keep_pixels in (True, False):
            got = reconstruct(rec, window=("period", 1_000), size=(4, 6), keep_pixels=keep_pixels)
            np.testing.assert_allclose(got.responses, want, rtol=0, atol=1e-12)
            assert got.summary.linearization == "counts" and got.summary.linear is False
            np.testing.assert_array_equal(got.binary, np.where(want >= want.mean(axis=(1, 2), keepdims=True), 1, -1))
        # the same on windows cut by hand, through the stages alone
        win = windows_periodic(0, 6_000, 1_000)
        np.testing.assert_allclose(evtk.reconstruct.reconstruct_counts(accumulate(rec, win), None, size=(4, 6))
                                   .responses, want, rtol=0, atol=1e-12)
    res = CliRunner().invoke(main, ["reconstruct", str(path), "-o", str(tmp_path / "r.npz"), "--window",
                                    "period:1000", "--size", "4x6", "--json"])
    assert res.exit_code == 0, res.output
    assert json.loads(res.output)["linearization"] == "counts"
    np.testing.assert_allclose(np.load(tmp_path / "r.npz")["responses"], want, rtol=0, atol=1e-12)


@pytest.mark.parametrize("theta", [0.2, 0.05])
def test_fixed_windows_with_a_theta_given_are_exp_n_theta(tmp_path, theta):
    """A theta the user gives still linearises fixed windows by exp(n theta), as every fixed window did before."""
    from evtk.reconstruct import ReconstructOptions, reconstruct

    ev, on, off = _fixed_window_events()
    path = tmp_path / "fixed.h5"
    evtk.write_events(path, ev)
    want = _block_means(np.expm1(theta * on - theta * off))
    with evtk.open(path) as rec:
        for keep_pixels in (True, False):
            got = reconstruct(rec, options=ReconstructOptions(window=("period", 1_000), size=(4, 6), theta=theta),
                              keep_pixels=keep_pixels)
            np.testing.assert_allclose(got.responses, want, rtol=1e-12, atol=1e-12)
            assert got.summary.linearization == "exp(n theta)" and got.summary.theta_on == theta
    from click.testing import CliRunner

    from evtk.cli import main

    out = tmp_path / "r.npz"
    res = CliRunner().invoke(main, ["reconstruct", str(path), "-o", str(out), "--window", "period:1000", "--size",
                                    "4x6", "--theta", str(theta), "--json"])
    assert res.exit_code == 0, res.output
    assert json.loads(res.output)["linearization"] == "exp(n theta)"
    np.testing.assert_allclose(np.load(out)["responses"], want, rtol=1e-12, atol=1e-12)
    for bad, code in (("0", 2), ("-0.2", 2), ("nan", 1), ("inf", 1)):
        res = CliRunner().invoke(main, ["reconstruct", str(path), "-o", str(out), "--window", "period:1000",
                                        "--theta", bad])
        assert res.exit_code == code and "theta" in res.output and "Traceback" not in res.output, res.output
    for bad in (float("nan"), -1.0, "0.2x"):
        with pytest.raises(EvtkError, match="theta must be a positive finite number"):
            ReconstructOptions(theta=bad)


def test_deblur_undoes_the_footprint_on_exact_light():
    """The footprint model inverts the optics exactly: light itself, deblurred, is the correlation."""
    from scipy import signal

    from evtk.optics import Bench, response_origin_px, response_region, screen_response
    from evtk.reconstruct import footprint_matrix, to_response_grid

    bench = Bench(source_extent="area", psf_sigma_um=60.0)
    rng = np.random.default_rng(8)
    k = rng.integers(0, 2, (3, 3))
    f = rng.integers(0, 2, (16, 16))
    region = response_region(bench, k.shape, f.shape)
    light = screen_response(k, f, bench, region, leak=False)
    ox, oy = response_origin_px(bench, k.shape, f.shape)
    cells = to_response_grid(light, region, (ox, oy), 1.0, (18, 18))
    assert np.abs(cells - signal.correlate2d(f, k, "full")).max() > 0.1  # blurred
    my = footprint_matrix(bench, oy, region[2], region[3], 18, 1.0)
    mx = footprint_matrix(bench, ox, region[0], region[1], 18, 1.0)
    restored = np.linalg.solve(my, np.linalg.solve(mx, cells.T).T)
    np.testing.assert_allclose(restored, signal.correlate2d(f, k, "full"), atol=1e-8)


def test_count_curve_inversion_restores_the_scale(tmp_path):
    """Refractory compression makes exp(n*theta) underestimate light; inverting the model does not."""
    from evtk.optics import Bench
    from evtk.reconstruct import count_curve, reconstruct
    from evtk.sensor import SensorModel
    from evtk.simulate import Simulation

    rng = np.random.default_rng(0)
    sim = Simulation(rng.choice([-1, 1], (3, 3)), rng.choice([-1, 1], (16, 16)), bench=Bench(source_extent="point"),
                     sensor=SensorModel(shot_noise=False, background_rate_hz=0.0, theta_mismatch=0.0), seed=1)
    path = tmp_path / "s.aedat4"
    sim.write(path)
    meta = sim.metadata()["simulation"]
    u, n = count_curve(meta)
    assert np.all(np.diff(n) >= 0) and n[0] == 0 and n[-1] > 20
    # compression: bright steps give fewer counts than whole thresholds
    assert n[-1] < np.floor(u[-1] / sim.sensor.theta_on)
    with evtk.open(path) as rec:  # without the flat field, which would absorb the compression too
        model = reconstruct(rec, flat_field=False)
        simple = reconstruct(rec, theta=sim.sensor.theta_on, flat_field=False)
    scale = lambda r: (r.cells.ravel() @ r.ideal.ravel()) / (r.cells.ravel() @ r.cells.ravel())  # noqa: E731
    assert abs(scale(model) - 1) < 0.15 < abs(scale(simple) - 1)
    assert model.summary["error"]["correlation"] > 0.99


def test_count_curve_is_shared_only_between_equal_settings():
    """The cached curve is the one a fresh computation gives, cannot be altered by a caller, and a different
    threshold, window or numpy-typed record gets its own."""
    import copy

    from evtk.reconstruct import _count_curve, count_curve
    from evtk.simulate import Simulation

    meta = Simulation(np.ones((3, 3)), np.ones((16, 16)), seed=1).metadata()["simulation"]
    u, n = count_curve(meta)
    with pytest.raises(ValueError):
        n[0] = 5
    _count_curve.cache_clear()
    u2, n2 = count_curve(copy.deepcopy(meta))
    assert u2 is not u and np.array_equal(u, u2) and np.array_equal(n, n2)
    assert count_curve(meta)[1] is n2  # shared
    other = copy.deepcopy(meta)
    other["sensor"]["theta_on"] = np.float64(meta["sensor"]["theta_on"] * 2)  # numpy scalars are fine in the key
    assert count_curve(other)[1][-1] < n[-1]
    assert count_curve(meta, length_us=meta["window_us"] / 4)[1][-1] < n[-1]


def test_flat_field_gain_finds_each_pixels_threshold(tmp_path):
    """Threshold mismatch is a per-pixel gain on counts; the flat fields measure it.

    Oracle: the simulated device's own thresholds. Mismatched, noise-free
    pixels reconstruct far better calibrated than not.
    """
    from evtk.optics import Bench
    from evtk.reconstruct import flat_field_gain, reconstruct
    from evtk.sensor import SensorModel
    from evtk.simulate import Simulation

    rng = np.random.default_rng(5)
    k, f = rng.choice([-1, 1], (3, 3)), rng.choice([-1, 1], (16, 16))
    sensor = SensorModel(shot_noise=False, background_rate_hz=0.0)  # thresholds 0.2 +- 0.02
    sim = Simulation(k, f, bench=Bench(source_extent="point"), sensor=sensor, seed=2, flat_field=3)
    path = tmp_path / "m.aedat4"
    sim.write(path)
    with evtk.open(path) as rec:
        cal = reconstruct(rec)
        raw = reconstruct(rec, flat_field=False)
    x0, x1, y0, y1 = sim.region
    yy, xx = np.mgrid[y0:y1, x0:x1]
    true_gain = sim._theta_on[yy * sim.bench.sensor_width + xx] / sensor.theta_on
    net = cal.counts.on[:3].astype(float) - cal.counts.off[:3]
    from evtk.reconstruct import _expected_flat_counts, count_curve

    meta = sim.metadata()["simulation"]
    expected = _expected_flat_counts(meta, sim.bench, sim.region, count_curve(meta), 0.2)
    gain = flat_field_gain(net, expected)
    lit = expected >= 3  # the rest keep gain 1
    assert lit.mean() > 0.5 and np.all(gain[~lit] == 1)
    assert np.corrcoef(gain[lit], true_gain[lit])[0, 1] > 0.9
    err, spread = np.abs(gain[lit] - true_gain[lit]), np.abs(true_gain[lit] - 1)
    assert np.median(err) < 0.3 * np.median(spread)
    assert cal.summary["flat_field_captures"] == 3 and raw.summary["flat_field_captures"] == 0
    assert cal.summary["error"]["correlation"] > 0.97 > 0.9 > raw.summary["error"]["correlation"]
    assert cal.summary["error"]["nrmse_range"] < 0.5 * raw.summary["error"]["nrmse_range"]
    # bad input
    with pytest.raises(EvtkError, match="at least one"):
        flat_field_gain(np.zeros((0, 2)), np.ones(2))
    with pytest.raises(EvtkError, match="shape"):
        flat_field_gain(np.ones((1, 2)), np.ones(3))
    # silent or dim pixels keep gain 1; gains are clipped
    np.testing.assert_array_equal(flat_field_gain(np.array([[0.0, 10.0, 1.0, 100.0]]), np.array([20.0, 2.0, 20.0, 20.0])),
                                  [1.0, 1.0, 2.0, 0.5])


def test_reconstruct_counts_from_the_fast_path_equals_the_recording(tmp_path):
    """The simulator's exact count path and the recording give the same counts, hence the same responses
    (the count path has no event times: compare with the recording's reconstruction from counts alone)."""
    from evtk.reconstruct import WindowCounts, reconstruct, reconstruct_counts
    from evtk.sensor import SensorModel
    from evtk.simulate import Simulation

    rng = np.random.default_rng(4)
    sim = Simulation(rng.choice([-1, 1], (3, 3)), rng.choice([-1, 1], (16, 16)), repeat=2, seed=7,
                     sensor=SensorModel(shot_noise=False, background_rate_hz=0.0))
    path = tmp_path / "r.aedat4"
    sim.write(path)
    with evtk.open(path) as rec:
        a = reconstruct(rec, size=(8, 8), timing=False)
        timed = reconstruct(rec, size=(8, 8))
    b = reconstruct_counts(WindowCounts.from_capture_counts(sim.responses(method="exact")),
                           sim.metadata()["simulation"], size=(8, 8))
    assert a.summary["linearization"] == b.summary["linearization"] == "pixel model"
    assert timed.summary["linearization"] == "pixel model and event times" and timed.summary["timed_share"] > 0.5
    with pytest.raises(EvtkError, match="no event times"):
        reconstruct_counts(b.counts, sim.metadata()["simulation"], timing=True)
    np.testing.assert_array_equal(a.counts.on, b.counts.on)
    np.testing.assert_array_equal(a.counts.off, b.counts.off)
    np.testing.assert_allclose(b.cells, a.cells)
    np.testing.assert_array_equal(b.binary, a.binary)
    assert b.summary["error"] == a.summary["error"]
    with pytest.raises(EvtkError, match="crop"):
        reconstruct_counts(b.counts, sim.metadata()["simulation"], crop="middle")


def test_linearize_by_table_equals_expm1_per_pixel():
    """Integer counts are looked up in a table of their distinct values: the same numbers as expm1 per pixel."""
    from evtk.reconstruct import linearize

    rng = np.random.default_rng(2)
    on = rng.integers(0, 40, (30, 20, 20)).astype(np.int32)
    off = rng.integers(0, 25, (30, 20, 20)).astype(np.int32)
    for a, b in ((0.2, 0.2), (0.17, 0.31)):
        want = np.expm1(on.astype(np.float64) * a - off.astype(np.float64) * b)
        assert np.array_equal(linearize(on, off, a, b), want)
        assert np.array_equal(linearize(on.astype(np.float64), off, a, b), want)  # no table for floats
    assert np.array_equal(linearize(on, None, 0.2), np.expm1(on * 0.2))
    wide = on * 3000  # 117,001 x 25 distinct pairs, too many for a table: expm1 per pixel
    assert np.array_equal(linearize(wide, off, 0.005), np.expm1(wide * 0.005 - off * 0.005))
    big = np.full((64, 64), 3600, np.int32)
    with pytest.raises(EvtkError, match="exp\\(700\\)"):
        linearize(big, np.zeros_like(big), 0.2)


def test_reconstruction_files_read_back_and_describe_themselves(tmp_path):
    """Both containers round-trip every array and the summary; info describes responses (not "events 0"),
    enob on the file equals enob on the recording, and damaged files are one FormatError each."""
    import h5py
    from click.testing import CliRunner

    from evtk.cli import main
    from evtk.io.reconstruction import is_reconstruction
    from evtk.reconstruct import load_reconstruction, reconstruct
    from evtk.simulate import Simulation

    rec_path = tmp_path / "run.aedat4"
    Simulation([[1, 0, 1], [0, 1, 0], [1, 0, 1]], np.eye(6, dtype=int), repeat=3, seed=2).write(rec_path)
    with evtk.open(rec_path) as rec:
        result = reconstruct(rec)
    for name in ("out.h5", "out.npz"):
        res = CliRunner().invoke(main, ["reconstruct", str(rec_path), "-o", str(tmp_path / name), "--oracle"])
        assert res.exit_code == 0, res.output
        assert is_reconstruction(tmp_path / name)
        back = load_reconstruction(tmp_path / name)
        for key in ("responses", "binary", "cells", "ideal", "pairs"):
            assert np.array_equal(getattr(back, key), getattr(result, key)), key
        assert np.array_equal(back.counts.on, result.counts.on) and np.array_equal(back.counts.off, result.counts.off)
        assert back.summary["error"] == pytest.approx(result.summary["error"])
        assert back.summary["source"] == str(rec_path) and back.summary["sensor_size"] == list(rec.sensor_size)
        info = CliRunner().invoke(main, ["info", str(tmp_path / name)])
        assert info.exit_code == 0 and "responses    3 of 16x16" in info.output and "events" not in info.output
        js = CliRunner().invoke(main, ["info", str(tmp_path / name), "--json"])
        assert json.loads(js.output)["scenes"] == 1
        a = CliRunner().invoke(main, ["enob", str(tmp_path / name), "--json"])
        b = CliRunner().invoke(main, ["enob", str(rec_path), "--json"])
        assert a.exit_code == 0 and json.loads(a.output)["scenes"] == json.loads(b.output)["scenes"]
    assert not is_reconstruction(rec_path)
    # damaged: an array missing, a shape that does not match, NaN in a response
    with h5py.File(tmp_path / "out.h5", "a") as f:
        del f["reconstruction/off"]
    with pytest.raises(evtk.FormatError, match="no off"):
        load_reconstruction(tmp_path / "out.h5")
    arrays = dict(np.load(tmp_path / "out.npz"))
    for key, value, msg in (("pairs", arrays["pairs"][:, :2], "pairs must be"),
                            ("responses", np.full_like(arrays["responses"], np.nan), "NaN"),
                            ("on", arrays["on"][:2], "do not match")):
        bad = dict(arrays, **{key: value})
        np.savez(tmp_path / "bad.npz", **bad)
        with pytest.raises(evtk.FormatError, match=msg):
            load_reconstruction(tmp_path / "bad.npz")
    res = CliRunner().invoke(main, ["info", str(tmp_path / "bad.npz")])
    assert res.exit_code == 1 and "do not match" in res.output


def test_binarisation_default_follows_the_sign_of_the_responses(tmp_path):
    """auto: an unsigned kernel on 0/1 features is split at each response's mean (sign would give +1 almost
    everywhere); a signed run by sign; the summary names the rule used, and the CLI and demo agree."""
    from evtk.reconstruct import binarize, reconstruct
    from evtk.simulate import Simulation, default_features

    f = default_features()
    for signed, rule in ((False, "mean"), (True, "sign")):
        k = np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]])
        sim = Simulation(np.where(k > 0, 1, -1) if signed else k, np.where(f > 0, 1, -1) if signed else f, seed=1)
        path = tmp_path / f"s{signed}.h5"
        sim.write(path)
        with evtk.open(path) as rec:
            r = reconstruct(rec)
        assert r.summary["binarize"] == rule
        assert np.array_equal(r.binary, binarize(r.responses, rule))
        ones = float(np.mean(r.binary > 0))
        assert 0.2 < ones < 0.8, ones
        if not signed:
            assert np.mean(binarize(r.responses, "sign") > 0) > 0.85  # why sign is not the rule here


def test_the_summary_is_typed_and_still_reads_as_a_dict(tmp_path):
    """Issue 30: every route returns a ReconstructionSummary, whose entries are typed attributes; it reads and
    writes as the dict it was (an entry the route did not set is a KeyError, its attribute None), and a file
    gives back the same entries, the file's own metadata kept beside them."""
    from evtk.reconstruct import ReconstructionSummary, load_reconstruction, reconstruct, save_reconstruction
    from evtk.simulate import Simulation

    Simulation([[1, 0, 1], [0, 1, 0], [1, 0, 1]], np.eye(6, dtype=int), repeat=2, seed=2).write(tmp_path / "r.h5")
    with evtk.open(tmp_path / "r.h5") as rec:
        result = reconstruct(rec)
    s = result.summary
    assert isinstance(s, ReconstructionSummary)
    assert s.windows == s["windows"] == len(result.counts.windows) and s.captures == s["captures"]
    assert s.error == s["error"] and s.error["correlation"] > 0.9 and s.linearization == s["linearization"]
    assert s.match is None and "match" not in s and s.get("match", "absent") == "absent"
    with pytest.raises(KeyError):
        s["match"]
    s["route"] = "by hand"  # written by key, read as an attribute
    s.update(note_of_mine=1)  # an entry that is not an attribute is kept aside
    assert s.route == "by hand" and s.extra == {"note_of_mine": 1} and dict(s)["note_of_mine"] == 1
    plain = s.to_dict()
    assert type(plain) is dict and json.loads(json.dumps(plain)) == plain
    assert list(ReconstructionSummary.from_dict(plain).to_dict().items()) == list(plain.items())
    save_reconstruction(tmp_path / "out.npz", result, rec.sensor_size)
    back = load_reconstruction(tmp_path / "out.npz").summary
    assert isinstance(back, ReconstructionSummary) and back.windows == s.windows and back.route == "by hand"
    assert back.extra["sensor_size"] == list(rec.sensor_size) and back.extra["note_of_mine"] == 1


def test_one_entry_takes_its_route_from_the_plan(tmp_path):
    """Issue 30: ``reconstruct(rec, plan, options)`` is the one entry. The oracle is the plan read from the
    simulation record (the same numbers as the recording's own record); a bench plan (the schedule alone, as
    a bench has it) runs the calibrated route (its pixel model fitted to the run's level captures) or, asked
    for, exp(n theta) with no model; settings a bench plan cannot honour are one clear error each."""
    from evtk.plan import Plan
    from evtk.reconstruct import ReconstructOptions, reconstruct, schedule_of_record
    from evtk.simulate import Simulation

    rng = np.random.default_rng(4)
    Simulation(rng.choice([-1, 1], (3, 3)), rng.choice([-1, 1], (16, 16)), seed=4, levels=6,
               flat_field=2).write(tmp_path / "r.h5")
    with evtk.open(tmp_path / "r.h5") as rec:
        record = rec.metadata["simulation"]
        own = reconstruct(rec, options=ReconstructOptions(size=(8, 8)))
        oracle = reconstruct(rec, Plan.from_record(record), ReconstructOptions(size=(8, 8)))
        bench_plan = schedule_of_record(record)
        fitted = reconstruct(rec, bench_plan)
        plain = reconstruct(rec, bench_plan, linearization="exp(n theta)")
        for bad, match in (({"window": "triggers"}, "bench plan's windows"), ({"theta": 0.3}, "leave out"),
                           ({"linearization": "cubic"}, "linearization must be"), ({"colour": 1}, "no setting")):
            with pytest.raises(EvtkError, match=match):
                reconstruct(rec, bench_plan, **bad)
        with pytest.raises(EvtkError, match="leave linearization out"):
            reconstruct(rec, Plan.from_record(record), linearization="table")
    assert np.array_equal(oracle.responses, own.responses) and oracle.responses.shape[1:] == (8, 8)
    assert bench_plan.record is None and bench_plan.region is None and Plan.from_record(record).record is not None
    assert fitted.summary.pixel_model_from == "the run's own level captures" and fitted.summary.match["matched"] > 0
    assert fitted.summary.linearization.startswith("pixel model")
    assert plain.summary.linearization == "exp(n theta)" and plain.summary.pixel_model is None
    assert fitted.summary.error["correlation"] > plain.summary.error["correlation"] - 0.05
    import evtk.reconstruct as R

    assert not any(hasattr(R, n) for n in ("reconstruct_bench", "reconstruct_calibrated", "fitted_record"))
