"""The simulator's other physics: each one's defining property (v2e knee, log-node, frame readout, mirror, drift,
rise time)."""

from __future__ import annotations

import numpy as np
import pytest

from evtk.errors import EvtkError
from evtk.sensor import PixelState, SensorModel, log_noise_std, simulate_pixels, time_constant_us
from evtk.simulate import Simulation


def _step(model, base_rate, u, n_pix=4, settle_us=2000.0, window_us=3000.0, seed=3, t0_us=0.0):
    """Pixels settled at ``base_rate`` then a step of log size ``u``: their events (t relative to the step)."""
    rates = np.array([[base_rate] * n_pix, [base_rate * np.exp(u)] * n_pix])
    lvl = np.log(rates)
    st = PixelState(lvl[0], 0.0, np.full(n_pix, model.theta_on), np.full(n_pix, model.theta_off),
                    np.random.default_rng(0))
    t, i, p, _, _ = simulate_pixels(st, lvl, time_constant_us(rates, model), log_noise_std(rates, model),
                                    np.array([0.0, settle_us]), np.array([settle_us, settle_us + window_us]),
                                    model, seed, t0_us=t0_us)
    return t - settle_us, i, p


def _quiet(**kw):
    return SensorModel(shot_noise=False, theta_mismatch=0.0, background_rate_hz=0.0, **kw)


def test_v2e_time_constant_is_flat_above_the_knee():
    m = _quiet(pixel="v2e", tau_min_us=80.0, tau_electrons=400.0)
    knee = m.tau_electrons / m.tau_min_us * 1e6  # e/s
    tau = time_constant_us(np.array([2 * knee, 20 * knee, 0.25 * knee]), m)
    assert tau[0] == tau[1] == m.tau_min_us and tau[2] == pytest.approx(4 * m.tau_min_us)
    # in the events: the same step above the knee is followed equally fast, at any light; evtk's pixel is not
    first = {}
    for pixel in ("v2e", "evtk"):
        model = _quiet(pixel=pixel, tau_min_us=80.0, tau_electrons=400.0)
        first[pixel] = [np.min(_step(model, r, 1.0)[0]) for r in (2 * knee, 20 * knee)]
    assert first["v2e"][0] == pytest.approx(first["v2e"][1], rel=0.05)
    assert first["v2e"][0] == pytest.approx(80.0 * np.log(1.0 / 0.8), rel=0.25)  # tau ln(u / (u - theta))
    assert first["evtk"][0] > 1.1 * first["evtk"][1]  # tau_min + tau_electrons / lam: slower at less light


def test_v2e_resets_to_the_level_and_leaks():
    m = _quiet(pixel="v2e", tau_min_us=80.0, tau_electrons=400.0, refractory_us=1.0)
    t, _, p = _step(m, 1e8, 1.1, n_pix=1)
    # after each event the reference is where the photoreceptor was: the events are one threshold apart along
    # V(t) = u (1 - exp(-t / tau)), each timed where the path crosses
    assert np.all(p == 1) and t.size == 5
    np.testing.assert_allclose(np.sort(t), -80.0 * np.log(1 - 0.2 * np.arange(1, 6) / 1.1), rtol=0.1)
    leak = _quiet(pixel="v2e", leak_rate_hz=200.0)
    t, _, p = _step(leak, 1e8, 0.0, n_pix=50, window_us=100_000.0)
    rate_hz = t.size / 50 / 0.1
    assert np.all(p == 1) and 150 < rate_hz < 250  # the reference sinks one threshold per leak event


def test_v2e_shot_events_are_most_in_the_dark():
    m = _quiet(pixel="v2e", shot_event_rate_hz=500.0)
    dark = _step(m, m.dark_current_e_per_s, 0.0, n_pix=50, window_us=100_000.0)[0].size
    bright = _step(m, 100 * m.dark_current_e_per_s, 0.0, n_pix=50, window_us=100_000.0)[0].size
    assert 0.7 * 500 * 50 * 0.1 < dark < 1.3 * 500 * 50 * 0.1
    assert bright < 0.2 * dark  # sqrt(dark / lam) = 0.1


def test_log_node_fires_one_event_per_threshold_with_interpolated_times():
    m = _quiet(pixel="log-node", sample_us=10.0)
    assert time_constant_us(1e6, m) == 0.0 and log_noise_std(1e6, m) == 0.0
    t, _, p = _step(m, 1e6, 1.1, n_pix=1)
    assert t.size == 5 and np.all(p == 1)  # floor(1.1 / 0.2)
    np.testing.assert_allclose(np.sort(t), 10.0 * 0.2 * np.arange(1, 6) / 1.1)
    t, _, p = _step(m, 1e6, -1.1, n_pix=1)
    assert t.size == 5 and np.all(p == 0)


