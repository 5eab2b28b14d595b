"""`evtk enob` on fixed windows without a plan: net counts summed exactly in integers, a batch of windows at a time,
give the numbers the float route gives (issue 32), and `--theta` linearises as reconstruct's does."""

import json

import numpy as np
import pytest
from click.testing import CliRunner

import evtk
from evtk import EvtkError
from evtk.cli import main
from evtk.metrics import SinadAccumulator, flip_rates, sinad
from evtk.reconstruct import binarize, downsample, plan, reconstruct
from evtk.reconstruct.fixed import count_batches, net_count_batches, pixel_values
from evtk.sweeps import recording_noise, scene_noise

# every test twice: with evtk's compiled kernels and without them (tests/conftest.py)
pytestmark = pytest.mark.usefixtures("compiled")


def _hostile_recording(path, size=(48, 32), period_us=1000, windows=150, seed=0):
    """Random events with a hot pixel (hundreds of events a window), a pixel of the same count in every window (no
    variance), pixels that never fire, windows with no events at all, and events stamped exactly on window bounds."""
    rng = np.random.default_rng(seed)
    w_px, h_px = size
    t_end = period_us * windows
    n = 30 * windows * 8
    t = rng.integers(0, t_end, n)
    x = rng.integers(0, w_px - 5, n)  # the last four columns never fire, nor does column 7 but for the steady pixel
    x[x >= 7] += 1
    y = rng.integers(0, h_px, n)
    p = (rng.random(n) < 0.3 + 0.4 * (x > w_px // 2)).astype(np.uint8)
    quiet = (t // period_us) % 7 == 3  # every seventh window empty
    t, x, y, p = t[~quiet], x[~quiet], y[~quiet], p[~quiet]
    hot_t = rng.integers(0, t_end, 300 * windows)  # the hot pixel, mostly ON
    steady_t = np.repeat(np.arange(windows) * period_us, 3) + np.tile([200, 201, 500], windows)  # 3 ON a window
    bounds_t = np.arange(windows) * period_us  # on the bounds
    t = np.concatenate([t, hot_t, steady_t, bounds_t])
    x = np.concatenate([x, np.full(hot_t.size, 5), np.full(steady_t.size, 7), np.full(windows, 9)])
    y = np.concatenate([y, np.full(hot_t.size, 6), np.full(steady_t.size, 2), rng.integers(0, h_px, windows)])
    p = np.concatenate([p, (rng.random(hot_t.size) < 0.9).astype(np.uint8), np.ones(steady_t.size, np.uint8),
                        rng.integers(0, 2, windows).astype(np.uint8)])
    order = np.argsort(t, kind="stable")
    ev = evtk.Events(t[order], x[order].astype(np.uint16), y[order].astype(np.uint16), p[order], size)
    evtk.write_events(path, ev)
    return ev


def _float_route(rec, window, skip_us=0, length_us=None, region=None, size=(16, 16), batch=7, **report):
    """The route `evtk enob` took before: each batch's ON and OFF counts, each pixel's float value, the float
    accumulator and each window's float response binarised at its mean."""
    _, win, reg = plan(rec, window, skip_us, length_us, region, check_memory=False)
    x0, x1, y0, y1 = reg
    acc = SinadAccumulator(len(win), (y1 - y0, x1 - x0))
    binary = []
    for _, on, off, _ in count_batches(rec, win, reg, None, 0, batch):
        values = pixel_values(on, off, False, 0.2)
        acc.add(values)
        binary.append(binarize(downsample(values, size), "mean"))
    return acc.report(**report), flip_rates(np.concatenate(binary))


def _same_report(got, want):
    for key in ("sinad_db", "enob_bits", "signal_rms", "noise_std"):
        assert getattr(got, key) == pytest.approx(getattr(want, key), rel=1e-9, abs=1e-12), key
    assert got.noise_free == want.noise_free and got.repeats == want.repeats and got.pixels == want.pixels
    if want.ci_db is None:
        assert got.ci_db is None
    else:
        assert np.allclose(got.ci_db, want.ci_db, rtol=1e-9, atol=1e-12)
    if want.per_pixel_db is not None:
        assert np.array_equal(np.ma.getmaskarray(got.per_pixel_db), np.ma.getmaskarray(want.per_pixel_db))
        a, b = got.per_pixel_db.filled(0.0), want.per_pixel_db.filled(0.0)
        assert np.array_equal(np.isinf(a), np.isinf(b))
        assert np.allclose(a[np.isfinite(a)], b[np.isfinite(b)], rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("interval", ["jackknife", "bootstrap", None])
@pytest.mark.parametrize("cut", [{}, {"skip_us": 100, "length_us": 650}])
def test_net_counts_give_the_float_routes_numbers(tmp_path, interval, cut):
    """Hot, steady, silent pixels, empty windows and events on the bounds: the integer route's SINAD, interval,
    per-pixel SINAD and flips equal the float route's (and the whole reconstruction's)."""
    path = tmp_path / "bench.aedat4"
    _hostile_recording(path)
    with evtk.open(path) as rec:
        (row,) = recording_noise(rec, ("period", 1000), interval=interval, per_pixel=True, **cut)
        want, flips = _float_route(rec, ("period", 1000), interval=interval, per_pixel=True, **cut)
        whole = scene_noise(reconstruct(rec, window=("period", 1000), **cut), interval=interval, per_pixel=True)[0]
    assert row["repeats"] == want.repeats >= 148  # more than the 64 groups of repeats: several windows a group
    _same_report(row["sinad"], want)
    _same_report(row["sinad"], whole["sinad"])
    assert np.isinf(row["sinad"].per_pixel_db[2, 7])  # the steady pixel: signal, no noise
    assert row["sinad"].per_pixel_db.mask[:, -4:].all()  # the silent columns: no signal
    assert (row["flips"].pairwise_pct, row["flips"].majority_pct) == (flips.pairwise_pct, flips.majority_pct)
    assert row["flips"].pairwise_pct == whole["flips"].pairwise_pct


def test_batches_smaller_than_a_group_of_repeats(tmp_path, monkeypatch):
    """A batch cap of one window (each group of repeats summed over several batches before its one merge) and a
    budget of 4 MiB give the same numbers."""
    import evtk.sweeps as sweeps

    path = tmp_path / "bench.aedat4"
    _hostile_recording(path)
    with evtk.open(path) as rec:
        want, flips = _float_route(rec, ("period", 1000), per_pixel=True)
        monkeypatch.setattr(sweeps, "NOISE_NET_BINS", 48 * 32)
        (one,) = recording_noise(rec, ("period", 1000), per_pixel=True)
        monkeypatch.undo()
        monkeypatch.setenv("EVTK_MEMORY_LIMIT_MB", "4")
        (small,) = recording_noise(rec, ("period", 1000), per_pixel=True)
    for row in (one, small):
        _same_report(row["sinad"], want)
        assert row["flips"].pairwise_pct == flips.pairwise_pct


def test_net_counts_on_a_region_a_window_a_batch_and_sizes_that_do_not_divide(tmp_path):
    """A region inside the sensor (events outside it left out), one window a batch, a response size that does not
    divide the region: still the float route's numbers."""
    path = tmp_path / "bench.aedat4"
    _hostile_recording(path, size=(50, 30), windows=25, seed=3)
    region = (3, 40, 1, 29)
    with evtk.open(path) as rec:
        (row,) = recording_noise(rec, ("period", 1000), region=region, size=(5, 7), per_pixel=True)
        want, flips = _float_route(rec, ("period", 1000), region=region, size=(5, 7), batch=1, per_pixel=True)
        _, win, _ = plan(rec, ("period", 1000), region=region, check_memory=False)
        one = [(net.copy(), most) for _, net, most in net_count_batches(rec, win, region, batch_windows=1)]
        some = [net.copy() for _, net, _ in net_count_batches(rec, win, region, [0, 2, 3, 11])]
        both = [(on - off) for _, on, off, _ in count_batches(rec, win, region, None, 0, 4)]
    assert row["sinad"].per_pixel_db.shape == (28, 37)
    _same_report(row["sinad"], want)
    assert row["flips"].pairwise_pct == flips.pairwise_pct
    assert np.array_equal(np.concatenate([n for n, _ in one]), np.concatenate(both))  # the same, window by window
    assert np.array_equal(np.concatenate(some), np.concatenate(both))  # batches of 2, 1, 8 and the rest
    assert all(np.abs(n).max() <= most for n, most in one) and max(most for _, most in one) >= 300  # the hot pixel


@pytest.mark.parametrize("in_memory", [True, False])
def test_net_counts_of_windows_in_any_order_equal_on_minus_off(tmp_path, in_memory):
    """Overlapping windows in any order (read a batch at a time through the time-window reads), read in chunks
    of 777 events, from a file or from events in memory: each window's net counts are its ON minus OFF counts."""
    from evtk.reconstruct.windows import Windows

    path = tmp_path / "bench.aedat4"
    ev = _hostile_recording(path, windows=30)
    rng = np.random.default_rng(7)
    starts = rng.integers(0, 29_000, 23)
    win = Windows(starts, starts + rng.integers(1, 3_000, 23), np.arange(23), "test")
    region = (0, 48, 0, 32)
    with evtk.open(path) as rec:
        source = ev if in_memory else rec
        got = [(i, net.copy(), most) for i, net, most in net_count_batches(source, win, region, [0, 5, 6, 20],
                                                                          chunk_events=777)]
        want = np.concatenate([on - off for _, on, off, _ in count_batches(source, win, region, None, 0, 3)])
    assert [i for i, _, _ in got] == [0, 5, 6, 20]
    assert np.array_equal(np.concatenate([n for _, n, _ in got]), want)
    assert all(np.abs(n).max(initial=0) <= most for _, n, most in got)
    with pytest.raises(EvtkError, match="batches"):
        next(net_count_batches(ev, win, region, [1, 5]))


def test_the_net_route_forms_no_float_frame_per_window(tmp_path, monkeypatch):
    """Issue 32: enob without a plan or theta counts net counts into int32 frames and never takes the ON and OFF
    counts of every pixel through a float value (the work that made it 4.5x a read)."""
    import evtk.sweeps as sweeps

    path = tmp_path / "bench.aedat4"
    _hostile_recording(path, windows=12)

    def refused(*args, **kwargs):
        raise AssertionError("a float value per window and pixel")

    monkeypatch.setattr(sweeps, "pixel_values", refused)
    monkeypatch.setattr(sweeps, "count_batches", refused)
    res = CliRunner().invoke(main, ["enob", str(path), "--window", "period:1000", "--json"])
    assert res.exit_code == 0, res.output
    assert json.loads(res.output)["scenes"][0]["repeats"] == 12


def test_one_window_and_no_signal_are_refused_as_before(tmp_path):
    path = tmp_path / "one.aedat4"  # one whole period of 1000 us
    t = np.arange(0, 1500, 10)
    evtk.write_events(path, evtk.Events(t, (t % 4).astype(np.uint16), np.zeros(t.size, np.uint16),
                                        (t % 3 == 0).astype(np.uint8), (4, 4)))
    res = CliRunner().invoke(main, ["enob", str(path), "--window", "period:1000"])
    assert res.exit_code == 1 and "captured at least twice" in res.output
    dark = tmp_path / "dark.aedat4"  # ON and OFF in equal numbers at every pixel of every window: no signal
    t = np.repeat(np.arange(0, 4000, 500), 2)
    evtk.write_events(dark, evtk.Events(t, np.zeros(t.size, np.uint16), np.zeros(t.size, np.uint16),
                                        np.tile([0, 1], t.size // 2).astype(np.uint8), (4, 4)))
    with evtk.open(dark) as rec:
        (row,) = recording_noise(rec, ("period", 1000))
    assert row["sinad"] is None and row["repeats"] == 3


@pytest.mark.parametrize("dtype", [np.int64, np.uint64, np.int32, np.int8, bool])
def test_whole_number_captures_are_summed_exactly(dtype):
    """Counts of every size, constant pixels and blocks across groups: the integer sums give what the float route
    gives, and huge counts (whose squares leave int64) go the float route instead of wrapping."""
    rng = np.random.default_rng(5)
    if dtype is bool:
        x = rng.random((150, 6, 5)) < 0.4
    else:
        info = np.iinfo(dtype)
        hi = min(info.max, 2**62)
        x = rng.integers(max(info.min, -hi) // 2 if info.min else 0, hi // 2, (150, 6, 5), dtype=dtype)
        x[:, 0, 0] = hi // 3  # a constant pixel: no noise
        if dtype in (np.int64, np.uint64):
            x[:, 1, :] = rng.integers(0, 3, (150, 5)) + 2**40  # a large mean, tiny noise
    acc = SinadAccumulator(150, (6, 5))
    for a, b in ((0, 1), (1, 9), (9, 70), (70, 150)):  # blocks cutting across the groups of repeats
        acc.add(x[a:b])
    got = acc.report(per_pixel=True)
    want = sinad(x.astype(np.float64), per_pixel=True)
    _same_report(got, want)


def test_huge_counts_never_wrap():
    """Net counts near 2**31 (a window of two billion events at a pixel): squares summed over a block would leave
    int64; the accumulator measures them in floats, as before."""
    x = np.full((70, 3), 2**31 - 1, np.int32)
    x[::2, 1] = -(2**31) + 1
    x[:, 2] = np.arange(70) * 30_000_000
    acc = SinadAccumulator(70, 3)
    acc.add(x)
    _same_report(acc.report(), sinad(x.astype(np.float64)))


def test_enob_theta_linearises_as_reconstruct_does(tmp_path):
    """`evtk enob --theta` (it had none) measures exp(n theta) - 1, as `reconstruct --theta` and the API do, and
    refuses 0, negative, NaN and infinite thresholds as ReconstructOptions does."""
    path = tmp_path / "bench.aedat4"
    _hostile_recording(path, windows=10)
    res = CliRunner().invoke(main, ["enob", str(path), "--window", "period:1000", "--theta", "0.05", "--json"])
    assert res.exit_code == 0, res.output
    out = json.loads(res.output)
    assert out["route"] == "fixed windows (--window period:1000): exp(n theta), theta = 0.05"
    with evtk.open(path) as rec:
        (row,) = recording_noise(rec, ("period", 1000), theta=0.05)
        whole = scene_noise(reconstruct(rec, window=("period", 1000), theta=0.05))[0]
        (net,) = recording_noise(rec, ("period", 1000))
    assert out["scenes"][0]["sinad"]["sinad_db"] == pytest.approx(row["sinad"].sinad_db, rel=1e-12)
    assert row["sinad"].sinad_db == pytest.approx(whole["sinad"].sinad_db, rel=1e-9)
    assert row["sinad"].sinad_db != pytest.approx(net["sinad"].sinad_db, rel=1e-3)
    for bad in ("0", "-0.1", "nan", "inf"):
        res = CliRunner().invoke(main, ["enob", str(path), "--window", "period:1000", "--theta", bad])
        assert res.exit_code != 0 and "Traceback" not in res.output, (bad, res.output)
        assert "theta" in res.output.lower() and len(res.output.strip().splitlines()) <= 3, res.output
        if bad in ("nan", "inf"):  # (click's range refuses the others) the option's own name, before any counting
            assert "theta must be a positive finite number" in res.output, res.output
    stored = tmp_path / "r.h5"  # responses already: nothing to linearise
    assert CliRunner().invoke(main, ["reconstruct", str(path), "--window", "period:1000", "-o", str(stored)]).exit_code == 0
    res = CliRunner().invoke(main, ["enob", str(stored), "--theta", "0.1"])
    assert res.exit_code == 1 and "holds responses already" in res.output, res.output
    with pytest.raises(EvtkError, match="theta"):
        from evtk.reconstruct import ReconstructOptions

        ReconstructOptions(theta=float("nan"))


@pytest.mark.parametrize("region", [(0, 8, 0, 4), (0, 6, 1, 4)])
def test_int16_frames_widen_before_a_window_could_overflow_them(region):
    """Net counts go into int16 frames while no window of the batch holds more than 32,767 events: a window of
    40,000 ON events at one pixel (counted 1,000 events a chunk, so the batch widens to int32 after counting
    began) keeps its 40,000, a window of exactly 32,767 stays int16, an empty window and a one-event window count
    right, and events outside a region (its dump bins, which may wrap) never reach a pixel."""
    from evtk.reconstruct.windows import Windows

    rng = np.random.default_rng(11)
    parts = [  # (t0, events, x, y, p) of each window of 1,000 us
        (0, 40_000, 3, 2, 1), (1000, 0, 0, 0, 0), (2000, 1, 2, 3, 0), (3000, 32_767, 0, 1, 1), (4000, 300, 7, 0, 0)]
    t, x, y, p = [], [], [], []
    for t0, n, px, py, pol in parts:
        t.append(np.sort(rng.integers(t0, t0 + 1000, n)))
        x.append(np.full(n, px))
        y.append(np.full(n, py))
        p.append(np.full(n, pol))
    noise = rng.integers(0, 2000, 2000)  # and a sprinkle over windows 0 and 4, everywhere, both polarities
    noise[noise >= 1000] += 3000
    t = np.concatenate(t + [noise])
    order = np.argsort(t, kind="stable")
    x = np.concatenate(x + [rng.integers(0, 8, 2000)])[order].astype(np.uint16)
    y = np.concatenate(y + [rng.integers(0, 4, 2000)])[order].astype(np.uint16)
    p = np.concatenate(p + [rng.integers(0, 2, 2000)])[order].astype(np.uint8)
    ev = evtk.Events(t[order], x, y, p, (8, 4))
    win = Windows(np.arange(5) * 1000, np.arange(1, 6) * 1000, np.arange(5), "test")
    x0, x1, y0, y1 = region
    want = np.zeros((5, y1 - y0, x1 - x0), np.int64)  # each window's net counts, one event at a time
    w = ev.t // 1000
    inside = (ev.x >= x0) & (ev.x < x1) & (ev.y >= y0) & (ev.y < y1)
    np.add.at(want, (w[inside], ev.y[inside] - y0, ev.x[inside] - x0), 2 * ev.p[inside].astype(np.int64) - 1)
    assert want.max() > 40_000 - 100 and np.abs(want).max() > np.iinfo(np.int16).max
    for batches in ([0, 1, 2, 3, 4], [0], [0, 3]):
        got = [(i, net.copy()) for i, net, _ in net_count_batches(ev, win, region, batches, chunk_events=1000)]
        assert np.array_equal(np.concatenate([n for _, n in got]), want), batches
        for i, net in got:  # int16 exactly where every window of the batch held at most 32,767 events
            held = max(int(np.sum(w == k)) for k in range(i, i + len(net)))
            assert net.dtype == (np.int16 if held <= np.iinfo(np.int16).max else np.int32), (batches, i)


def test_int16_captures_are_summed_in_their_own_type_only_where_they_cannot_leave_it():
    """A block's sums in int16 (no copy) where k * largest**2 fits it, int32 beyond: the reports equal those of
    the same counts as int64, bit for bit, on both sides of the limit (16 repeats of magnitude 45: squares summed
    to 32,400; of 46: 33,856, which int16 would wrap; 1,024 repeats: groups of 16). add returns the magnitude it
    checked."""
    rng = np.random.default_rng(2)
    for big in (45, 46, 181):
        x = rng.integers(-big, big + 1, (1024, 5, 7)).astype(np.int16)
        x[:, 0, 0] = big  # the largest magnitude at one pixel in every repeat: its squares summed reach k * big**2
        x[::3, 1, 1] = -big
        wide = SinadAccumulator(1024, (5, 7))
        narrow = SinadAccumulator(1024, (5, 7))
        for a, b in ((0, 16), (16, 20), (20, 1024)):  # a group, part of one, and the rest
            assert narrow.add(x[a:b]) == big
            wide.add(x[a:b].astype(np.int64))
        got, want = narrow.report(per_pixel=True), wide.report(per_pixel=True)
        assert (got.sinad_db, got.noise_std, got.signal_rms, got.ci_db) == (want.sinad_db, want.noise_std,
                                                                             want.signal_rms, want.ci_db), big
        assert np.array_equal(got.per_pixel_db.filled(-1.0), want.per_pixel_db.filled(-1.0)), big
        assert np.array_equal(got.per_pixel_db.mask, want.per_pixel_db.mask)
    assert SinadAccumulator(2, 1).add([[0.5], [1.5]]) is None  # float captures: no magnitude


@pytest.mark.parametrize("level", [3000, 1000, 20])
def test_block_means_of_int16_counts_sum_in_a_type_they_fit(level):
    """Block means of int16 net counts: rows of 15 pixels summed in int16 only where 15 * largest fits it, the
    rows' sums of 300 pixels in int32 where int16 would wrap (3,000: rows of 45,000; 1,000: blocks of 300,000)."""
    from evtk.sweeps import _net_block_means

    rng = np.random.default_rng(4)
    net = rng.integers(-level, level + 1, (3, 30, 40)).astype(np.int16)
    net[:, :15, :20] = level  # a whole block at the largest magnitude
    net[1, 15:, 20:] = -level
    want = net.astype(np.int64).reshape(3, 2, 15, 2, 20).sum(axis=(2, 4)) / 300
    assert np.array_equal(_net_block_means(net, (2, 2), level), want)
