"""The timing linearisation's numpy path (used while numba is not loaded) and compiled kernel (used where the
install built it) against numba's scalar kernel."""

import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import evtk
from evtk import _native
from evtk.optics import Bench
from evtk.reconstruct import accumulate, count_curve, timing, windows_from_schedule
from evtk.sensor import SensorModel
from evtk.simulate import Simulation

QUIET = SensorModel(shot_noise=False, background_rate_hz=0.0, theta_mismatch=0.0)


def _meta(sensor, **kw):
    return Simulation(np.ones((3, 3)), np.ones((16, 16)), sensor=sensor, seed=1, **kw).metadata()["simulation"]


def _paths(monkeypatch, func, *args):
    """``func(*args)`` through numba's kernel, and through the other paths: numpy's (numba not loaded) and the
    compiled kernel (where the install built it), as ``(numba's, {path: result})``."""
    monkeypatch.setenv("EVTK_NATIVE", "0")
    monkeypatch.setattr(timing, "numba_ready", lambda: False)
    others = {"numpy": func(*args)}
    monkeypatch.setattr(timing, "numba_ready", lambda: True)
    want = func(*args)
    monkeypatch.delenv("EVTK_NATIVE")
    if _native.enabled() and _native.TIMED_KERNELS:
        calls = []
        monkeypatch.setattr(_native, "_kernel_timing_solve", _spy(_native._kernel_timing_solve, calls))
        others["compiled"] = func(*args)
        assert calls or not want.size  # the kernel solved them, not a fallback
    return want, others


def _spy(real, calls):
    def spy(*args):
        calls.append(args[0].shape)
        return real(*args)

    return spy


def _assert_paths(others, want):
    assert others
    for got in others.values():
        _assert_close(got, want)


def _assert_close(got, want, rel=1e-9):
    assert got.shape == want.shape
    assert np.array_equal(np.isnan(got), np.isnan(want))
    ok = ~np.isnan(want)
    assert np.all(np.abs(got[ok] - want[ok]) <= rel * np.abs(want[ok]))


def _edge_inputs(rng, curve, n_w, n_px, blank, theta=0.2, offset_us=0):
    """Counts and times of every kind: fewer than two events, no first time, last before first, random times
    (mostly no chain's: events closer than the refractory period allows, or out of the count's band), counts at
    and above the curve's top (blinding light), and the whole-us times of noise-free chains after a step ``u``
    with the count the curve gives it, stamped from ``offset_us`` after the step."""
    top = int(curve[1][-1])
    shape = (n_w, n_px)
    n = rng.integers(0, top + 3, shape)
    first = rng.integers(-1, 400, shape)
    last = first + rng.integers(-3, 8000, shape)
    # a chain: E_n = q^(n-1) E_1 - (1 - q^(n-1)) theta / ((1 - q) u), with E = exp(-t / tau)
    u = rng.uniform(0.3, curve[0][-1], shape)
    tau = QUIET.tau_min_us + QUIET.tau_electrons / (blank * np.exp(u) * 1e-6)
    n_chain = np.maximum(np.interp(u, *curve).astype(np.int64) - 1, 2)
    a = rng.uniform(offset_us, offset_us + 300.0, shape)
    q = np.exp(-QUIET.refractory_us / tau)
    e_n = q ** (n_chain - 1) * np.exp(-a / tau) - (1 - q ** (n_chain - 1)) * theta / ((1 - q) * u)
    with np.errstate(invalid="ignore", divide="ignore"):
        b = -tau * np.log(e_n)
    chain = np.isfinite(b) & (b > a)
    kind = rng.integers(0, 8, shape)
    n = np.where(kind == 0, rng.integers(0, 2, shape), n)
    first = np.where(kind == 1, -1, first)
    last = np.where(kind == 2, first - 1 - rng.integers(0, 5, shape), last)
    use = (kind >= 3) & chain
    n = np.where(use, n_chain, n)
    first = np.where(use, np.floor(a - offset_us), first).astype(np.int64)
    last = np.where(use, np.floor(np.where(chain, b, 0.0) - offset_us), last).astype(np.int64)
    return n, first, last


