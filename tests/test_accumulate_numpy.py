"""The numpy and compiled chunk counters of evtk.reconstruct.accumulate give what the numba kernel gives, and the
choice between them; linearize imports no numba."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from evtk import Events, _native
from evtk.reconstruct import accumulate
from evtk.reconstruct.accumulate import accumulate_batches
from evtk.reconstruct.linearize import linearize as _linearize  # noqa: F401  (loads the module)
from evtk.reconstruct.windows import Windows

A = sys.modules["evtk.reconstruct.accumulate"]
NATIVE = _native.BUILT and _native.TIMED_KERNELS


def _compiled(t, x, y, p, starts, ends, x0, x1, y0, y1, whole, counts, total, started, first, last):
    """The compiled kernel's count, which must take these columns (no fallback)."""
    used = _native.accumulate_chunk(t, x, y, p, starts, ends, (x0, x1, y0, y1), counts, total, started, first, last)
    assert used is not None
    return used


def _chunks_counted(kernel, chunks, starts, ends, region, whole, n_w, timed):
    x0, x1, y0, y1 = region
    frame = (x1 - x0) * (y1 - y0)
    counts = np.full(2 * n_w * frame, 77, np.int32)  # not zeroed: each window is zeroed when first reached
    total = np.zeros(n_w, np.int64)
    started = np.zeros(n_w, np.bool_)
    first = np.full(n_w * frame if timed else 0, 55, np.int32)
    last = np.full(n_w * frame if timed else 0, 55, np.int32)
    used = 0
    for t, x, y, p in chunks:
        used += kernel(t, x, y, p, starts, ends, x0, x1, y0, y1, whole, counts, total, started, first, last)
    return counts, total, started, first, last, used


def _random_case(rng, n, sensor, t0=0):
    t = np.sort(rng.integers(t0, t0 + 5000, n)).astype(np.int64)
    x = rng.integers(0, sensor[0], n).astype(np.uint16)
    y = rng.integers(0, sensor[1], n).astype(np.uint16)
    p = rng.integers(0, 2, n).astype(np.uint8)
    n_w = int(rng.integers(1, 12))
    starts = rng.integers(t0 - 1000, t0 + 6000, n_w).astype(np.int64)  # some before, some after the events
    ends = starts + rng.integers(0, 3000, n_w)  # overlapping, some empty (length 0)
    return t, x, y, p, starts, ends


@pytest.mark.parametrize("timed", [False, True])
@pytest.mark.parametrize("seed", range(12))
def test_numpy_counter_matches_numba(seed, timed):
    rng = np.random.default_rng(seed)
    sensor = (13, 9)
    n = [0, 1, 7, 400, 3000][seed % 5]
    t0 = [0, 2**62, -(2**62)][seed % 3]  # time stamps far from zero (windows stay short)
    t, x, y, p, starts, ends = _random_case(rng, n, sensor, t0)
    whole_region = (0, sensor[0], 0, sensor[1])
    for region in (whole_region, (0, 5, 0, 4), (3, 11, 2, 9), (12, 13, 8, 9)):
        whole = region == whole_region
        cuts = np.sort(rng.integers(0, n + 1, 3))  # several chunks into the same arrays (some empty)
        chunks = [(t[a:b], x[a:b], y[a:b], p[a:b]) for a, b in zip([0, *cuts], [*cuts, n])]
        ref = _chunks_counted(A._accumulate_chunk, chunks, starts, ends, region, whole, starts.size, timed)
        for kernel in (A._accumulate_chunk_numpy, _compiled) if NATIVE else (A._accumulate_chunk_numpy,):
            got = _chunks_counted(kernel, chunks, starts, ends, region, whole, starts.size, timed)
            for r, g in zip(ref, got):
                np.testing.assert_array_equal(np.asarray(g), np.asarray(r))


def _events(rng, n, sensor):
    t = np.sort(rng.integers(0, 10_000, n))
    return Events(t, rng.integers(0, sensor[0], n), rng.integers(0, sensor[1], n), rng.integers(0, 2, n), sensor)


