"""EVT 3.0's numpy decoder (evtk.io.prophesee.evt3) against a plain word-by-word loop: the same events, triggers,
decoder state and stops on random word streams (slices of a few words included), and whole-file reads on threads
against reads one block at a time: the same events, triggers, index and damage."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

import evtk
from evtk import _native
from evtk.io.prophesee import _evt3 as evt3
from evtk.io.prophesee import _whole, recording
from evtk.io.prophesee.decoders import ST_COORD, ST_FULL, ST_OK, ST_TYPE


def _outs(cap):
    return (np.zeros(cap, np.int64), np.zeros(cap, np.uint16), np.zeros(cap, np.uint16), np.zeros(cap, np.uint8),
            np.zeros(cap, np.int64), np.zeros(cap, np.uint8), np.zeros(cap, np.uint8))


def _loop(words, state, width, height, decode, t, x, y, p, tt, tk, tch):
    """EVT 3.0 decoded a word at a time, as the format describes it (the reference)."""
    high, low, epoch, yy, base, pol = (int(v) for v in state)
    n = m = 0
    t_min, t_max = 2**62, -(2**62)
    status, bad = ST_OK, -1
    for i, word in enumerate(int(v) for v in words):
        kind, v = word >> 12, word & 0xFFF
        if kind == 0:
            yy = v & 0x7FF
        elif kind in (2, 4, 5):
            if kind == 2:
                first, mask, step, ep = v & 0x7FF, 1, 0, (v >> 11) & 1
            else:
                first, mask, step, ep = base, v if kind == 4 else v & 0xFF, 12 if kind == 4 else 8, pol
            if decode and n + bin(mask).count("1") > len(t):
                status, bad = ST_FULL, i
                break
            tcur = (epoch << 24) | (high << 12) | low
            for k in range(12):
                if (mask >> k) & 1:
                    if first + k >= width or yy >= height:
                        status, bad = ST_COORD, i
                        break
                    if decode:
                        t[n], x[n], y[n], p[n] = tcur, first + k, yy, ep
                    n += 1
                    t_min, t_max = min(t_min, tcur), max(t_max, tcur)
            if status != ST_OK:
                break
            base += step
        elif kind == 3:
            base, pol = v & 0x7FF, (v >> 11) & 1
        elif kind == 6:
            low = v
        elif kind == 8:
            if v < high and high - v > 2048:
                epoch += 1
            high = v
        elif kind == 10:
            if decode and m >= len(tt):
                status, bad = ST_FULL, i
                break
            if decode:
                tt[m], tk[m], tch[m] = (epoch << 24) | (high << 12) | low, 1 if v & 1 else 2, (v >> 8) & 0xF
            m += 1
        elif kind not in (7, 14, 15):
            status, bad = ST_TYPE, i
            break
    state[:] = high, low, epoch, yy, base, pol
    return n, m, status, bad, t_min, t_max


def _random_words(rng, n, trial):
    kinds_all = [0, 2, 3, 4, 5, 6, 7, 8, 10, 14, 15, 1, 9, 11, 12, 13]
    probs = np.array([.15, .15, .1, .12, .1, .12, .03, .1, .04, .03, .02, .01, .01, .01, .01, .01])
    if trial % 5 == 0:  # no damaged types: whole streams
        probs[11:] = 0
    if trial % 7 == 0:  # y and time low rarely (runs of events: the decoder's other way of carrying them)
        probs[[0, 6, 8]] = .005
    if trial % 4 == 1:  # no vectors (the decoder's one-event-a-word way), vector bases still set and carried
        probs[[3, 4]] = 0
    kinds = rng.choice(kinds_all, n, p=probs / probs.sum())
    v = rng.integers(0, 4096, n)
    if trial % 3:  # mostly on the 40x25 sensor; else ST_COORD early
        small = (kinds == 0) | (kinds == 2) | (kinds == 3)
        v[small] = (v[small] & 0x800) | rng.integers(0, 20, small.sum())
    if trial % 11 == 0:  # time highs that go back by more than half: wraps of the 24-bit time
        v[kinds == 8] = rng.choice([0, 4095, 1, 3000, 2048, 2049, 2047], (kinds == 8).sum())  # drops of 2048: none
    return ((kinds << 12) | v).astype(np.uint16)


def _route(monkeypatch, route):
    """Take the numpy route (``EVTK_NATIVE=0``) or the compiled kernel's, making sure the other is not taken."""
    if route == "numpy":
        monkeypatch.setenv("EVTK_NATIVE", "0")
        return
    if not _native.BUILT or _native._kernel_evt3_run is None:
        pytest.skip("evtk's compiled kernels were not built (no C compiler at install)")
    monkeypatch.delenv("EVTK_NATIVE", raising=False)

    def refuse(*args, **kwargs):
        raise AssertionError("the numpy route was taken")

    monkeypatch.setattr(evt3, "_numpy_run", refuse)
    monkeypatch.setattr(evt3, "_scan_slice", refuse)


@pytest.mark.parametrize("slice_words, h_limit, route", [(8, evt3._H_LIMIT, "numpy"), (1 << 16, evt3._H_LIMIT, "numpy"),
                                                         (1 << 16, 0, "numpy"), (8, evt3._H_LIMIT, "native")],
                         ids=["slices-of-8", "one-slice", "time-high-apart", "compiled"])