def test_numpy_path_is_taken_while_numba_is_not_loaded(monkeypatch):
    """Without the compiled kernel, with numba not loaded and small work, numba's kernel is never called (so a
    fresh process pays no compiler start here); once numba is loaded, or the work is large enough to pay its start,
    it is. With the compiled kernel, neither numba's nor numpy's path runs, whatever numba's state."""
    meta = _meta(QUIET)
    blank, curve = meta["blank_rate_e_per_s"], count_curve(meta)
    rng = np.random.default_rng(0)
    n, first, last = _edge_inputs(rng, curve, 6, 50, blank)
    monkeypatch.setenv("EVTK_NATIVE", "0")
    monkeypatch.setattr(timing, "numba_ready", lambda: True)
    timing.linearize_by_timing(n, first, last, 0.2, QUIET, blank, curve)  # numba's kernel compiled (put in place)
    calls, by_numpy = [], []
    monkeypatch.setattr(timing, "_timing_solve_jit", _spy(timing._timing_solve_jit, calls))
    monkeypatch.setattr(timing, "_timing_solve_np", _spy(timing._timing_solve_np, by_numpy))
    monkeypatch.setattr(timing, "numba_ready", lambda: False)
    timing.linearize_by_timing(n, first, last, 0.2, QUIET, blank, curve)
    assert calls == [] and by_numpy
    monkeypatch.setattr(timing, "_NUMPY_MAX_PAIRS", n.size - 1)  # large work: numba pays its start
    timing.linearize_by_timing(n, first, last, 0.2, QUIET, blank, curve)
    assert calls
    calls.clear()
    monkeypatch.setattr(timing, "_NUMPY_MAX_PAIRS", n.size)
    monkeypatch.setattr(timing, "numba_ready", lambda: True)
    timing.linearize_by_timing(n, first, last, 0.2, QUIET, blank, curve)
    assert calls
    if not _native.TIMED_KERNELS:
        return
    monkeypatch.delenv("EVTK_NATIVE")
    calls.clear()
    by_numpy.clear()
    for ready in (False, True):
        monkeypatch.setattr(timing, "numba_ready", lambda ready=ready: ready)
        timing.linearize_by_timing(n, first, last, 0.2, QUIET, blank, curve)
    assert calls == [] and by_numpy == []


@pytest.mark.parametrize("seed", range(4))
def test_numpy_path_matches_numba_on_random_and_edge_inputs(monkeypatch, seed):
    meta = _meta(QUIET)
    blank, curve = meta["blank_rate_e_per_s"], count_curve(meta)
    rng = np.random.default_rng(seed)
    theta = rng.uniform(0.15, 0.25, 97)
    n, first, last = _edge_inputs(rng, curve, 40, 97, blank, theta, 37)
    monkeypatch.setattr(timing, "_NUMPY_CHUNK_PAIRS", 500)  # several chunks
    want, got = _paths(monkeypatch, timing.linearize_by_timing, n, first, last, theta, QUIET, blank, curve, 37.0)
    assert np.isfinite(want).mean() > 0.15 and np.isnan(want).mean() > 0.4  # both kinds of answer are exercised
    _assert_paths(got, want)


def test_paths_agree_where_the_secant_steps_fail_and_the_band_brackets_the_step(monkeypatch):
    """Counts at and around the curve's top, long spans and thresholds well below the nominal one: the secant steps
    leave the band or stall for a share of these pairs, which the Illinois method then solves within the band
    (its halvings on both sides); every path gives numba's numbers there too."""
    meta = _meta(QUIET)
    blank, curve = meta["blank_rate_e_per_s"], count_curve(meta)
    top = int(curve[1][-1])
    rng = np.random.default_rng(11)
    shape = (60, 97)
    n = rng.integers(top - 1, top + 3, shape)
    first = rng.integers(0, 300, shape)
    last = first + rng.integers(0, 30_000, shape)
    theta = rng.uniform(0.05, 0.08, shape[1])
    want, got = _paths(monkeypatch, timing.linearize_by_timing, n, first, last, theta, QUIET, blank, curve, 37.0)
    assert np.isfinite(want).mean() > 0.02
    _assert_paths(got, want)


@pytest.mark.parametrize("shape", [(0, 5), (3, 0), (1, 1), (7, 1)])
def test_numpy_path_on_no_windows_no_pixels_one_pixel(monkeypatch, shape):
    meta = _meta(QUIET)
    blank, curve = meta["blank_rate_e_per_s"], count_curve(meta)
    n = np.full(shape, 6)
    first, last = np.full(shape, 20), np.full(shape, 900)
    want, got = _paths(monkeypatch, timing.linearize_by_timing, n, first, last, 0.2, QUIET, blank, curve)
    _assert_paths(got, want)


