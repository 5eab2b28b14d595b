"""The fixed-window counting and the SINAD sums split over threads (evtk._parallel) give exactly one thread's
numbers, whatever the cut: runs of windows straddling a chunk, a batch or another run, pixels outside the region
(each run has its own dump bin), windows without events, pixel runs that do not divide the frame.

``MIN_PART`` is lowered so that the small test data is cut into several parts; each test also checks that the
work was in fact cut (one thread's path would pass the equality checks trivially).
"""

from __future__ import annotations

import sys

import numpy as np
import pytest

import evtk
from evtk import _parallel
from evtk.metrics import SinadAccumulator
from evtk.reconstruct import Windows, windows_periodic
from evtk.reconstruct.fixed import net_count_batches
from evtk.sweeps import recording_noise

# every test twice: with evtk's compiled kernels and without them (tests/conftest.py)
pytestmark = pytest.mark.usefixtures("compiled")

SENSOR = (23, 17)  # a frame of 391 pixels: no run of pixels divides it evenly


def _events(seed: int = 3, n: int = 30_000) -> evtk.Events:
    """Events over 30 windows of 1000 us; windows 10-12 empty, a hot pixel, many stamps on window bounds."""
    rng = np.random.default_rng(seed)
    t = rng.integers(0, 30_000, n)
    t = np.where(rng.random(n) < 0.1, (t // 1000) * 1000, t)
    t = np.where((t >= 10_000) & (t < 13_000), t + 3_000, t)
    x = rng.integers(0, SENSOR[0], n)
    y = rng.integers(0, SENSOR[1], n)
    hot = rng.random(n) < 0.05
    x[hot], y[hot] = 5, 6
    p = np.where(hot, rng.random(n) < 0.9, rng.random(n) < 0.5)
    order = np.argsort(t, kind="stable")
    return evtk.Events(t[order], x[order].astype(np.uint16), y[order].astype(np.uint16), p[order].astype(np.uint8),
                       SENSOR)


def _reference(ev: evtk.Events, win, region) -> np.ndarray:
    """Each window's net counts over the region, one window at a time with plain indexing."""
    x0, x1, y0, y1 = region
    out = np.zeros((len(win), y1 - y0, x1 - x0), np.int64)
    for w in range(len(win)):
        m = (ev.t >= win.t_start_us[w]) & (ev.t < win.t_end_us[w])
        m &= (ev.x >= x0) & (ev.x < x1) & (ev.y >= y0) & (ev.y < y1)
        np.add.at(out[w], (ev.y[m].astype(np.int64) - y0, ev.x[m].astype(np.int64) - x0),
                  np.where(ev.p[m] > 0, 1, -1))
    return out


@pytest.fixture
def cut_small(monkeypatch):
    """Parts of 64 elements and up, and a record of how many parts each split used."""
    monkeypatch.setattr(_parallel, "MIN_PART", 64)
    monkeypatch.setattr(_parallel, "MOST_PARTS", 64)  # the cuts' arithmetic on more parts than the default's two
    used: list[int] = []
    run = _parallel.run

    def counting(fn, args):
        used.append(len(args))
        return run(fn, args)

    monkeypatch.setattr(_parallel, "run", counting)
    for mod in ("evtk.reconstruct.fixed", "evtk.metrics.sinad"):
        monkeypatch.setattr(sys.modules[mod], "run", counting)
    return used


def _net(source, win, region, batch, chunk):
    return np.concatenate([net.copy() for _, net, _ in net_count_batches(source, win, region, batch,
                                                                         chunk_events=chunk)])


@pytest.mark.parametrize("region", [(0, 23, 0, 17), (2, 20, 1, 15), (5, 6, 6, 7)])
@pytest.mark.parametrize("batch, chunk", [(30, 4_000_000), (7, 1_733), ([0, 4, 5, 19], 997)])
@pytest.mark.parametrize("threads", ["4", "6", "16"])
def test_net_counts_on_several_threads_equal_one_thread(cut_small, monkeypatch, tmp_path, region, batch, chunk,
                                                        threads):
    ev = _events()
    path = tmp_path / "r.aedat4"
    evtk.write_events(path, ev)
    win = windows_periodic(0, 30_000, 1000)
    ref = _reference(ev, win, region)
    monkeypatch.setenv("EVTK_THREADS", "1")
    with evtk.open(path) as rec:
        one = _net(rec, win, region, batch, chunk)
    assert max(cut_small, default=1) == 1
    monkeypatch.setenv("EVTK_THREADS", threads)
    with evtk.open(path) as rec:
        many = _net(rec, win, region, batch, chunk)
    sorted_many = _net(ev, win, region, batch, chunk)  # in-memory events: chunks are slices
    assert max(cut_small) > 1  # the counting was in fact split
    np.testing.assert_array_equal(one, ref)
    np.testing.assert_array_equal(many, ref)
    np.testing.assert_array_equal(sorted_many, ref)


def test_overlapping_windows_on_several_threads(cut_small, monkeypatch):
    # windows that overlap go batch by batch through the time-window reads, their events gathered, not sliced
    ev = _events(5)
    starts = np.arange(0, 28_000, 700)
    win = Windows(starts[::-1].copy(), starts[::-1] + 1_500, np.arange(starts.size), "test")  # in any order
    monkeypatch.setenv("EVTK_THREADS", "4")
    got = _net(ev, win, (1, 22, 2, 16), 9, 1_000)
    assert max(cut_small) > 1
    np.testing.assert_array_equal(got, _reference(ev, win, (1, 22, 2, 16)))


@pytest.mark.parametrize("dtype, scale", [(np.int32, 1), (np.int16, 1), (np.int64, 3_000_000)])
def test_sinad_sums_on_several_threads_equal_one_thread(cut_small, monkeypatch, dtype, scale):
    # integer captures: per-pixel sums and squares on runs of pixels; every figure the same to the last bit
    rng = np.random.default_rng(1)
    x = ((rng.poisson(3, (90, 391)) - rng.poisson(2, (90, 391))) * scale + 7 * scale).astype(dtype)
    reports = []
    for threads in ("1", "6"):
        monkeypatch.setenv("EVTK_THREADS", threads)
        acc = SinadAccumulator(90, (17, 23))
        for a in range(0, 90, 13):
            acc.add(x[a:a + 13])
        reports.append(acc.report(per_pixel=True, interval="jackknife"))
    assert max(cut_small) > 1
    one, many = reports
    assert (one.sinad_db, one.ci_db, one.noise_std) == (many.sinad_db, many.ci_db, many.noise_std)
    np.testing.assert_array_equal(one.per_pixel_db, many.per_pixel_db)


def test_enob_of_a_recording_on_several_threads_equals_one_thread(cut_small, monkeypatch, tmp_path):
    path = tmp_path / "r.aedat4"
    evtk.write_events(path, _events(9))
    rows = []
    for threads in ("1", "4"):
        monkeypatch.setenv("EVTK_THREADS", threads)
        with evtk.open(path) as rec:
            rows.append(recording_noise(rec, ("period", 1000), size=(17, 23), per_pixel=True)[0])
    assert max(cut_small) > 1
    one, many = rows
    assert one["sinad"].sinad_db == many["sinad"].sinad_db and one["sinad"].ci_db == many["sinad"].ci_db
    np.testing.assert_array_equal(one["sinad"].per_pixel_db, many["sinad"].per_pixel_db)
    assert one["flips"].pairwise_pct == many["flips"].pairwise_pct
    np.testing.assert_array_equal(one["flips"].per_pixel, many["flips"].per_pixel)


@pytest.mark.parametrize("region, cells", [((0, 23, 0, 17), None), ((2, 20, 1, 15), (7, 9)), ((0, 23, 0, 17), (17, 1))])
@pytest.mark.parametrize("batch, chunk", [(None, 4_000_000), (4, 1_111)])
def test_on_and_off_counts_on_several_threads_equal_one_thread(cut_small, monkeypatch, tmp_path, region, cells,
                                                               batch, chunk):
    # count_batches (evtk reconstruct's route): each run of windows counts into its own windows' bins
    from evtk.reconstruct.fixed import count_batches

    ev = _events(11)
    path = tmp_path / "r.aedat4"
    evtk.write_events(path, ev)
    win = windows_periodic(0, 30_000, 1000)
    got = []
    for threads in ("1", "6"):
        monkeypatch.setenv("EVTK_THREADS", threads)
        with evtk.open(path) as rec:
            got.append([(i, on.copy(), off.copy(), used) for i, on, off, used in
                        count_batches(rec, win, region, cells, batch_windows=batch, chunk_events=chunk)])
    assert max(cut_small) > 1
    one, many = got
    assert [(i, used) for i, _, _, used in one] == [(i, used) for i, _, _, used in many]
    for (_, on1, off1, _), (_, on2, off2, _) in zip(one, many):
        np.testing.assert_array_equal(on1, on2)
        np.testing.assert_array_equal(off1, off2)
    net = np.concatenate([on - off for _, on, off, _ in one])
    if cells is None:  # and they are the counts themselves
        np.testing.assert_array_equal(net, _reference(ev, win, region))


@pytest.mark.parametrize("pixels", [1, 2, 5])
def test_captures_of_fewer_pixels_than_threads(cut_small, monkeypatch, pixels):
    # many repeats of a few pixels: the runs of pixels are never empty (an empty run's max raised)
    monkeypatch.setenv("EVTK_THREADS", "16")
    x = np.random.default_rng(2).integers(-9, 9, (4_000, pixels)).astype(np.int32)
    acc = SinadAccumulator(4_000, pixels)
    acc.add(x)
    monkeypatch.setenv("EVTK_THREADS", "1")
    one = SinadAccumulator(4_000, pixels)
    one.add(x)
    assert acc.report().sinad_db == one.report().sinad_db


@pytest.mark.parametrize("floats", [False, True])
@pytest.mark.parametrize("interval", ["jackknife", "bootstrap", None])
def test_the_reports_runs_of_pixels_on_two_threads_give_one_threads_figures(monkeypatch, floats, interval):
    """The report centres the groups' means a run of pixels at a time; without the groups' Gram matrix (counts'
    exact jackknife, no interval) the runs go to two threads, each run's sums kept apart and added in the runs'
    order: every figure the same to the last bit whatever the threads."""
    sinad_module = sys.modules["evtk.metrics.sinad"]
    calls: list[tuple[str, int]] = []
    real = sinad_module.run

    def spy(fn, args):
        calls.append((fn.__qualname__, len(args)))
        return real(fn, args)

    monkeypatch.setattr(sinad_module, "run", spy)
    rng = np.random.default_rng(4)
    x = rng.poisson(3, (150, 391)) - rng.poisson(2, (150, 391))
    x = x * 0.37 + 5.0 if floats else x.astype(np.int16)
    reports = []
    for threads in ("1", "2", "5"):
        monkeypatch.setenv("EVTK_THREADS", threads)
        acc = SinadAccumulator(150, (17, 23))
        for a in range(0, 150, 40):
            acc.add(x[a:a + 40])
        reports.append(acc.report(per_pixel=True, interval=interval, seed=3))
    split = [k for name, k in calls if name.startswith("SinadAccumulator._between")]
    assert max(split) == (1 if floats and interval is not None or interval == "bootstrap" else 2), split
    one = reports[0]
    for other in reports[1:]:
        assert (other.sinad_db, other.ci_db, other.noise_std) == (one.sinad_db, one.ci_db, one.noise_std)
        np.testing.assert_array_equal(other.per_pixel_db, one.per_pixel_db)


@pytest.mark.parametrize("threads", ["2", "4", "16", "64"])
def test_counting_is_cut_into_two_parts_at_most_by_default(monkeypatch, threads):
    # the scatter-adds keep the GIL: more parts only took turns for it on a 16-core machine (issue 32, tenth round)
    monkeypatch.setenv("EVTK_THREADS", threads)
    assert _parallel.parts(10**9) == min(int(threads) // 2, _parallel.MOST_PARTS) == min(int(threads) // 2, 2)
    assert _parallel.parts(2 * _parallel.MIN_PART - 1) == 1
