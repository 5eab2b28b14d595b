"""evtk's compiled counting (``evtk._ckernels`` behind ``evtk._native``): the same counts as numpy's scattered adds,
every argument it cannot take refused without touching memory outside its buffers, and the fixed-window routes
giving the same numbers with it and without it."""

from __future__ import annotations

import numpy as np
import pytest

import evtk
from evtk import _native, _parallel
from evtk.reconstruct import Windows, windows_periodic
from evtk.reconstruct.fixed import count_batches, net_count_batches

needs_kernel = pytest.mark.skipif(not _native.BUILT, reason="evtk._ckernels was not built (no C compiler)")


def _oracle(x, y, p, picks, at, ky, kx, on_step, limit, per_window, dump, net, out):
    """The kernel's rule in numpy: each window's picked events to ``w * per_window + k`` or ``dump``."""
    for w in range(len(at) - 1):
        e = picks[at[w]:at[w + 1]]
        on = (p[e] != 0).astype(np.int64)
        k = ky[y[e]] + kx[x[e]] + on_step * on
        inside = (k >= 0) & (k < limit)
        bins = np.where(inside, w * per_window + k, dump)
        np.add.at(out, bins, (2 * on - 1 if net else np.ones_like(on)).astype(out.dtype))


def _case(rng, n_ev=5_000, n_w=7, size=(37, 29), per_window=None, picks=False):
    w, h = size
    x = rng.integers(0, 2 * w, n_ev).astype(np.uint16)  # half of them off the table's sensor: the dump
    y = rng.integers(0, h, n_ev).astype(np.uint16)
    p = rng.integers(0, 2, n_ev).astype(np.uint8)
    frame = w * h
    per_window = per_window or 2 * frame
    dump = n_w * per_window
    ky = _native.padded_table(np.arange(h, dtype=np.int64) * w, dump)
    kx = _native.padded_table(np.arange(w, dtype=np.int64), dump)
    counts = rng.integers(0, (n_ev - 100) // n_w, n_w)
    counts[rng.integers(0, n_w)] = 0  # a window without events
    at = np.concatenate(([0], np.cumsum(counts))).astype(np.int64)
    where = (rng.integers(0, n_ev, int(at[-1])).astype(np.int64) if picks else slice(100, 100 + int(at[-1])))
    return x, y, p, where, at, ky, kx, frame, per_window, dump


@needs_kernel
@pytest.mark.parametrize("dtype", [np.int16, np.int32])
@pytest.mark.parametrize("net", [True, False])
@pytest.mark.parametrize("picks", [True, False])
def test_the_kernel_counts_what_numpys_scattered_adds_count(dtype, net, picks):
    rng = np.random.default_rng(7)
    x, y, p, where, at, ky, kx, frame, per_window, dump = _case(rng, picks=picks)
    on_step = 0 if net else frame
    limit = frame if net else 2 * frame
    got = np.zeros(dump + 1, dtype)
    want = np.zeros_like(got)
    assert _native.count_windows(x, y, p, where, at, ky, kx, on_step, limit, per_window, dump, net, got)
    indices = where if picks else np.arange(where.start, where.stop, dtype=np.int64)
    _oracle(x, y, p, indices, at, ky, kx, on_step, limit, per_window, dump, net, want)
    np.testing.assert_array_equal(got, want)
    assert got[dump] != 0  # the off-sensor half went to the dump, not to another pixel


@needs_kernel
@pytest.mark.parametrize("dtype", [np.int16, np.int32])
@pytest.mark.parametrize("built_clearing", [True, False])
def test_the_kernel_clears_the_windows_it_is_given_and_no_others(dtype, built_clearing, monkeypatch):
    # bins full of leftovers: windows 2 .. 4 are cleared before they are counted (the first cleared one without
    # events of its own), the others keep what they held, counts added to it; a build before the kernel cleared
    # (no COUNT_CLEARS) gets the same bins from the wrapper
    monkeypatch.setattr(_native, "_COUNT_CLEARS", int(built_clearing))
    rng = np.random.default_rng(11)
    x, y, p, where, at, ky, kx, frame, per_window, dump = _case(rng, n_w=7)
    at[3] = at[2]  # window 2: no events
    old = rng.integers(-99, 99, dump + 1).astype(dtype)
    got = old.copy()
    assert _native.count_windows(x, y, p, where, at, ky, kx, 0, frame, per_window, dump, True, got, (2, 5))
    want = old.copy()
    want[2 * per_window:5 * per_window] = 0
    _oracle(x, y, p, np.arange(where.start, where.stop, dtype=np.int64), at, ky, kx, 0, frame, per_window, dump,
            True, want)
    np.testing.assert_array_equal(got, want)
    assert np.any(got[:2 * per_window] != 0) and not np.any(got[2 * per_window:3 * per_window])


@needs_kernel
def test_the_kernel_wraps_in_the_bins_type_as_numpy_does():
    # 40,000 ON events on one pixel: int16 bins wrap (the callers widen them before that can happen)
    n = 40_000
    x, y, p = (np.zeros(n, np.uint16), np.zeros(n, np.uint16), np.ones(n, np.uint8))
    table = _native.padded_table(np.zeros(1, np.int64), 5)
    at = np.array([0, n], np.int64)
    got = np.zeros(6, np.int16)
    assert _native.count_windows(x, y, p, slice(0, n), at, table, table, 0, 1, 1, 5, True, got)
    want = np.zeros(6, np.int16)
    np.add.at(want, np.zeros(n, np.intp), np.int16(1))
    np.testing.assert_array_equal(got, want)


def _args(n=10):
    rng = np.random.default_rng(1)
    x, y, p, where, at, ky, kx, frame, per_window, dump = _case(rng, n_ev=n * 100, n_w=3)
    return dict(x=x, y=y, p=p, where=where, at=at, ky=ky, kx=kx, on_step=0, limit=frame, per_window=per_window,
                dump=dump, net=True, out=np.zeros(dump + 1, np.int16))


@pytest.mark.parametrize("change", [
    lambda a: a.update(x=a["x"].astype(np.int32)),  # coordinates not uint16
    lambda a: a.update(p=a["p"].view(np.bool_)),  # polarities not uint8
    lambda a: a.update(y=a["y"][::-1]),  # not contiguous
    lambda a: a.update(y=a["y"][:-1]),  # columns of different lengths
    lambda a: a.update(ky=a["ky"][:1000]),  # a table shorter than every uint16 coordinate
    lambda a: a.update(at=a["at"].astype(np.int32)),
    lambda a: a.update(out=np.zeros(10, np.int64)),  # bins of another type
    lambda a: a.update(out=np.zeros(a["dump"], np.int16)),  # the dump bin outside the bins
    lambda a: a.update(limit=a["per_window"] + 1),  # a window's bins reaching the next window's
    lambda a: a.update(where=slice(0, None, 2)),  # a slice with a step
    lambda a: a.update(where=np.arange(3, dtype=np.int32)),
    lambda a: a.update(at=np.zeros(1, np.int64)),  # no window
])
def test_the_wrapper_turns_away_what_the_kernel_does_not_take_and_counts_nothing(change):
    args = _args()
    change(args)
    before = args["out"].copy()
    assert not _native.count_windows(**args)
    np.testing.assert_array_equal(args["out"], before)


def test_evtk_native_0_turns_the_kernel_off(monkeypatch):
    monkeypatch.setenv("EVTK_NATIVE", "0")
    assert not _native.enabled()
    args = _args()
    assert not _native.count_windows(**args)
    assert not args["out"].any()


@needs_kernel
@pytest.mark.parametrize("change, fault", [
    (lambda a: a.__setitem__(6, np.array([0, 10**9], np.int64)), "outside the picks"),  # at past the events
    (lambda a: a.__setitem__(3, np.array([5, -1], np.int64)), "pick outside"),  # a pick outside the events
    (lambda a: a.__setitem__(7, np.zeros(10, np.int64)), "65536"),  # a short table
    (lambda a: a.__setitem__(12, 10**9), "outside the bins"),  # the dump bin
    (lambda a: a.__setitem__(10, 10**9), "outside the bins"),  # a limit past the window
    (lambda a: a.__setitem__(6, np.array([0, 50, 100], np.int64)) or a.__setitem__(11, 10**9),
     "outside the bins"),  # the second window's bins past the bins
    (lambda a: a.__setitem__(6, np.array([0, 30, 60, 100], np.int64)) or a.__setitem__(11, 1 << 62),
     "outside the bins"),  # the third window's bins at 2**63: a product that would wrap below zero
    (lambda a: a.__setitem__(15, 8), "2 or 4 bytes"),
    (lambda a: a.__setitem__(1, a[1][:-1]), "differ in length"),
])
def test_the_kernel_itself_refuses_arguments_that_would_reach_outside_its_buffers(change, fault):
    # called directly, past the wrapper's checks: a ValueError naming the fault, never a crash
    n = 100
    x, y, p = np.zeros(n, np.uint16), np.zeros(n, np.uint16), np.ones(n, np.uint8)
    table = np.zeros(_native.TABLE_SIZE, np.int64)
    args = [x, y, p, np.zeros(0, np.int64), False, 0, np.array([0, n], np.int64), table, table, 0, 1, 1, 3, True,
            np.zeros(4, np.int16), 2]
    if fault == "pick outside":
        args[4], args[6] = True, np.array([0, 2], np.int64)
    change(args)
    with pytest.raises(ValueError, match=fault):
        _native._kernel_count_windows(*args)


def _recording_events(n=120_000, size=(64, 48), span_us=60_000, seed=5):
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(0, span_us, n)).astype(np.int64)
    t[: n // 3] = 1_000  # a window with 40,000 events: int16 net counts widen to int32
    return evtk.Events(np.sort(t), rng.integers(0, size[0], n).astype(np.uint16),
                       rng.integers(0, size[1], n).astype(np.uint16), rng.integers(0, 2, n).astype(np.uint8), size)


def _both(monkeypatch, fn):
    out = {}
    for value in ("1", "0"):
        monkeypatch.setenv("EVTK_NATIVE", value)
        out[value] = fn()
    return out["1"], out["0"]


@needs_kernel
@pytest.mark.parametrize("region", [(0, 64, 0, 48), (5, 41, 7, 31)])
@pytest.mark.parametrize("overlapping", [False, True])
def test_net_counts_are_the_same_with_the_kernel_and_without(monkeypatch, region, overlapping):
    ev = _recording_events()
    if overlapping:  # windows that overlap and come out of order: their events are picked by index
        rng = np.random.default_rng(2)
        starts = np.sort(rng.integers(0, 55_000, 40))[::-1].astype(np.int64)
        starts[5] = 500  # one of them holds the 40,000 events at 1 ms
        win = Windows(starts, starts + 4_000, np.arange(40), "test")
    else:
        win = windows_periodic(0, 60_000, 1_000)

    def counts():
        return [(i, c.copy(), most) for i, c, most in net_count_batches(ev, win, region, batch_windows=9,
                                                                          chunk_events=7_000)]

    native, numpy = _both(monkeypatch, counts)
    assert len(native) == len(numpy)
    for (i, a, m), (j, b, n) in zip(native, numpy):
        assert (i, m) == (j, n) and a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)
    assert any(a.dtype == np.int32 for _, a, _ in native)  # the widened batch was reached


