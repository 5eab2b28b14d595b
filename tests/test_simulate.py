"""Simulated runs: passes, schedule, recordings dv-processing opens, fast path agreement, extremes, CLI."""

import json

import numpy as np
import pytest
from click.testing import CliRunner
from scipy import signal

import evtk
from evtk import EvtkError, TriggerKind
from evtk.cli import main
from evtk.optics import Bench
from evtk.sensor import SensorModel
from evtk.simulate import METADATA_KEY, Schedule, Simulation, load_patterns, split_passes

K3 = np.array([[1, 0, 1], [0, 1, 0], [1, 0, 1]])


def _features(seed=0, shape=(16, 16), signed=False):
    rng = np.random.default_rng(seed)
    return rng.choice([-1, 1] if signed else [0, 1], shape)


def test_split_passes_recombine_to_the_signed_response():
    rng = np.random.default_rng(1)
    for _ in range(20):
        k = rng.choice([-1, 0, 1], (3, 3))
        f = rng.choice([-1, 0, 1], (8, 8))
        passes = split_passes(k, f)
        total = sum(ks * fs * signal.correlate2d(fp, kp, "full") for ks, fs, kp, fp in passes)
        if not passes:
            assert not k.any() or not f.any()
            continue
        np.testing.assert_array_equal(total, signal.correlate2d(f, k, "full"))
        for _, _, kp, fp in passes:
            assert kp.any() and fp.any() and set(np.unique(kp)) <= {0, 1}
    # an unsigned pair is one pass; a kernel without negative part is two
    assert len(split_passes(K3, _features())) == 1
    assert [(a, b) for a, b, _, _ in split_passes(K3, _features(signed=True))] == [(1, 1), (1, -1)]


def test_schedule_triggers_and_metadata():
    k = np.stack([K3, -K3 + (K3 == 0)])  # two kernels, the second signed
    f = _features(2, signed=True)
    sim = Simulation(k, f, window_us=500, settle_us=700, repeat=2, start_us=1000, seed=3)
    s = sim.schedule
    assert len(s) == 2 + 2 * (2 + 4)
    # two flat fields first: every mirror on, the brightest light the bench gives
    assert s.kernel_id[:2].tolist() == [-1, -1] and s.features_id[:2].tolist() == [-1, -1]
    assert np.all(s.kernel_id[2:] >= 0)
    np.testing.assert_array_equal(sim.ideal(0), signal.correlate2d(np.ones((16, 16)), np.ones((3, 3)), "full"))
    assert len(Simulation(k, f, flat_field=0).schedule) == 2 + 4
    assert s.t_on_us[0] == 1000 + 700
    np.testing.assert_array_equal(np.diff(s.t_on_us), 1200)
    np.testing.assert_array_equal(s.t_off_us - s.t_on_us, 500)
    tr = sim.triggers()
    assert np.array_equal(tr.t[0::2], s.t_on_us) and np.array_equal(tr.t[1::2], s.t_off_us)
    assert set(tr.kind[0::2]) == {TriggerKind.EXTERNAL_SIGNAL_RISING_EDGE}
    assert set(tr.kind[1::2]) == {TriggerKind.EXTERNAL_SIGNAL_FALLING_EDGE}
    meta = json.loads(json.dumps(sim.metadata()))[METADATA_KEY]
    s2 = Schedule.from_dict(meta["schedule"])
    for col in Schedule._COLUMNS:
        np.testing.assert_array_equal(getattr(s2, col), getattr(s, col))
    assert Bench.from_dict({**meta["bench"], "origin_px": None}) == sim.bench
    assert SensorModel.from_dict(meta["sensor"]) == sim.sensor
    # ground truth: each pass, and the signed pair it combines into
    for c in range(2, len(s)):
        kp = (k[s.kernel_id[c]] * s.kernel_sign[c] > 0).astype(int)
        fp = (f * s.features_sign[c] > 0).astype(int)
        np.testing.assert_array_equal(sim.ideal(c), signal.correlate2d(fp, kp, "full"))
    np.testing.assert_array_equal(sim.ideal_pair(1, 0), signal.correlate2d(f, k[1], "full"))


