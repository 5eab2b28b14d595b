"""SINAD/ENOB, flip rates and the Poisson factors against analytic results and independent oracles."""

import itertools
import json
import math

import numpy as np
import pytest
from scipy import stats

from evtk import EvtkError
from evtk.metrics import (
    capture_terms,
    cumulative_factor,
    enob_bits,
    flip_rates,
    log_cumulative_factor,
    lowest_cumulative_factor,
    poisson_log_pmf,
    poisson_pmf,
    sinad,
)


@pytest.mark.parametrize("snr_db", [0.0, 20.0, 48.0, 90.0])
def test_gaussian_noise_of_known_snr_gives_its_enob(snr_db):
    """Signal power S and noise variance N: SINAD = 10 log10((S + N) / N), eq. 8's ENOB within 0.05 bits."""
    rng = np.random.default_rng(int(snr_db))
    signal = rng.choice([-1.0, 1.0], 4096) * 3.0  # power 9
    sigma = math.sqrt(9.0 / 10 ** (snr_db / 10))
    x = signal + rng.normal(0.0, sigma, (20, signal.size))
    r = sinad(x)
    expected_db = 10 * math.log10((9.0 + sigma ** 2) / sigma ** 2)
    assert abs(r.enob_bits - enob_bits(expected_db)) < 0.05
    assert r.ci_db[0] <= r.sinad_db <= r.ci_db[1]
    assert r.ci_db[0] - 0.1 < expected_db < r.ci_db[1] + 0.1
    assert not r.noise_free and r.repeats == 20 and r.pixels == 4096


@pytest.mark.parametrize("lam", [1e-3, 1e-1, 1.0, 10.0, 1e3, 1e6, 1e9])
def test_poisson_counts_give_the_sinad_their_moments_imply(lam):
    """Counts of mean lam: E[X^2] / Var[X] = (lam^2 + lam) / lam = 1 + lam.

    Tolerances are five standard deviations of the estimate, measured over 20 seeds.
    """
    pixels = 1_000_000 if lam < 1 else 100_000
    x = np.random.default_rng(7).poisson(lam, (10, pixels))
    r = sinad(x, interval=None)
    tol_db = 0.01 if lam < 1 else 0.03
    assert r.sinad_db == pytest.approx(10 * math.log10(1 + lam), abs=tol_db)
    assert r.noise_std == pytest.approx(math.sqrt(lam), rel=0.02)


def test_large_means_with_tiny_noise_lose_nothing():
    """1e9 counts with noise of 1e-3: a one-pass E[x^2] - E[x]^2 would return garbage (or a negative variance)."""
    rng = np.random.default_rng(3)
    x = 1e9 + rng.normal(0, 1e-3, (8, 10_000))
    r = sinad(x)
    assert r.sinad_db == pytest.approx(10 * math.log10(1e18 / 1e-6), abs=0.05)  # 240 dB
    assert r.noise_std == pytest.approx(1e-3, rel=0.02)
    assert np.isfinite(r.ci_db).all()


def test_zero_noise_is_infinite_sinad_flagged_and_json_null():
    x = np.tile(np.arange(1.0, 7.0), (5, 1))
    r = sinad(x, per_pixel=True)
    assert r.sinad_db == math.inf and r.enob_bits == math.inf and r.noise_free and r.noise_std == 0.0
    d = json.loads(json.dumps(r.to_dict()))
    assert d["sinad_db"] is None and d["enob_bits"] is None and d["noise_free"] is True
    assert d["per_pixel_db"] == [None] * 6
    # some pixels noise-free, some silent: per-pixel inf and masked, pooled finite
    y = np.zeros((4, 3))
    y[:, 0] = 5.0
    y[:, 1] = [1.0, 2.0, 1.0, 2.0]
    r = sinad(y, per_pixel=True)
    assert np.isfinite(r.sinad_db) and not r.noise_free
    assert r.per_pixel_db[0] == math.inf and r.per_pixel_db.mask.tolist() == [False, False, True]
    expected_pixel_1 = 10 * math.log10(np.mean([1.0, 4.0, 1.0, 4.0]) / np.var([1.0, 2.0, 1.0, 2.0], ddof=1))
    assert r.per_pixel_db[1] == pytest.approx(expected_pixel_1)


