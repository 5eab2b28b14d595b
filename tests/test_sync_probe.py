"""The synchronous-readout test's early answer: a probe of the first events rules a frame grid out exactly when the
full test would (the divisor of a subset's stamp differences is a multiple of the whole set's)."""

from __future__ import annotations

from unittest import mock

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import evtk.reconstruct.bench as bench
from evtk.events import Events


class _Rec:
    """A recording held in memory that counts what is read from it."""

    sensor_size = (8, 4)

    def __init__(self, t, pix):
        order = np.argsort(t, kind="stable")
        self.t, self.pix = np.asarray(t, np.int64)[order], np.asarray(pix, np.int64)[order]
        self.read = 0

    def _rows(self, i, j):
        self.read += j - i
        pix = self.pix[i:j]
        return Events(self.t[i:j], pix % 8, pix // 8, np.ones(j - i, np.uint8), sensor_size=self.sensor_size)

    def events(self, a, b):
        return self._rows(*np.searchsorted(self.t, [a, b]))

    def iter_events(self, chunk_events, a=None, b=None):
        i, j = np.searchsorted(self.t, [-2**62 if a is None else a, 2**62 if b is None else b])
        for k in range(i, j, chunk_events):
            yield self._rows(k, min(j, k + chunk_events))


def _full(rec, on, off):
    """The test without its early answer: every window's events read."""
    with mock.patch.object(bench, "_asynchronous_early", return_value=False):
        return bench.synchronous_readout(rec, on, off)


@settings(max_examples=200, deadline=None)
@given(st.sampled_from([1, 3, 7, 10, 11, 150, 990]), st.integers(0, 3), st.integers(1, 400), st.integers(0, 2**32))
def test_the_probe_answers_as_the_full_test(period, jitter_every, n, seed):
    rng = np.random.default_rng(seed)
    frames = np.sort(rng.integers(0, 40, n))
    t = 1_000 + frames * period
    if jitter_every:  # a few stamps off the grid, late in the run: only the whole set shows them
        late = np.arange(n) >= n - n // (2 + jitter_every)
        t = np.where(late & (rng.random(n) < 0.3), t + 1, t)
    pix = np.where(rng.random(n) < 0.5, rng.integers(0, 32, n), np.arange(n) % 32)
    on, off = np.array([0, 1_000 + 20 * period]), np.array([1_000 + 20 * period, 10**9])
    assert bench.synchronous_readout(_Rec(t, pix), on, off) == _full(_Rec(t, pix), on, off)


def test_an_asynchronous_camera_is_told_from_its_first_events():
    """Before, every window's events were read whole (two bright flat fields: most of a second of events); now
    the first chunk shows stamps 1 us apart and the rest is not read. The probe reads from the start without a
    window (no packet-span scan); events before and between the windows count for nothing."""
    t = np.arange(200_000) // 3  # three events a microsecond
    rec = _Rec(t, np.arange(t.size) % 32)
    on, off = np.array([0, 40_000]), np.array([40_000, 70_000])
    assert bench.synchronous_readout(rec, on, off) is None
    assert rec.read <= bench.SYNC_PROBE_EVENTS
    assert _full(_Rec(t, np.arange(t.size) % 32), on, off) is None


@pytest.mark.parametrize("t", [[], [5], [5, 5, 5]])
def test_few_or_equal_stamps_give_no_grid(t):
    rec = _Rec(np.array(t, np.int64), np.zeros(len(t), np.int64))
    assert bench.synchronous_readout(rec, np.array([0]), np.array([100])) is None


@pytest.mark.parametrize("period", [11, 150])
@pytest.mark.parametrize("off_grid", [False, True])
def test_a_frame_grid_is_still_named(period, off_grid):
    """32 pixels firing every frame for 40 frames: a synchronous readout, which the probe must not rule out; one
    stamp off the grid in the last frame makes the divisor 1, which the whole test (and the probe) then sees."""
    frames = np.repeat(np.arange(40), 32)
    t = 1_000 + frames * period
    if off_grid:
        t[-1] += 1
    pix = np.tile(np.arange(32), 40)
    on, off = np.array([0]), np.array([10**9])
    want = None if off_grid else float(period)
    assert _full(_Rec(t, pix), on, off) == want
    assert bench.synchronous_readout(_Rec(t, pix), on, off) == want


def test_stamps_outside_the_windows_do_not_rule_a_grid_out():
    """The probe reads from the recording's start: events before and between the windows (off the grid here)
    must count for nothing, or a synchronous readout would pass for an asynchronous one."""
    period = 150
    frames = np.repeat(np.arange(40), 32)
    t_grid = 30_000 + frames * period  # the window [30000, 36000)
    noise = np.array([5, 17, 29_999, 36_001, 36_007])  # off the grid, outside it
    t = np.concatenate([t_grid, noise])
    pix = np.concatenate([np.tile(np.arange(32), 40), np.arange(noise.size)])
    on, off = np.array([30_000]), np.array([36_000])
    assert _full(_Rec(t, pix), on, off) == float(period)
    assert bench.synchronous_readout(_Rec(t, pix), on, off) == float(period)