@pytest.mark.parametrize("ext", [".aedat4", ".h5"])
def test_written_recording_opens_in_evtk_and_matches_events(tmp_path, ext):
    sim = Simulation(K3, _features(4), repeat=2, seed=5)
    ev = sim.events()
    assert len(ev) > 1000 and ev.is_sorted
    path = tmp_path / f"run{ext}"
    summary = sim.write(path)
    assert summary["events"] == len(ev)
    with evtk.open(path) as rec:
        got = rec.events()
        assert got == ev  # deterministic for the seed, streamed in batches
        assert rec.triggers() == sim.triggers()
        meta = rec.metadata[METADATA_KEY]
        assert meta["seed"] == 5 and meta["window_us"] == sim.window_us
        assert meta["kernels"] == [K3.tolist()]
    assert not list(tmp_path.glob("*.evtk-partial"))


def test_dv_processing_opens_the_simulated_recording(tmp_path):
    dv = pytest.importorskip("dv_processing")
    sim = Simulation(K3, _features(6), repeat=2, seed=7)
    path = tmp_path / "run.aedat4"
    sim.write(path)
    ev = sim.events()
    rec = dv.io.MonoCameraRecording(str(path))
    assert rec.getEventResolution() == (320, 240)
    n, ts = 0, []
    while rec.isRunning():
        batch = rec.getNextEventBatch()
        if batch is None:
            break
        n += batch.size()
        ts.append(batch.timestamps())
    assert n == len(ev)
    np.testing.assert_array_equal(np.concatenate(ts), ev.t)
    trig = []
    while True:
        b = rec.getNextTriggerBatch()
        if b is None:
            break
        trig += [(t.timestamp, int(t.type)) for t in b]
    tr = sim.triggers()
    assert trig == list(zip(tr.t.tolist(), tr.kind.tolist()))


def _window_counts(ev, sim, region):
    """ON/OFF counts per capture window over region, accumulated straight from the events."""
    x0, x1, y0, y1 = region
    s = sim.schedule
    on = np.zeros((len(s), y1 - y0, x1 - x0), int)
    off = np.zeros_like(on)
    for c in range(len(s)):
        w = ev.between(int(s.t_on_us[c]), int(s.t_off_us[c]))
        keep = (w.x >= x0) & (w.x < x1) & (w.y >= y0) & (w.y < y1)
        for arr, pol in ((on, 1), (off, 0)):
            sel = keep & (w.p == pol)
            np.add.at(arr[c], (w.y[sel] - y0, w.x[sel] - x0), 1)
    return on, off


def test_fast_path_equals_event_path_without_noise():
    quiet = SensorModel(shot_noise=False, background_rate_hz=0.0)
    sim = Simulation(K3, _features(8, signed=True), sensor=quiet, repeat=2, seed=1)
    r = sim.responses(method="exact")
    on, off = _window_counts(sim.events(), sim, r.region)
    np.testing.assert_array_equal(r.on, on)
    np.testing.assert_array_equal(r.off, off)
    assert r.on.sum() > 0


def test_fast_path_agrees_statistically_with_event_path():
    """Per-pixel mean and variance over 60 repeats (stated tolerance: see asserts)."""
    f = _features(9)
    n_rep = 60
    ev_sim = Simulation(K3, f, repeat=n_rep, seed=11, sensor=SensorModel(background_rate_hz=50.0))
    # the same camera (seed: threshold mismatch), an independent trial (noise_seed)
    fast_sim = Simulation(K3, f, repeat=n_rep, seed=11, noise_seed=12, sensor=SensorModel(background_rate_hz=50.0))
    assert fast_sim.settle_us >= fast_sim.recommended_settle_us()  # so "auto" is the count table
    fast = fast_sim.responses()
    on, _ = _window_counts(ev_sim.events(), ev_sim, fast.region)
    m_ev, m_fast = on.mean(0), fast.on.mean(0)
    v_ev, v_fast = on.var(0, ddof=1), fast.on.var(0, ddof=1)
    lit = m_ev > 1
    assert lit.sum() > 100
    # means: |difference| within 4 standard errors at 99 % of pixels, and no overall bias beyond 2 %
    se = np.sqrt((v_ev + v_fast) / n_rep) + 1e-9
    assert np.mean(np.abs(m_ev - m_fast) <= 4 * se) >= 0.99
    assert m_fast[lit].mean() == pytest.approx(m_ev[lit].mean(), rel=0.02)
    # variances: pooled over lit pixels within 15 %
    assert v_fast[lit].mean() == pytest.approx(v_ev[lit].mean(), rel=0.15)
    # the threshold mismatch makes pixels differ; both paths see the same pattern of differences
    assert np.corrcoef(m_ev[lit], m_fast[lit])[0, 1] > 0.9