def test_evt3_decoder_equals_a_word_by_word_loop(monkeypatch, slice_words, h_limit, route):
    """numpy's decoder and the compiled one. h_limit 0: numpy adds the time high's part apart, as after 2**28 wraps
    of the 24-bit time."""
    _route(monkeypatch, route)
    monkeypatch.setattr(evt3, "SLICE_WORDS", slice_words)
    monkeypatch.setattr(evt3, "_H_LIMIT", h_limit)
    rng = np.random.default_rng(7)
    for trial in range(600):
        n = int(rng.integers(0, 90))
        words = _random_words(rng, n, trial)
        state = np.array([rng.integers(0, 4096), rng.integers(0, 4096), rng.integers(0, 3), rng.integers(0, 30),
                          rng.integers(0, 30), rng.integers(0, 2)], np.int64)
        cap = 12 * n + 1 if trial % 4 else int(rng.integers(0, 30))  # small outputs: ST_FULL
        for decode in (False, True):
            got, want = _outs(cap), _outs(cap)
            s1, s2 = state.copy(), state.copy()
            r1 = tuple(int(a) for a in evt3.run(words, s1, 40, 25, decode, *got))
            r2 = _loop(words, s2, 40, 25, decode, *want)
            assert r1 == r2 and np.array_equal(s1, s2), (trial, decode, r1, r2, s1, s2)
            for a, b, k in zip(got, want, (r1[0],) * 4 + (r1[1],) * 3):
                assert np.array_equal(a[:k], b[:k]), trial
        # the counting scan: the same counts, and the same state once its effect is applied (up to a bad type)
        n_ev, n_tr, stop, effect = evt3.scan(words)
        s3, s4 = state.copy(), state.copy()
        evt3.advance(s3, effect)
        r = _loop(words[:stop] if stop >= 0 else words, s4, 1 << 16, 1 << 16, False, *_outs(0))
        assert (n_ev, n_tr) == r[:2] and np.array_equal(s3, s4), trial


@pytest.mark.parametrize("route", ["numpy", "native"])
def test_evt3_vectors_moved_past_65535_stop_at_the_sensor_s_edge(monkeypatch, route):
    """Vector words without events move the base on by 12 each until it passes 65535: the next vector's event lies
    off the sensor (not at its x modulo 65536), for the word-by-word loop and both decoders."""
    _route(monkeypatch, route)
    words = np.array([(0 << 12) | 1, (3 << 12) | 0] + [4 << 12] * 5462 + [(4 << 12) | 1, (2 << 12) | 3], np.uint16)
    for sensor in ((40, 25), (1 << 16, 1 << 16)):
        got, want = _outs(16), _outs(16)
        s1, s2 = np.zeros(6, np.int64), np.zeros(6, np.int64)
        r1 = tuple(int(a) for a in evt3.run(words, s1, *sensor, True, *got))
        r2 = _loop(words, s2, *sensor, True, *want)
        assert r1 == r2 and r1[2] == ST_COORD and r1[3] == 5464 and np.array_equal(s1, s2), (r1, r2)


def _evt3_file(path, words, sensor=(40, 25)):
    head = f"% evt 3.0\n% format EVT3;width={sensor[0]};height={sensor[1]}\n".encode()
    path.write_bytes(head + np.asarray(words, "<u2").tobytes())


def _index_one_block_at_a_time(path):
    """The reader's index counted block after block from the state the last one left: rows and first problem."""
    with evtk.open(path, salvage=True) as rec:
        rows, state = [], rec._initial_state()
        for b in range(rec._n_blocks()):
            start, words = state.copy(), rec._words(b)
            n_ev, n_tr, st, bad, lo, hi = evt3.run(words, state, 1 << 16, 1 << 16, False, *_outs(0))
            rows.append((start, n_ev, n_tr, lo, hi))
            if st != ST_OK:
                return rows, rec._word_problem(words, st, bad, b * rec._per_block())
        return rows, None


def _one_block_at_a_time(path, salvage):
    """Events, triggers, index and damage read block by block (the reader's streaming path)."""
    with evtk.open(path, salvage=salvage) as rec:
        parts, trs, problem = [], [], None
        for ev, tr, problem in rec._through():
            parts.append(ev)
            trs.append(tr)
            if problem:
                break
        return (evtk.Events.concatenate(parts, sensor_size=rec.sensor_size), evtk.Triggers.concatenate(trs),
                rec._blocks, problem)


def _assert_whole_read_equals_block_by_block(path, salvage, trial):
    """A whole read (``events``; its triggers and index rows, or its damage) against the block-by-block read."""
    ev_b, tr_b, rows_b, problem = _one_block_at_a_time(path, salvage)
    with evtk.open(path, salvage=salvage) as rec:
        if problem and not salvage:
            with pytest.raises(evtk.FormatError) as err:
                rec.events()
            assert err.value.offset == problem[0], trial
            return
        ev = rec.events()
        assert ev == ev_b, trial
        if problem:
            assert rec.damage.offset == problem[0] and rec._blocks is None, trial
            return
        assert rec.triggers() == tr_b, trial
        assert len(rec._blocks) == len(rows_b), trial
        for a, b in zip(rec._blocks, rows_b):
            assert np.array_equal(a[0], b[0]) and a[1:] == b[1:], trial


