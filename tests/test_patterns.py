"""Driving the bench: job files, the DMD frames and the schedule, and the simulator taking the same job."""

import json

import numpy as np
import pytest
from click.testing import CliRunner
from PIL import Image

import evtk
from evtk import EvtkError
from evtk.cli import main
from evtk.patterns import dmd_frame, job_simulation, load_job, write_patterns
from evtk.reconstruct import windows_from_triggers

JOB = """
kernels = ["010111010", "101010101"]
signed = true
repeat = 2
flat_field = 2
window_us = 1000
seed = 3
[bench]
power_mw = 20.0
"""


@pytest.fixture
def job(tmp_path):
    path = tmp_path / "job.toml"
    path.write_text(JOB)
    return path


@pytest.mark.parametrize("fmt", ["png", "bmp"])
def test_frames_are_the_passes_upsampled_at_the_dmd_resolution(tmp_path, job, fmt):
    """Every capture's frames decode (with Pillow) to its +/- pass, each element an upsample x upsample block of
    mirrors, centred on a 1-bit frame of the DMD's size; identical frames are written once."""
    sim = job_simulation(job)
    out = write_patterns(sim, tmp_path / "out", fmt)
    doc = json.loads((tmp_path / "out" / "schedule.json").read_text())
    b = sim.bench
    assert out["captures"] == len(sim.schedule) == len(doc["captures"])
    assert doc["dmd"]["kernel_mirrors_per_element"] == b.kernel_mirrors == round(b.varsigma)  # eq. 4
    for c, cap in enumerate(doc["captures"]):
        kpat, fpat = sim._pass_patterns(c)
        for key, pat, up in (("kernel_frame", kpat, b.kernel_mirrors), ("features_frame", fpat, b.feature_upsample)):
            img = Image.open(tmp_path / "out" / cap[key])
            assert img.mode == "1" and img.size == (b.dmd_cols, b.dmd_rows)
            got = np.asarray(img, dtype=bool)
            h, w = pat.shape[0] * up, pat.shape[1] * up
            r0, c0 = (b.dmd_rows - h) // 2, (b.dmd_cols - w) // 2
            want = np.zeros_like(got)
            want[r0:r0 + h, c0:c0 + w] = np.repeat(np.repeat(np.asarray(pat) > 0, up, 0), up, 1)
            assert np.array_equal(got, want), (c, key)
        for col in ("t_on_us", "t_off_us", "kernel_id", "features_id", "kernel_sign", "features_sign", "repeat"):
            assert cap[col] == int(getattr(sim.schedule, col)[c])
    frames = {cap["kernel_frame"] for cap in doc["captures"]}
    assert len(frames) == out["kernel_frames"] == len({(k, s) for k, s in zip(sim.schedule.kernel_id,
                                                                              sim.schedule.kernel_sign)})
    assert not np.asarray(Image.open(tmp_path / "out" / doc["dark_frame"]), dtype=bool).any()
    assert "sensor" not in doc and "gain_e_per_s_per_unit" not in doc  # nothing only the simulator knows


def test_the_simulator_takes_the_same_job_and_its_triggers_match_the_schedule(tmp_path, job):
    res = CliRunner().invoke(main, ["patterns", str(job), "-o", str(tmp_path / "frames"), "--json"])
    assert res.exit_code == 0, res.output
    res = CliRunner().invoke(main, ["simulate", "--job", str(job), "-o", str(tmp_path / "run.aedat4")])
    assert res.exit_code == 0, res.output
    doc = json.loads((tmp_path / "frames" / "schedule.json").read_text())
    with evtk.open(tmp_path / "run.aedat4") as rec:
        win = windows_from_triggers(rec.triggers())
        record = rec.metadata["simulation"]
    assert np.array_equal(win.t_start_us, [c["t_on_us"] for c in doc["captures"]])
    assert np.array_equal(win.t_end_us, [c["t_off_us"] for c in doc["captures"]])
    assert record["kernels"] == doc["kernels"] and record["features"] == doc["features"]
    res = CliRunner().invoke(main, ["simulate", "--job", str(job), "--repeat", "3", "-o", str(tmp_path / "x.h5")])
    assert res.exit_code == 2 and "--repeat" in res.output


@pytest.mark.parametrize("text, match", [
    ("repeat = 2", "names no kernels"),
    ('kernels = ["0101"]\nbogus = 1', "unknown job settings"),
    ('kernels = ["010"]', "square"),
    ('kernels = ["010111010"]\nrepeat = "many"', "whole number"),
    ('kernels = ["010111010"]\nsigned = "yes"', "true or false"),
    ('kernels = ["010111010"]\n[bench]\nnot_a_field = 1', "not_a_field"),
    ('kernels = ["010111010"]\n[bench]\ndmd_cols = 40', "mirrors"),
    ("kernels = [", "not a valid job file"),
])
def test_bad_jobs_are_one_clear_error(tmp_path, text, match):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(EvtkError, match=match):
        write_patterns(job_simulation(path), tmp_path / "out")
    res = CliRunner().invoke(main, ["patterns", str(path), "-o", str(tmp_path / "out2")])
    assert res.exit_code == 1 and res.output.startswith("evtk: error:"), res.output


def test_job_values_in_every_form(tmp_path):
    np.save(tmp_path / "f.npy", np.eye(5, dtype=int))
    (tmp_path / "j.json").write_text(json.dumps({"kernels": [[1, 0], [0, 1]], "features": "f.npy", "repeat": 1}))
    job = load_job(tmp_path / "j.json")
    assert job["kernels"].shape == (2, 2) and job["features"].shape == (5, 5) and job["settle_us"] is None
    frame, at = dmd_frame(np.eye(3), 4, 20, 16)
    assert frame.sum() == 3 * 16 and at == (2, 4)
    with pytest.raises(EvtkError, match="image format"):
        write_patterns(job_simulation(tmp_path / "j.json"), tmp_path / "o", "jpg")


