"""SinadAccumulator's whole-number route (the counts `evtk enob` gives it, one group of repeats a block) against an
exact reference of eq. 8 computed here in Python integers, on the inputs that stress its integer sums."""

import math
from fractions import Fraction

import numpy as np
import pytest

from evtk import EvtkError
from evtk.metrics import SinadAccumulator, sinad
from evtk.metrics.sinad import _t_quantile_two_sided


def _close(a, b):
    if math.isinf(b):
        return a == b
    return a == pytest.approx(b, rel=1e-9, abs=1e-12)


def _exact_db(rows):
    """SINAD in dB of repeats ``rows`` (lists of Python ints, one per repeat), by eq. 8 in exact rationals:
    power the mean square, noise the pixels' mean variance over repeats (ddof 1)."""
    r, p = len(rows), len(rows[0])
    s1 = [sum(row[i] for row in rows) for i in range(p)]
    s2 = [sum(row[i] ** 2 for row in rows) for i in range(p)]
    power = Fraction(sum(s2), r * p)
    noise = Fraction(sum(r * a - b * b for a, b in zip(s2, s1)), r * (r - 1) * p)
    if noise == 0:
        return math.inf, power, noise
    return 10 * math.log10(power / noise), power, noise


def _check(x, blocks, per_pixel=True, interval="jackknife"):
    """Feed whole-number captures ``x`` (repeats x ...) in ``blocks`` (cuts), and compare the report with the
    exact reference: SINAD, signal and noise, the per-pixel values and the jackknife interval over the groups."""
    r = x.shape[0]
    acc = SinadAccumulator(r, x.shape[1:])
    for a, b in zip(blocks, blocks[1:]):
        assert acc.add(x[a:b]) == max(abs(int(v)) for v in x[a:b].ravel())  # the magnitude, exactly
    got = acc.report(per_pixel=per_pixel, interval=interval)
    rows = [[int(v) for v in row] for row in x.reshape(r, -1)]
    db, power, noise = _exact_db(rows)
    assert _close(got.sinad_db, db)
    assert got.noise_free == (noise == 0) and got.repeats == r and got.pixels == len(rows[0])
    assert _close(got.signal_rms, math.sqrt(power)) and _close(got.noise_std, math.sqrt(noise))
    if per_pixel:
        pp = got.per_pixel_db.reshape(-1)
        for i in range(len(rows[0])):
            col = [[row[i]] for row in rows]
            if all(v[0] == 0 for v in col):
                assert pp.mask[i]
            else:
                assert not pp.mask[i] and _close(float(pp[i]), _exact_db(col)[0]), i
    if interval == "jackknife" and math.isfinite(db):
        starts = list(acc.group_starts) + [r]
        loo = []
        for a, b in zip(starts, starts[1:]):
            d, pw, nz = _exact_db(rows[:a] + rows[b:])
            assert nz > 0 and pw > 0  # (the inputs here keep noise and signal in every leave-one-out)
            loo.append(d)
        g = len(loo)
        mean = sum(loo) / g
        se = math.sqrt((g - 1) / g * sum((v - mean) ** 2 for v in loo))
        t = _t_quantile_two_sided(0.95, g - 1)
        assert np.allclose(got.ci_db, (db - t * se, db + t * se), rtol=1e-9, atol=1e-9)
    return acc, got


def _enob_blocks(acc_repeats):
    """Blocks of one group of repeats each, as `evtk enob` gives them."""
    return list(SinadAccumulator(acc_repeats, 1).group_starts) + [acc_repeats]


@pytest.mark.parametrize("repeats", [2, 3, 64, 65, 1000])
def test_counts_a_group_a_block_equal_the_exact_reference(repeats):
    """int16 net counts, one group a block (one repeat a group up to 64 repeats, groups of two sizes beyond), with
    a constant pixel, a dark one and a hot one: every number of the report equals eq. 8 computed exactly."""
    rng = np.random.default_rng(repeats)
    x = rng.integers(-3, 4, (repeats, 4, 5)).astype(np.int16)
    x[:, 0, 0] = 7  # constant: no noise (per-pixel +inf)
    x[:, 0, 1] = 0  # dark: no signal (masked)
    x[:, 3, 4] = 200 + rng.integers(0, 2, repeats)  # a large mean with tiny noise
    _check(x, _enob_blocks(repeats), interval="jackknife" if repeats >= 3 else None)


