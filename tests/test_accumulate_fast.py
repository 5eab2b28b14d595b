"""Windows without a schedule a batch at a time (evtk.reconstruct._batched, .fixed) against the whole-run path.

The whole-run path (accumulate every window, then reconstruct_counts) stays reachable and is the reference: the
batched path must give the same counts, values and responses (to 1e-9), and keep memory bounded by a batch.
"""

from __future__ import annotations

import numpy as np
import pytest

import evtk
from evtk.errors import EvtkError
from evtk.reconstruct import Windows, accumulate, reconstruct, reconstruct_counts
from evtk.reconstruct._batched import reconstruct_windows
from evtk.reconstruct.accumulate import accumulate_batches
from evtk.reconstruct.fixed import fixed_responses

# every test twice: with evtk's compiled kernels and without them (tests/conftest.py)
pytestmark = pytest.mark.usefixtures("compiled")


def _events(n=60_000, size=(40, 30), span_us=50_000, seed=3):
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(0, span_us, n))
    # a bright corner: pixels with many events, so counts and rises vary
    x = np.where(rng.random(n) < 0.2, rng.integers(0, 4, n), rng.integers(0, size[0], n))
    y = np.where(rng.random(n) < 0.2, rng.integers(0, 4, n), rng.integers(0, size[1], n))
    p = (rng.random(n) < 0.6).astype(np.uint8)
    return evtk.Events(t, x.astype(np.uint16), y.astype(np.uint16), p, size)


def _whole_run(source, win, region, **options):
    return reconstruct_counts(accumulate(source, win, region), None, **options)


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    path = tmp_path_factory.mktemp("fast") / "rec.aedat4"
    evtk.write_events(path, _events())
    return path


@pytest.mark.parametrize("batch", [1, 3, 7, None])
@pytest.mark.parametrize("region", [(0, 40, 0, 30), (3, 29, 2, 17)])
def test_batched_counts_and_values_equal_the_whole_run(recording, batch, region):
    with evtk.open(recording) as rec:
        win = evtk.reconstruct.windows_periodic(0, 50_000, 2_000, skip_us=100, length_us=1_500)
        ref = _whole_run(rec, win, region)
        got = reconstruct_windows(rec, win, region, keep_pixels=True, batch_windows=batch)
    np.testing.assert_array_equal(got.counts.on, ref.counts.on)
    np.testing.assert_array_equal(got.counts.off, ref.counts.off)
    assert got.counts.events_used == ref.counts.events_used
    np.testing.assert_array_equal(got.cells, ref.cells)
    np.testing.assert_array_equal(got.responses, ref.responses)
    np.testing.assert_array_equal(got.binary, ref.binary)
    assert got.summary == ref.summary


def test_windows_in_any_order_and_overlapping_count_as_in_the_whole_run():
    ev = _events()
    rng = np.random.default_rng(5)
    starts = rng.integers(0, 45_000, 23)
    win = Windows(starts, starts + rng.integers(1, 9_000, 23), np.arange(23), "test")
    ref = accumulate(ev, win)
    for i, c in accumulate_batches(ev, win, (0, 40, 0, 30), batch_windows=4):
        np.testing.assert_array_equal(c.on, ref.on[i:i + len(c.windows)])
        np.testing.assert_array_equal(c.off, ref.off[i:i + len(c.windows)])


@pytest.mark.parametrize("options", [{}, {"linear": False}, {"size": (7, 9)}, {"theta": 0.05},
                                     {"binarize_method": "sign", "size": (30, 40)}])
def test_responses_alone_equal_the_whole_run(recording, options):
    with evtk.open(recording) as rec:
        win = evtk.reconstruct.windows_periodic(0, 50_000, 2_500)
        ref = _whole_run(rec, win, (2, 38, 1, 29), **options)
        got = fixed_responses(rec, win, (2, 38, 1, 29), batch_windows=6, **options)
    assert got.responses.shape == ref.responses.shape
    np.testing.assert_allclose(got.responses, ref.responses, rtol=0, atol=1e-9 * max(1.0, np.abs(ref.responses).max()))
    np.testing.assert_array_equal(got.binary, ref.binary)
    assert got.summary == ref.summary