def _camera_copy(sim_path, out_path, offset_us, drop=(), extra=()):
    """What the camera would have written: the events and trigger edges, on its own clock, no evtk metadata;
    trigger edges ``drop`` (indices) lost and ``extra`` (time, kind) edges added."""
    with evtk.open(sim_path) as rec:
        ev, tr, record = rec.events(), rec.triggers(), rec.metadata["simulation"]
    keep = np.ones(len(tr), bool)
    keep[list(drop)] = False
    t = np.r_[tr.t[keep], [e[0] for e in extra]].astype(np.int64) + offset_us
    kind = np.r_[tr.kind[keep], [e[1] for e in extra]].astype(np.uint8)
    order = np.argsort(t, kind="stable")
    evtk.write_events(out_path, evtk.Events(ev.t + offset_us, ev.x, ev.y, ev.p, ev.sensor_size),
                      evtk.Triggers(t[order], kind[order]))
    return record


def test_bench_reconstruction_from_the_schedule_alone(tmp_path):
    """patterns -> a simulated run -> the camera's copy (own clock, a lost edge, a spurious pair, no record) ->
    reconstruct --schedule: every window is matched to its capture, the pair with a lost pass is left out and
    reported, and with flat-field calibration the responses correlate with the job's digital correlation nearly
    as well as the oracle reconstruction that inverts the simulator's own pixel model."""
    from evtk.plan import as_plan
    from evtk.reconstruct import reconstruct

    job = tmp_path / "job.toml"
    job.write_text('kernels = ["010111010"]\nrepeat = 3\nflat_field = 2\nwindow_us = 1000\nseed = 2\n')
    assert CliRunner().invoke(main, ["patterns", str(job), "-o", str(tmp_path / "p")]).exit_code == 0
    assert CliRunner().invoke(main, ["simulate", "--job", str(job), "-o", str(tmp_path / "sim.h5")]).exit_code == 0
    record = _camera_copy(tmp_path / "sim.h5", tmp_path / "cam.aedat4", 7_000_003, drop=[6],
                          extra=[(10, 1), (20, 2)])
    with evtk.open(tmp_path / "sim.h5") as rec:
        oracle = reconstruct(rec)
    with evtk.open(tmp_path / "cam.aedat4") as rec:
        assert rec.metadata.get("simulation") is None
        placed = as_plan(tmp_path / "p" / "schedule.json").replace(region=record["response_region"],
                                                                   origin_px=record["response_origin_px"])
        bench = reconstruct(rec, placed, linearization="exp(n theta)")
        plain = reconstruct(rec, placed, linearization="exp(n theta)", flat_field=False)
    m = bench.summary["match"]
    assert m["offset_us"] == 7_000_003 and m["missing"] == [3] and m["extra"] == 1 and m["matched"] == 4
    assert bench.summary["pairs_left_out"] == [(0, 0, 1)] and len(bench.pairs) == 2
    assert bench.summary["binarize"] == "mean" and bench.summary["flat_field_captures"] == 2
    corr, oracle_corr = bench.summary["error"]["correlation"], oracle.summary["error"]["correlation"]
    assert corr > 0.85 and corr > oracle_corr - 0.08, (corr, oracle_corr)
    assert corr > plain.summary["error"]["correlation"] + 0.1  # the flat field is what makes it work
    region = ",".join(map(str, record["response_region"]))
    res = CliRunner().invoke(main, ["reconstruct", str(tmp_path / "cam.aedat4"), "--schedule",
                                    str(tmp_path / "p" / "schedule.json"), "--region", region, "-o",
                                    str(tmp_path / "r.h5")])
    assert res.exit_code == 0 and "missing [3], 1 extra" in res.output, res.output
    assert "digital correlation of the schedule's patterns" in res.output
    assert evtk.load_reconstruction(tmp_path / "r.h5").responses.shape == (2, 16, 16)
    for bad, msg in ((["--region", region, "--window", "triggers"], "leave out --window"),
                     (["--oracle"], "--oracle reads the simulation record"), (["--origin-px", "3,4"], "with --region")):
        res = CliRunner().invoke(main, ["reconstruct", str(tmp_path / "cam.aedat4"), "--schedule",
                                        str(tmp_path / "p" / "schedule.json"), "-o", str(tmp_path / "x.h5"), *bad])
        assert res.exit_code == 2 and msg in res.output, res.output


def test_a_schedule_that_does_not_belong_to_the_recording_is_one_error(tmp_path):
    from evtk.plan import as_plan
    from evtk.reconstruct import load_schedule, reconstruct

    (tmp_path / "s.json").write_text('{"evtk_schedule_version": 1, "captures": [{"capture": 0}]}')
    with pytest.raises(EvtkError, match="malformed"):
        load_schedule(tmp_path / "s.json")
    (tmp_path / "n.json").write_text("[1, 2]")
    with pytest.raises(EvtkError, match="not an evtk schedule"):
        load_schedule(tmp_path / "n.json")
    job = tmp_path / "job.toml"
    job.write_text('kernels = ["010111010"]\nflat_field = 0\n')
    write_patterns(job_simulation(job), tmp_path / "p")
    ev = evtk.Events([5, 6], [0, 1], [0, 0], [1, 0], (320, 240))
    evtk.write_events(tmp_path / "none.h5", ev)
    with evtk.open(tmp_path / "none.h5") as rec, pytest.raises(EvtkError, match="no complete window"):
        reconstruct(rec, as_plan(tmp_path / "p" / "schedule.json").replace(region=(0, 10, 0, 10)),
                    linearization="exp(n theta)")