@needs_kernel
@pytest.mark.parametrize("cells", [None, (4, 6), (3, 3)])
@pytest.mark.parametrize("region", [(0, 64, 0, 48), (10, 46, 3, 39)])
def test_on_and_off_counts_are_the_same_with_the_kernel_and_without(monkeypatch, cells, region):
    ev = _recording_events(n=60_000)
    rng = np.random.default_rng(4)
    starts = rng.integers(0, 55_000, 30).astype(np.int64)  # overlapping, in any order
    win = Windows(starts, starts + 5_000, np.arange(30), "test")

    def counts():
        return [(i, on.copy(), off.copy(), used) for i, on, off, used in
                count_batches(ev, win, region, cells, batch_windows=7, chunk_events=9_000)]

    native, numpy = _both(monkeypatch, counts)
    for (i, on_a, off_a, used_a), (j, on_b, off_b, used_b) in zip(native, numpy, strict=True):
        assert (i, used_a) == (j, used_b)
        np.testing.assert_array_equal(on_a, on_b)
        np.testing.assert_array_equal(off_a, off_b)


def test_counting_that_releases_the_gil_takes_half_the_threads(monkeypatch):
    # numpy's scattered adds hold the GIL: at most MOST_PARTS parts; the compiled kernel: half the threads
    monkeypatch.setenv("EVTK_THREADS", "16")
    work = 64 * _parallel.MIN_PART
    assert _parallel.parts(work) == _parallel.MOST_PARTS
    assert _parallel.parts(work, gil_free=True) == 8
    assert _parallel.parts(_parallel.MIN_PART, gil_free=True) == 1  # each part still worth a thread