def test_constant_captures_are_noise_free_exactly():
    x = np.tile(np.arange(-4, 8, dtype=np.int16).reshape(3, 4), (300, 1, 1))
    _, got = _check(x, _enob_blocks(300), interval=None)
    assert got.sinad_db == math.inf and got.noise_free and got.noise_std == 0.0
    assert np.isinf(got.per_pixel_db.filled(0.0)).sum() == 11  # every pixel but the one at 0


@pytest.mark.parametrize("big", [45, 46, 127, 128, 181, 182, 32767])
def test_int16_sums_switch_type_before_they_could_wrap(big):
    """Magnitudes on both sides of every limit of the int16 and int32 sums of groups of 16 repeats (1024 repeats),
    down to -32768: exact."""
    rng = np.random.default_rng(big)
    x = rng.integers(-big, big + 1, (1024, 3, 3)).astype(np.int16)
    x[:, 0, 0] = big
    x[1::2, 0, 1] = -big if big < 32767 else -32768
    starts = _enob_blocks(1024)
    _check(x, starts)
    _check(x, [0, 1, 17, 40, 1024])  # blocks across groups: partial sums kept, then merged


def test_huge_counts_spill_their_int64_sums_before_they_could_overflow():
    """int32 counts near 2**29 in groups of 3 (192 repeats): the sums of each size of group would leave int64
    after two groups and the pixels' sums of a group already do; both are moved to floats in time: exact."""
    rng = np.random.default_rng(9)
    x = (2**29 - rng.integers(0, 1000, (192, 5))).astype(np.int32)
    x[:, 0] = -(2**29)
    x[::2, 1] = 0
    _check(x, _enob_blocks(192))


def test_three_sizes_of_groups_and_a_float_block_keep_to_the_float_routes_numbers():
    """200 repeats (groups of 3 and 4) fed whole groups of small counts, a float block, and groups of counts near
    2**30 one repeat at a time (whose sums are merged two repeats in, then by Chan's update): three sizes of group
    held at once, matched against the exact reference and the float route, with both intervals."""
    rng = np.random.default_rng(3)
    x = rng.integers(-50, 50, (200, 6)).astype(np.int64)
    x[100:, 2] = 2**30 - 1 - rng.integers(0, 3, 100)
    starts = _enob_blocks(200)
    blocks = [0, 1] + [s for s in starts if 1 < s <= 100] + list(range(101, 201))
    _check(x, blocks)
    acc = SinadAccumulator(200, 6)
    acc.add(x[:1].astype(np.float64))  # a float block, then whole numbers in the same group
    for a, b in zip(blocks[1:], blocks[2:]):
        acc.add(x[a:b])
    for interval in ("jackknife", "bootstrap"):
        got, want = acc.report(per_pixel=True, interval=interval), sinad(x.astype(np.float64), per_pixel=True,
                                                                        interval=interval)
        for key in ("sinad_db", "signal_rms", "noise_std"):
            assert _close(getattr(got, key), getattr(want, key)), key
        assert np.allclose(got.ci_db, want.ci_db, rtol=1e-9, atol=1e-9)
        assert np.allclose(got.per_pixel_db, want.per_pixel_db, rtol=1e-9)


def test_bootstrap_of_counts_equals_the_float_routes():
    """The bootstrap interval of int16 counts a group a block (1000 repeats) equals that of the same captures in
    floats (Chan's update, summed in float64)."""
    rng = np.random.default_rng(1)
    x = rng.integers(-2, 3, (1000, 7, 3)).astype(np.int16)
    acc = SinadAccumulator(1000, (7, 3))
    for a, b in zip(_enob_blocks(1000), _enob_blocks(1000)[1:]):
        acc.add(x[a:b])
    got = acc.report(interval="bootstrap", per_pixel=True)
    want = sinad(x.astype(np.float64), interval="bootstrap", per_pixel=True)
    assert _close(got.sinad_db, want.sinad_db)
    assert np.allclose(got.ci_db, want.ci_db, rtol=1e-9, atol=1e-9)
    assert np.allclose(got.per_pixel_db, want.per_pixel_db, rtol=1e-9)


