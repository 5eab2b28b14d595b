"""One memory budget and one work bound for every command whose work follows from its input (issue 29, item 6).

Each test writes its own tiny hostile file (two events stamped far apart, a huge declared sensor, stamps at
the ends of int64) and checks that the command refuses it in one line before allocating or looping, or gives
a defined answer; and that a normal file still goes through under the default budget.
"""

import json

import numpy as np
import pytest
from click.testing import CliRunner
from conftest import random_events

import evtk
from evtk.cli import main
from evtk.events import TriggerKind, Triggers
from evtk.limits import BASE_WINDOW_WORK, require_window_work, window_work
from evtk.metrics import SinadAccumulator, flip_rates, sinad
from evtk.reconstruct import Windows, accumulate, windows_from_triggers, windows_periodic
from evtk.recover import all_kernels, response_matrix

T_MAX = 2**63 - 1


def _cli(*args):
    r = CliRunner().invoke(main, [str(a) for a in args])
    return r.exit_code, r.output


def _one_line_error(code, out):
    assert code == 1, out
    assert out.startswith("evtk: error: ") and len(out.strip().splitlines()) == 1, out
    assert "Traceback" not in out


def _two_events(path, t, sensor=(32, 24)):
    evtk.write_events(path, evtk.Events(t, [0, 1], [0, 0], [1, 0], sensor))
    return path


# -- a window count from a time span: memory and work, checked before any loop -----------------------------------


@pytest.mark.parametrize("ext", ["aedat4", "h5"])
@pytest.mark.parametrize("command", ["enob", "flips"])
def test_far_stamps_are_refused_naming_the_window_spec_and_the_span(tmp_path, ext, command):
    """2**62 us between two events: 4.6e15 windows; the message says which windows and over which span."""
    path = _two_events(tmp_path / f"far.{ext}", [0, 2**62])
    assert path.stat().st_size < 20_000
    code, out = _cli(command, path, "--window", "period:1000")
    _one_line_error(code, out)
    assert "--window period:1000 over 0 .. 4,611,686,018,427,387,905 us" in out and "MiB" in out, out


@pytest.mark.parametrize("ext", ["aedat4", "h5"])
@pytest.mark.parametrize("command", ["enob", "flips"])
def test_millions_of_empty_windows_are_refused_before_they_are_counted(tmp_path, ext, command):
    """Two events 2e9 us apart cut into 1 ms windows: 2 million windows that fit the memory budget (76 MiB)
    but would take the streamed measurement most of a minute; refused at once, by the work they ask."""
    path = _two_events(tmp_path / f"apart.{ext}", [0, 2 * 10**9])
    code, out = _cli(command, path, "--window", "period:1000")
    _one_line_error(code, out)
    assert "2,000,000 windows" in out and "for 2 events" in out and "period:1000 over 0 .. 2,000,000,001" in out