def _numpy_sums(net, size):
    a = net.astype(object) if np.abs(net.astype(np.int64)).max(initial=0) > 1 << 20 else net.astype(np.int64)
    k, h, w = net.shape
    blocks = None
    if size is not None and h % size[0] == 0 and w % size[1] == 0:
        blocks = a.reshape(k, size[0], h // size[0], size[1], w // size[1]).sum((2, 4))
    return a.sum(0), (a * a).sum(0), int(np.abs(a).max(initial=0)), blocks


@needs_kernel
@pytest.mark.parametrize("dtype", [np.int16, np.int32])
@pytest.mark.parametrize(("shape", "size", "most"), [
    ((16, 240, 320), (16, 16), 40),        # enob's batches: SSE2 pairs, blocks of 15 x 20
    ((7, 12, 21), (4, 3), 90),             # an odd number of windows, blocks of odd width (no pair sums)
    ((3_000, 2, 8), (2, 4), 1_000),        # k * m * m past int32: the eight pixels summed again in 64 bits
    ((5, 6, 21), (2, 7), 30),              # rows of 21: a tail past the eight-pixel groups
    ((3, 8, 12), (16, 16), 9),             # a grid that does not divide the frame: no block sums
    ((4, 6, 6), (3, 2), 32767),            # the largest int16 magnitudes: int32 sums would overflow
    ((70_000, 2, 2), (1, 1), 32767),       # many windows: the squares' sums past int32
    ((1, 1, 1), None, 5),
])
def test_the_net_sums_kernel_gives_numpys_sums(dtype, shape, size, most):
    rng = np.random.default_rng(sum(shape) + most)
    net = rng.integers(-most, most, shape, endpoint=True).astype(dtype)
    got = _native.net_sums(net, size)
    want = _numpy_sums(net, size)
    assert got is not None
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])
    assert got[2] == want[2]
    if want[3] is None:
        assert got[3] is None
    else:
        np.testing.assert_array_equal(got[3], want[3])