def test_response_follows_the_light():
    """Brighter pixels of the ideal response get more ON events in their window."""
    sim = Simulation(K3, _features(13), repeat=20, seed=2)
    r = sim.responses()
    x0, x1, y0, y1 = r.region
    light = sim.pass_response(0, r.region)
    mean_on = r.on.mean(0)
    from scipy import stats

    lit = light > 0.05
    # thresholds scatter from pixel to pixel: compare with each pixel's log step in its own thresholds
    theta = sim._theta_on.reshape(240, 320)[y0:y1, x0:x1]
    steps = np.log(sim._rate(light) / sim.blank_rate_e_per_s) / theta
    assert stats.spearmanr(steps[lit], mean_on[lit]).statistic > 0.95
    assert mean_on[light > 0.8 * light.max()].mean() > mean_on[lit & (light < 0.2 * light.max())].mean() + 5


@pytest.mark.parametrize("scale", [0.0, 1e-6, 1e-3, 1.0, 1e3, 1e6])
@pytest.mark.parametrize("k,f", [(np.zeros((3, 3)), np.ones((16, 16))), (np.ones((3, 3)), np.ones((16, 16))),
                                 (np.ones((1, 1)), np.eye(16)), (K3, np.zeros((16, 16)))])
def test_extreme_light_and_patterns(scale, k, f):
    bench = Bench()
    bench = bench.replace(power_mw=bench.power_mw * scale)
    if not k.any() or not f.any():
        with pytest.raises(EvtkError, match="nothing to show"):
            Simulation(k, f, bench=bench)
        return
    sim = Simulation(k, f, bench=bench, seed=1)
    ev = sim.events()
    assert ev.is_sorted and np.all(ev.t >= sim.start_us) and np.all(ev.t <= sim.end_us)
    span_us = sim.end_us - sim.start_us
    per_pixel = np.bincount(ev.y.astype(np.int64) * 320 + ev.x, minlength=320 * 240)
    # the refractory period bounds every pixel (plus its background activity, a handful at most)
    assert per_pixel.max() <= span_us / sim.sensor.refractory_us + 10
    r = sim.responses()
    assert np.all(r.on >= 0) and np.all(np.isfinite(r.on))
    assert sim.settle_us >= sim.bench.min_window_us


def test_timestamps_near_the_int64_limit():
    for start in (2**62, 2**63 - 1 - 12_000, -(2**60)):
        sim = Simulation(K3, _features(1), start_us=start, seed=1, settle_us=2000)
        ev = sim.events()
        assert len(ev) > 100 and ev.t.min() >= start and ev.t.max() <= sim.end_us and ev.is_sorted
        assert np.array_equal(np.diff(ev.t) >= 0, np.ones(len(ev) - 1, bool))
    with pytest.raises(EvtkError, match="int64"):
        Simulation(K3, _features(1), start_us=2**63 - 10)


def test_determinism():
    a = Simulation(K3, _features(3), repeat=2, seed=42).events()
    b = Simulation(K3, _features(3), repeat=2, seed=42).events()
    c = Simulation(K3, _features(3), repeat=2, seed=43).events()
    assert a == b and not a == c


def test_streaming_batches_are_time_ordered_and_bounded():
    sim = Simulation(K3, _features(3), repeat=10, seed=1)
    chunks = list(sim.iter_events(batch_captures=3))
    assert len(chunks) == 4
    for a, b in zip(chunks, chunks[1:]):
        assert a.t[-1] <= b.t[0]
    # each batch covers its own captures only
    period = sim.window_us + sim.settle_us
    for i, ch in enumerate(chunks[1:], start=1):
        assert ch.t[0] >= sim.schedule.t_on_us[3 * i] - 1 and ch.t[-1] < sim.schedule.t_on_us[3 * i] + 3 * period