def test_the_work_bound_grows_with_the_events():
    pixels = 32 * 24
    n_free = BASE_WINDOW_WORK // window_work(1, pixels)
    require_window_work(n_free, pixels, 2, "free")  # any recording may ask this much
    with pytest.raises(evtk.EvtkError, match="more work than the recording holds"):
        require_window_work(n_free + 1, pixels, 2, "two events")
    require_window_work(10 * n_free, pixels, 10 * n_free * (pixels + 256) // 1024, "many events")
    with pytest.raises(evtk.EvtkError, match=r"period:1000 over 0 \.\. 2,000,000,000 us"):
        windows_periodic(0, 2 * 10**9, 1000, events=2)
    assert len(windows_periodic(0, 2 * 10**9, 1000, events=10**6)) == 2 * 10**6  # many events justify the windows


@pytest.mark.parametrize("command", [("enob",), ("flips",), ("reconstruct", "--keep-pixels", "-o", "OUT")])
def test_huge_declared_sensor_is_refused_under_a_small_budget(tmp_path, command):
    """A 2048x2048 sensor holding two events: one window's counts and stages take 256 MiB; the budget is 64.
    (Responses alone need no window's pixels: see the next test.)"""
    path = _two_events(tmp_path / "wide.aedat4", [0, 10_000], sensor=(2048, 2048))
    args = [a if a != "OUT" else tmp_path / "r.h5" for a in command]
    code, out = _cli("--memory-limit-mb", "64", *args[:1], path, *args[1:], "--window", "period:1000")
    _one_line_error(code, out)
    assert "MiB" in out and "64 MiB allowed" in out, out
    assert not (tmp_path / "r.h5").exists()


def test_responses_alone_of_a_huge_declared_sensor_fit_a_small_budget(tmp_path):
    """Without --keep-pixels the fixed windows' net counts go straight to their output cells: the 2048x2048
    sensor's 10 responses fit 64 MiB, and the one event counted lands in the right cell."""
    path = _two_events(tmp_path / "wide.aedat4", [0, 10_000], sensor=(2048, 2048))
    code, out = _cli("--memory-limit-mb", "64", "reconstruct", path, "-o", tmp_path / "r.npz",
                     "--window", "period:1000")
    assert code == 0, out
    got = evtk.load_reconstruction(tmp_path / "r.npz")
    assert got.responses.shape == (10, 16, 16)
    ev = evtk.read_events(path)
    first = ev.t == 0
    cell = (int(ev.y[first][0]) // 128, int(ev.x[first][0]) // 128)
    sign = 1.0 if int(ev.p[first][0]) else -1.0
    expected = np.zeros((10, 16, 16))
    expected[0][cell] = sign / 128**2  # one event's net count, the mean over its cell's 128x128 pixels
    np.testing.assert_allclose(got.responses, expected, rtol=1e-12, atol=0)


def test_a_normal_file_goes_through_under_the_default_budget(tmp_path):
    ev = random_events(200_000, seed=4, sensor_size=(64, 48))
    path = tmp_path / "ok.aedat4"
    evtk.write_events(path, ev)
    windows = (int(ev.t[-1]) + 1 - int(ev.t[0])) // 10_000
    code, out = _cli("enob", path, "--window", "period:10000", "--json")
    assert code == 0, out
    (scene,) = json.loads(out)["scenes"]
    assert scene["repeats"] == windows > 90 and np.isfinite(scene["sinad"]["sinad_db"])
    code, out = _cli("flips", path, "--window", "period:10000", "--json")
    assert code == 0, out
    assert json.loads(out)["rows"][0]["repeats"] == windows


# -- estimates before allocation in the stages themselves ---------------------------------------------------------


def test_accumulate_sizes_its_counts_before_allocating(monkeypatch):
    ev = evtk.Events([0, 5], [0, 1], [0, 0], [1, 0], (2048, 2048))
    win = Windows([0, 3], [3, 6], [0, 1], "test")
    monkeypatch.setenv("EVTK_MEMORY_LIMIT_MB", "16")  # 2 windows x 2048x2048 x 2 x int32 = 64 MiB
    with pytest.raises(evtk.EvtkError, match="counting 2 windows over 2048x2048 pixels"):
        accumulate(ev, win)
    monkeypatch.setenv("EVTK_MEMORY_LIMIT_MB", "100")
    assert accumulate(ev, win).on[0, 0, 0] == 1


def test_metrics_size_their_work(monkeypatch):
    monkeypatch.setenv("EVTK_MEMORY_LIMIT_MB", "64")
    with pytest.raises(evtk.EvtkError, match="SINAD of 1,000 captures of 1,000,000 pixels"):
        SinadAccumulator(1000, (1000, 1000))  # 64 groups x 10^6 pixels x 8 B, twice
    monkeypatch.setenv("EVTK_MEMORY_LIMIT_MB", "1")
    with pytest.raises(evtk.EvtkError, match="flip rates of 100 captures"):
        flip_rates(np.ones((100, 20_000), np.int8))


def test_recovery_sizes_its_candidates_and_its_model(monkeypatch):
    monkeypatch.setenv("EVTK_MEMORY_LIMIT_MB", "4")
    with pytest.raises(evtk.EvtkError, match="65,536 kernels of 4x4"):
        all_kernels(4)
    monkeypatch.setenv("EVTK_MEMORY_LIMIT_MB", "16")
    with pytest.raises(evtk.EvtkError, match="3x3 kernel on 600x600 features"):
        response_matrix(np.ones((600, 600), np.int8), 3)


# -- a defined answer, never NaN ----------------------------------------------------------------------------------


def test_sinad_interval_when_leaving_a_group_out_leaves_no_signal():
    """All the signal in the first of 64 groups of repeats (a few events among many empty windows): leaving
    that group out leaves zero power, so the interval has no finite lower end; it was NaN and an error."""
    x = np.zeros((640, 50))
    x[:10] = np.random.default_rng(0).random((10, 50))
    r = sinad(x)
    assert np.isfinite(r.sinad_db)
    assert r.ci_db[0] == -np.inf and r.ci_db[1] >= r.sinad_db
    assert not np.isnan(r.ci_enob).any()


# -- time stamps at the ends of int64 ----------------------------------------------------------------------------


def test_periodic_windows_never_end_past_the_largest_stamp():
    with pytest.raises(evtk.EvtkError, match="ends past the largest time stamp"):
        windows_periodic(T_MAX - 999, T_MAX + 1, 1000)
    w = windows_periodic(T_MAX - 1999, T_MAX + 1, 1000)
    assert w.t_start_us.tolist() == [T_MAX - 1999] and w.t_end_us.tolist() == [T_MAX - 999]
    assert w.dropped == {"ends past the largest time stamp": 1}
    w = windows_periodic(-(2**63), T_MAX, 2**62, events=2)  # the whole int64 range in three windows
    assert (w.length_us == 2**62).all() and len(w) == 3 and w.t_start_us[0] == -(2**63)


def test_trimming_near_the_largest_stamp_does_not_wrap():
    rising, falling = TriggerKind.EXTERNAL_SIGNAL_RISING_EDGE, TriggerKind.EXTERNAL_SIGNAL_FALLING_EDGE
    trig = Triggers([T_MAX - 100, T_MAX - 10], [rising, falling])
    w = windows_from_triggers(trig, skip_us=20, length_us=2**62)
    assert w.t_start_us.tolist() == [T_MAX - 80] and w.t_end_us.tolist() == [T_MAX - 10]


def test_a_window_longer_than_int64_holds_is_an_error():
    with pytest.raises(evtk.EvtkError, match="longer than 2\\*\\*63 - 1 us"):
        Windows([-(2**63) + 5], [T_MAX - 5], [0], "test")
    rising, falling = TriggerKind.EXTERNAL_SIGNAL_RISING_EDGE, TriggerKind.EXTERNAL_SIGNAL_FALLING_EDGE
    with pytest.raises(evtk.EvtkError, match="longer than 2\\*\\*63 - 1 us"):
        windows_from_triggers(Triggers([-(2**63) + 5, T_MAX - 5], [rising, falling]))


@pytest.mark.parametrize("t", [[T_MAX - 999, T_MAX], [T_MAX - 5000, T_MAX], [-(2**63), -(2**63) + 5000], [7], []],
                         ids=["last-period-past-max", "near-max", "near-min", "one-event", "no-events"])
@pytest.mark.parametrize("command", [("enob",), ("flips",), ("reconstruct", "-o", "OUT")])
def test_extreme_stamps_give_an_answer_or_one_clear_line(tmp_path, t, command):
    path = tmp_path / "x.h5"
    n = len(t)
    evtk.write_events(path, evtk.Events(t, [0] * n, [0] * n, [1] * n, (32, 24)))
    args = [a if a != "OUT" else tmp_path / "r.h5" for a in command]
    code, out = _cli(*args[:1], path, *args[1:], "--window", "period:1000")
    if code:
        _one_line_error(code, out)
        assert "reversed" not in out and "leaves nothing" not in out, out  # what a wrapped int64 said
        assert any(s in out for s in ("no events", "shorter than one period", "largest time stamp",
                                      "captured at least twice")), out
    else:
        assert "nan" not in out.lower(), out