@needs_kernel
def test_the_net_sums_kernel_sums_again_where_int32_would_overflow():
    # magnitudes of 30,000 over six windows: each pixel's squares pass 2**31, so the eight-pixel groups' int32
    # sums would wrap; they are summed again in 64 bits
    rng = np.random.default_rng(8)
    net = (30_000 * rng.choice([-1, 1], (6, 2, 16))).astype(np.int16)
    got, want = _native.net_sums(net, (1, 2)), _numpy_sums(net, (1, 2))
    assert int(want[1].min()) > 2**31
    for a, b in zip(got, want):
        np.testing.assert_array_equal(a, b)


@needs_kernel
@pytest.mark.parametrize("dtype", [np.int16, np.int32])
def test_the_net_sums_kernel_at_the_types_ends(dtype):
    # -32768 (int16) or int32's ends: the 64-bit route, exact for int16; int32's squares wrap past int64 as two's
    # complement (the caller's bound, k * big**2 < 2**63, then sends the repeats to numpy's float route)
    info = np.iinfo(dtype)
    net = np.array([[[info.min, info.max, 0, -1, 1, info.min, 3, info.max, 2]]] * 3, dtype).reshape(3, 1, 9)
    net[1] = -net[1] // 2
    got = _native.net_sums(net, (1, 3))
    want = _numpy_sums(net, (1, 3))
    wrapped = [((int(v) + 2**63) % 2**64) - 2**63 for v in np.asarray(want[1], dtype=object).ravel()]
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1].ravel(), np.array(wrapped, np.int64))
    assert got[2] == want[2] == -int(info.min)
    np.testing.assert_array_equal(got[3], want[3])