def test_numpy_path_on_huge_times_where_the_log_form_is_used(monkeypatch):
    """Times long after the step (``b / tau`` past 700, where ``exp(-b/tau)`` underflows): the log form, in
    both paths; and times near the int64 stamps' end give a number or NaN, never inf."""
    meta = _meta(QUIET)
    blank, curve = meta["blank_rate_e_per_s"], count_curve(meta)
    rng = np.random.default_rng(7)
    n = rng.integers(2, 30, (5, 200))
    first = rng.integers(0, 10**6, n.shape)
    last = first + rng.integers(10**5, 10**7, n.shape)
    want, got = _paths(monkeypatch, timing.linearize_by_timing, n, first, last, 0.2, QUIET, blank, curve)
    _assert_paths(got, want)
    a, b = np.full(50, 0.5), np.full(50, 3e6) + np.arange(50)  # b / tau in the thousands
    lr = math.log(blank) + np.linspace(0.5, 5.0, 50)
    f = timing._timing_factor(np.full(50, 4), a, b, lr, QUIET.tau_min_us, QUIET.tau_electrons, QUIET.refractory_us)
    tau = QUIET.tau_min_us + QUIET.tau_electrons / (np.exp(lr) * 1e-6)
    assert np.all(b / tau > 700.0) and np.all(f > 0)
    for k in range(50):
        one = timing._timing_factor_jit(4, a[k], b[k], lr[k], QUIET.tau_min_us, QUIET.tau_electrons,
                                        QUIET.refractory_us)
        assert f[k] == pytest.approx(one, rel=1e-9)
    n = np.array([[2, 3, 40]])
    first, last = np.array([[0, 2**62, 0]]), np.array([[2**62, 2**62 + 9, 2**63 - 2]])
    want, got = _paths(monkeypatch, timing.linearize_by_timing, n, first, last, 0.2, QUIET, blank, curve)
    _assert_paths(got, want)
    assert not any(np.any(np.isinf(v)) for v in got.values())


def test_numpy_path_matches_numba_on_a_simulated_job(monkeypatch):
    """A job's own counts and times (shot noise on, threshold mismatch): the light and the thresholds through
    numpy's path equal numba's; the thresholds, whose numba kernel numpy replaced, equal the mean of the one-pixel
    factor over the windows whose times determine them; the settle path equals its recurrence done pixel by
    pixel."""
    sm = SensorModel()
    sim = Simulation(np.ones((3, 3)), np.ones((16, 16)), bench=Bench(source_extent="point"), sensor=sm, seed=5,
                     flat_field=2)
    meta = sim.metadata()["simulation"]
    region = tuple(meta["response_region"])
    c = accumulate(sim.events(), windows_from_schedule(meta), region, times=True)
    blank, curve = meta["blank_rate_e_per_s"], count_curve(meta)
    want, got = _paths(monkeypatch, timing.linearize_by_timing, c.on, c.on_first_us, c.on_last_us, 0.2, sm, blank,
                       curve, 3.0)
    assert np.isfinite(want).mean() > 0.3
    _assert_paths(got, want)

    ff = np.asarray(meta["schedule"]["kernel_id"]) < 0
    flat_u = np.random.default_rng(1).uniform(1.0, 4.0, c.on.shape[1:])
    theta = timing.timing_thresholds(c.on[ff], c.on_first_us[ff], c.on_last_us[ff], flat_u, sm, blank, 3.0)
    on, first, last = (a[ff].reshape(int(ff.sum()), -1) for a in (c.on, c.on_first_us, c.on_last_us))
    want_theta = np.full(on.shape[1], np.nan)
    for i in range(on.shape[1]):
        total, k = 0.0, 0
        for w in range(on.shape[0]):
            if on[w, i] >= 2 and first[w, i] >= 0:
                f = timing._timing_factor_jit(on[w, i], first[w, i] + 3.5, last[w, i] + 3.5,
                                              math.log(blank) + flat_u.ravel()[i], sm.tau_min_us,
                                              sm.tau_electrons, sm.refractory_us)
                if f > 0:
                    total, k = total + flat_u.ravel()[i] / f, k + 1
        if k:
            want_theta[i] = total / k
    assert np.isfinite(want_theta).mean() > 0.5
    _assert_close(theta.ravel(), want_theta)

    t_on = np.asarray(meta["schedule"]["t_on_us"])
    t_off = np.asarray(meta["schedule"]["t_off_us"])
    u = np.random.default_rng(2).uniform(0.0, 5.0, (t_on.size,) + c.on.shape[1:])
    eps = timing._settle_residual(u, t_on, t_off, sm, blank)
    order = np.argsort(t_on, kind="stable")
    tau_dark = float(timing.time_constant_us(blank, sm))
    flat = u.reshape(u.shape[0], -1)
    for i in range(0, flat.shape[1], 37):
        level, prev_off = 0.0, None
        for w in order:
            if prev_off is not None:
                level *= math.exp(-max(t_on[w] - prev_off, 0) / tau_dark)
            assert eps.reshape(u.shape[0], -1)[w, i] == pytest.approx(level, rel=1e-12, abs=1e-300)
            tau = float(timing.time_constant_us(blank * math.exp(flat[w, i]), sm))
            level = flat[w, i] + (level - flat[w, i]) * math.exp(-max(t_off[w] - t_on[w], 0) / tau)
            prev_off = t_off[w]