@pytest.mark.parametrize("times", [False, True])
def test_accumulate_same_through_both_counters(monkeypatch, times):
    rng = np.random.default_rng(5)
    ev = _events(rng, 5000, (20, 10))
    win = Windows([9000, 0, 2500, 3000, 20_000], [9500, 3000, 6000, 3001, 21_000], np.arange(5), "test")
    out = {}
    routes = (("numpy", 10**9), ("numba", -1)) + ((("compiled", None),) if NATIVE else ())
    calls: list = []
    if NATIVE:
        real = _native._kernel_accumulate_chunk
        monkeypatch.setattr(_native, "_kernel_accumulate_chunk", lambda *a: calls.append(1) or real(*a))
    for name, limit in routes:
        if limit is None:
            monkeypatch.delenv("EVTK_NATIVE")
        else:
            monkeypatch.setenv("EVTK_NATIVE", "0")
            monkeypatch.setattr(A, "_NUMPY_MAX_EVENTS", limit)
        monkeypatch.setattr(A, "_numpy_work", 0)
        monkeypatch.setattr(A, "numba_ready", lambda: False)
        c = accumulate(ev, win, (2, 17, 1, 9), times=times)
        out[name] = (c.on, c.off, c.on_first_us, c.on_last_us, c.events_used)
        out[name + " batches"] = [b for _, c in accumulate_batches(ev, win, (0, 20, 0, 10), batch_windows=2)
                                  for b in (c.on, c.off, c.events_used)]
    for name, _ in routes[:1] + routes[2:]:
        assert len(out[name]) == len(out["numba"]) and len(out[name + " batches"]) == len(out["numba batches"])
        for a, b in zip(out[name], out["numba"]):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        for a, b in zip(out[name + " batches"], out["numba batches"]):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    if NATIVE:
        assert calls  # the compiled route counted, not a fallback


def test_counter_choice(monkeypatch):
    monkeypatch.setenv("EVTK_NATIVE", "0")
    monkeypatch.setattr(A, "numba_ready", lambda: False)
    monkeypatch.setattr(A, "_numpy_work", 0)
    assert A._chunk_counter(1000, 5000) is A._accumulate_chunk_numpy
    assert A._chunk_counter(A._NUMPY_MAX_EVENTS + 1, 0) is A._accumulate_chunk
    assert A._chunk_counter(1000, 5 * A._NUMPY_MAX_EVENTS) is A._accumulate_chunk  # many windows' pixels
    assert A._chunk_counter(None, 0) is A._accumulate_chunk
    # numpy's work adds up in a process: past the limit, numba's start costs less than more numpy
    monkeypatch.setattr(A, "_numpy_work", 0)
    half = A._NUMPY_MAX_EVENTS // 2
    assert A._chunk_counter(half, 0) is A._accumulate_chunk_numpy
    assert A._chunk_counter(half, 0) is A._accumulate_chunk_numpy
    assert A._chunk_counter(half, 0) is A._accumulate_chunk
    monkeypatch.setattr(A, "numba_ready", lambda: True)
    assert A._chunk_counter(1000, 5000) is A._accumulate_chunk
    monkeypatch.delenv("EVTK_NATIVE")  # the compiled kernel where built, whatever the size and numba's state
    for ready in (False, True):
        monkeypatch.setattr(A, "numba_ready", lambda ready=ready: ready)
        for events in (1000, None, 10 * A._NUMPY_MAX_EVENTS):
            assert (A._chunk_counter(events, 0) is A._accumulate_chunk_native) == NATIVE


@pytest.mark.parametrize("native", ["0", "1"])
@pytest.mark.parametrize("limit", [10**9, -1])
def test_region_at_the_corner_leaves_out_events_beyond_it(monkeypatch, limit, native):
    # a region from (0, 0) smaller than the sensor: the old kernel took it for the whole sensor and counted the
    # events beyond it at wrong pixels (or past the end of the counts)
    monkeypatch.setenv("EVTK_NATIVE", native)
    monkeypatch.setattr(A, "_NUMPY_MAX_EVENTS", limit)
    monkeypatch.setattr(A, "_numpy_work", 0)
    monkeypatch.setattr(A, "numba_ready", lambda: False)
    ev = Events([1, 2, 3, 4], [5, 1, 0, 7], [0, 0, 1, 3], [1, 1, 1, 0], (8, 4))
    c = accumulate(ev, Windows([0], [10], [0], "one"), (0, 2, 0, 2))
    assert c.events_used == 2
    assert c.on[0].tolist() == [[0, 1], [1, 0]]
    assert c.off[0].tolist() == [[0, 0], [0, 0]]
    for _, b in accumulate_batches(ev, Windows([0], [10], [0], "one"), (0, 2, 0, 2)):
        assert b.events_used == 2 and b.on[0].tolist() == [[0, 1], [1, 0]]