@pytest.mark.parametrize("threads, route", [("1", "numpy"), ("3", "numpy"), ("3", "native")])
def test_a_whole_evt3_read_on_threads_equals_the_block_by_block_read(tmp_path, monkeypatch, threads, route):
    """Blocks of 64 words decoded on 3 threads from the states the counting pass gives them: the events, triggers,
    index rows and first problem of a read one block after another, damaged streams included; with numpy, and with
    the compiled kernel."""
    _route(monkeypatch, route)
    monkeypatch.setattr(recording, "BLOCK_WORDS", 64)
    monkeypatch.setattr(_whole, "THREADED_BLOCKS", 2)
    monkeypatch.setattr(_whole, "THREAD_BYTES", 1)  # each thread's memory paid for by any file
    monkeypatch.setenv("EVTK_THREADS", threads)
    rng = np.random.default_rng(11)
    path = tmp_path / "r.raw"
    for trial in range(60):
        words = _random_words(rng, int(rng.integers(0, 900)), trial if trial % 2 else 5 * trial)
        _evt3_file(path, words)
        for salvage in (False, True):
            # the index alone (a window's first step, `evtk info`), counted on the threads
            rows_i, problem_i = _index_one_block_at_a_time(path)
            with evtk.open(path, salvage=salvage) as rec:
                if problem_i and not salvage:
                    with pytest.raises(evtk.FormatError) as err:
                        rec._index()
                    assert err.value.offset == problem_i[0], trial
                else:
                    rows = rec._index()
                    assert (rec.damage.offset if problem_i else None) == (problem_i[0] if problem_i else None), trial
                    assert len(rows) == len(rows_i), trial
                    for a, b in zip(rows, rows_i):
                        assert np.array_equal(a[0], b[0]) and tuple(int(v) for v in a[1:]) == b[1:], trial
            _assert_whole_read_equals_block_by_block(path, salvage, trial)


def test_the_evt3_index_finds_a_vector_base_moved_off_the_counting_sensor(tmp_path, monkeypatch):
    """The index counts on a 65536-wide sensor without decoding, unless a block's vectors could reach its edge:
    5,600 VECT_12 words after one base move the base past x = 65535, a stop the index must give as the
    block-by-block count does (and time ranges around it)."""
    monkeypatch.setattr(recording, "BLOCK_WORDS", 512)
    monkeypatch.setattr(_whole, "THREADED_BLOCKS", 2)
    monkeypatch.setenv("EVTK_THREADS", "2")
    words = [(8 << 12) | 5, (6 << 12) | 9, 3, (3 << 12)] + [(4 << 12) | 0xFFF, (6 << 12) | 10] * 5600
    path = tmp_path / "far.raw"
    _evt3_file(path, words)
    rows_i, problem_i = _index_one_block_at_a_time(path)
    assert problem_i is not None and "outside" in problem_i[1]
    with evtk.open(path, salvage=True) as rec:
        rows = rec._index()
        assert rec.damage.offset == problem_i[0] and len(rows) == len(rows_i)
        for a, b in zip(rows, rows_i):
            assert np.array_equal(a[0], b[0]) and tuple(int(v) for v in a[1:]) == b[1:]


def test_a_large_evt3_file_reads_its_writer_s_events(tmp_path, monkeypatch):
    monkeypatch.setattr(recording, "BLOCK_WORDS", 1 << 12)
    monkeypatch.setenv("EVTK_THREADS", "2")
    rng = np.random.default_rng(1)
    ev = evtk.Events(np.sort(rng.integers(0, 40_000_000, 30_000)), rng.integers(0, 320, 30_000).astype(np.uint16),
                     rng.integers(0, 240, 30_000).astype(np.uint16), rng.integers(0, 2, 30_000).astype(np.uint8),
                     (320, 240))
    path = tmp_path / "a.raw"
    evtk.write_events(path, ev, fmt="evt3")
    got = evtk.read_events(path)
    for a, b in zip((got.t, got.x, got.y, got.p), (ev.t, ev.x, ev.y, ev.p)):
        assert np.array_equal(a, b)


_PEAK_CHILD = """
import sys
import evtk

def hwm():
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmHWM:")) * 1024

with evtk.open(sys.argv[1]) as rec:
    before = hwm()
    ev = rec.events()
    after = hwm()
arrays = sum(a.nbytes for a in (ev.t, ev.x, ev.y, ev.p))
print(len(ev), (after - before) / arrays, "numba" in sys.modules)
"""