def test_frame_readout_fires_at_most_once_per_pixel_per_frame_on_the_grid():
    sm = SensorModel(readout_period_us=150.0, frame_compare=True, background_rate_hz=0.0)
    sim = Simulation(np.ones((3, 3)), np.eye(16), sensor=sm, seed=2, levels=3)
    ev = sim.events()
    assert len(ev) > 1000 and np.all(ev.t % 150 == 0)
    key = (ev.t // 150) * (1 << 32) + ev.y.astype(np.int64) * 65536 + ev.x
    assert np.unique(key).size == key.size
    # the stamped asynchronous readout of the same frame period does fire several times per frame
    ev2 = Simulation(np.ones((3, 3)), np.eye(16), sensor=SensorModel(readout_period_us=150.0), seed=2,
                     levels=3).events()
    key2 = (ev2.t // 150) * (1 << 32) + ev2.y.astype(np.int64) * 65536 + ev2.x
    assert np.unique(key2).size < key2.size
    with pytest.raises(EvtkError, match="frame_compare"):
        SensorModel(frame_compare=True)


def _count_image(sim):
    ev = sim.events()
    img = np.zeros((sim.bench.sensor_height, sim.bench.sensor_width))
    np.add.at(img, (ev.y[ev.p == 1], ev.x[ev.p == 1]), 1)
    return img


def test_mirrored_camera_mirrors_the_raw_events():
    rng = np.random.default_rng(5)
    k, f = rng.choice([0, 1], (3, 3)), rng.choice([0, 1], (16, 16))
    sm = _quiet()
    plain = _count_image(Simulation(k, f, sensor=sm, seed=1, camera={"offset_px": (0.0, 0.0), "k1": 1e-12}))
    mirrored = _count_image(Simulation(k, f, sensor=sm, seed=1, camera={"mirror": True, "k1": 1e-12}))
    assert plain.sum() > 1000
    lit = (plain > 0) | (plain[:, ::-1] > 0)
    assert np.mean((mirrored == plain[:, ::-1])[lit]) > 0.97 and np.mean((mirrored == plain)[lit]) < 0.7
    turned = _count_image(Simulation(k, f, sensor=sm, seed=1, camera={"rotation_deg": 180.0}))
    lit = (plain > 0) | (plain[::-1, ::-1] > 0)
    assert np.mean((turned == plain[::-1, ::-1])[lit]) > 0.97


def test_clock_drift_scales_event_stamps_against_the_triggers():
    args = (np.ones((3, 3)), np.eye(16))
    a = Simulation(*args, seed=4, start_us=1000)
    b = Simulation(*args, seed=4, start_us=1000, sensor=SensorModel(clock_drift_ppm=2000.0))
    ea, eb = a.events(), b.events()
    np.testing.assert_array_equal(a.triggers().t, b.triggers().t)
    np.testing.assert_array_equal(eb.t, ea.t + np.round((ea.t - 1000) * 2e-3).astype(np.int64))
    span = (eb.t[-1] - eb.t[0]) / (ea.t[-1] - ea.t[0])
    assert span == pytest.approx(1.002, abs=2e-4)


def test_light_rise_spreads_the_first_events_after_the_edge():
    sm = _quiet(pixel="log-node", sample_us=1.0)

    def delays(rise):
        sim = Simulation(np.ones((3, 3)), np.ones((16, 16)), sensor=sm, seed=1, light_rise_us=rise, flat_field=0)
        ev = sim.events()
        on = ev.t[ev.p == 1] - sim.schedule.t_on_us[0]
        return on[(on >= 0) & (on < sim.window_us)]

    sharp, slow = delays(0.0), delays(20.0)
    assert np.all(sharp <= 1) and sharp.size == pytest.approx(slow.size, rel=0.05)
    assert 0.2 * 20 < np.median(slow) < 5 * 20 and np.max(slow) > 20
    with pytest.raises(EvtkError, match="light_rise_us"):
        Simulation(np.ones((3, 3)), np.eye(16), light_rise_us=-1.0)


def test_other_physics_are_validated():
    with pytest.raises(EvtkError, match="pixel"):
        SensorModel(pixel="davis")
    with pytest.raises(EvtkError, match="leak_rate_hz"):
        SensorModel(leak_rate_hz=1.0)
    with pytest.raises(EvtkError, match="mirror"):
        Simulation(np.ones((3, 3)), np.eye(16), camera={"mirror": 1})
    assert not SensorModel().stepped and SensorModel(pixel="v2e").stepped
    # the count table models evtk's own pixel: another physics is counted exactly, or refused by name
    sim = Simulation(np.ones((3, 3)), np.eye(16), sensor=SensorModel(pixel="v2e"), seed=1)
    with pytest.raises(EvtkError, match="count table"):
        sim.responses(method="table")
    counts = sim.responses()
    ev = sim.events()
    assert counts.on.sum() > 0 and abs(int(counts.on.sum()) - int(np.sum(ev.p == 1))) < 0.2 * np.sum(ev.p == 1)


def test_level_table_is_monotone_and_reads_its_levels_back():
    from evtk.reconstruct.calibrated import held_out_table_error
    from evtk.reconstruct.linearize import isotonic, level_curve, level_table_values, linearize_by_model

    assert isotonic([3.0, 1.0, 2.0, 5.0]).tolist() == [2.0, 2.0, 2.0, 5.0]
    light = np.array([1.0, 3.0, 4.0, 6.0, 7.0, 9.0])
    counts = np.log1p(light / 0.05) / 0.2  # a log pixel of another form than evtk's model: no low-pass at all
    read = level_table_values(counts, counts, light)
    np.testing.assert_allclose(read, light)
    assert level_table_values(np.array([-2.0]), counts, light)[0] < 0  # below the table: along its first segment
    assert held_out_table_error(light, counts) < 0.15
    assert held_out_table_error(light, 2 * light) == pytest.approx(0.0, abs=1e-12)
    u, n = level_curve(light, counts, 0.05)
    assert np.all(np.diff(n) >= 0) and np.all(n == np.round(n))
    back = linearize_by_model(np.round(counts), (u, n)) * 0.05
    np.testing.assert_allclose(back, light, rtol=0.15)
    with pytest.raises(EvtkError, match="do not grow"):
        level_table_values(np.zeros(3), [0.0, 0.0], [1.0, 2.0])


def test_calibrated_route_holds_on_a_log_node_pixel(tmp_path):
    """The fitted model cannot describe a pixel without a low-pass and misreads the level captures; the route
    then reads them by their own table, deblurred, instead of falling back to exp(n theta)."""
    import evtk

    rng = np.random.default_rng(4000)
    k, f = rng.choice([-1, 1], (3, 3)), rng.choice([-1, 1], (16, 16))
    sim = Simulation(k, f, sensor=SensorModel(pixel="log-node", theta_mismatch=0.008), seed=0, levels=6,
                     calibration=2, light_rise_us=3.0)
    path = tmp_path / "run.h5"
    sim.write(path)
    with evtk.open(path) as rec:
        auto = evtk.reconstruct_recording(rec)
        plain = evtk.reconstruct_recording(rec, deblur=False)
    s = auto.summary
    assert s["linearization"] == "the level captures' table" and s["pixel_model_rejected"]
    assert "table" in s["pixel_model_note"] and s["deblurred"]
    r_auto = s["error"]["correlation"]
    assert r_auto > 0.93 and r_auto > plain.summary["error"]["correlation"] + 0.02


def test_a_rising_light_is_a_job_setting_and_the_record_keeps_it(tmp_path):
    """The light's rise time travels like its delay: a job sets it, the simulation record of the recording keeps
    it (a recording says what light it saw), and a record whose value is out of range is refused by name."""
    import evtk
    from evtk.patterns import job_simulation
    from evtk.plan import METADATA_KEY, SimulationRecord

    job = tmp_path / "job.toml"
    job.write_text('kernels = ["010111010"]\nrepeat = 1\nflat_field = 0\nlight_rise_us = 4.5\n')
    sim = job_simulation(job)
    assert sim.light_rise_us == 4.5
    sim.write(tmp_path / "r.h5")
    with evtk.open(tmp_path / "r.h5") as rec:
        record = SimulationRecord.from_metadata(rec.metadata)
        raw = rec.metadata[METADATA_KEY]
    assert record.light_rise_us == 4.5
    bad = dict(raw, light_rise_us=-2.0)
    with pytest.raises(EvtkError, match="light_rise_us"):
        SimulationRecord.from_dict(bad)
    job.write_text('kernels = ["010111010"]\nlight_rise_us = "slow"\n')
    with pytest.raises(EvtkError, match="light_rise_us"):
        job_simulation(job)
