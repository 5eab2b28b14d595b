"""Noise experiments: per-scene reports, the power sweep, the trade-off, and their commands."""

import json

import numpy as np
import pytest
from click.testing import CliRunner

import evtk
from evtk import EvtkError
from evtk.cli import main
from evtk.metrics import flip_rates, sinad
from evtk.sensor import SensorModel
from evtk.simulate import Simulation, default_features
from evtk.sweeps import (
    flip_sweep,
    pareto_front,
    random_kernels,
    recording_noise,
    scene_noise,
    simulated_reconstruction,
    tradeoff,
)

F16 = np.where(default_features() > 0, 1, -1)


def test_random_kernels_are_distinct_signed_and_bounded():
    k = random_kernels(20, seed=3)
    assert k.shape == (20, 3, 3) and set(np.unique(k)) == {-1, 1}
    assert len({x.tobytes() for x in k}) == 20
    np.testing.assert_array_equal(k, random_kernels(20, seed=3))
    assert len({x.tobytes() for x in random_kernels(4, (1, 2))}) == 4
    with pytest.raises(EvtkError, match="distinct"):
        random_kernels(5, (1, 2))


def test_pareto_front_against_brute_force():
    rng = np.random.default_rng(0)
    for _ in range(20):
        c, e = rng.integers(0, 6, 12).astype(float), rng.integers(0, 6, 12).astype(float)
        brute = [not any((c[j] <= c[i] and e[j] <= e[i] and (c[j] < c[i] or e[j] < e[i])) for j in range(12))
                 for i in range(12)]
        assert pareto_front(c, e).tolist() == brute
    with pytest.raises(EvtkError):
        pareto_front([1.0, np.nan], [1.0, 2.0])


def test_scene_noise_matches_the_metrics_on_each_scene():
    result, sim = simulated_reconstruction(random_kernels(2, seed=1), F16, repeat=5, seed=2)
    scenes = scene_noise(result, interval=None)
    assert [(s["kernel_id"], s["features_id"], s["repeats"]) for s in scenes] == [(0, 0, 5), (1, 0, 5)]
    for s in scenes:
        idx = [i for i, (k, f, _) in enumerate(result.pairs.tolist()) if k == s["kernel_id"]]
        assert s["sinad"].sinad_db == pytest.approx(sinad(result.cells[idx], interval=None).sinad_db)
        assert s["flips"].pairwise_pct == pytest.approx(flip_rates(result.binary[idx]).pairwise_pct)
        assert -1 <= s["error"]["correlation"] <= 1


def test_noise_free_pixels_repeat_exactly_and_say_so():
    quiet = SensorModel(shot_noise=False, background_rate_hz=0.0)
    result, _ = simulated_reconstruction(random_kernels(1, seed=4), F16, sensor=quiet, repeat=4, seed=1)
    (scene,) = scene_noise(result)
    assert scene["sinad"].noise_free and scene["sinad"].sinad_db == np.inf and scene["flips"].pairwise_pct == 0.0
    d = json.loads(json.dumps(scene["sinad"].to_dict()))
    assert d["sinad_db"] is None and d["noise_free"] is True


def test_flip_sweep_dim_light_flips_more():
    """Fig. 3 (right): fewer photons, noisier counts, more flips and fewer effective bits."""
    rows = flip_sweep([0.05, 20.0], random_kernels(3, seed=0), F16, repeats=6, seed=1)
    assert len(rows) == 6 and {r["power_mw"] for r in rows} == {0.05, 20.0}
    dim = [r for r in rows if r["power_mw"] == 0.05]
    bright = [r for r in rows if r["power_mw"] == 20.0]
    assert np.mean([r["pairwise_pct"] for r in dim]) > 2 * np.mean([r["pairwise_pct"] for r in bright])
    assert np.mean([r["enob_bits"] for r in dim]) < np.mean([r["enob_bits"] for r in bright])
    for r in rows:
        assert 0 <= r["majority_pct"] <= r["pairwise_pct"] <= 100
    # no light reaches a threshold: every response is zero, nothing flips, and no ENOB is claimed
    (dark,) = flip_sweep([1e-4], random_kernels(1), F16, repeats=3)
    assert dark["pairwise_pct"] == 0.0 and dark["enob_bits"] is None
    with pytest.raises(EvtkError, match="positive"):
        flip_sweep([0.0], random_kernels(1), F16)
    with pytest.raises(EvtkError, match="two repeats"):
        flip_sweep([1.0], random_kernels(1), F16, repeats=1)