def test_reconstruct_without_pixels_fits_a_budget_the_whole_run_does_not(recording, monkeypatch):
    with evtk.open(recording) as rec:
        full = reconstruct(rec, window=("period", 50))  # 1000 windows of the whole 40x30 sensor
        # the whole run needs every window's counts and float stages (~77 MB): far over 8 MiB
        monkeypatch.setenv("EVTK_MEMORY_LIMIT_MB", "8")
        lean = reconstruct(rec, window=("period", 50), keep_pixels=False)
        with pytest.raises(EvtkError, match="MiB"):
            reconstruct(rec, window=("period", 50), keep_pixels=True)
    np.testing.assert_allclose(lean.responses, full.responses, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(lean.binary, full.binary)
    assert lean.summary["events_used"] == full.summary["events_used"]
    assert lean.cells.shape == lean.responses.shape  # no windows x sensor array kept
    assert lean.counts.on.size == 0


def test_a_rise_beyond_exp_700_is_refused_as_by_the_whole_run():
    n = 4000  # 4000 ON events in one pixel and window: a rise of 800 at theta 0.2
    ev = evtk.Events(np.arange(n), np.zeros(n, np.uint16), np.zeros(n, np.uint16), np.ones(n, np.uint8), (64, 64))
    win = Windows([0], [n], [0], "test")
    with pytest.raises(EvtkError, match="exp\\(700\\)"):
        _whole_run(ev, win, (0, 64, 0, 64), theta=0.2)
    with pytest.raises(EvtkError, match="exp\\(700\\)"):
        fixed_responses(ev, win, (0, 64, 0, 64), theta=0.2)


def test_a_region_off_the_sensor_is_refused():
    ev = _events()
    win = Windows([0], [1000], [0], "test")
    for f in (fixed_responses, reconstruct_windows):
        with pytest.raises(EvtkError, match="not a non-empty part"):
            f(ev, win, (0, 41, 0, 30))


@pytest.mark.parametrize("theta", [0.2, 3.0, 9.0])
def test_counts_beyond_the_look_up_table_equal_the_whole_run(theta):
    # one pixel with 100 ON and 70 OFF events in a window, its neighbours a few: beyond the 64-count table
    rng = np.random.default_rng(8)
    xs = np.r_[np.full(170, 5), rng.integers(0, 16, 300)]
    ys = np.r_[np.full(170, 6), rng.integers(0, 12, 300)]
    ps = np.r_[np.ones(100), np.zeros(70), rng.integers(0, 2, 300)]
    order = rng.permutation(xs.size)
    t = np.sort(rng.integers(0, 2_000, xs.size))
    ev = evtk.Events(t, xs[order].astype(np.uint16), ys[order].astype(np.uint16), ps[order].astype(np.uint8), (16, 12))
    win = Windows([0], [2_000], [0], "test")
    options = {"theta": theta, "size": (4, 4)}
    try:
        ref = _whole_run(ev, win, (0, 16, 0, 12), **options)
    except EvtkError as exc:  # a rise beyond exp(700): refused by both
        with pytest.raises(EvtkError, match="exp\\(700\\)"):
            fixed_responses(ev, win, (0, 16, 0, 12), **options)
        assert "exp(700)" in str(exc)
        return
    got = fixed_responses(ev, win, (0, 16, 0, 12), **options)
    np.testing.assert_allclose(got.responses, ref.responses, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(got.binary, ref.binary)


@pytest.mark.parametrize("method", ["sign", "mean"])
@pytest.mark.parametrize("size", [(7, 9), (30, 40)])
def test_net_counts_tied_at_the_threshold_binarise_alike_in_both_paths(method, size):
    # net counts of -1, 0 or +1 in every pixel: whole numbers, whose resampled responses (shares of a third,
    # a seventh, ...) land exactly on 0 or on their mean in many cells, summed in another order by each path
    rng = np.random.default_rng(11)
    n_w, w_px, h_px = 40, 21, 15
    net = rng.integers(-1, 2, (n_w, h_px, w_px))
    k, y, x = np.nonzero(net)
    t = k * 1_000 + rng.integers(0, 1_000, k.size)
    order = np.argsort(t, kind="stable")
    ev = evtk.Events(t[order], x[order].astype(np.uint16), y[order].astype(np.uint16),
                     (net[k, y, x] > 0)[order].astype(np.uint8), (w_px, h_px))
    win = evtk.reconstruct.windows_periodic(0, n_w * 1_000, 1_000)
    region = (0, w_px, 0, h_px)
    options = {"linear": False, "binarize_method": method, "size": size}
    ref = _whole_run(ev, win, region, **options)
    np.testing.assert_array_equal(ref.counts.on - ref.counts.off, net)
    thr = 0.0 if method == "sign" else ref.responses.mean(axis=(1, 2), keepdims=True)
    scale = np.abs(ref.responses).max(axis=(1, 2), keepdims=True)
    assert np.sum(np.abs(ref.responses - thr) <= 1e-9 * scale) > 0  # the input does hold ties
    for got in (fixed_responses(ev, win, region, batch_windows=3, **options),
                reconstruct_windows(ev, win, region, keep_pixels=False, batch_windows=7, **options)):
        np.testing.assert_allclose(got.responses, ref.responses, rtol=0, atol=1e-9 * scale.max())
        np.testing.assert_array_equal(got.binary, ref.binary)