@pytest.mark.parametrize("bad,match", [
    (np.ones((1, 5)), "at least two"),
    (np.ones(1), "at least two"),
    (np.zeros((3, 4)), "zero everywhere"),
    (np.array([[1.0, np.nan], [1.0, 2.0]]), "NaN"),
    (np.array([[1.0, np.inf], [1.0, 2.0]]), "NaN or infinite"),
    (np.array([["a", "b"], ["c", "d"]]), "numeric"),
])
def test_sinad_bad_input(bad, match):
    with pytest.raises(EvtkError, match=match):
        sinad(bad)


def test_sinad_bootstrap_reflects_a_repeat_level_disturbance():
    """One repeat off by a common offset: the interval widens, and stays around the estimate."""
    rng = np.random.default_rng(11)
    clean = 5.0 + rng.normal(0, 1, (12, 5000))
    off = clean.copy()
    off[4] += 1.0
    a, b = sinad(clean), sinad(off)
    assert b.ci_db[1] - b.ci_db[0] > 3 * (a.ci_db[1] - a.ci_db[0])
    for r in (a, b):
        assert r.ci_db[0] <= r.sinad_db <= r.ci_db[1]
    assert sinad(clean[:2]).ci_db is None  # two repeats: no interval


def test_flip_rates_against_brute_force():
    rng = np.random.default_rng(0)
    for r in (2, 3, 4, 10):
        b = np.where(rng.random((r, 6, 5)) < 0.3, -1, 1)
        rep = flip_rates(b)
        pairs = list(itertools.combinations(range(r), 2))
        brute_pairwise = 100 * np.mean([np.mean(b[i] != b[j]) for i, j in pairs])
        majority = np.where(b.sum(0) >= 0, 1, -1)
        brute_majority = 100 * np.mean(b != majority)
        assert rep.pairwise_pct == pytest.approx(brute_pairwise)
        assert rep.majority_pct == pytest.approx(brute_majority)
        np.testing.assert_allclose(rep.per_pixel, np.mean(b != majority, axis=0))
        # 0/1 and bool inputs mean the same
        assert flip_rates(b > 0).pairwise_pct == pytest.approx(rep.pairwise_pct)
        assert flip_rates((b > 0).astype(np.uint8)).majority_pct == pytest.approx(rep.majority_pct)
    assert flip_rates(np.ones((5, 16, 16))).pairwise_pct == 0.0
    with pytest.raises(EvtkError, match="binary"):
        flip_rates(np.array([[0, 2], [1, 1]]))
    with pytest.raises(EvtkError, match="at least two"):
        flip_rates(np.ones((1, 4)))


def test_poisson_log_pmf_against_mpmath_over_24_decades():
    mp = pytest.importorskip("mpmath")
    mp.mp.dps = 50
    for lam in (1e-12, 1e-6, 1e-3, 0.5, 1.0, 30.0, 1e4, 1e8, 1e12):
        ks = sorted({0, 1, 2, int(lam), int(lam) + 1, int(lam + 5 * math.sqrt(lam)) + 3, int(3 * lam) + 7})
        got = poisson_log_pmf(np.array(ks), lam)
        for k, g in zip(ks, got):
            ref = float(k * mp.log(lam) - lam - mp.loggamma(k + 1))
            assert g == pytest.approx(ref, rel=1e-13, abs=1e-9), (lam, k)
    # scipy as a second oracle where it is accurate
    k = np.arange(0, 60)
    np.testing.assert_allclose(poisson_pmf(k, 7.5), stats.poisson.pmf(k, 7.5), rtol=1e-12)
    assert poisson_log_pmf(0, 0.0) == 0.0 and poisson_log_pmf(3, 0.0) == -math.inf
    assert poisson_pmf(10**6, 1e-12) == 0.0  # underflows to zero, its log stays finite
    assert np.isfinite(poisson_log_pmf(10**6, 1e-12))
    for bad in (-1, 1.5, np.nan):
        with pytest.raises(EvtkError):
            poisson_log_pmf(bad, 1.0)
    for bad in (-1.0, np.inf, np.nan):
        with pytest.raises(EvtkError):
            poisson_log_pmf(1, bad)