def test_linearize_imports_no_numba():
    src = (Path(A.__file__).parent / "linearize.py").read_text()
    assert "import numba" not in src and "from numba" not in src
    # with numba out of reach (and evtk.sensor, which still needs it, stubbed), linearize imports and linearises
    code = """
import importlib.abc, sys
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name == "numba" or name.startswith("numba."):
            raise ImportError("numba blocked")
sys.meta_path.insert(0, Block())
try:
    import evtk.sensor
except ImportError:
    stub = type(sys)("evtk.sensor")
    for n in ("PixelState", "SensorModel", "log_noise_std", "simulate_pixels", "time_constant_us"):
        setattr(stub, n, None)
    sys.modules["evtk.sensor"] = stub
import numpy as np
from evtk.reconstruct.linearize import linearize
on = np.arange(5000, dtype=np.uint8) % 7
off = np.arange(5000, dtype=np.int16) % 3
v = linearize(on, off, 0.2, 0.3)
assert np.allclose(v, np.expm1(on * 0.2 - off * 0.3))
assert "numba" not in sys.modules
"""
    subprocess.run([sys.executable, "-c", code], check=True)


@pytest.mark.parametrize("dtypes", [(np.int32, np.int32), (np.uint8, np.int16), (np.int64, np.uint16)])
def test_linearize_numpy_look_up_matches_numba(dtypes):
    L = sys.modules["evtk.reconstruct.linearize"]
    rng = np.random.default_rng(3)
    on = rng.integers(0, 200, 7000).astype(dtypes[0])
    off = rng.integers(0, 100, 7000).astype(dtypes[1])
    assert L._count_extent(on, off) == tuple(int(v) for v in L._count_extent_jit(on, off))
    assert L._count_extent(on[:0], off[:0]) == tuple(int(v) for v in L._count_extent_jit(on[:0], off[:0]))
    table = rng.random(200 * 101)
    a, b = np.empty(on.size), np.empty(on.size)
    L._look_up(on, off, table, 101, a)
    L._look_up_jit(on, off, table, 101, b)
    np.testing.assert_array_equal(a, b)


def test_numpy_counter_takes_signed_coordinates_off_a_region():
    # Events hold uint16 coordinates, but the counter is handed columns as they come: signed ones, some negative
    # or past the region, stopped the old counter on a casting error (an int64 key plus uint64 offsets)
    t = np.arange(6, dtype=np.int64)
    x = np.array([0, 3, 5, -1, 2, 4], np.int32)
    y = np.array([1, 2, 3, 0, -2, 0], np.int64)
    p = np.array([1, 0, 1, 1, 0, 1], np.uint8)
    counts = np.full(2 * 4 * 3, 9, np.int32)
    first, last = np.zeros(12, np.int32), np.zeros(12, np.int32)
    used = A._accumulate_chunk_numpy(t, x, y, p, np.array([0]), np.array([10]), 1, 5, 0, 3, False, counts,
                                     np.zeros(1, np.int64), np.zeros(1, np.bool_), first, last)
    assert used == 2  # (3, 2) OFF and (4, 0) ON; the rest lie outside x 1..4, y 0..2
    off, on = counts[:12].reshape(3, 4), counts[12:].reshape(3, 4)
    assert off.tolist() == [[0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 1, 0]]
    assert on.tolist() == [[0, 0, 0, 1], [0, 0, 0, 0], [0, 0, 0, 0]]
    assert first.reshape(3, 4)[0, 3] == last.reshape(3, 4)[0, 3] == 5 and (first >= 0).sum() == 1