def test_long_batches_sort_without_a_bin_per_microsecond(monkeypatch):
    """A batch spanning more than the counting sort's bins (very long settles) is sorted by a stable argsort
    instead: the same events in the same order."""
    import evtk.simulate.events as es

    sim = Simulation(K3, _features(3), repeat=3, seed=5)
    counting = sim.events()
    monkeypatch.setattr(es, "_COUNTING_SORT_MAX_US", 1000)
    assert sim.window_us + sim.settle_us > 1000
    assert sim.events() == counting and counting.is_sorted and len(counting) > 1000


@pytest.mark.parametrize("kwargs,match", [
    ({"window_us": 100}, "eq. 7"),
    ({"window_us": 0}, "window_us"),
    ({"settle_us": 0}, "settle_us"),
    ({"repeat": 0}, "repeat"),
    ({"seed": -1}, "seed"),
    ({"window_us": 1.5e3 + 0.5}, "whole"),
])
def test_invalid_parameters(kwargs, match):
    with pytest.raises(EvtkError, match=match):
        Simulation(K3, _features(), **kwargs)


def test_invalid_patterns():
    with pytest.raises(EvtkError, match="-1, 0 and 1"):
        Simulation(K3 * 2, _features())
    with pytest.raises(EvtkError, match="kernel DMD"):
        Simulation(np.ones((300, 300)), _features())
    with pytest.raises(EvtkError, match="shape"):
        Simulation(np.ones((2, 2, 2, 2)), _features())
    with pytest.raises(EvtkError, match="positive"):
        Simulation(K3, _features(), bench=Bench(u_mm=0))


def test_load_patterns(tmp_path):
    assert load_patterns("101010101", "kernel").tolist() == [[1, 0, 1], [0, 1, 0], [1, 0, 1]]
    with pytest.raises(EvtkError, match="square"):
        load_patterns("1010", "kernel") if False else load_patterns("10101", "kernel")
    np.save(tmp_path / "f.npy", _features())
    assert load_patterns(tmp_path / "f.npy", "features").shape == (16, 16)
    from skimage import io as skio

    img = (np.kron(_features(), np.ones((2, 2))) * 255).astype(np.uint8)
    skio.imsave(tmp_path / "f.png", img, check_contrast=False)
    np.testing.assert_array_equal(load_patterns(tmp_path / "f.png", "features"), img > 127)
    (tmp_path / "bad.png").write_bytes(b"not a png")
    with pytest.raises(EvtkError, match="bad.png"):
        load_patterns(tmp_path / "bad.png", "features")


def test_cli_simulate(tmp_path):
    out = tmp_path / "sim.aedat4"
    np.save(tmp_path / "f.npy", _features(5))
    bench = tmp_path / "bench.toml"
    bench.write_text("power_mw = 40.0\n[sensor]\nbackground_rate_hz = 0.0\n")
    res = CliRunner().invoke(main, ["simulate", "--kernel-bits", "101010101", "--features", str(tmp_path / "f.npy"),
                                    "--repeat", "2", "--bench", str(bench), "--seed", "3", "-o", str(out), "--json",
                                    "--save-bench", str(tmp_path / "used.json")])
    assert res.exit_code == 0, res.output
    summary = json.loads(res.output)
    assert summary["captures"] == 2 + 6 + 2 and summary["stride_eff"] == pytest.approx(1.0)
    with evtk.open(out) as rec:
        assert len(rec.events()) == summary["events"]
        meta = rec.metadata[METADATA_KEY]
        assert meta["bench"]["power_mw"] == 40.0 and meta["sensor"]["background_rate_hz"] == 0.0
    used = json.loads((tmp_path / "used.json").read_text())
    assert used["power_mw"] == 40.0 and used["sensor"]["background_rate_hz"] == 0.0
    # the same run from the library gives the same events
    sim = Simulation(K3, _features(5), bench=Bench(power_mw=40.0), sensor=SensorModel(background_rate_hz=0.0),
                     repeat=2, seed=3, levels=6)
    with evtk.open(out) as rec:
        assert rec.events() == sim.events()


