"""Every value a user can write in a job, bench, schedule, calibration or simulation record is checked where it is
read: a hostile value is a clean EvtkError naming the file and key, or a correct run; never a traceback, NaN, a
silently wrong answer or an allocation before the check."""

from __future__ import annotations

import copy
import json
import math
import os
import re
import signal

import numpy as np
import pytest

from evtk import EvtkError

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib
from evtk import io as evio
from evtk.calibrate import calibrate, load_calibration, save_calibration
from evtk.optics import Bench, load_bench, save_bench
from evtk.patterns import job_simulation, load_job, write_patterns
from evtk.reconstruct import load_schedule, nominal_placement, schedule_of_record
from evtk.simulate import SimulationRecord

HOSTILE = [math.inf, -math.inf, math.nan, 1e308, -1e308, 2 ** 63, 10 ** 18, 0, -3, -5, 0.5, "ab", "", [], [[]],
           [1e308, 1e308], True, None]

JOB = {"kernels": ["010111010"], "repeat": 1, "flat_field": 1, "calibration": 1, "levels": 3, "window_us": 1000}


def _toml_scalar(v):
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf") if math.isinf(v) else repr(v)
    if isinstance(v, (int, str)):
        return json.dumps(v) if isinstance(v, str) else str(v)
    return "[" + ", ".join(_toml_scalar(x) for x in v) + "]"


def _write(path, data):
    """``data`` as TOML (``.toml``: nan and inf written as TOML has them; None keys left out) or JSON (NaN and
    Infinity as Python's json writes them)."""
    path = str(path)
    if path.endswith(".toml"):
        flat = [f"{k} = {_toml_scalar(v)}" for k, v in data.items() if v is not None and not isinstance(v, dict)]
        for k, v in data.items():
            if isinstance(v, dict):
                flat += ["", f"[{k}]"] + [f"{kk} = {_toml_scalar(vv)}" for kk, vv in v.items() if vv is not None
                                           and not isinstance(vv, dict)]
        text = "\n".join(flat) + "\n"
    else:
        text = json.dumps(data)
    with open(path, "w") as f:
        f.write(text)
    return path


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    """A small run: its job, bench, schedule.json, calibration and simulation record."""
    d = tmp_path_factory.mktemp("settings")
    _write(d / "job.json", JOB)
    sim = job_simulation(d / "job.json")
    sim.write(d / "rec.aedat4")
    write_patterns(sim, d / "pat")
    with evio.open(d / "rec.aedat4") as rec:
        cal = calibrate(rec, d / "pat" / "schedule.json")
    save_calibration(d / "cal.json", cal)
    save_bench(d / "bench.json", Bench())
    return {"dir": d, "job": JOB, "bench": json.loads((d / "bench.json").read_text()),
            "schedule": json.loads((d / "pat" / "schedule.json").read_text()),
            "cal": json.loads((d / "cal.json").read_text()), "record": sim.record().to_dict(), "sim": sim}


def _finite(*values):
    for v in values:
        a = np.asarray(v, dtype=np.float64)
        assert np.all(np.isfinite(a)), f"a non-finite result {v!r}"


def _use_job(path):
    job = load_job(path)
    sim = job_simulation(path)
    rec = sim.record()
    _finite(rec.response_origin_px, rec.gain_e_per_s_per_unit, rec.blank_rate_e_per_s, sim.settle_us)
    return job


def _use_bench(path):
    b, _ = load_bench(path)
    _finite(b.sigma, b.varsigma, b.stride_eff, b.min_window_us, b.pixel_cells, b.electrons_per_s_per_unit((3, 3)))
    return b


def _use_schedule(path):
    s = load_schedule(path)
    region, origin = nominal_placement(s)
    _finite(region, origin, s.schedule.t_on_us)
    return s


def _use_calibration(path):
    cal = load_calibration(path)
    x0, x1, y0, y1 = cal.region
    corners = np.array([[x0, y0], [x1, y1]], np.float64)
    _finite(cal.cell_map().to_cells(corners), cal.to_pixels(np.zeros((1, 2))), cal.blur_px, cal.step_px)
    return cal


def _use_record(d):
    r = SimulationRecord.from_dict(d)
    s = schedule_of_record(r)
    m = r.placement()
    _finite(r.blur_px, nominal_placement(s)[1], r.response_origin_px)
    if m is not None:
        _finite(m.to_cells(np.array([[10.0, 10.0]])))
    return r