@pytest.mark.skipif(not NATIVE, reason="the compiled kernels are not built")
@pytest.mark.parametrize("timed", [False, True])
def test_compiled_counter_in_runs_of_windows_on_many_threads(monkeypatch, timed):
    """With eight threads the compiled counter cuts the windows a chunk meets into runs, one a thread (no two
    writing one window); the counts, totals and times equal numba's, window by window."""
    monkeypatch.setenv("EVTK_THREADS", "8")
    monkeypatch.setattr(sys.modules["evtk._parallel"], "MIN_PART", 64)
    runs = []
    real = _native._kernel_accumulate_chunk
    monkeypatch.setattr(_native, "_kernel_accumulate_chunk", lambda *a: runs.append(a[-2:]) or real(*a))
    rng = np.random.default_rng(9)
    n = 60_000
    t = np.sort(rng.integers(0, 100_000, n)).astype(np.int64)
    x, y = rng.integers(0, 40, n).astype(np.uint16), rng.integers(0, 30, n).astype(np.uint16)
    p = rng.integers(0, 2, n).astype(np.uint8)
    starts = np.sort(rng.integers(-5_000, 100_000, 90)).astype(np.int64)
    ends = starts + rng.integers(0, 9_000, 90)
    chunks = [(t[a:b], x[a:b], y[a:b], p[a:b]) for a, b in ((0, 25_000), (25_000, 25_000), (25_000, n))]
    for region in ((0, 40, 0, 30), (5, 33, 2, 21)):
        ref = _chunks_counted(A._accumulate_chunk, chunks, starts, ends, region, region[1] == 40, 90, timed)
        runs.clear()
        got = _chunks_counted(_compiled, chunks, starts, ends, region, region[1] == 40, 90, timed)
        assert len(runs) > 4 and all(a < z for a, z in runs)
        for r, g in zip(ref, got):
            np.testing.assert_array_equal(np.asarray(g), np.asarray(r))


@pytest.mark.skipif(not NATIVE, reason="the compiled kernels are not built")
def test_compiled_counter_refuses_what_does_not_fit_and_hands_other_columns_back():
    """The kernel refuses windows past the starts, counts shorter than the windows' frames, columns of two lengths
    and a region off the coordinates (before touching memory); the wrapper gives None, nothing counted, for columns
    of other types, and the chunk counter then counts them another way (numpy's, with numba not loaded)."""
    t = np.arange(6, dtype=np.int64)
    x, y = np.array([0, 3, 5, 1, 2, 4], np.uint16), np.array([1, 2, 0, 0, 2, 0], np.uint16)
    p = np.array([1, 0, 1, 1, 0, 1], np.uint8)
    starts, ends = np.array([0, 2], np.int64), np.array([4, 10], np.int64)
    counts, total, started = np.zeros(2 * 2 * 12, np.int32), np.zeros(2, np.int64), np.zeros(2, np.bool_)
    no = np.empty(0, np.int32)
    kernel = _native._kernel_accumulate_chunk
    with pytest.raises(ValueError, match="windows outside"):
        kernel(t, x, y, p, starts, ends, 1, 5, 0, 3, counts, total, started, no, no, 0, 3)
    with pytest.raises(ValueError, match="shorter"):
        kernel(t, x, y, p, starts, ends, 1, 5, 0, 3, counts[:-1], total, started, no, no, 0, 2)
    with pytest.raises(ValueError, match="times shorter"):
        kernel(t, x, y, p, starts, ends, 1, 5, 0, 3, counts, total, started, no[:0], np.zeros(3, np.int32), 0, 2)
    with pytest.raises(ValueError, match="two lengths"):
        kernel(t, x[:5], y, p, starts, ends, 1, 5, 0, 3, counts, total, started, no, no, 0, 2)
    with pytest.raises(ValueError, match="region"):
        kernel(t, x, y, p, starts, ends, 1, 70_000, 0, 3, counts, total, started, no, no, 0, 2)
    assert not counts.any() and not started.any()
    signed = x.astype(np.int32)
    assert _native.accumulate_chunk(t, signed, y, p, starts, ends, (1, 5, 0, 3), counts, total, started, no,
                                    no) is None
    assert not counts.any()
    used = A._accumulate_chunk_native(t, signed, y, p, starts, ends, 1, 5, 0, 3, False, counts, total, started,
                                      no, no)
    ref = np.zeros_like(counts)
    want = A._accumulate_chunk_numpy(t, signed, y, p, starts, ends, 1, 5, 0, 3, False, ref, np.zeros(2, np.int64),
                                     np.zeros(2, np.bool_), no, no)
    assert used == want > 0
    np.testing.assert_array_equal(counts, ref)