def test_cumulative_factor_against_scipy_and_direct_sums():
    # phi = 1: C = P(1 <= X <= N_e)
    for lam, n in itertools.product((0.3, 4.0, 50.0, 900.0), (1, 5, 60, 2000)):
        c = cumulative_factor(lam, 1, n)
        assert c == pytest.approx(stats.poisson.cdf(n, lam) - stats.poisson.pmf(0, lam), rel=1e-10, abs=1e-300)
    # phi > 1: the direct sum over multiples
    for lam, phi, n in ((20.0, 3, 12), (1e3, 7, 200), (2.0, 2, 50)):
        direct = sum(stats.poisson.pmf(i * phi, lam) for i in range(1, n + 1))
        assert cumulative_factor(lam, phi, n) == pytest.approx(direct, rel=1e-10)
    # the paper's limits: dark or no time -> 0; longer windows and brighter light -> 1
    assert cumulative_factor(0.0, 1, 100) == 0.0 and cumulative_factor(5.0, 1, 0) == 0.0
    assert cumulative_factor(1e-12, 1, 10) == pytest.approx(1e-12, rel=1e-6)
    assert cumulative_factor(40.0, 1, 10**6) == pytest.approx(1.0, abs=1e-15)
    cs = [cumulative_factor(lam, 1, 10**6) for lam in (0.1, 1.0, 10.0, 100.0)]
    assert all(a < b for a, b in zip(cs, cs[1:]))


def test_cumulative_factor_extremes_stay_finite_in_log_space():
    """lam from 1e-12 to 1e12, windows from 1 to 1e9 terms: finite logs, in the right place, quickly."""
    for lam in (1e-12, 1e-3, 1.0, 1e6, 1e12):
        for n in (1, 10, 10**4, 10**9):
            v = log_cumulative_factor(lam, 1, n)
            assert np.isfinite(v) and v <= 0.0
    # a window far short of the mean: only the last term counts
    assert log_cumulative_factor(1e12, 1, 10) == pytest.approx(poisson_log_pmf(10, 1e12), rel=1e-12)
    # a window covering the whole distribution: C = 1 - exp(-lam)
    assert log_cumulative_factor(1e12, 1, 10**13) == pytest.approx(0.0, abs=1e-12)
    assert log_cumulative_factor(1e-12, 1, 10**9) == pytest.approx(math.log(-math.expm1(-1e-12)), rel=1e-9)
    np.testing.assert_allclose(log_cumulative_factor(np.array([1.0, 2.0]), 1, 3),
                               [log_cumulative_factor(1.0, 1, 3), log_cumulative_factor(2.0, 1, 3)])
    for bad in ({"photons_per_unit": 0}, {"photons_per_unit": 1.5}, {"n_terms": -1}, {"n_terms": 2.5}):
        with pytest.raises(EvtkError):
            log_cumulative_factor(1.0, **{"photons_per_unit": 1, "n_terms": 3, **bad})


def test_lowest_cumulative_factor_and_capture_terms():
    feats = np.array([[0.2, 1.0], [0.7, 0.4]])
    assert lowest_cumulative_factor(feats, 50.0, 1, 30) == cumulative_factor(10.0, 1, 30)
    assert lowest_cumulative_factor(feats, 50.0, 1, 30, log=True) == log_cumulative_factor(10.0, 1, 30)
    assert lowest_cumulative_factor(np.zeros(3), 50.0, 1, 30) == 0.0  # a dark input zeroes the bound
    with pytest.raises(EvtkError):
        lowest_cumulative_factor([], 1.0)
    with pytest.raises(EvtkError):
        lowest_cumulative_factor([1.0, -1.0], 1.0)
    assert capture_terms(1000, 1.0) == 1000 and capture_terms(999.9999999999, 1.0) == 1000
    assert capture_terms(1000, 300.0) == 3 and capture_terms(0, 1.0) == 0
    with pytest.raises(EvtkError):
        capture_terms(10, 0.0)