def _mutations(doc, tables):
    """(label, mutated document setter) for every top-level key and every key of the named sub-tables."""
    keys = [(k,) for k in doc]
    for t in tables:
        sub = doc.get(t)
        if isinstance(sub, dict):
            keys += [(t, k) for k in sub]
        elif isinstance(sub, list) and sub and isinstance(sub[0], dict):
            keys += [(t, 0, k) for k in sub[0]]
    return keys


def _set(doc, key, value):
    out = copy.deepcopy(doc)
    node = out
    for k in key[:-1]:
        node = node[k]
    node[key[-1]] = value
    return out


def _check_all(doc, tables, write_and_use, value):
    """Mutate each key to ``value``; collect every outcome that is neither a success nor an EvtkError."""
    bad = []

    def hang(*_):
        raise TimeoutError("still running after 60 s")

    old = signal.signal(signal.SIGALRM, hang)
    try:
        for key in _mutations(doc, tables):
            signal.alarm(60)  # a hang is a failure too
            try:
                write_and_use(_set(doc, key, value))
            except EvtkError as exc:
                assert str(exc) and "\n" not in str(exc).strip(), str(exc)
            except Exception as exc:  # noqa: BLE001 - what this test looks for
                bad.append(f"{'.'.join(map(str, key))} = {value!r}: {type(exc).__name__}: {exc}")
            finally:
                signal.alarm(0)
    finally:
        signal.signal(signal.SIGALRM, old)
    return bad


@pytest.mark.parametrize("value", HOSTILE, ids=repr)
@pytest.mark.parametrize("kind", ["job.toml", "job.json", "bench.toml", "bench.json", "schedule.json", "cal.toml",
                                  "cal.json", "record"])
def test_every_key_of_every_settings_file_set_to_a_hostile_value_is_a_clean_error_or_a_correct_run(
        base, tmp_path, kind, value):
    if kind == "record":
        bad = _check_all(base["record"], ("bench", "sensor", "schedule"), _use_record, value)
    else:
        name, ext = kind.split(".")
        doc = {"job": dict(base["job"], bench={"u_mm": 300.0, "dmd_cols": 1920},
                           sensor={"theta_on": 0.2, "tau_min_us": 100.0, "noise_step_max_us": 1000.0},
                           camera={"rotation_deg": 0.5, "defocus_px": 0.2, "tilt": [0.01, 0.0],
                                   "offset_px": [0.5, -0.5], "k1": 0.01}),
               "bench": base["bench"], "schedule": base["schedule"], "cal": base["cal"]}[name]
        use = {"job": _use_job, "bench": _use_bench, "schedule": _use_schedule, "cal": _use_calibration}[name]
        tables = {"job": ("bench", "sensor", "camera"), "bench": (), "schedule": ("calibration", "captures", "bench"),
                  "cal": ("pixel_model",)}[name]
        path = tmp_path / kind

        def write_and_use(d):
            return use(_write(path, d))

        bad = _check_all(doc, tables, write_and_use, value)
    assert not bad, "\n".join(bad)


def _schedule(base, tmp_path, **changes):
    doc = copy.deepcopy(base["schedule"])
    for k, v in changes.items():
        if k == "dot_spacing":
            doc["calibration"][k] = v
        elif k in ("kernel_id", "features_id"):
            doc["captures"][-1][k] = v
        else:
            doc[k] = v
    return _write(tmp_path / "schedule.json", doc)


@pytest.mark.parametrize("key, value, needle", [
    ("dot_spacing", -3, "dot_spacing = -3 must be a whole number from 2"),
    ("window_us", -5, "window_us = -5 must be a whole number from 1"),
    ("kernel_id", -9, "kernel_id = -9 names no pattern"),
    ("kernel_id", 7, "kernel_id = 7 names no pattern"),
    ("features_id", -7, "features_id = -7 names no pattern"),
])
def test_schedule_values_that_would_silently_change_the_result_are_refused(base, tmp_path, key, value, needle):
    path = _schedule(base, tmp_path, **{key: value})
    with pytest.raises(EvtkError, match=needle) as err:
        load_schedule(path)
    assert str(path) in str(err.value)


def test_schedule_dot_spacing_refused_before_calibrate_places_wrong_dots(base, tmp_path):
    path = _schedule(base, tmp_path, dot_spacing=-3)
    with evio.open(base["dir"] / "rec.aedat4") as rec, pytest.raises(EvtkError, match="dot_spacing"):
        calibrate(rec, path)