def test_tradeoff_rows_time_and_front():
    rows = tradeoff([200, 1000], random_kernels(1, seed=2), F16, settles_us=[1000, 12000], repeats=4,
                    time_events=False)
    assert [(r["window_us"], r["settle_us"]) for r in rows] == [(200, 1000), (200, 12000), (1000, 1000),
                                                                (1000, 12000)]
    for r in rows:
        assert r["device_us_per_capture"] == r["window_us"] + r["settle_us"]
        assert r["compute_us_per_capture"] > 0 and r["captures"] == 2 + 4 * 4
    front = pareto_front([r["device_us_per_capture"] for r in rows], [r["nrmse"] for r in rows])
    assert [r["pareto"] for r in rows] == front.tolist() and front[0]  # the fastest is always on the front
    # pixels left short of the dark level (1 ms settle) err more than settled ones
    by = {(r["window_us"], r["settle_us"]): r for r in rows}
    assert by[(1000, 1000)]["nrmse"] > by[(1000, 12000)]["nrmse"]
    with pytest.raises(EvtkError, match="eq. 7"):
        tradeoff([100], random_kernels(1), F16)


def test_cli_enob_flips_tradeoff(tmp_path):
    paths = []
    for power in (0.05, 20.0):
        sim = Simulation(random_kernels(2, seed=5), F16[:8, :8], repeat=4, seed=1,
                         bench=evtk.optics.Bench(power_mw=power))
        paths.append(tmp_path / f"p{power}.aedat4")
        sim.write(paths[-1])
    res = CliRunner().invoke(main, ["enob", str(paths[1]), "--json", "--interval", "bootstrap", "--plot",
                                    str(tmp_path / "e.png")])
    assert res.exit_code == 0, res.output
    out = json.loads(res.output)
    assert len(out["scenes"]) == 2 and out["scenes"][0]["repeats"] == 4
    lo, hi = out["scenes"][0]["sinad"]["ci_enob"]
    assert lo <= out["scenes"][0]["sinad"]["enob_bits"] <= hi
    assert (tmp_path / "e.png").stat().st_size > 1000
    with evtk.open(paths[1]) as rec:
        from evtk.reconstruct import reconstruct

        lib = scene_noise(reconstruct(rec), interval=None)
    assert out["scenes"][1]["sinad"]["sinad_db"] == pytest.approx(lib[1]["sinad"].sinad_db)
    text = CliRunner().invoke(main, ["enob", str(paths[1])])
    assert text.exit_code == 0 and "ENOB" in text.output and "SINAD dB" in text.output

    res = CliRunner().invoke(main, ["flips", *map(str, paths), "--json", "--plot", str(tmp_path / "f.png")])
    assert res.exit_code == 0, res.output
    rows = json.loads(res.output)["rows"]
    assert sorted({r["power_mw"] for r in rows}) == [0.05, 20.0] and len(rows) == 4
    assert (tmp_path / "f.png").stat().st_size > 1000

    res = CliRunner().invoke(main, ["flips", "--power-mw", "0.05,20", "--kernels", "2", "--repeats", "3", "--json"])
    assert res.exit_code == 0, res.output
    assert len(json.loads(res.output)["rows"]) == 4

    res = CliRunner().invoke(main, ["tradeoff", "--window-us", "200,500", "--kernels", "1", "--repeats", "3",
                                    "--fast", "--json", "--plot", str(tmp_path / "t.png")])
    assert res.exit_code == 0, res.output
    rows = json.loads(res.output)["rows"]
    assert [r["window_us"] for r in rows] == [200, 500] and any(r["pareto"] for r in rows)
    res = CliRunner().invoke(main, ["tradeoff", "--window-us", "200,500", "--kernels", "1", "--repeats", "3", "--fast"])
    assert res.exit_code == 0 and "device us/capture" in res.output and "*" in res.output
    for bad, msg, code in ((["--window-us", "fast"], "comma-separated", 2), (["--window-us", "-5"], "positive", 2),
                           (["--window-us", "250.5"], "whole", 2), (["--window-us", "50"], "eq. 7", 1)):
        res = CliRunner().invoke(main, ["tradeoff", *bad])  # a malformed value is a usage error, a bad setting not
        assert res.exit_code == code and msg in res.output, res.output


