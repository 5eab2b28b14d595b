"""Calibration from the device's own dot-grid captures, and the full bench round trip with it."""

import json

import numpy as np
import pytest
from click.testing import CliRunner

import evtk
from evtk import EvtkError
from evtk.calibrate import calibrate, load_calibration, save_calibration
from evtk.cli import main
from evtk.patterns import job_simulation, write_patterns

JOB = """kernels = ["010111010"]
repeat = 2
flat_field = 2
calibration = 2
dot_spacing = 4
window_us = 1000
seed = {seed}
[bench]
origin_px = [{x}, {y}]
power_mw = {power}
"""


def _bench_copy(tmp_path, seed, x, y, power=20.0):
    """patterns + a simulated run of a job, and the camera's copy of the run (no evtk record)."""
    job = tmp_path / f"job{seed}.toml"
    job.write_text(JOB.format(seed=seed, x=x, y=y, power=power))
    sim = job_simulation(job)
    write_patterns(sim, tmp_path / f"p{seed}")
    sim.write(tmp_path / f"sim{seed}.h5")
    with evtk.open(tmp_path / f"sim{seed}.h5") as rec:
        ev, tr, record = rec.events(), rec.triggers(), rec.metadata["simulation"]
    evtk.write_events(tmp_path / f"cam{seed}.aedat4", ev, tr)
    return job, tmp_path / f"p{seed}" / "schedule.json", tmp_path / f"cam{seed}.aedat4", record


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_calibration_recovers_where_the_response_lies(tmp_path, seed):
    """Random sub-pixel placements of the response: the map from cells to pixels comes back within 0.11 px RMS
    over every cell of the response (0.2 px at its corner, cell (0, 0), an extrapolation from the dots), the step
    within 1 %, the region covers the simulation's, and the dots fit the map within a tenth of a pixel (RMS)."""
    rng = np.random.default_rng(seed)
    x, y = 140 + 20 * rng.random(), 100 + 20 * rng.random()
    _, schedule, cam, record = _bench_copy(tmp_path, seed, x, y)
    with evtk.open(cam) as rec:
        cal = calibrate(rec, schedule)
    truth = np.array(record["response_origin_px"])
    assert np.allclose(truth, [x, y])
    rows, cols = cal.response_shape
    cells = np.stack(np.meshgrid(np.arange(cols), np.arange(rows)), -1).reshape(-1, 2).astype(float)
    err = cal.to_pixels(cells) - (cells + truth)  # the simulated optics: one pixel per cell, no rotation
    # 0.058-0.103 px over the seeds with the orientation marker's dot left out, 0.058-0.097 with the whole grid
    assert np.sqrt(np.mean(np.sum(err ** 2, axis=1))) < 0.11
    assert np.linalg.norm(np.array(cal.origin_px) - truth) < 0.2, (cal.origin_px, truth)
    assert cal.step_px == pytest.approx(1.0, rel=0.01) and cal.residual_rms_px < 0.1
    assert cal.dots_found == cal.dots_expected == 15 and cal.inliers == 15  # 4x4 grid less the marker's dot
    x0, x1, y0, y1 = cal.region
    rx0, rx1, ry0, ry1 = record["response_region"]
    assert x0 <= rx0 and x1 >= rx1 and y0 <= ry0 and y1 >= ry1 and (x1 - x0) <= (rx1 - rx0) + 4
    for name in ("c.toml", "c.json"):
        save_calibration(tmp_path / name, cal)
        back = load_calibration(tmp_path / name)
        assert np.allclose(back.matrix, cal.matrix) and back.region == cal.region


def test_bench_round_trip_patterns_simulate_calibrate_reconstruct(tmp_path):
    """patterns -> simulated run -> the camera's copy -> calibrate -> reconstruct --calibration: the error is
    within 15 % of the same pipeline given the true placement, and close to the oracle that inverts the
    simulator's own pixel model."""
    from evtk.plan import as_plan
    from evtk.reconstruct import reconstruct

    job, schedule, cam, record = _bench_copy(tmp_path, 7, 152.3, 108.6)
    res = CliRunner().invoke(main, ["calibrate", str(cam), "--schedule", str(schedule), "-o",
                                    str(tmp_path / "cal.toml"), "--png", str(tmp_path / "cal.png"), "--json"])
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout)["dots_found"] == 15 and (tmp_path / "cal.png").stat().st_size > 5000
    res = CliRunner().invoke(main, ["reconstruct", str(cam), "--schedule", str(schedule), "--calibration",
                                    str(tmp_path / "cal.toml"), "-o", str(tmp_path / "r.h5"), "--json"])
    assert res.exit_code == 0, res.output
    calibrated = json.loads(res.stdout)["error"]
    with evtk.open(cam) as rec:
        known = reconstruct(rec, as_plan(schedule).replace(region=record["response_region"],
                                                           origin_px=record["response_origin_px"]),
                            linearization="exp(n theta)")
    with evtk.open(tmp_path / "sim7.h5") as rec:
        oracle = reconstruct(rec)
    assert calibrated["nrmse"] <= 1.15 * known.summary["error"]["nrmse"]
    assert calibrated["correlation"] > oracle.summary["error"]["correlation"] - 0.05