@needs_kernel
def test_the_net_sums_kernel_on_several_threads_equals_one(monkeypatch):
    rng = np.random.default_rng(3)
    net = rng.integers(-60, 60, (9, 240, 320)).astype(np.int16)
    monkeypatch.setenv("EVTK_THREADS", "1")
    one = _native.net_sums(net, (16, 16))
    monkeypatch.setenv("EVTK_THREADS", "8")
    monkeypatch.setattr(_parallel, "MIN_PART", 1)
    many = _native.net_sums(net, (16, 16))
    for a, b in zip(one, many):
        np.testing.assert_array_equal(a, b)


@needs_kernel
def test_the_net_sums_kernel_sums_into_the_arrays_it_is_given_where_they_fit():
    rng = np.random.default_rng(4)
    net = rng.integers(-50, 50, (5, 12, 16)).astype(np.int16)
    want = _numpy_sums(net, (4, 4))
    s1, s2 = np.full((12, 16), 99, np.int64), np.full((12, 16), 99, np.int64)
    got = _native.net_sums(net, (4, 4), (s1, s2))
    assert got[0] is s1 and got[1] is s2  # (the arrays given, every value written)
    for a, b in zip(got, want):
        np.testing.assert_array_equal(a, b)
    base = np.zeros((12, 16), np.int64)
    for out in [(s1, s1), (s1[:6], s2[:6]), (s1.astype(np.int32), s2), (s1.T, s2.T), (base, base.view()),
                (s1, np.zeros((12, 16), np.int64)[::-1])]:  # shared, short, int32, strided, one memory
        got = _native.net_sums(net, (4, 4), out)
        assert not any(a is b for a in got[:2] for b in out)  # not used: new arrays
        for a, b in zip(got, want):
            np.testing.assert_array_equal(a, b)


@needs_kernel
def test_the_net_sums_kernel_refuses_what_does_not_fit():
    net = np.zeros((2, 4, 6), np.int16)
    s = np.zeros(24, np.int64)
    for args in [(net, 3, 2, 4, 6, 0, 4, 0, 0, s, s.copy(), s),                # a width of 3 bytes
                 (net, 2, 3, 4, 6, 0, 4, 0, 0, s, s.copy(), s),                # more windows than the counts
                 (net, 2, 2, 4, 6, 0, 5, 0, 0, s, s.copy(), s),                # rows past the frame
                 (net, 2, 2, 4, 6, 0, 4, 0, 0, s[:10], s.copy(), s),           # sums too short
                 (net, 2, 2, 4, 6, 0, 4, 0, 0, s, s, s),                       # one array for both sums
                 (net, 2, 2, 4, 6, 0, 4, 3, 2, s, s.copy(), s),                # blocks that do not tile
                 (net, 2, 2, 4, 6, 1, 4, 2, 2, s, s.copy(), s),                # rows that split a block row
                 (net, 2, 2, 4, 6, 0, 4, 2, 0, s, s.copy(), s),                # one block size of two
                 (net, 2, 2, 4, 6, 0, 4, 1, 1, s, s.copy(), np.zeros(5, np.int64))]:  # block sums too short
        with pytest.raises(ValueError):
            _native._kernel_net_sums(*args)
    assert _native.net_sums(np.zeros((2, 3), np.int16)) is None and _native.net_sums(np.zeros((1, 2, 2), np.int8)) is None