@pytest.mark.parametrize("args,match", [
    (["--kernel-bits", "10201"], "0s and 1s"),
    (["--kernel-bits", "1010"], None),
    (["--kernel-bits", "11111", "--window-us", "1000"], "square"),
    (["--window-us", "50"], "eq. 7"),
    (["--power-mw", "-1"], "power_mw"),
])
def test_cli_simulate_errors(tmp_path, args, match):
    res = CliRunner().invoke(main, ["simulate", *args, "-o", str(tmp_path / "x.aedat4")])
    if match is None:  # a 2x2 kernel is fine
        assert res.exit_code == 0, res.output
        return
    assert res.exit_code == 1
    assert res.output.startswith("evtk: error:") and match in res.output
    assert "Traceback" not in res.output
    assert not (tmp_path / "x.aedat4").exists()


def test_cli_default_run_uses_embedded_features(tmp_path):
    res = CliRunner().invoke(main, ["simulate", "-o", str(tmp_path / "d.h5")])
    assert res.exit_code == 0, res.output
    assert "effective stride 1" in res.output
    with evtk.open(tmp_path / "d.h5") as rec:
        meta = rec.metadata[METADATA_KEY]
        f = np.array(meta["features"][0])
        assert f.shape == (16, 16) and 0 < f.sum() < 256


def test_metadata_origin_maps_the_ground_truth_onto_the_sensor():
    """Counts read at the pixels the metadata names line up with the ideal response."""
    from scipy import stats

    # point sources and identical noise-free pixels: equal light, equal counts
    sim = Simulation(K3, _features(21), bench=Bench(source_extent="point"), seed=4,
                     sensor=SensorModel(shot_noise=False, theta_mismatch=0.0, background_rate_hz=0.0))
    meta = sim.metadata()[METADATA_KEY]
    r = sim.responses()
    x0, _, y0, _ = meta["response_region"]
    ox, oy = meta["response_origin_px"]
    ideal = sim.ideal(sim.flat_field)
    on = r.on[sim.flat_field:].mean(0)
    ys = int(round(oy)) - y0 + np.arange(ideal.shape[0])
    xs = int(round(ox)) - x0 + np.arange(ideal.shape[1])
    sampled = on[np.ix_(ys, xs)]
    assert stats.spearmanr(ideal.ravel(), sampled.ravel()).statistic > 0.99
    for level in np.unique(ideal):  # a monotone map from light to counts
        assert np.ptp(sampled[ideal == level]) == 0
    # one pixel off, the match is clearly worse
    shifted = on[np.ix_(ys, xs + 1)]
    assert stats.spearmanr(ideal.ravel(), shifted.ravel()).statistic < 0.8


def test_background_activity_and_hot_pixels_follow_their_rates():
    """Dark features: what the sensor reports away from the pattern is BA and hot pixels (Poisson)."""
    rate_hz, hot_rate_hz, frac = 20.0, 5000.0, 0.002
    sensor = SensorModel(background_rate_hz=rate_hz, hot_pixel_fraction=frac, hot_pixel_rate_hz=hot_rate_hz)
    sim = Simulation(np.ones((1, 1)), np.eye(4), sensor=sensor, repeat=8, seed=3)
    ev = sim.events()
    x0, x1, y0, y1 = sim.region
    span_s = (sim.end_us - sim.start_us) * 1e-6
    outside = ~((ev.x >= x0) & (ev.x < x1) & (ev.y >= y0) & (ev.y < y1))
    pix = ev.y[outside].astype(np.int64) * 320 + ev.x[outside]
    hot = np.isin(pix, sim._hot)
    assert sim._hot.size == round(frac * 320 * 240)
    hx, hy = sim._hot % 320, sim._hot // 320
    hot_outside = np.sum(~((hx >= x0) & (hx < x1) & (hy >= y0) & (hy < y1)))
    n_pix = 320 * 240 - (x1 - x0) * (y1 - y0) - hot_outside
    expected_ba = rate_hz * span_s * n_pix
    assert abs((~hot).sum() - expected_ba) < 5 * np.sqrt(expected_ba)  # Poisson, 5 sigma
    per_hot = np.bincount(np.searchsorted(sim._hot, pix[hot]), minlength=sim._hot.size)
    expected_hot = hot_rate_hz * span_s
    assert abs(per_hot.mean() - expected_hot) < 5 * np.sqrt(expected_hot / sim._hot.size) + rate_hz * span_s
    assert np.mean(ev.p[outside]) == pytest.approx(0.5, abs=0.02)