@pytest.mark.parametrize("key, value, needle", [
    ("blur_px", 99.9, r"blur_px = 99.9 must be a finite number from 0 to 4"),
    ("origin_px", [float("nan"), 100.0], "origin_px"),
    ("origin_px", [1e308, 100.0], "origin_px"),
    ("origin_px", [100.0, 100.0], "not where the matrix puts cell"),
    ("matrix", [[1.0, 2.0, 3.0], [2.0, 4.0, 6.0], [0.0, 0.0, 1.0]], "singular"),
    ("matrix", [[1.0, 0.0, 150.0], [0.0, 1.0, 110.0], [0.1, 0.0, -1.0]], "infinity"),
    ("region", [0, 1000, 0, 10], "region"),
    ("step_px", -1.0, "step_px"),
])
def test_calibration_values_no_fit_could_give_are_refused(base, tmp_path, key, value, needle):
    doc = dict(base["cal"], **{key: value})
    path = tmp_path / "cal.toml"
    _write(path, doc)
    with pytest.raises(EvtkError, match=needle) as err:
        load_calibration(path)
    assert str(path) in str(err.value)


@pytest.mark.parametrize("origin", ["ab", [float("nan"), 1.0], [1e308, 1e308], [1.0]])
def test_bench_origin_that_is_not_a_pixel_is_one_error(tmp_path, origin):
    path = tmp_path / "bench.json"
    path.write_text(json.dumps({"origin_px": origin}).replace("NaN", "1e999"))
    with pytest.raises(EvtkError, match="origin_px"):
        load_bench(path)


def test_record_with_a_bad_origin_or_unknown_pattern_is_refused(base):
    for key, value in (("response_origin_px", [float("nan"), 1.0]), ("response_origin_px", [1e308, 0.0]),
                       ("window_us", -5), ("dot_spacing", -3)):
        with pytest.raises(EvtkError, match=key):
            SimulationRecord.from_dict(dict(base["record"], **{key: value}))
    sched = dict(base["record"]["schedule"], kernel_id=[-9] + base["record"]["schedule"]["kernel_id"][1:])
    with pytest.raises(EvtkError, match="names no pattern"):
        SimulationRecord.from_dict(dict(base["record"], schedule=sched))


@pytest.mark.parametrize("name", ["job.toml", "bench.toml", "cal.toml", "schedule.json"])
def test_a_settings_file_that_is_a_device_is_refused_unread(name, tmp_path):
    if not os.path.exists("/dev/zero"):
        pytest.skip("no /dev/zero")
    link = tmp_path / name
    link.symlink_to("/dev/zero")
    reader = {"job": load_job, "bench": load_bench, "cal": load_calibration, "schedule": load_schedule}
    with pytest.raises(EvtkError, match="regular file"):
        reader[name.split(".")[0]](link)


def test_a_settings_file_past_the_size_cap_is_refused(tmp_path):
    path = tmp_path / "job.toml"
    with open(path, "w") as f:
        f.write('kernels = ["1"]\n')
        f.write(("#" * 1023 + "\n") * (17 * 1024))
    with pytest.raises(EvtkError, match="too large"):
        load_job(path)


def test_a_huge_dmd_is_refused_before_its_frames_are_allocated(tmp_path, monkeypatch):
    job = tmp_path / "job.toml"
    job.write_text('kernels = ["1"]\n[bench]\ndmd_cols = 60000\ndmd_rows = 60000\n')
    with pytest.raises(EvtkError, match="dmd_cols = 60000 must be a whole number from 1 to 16384"):
        load_job(job)
    # within the physical range, the frame is still sized against the budget first
    monkeypatch.setenv("EVTK_MEMORY_LIMIT_MB", "64")
    job.write_text('kernels = ["1"]\n[bench]\ndmd_cols = 16000\ndmd_rows = 16000\n')
    with pytest.raises(EvtkError, match="DMD frame would need"):
        write_patterns(job_simulation(job), tmp_path / "out")
    assert not list((tmp_path / "out").rglob("*.png"))


def test_a_job_of_a_hundred_thousand_repeats_is_sized_before_it_runs(tmp_path):
    path = _write(tmp_path / "job.toml", dict(JOB, repeat=100000))
    with pytest.raises(EvtkError, match=r"100,000 repeats.*fewer repeats") as err:
        job_simulation(path)
    assert str(path) in str(err.value)


def test_a_job_with_values_in_range_still_runs_and_keeps_them(tmp_path):
    path = _write(tmp_path / "job.toml", dict(JOB, repeat=2, dot_spacing=3, seed=2 ** 63 - 1, settle_us=20000))
    job = load_job(path)
    assert (job["repeat"], job["dot_spacing"], job["seed"], job["settle_us"]) == (2, 3, 2 ** 63 - 1, 20000)
    assert job_simulation(path).settle_us == 20000