def _brute_bootstrap(x, n, seed):
    """The U-statistic bootstrap written out pair by pair (the definition; quadratic in the repeats)."""
    r = x.shape[0]
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, r, size=(n, r))
    out = []
    for row in idx:
        pairs = [(a, b) for i, a in enumerate(row) for b in row[i + 1:] if a != b]
        if not pairs:
            continue
        noise = np.mean([np.mean((x[a] - x[b]) ** 2) / 2 for a, b in pairs])
        power = np.mean([np.mean(x[a] ** 2) for a in row])
        out.append(np.inf if noise == 0 else 10 * np.log10(power / noise))
    return np.asarray(out)


def test_sinad_is_linear_and_its_bootstrap_matches_the_pairwise_definition():
    from evtk.metrics import SinadAccumulator, _bootstrap_db

    rng = np.random.default_rng(3)
    x = 5 + rng.normal(size=(7, 40))
    acc = SinadAccumulator(7, (40,))
    for part in (x[:2], x[2:3], x[3:]):  # fed in pieces: the same terms as all at once
        acc.add(part)
    got = _bootstrap_db(acc._group_terms(), 200, seed=11)
    want = _brute_bootstrap(x, 200, seed=11)
    assert np.allclose(got[: len(want)], want)
    # more repeats than groups: the point estimate is still the pooled per-pixel variance, exactly
    y = 100 + rng.normal(scale=2.0, size=(300, 50))
    r = sinad(y, interval="bootstrap", resamples=200)
    noise = y.var(axis=0, ddof=1).mean()
    assert r.sinad_db == pytest.approx(10 * math.log10(np.mean(y ** 2) / noise), rel=1e-12)
    assert r.ci_db[0] < r.sinad_db < r.ci_db[1]


def test_sinad_of_many_windows_holds_no_repeat_by_repeat_matrix():
    """2,000 windows of 2,000 pixels: memory of the estimate and of its bootstrap stays near the data's own."""
    import tracemalloc

    x = np.random.default_rng(0).poisson(20.0, size=(2000, 2000)).astype(np.float64)
    tracemalloc.start()
    r = sinad(x)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 3 * x.nbytes, peak / 2**20  # the pairwise version needed 2000 x 2000 x 2000 x 8 bytes
    assert r.sinad_db == pytest.approx(10 * math.log10(np.mean(x ** 2) / x.var(axis=0, ddof=1).mean()))


@pytest.mark.parametrize("repeats", [3, 5, 12])
@pytest.mark.parametrize("shared", [False, True])
def test_sinad_jackknife_interval_covers_the_true_sinad_at_its_nominal_rate(repeats, shared):
    """Coverage by simulation: 400 scenes of known SINAD, independent noise or noise shared by a whole repeat.

    The true ratio follows from the model: signal power S, per-pixel noise variance N (plus, when shared, a
    gain drawn once per repeat with variance g^2, which adds g^2 s_p^2 to pixel p's variance). A 95 %
    interval must cover it in 90-99 % of the scenes (400 trials: +-2.2 % is one standard error at 95 %);
    the percentile bootstrap of the same data covers at most 85 % at three repeats.
    """
    rng = np.random.default_rng(100 * repeats + shared)
    signal = 3.0 * rng.normal(size=64)
    g = 0.1 if shared else 0.0
    s2 = np.mean(signal ** 2)
    truth = 10 * math.log10((s2 * (1 + g ** 2) + 1.0) / (s2 * g ** 2 + 1.0))
    hits = boot_hits = 0
    trials = 400
    for _ in range(trials):
        gain = 1.0 + g * rng.normal(size=(repeats, 1))
        x = signal * gain + rng.normal(size=(repeats, signal.size))
        lo, hi = sinad(x).ci_db
        hits += lo <= truth <= hi
        if repeats == 3:
            blo, bhi = sinad(x, interval="bootstrap", resamples=400, seed=_).ci_db
            boot_hits += blo <= truth <= bhi
    assert 0.90 <= hits / trials <= 0.99, hits / trials
    if repeats == 3:
        assert boot_hits / trials < 0.85  # the reason the jackknife is the default