def test_calibration_bad_input_is_one_clear_error_each(tmp_path):
    # too few dots seen: the light is too weak for the single kernel element
    _, schedule, cam, _ = _bench_copy(tmp_path, 3, 150.0, 110.0, power=0.002)
    with evtk.open(cam) as rec, pytest.raises(EvtkError, match="calibration dots were seen"):
        calibrate(rec, schedule)
    # a schedule without calibration captures
    job = tmp_path / "plain.toml"
    job.write_text('kernels = ["010111010"]\n')
    write_patterns(job_simulation(job), tmp_path / "plain")
    _, schedule, cam, _ = _bench_copy(tmp_path, 4, 150.0, 110.0)
    with evtk.open(cam) as rec, pytest.raises(EvtkError, match="no calibration captures"):
        calibrate(rec, tmp_path / "plain" / "schedule.json")
    # a calibration from another sensor size
    with evtk.open(cam) as rec:
        cal = calibrate(rec, schedule)
    cal.sensor_size = [640, 480]
    save_calibration(tmp_path / "other.toml", cal)
    res = CliRunner().invoke(main, ["reconstruct", str(cam), "--schedule", str(schedule), "--calibration",
                                    str(tmp_path / "other.toml"), "-o", str(tmp_path / "x.h5")])
    assert res.exit_code == 1 and "640x480 sensor" in res.output, res.output
    (tmp_path / "junk.toml").write_text("matrix = 3\n")
    with pytest.raises(EvtkError, match="not an evtk calibration"):
        load_calibration(tmp_path / "junk.toml")


def test_background_activity_is_measured_outside_the_response(tmp_path):
    """Pixels away from the pattern in the settled dark fire at the sensor's background rate (Poisson): the
    estimate is within 10 % of the simulated 5 Hz, and a calibration file keeps it."""
    from evtk.sensor import SensorModel
    from evtk.simulate import Simulation

    sim = Simulation(np.ones((3, 3)), np.ones((16, 16)), repeat=20, calibration=2, seed=5,
                     sensor=SensorModel(background_rate_hz=5.0))
    sim.write(tmp_path / "r.h5")
    with evtk.open(tmp_path / "r.h5") as rec:
        from evtk.reconstruct import schedule_of_record

        cal = calibrate(rec, schedule_of_record(rec.metadata["simulation"]))
    assert cal.background_rate_hz == pytest.approx(5.0, rel=0.1)
    save_calibration(tmp_path / "c.toml", cal)
    assert load_calibration(tmp_path / "c.toml").background_rate_hz == pytest.approx(cal.background_rate_hz)


def test_calibrate_and_simulate_produce_plans(tmp_path):
    """Issue 30: a calibration places a run's plan (region, origin, map, defocus, pixel model) and the reconstruction
    of that plan is the calibrated route's; a simulation's plan is the oracle, read from its record."""
    from evtk.plan import Plan
    from evtk.reconstruct import reconstruct
    from evtk.workflow import reconstruct_recording

    job, schedule, cam, record = _bench_copy(tmp_path, 6, 151.2, 109.4)
    with evtk.open(cam) as rec:
        cal = calibrate(rec, schedule)
        plan = cal.place(schedule)
        assert isinstance(plan, Plan) and plan.region == tuple(cal.region) and plan.cell_map is not None
        assert plan.origin_px == tuple(cal.origin_px) and plan.blur_px == cal.blur_px and plan.record is None
        by_plan = reconstruct(rec, plan)
        by_route = reconstruct_recording(rec, schedule=schedule, calibration=cal)
    assert np.array_equal(by_plan.responses, by_route.responses)
    sim = job_simulation(job)
    oracle = sim.plan()
    assert oracle.record is not None and oracle.region == tuple(record["response_region"])
    with evtk.open(tmp_path / "sim6.h5") as rec:
        assert np.array_equal(reconstruct(rec, oracle).responses, reconstruct(rec).responses)
