"""Event-pixel model: closed-form crossings, shot-noise statistics, extreme light."""

import math

import numpy as np
import pytest

from evtk import EvtkError
from evtk.sensor import (
    PixelState,
    SensorModel,
    log_noise_std,
    pixel_thresholds,
    simulate_pixels,
    time_constant_us,
)


def _step(model, lam0, lam1, n, window_us=1000.0, settle_us=10000.0, seed=1, lead_us=5000.0, theta=None):
    """n pixels: dark lead-in, a step to lam1 for window_us, back to lam0; counts per segment."""
    rng = np.random.default_rng(0)
    rates = np.array([[lam0] * n, [lam1] * n, [lam0] * n], dtype=np.float64)
    lvl = np.log(rates)
    tau = time_constant_us(rates, model)
    s = log_noise_std(rates, model)
    if theta is None:
        on, off = pixel_thresholds(model, n, rng)
    else:
        on = off = np.full(n, theta)
    st = PixelState(lvl[0], s[0], on, off, rng)
    starts = np.array([0.0, lead_us, lead_us + window_us])
    ends = np.array([lead_us, lead_us + window_us, lead_us + window_us + settle_us])
    return simulate_pixels(st, lvl, tau, s, starts, ends, model, seed, count_slot=np.array([0, 1, 2]), n_slots=3)


def _brute_force(l0, l1, theta, refr_us, tau_us, t_end_us, dt=0.01):
    """Event times of one noise-free pixel by fine time steps (independent oracle).

    Exact exponential steps of ``dt``; a crossing inside a step is placed by
    linear interpolation and the wake-up level is taken exactly at its time.
    """
    v = vref = l0
    blind = -1.0
    out = []
    decay = math.exp(-dt / tau_us)
    for i in range(int(t_end_us / dt)):
        t0 = i * dt
        v_prev, v = v, l1 + (v - l1) * decay
        if blind >= 0 and t0 + dt >= blind:
            vref = l1 + (v_prev - l1) * math.exp(-(blind - t0) / tau_us)
            blind = -1.0
        if blind < 0 and abs(v - vref) >= theta:
            b = vref + theta if v > vref else vref - theta
            tc = t0 + dt * (b - v_prev) / (v - v_prev)
            out.append((tc, int(v > vref)))
            blind = tc + refr_us
            # the crossing and the wake-up can both fall in this step only if refr < dt (not tested)
    return out


@pytest.mark.parametrize("lam1,refr", [(2e6, 10.0), (2e7, 2.0), (3e5, 50.0)])
def test_closed_form_matches_brute_force(lam1, refr):
    m = SensorModel(shot_noise=False, theta_mismatch=0.0, refractory_us=refr)
    lam0 = m.dark_current_e_per_s
    t, pix, pol, on, off = _step(m, lam0, lam1, 1, window_us=400.0, settle_us=1.0, lead_us=1.0)
    tau = float(time_constant_us(lam1, m))
    oracle = _brute_force(math.log(lam0), math.log(lam1), 0.2, refr, tau, 400.0)
    mine = sorted(zip(t - 1.0, pol))
    mine = [e for e in mine if 0 <= e[0] < 400]
    assert len(mine) == len(oracle) >= 3
    for (ta, pa), (tb, pb) in zip(mine, oracle):
        assert pa == pb == 1
        assert ta == pytest.approx(tb, abs=1e-3)


def test_slow_pixel_counts_whole_thresholds():
    """Refractory much shorter than tau: an ON count of floor(step / theta), OFF the same coming back."""
    m = SensorModel(shot_noise=False, theta_mismatch=0.0, refractory_us=1.0, tau_min_us=500.0)
    lam0 = m.dark_current_e_per_s
    # steps of n + 1/2 thresholds: the drift during the short refractory periods stays below half a threshold
    for ratio in (math.exp(0.2 * 5.5), math.exp(0.2 * 10.5), math.exp(0.2 * 20.5)):
        _, _, _, on, off = _step(m, lam0, lam0 * ratio, 4, window_us=20000.0, settle_us=200000.0)
        assert np.all(on[1] == math.floor(math.log(ratio) / 0.2))
        assert np.all(off[2] == math.floor(math.log(ratio) / 0.2))