def test_patterns_draws_each_distinct_frame_once_whatever_the_repeats(tmp_path):
    path = _write(tmp_path / "job.toml", dict(JOB, repeat=50, calibration=0, levels=0))
    summary = write_patterns(job_simulation(path), tmp_path / "out")
    assert summary["captures"] == 51
    assert summary["kernel_frames"] == 2 and summary["features_frames"] == 2  # flat fields and the one pair


def test_a_pattern_image_is_sized_from_its_header_before_it_is_decoded(tmp_path, monkeypatch):
    from PIL import Image

    from evtk.simulate import load_patterns

    png = tmp_path / "features.png"
    Image.new("1", (3000, 3000)).save(png)  # a few KiB that decode to 9 million pixels (72 MB as float64)
    monkeypatch.setenv("EVTK_MEMORY_LIMIT_MB", "16")
    with pytest.raises(EvtkError, match=r"features image.*3000x3000"):
        load_patterns(png, "features")
    job = _write(tmp_path / "job.toml", {"kernels": ["1"], "features": "features.png"})
    with pytest.raises(EvtkError, match=r"features image.*3000x3000"):
        load_job(job)


def test_a_pattern_array_is_sized_from_its_header_before_it_is_read(tmp_path, monkeypatch):
    from evtk.simulate import load_patterns

    npy = tmp_path / "k.npy"
    np.save(npy, np.zeros((64, 512, 512), np.int8))
    monkeypatch.setenv("EVTK_MEMORY_LIMIT_MB", "4")
    with pytest.raises(EvtkError, match=r"kernel .*k\.npy"):
        load_patterns(npy, "kernel")
    np.save(npy, np.zeros((2, 2, 2, 2), np.int8))
    with pytest.raises(EvtkError, match=r"\(h, w\) or \(n, h, w\)"):
        load_patterns(npy, "kernel")


@pytest.mark.parametrize("key, value", [("theta_on", 1e18), ("theta_mismatch", 1e308), ("tau_min_us", 1e9),
                                        ("noise_step_fraction", 1e-300), ("noise_step_max_us", 1e-300)])
def test_sensor_values_that_overflow_or_never_finish_are_refused_where_the_job_is_read(tmp_path, key, value):
    """theta_on = 1e18 indexed outside a pixel's events, tau_min_us = 1e9 asked for 380 GiB, a noise step of
    1e-300 us never reached the end of a window."""
    path = _write(tmp_path / "job.json", dict(JOB, sensor={key: value}))
    with pytest.raises(EvtkError, match=f"sensor {key}") as err:
        load_job(path)
    assert str(path) in str(err.value)


def _cli(*args):
    from click.testing import CliRunner

    from evtk.cli import main

    r = CliRunner().invoke(main, list(map(str, args)))
    return r.exit_code, r.output


def test_the_commands_print_one_line_naming_the_file_and_key(base, tmp_path):
    d = base["dir"]
    bench = tmp_path / "bench.toml"
    bench.write_text('origin_px = "ab"\n')
    code, out = _cli("simulate", "--bench", bench, "-o", tmp_path / "s.aedat4")
    assert code == 1 and "origin_px" in out and str(bench) in out and len(out.strip().splitlines()) == 1, out
    cal = tmp_path / "cal.json"
    cal.write_text(json.dumps(dict(base["cal"], blur_px=99.9)))
    code, out = _cli("reconstruct", d / "rec.aedat4", "--schedule", d / "pat" / "schedule.json", "--calibration", cal,
                     "-o", tmp_path / "r.h5")
    assert code == 1 and "blur_px = 99.9" in out and len(out.strip().splitlines()) == 1, out
    code, out = _cli("calibrate", d / "rec.aedat4", "--schedule", _schedule(base, tmp_path, dot_spacing=-3),
                     "-o", tmp_path / "c.toml")
    assert code == 1 and "dot_spacing = -3" in out and len(out.strip().splitlines()) == 1, out
    job = _write(tmp_path / "job.toml", dict(JOB, window_us=-5))
    code, out = _cli("patterns", job, "-o", tmp_path / "frames")
    assert code == 1 and "window_us = -5" in out and len(out.strip().splitlines()) == 1, out
    assert not list(tmp_path.glob("*.h5")) and not (tmp_path / "c.toml").exists()