def test_runs_of_pixels_on_several_threads_give_the_same_sums(monkeypatch):
    """Blocks large enough to be cut into runs of pixels on the counting threads (8 threads asked for): the
    numbers of the float route (every pixel's own sums, whatever the runs)."""
    from evtk._parallel import parts

    monkeypatch.setenv("EVTK_THREADS", "8")
    rng = np.random.default_rng(8)
    x = rng.integers(-6, 7, (130, 2, 40000)).astype(np.int16)
    x[:, 1, :100] = 300  # int32 sums in the groups' first run
    x[::2, 1, 100] = -300
    blocks = _enob_blocks(130)
    assert parts(x[: blocks[1]].size) > 1
    acc = SinadAccumulator(130, x.shape[1:])
    for a, b in zip(blocks, blocks[1:]):
        assert acc.add(x[a:b]) == 300
    for interval in ("jackknife", "bootstrap"):
        got = acc.report(per_pixel=True, interval=interval)
        want = sinad(x.astype(np.float64), per_pixel=True, interval=interval)
        for key in ("sinad_db", "signal_rms", "noise_std"):
            assert _close(getattr(got, key), getattr(want, key)), key
        assert np.allclose(got.ci_db, want.ci_db, rtol=1e-9, atol=1e-12)
        assert np.array_equal(got.per_pixel_db.mask, want.per_pixel_db.mask)
        assert np.allclose(got.per_pixel_db, want.per_pixel_db, rtol=1e-9, atol=1e-12)


def test_the_memory_estimate_bounds_an_accumulator_mixing_floats_and_counts():
    """``bytes_needed`` is what the budget checks before an accumulator exists: with the groups' integer sums
    kept beside their float means, a run that mixes float blocks with counts holds both arrays, and the estimate
    counted only the float one (tracemalloc sees numpy's allocations, untouched pages included)."""
    import tracemalloc

    repeats, pixels = 64, 40_000
    rng = np.random.default_rng(4)
    counts = rng.integers(-300, 300, (repeats, pixels)).astype(np.int16)  # int16 sums: a whole group's
    tracemalloc.start()
    try:
        acc = SinadAccumulator(repeats, pixels)
        for g in range(repeats - 1):
            acc.add(counts[g:g + 1] if g % 2 else counts[g:g + 1].astype(np.float64))  # floats and counts
        acc.add(counts[repeats - 1:].astype(np.int32) * 200)  # sums that need int32: the int16 ones widened
        acc.report(per_pixel=True)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak <= SinadAccumulator.bytes_needed(repeats, pixels), (peak, SinadAccumulator.bytes_needed(repeats,
                                                                                                        pixels))


def _counts_with_one_noisy_group(seed):
    """Whole-number captures identical in every repeat but those of one group of the accumulator's, which alone
    hold noise (one pixel moved by 1-4): leaving that group out leaves none."""
    rng = np.random.default_rng(seed)
    r, p = int(rng.integers(3, 700)), int(rng.integers(1, 40))
    x = np.tile(rng.integers(-50, 50, p), (r, 1)).astype(np.int16)
    starts = _enob_blocks(r)
    g = int(rng.integers(0, len(starts) - 1))
    a, b = starts[g], starts[g + 1]
    x[a:b, int(rng.integers(0, p))] += rng.integers(1, 5, b - a).astype(np.int16)
    return x, starts


def test_a_leave_out_without_noise_reaches_infinity_exactly_for_counts():
    """Counts a group a block (as enob gives them) where one group alone holds the noise: the jackknife's leave-out
    of that group has no noise, so the interval's upper end is +inf. The leave-outs came from the groups' float
    Gram matrix, whose rounding left that noise a tiny positive number in about half these cases (an upper end
    of 350-410 dB); they are exact integers now."""
    for seed in range(40):
        x, starts = _counts_with_one_noisy_group(seed)
        acc = SinadAccumulator(x.shape[0], x.shape[1:])
        for a, b in zip(starts, starts[1:]):
            acc.add(x[a:b])
        got = acc.report(interval="jackknife")
        assert math.isfinite(got.sinad_db) and got.ci_db[1] == math.inf, (seed, got.ci_db)
        assert got.ci_db[0] <= got.sinad_db


