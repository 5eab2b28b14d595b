"""EVT 3.0's numpy decoder (small files, no compiler to load) against its numba loop (large files): the same
events, triggers, decoder state and stops on random word streams, slices of a few words included."""

from __future__ import annotations

import numpy as np
import pytest

import evtk
from evtk.io.prophesee import decoders, recording


def _outs(cap):
    return (np.zeros(cap, np.int64), np.zeros(cap, np.uint16), np.zeros(cap, np.uint16), np.zeros(cap, np.uint8),
            np.zeros(cap, np.int64), np.zeros(cap, np.uint8), np.zeros(cap, np.uint8))


@pytest.mark.parametrize("slice_words", [8, 1 << 16])
def test_evt3_numpy_decoder_equals_the_numba_loop(monkeypatch, slice_words):
    monkeypatch.setattr(decoders, "SLICE_WORDS", slice_words)
    rng = np.random.default_rng(7)
    kinds_all = [0, 2, 3, 4, 5, 6, 7, 8, 10, 14, 15, 1, 9]  # 1 and 9 are no EVT 3.0 type: ST_TYPE
    probs = [.15, .15, .1, .12, .1, .12, .03, .1, .04, .03, .02, .02, .02]
    for trial in range(400):
        n = int(rng.integers(0, 60))
        kinds = rng.choice(kinds_all, n, p=probs)
        v = rng.integers(0, 4096, n)
        if trial % 3:  # mostly on the 40x25 sensor; else ST_COORD early
            small = (kinds == 0) | (kinds == 2) | (kinds == 3)
            v[small] = (v[small] & 0x800) | rng.integers(0, 20, small.sum())
        words = ((kinds << 12) | v).astype(np.uint16)
        state = np.array([rng.integers(0, 4096), rng.integers(0, 4096), rng.integers(0, 3), rng.integers(0, 30),
                          rng.integers(0, 30), rng.integers(0, 2)], np.int64)
        cap = n + 12 if trial % 4 else int(rng.integers(0, 30))  # small outputs: ST_FULL
        for decode in (False, True):
            got, want = _outs(cap), _outs(cap)
            s1, s2 = state.copy(), state.copy()
            r1 = tuple(int(a) for a in decoders._evt3_run(words, s1, 40, 25, decode, *got))
            r2 = tuple(int(a) for a in decoders._evt3_run_jit(words, s2, 40, 25, decode, *want))
            assert r1 == r2 and np.array_equal(s1, s2), (trial, decode, r1, r2)
            for a, b, k in zip(got, want, (r1[0],) * 4 + (r1[1],) * 3):
                assert np.array_equal(a[:k], b[:k]), trial


def test_a_large_evt3_file_reads_the_same_through_numba(tmp_path, monkeypatch):
    ev = evtk.Events(np.sort(np.random.default_rng(1).integers(0, 200_000, 30_000)),
                     np.random.default_rng(2).integers(0, 320, 30_000).astype(np.uint16),
                     np.random.default_rng(3).integers(0, 240, 30_000).astype(np.uint16),
                     np.random.default_rng(4).integers(0, 2, 30_000).astype(np.uint8), (320, 240))
    path = tmp_path / "a.raw"
    evtk.write_events(path, ev, fmt="evt3")
    small = evtk.read_events(path)
    monkeypatch.setattr(recording, "EVT3_JIT_WORDS", 0)
    large = evtk.read_events(path)
    for a, b, c in zip((small.t, small.x, small.y, small.p), (large.t, large.x, large.y, large.p),
                       (ev.t, ev.x, ev.y, ev.p)):
        assert np.array_equal(a, b) and np.array_equal(a, c)