def test_count_table_and_exact_counts_agree():
    """The tabulated fast path against the pixel model run per capture (same camera, other noise)."""
    f = _features(17, signed=True)
    a = Simulation(K3, f, repeat=30, seed=5, noise_seed=1).responses(method="exact")
    b = Simulation(K3, f, repeat=30, seed=5, noise_seed=2).responses(method="table")
    for counts_a, counts_b in ((a.on, b.on), (a.off, b.off)):
        ma, mb = counts_a.mean(0), counts_b.mean(0)
        va, vb = counts_a.var(0, ddof=1), counts_b.var(0, ddof=1)
        se = np.sqrt((va + vb) / counts_a.shape[0]) + 1e-9
        assert np.mean(np.abs(ma - mb) <= 4 * se) >= 0.99
        assert mb.mean() == pytest.approx(ma.mean(), rel=0.03, abs=0.01)
        assert vb.mean() == pytest.approx(va.mean(), rel=0.15, abs=0.01)


def test_count_table_is_reused_and_fast_path_methods():
    sim = Simulation(K3, _features(2), seed=1)
    t1 = sim.count_table()
    t2 = Simulation(K3, _features(3), seed=1).count_table()  # same bench, sensor, timing: same table
    assert t1 is t2
    u, th, on, off = t1
    assert on.shape == (th.size, u.size, Simulation.TABLE_REPLICATES)
    # more light, more ON counts; higher thresholds, fewer
    assert np.all(np.diff(on.mean(2)[th.size // 2]) >= -0.5) and on.mean(2)[:, -1].min() > 10
    assert on.mean(2)[0, -1] > on.mean(2)[-1, -1]
    with pytest.raises(EvtkError, match="method"):
        sim.responses(method="magic")
    short = Simulation(K3, _features(2), seed=1, settle_us=1000)
    assert short.responses().on.shape == short.responses(method="exact").on.shape


def test_simulation_record_is_typed_and_round_trips_through_a_recording(tmp_path):
    """The record a recording stores reads back as the same typed record; a broken one is one clear error."""
    import evtk
    from evtk.errors import EvtkError
    from evtk.simulate import SimulationRecord

    sim = Simulation(np.array([[1, -1], [0, 1]]), np.ones((8, 8)), repeat=2, flat_field=1, seed=4)
    sim.write(tmp_path / "r.h5")
    with evtk.open(tmp_path / "r.h5") as rec:
        back = SimulationRecord.from_metadata(rec.metadata)
    mine = sim.record()
    assert back.sensor == sim.sensor and back.bench.to_dict() == sim.bench.to_dict()
    assert np.array_equal(back.kernels, sim.kernels) and back.kernels.dtype == np.int64
    assert np.array_equal(back.schedule.t_on_us, sim.schedule.t_on_us)
    assert back.response_region == mine.response_region and back.response_origin_px == mine.response_origin_px
    assert back.signed and back.repeat == 2 and back.flat_field == 1
    assert SimulationRecord.from_metadata({}) is None
    d = mine.to_dict()
    del d["blank_rate_e_per_s"]
    with pytest.raises(EvtkError, match="lacks blank_rate_e_per_s"):
        SimulationRecord.from_dict(d)
    with pytest.raises(EvtkError, match="malformed"):
        SimulationRecord.from_dict(dict(mine.to_dict(), window_us="soon"))
    with pytest.raises(EvtkError, match="malformed"):
        SimulationRecord.from_dict(dict(mine.to_dict(), response_region=[0, 1]))
    older = {k: v for k, v in mine.to_dict().items() if k not in ("dot_spacing", "calibration", "evtk_version")}
    assert SimulationRecord.from_dict(older).dot_spacing == 4  # records from before these keys still read