def test_exact_leave_outs_equal_the_gram_routes_and_skip_its_product(monkeypatch):
    """The jackknife of counts takes its leave-one-outs from exact integer sums: the same noise and power as the
    groups' terms (``_group_terms``, the bootstrap's) give, to 1e-12, without the groups' Gram matrix (a groups x
    groups x pixels product, half of a 64-group report's time); captures in floats still take the Gram route."""
    from evtk.metrics.sinad import _leave_one_out

    rng = np.random.default_rng(5)
    x = rng.integers(-9, 10, (640, 12, 7)).astype(np.int16)
    x[:, 0, 0] = 3
    acc = SinadAccumulator(640, (12, 7))
    for a, b in zip(_enob_blocks(640), _enob_blocks(640)[1:]):
        acc.add(x[a:b])
    noise, power = acc._exact_leave_one_out(acc._exact_totals())
    want_noise, want_power = _leave_one_out(acc._group_terms())
    assert np.allclose(noise, want_noise, rtol=1e-12, atol=0) and np.allclose(power, want_power, rtol=1e-12, atol=0)
    asked = []
    between = SinadAccumulator._between

    def spy(self, gram, per_pixel):
        asked.append(gram)
        return between(self, gram, per_pixel)

    monkeypatch.setattr(SinadAccumulator, "_between", spy)
    acc.report(interval="jackknife")
    assert asked == []  # the counts' noise and leave-outs: exact sums, no float pass over the groups' means
    floats = sinad(x.astype(np.float64), interval="jackknife")
    assert asked == [True]
    assert np.allclose(acc.report(interval="jackknife").ci_db, floats.ci_db, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("interval", ["jackknife", "bootstrap", None])
def test_sums_added_give_the_state_the_repeats_give(interval):
    # add_sums of each group's per-pixel sums (as enob's compiled kernel gives them) against add of the repeats
    rng = np.random.default_rng(5)
    reps = rng.integers(-30, 30, (130, 4, 5)).astype(np.int16)
    by_rows, by_sums = SinadAccumulator(130, (4, 5)), SinadAccumulator(130, (4, 5))
    starts = by_sums.group_starts.tolist() + [130]
    for a, z in zip(starts, starts[1:]):
        for lo in range(a, z, 3):  # blocks within the group
            hi = min(z, lo + 3)
            block = reps[lo:hi].astype(np.int64)
            by_rows.add(reps[lo:hi])
            assert by_sums.add_sums(hi - lo, block.sum(0), (block * block).sum(0), int(np.abs(block).max()))
    ra, rb = by_rows.report(interval=interval), by_sums.report(interval=interval)
    assert ra.sinad_db == rb.sinad_db and ra.ci_enob == rb.ci_enob


@pytest.mark.parametrize("per_pixel", [False, True])
def test_sums_added_from_the_same_two_arrays_batch_after_batch_give_the_same_state(per_pixel):
    # enob sums every batch into the same two arrays (evtk._native.net_sums' out): the accumulator must copy what
    # it keeps, whole groups and blocks within a group alike, before the arrays are overwritten
    rng = np.random.default_rng(9)
    reps = rng.integers(-30, 30, (130, 4, 5)).astype(np.int16)
    fresh = SinadAccumulator(130, (4, 5), per_pixel=per_pixel)
    reused = SinadAccumulator(130, (4, 5), per_pixel=per_pixel)
    s1, s2 = np.empty((4, 5), np.int64), np.empty((4, 5), np.int64)
    starts = reused.group_starts.tolist() + [130]
    for a, z in zip(starts, starts[1:]):
        for lo, hi in ([(a, z)] if a % 2 else [(a, (a + z) // 2), ((a + z) // 2, z)]):  # whole groups and halves
            block = reps[lo:hi].astype(np.int64)
            big = int(np.abs(block).max())
            assert fresh.add_sums(hi - lo, block.sum(0), (block * block).sum(0), big)
            np.sum(block, 0, out=s1)
            np.sum(block * block, 0, out=s2)
            assert reused.add_sums(hi - lo, s1, s2, big)
            s1.fill(7_777)  # (what the next batch's sums would overwrite)
            s2.fill(-1)
    for interval in ("jackknife", None):
        ra, rb = fresh.report(per_pixel, interval=interval), reused.report(per_pixel, interval=interval)
        assert ra.sinad_db == rb.sinad_db and ra.ci_enob == rb.ci_enob and ra.noise_std == rb.noise_std
        if per_pixel:
            np.testing.assert_array_equal(ra.per_pixel_db, rb.per_pixel_db)


def test_sums_refused_where_they_do_not_fit_the_groups_or_the_pixels():
    acc = SinadAccumulator(40, (2,))
    first_group = int(acc.group_starts[1])
    with pytest.raises(Exception, match="span two groups"):
        acc.add_sums(first_group + 1, np.zeros(2, np.int64), np.zeros(2, np.int64), 0)
    with pytest.raises(Exception, match="2 values"):
        acc.add_sums(1, np.zeros(3, np.int64), np.zeros(3, np.int64), 0)
    with pytest.raises(Exception, match="integers"):
        acc.add_sums(1, np.zeros(2), np.zeros(2), 0)
    # sums whose squares could leave int64: nothing added, add() takes the repeats by the float route
    assert not acc.add_sums(1, np.zeros(2, np.int64), np.zeros(2, np.int64), 2**31)
    assert acc.added == 0


@pytest.mark.parametrize("interval", ["jackknife", "bootstrap", None])
def test_counts_noise_from_exact_sums_equals_the_float_route(interval, monkeypatch):
    """Counts merged from exact integer sums give the pooled noise as one exact quotient, ``(R sum S2 - sum_p
    T_p^2) / (R (R - 1) p)``, without the float pass over the groups' means (``_between``) unless an interval or
    per-pixel figures need it: the same SINAD as the float route (the captures as floats) to 1e-12, and as numpy's
    own pooled variance (ddof 1). An accumulator made without per-pixel sums gives the same figures and refuses
    per-pixel SINAD."""
    rng = np.random.default_rng(11)
    x = rng.poisson(4.0, (96, 9, 5)).astype(np.int16) - 2
    x[:, 2, 3] = 7  # a noiseless pixel among noisy ones
    calls = []
    between = SinadAccumulator._between

    def spy(self, gram, per_pixel):
        calls.append((gram, per_pixel))
        return between(self, gram, per_pixel)

    monkeypatch.setattr(SinadAccumulator, "_between", spy)
    blocks = _enob_blocks(96)
    got = {}
    for keep in (True, False):
        acc = SinadAccumulator(96, (9, 5), per_pixel=keep)
        for a, b in zip(blocks, blocks[1:]):
            acc.add(x[a:b])
        assert bool(acc._sizes) == keep  # (no per-pixel int64 sums kept without per-pixel figures)
        calls.clear()
        got[keep] = acc.report(interval=interval)
        assert calls == ([(True, False)] if interval == "bootstrap" else []), (keep, calls)
        if not keep:
            with pytest.raises(EvtkError, match="per_pixel=True"):
                acc.report(per_pixel=True, interval=interval)
    floats = sinad(x.astype(np.float64), interval=interval)
    noise = float(np.var(x.astype(np.float64), axis=0, ddof=1).mean())
    for rep in got.values():
        assert math.isclose(rep.noise_std ** 2, noise, rel_tol=1e-12)
        assert math.isclose(rep.sinad_db, floats.sinad_db, rel_tol=1e-12)
        if interval is not None:
            assert np.allclose(rep.ci_db, floats.ci_db, rtol=1e-9, atol=1e-12)
    assert got[True].sinad_db == got[False].sinad_db and got[True].ci_db == got[False].ci_db


def test_counts_of_identical_repeats_are_exactly_noiseless():
    """Repeats that are all the same counts have no noise, exactly (an integer numerator of 0), however large
    the counts: infinite SINAD and noise_free, never a tiny positive noise from rounding."""
    x = np.tile(np.array([[30000, -29999, 7], [1, 0, -32768]], np.int16), (40, 1, 1))
    acc = SinadAccumulator(40, (2, 3), per_pixel=False)
    for a, b in zip(_enob_blocks(40), _enob_blocks(40)[1:]):
        acc.add(x[a:b])
    rep = acc.report(interval=None)
    assert rep.noise_free and rep.sinad_db == math.inf and rep.noise_std == 0.0