@pytest.mark.parametrize("slice_words", [7, 1 << 16])
def test_event_stream_numpy_decoder_equals_the_numba_loop(monkeypatch, slice_words):
    """Event Stream's numpy decoder (0xFE/0xFF bytes between 5-byte events, events cut by a slice's end, events
    off the sensor) against the numba loop it stands in for; after an event off the sensor decoding stops, and
    only the time and position in the stream are compared."""
    monkeypatch.setattr(decoders, "SLICE_WORDS", slice_words)
    monkeypatch.setattr(decoders, "ES_MARKER_SHARE", 1.0)  # never hand a slice to numba
    rng = np.random.default_rng(5)
    for trial in range(400):
        n = int(rng.integers(0, 80))
        parts = []
        while sum(len(q) for q in parts) < n:
            r = rng.random()
            if r < 0.05:
                parts.append(np.full(int(rng.integers(1, 4)), 0xFF, np.uint8))
            elif r < 0.07:
                parts.append(np.array([0xFE], np.uint8))
            else:
                b0, xx, yy = int(rng.integers(0, 0xFE)), int(rng.integers(0, 48)), int(rng.integers(0, 30))
                parts.append(np.array([b0, xx & 0xFF, xx >> 8, yy & 0xFF, yy >> 8], np.uint8))
        data = np.concatenate(parts)[:n] if parts else np.zeros(0, np.uint8)
        state = np.array([rng.integers(0, 1000), rng.integers(0, 5), rng.integers(0, 300), rng.integers(0, 300),
                          rng.integers(0, 2)], np.int64)
        for decode in (False, True):
            cap = len(data) // 5 + 1
            got, want = _outs(cap), _outs(cap)
            s1, s2 = state.copy(), state.copy()
            r1 = tuple(int(a) for a in decoders._es_np_run(data, s1, 40, 25, decode, *got))
            r2 = tuple(int(a) for a in decoders._es_dvs_run(data, s2, 40, 25, decode, *want))
            compared = 2 if r2[2] == decoders.ST_COORD else 5
            assert r1 == r2 and np.array_equal(s1[:compared], s2[:compared]), (trial, decode, r1, r2)
            for a, b in zip(got[:4], want[:4]):
                assert np.array_equal(a[:r1[0]], b[:r1[0]]), trial


@pytest.mark.parametrize("slice_words", [1000, 1 << 16])
def test_event_stream_numpy_decoder_equals_the_numba_loop_on_long_streams(monkeypatch, slice_words):
    """As above on streams of up to 20 kB, with coordinates up to 639 (low bytes of 0xFE and 0xFF inside the
    events, which are no markers) and runs of up to eight marker bytes: the numpy decoder finds the next marker on
    the grid of event starts and the end of its run from tables of the slice's marker bytes."""
    monkeypatch.setattr(decoders, "SLICE_WORDS", slice_words)
    monkeypatch.setattr(decoders, "ES_MARKER_SHARE", 1.0)
    rng = np.random.default_rng(11)
    for trial in range(60):
        n = int(rng.integers(0, 20_000))
        parts, size = [], 0
        while size < n:
            r = rng.random()
            if r < 0.02:
                part = np.full(int(rng.integers(1, 9)), 0xFF, np.uint8)
            elif r < 0.03:
                part = np.array([0xFE, 0xFF][:int(rng.integers(1, 3))], np.uint8)
            else:
                b0, xx, yy = int(rng.integers(0, 0xFE)), int(rng.integers(0, 640)), int(rng.integers(0, 480))
                part = np.array([b0, xx & 0xFF, xx >> 8, yy & 0xFF, yy >> 8], np.uint8)
            parts.append(part)
            size += len(part)
        data = np.concatenate(parts)[:n] if parts else np.zeros(0, np.uint8)
        width, height = (700, 500) if trial % 4 else (600, 470)  # every fourth: an event off the sensor
        state = np.array([rng.integers(0, 1000), 0, 0, 0, 0], np.int64)
        for decode in (False, True):
            cap = len(data) // 5 + 1
            got, want = _outs(cap), _outs(cap)
            s1, s2 = state.copy(), state.copy()
            r1 = tuple(int(a) for a in decoders._es_np_run(data, s1, width, height, decode, *got))
            r2 = tuple(int(a) for a in decoders._es_dvs_run(data, s2, width, height, decode, *want))
            compared = 2 if r2[2] == decoders.ST_COORD else 5
            assert r1 == r2 and np.array_equal(s1[:compared], s2[:compared]), (trial, decode, r1, r2)
            for a, b in zip(got[:4], want[:4]):
                assert np.array_equal(a[:r1[0]], b[:r1[0]]), trial