def test_enob_of_a_recording_without_a_schedule(tmp_path):
    """A bench recording: every period window is a repeat of one scene."""
    rng = np.random.default_rng(0)
    n = 60_000
    t = np.sort(rng.integers(0, 50_000, n))
    x = rng.integers(0, 8, n).astype(np.uint16)
    ev = evtk.Events(t, x, np.zeros(n, np.uint16), (rng.random(n) < 0.8).astype(np.uint8), (8, 1))
    path = tmp_path / "bench.h5"
    evtk.write_events(path, ev)
    res = CliRunner().invoke(main, ["enob", str(path), "--window", "period:5000", "--json", "--interval", "none"])
    assert res.exit_code == 0, res.output
    (scene,) = json.loads(res.output)["scenes"]
    assert scene["kernel_id"] == -1 and scene["repeats"] == 10 and scene["sinad"]["ci_db"] is None
    res = CliRunner().invoke(main, ["enob", str(path)])
    assert res.exit_code == 1 and "no capture schedule" in res.output


def test_recording_noise_in_batches_equals_the_whole_reconstruction(tmp_path, monkeypatch):
    """Windows measured a few at a time give the whole reconstruction's SINAD, interval, per-pixel SINAD and
    flips; with a memory budget too small for every window at once, enob and reconstruct's responses still run
    where reconstruct keeping every pixel cannot."""
    import evtk.sweeps as sweeps
    from evtk.reconstruct import reconstruct

    rng = np.random.default_rng(1)
    n = 400_000
    t = np.sort(rng.integers(0, 2_000_000, n))
    x = rng.integers(0, 64, n).astype(np.uint16)
    y = rng.integers(0, 48, n).astype(np.uint16)
    p = (rng.random(n) < 0.3 + 0.5 * (x > 32)).astype(np.uint8)
    path = tmp_path / "bench.aedat4"
    evtk.write_events(path, evtk.Events(t, x, y, p, (64, 48)))
    with evtk.open(path) as rec:
        whole = scene_noise(reconstruct(rec, window=("period", 10_000)), per_pixel=True)[0]
        monkeypatch.setattr(sweeps, "NOISE_BATCH_BYTES", 7 * 64 * 48 * 64)  # 7 windows a batch: 29 batches
        (part,) = sweeps.recording_noise(rec, ("period", 10_000), per_pixel=True)
    assert part["repeats"] == whole["repeats"] > 190
    assert part["sinad"].sinad_db == pytest.approx(whole["sinad"].sinad_db, rel=1e-9)
    assert np.allclose(part["sinad"].ci_db, whole["sinad"].ci_db, rtol=1e-9)
    assert np.allclose(part["sinad"].per_pixel_db, whole["sinad"].per_pixel_db, rtol=1e-9)
    assert part["flips"].pairwise_pct == pytest.approx(whole["flips"].pairwise_pct)
    monkeypatch.undo()
    monkeypatch.setenv("EVTK_MEMORY_LIMIT_MB", "4")  # 200 windows x 64x48 x 64 B = 37.5 MiB
    res = CliRunner().invoke(main, ["reconstruct", str(path), "--window", "period:10000", "--keep-pixels", "-o",
                                    str(tmp_path / "r.h5")])
    assert res.exit_code == 1 and "MiB" in res.output, res.output
    # the responses alone (the default) are counted a batch at a time, within the budget
    res = CliRunner().invoke(main, ["reconstruct", str(path), "--window", "period:10000", "-o",
                                    str(tmp_path / "r.h5")])
    assert res.exit_code == 0, res.output
    res = CliRunner().invoke(main, ["enob", str(path), "--window", "period:10000", "--json"])
    assert res.exit_code == 0, res.output
    got = json.loads(res.output)["scenes"][0]["sinad"]["sinad_db"]
    assert got == pytest.approx(whole["sinad"].sinad_db, rel=1e-9)


def test_demo_runs_on_the_embedded_defaults(tmp_path):
    out = tmp_path / "demo"
    res = CliRunner().invoke(main, ["demo", "--out", str(out), "--repeat", "3", "--json"])
    assert res.exit_code == 0, res.output
    s = json.loads(res.stdout)
    assert "evtk demo: simulating" in res.stderr  # progress from the start, before any compiling
    for key in ("recording", "reconstruction", "enob_plot"):
        assert (out / s[key].split("/")[-1]).stat().st_size > 0
    assert [p.split("/")[-1] for p in s["contact_sheet"]] == ["responses.png"]  # three responses: one page
    assert s["captures"] == 2 + 6 + 3 and s["repeats"] == 3  # flat fields, level captures, the repeats
    assert s["route"].startswith("calibrated")
    with evtk.open(s["recording"]) as rec:
        again = evtk.reconstruct_recording(rec, binarize_method="mean")
    assert s["error"]["correlation"] == pytest.approx(again.summary["error"]["correlation"])
    assert s["flips"]["pairwise_pct"] == pytest.approx(flip_rates(again.binary).pairwise_pct)
    text = CliRunner().invoke(main, ["demo", "--out", str(out), "--repeat", "2"])
    assert text.exit_code == 0 and "effective bits" in text.output and "flipped" in text.output