def test_noise_statistics_do_not_move_with_the_step():
    """Stated tolerance: mean counts within 4 % and variances within 15 % of a 20x finer step."""
    fine = SensorModel(noise_step_fraction=0.02)
    default = SensorModel()
    assert default.noise_step_fraction / fine.noise_step_fraction >= 20
    n = 3000
    for lam1 in (1e5, 2e6):
        a = _step(fine, fine.dark_current_e_per_s, lam1, n, seed=3)
        b = _step(default, default.dark_current_e_per_s, lam1, n, seed=4)
        for seg, counts in ((1, 3), (2, 4)):
            ma, mb = a[counts][seg].mean(), b[counts][seg].mean()
            va, vb = a[counts][seg].var(), b[counts][seg].var()
            assert mb == pytest.approx(ma, rel=0.04), (lam1, seg)
            assert vb == pytest.approx(va, rel=0.15), (lam1, seg)


def test_shot_noise_shrinks_and_settles_with_light():
    """Eqs. 9-11: dim light gives a smaller, noisier response; bright light approaches noise-free."""
    noisy = SensorModel(refractory_us=1.0)
    clean = noisy.replace(shot_noise=False, theta_mismatch=0.0)
    lam0 = noisy.dark_current_e_per_s
    means, cvs = [], []
    for ratio in (2.0, 20.0, 2000.0):
        out = _step(noisy, lam0, lam0 * ratio, 2000, window_us=1000.0, theta=0.2)
        net = out[3][1] - out[4][1]  # ON minus OFF in the window: what the step left behind
        means.append(net.mean() / (math.log(ratio) / 0.2))  # fraction of the ideal count
        cvs.append(net.std() / net.mean())
    # the dim pixel is too slow for the window: a smaller share of its step is counted
    # (at 2000x the count is compressed too, but by the refractory period, not by noise)
    assert means[0] < 0.6 < 0.8 < means[1]
    assert cvs[0] > cvs[1] > cvs[2]
    bright = _step(noisy, lam0, lam0 * 2000, 2000, window_us=1000.0, theta=0.2)
    ideal = _step(clean, lam0, lam0 * 2000, 1, window_us=1000.0)
    assert (bright[3][1] - bright[4][1]).mean() == pytest.approx(ideal[3][1][0] - ideal[4][1][0], rel=0.05)


def test_noise_std_formula():
    m = SensorModel()
    lam = np.array([1e3, 1e6, 1e12])
    s = log_noise_std(lam, m)
    np.testing.assert_allclose(s, 1 / np.sqrt(2 * (lam * 1e-6 * m.tau_min_us + m.tau_electrons)))
    assert s[0] < 1 / math.sqrt(2 * m.tau_electrons) and s[2] < 1e-3
    assert np.all(log_noise_std(lam, m.replace(shot_noise=False)) == 0)
    tau = time_constant_us(lam, m)
    assert tau[0] > tau[1] > tau[2] >= m.tau_min_us


def test_far_state_stays_an_exact_gaussian():
    """Far from thresholds the state is carried as mean/variance of the OU process, exactly."""
    m = SensorModel(theta_on=50.0, theta_off=50.0, theta_mismatch=0.0)
    lam = np.array([[1e6], [1e6]])
    s = log_noise_std(lam, m)
    tau = time_constant_us(lam, m)
    st = PixelState(np.array([math.log(1e6) + 3.0]), 0.0, [50.0], [50.0], np.random.default_rng(0))
    st.mean[:] = math.log(1e6) + 3.0
    simulate_pixels(st, np.log(lam), tau, s, np.array([0.0, 100.0]), np.array([100.0, 250.0]), m, 1)
    a = math.exp(-250.0 / tau[0, 0])
    assert st.mean[0] == pytest.approx(math.log(1e6) + 3.0 * a, rel=1e-12)
    assert st.var[0] == pytest.approx(s[0, 0] ** 2 * (1 - a * a), rel=1e-9)


@pytest.mark.parametrize("lam1", [0.0, 1e-3, 1e3, 1e9, 1e15])
def test_extreme_light_is_finite_and_bounded(lam1):
    m = SensorModel(refractory_us=2.0)
    lam0 = m.dark_current_e_per_s
    t, pix, pol, on, off = _step(m, lam0, lam0 + lam1, 200, window_us=1000.0, settle_us=1000.0, lead_us=100.0)
    assert np.all(np.isfinite(t))
    assert np.all((t >= 0) & (t < 2100.0))
    per_pixel = np.bincount(pix, minlength=200)
    assert per_pixel.max() <= 2100.0 / 2.0 + 3  # the refractory period bounds the rate