@pytest.mark.skipif(not os.path.exists("/proc/self/status"), reason="reads VmHWM from /proc")
def test_a_large_evt3_read_peaks_within_a_tenth_of_its_arrays_and_loads_no_compiler(tmp_path):
    """Issue 32 item 5: 8.4 M words (more than the 8 M from which numba's loop, 100 MiB and more of runtime, used
    to decode) read whole on two threads in a fresh process: the peak resident memory grows by at most 1.1 times
    the arrays returned, and numba is never imported."""
    n_ev = 4_200_000
    k = np.arange(n_ev)
    words = np.empty(2 * n_ev, np.uint16)
    words[0::2] = k * 7 % 480  # EVT_ADDR_Y
    words[1::2] = (2 << 12) | (k * 13 % 640) | ((k & 1) << 11)  # EVT_ADDR_X
    words[0:-1:40] = (6 << 12) | ((k[::20] // 20) & 0xFFF)  # a time low every 20 events, for a y word
    _evt3_file(tmp_path / "big.raw", words, (640, 480))
    env = dict(os.environ, EVTK_THREADS="2", PYTHONPATH=os.pathsep.join(sys.path))
    out = subprocess.run([sys.executable, "-c", _PEAK_CHILD, str(tmp_path / "big.raw")], env=env, cwd=tmp_path,
                         capture_output=True, text=True, check=True).stdout.split()
    assert int(out[0]) == n_ev
    assert float(out[1]) <= 1.1, out
    assert out[2] == "False"


def _es_loop(data, state, width, height, atis=False):
    """Event Stream 2.x DVS (or ATIS) bytes decoded one at a time, as the format's tables describe them (the
    reference): returns the events, the stop (``(ST_COORD, index of the event's last byte)`` or ``(ST_OK, -1)``)
    and the state (ATIS: the threshold crossings left out last, and None where a stop leaves a value as it was).
    ATIS threshold crossings are counted, not events."""
    tc, phase, xi, yi, flags = (int(v) for v in state[:5])
    left = int(state[5]) if atis else 0
    ev = []
    for i, b in enumerate(data.tolist()):
        if phase == 0:
            if atis and b >= 0xFC:
                tc += 63 * (b & 3)
            elif atis:
                tc, flags, phase = tc + (b >> 2), b & 3, 1
            elif b == 0xFF:
                tc += 127
            elif b != 0xFE:
                tc, flags, phase = tc + (b >> 1), b & 1, 1
        elif phase == 1:
            xi, phase = b, 2
        elif phase == 2:
            xi, phase = xi | b << 8, 3
        elif phase == 3:
            yi, phase = b, 4
        else:
            yi, phase = yi | b << 8, 0
            if xi >= width or yi >= height:
                return ev, (ST_COORD, i), [tc, phase] + ([None, None, None, left] if atis else [])
            if atis and flags & 1:
                left += 1
            else:
                ev.append((tc, xi, height - 1 - yi, flags >> 1 if atis else flags))
    return ev, (ST_OK, -1), [tc, phase, xi, yi, flags] + ([left] if atis else [])


def _es_bytes(rng, items, ff_share):
    """Random Event Stream bytes: events (some with 0xFE/0xFF inside, a few off a 640x480 sensor) between single
    0xFE bytes and runs of 0xFF."""
    out = []
    for _ in range(items):
        r = rng.random()
        if r < ff_share:
            out += [0xFF] * int(rng.integers(1, 12))
        elif r < 1.2 * ff_share:
            out.append(0xFE)
        else:
            x, y = int(rng.integers(0, 640)), int(rng.integers(0, 480))
            if rng.random() < 0.05:
                x, y = 0x1FF, 0xFE  # x's low byte 0xFF, y's 0xFE: such bytes inside an event are not markers
            if rng.random() < 0.0005:
                x = 640 + int(rng.integers(0, 100))
            out += [int(rng.integers(0, 0xFE)), x & 0xFF, x >> 8, y & 0xFF, y >> 8]
    return np.array(out, np.uint8)


@pytest.mark.parametrize("slice_bytes", [7, 333, 1 << 16])
def test_event_stream_numpy_decoder_equals_a_byte_by_byte_loop(monkeypatch, slice_bytes):
    """The numpy Event Stream decoder (one cumulative sum for the times, straight into the time column, with the
    0xFF bytes between event ranges added at each range's first event) gives the loop's events, stop and clock,
    slices cutting events and runs of 0xFF anywhere, with and without decoding (the index's count)."""
    from evtk.io.prophesee import _fallbacks

    monkeypatch.setattr(_fallbacks, "ES_MARKER_SHARE", 1.0)  # every slice through numpy, however many 0xFF
    monkeypatch.setattr(_fallbacks, "ES_SLICE_BYTES", slice_bytes)
    rng = np.random.default_rng(slice_bytes)
    for trial in range(60):
        data = _es_bytes(rng, int(rng.integers(1, 2500)), [0.0, 0.002, 0.02, 0.2][trial % 4])
        start = [int(rng.integers(0, 1 << 40)), 0, 0, 0, 0]
        want, stop, clock = _es_loop(data, start, 640, 480)
        for decode in (True, False):
            state = np.array(start, np.int64)
            out = _outs(len(data) // 5 + 1)
            n, _, status, bad, lo, hi = _fallbacks._es_np_run(data, state, 640, 480, decode, *out)
            assert (status, bad) == stop and n == len(want)
            assert state[:len(clock)].tolist() == clock
            if want:
                assert (lo, hi) == (want[0][0], want[-1][0])
            if decode:
                got = list(zip(*(c[:n].tolist() for c in out[:4])))
                assert got == want


def _random_evt2_words(rng, n, trial):
    """EVT 2.0 words: events (mostly on the 40x25 sensor), time highs (wrapping at times), triggers, padding, and
    now and then a word of no type."""
    kinds = rng.choice([0, 1, 8, 10, 14, 15, 2, 9, 12], n, p=[.3, .3, .15, .08, .05, .05, .03, .02, .02])
    if trial % 4 == 0 or trial % 3 == 1:  # no damaged types: whole streams
        kinds[np.isin(kinds, [2, 9, 12])] = 0
    w = rng.integers(0, 1 << 28, n, dtype=np.int64)
    if trial % 3:  # on the sensor (trial % 3 == 1), or now and then just off it; else anywhere (ST_COORD early)
        ev = kinds <= 1
        off = 2 if trial % 3 == 2 else 0
        w[ev] = ((w[ev] & ~np.int64((1 << 22) - 1)) | (rng.integers(0, 40 + off, ev.sum()) << 11)
                 | rng.integers(0, 25 + off, ev.sum()))
    if trial % 5 == 0:  # time highs that wrap: near the top of the 28-bit counter, then near 0
        hi = kinds == 8
        w[hi] = rng.choice([0, 5, (1 << 28) - 3, (1 << 27), (1 << 27) + 1], hi.sum())
    return ((kinds.astype(np.int64) << 28) | w).astype(np.uint32)


def _random_dat_words(rng, n, trial):
    """DAT events as (time stamp, data) pairs: stamps that wrap at times, coordinates mostly on the 40x25 sensor."""
    stamps = np.sort(rng.integers(0, 1 << 32, n, dtype=np.int64)) if trial % 2 else rng.choice(
        [0, 7, (1 << 31), (1 << 31) + 1, (1 << 32) - 1], n)
    off = {0: 1 << 14, 1: 0, 2: 2}[trial % 3]  # anywhere, on the 40x25 sensor, now and then just off it
    xs, ys = rng.integers(0, 40 + off, n), rng.integers(0, 25 + off, n)
    data = (rng.integers(0, 16, n) << 28) | (ys << 14) | xs
    return np.stack([stamps, data], 1).reshape(-1).astype(np.uint32)


@pytest.mark.parametrize("fmt", ["evt2", "dat"])
def test_the_compiled_evt2_and_dat_decoders_give_numpy_s_results(fmt):
    """Random words, both modes: the compiled kernels' counts, stops, time ranges, states and columns are numpy's
    decoders' (the oracle, itself compared with files expelliarmus reads in tests/test_prophesee.py)."""
    from evtk.io.prophesee import _fallbacks, decoders

    if not _native.BUILT or _native._kernel_evt2_run is None:
        pytest.skip("evtk's compiled kernels were not built (no C compiler at install)")
    rng = np.random.default_rng(5)
    for trial in range(400):
        n = int(rng.integers(0, 120))
        if fmt == "evt2":
            words = _random_evt2_words(rng, n, trial)
            state = np.array([rng.integers(0, 1 << 28), rng.integers(0, 3)], np.int64)
        else:
            words = _random_dat_words(rng, n, trial)
            state = np.array([-1 if trial % 2 else rng.integers(0, 1 << 32), rng.integers(0, 3)], np.int64)
        for decode in (False, True):
            got, want = _outs(len(words)), _outs(len(words))
            s1, s2 = state.copy(), state.copy()
            if fmt == "evt2":
                r1 = _native.evt2_run(words, s1, 40, 25, decode, *got, decoders._NATIVE_STATUS)
                r2 = _fallbacks._evt2_numpy_run(words, s2, 40, 25, decode, *want)
            else:
                r1 = _native.dat_run(words, s1, 40, 25, decode, *got[:4], decoders._NATIVE_STATUS)
                r2 = _fallbacks._dat_numpy_run(words, s2, 40, 25, decode, *want)
            assert r1 is not None
            r2 = tuple(int(v) for v in r2)
            assert r1 == r2 and np.array_equal(s1, s2), (trial, decode, r1, r2, s1, s2)
            for a, b, k in zip(got, want, (r1[0],) * 4 + (r1[1],) * 3):
                assert np.array_equal(a[:k], b[:k]), trial


def _raw_file(path, fmt, words, sensor=(40, 25)):
    """An EVT 2.0 (.raw) or DAT (.dat) file of the given words on a 40x25 sensor."""
    if fmt == "evt2":
        head = f"% evt 2.0\n% format EVT2;width={sensor[0]};height={sensor[1]}\n".encode()
    else:
        head = f"% Data file containing Event2D events.\n% Version 2\n% Width {sensor[0]}\n% Height {sensor[1]}\n"
        head = head.encode() + bytes([0x0C, 8])
    path.write_bytes(head + np.asarray(words, "<u4").tobytes())


@pytest.mark.parametrize("fmt", ["evt2", "dat"])
@pytest.mark.parametrize("route, layout", [("numpy", "threads"), ("native", "threads"), ("native", "in place")])
def test_a_whole_evt2_or_dat_read_equals_the_block_by_block_read(tmp_path, monkeypatch, fmt, route, layout):
    """Blocks of 64 items on 3 threads, from the states and places the counting pass gives them, or on one thread
    straight into columns as long as the items: the events, triggers, index rows and first problem of a read one
    block after another (the streaming path), damaged streams included (words of no type, events off the sensor);
    with numpy's scan and decoders, and the kernels."""
    _route(monkeypatch, route)
    calls = []
    whole = _whole.read_whole
    monkeypatch.setattr(_whole, "read_whole", lambda *a, **k: calls.append(1) or whole(*a, **k))
    if route == "native":  # neither numpy scan may be taken either
        def refuse(*args, **kwargs):
            raise AssertionError("the numpy route was taken")

        from evtk.io.prophesee import _fallbacks
        monkeypatch.setattr(_fallbacks, "_evt2_numpy_run", refuse)
        monkeypatch.setattr(_fallbacks, "_dat_numpy_run", refuse)
        monkeypatch.setattr(_whole, "_first_stop", refuse)
        monkeypatch.setattr(_whole, "_clock_effect", refuse)
    monkeypatch.setattr(recording, "BLOCK_WORDS", 64 * (2 if fmt == "dat" else 1))
    if layout == "threads":  # from 2 blocks, each thread's memory paid for by any file
        monkeypatch.setattr(_whole, "THREADED_BLOCKS", 2)
        monkeypatch.setattr(_whole, "THREAD_BYTES", 1)
    monkeypatch.setenv("EVTK_THREADS", "3")
    rng = np.random.default_rng(13)
    path = tmp_path / ("r.raw" if fmt == "evt2" else "r.dat")
    for trial in range(40):
        n = int(rng.integers(0, 700))
        words = _random_evt2_words(rng, n, trial) if fmt == "evt2" else _random_dat_words(rng, n, trial)
        _raw_file(path, fmt, words)
        for salvage in (False, True):
            _assert_whole_read_equals_block_by_block(path, salvage, trial)
    assert bool(calls) == (layout == "threads")


@pytest.mark.parametrize("fmt", ["evt2", "dat"])
def test_the_compiled_evt2_and_dat_scans_give_numpy_s_counts_and_effects(monkeypatch, fmt):
    """The counting pass of a whole read: the kernels' counts, stops and effects are the numpy scans'."""
    if not _native.BUILT or _native._kernel_evt2_scan is None:
        pytest.skip("evtk's compiled kernels were not built (no C compiler at install)")
    rng = np.random.default_rng(17)
    numpy_scan = _whole._evt2_scan if fmt == "evt2" else _whole._dat_scan
    for trial in range(300):
        n = int(rng.integers(0, 150))
        words = _random_evt2_words(rng, n, trial) if fmt == "evt2" else _random_dat_words(rng, n, trial)
        got = _native.prophesee_scan(fmt, words)
        monkeypatch.setenv("EVTK_NATIVE", "0")
        want = numpy_scan(words)
        monkeypatch.delenv("EVTK_NATIVE")
        assert got is not None and got == want, (trial, got, want)


#: Per encoding: the kernel's name, the word type, the state's least values, the values past its most for the
#: wrapper and for the raw kernel (the states its words can leave; the EVT 3.0 wrapper keeps the epoch below 2**39,
#: where the time still fits int64), the most where the time fits int64 (compared with numpy there), and a state
#: inside them.
_STATE_RANGES = {
    "evt3": ("evt3_run", np.uint16, (0, 0, 0, 0, 0, 0), (4096, 4096, 1 << 39, 2048, 1 << 40, 2),
             (4096, 4096, 1 << 40, 2048, 1 << 40, 2), (4095, 4095, (1 << 39) - 1, 2047, (1 << 40) - 1, 1),
             (7, 9, 3, 5, 11, 1)),
    "evt2": ("evt2_run", np.uint32, (0, 0), (1 << 28, 1 << 40), (1 << 28, 1 << 40), ((1 << 28) - 1, (1 << 29) - 1),
             (5, 2)),
    "dat": ("dat_run", np.uint32, (-1, 0), (1 << 32, 1 << 40), (1 << 32, 1 << 40), ((1 << 32) - 1, (1 << 31) - 1),
            (-1, 2)),
}


@pytest.mark.parametrize("fmt", sorted(_STATE_RANGES))
def test_a_state_or_sensor_no_file_can_give_goes_to_numpy_and_the_raw_kernel_refuses_it(fmt):
    """Each value of a decoder's state one past either end of its range (a vector base at 2**63 - 1 made the
    EVT 3.0 kernel's sum overflow, found by tests/fuzz/kernels.py under UBSan), and sensors of other sizes: the
    wrapper returns None (the numpy route), the raw kernel raises ValueError and leaves the state and columns
    alone; at either end itself (where the time fits int64) both decode as numpy does."""
    from evtk import _ckernels
    from evtk.io.prophesee import _fallbacks, decoders

    if not _native.BUILT or _native._kernel_evt3_run is None:
        pytest.skip("evtk's compiled kernels were not built (no C compiler at install)")
    name, dtype, lowest, above, kernel_above, top, inside = _STATE_RANGES[fmt]
    rng = np.random.default_rng(3)
    words = {"evt3": lambda: _random_words(rng, 300, 4), "evt2": lambda: _random_evt2_words(rng, 300, 1),
             "dat": lambda: _random_dat_words(rng, 150, 1)}[fmt]().astype(dtype)
    numpy_run = {"evt3": evt3._numpy_run, "evt2": _fallbacks._evt2_numpy_run, "dat": _fallbacks._dat_numpy_run}[fmt]
    for k in range(len(lowest)):
        for value in sorted({lowest[k] - 1, above[k], kernel_above[k], lowest[k], top[k]}):
            state = np.array(inside, np.int64)
            state[k] = value
            got, want = _outs(12 * len(words)), _outs(12 * len(words))
            cols = got[:4] if fmt == "dat" else got
            wrapped = getattr(_native, name)(words, state.copy(), 40, 25, True, *cols, decoders._NATIVE_STATUS)
            if not lowest[k] <= value < above[k]:
                assert wrapped is None, (k, value)
            if not lowest[k] <= value < kernel_above[k]:
                before = state.copy()
                with pytest.raises(ValueError, match="state"):
                    getattr(_ckernels, name)(words, state, 40, 25, True, *cols)
                assert np.array_equal(state, before) and not got[0].any(), (k, value)
            if lowest[k] <= value <= top[k]:
                s1, s2 = state.copy(), state.copy()
                r1 = getattr(_native, name)(words, s1, 40, 25, True, *cols, decoders._NATIVE_STATUS)
                r2 = tuple(int(v) for v in numpy_run(words, s2, 40, 25, True, *want))
                assert r1 == r2 and np.array_equal(s1, s2), (k, value, r1, r2)
                assert all(np.array_equal(a[:r1[0]], b[:r1[0]]) for a, b in zip(got[:4], want[:4])), (k, value)
    # the sensor: 0 to 65536 pixels a side (a width of -2**63 made the EVT 3.0 kernel's room overflow: UBSan)
    for width, height in ((-1, 25), (40, -1), (65537, 25), (40, 65537), (-(1 << 63), 25), (65536, 65536), (0, 0)):
        state = np.array(inside, np.int64)
        got, want = _outs(12 * len(words)), _outs(12 * len(words))
        cols = got[:4] if fmt == "dat" else got
        wrapped = getattr(_native, name)(words, state.copy(), width, height, True, *cols, decoders._NATIVE_STATUS)
        if not (0 <= width <= 65536 and 0 <= height <= 65536):
            assert wrapped is None, (width, height)
            with pytest.raises(ValueError, match="sensor"):
                getattr(_ckernels, name)(words, state, width, height, True, *cols)
            continue
        r2 = tuple(int(v) for v in numpy_run(words, state.copy(), width, height, True, *want))
        assert wrapped == r2, (width, height)
        assert all(np.array_equal(a[:r2[0]], b[:r2[0]]) for a, b in zip(got[:4], want[:4])), (width, height)


@pytest.mark.parametrize("atis", [False, True], ids=["dvs", "atis"])
def test_the_compiled_event_stream_decoder_equals_a_byte_by_byte_loop(atis):
    """DVS and ATIS bytes (markers in runs and inside events, events off the sensor, starts inside an event),
    both modes: the kernel's events, stop, time range and state are the loops' (and, for DVS, numpy's
    decoder's)."""
    from evtk.io.prophesee import _fallbacks, decoders

    if not _native.BUILT or _native._kernel_es_run is None:
        pytest.skip("evtk's compiled kernels were not built (no C compiler at install)")
    rng = np.random.default_rng(8)
    for trial in range(300):
        data = _es_bytes(rng, int(rng.integers(1, 600)), [0.0, 0.02, 0.2, 0.6][trial % 4])
        if atis and trial % 3:  # ATIS markers: 0xFC to 0xFF
            data[data >= 0xFE] = rng.integers(0xFC, 0x100, int((data >= 0xFE).sum()))
        phase = int(rng.integers(0, 5)) if trial % 5 == 0 else 0
        start = [int(rng.integers(0, 1 << 40)), phase, int(rng.integers(0, 640)), int(rng.integers(0, 480)),
                 int(rng.integers(0, 4 if atis else 2)), int(rng.integers(0, 9))]
        want, stop, clock = _es_loop(data, start if atis else start[:5], 640, 480, atis)
        for decode in (True, False):
            state = np.array(start, np.int64)
            out = _outs(len(data) // 5 + 1)
            got = _native.es_run(data, state, 640, 480, decode, atis, *out[:4], decoders._NATIVE_STATUS)
            assert got is not None
            n, m, status, bad, lo, hi = got
            assert (status, bad) == stop and n == len(want) and m == 0, (trial, decode)
            assert [v for v, w in zip(state.tolist(), clock) if w is not None] == [w for w in clock if w is not None]
            if not atis:
                assert state[5] == start[5]
            if want:
                assert (lo, hi) == (min(e[0] for e in want), max(e[0] for e in want))
            if decode:
                assert list(zip(*(c[:n].tolist() for c in out[:4]))) == want, trial
            if not atis and decode:  # numpy's decoder: the same
                s2, o2 = np.array(start, np.int64), _outs(len(data) // 5 + 1)
                r2 = _fallbacks._es_np_run(data, s2, 640, 480, True, *o2)
                assert tuple(int(v) for v in r2[:4]) == (n, 0, status, bad)
                assert all(np.array_equal(a[:n], b[:n]) for a, b in zip(out[:4], o2[:4]))


def test_the_event_stream_kernel_refuses_what_no_file_gives():
    """States no bytes leave, sensors past 65536 and columns too short for the bytes: the wrapper returns None (the
    Python routes), the raw kernel raises ValueError."""
    from evtk import _ckernels
    from evtk.io.prophesee import decoders

    if not _native.BUILT or _native._kernel_es_run is None:
        pytest.skip("evtk's compiled kernels were not built (no C compiler at install)")
    data = _es_bytes(np.random.default_rng(1), 50, 0.1)
    good = [5, 0, 0, 0, 0, 0]
    bad_states = [[-1, 0, 0, 0, 0, 0], [1 << 62, 0, 0, 0, 0, 0], [0, 5, 0, 0, 0, 0], [0, 0, 1 << 16, 0, 0, 0],
                  [0, 0, 0, -1, 0, 0], [0, 0, 0, 0, 4, 0], [0, 0, 0, 0, 0, -1]]
    cases = [(s, 640, 480, len(data) // 5 + 1, "state") for s in bad_states]
    cases += [(good, 65537, 480, len(data) // 5 + 1, "sensor"), (good, 640, -1, len(data) // 5 + 1, "sensor"),
              (good, 640, 480, len(data) // 5, "columns")]
    for state, width, height, room, what in cases:
        out = _outs(room)[:4]
        s = np.array(state, np.int64)
        assert _native.es_run(data, s, width, height, True, False, *out, decoders._NATIVE_STATUS) is None, what
        with pytest.raises(ValueError, match=what if what != "columns" else "fewer events"):
            _ckernels.es_run(data, s, width, height, True, False, *out)
    out = _outs(len(data) // 5 + 1)[:4]  # at the ends of the ranges: decoded
    top = np.array([(1 << 62) - 1, 4, 65535, 65535, 3, (1 << 62) - 1], np.int64)
    assert _native.es_run(data, top, 65536, 65536, True, True, *out, decoders._NATIVE_STATUS) is not None


@pytest.mark.parametrize("quiet", [False, True], ids=["busy", "quiet"])
def test_an_event_stream_file_reads_alike_on_both_routes(tmp_path, monkeypatch, quiet):
    """A DVS Event Stream file, busy or with long silences (runs of 0xFF, which numpy's route hands to numba's
    loop), whole, in windows and cut by blocks: the compiled kernel's events are the numpy route's."""
    from conftest import random_events

    monkeypatch.setattr(recording, "BLOCK_WORDS", 4099)
    ev = random_events(20_000, seed=9, sensor_size=(640, 480), span_us=20_000_000 if quiet else 200_000)
    path = tmp_path / "q.es"
    evtk.write_events(path, ev)
    from evtk.io.prophesee import _fallbacks

    got = {}
    for route in ("numpy", "native"):
        _route(monkeypatch, route)
        if route == "native":
            monkeypatch.setattr(_fallbacks, "_es_np_run", None)  # the numpy route not taken
        with evtk.open(path) as rec:
            got[route] = (rec.events(), rec.events(int(ev.t[5000]), int(ev.t[15000])), len(rec._blocks))
    assert got["native"][0] == got["numpy"][0] == ev
    assert got["native"][1:] == got["numpy"][1:] and got["native"][2] > 5


@pytest.mark.parametrize("fmt", ["evt2", "dat"])
@pytest.mark.parametrize("route", ["numpy", "native"])
def test_a_time_past_int64_stops_the_read_at_its_word_on_every_path(tmp_path, monkeypatch, fmt, route):
    """A time counter wrapped more often than int64 holds (2**29 EVT 2.0 wraps, 2**31 DAT: GiBs of words) stops
    every read at the word that passes 2**63 - 1 µs, with a FormatError naming its byte, or with salvage the events
    before it; before, numpy raised Python's OverflowError and the kernels wrapped to negative times. The reader
    starts here one wrap short of the limit (its initial state), over blocks of 64 items on 3 threads."""
    _route(monkeypatch, route)
    shift, slot = (34, 1) if fmt == "evt2" else (32, 1)
    most = (2**63 - 1) >> shift
    initial = recording.PropheseeRecording._initial_state

    def near_the_end(self):
        state = initial(self)
        state[slot] = most
        return state

    monkeypatch.setattr(recording.PropheseeRecording, "_initial_state", near_the_end)
    monkeypatch.setattr(recording, "BLOCK_WORDS", 64 * (2 if fmt == "dat" else 1))
    monkeypatch.setattr(_whole, "THREADED_BLOCKS", 2)
    monkeypatch.setattr(_whole, "THREAD_BYTES", 1)
    monkeypatch.setenv("EVTK_THREADS", "3")
    rng = np.random.default_rng(5)
    n_before, n_after = 150, 100
    xs, ys = rng.integers(0, 40, n_before + n_after), rng.integers(0, 25, n_before + n_after)
    if fmt == "evt2":
        top = 0xFFFFF00  # time highs in the counter's top half, rising; then one back at 16: a wrap
        words = [(8 << 28) | top]
        for k in range(n_before):
            words += [(8 << 28) | (top + k // 10)] if k % 10 == 0 else []
            words.append(_cd2(k % 64, int(xs[k]), int(ys[k])))
        stop = len(words)
        words += [(8 << 28) | 16] + [_cd2(k % 64, int(xs[k]), int(ys[k])) for k in range(n_before, n_before + 100)]
        item = 4
        t_before = [(most << 34) | ((top + k // 10) << 6) | (k % 64) for k in range(n_before)]
    else:
        stamps = [0xFFFFF000 + k for k in range(n_before)] + [16 + k for k in range(n_after)]
        words = []
        for k, ts in enumerate(stamps):
            words += [ts, (1 << 28) | (int(ys[k]) << 14) | int(xs[k])]
        stop, item = n_before, 8
        t_before = [(most << 32) | ts for ts in stamps[:n_before]]
    path = tmp_path / ("r.raw" if fmt == "evt2" else "r.dat")
    _raw_file(path, fmt, words)
    head = len(path.read_bytes()) - 4 * len(words)
    with pytest.raises(evtk.FormatError, match=r"passes 2\*\*63 - 1 us") as err:
        evtk.read_events(path)
    assert err.value.offset == head + item * stop
    with evtk.open(path, salvage=True) as rec:
        ev = rec.events()
        assert ev.t.tolist() == t_before and ev.x.tolist() == xs[:n_before].tolist()
        assert rec.damage.offset == head + item * stop
    with evtk.open(path, salvage=True) as rec:  # the windowed path: its index, then a window
        assert rec.events(t_before[40], t_before[90]) == ev.between(t_before[40], t_before[90])
    _assert_whole_read_equals_block_by_block(path, True, fmt)
    _assert_whole_read_equals_block_by_block(path, False, fmt)


def _cd2(t_low, x, y, on=1):
    """An EVT 2.0 CD word."""
    return (on << 28) | (t_low << 22) | (x << 11) | y