def test_decimation_keeps_every_dth_pixel_a_strided_response():
    """Decimation 2 on matched optics: the full reconstruction's cells at stride 2, against the strided ideal."""
    from scipy import signal

    from evtk.optics import Bench

    quiet = SensorModel(shot_noise=False, background_rate_hz=0.0)
    k = random_kernels(1, seed=9)
    full, _ = simulated_reconstruction(k, F16, bench=Bench(decimation=1), sensor=quiet, repeat=2, seed=3)
    dec, _ = simulated_reconstruction(k, F16, bench=Bench(decimation=2), sensor=quiet, repeat=2, seed=3)
    assert dec.summary["decimation"] == 2 and not dec.summary["deblurred"] and full.summary["deblurred"]
    from evtk.reconstruct import reconstruct_counts

    plain = reconstruct_counts(full.counts, _meta(k, Bench(decimation=1), quiet), deblur=False)
    np.testing.assert_allclose(dec.cells, plain.cells[:, ::2, ::2])
    ideal = signal.correlate2d(F16, k[0], "valid")[::2, ::2]
    np.testing.assert_array_equal(dec.ideal[0], ideal)
    rows = tradeoff([1000], k, F16, decimations=[1, 2], repeats=3, time_events=False)
    assert [r["decimation"] for r in rows] == [1, 2]


def _meta(k, bench, sensor):
    return Simulation(k, F16, bench=bench, sensor=sensor, repeat=2, seed=3).metadata()["simulation"]


def test_wilson_interval_matches_its_closed_form_values():
    """0 of 10: [0, 0.2775]; 5 of 10: [0.2366, 0.7634]; 10 of 10: [0.7225, 1] (the Wilson score interval)."""
    from evtk.plots import wilson_interval

    lo, hi = wilson_interval([0.0, 0.5, 1.0], [10, 10, 10])
    assert np.allclose(lo, [0.0, 0.2366, 0.7225], atol=1e-4) and np.allclose(hi, [0.2775, 0.7634, 1.0], atol=1e-4)


def test_enob_says_which_route_it_measured(tmp_path):
    """Issue 30: `evtk enob` on a simulated recording (the oracle route) and on that recording's own `evtk
    reconstruct` output (the calibrated route) give different figures; each says which route it measured."""
    sim = Simulation(random_kernels(1, seed=2), F16[:8, :8], repeat=3, seed=4)
    rec_path, out = tmp_path / "run.aedat4", tmp_path / "run.h5"
    sim.write(rec_path)
    on_rec = CliRunner().invoke(main, ["enob", str(rec_path), "--json", "--interval", "none"])
    assert on_rec.exit_code == 0, on_rec.output
    assert json.loads(on_rec.output)["route"].startswith("oracle: the simulation record's own pixel model")
    res = CliRunner().invoke(main, ["reconstruct", str(rec_path), "-o", str(out)])
    assert res.exit_code == 0, res.output
    on_out = CliRunner().invoke(main, ["enob", str(out)])
    assert on_out.exit_code == 0, on_out.output
    first = on_out.output.splitlines()[0]
    assert first.startswith(f"route: the responses stored in {out} (calibrated: "), first
    bench = tmp_path / "bench.h5"
    rng = np.random.default_rng(0)
    t = np.sort(rng.integers(0, 50_000, 20_000))
    evtk.write_events(bench, evtk.Events(t, rng.integers(0, 8, t.size).astype(np.uint16), np.zeros(t.size, np.uint16),
                                         (rng.random(t.size) < 0.8).astype(np.uint8), (8, 1)))
    fixed = CliRunner().invoke(main, ["enob", str(bench), "--window", "period:5000", "--json", "--interval", "none"])
    # nothing says how this recording's counts map to light: net counts, unless a theta is given
    assert json.loads(fixed.output)["route"] == "fixed windows (--window period:5000): net counts (ON - OFF), not linearised"
    with evtk.open(bench) as rec:
        (row,) = recording_noise(rec, ("period", 5000), interval=None, theta=0.3)
    assert row["route"] == "fixed windows (--window period:5000): exp(n theta), theta = 0.3"
