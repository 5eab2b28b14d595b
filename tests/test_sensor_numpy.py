"""The numpy loop for noise-free pixels against numba's kernel, and the kernels' deferred compiling (issue 32).

``simulate_pixels`` runs evtk's noise-free pixel in numpy (``evtk.sensor._run_pixels_numpy``) while numba is not
loaded, or for many pixels: the count curve of a calibrated reconstruction no longer pays numba's start in a
fresh process. Its counts must be the kernel's, event for event, and its state the kernel's to rounding.
"""

from __future__ import annotations

import copy
import json
import os
import subprocess
import sys
import textwrap
import threading
from pathlib import Path

import numpy as np
import pytest

import evtk.sensor as sensor
from evtk.optics import Bench
from evtk.sensor import PixelState, SensorModel, log_noise_std, simulate_pixels, time_constant_us

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def paths(monkeypatch):
    """``run(numpy, ...)``: simulate_pixels forced onto the numpy loop or numba's kernel, counting the loop's runs."""
    used = []
    loop = sensor._run_pixels_numpy

    def spy(*args):
        used.append(1)
        return loop(*args)

    monkeypatch.setattr(sensor, "_run_pixels_numpy", spy)

    def run(numpy, *args, **kwargs):
        monkeypatch.setattr(sensor, "_NUMPY_MAX_ROUNDS", 10**12 if numpy else -1)
        monkeypatch.setattr(sensor, "_NUMPY_WARM_PIXELS", 0)
        before = len(used)
        out = simulate_pixels(*args, **kwargs)
        assert (len(used) > before) == numpy  # the path asked for is the one taken
        return out

    return run


def _random_run(seed):
    """A random noise-free model and a run of it: thresholds, refractory from 1 us to 5 ms, time constants and
    light from dark to blinding, segments of zero length, one pixel or hundreds, pixels that start blind."""
    rng = np.random.default_rng(seed)
    refr = [1.0, float(rng.uniform(1, 50)), float(rng.uniform(100, 5000))][seed % 3]
    model = SensorModel(theta_on=rng.uniform(0.02, 1.0), theta_off=rng.uniform(0.02, 1.0), theta_mismatch=0.0,
                        refractory_us=refr, tau_min_us=rng.uniform(1, 500), tau_electrons=10 ** rng.uniform(0, 4),
                        dark_current_e_per_s=10 ** rng.uniform(2, 6), shot_noise=False, background_rate_hz=0.0)
    n_pix = [1, 7, 300][seed % 4 % 3]
    n_seg = int(rng.integers(1, 8))
    edges = np.concatenate([[0.0], np.cumsum(rng.choice([0.0, 1.0, 50.0, 1000.0, 20000.0], n_seg))])
    level = np.log(10 ** rng.uniform(2, 11, (n_seg, n_pix)))  # 100 e/s to 1e11 e/s
    th_on = np.maximum(model.theta_on + 0.05 * rng.standard_normal(n_pix), 0.01)
    th_off = np.maximum(model.theta_off + 0.05 * rng.standard_normal(n_pix), 0.01)
    state = PixelState(level[0] + rng.normal(0, 0.5, n_pix), 0.0, th_on, th_off, rng)
    state.blind_until_us = np.where(rng.random(n_pix) < 0.3, rng.uniform(-10, 3000, n_pix), -np.inf)
    slot = rng.integers(-1, 3, n_seg)
    return model, state, level, edges[:-1], edges[1:], slot


def _simulate(run, numpy, model, state, level, starts, ends, slot, emit):
    lam = np.exp(level)
    return run(numpy, state, level, time_constant_us(lam, model), log_noise_std(lam, model), starts, ends, model, 3,
               emit=emit, count_slot=slot, n_slots=3)


def _assert_same(a, b):
    """Counts and events equal; times to 1e-12 relative (numpy's exp and log against the C library's)."""
    for x, y in zip(a[1:], b[1:]):
        np.testing.assert_array_equal(x, y)
    np.testing.assert_allclose(a[0], b[0], rtol=1e-12, atol=1e-9)


@pytest.mark.parametrize("seed", range(60))
def test_numpy_loop_gives_the_kernels_counts_events_and_state(paths, seed):
    """Two calls in a row (the state carried over, the second with other light), events and counts per slot,
    against numba's kernel on the same input."""
    model, state, level, starts, ends, slot = _random_run(seed)
    out = {}
    for numpy in (True, False):
        st = copy.deepcopy(state)
        first = _simulate(paths, numpy, model, st, level, starts, ends, slot, True)
        second = _simulate(paths, numpy, model, st, 0.9 * level + 1.0, starts, ends, slot, seed % 2 == 0)
        out[numpy] = first, second, st
    for a, b in zip(out[True][:2], out[False][:2]):
        _assert_same(a, b)
    st_np, st_nb = out[True][2], out[False][2]
    for name in ("mean", "var", "vref"):
        np.testing.assert_allclose(getattr(st_np, name), getattr(st_nb, name), rtol=0, atol=1e-9)
    np.testing.assert_allclose(st_np.blind_until_us, st_nb.blind_until_us, rtol=1e-12, atol=1e-9)