def test_small_work_in_a_fresh_process_imports_no_numba_from_the_timing_module():
    """Whatever else imported numba before (the linearisation module does until its kernels are deferred too),
    the timing solve, the thresholds and the settle path on small inputs with numba not loaded do not load it."""
    code = """
import sys
import numpy as np
from evtk.reconstruct import count_curve, timing
from evtk.simulate import Simulation
from evtk.sensor import SensorModel
meta = Simulation(np.ones((3, 3)), np.ones((16, 16)), sensor=SensorModel(), seed=1).metadata()["simulation"]
curve = count_curve(meta)
for name in [m for m in sys.modules if m == "numba" or m.startswith("numba.")]:
    del sys.modules[name]
assert not timing.numba_ready()
n = np.array([[5, 3, 1], [2, 9, 0]])
first, last = np.array([[10, 30, 5], [0, 40, -1]]), np.array([[900, 700, 5], [600, 2000, -1]])
u = timing.linearize_by_timing(n, first, last, 0.2, SensorModel(), 1e5, curve)
th = timing.timing_thresholds(n, first, last, 2.0, SensorModel(), 1e5)
eps = timing._settle_residual(np.ones((2, 3)), np.array([0, 5000]), np.array([3000, 8000]), SensorModel(), 1e5)
print(np.isfinite(u).sum(), np.isfinite(th).sum(), "numba" in sys.modules)
"""
    env = dict(os.environ, PYTHONPATH=str(Path(evtk.__file__).parents[1]))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env=env)
    assert out.returncode == 0, out.stderr
    finite_u, finite_th, numba_loaded = out.stdout.split()
    assert int(finite_u) > 0 and int(finite_th) > 0
    assert numba_loaded == "False"


def test_settling_of_a_pixel_that_follows_the_light_at_once_is_defined():
    # a log-node pixel's time constant is 0: windows back to back (no dark gap) and empty windows (no light)
    # divided 0 by 0, and the settling residual came out NaN, which the reconstruction then carried
    import warnings

    from evtk.sensor import SensorModel

    sm = SensorModel(pixel="log-node")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no division warnings either
        eps = timing._settle_residual(np.ones((3, 2)), np.array([0, 3000, 3000]), np.array([3000, 6000, 3000]), sm,
                                      1e5)
    # it follows the light at once: the first window starts settled; the next ones follow with no dark between,
    # so they start where the light left it (1 log unit up: any time constant's limit as the gap goes to 0)
    np.testing.assert_array_equal(eps, [[0, 0], [1, 1], [1, 1]])
    # with dark between the windows it is back at the dark level at once
    np.testing.assert_array_equal(timing._settle_residual(np.ones((2, 2)), np.array([0, 5000]),
                                                          np.array([3000, 8000]), sm, 1e5), np.zeros((2, 2)))
    # a finite time constant still gives the exponential
    assert timing._decay(np.array([0.0, 10.0]), 5.0).tolist() == [1.0, float(np.exp(-2.0))]


@pytest.mark.skipif(not (_native.BUILT and _native.TIMED_KERNELS), reason="the compiled kernels are not built")
def test_compiled_solve_refuses_buffers_too_short_and_the_wrapper_passes_only_its_forms():
    """The kernel itself refuses rows past the counts, times or thresholds shorter than them and empty or uneven
    bands (before touching memory); the wrapper hands it only int64 and float64 C-contiguous arrays of matching
    shapes, and says False (the caller solves another way) for the rest."""
    n = np.full((4, 3), 5, np.int64)
    t = np.zeros((4, 3), np.int64)
    th, band, out = np.full(3, 0.2), np.linspace(0.0, 5.0, 8), np.empty((4, 3))
    args = (1e-3, 0.0, 1.0, 100.0, 1e5, 1.0)
    kernel = _native._kernel_timing_solve
    with pytest.raises(ValueError, match="rows outside"):
        kernel(n, t, t, th, band, band, out, 3, 0, 5, *args)
    with pytest.raises(ValueError, match="shorter"):
        kernel(n, t[:3], t, th, band, band, out, 3, 0, 4, *args)
    with pytest.raises(ValueError, match="shorter"):
        kernel(n, t, t, th[:2], band, band, out, 3, 0, 4, *args)
    with pytest.raises(ValueError, match="bands"):
        kernel(n, t, t, th, band, band[:-1], out, 3, 0, 4, *args)
    with pytest.raises(ValueError, match="bands"):
        kernel(n, t, t, th, band[:0], band[:0], out, 3, 0, 4, *args)
    forms = [(n.astype(np.int32), t, th, out), (n, t.T.copy().T, th, out), (n, t, th.astype(np.float32), out),
             (n, t, th, out[:, :2]), (n, t, th[:2], out)]
    for nn, tt, tth, oo in forms:
        assert not _native.timing_solve(nn, tt, tt, tth, band, band, oo, (0, 4), *args)
    assert _native.timing_solve(n, t, t, th, band, band, out, (0, 4), *args)