def test_sinad_accumulator_fed_in_pieces_equals_sinad_of_everything():
    """Blocks that straddle the groups (200 repeats, 64 groups): estimate, interval and per-pixel values agree."""
    from evtk.metrics import SinadAccumulator

    rng = np.random.default_rng(5)
    x = 1e6 + rng.normal(size=(200, 6, 7)) * np.linspace(0.5, 2, 7)
    whole = sinad(x, per_pixel=True)
    acc = SinadAccumulator(200, (6, 7))
    for a, b in [(0, 1), (1, 50), (50, 51), (51, 199), (199, 200)]:
        acc.add(x[a:b])
    part = acc.report(per_pixel=True)
    assert part.sinad_db == pytest.approx(whole.sinad_db, rel=1e-9)
    assert np.allclose(part.ci_db, whole.ci_db, rtol=1e-9)
    assert np.allclose(part.per_pixel_db, whole.per_pixel_db, rtol=1e-9)
    want = 10 * np.log10(np.mean(x ** 2, axis=0) / x.var(axis=0, ddof=1))
    assert np.allclose(part.per_pixel_db, want, rtol=1e-9)
    assert part.interval == "jackknife" and part.to_dict()["interval"] == "jackknife"


def test_sinad_accumulator_refuses_what_does_not_add_up():
    from evtk.metrics import SinadAccumulator

    acc = SinadAccumulator(3, (4,))
    with pytest.raises(EvtkError, match="4 values"):
        acc.add(np.ones((1, 5)))
    acc.add(np.ones((2, 4)))
    with pytest.raises(EvtkError, match="2 of the 3"):
        acc.report()
    with pytest.raises(EvtkError, match="more than the 3"):
        acc.add(np.ones((2, 4)))
    with pytest.raises(EvtkError, match="NaN"):
        acc.add(np.full((1, 4), np.nan))
    with pytest.raises(EvtkError, match="at least two"):
        SinadAccumulator(1, (4,))
    with pytest.raises(EvtkError, match="interval must be"):
        sinad(np.arange(12.0).reshape(3, 4), interval="bca")


def test_sinad_interval_reaches_infinity_when_a_left_out_repeat_holds_all_the_noise():
    x = np.tile(np.arange(1.0, 9.0), (4, 1))
    x[2, 3] += 1.0  # only repeat 2 differs: leaving it out leaves no noise
    r = sinad(x)
    assert np.isfinite(r.sinad_db) and r.ci_db[1] == math.inf and r.ci_db[0] <= r.sinad_db


def test_cumulative_factor_rises_with_the_window_and_falls_with_light_at_a_fixed_window():
    """The docs' reading of eq. 10: C -> 1 - exp(-lam) as N_e grows; at fixed N_e, C vanishes once lam >> N_e phi."""
    from scipy import stats

    assert cumulative_factor(5.0, 1, 10) == pytest.approx(stats.poisson.cdf(10, 5.0) - stats.poisson.pmf(0, 5.0))
    assert cumulative_factor(5.0, 1, 10) == pytest.approx(0.9796, abs=1e-4)
    assert cumulative_factor(100.0, 1, 10) < 1e-29
    assert cumulative_factor(100.0, 1, 200) == pytest.approx(1.0 - math.exp(-100.0))
    fixed = [cumulative_factor(lam, 1, 10) for lam in (0.5, 2.0, 5.0, 20.0, 100.0)]
    assert fixed[2] > fixed[1] > fixed[0] and fixed[2] > fixed[3] > fixed[4]  # rises, then falls