def test_numpy_loop_on_a_pixel_that_wakes_in_its_events_segment(paths):
    """One pixel stepped from dark to bright: events, each waking after exactly the refractory period in the same
    segment (the kernel's ``tr - t == refr`` branch), then a long blindness across the next segments."""
    for refr in (1.0, 7.0, 30_000.0):
        model = SensorModel(theta_mismatch=0.0, shot_noise=False, refractory_us=refr, background_rate_hz=0.0)
        level = np.log([[1e4], [1e9], [1e9], [1e3], [1e7]])
        starts, ends = np.array([0.0, 500.0, 900.0, 900.0, 5000.0]), np.array([500.0, 900.0, 900.0, 5000.0, 9e4])
        state = PixelState(level[0], 0.0, [0.15], [0.25], np.random.default_rng(0))
        a, b = (_simulate(paths, numpy, model, copy.deepcopy(state), level, starts, ends, np.arange(5) % 3, True)
                for numpy in (True, False))
        assert a[3].sum() + a[4].sum() > (0 if refr > 1000 else 20)
        _assert_same(a, b)


@pytest.mark.parametrize("seed", range(40))
def test_a_noise_free_pixel_s_counts_do_not_depend_on_the_segments_after_them(paths, seed):
    """What the count curve rests on when it leaves out the segments after the last counted one: a noise-free
    pixel is causal, on numpy's loop and numba's kernel alike; the counts of every slot up to a segment are the
    same whether the run stops there or goes on (light, blindness and refractory periods carried across)."""
    model, state, level, starts, ends, slot = _random_run(seed)
    for numpy in (True, False):
        for k in range(1, len(starts) + 1):
            cut = np.where(np.arange(len(starts)) < k, slot, -1)  # the slots counted within the first k segments
            ref = _simulate(paths, numpy, model, copy.deepcopy(state), level, starts, ends, cut, False)
            got = _simulate(paths, numpy, model, copy.deepcopy(state), level[:k], starts[:k], ends[:k], slot[:k],
                            False)
            np.testing.assert_array_equal(got[3], ref[3])
            np.testing.assert_array_equal(got[4], ref[4])


@pytest.mark.parametrize("sensor_changes", [{}, {"theta_on": 0.5, "theta_off": 0.3, "refractory_us": 300.0},
                                            {"tau_min_us": 5.0, "tau_electrons": 3000.0, "theta_on": 0.1},
                                            {"dark_current_e_per_s": 1e3, "refractory_us": 20.0}])
def test_count_curve_is_the_same_on_either_path(monkeypatch, sensor_changes):
    """The calibrated route's count curve (4000 light levels, a few segments) on several sensor models."""
    import importlib

    linearize = importlib.import_module("evtk.reconstruct.linearize")  # the package exports a function of that name
    model = SensorModel(shot_noise=False, theta_mismatch=0.0, background_rate_hz=0.0).replace(**sensor_changes)
    key = json.dumps({"sensor": model.to_dict(), "blank_rate_e_per_s": 1e5, "gain_e_per_s_per_unit": 5e6,
                      "bench": Bench().to_dict(), "window_us": 1000, "settle_us": 13340, "kernel_shape": [3, 3],
                      "skip_us": 0.0, "length_us": None, "points": 4000}, sort_keys=True)
    curves = []
    for rounds in (10**12, -1):
        monkeypatch.setattr(sensor, "_NUMPY_MAX_ROUNDS", rounds)
        monkeypatch.setattr(sensor, "_NUMPY_WARM_PIXELS", 0)
        curves.append(linearize._count_curve.__wrapped__(key))
    np.testing.assert_array_equal(curves[0][1], curves[1][1])
    assert curves[0][1][-1] > 0


def test_noisy_or_stepped_pixels_stay_on_numba(paths):
    """Shot noise, a state with variance, or another physics: the numpy loop does not take them."""
    level = np.log(np.full((2, 5), 1e6))
    for model, var in ((SensorModel(shot_noise=True), 0.0), (SensorModel(shot_noise=False), 1e-4),
                       (SensorModel(shot_noise=False, pixel="v2e"), 0.0)):
        state = PixelState(level[0], 0.0, np.full(5, 0.2), np.full(5, 0.2), np.random.default_rng(0))
        state.var[:] = var
        assert not sensor._numpy_path(state, level, time_constant_us(np.exp(level), model),
                                      log_noise_std(np.exp(level), model), np.zeros(2), np.ones(2), model)


def _fresh(code):
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)