def test_the_validator_tells_numbers_from_flags_text_and_overflow():
    from evtk.settings import Spec, check_array, check_value

    count = Spec("int", 1, 10 ** 7)
    assert check_value("f", "repeat", 2.0, count) == 2 and type(check_value("f", "repeat", 2.0, count)) is int
    for bad in (2.5, True, "3", None, math.inf, 2 ** 63, 10 ** 18, 0, [], {}):
        with pytest.raises(EvtkError, match=r"f: repeat = .* must be a whole number from 1 to 10000000"):
            check_value("f", "repeat", bad, count)
    with pytest.raises(EvtkError, match="must be a positive finite number"):
        check_value("f", "u_mm", -3, Spec("float", 0, 1e6, lo_open=True))
    assert check_value("f", "seed", None, Spec("int", 0, 5, optional=True)) is None
    assert check_array("f", "k", [[0, 1], [1, 0]], 2, -1, 1).dtype == np.int64
    for bad, needle in (([[0, 1], [1]], "equal length"), ([[0, "a"]], "text"), ([], "empty"), ([[2.0 ** 70]], "int64"),
                        ([[0.5]], "fraction"), ([[math.nan]], "NaN"), ([[2]], "holds 2"), ([2 ** 64 + 5], "int64")):
        with pytest.raises(EvtkError, match=needle):
            check_array("f", "k", bad, (1, 2), -1, 1 if bad != [[2.0 ** 70]] else None)


def test_a_calibration_of_another_response_size_is_refused(base, tmp_path):
    from evtk.workflow import reconstruct_recording

    cal = dict(base["cal"], response_shape=[base["cal"]["response_shape"][0] + 4, base["cal"]["response_shape"][1]])
    path = tmp_path / "cal.json"
    path.write_text(json.dumps(cal))
    with evio.open(base["dir"] / "rec.aedat4") as rec, pytest.raises(EvtkError, match="response"):
        reconstruct_recording(rec, schedule=base["dir"] / "pat" / "schedule.json", calibration=load_calibration(path))


def test_toml_text_reads_back_exactly():
    """The TOML evtk writes (tomli-w) reads back to the same table: every float to the last bit, text with
    quotes, escapes, control characters and characters beyond the BMP (the hand-written writer spelt those as JSON
    surrogate pairs, which no TOML reader accepts), nested arrays and a sub-table."""
    from evtk.settings import toml_text

    table = {
        "third": 0.1 + 0.2, "tiny": 5e-324, "huge": 1.7976931348623157e308, "neg": -0.0, "big": 2 ** 62,
        "flag": False, "label": 'say "hi"\\ \t\x7f \U0001F600 é', "matrix": [[1.0, 1e-300, -3.5], [0, 1, 2]],
        "empty": [], "np_float": np.float64(1) / 3, "np_int": np.int64(-7), "np_bool": np.bool_(True),
        "sensor": {"theta_on": 0.123456789012345678, "times_us": [1.0, 2.5e6], "name": "dvx"},
    }
    text = toml_text(table, "bench", comment="evtk bench\nsecond line")
    assert text.startswith("# evtk bench\n# second line\n")
    back = tomllib.loads(text)
    want = dict(table, np_float=float(table["np_float"]), np_int=-7, np_bool=True)
    assert back == want
    assert math.copysign(1, back["neg"]) == -1 and type(back["np_int"]) is int


@pytest.mark.parametrize("value, named", [(None, "k"), (math.nan, "k"), ([1.0, math.inf], "k[1]"),
                                          ({"inner": -math.inf}, "k.inner"), (object(), "k"), (b"raw", "k")])
def test_toml_text_refuses_what_toml_cannot_hold(value, named):
    from evtk.settings import toml_text

    with pytest.raises(EvtkError, match=rf"cannot store {re.escape(named)} = .* in a calibration file"):
        toml_text({"k": value}, "calibration")


def test_saved_bench_and_calibration_toml_read_back(tmp_path):
    """save_bench writes its TOML with tomli-w; what load_bench reads is what was saved."""
    b = Bench()
    save_bench(tmp_path / "b.toml", b, {"theta_on": 0.1 + 0.2})
    got, sensor = load_bench(tmp_path / "b.toml")
    assert got == b and sensor == {"theta_on": 0.1 + 0.2}
    with open(tmp_path / "b.toml", "rb") as f:
        assert tomllib.load(f) == dict({k: v for k, v in b.to_dict().items() if v is not None},
                                       sensor={"theta_on": 0.1 + 0.2})