def test_determinism_and_seed():
    m = SensorModel()
    a = _step(m, 5e4, 2e6, 50, seed=9)
    b = _step(m, 5e4, 2e6, 50, seed=9)
    c = _step(m, 5e4, 2e6, 50, seed=10)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    assert not (len(a[0]) == len(c[0]) and np.array_equal(a[0], c[0]))


@pytest.mark.parametrize("field,value", [("theta_on", 0.0), ("theta_off", -1.0), ("refractory_us", 0.5),
                                         ("dark_current_e_per_s", 0.0), ("tau_min_us", float("nan")),
                                         ("hot_pixel_fraction", 2.0), ("shot_noise", 1), ("background_rate_hz", -1)])
def test_sensor_rejects_bad_values(field, value):
    with pytest.raises(EvtkError, match=field):
        SensorModel(**{field: value})


def test_unknown_sensor_parameter():
    with pytest.raises(EvtkError, match="gamma"):
        SensorModel.from_dict({"gamma": 2})


def test_noisy_event_times_follow_the_noise_free_ones_in_bright_light():
    """With little shot noise, events land where the closed form puts them (to the us)."""
    noisy = SensorModel(theta_mismatch=0.0)
    clean = noisy.replace(shot_noise=False)
    lam0 = noisy.dark_current_e_per_s
    a = _step(noisy, lam0, 1e9, 300, window_us=1000.0, settle_us=1.0, lead_us=1.0, theta=0.2)
    b = _step(clean, lam0, 1e9, 1, window_us=1000.0, settle_us=1.0, lead_us=1.0, theta=0.2)
    first_clean = np.sort(b[0][b[2] == 1])[:5]
    for px in range(0, 300, 30):
        t = np.sort(a[0][(a[1] == px) & (a[2] == 1)])[:5]
        np.testing.assert_allclose(t, first_clean, atol=1.0)


def test_ziggurat_normals_follow_the_normal_law():
    """The pixel model's normal deviates (ziggurat): KS test against the normal CDF, the share beyond the
    ziggurat's base strip (the tail branch) and beyond 5 sd against the analytic tails, and the first four
    moments, over 2 M draws."""
    import numba
    from scipy import stats

    from evtk import _rng
    from evtk._rng import _ZIG_R

    _rng.rng_state(0)  # compiles the module's kernels (evtk._lazyjit): a kernel below calls numba's dispatchers
    normal, rng_state = _rng.normal, _rng.rng_state

    @numba.njit
    def draw(n, seed):
        st = rng_state(seed)
        out = np.empty(n)
        for i in range(n):
            out[i] = normal(st)
        return out

    n = 2_000_000
    x = draw(n, 11)
    assert stats.kstest(x, "norm").pvalue > 1e-3
    for edge in (_ZIG_R, 5.0):  # binomial counts of the two-sided tail, within 5 of their sd
        p = 2 * stats.norm.sf(edge)
        assert abs(np.sum(np.abs(x) > edge) - n * p) < 5 * np.sqrt(n * p) + 1
    assert abs(x.mean()) < 5 / np.sqrt(n) and abs(x.var() - 1) < 5 * np.sqrt(2 / n)
    assert abs(stats.skew(x)) < 5 * np.sqrt(6 / n) and abs(stats.kurtosis(x)) < 5 * np.sqrt(24 / n)
    assert np.sum(x > 0) == pytest.approx(n / 2, abs=5 * np.sqrt(n / 4))


def test_a_noise_free_pixel_state_needs_no_generator():
    """Noise-free pixels start at their light whether or not a generator is given (the count table's state loaded
    numpy.random, 12 ms of a fresh process, for a draw multiplied by 0); pixels with noise still need one."""
    from evtk.sensor import PixelState

    level = np.log(np.array([1e2, 5e3, 7e5]))
    with_rng = PixelState(level, 0.0, np.full(3, 0.2), np.full(3, 0.2), np.random.default_rng(3))
    without = PixelState(level, 0.0, np.full(3, 0.2), np.full(3, 0.2))
    assert np.array_equal(with_rng.mean, without.mean) and np.array_equal(with_rng.vref, without.vref)
    with pytest.raises(EvtkError, match="need an rng"):
        PixelState(level, np.array([0.0, 0.01, 0.0]), np.full(3, 0.2), np.full(3, 0.2))