def test_importing_the_sensor_loads_no_compiler_and_a_noise_free_run_none_either():
    """evtk.sensor and evtk._rng imported numba (0.2 s) and the count curve's run started its target (0.35 s more),
    in a fresh process whose read takes 0.1 s."""
    out = _fresh(textwrap.dedent("""
        import sys
        import numpy as np
        import evtk._rng, evtk.sensor as s
        assert "numba" not in sys.modules, "import"
        m = s.SensorModel(shot_noise=False, theta_mismatch=0.0)
        lvl = np.log(np.array([[1e5] * 50, np.geomspace(1e5, 1e9, 50)]))
        st = s.PixelState(lvl[0], 0.0, np.full(50, 0.2), np.full(50, 0.2), np.random.default_rng(0))
        r = s.simulate_pixels(st, lvl, s.time_constant_us(np.exp(lvl), m), s.log_noise_std(np.exp(lvl), m),
                              [0.0, 100.0], [100.0, 3000.0], m, 0, emit=False, count_slot=[-1, 0], n_slots=1)
        assert r[3].sum() > 100
        assert "numba" not in sys.modules, "run"
        """))
    assert out.returncode == 0, out.stderr[-2000:]


def _lazy_modules(tmp_path, monkeypatch, tag):
    """Two modules whose deferred kernels call each other's (imported by name, ``inline="always"`` among them),
    in a cycle."""
    a, b = f"lazy_a_{tag}", f"lazy_b_{tag}"
    (tmp_path / f"{a}.py").write_text(textwrap.dedent(f"""
        from evtk._lazyjit import njit

        @njit()
        def twice_plus_one(x):  # defined before its callee: compiled (wrapped) first
            return twice(x) + 1.0

        @njit(inline="always")
        def twice(x):
            return 2.0 * x

        @njit()
        def back(x):  # calls {b}'s kernel: a cycle between the modules
            return other_plus_one(x)

        def late():
            global other_plus_one
            from {b} import plus_one as other_plus_one
        """))
    (tmp_path / f"{b}.py").write_text(textwrap.dedent(f"""
        import {a}
        from evtk._lazyjit import njit
        from {a} import twice, twice_plus_one

        @njit()
        def plus_one(x):
            return x + 1.0

        @njit()
        def use(x):
            return twice_plus_one(x) + twice(x) + plus_one(x)

        {a}.late()
        """))
    monkeypatch.syspath_prepend(str(tmp_path))
    import importlib

    return importlib.import_module(a), importlib.import_module(b)


def test_deferred_kernels_compile_across_modules(tmp_path, monkeypatch):
    """A kernel calling another module's kernel, which calls its neighbour there: compiling only the caller's
    module left the callee's namespace holding Deferreds, which numba cannot type."""
    from evtk._lazyjit import Deferred

    lazy_a, lazy_b = _lazy_modules(tmp_path, monkeypatch, "seq")
    assert lazy_b.use(1.0) == 7.0
    for module in (lazy_a, lazy_b):
        assert not any(isinstance(v, Deferred) for v in vars(module).values())
    assert lazy_a.twice.targetoptions["inline"] == "always"
    assert lazy_a.back(3.0) == 4.0


def test_deferred_kernels_compile_once_from_many_threads(tmp_path, monkeypatch):
    """The modules' kernels first called from several threads at once, numba's ``njit`` made slow so that the
    threads overlap: a thread that finds a kernel compiled (and so skips the lock) must find every name of its
    module compiled too. Before, ``twice_plus_one`` was marked compiled while ``twice`` was still a Deferred in
    its namespace, and a second thread compiling it then failed in numba's typing."""
    import time

    import numba

    lazy_a, lazy_b = _lazy_modules(tmp_path, monkeypatch, "threads")
    njit = numba.njit
    njit(lambda x: x)(1.0)  # numba's start (its target's registries, 0.3 s) paid outside the race

    def slow_njit(*args, **options):
        time.sleep(0.1)
        return njit(*args, **options)

    monkeypatch.setattr(numba, "njit", slow_njit)
    calls = [(0.0, lazy_a.back, 3.0), (0.15, lazy_b.twice_plus_one, 5.0), (0.15, lazy_b.use, 1.0),
             (0.25, lazy_b.use, 2.0), (0.05, lazy_b.plus_one, 4.0), (0.3, lazy_b.twice, 6.0)]
    results, errors = [], []
    start = threading.Barrier(len(calls))

    def call(delay_s, kernel, x):
        start.wait()
        time.sleep(delay_s)
        try:
            results.append((kernel.__name__, kernel(x)))
        except Exception as exc:  # the test reports it
            errors.append(exc)

    threads = [threading.Thread(target=call, args=c) for c in calls]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert not errors, errors
    assert sorted(results) == [("back", 4.0), ("plus_one", 5.0), ("twice", 12.0), ("twice_plus_one", 11.0),
                               ("use", 7.0), ("use", 12.0)]


def test_a_deferred_kernel_replaced_in_its_module_still_compiles(tmp_path, monkeypatch):
    """A test's spy put in a kernel's place before its first call: the module's kernels were compiled but not the
    one the spy holds, whose call then failed ("'NoneType' object is not callable")."""
    import importlib

    (tmp_path / "lazy_spy.py").write_text(textwrap.dedent("""
        from evtk._lazyjit import njit

        @njit()
        def half(x):
            return 0.5 * x

        @njit()
        def other(x):
            return x
        """))
    monkeypatch.syspath_prepend(str(tmp_path))
    mod = importlib.import_module("lazy_spy")
    original = mod.half
    monkeypatch.setattr(mod, "half", lambda x: original(x))
    assert mod.half(3.0) == 1.5
