import numpy as np
import pytest
from conftest import random_events

import evtk
from evtk.events import STRUCTURED_LAYOUTS


def test_columns_are_converted_to_documented_dtypes():
    ev = evtk.Events([3, 1], [1, 2], [0, 5], [True, False], (10, 10))
    assert ev.t.dtype == np.int64 and ev.x.dtype == np.uint16 and ev.y.dtype == np.uint16 and ev.p.dtype == np.uint8
    assert ev.p.tolist() == [1, 0]
    assert len(ev) == 2


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(t=[1, 2], x=[1], y=[1, 2], p=[0, 1]), "differ in length"),
        (dict(t=[1], x=[-1], y=[0], p=[0]), "outside"),
        (dict(t=[1], x=[70000], y=[0], p=[0]), "outside"),
        (dict(t=[1], x=[0], y=[0], p=[2]), "outside"),
        (dict(t=[1.5], x=[0], y=[0], p=[0]), "non-integer"),
        (dict(t=[np.nan], x=[0], y=[0], p=[0]), "NaN"),
        (dict(t=[[1]], x=[0], y=[0], p=[0]), "one-dimensional"),
    ],
)
def test_bad_columns_raise_instead_of_wrapping(kwargs, match):
    with pytest.raises(evtk.EvtkError, match=match):
        evtk.Events(sensor_size=(10, 10), **kwargs)


@pytest.mark.parametrize("size", [(0, 10), (10, -1), (70000, 1), "ab", None])
def test_bad_sensor_size(size):
    with pytest.raises(evtk.EvtkError):
        evtk.Events([], [], [], [], size)


def test_between_is_half_open_and_matches_mask():
    ev = random_events(1000, seed=1, span_us=10_000)
    for lo, hi in [(None, None), (0, 5000), (2500, 2501), (5000, None), (None, 123), (20_000, 30_000), (7, 3)]:
        got = ev.between(lo, hi)
        mask = np.ones(len(ev), bool)
        if lo is not None:
            mask &= ev.t >= lo
        if hi is not None:
            mask &= ev.t < hi
        assert np.array_equal(got.t, ev.t[mask])
        assert np.array_equal(got.x, ev.x[mask])


def test_between_on_unsorted_stream_uses_mask():
    ev = random_events(500, seed=2, sort=False)
    assert not ev.is_sorted
    got = ev.between(100_000, 600_000)
    keep = (ev.t >= 100_000) & (ev.t < 600_000)
    assert np.array_equal(got.t, ev.t[keep]) and np.array_equal(got.p, ev.p[keep])


def test_between_at_int64_limits():
    lo, hi = np.iinfo(np.int64).min, np.iinfo(np.int64).max
    ev = evtk.Events([lo, 0, hi], [0, 1, 2], [0, 0, 0], [1, 1, 0], (4, 4))
    assert len(ev.between(lo, hi)) == 2  # hi itself excluded
    assert len(ev.between(None, None)) == 3
    assert len(ev.between(hi, None)) == 1
    assert ev.t_start_us == lo and ev.t_end_us == hi


def test_concatenate_and_slicing():
    a, b = random_events(10, seed=3), random_events(5, seed=4)
    c = evtk.Events.concatenate([a, b])
    assert len(c) == 15 and c[:10] == a and c[10:] == b
    assert c[3] == a[3:4] and c[-1] == b[4:]
    with pytest.raises(evtk.EvtkError, match="different sensor sizes"):
        evtk.Events.concatenate([a, random_events(1, sensor_size=(10, 10))])
    assert len(evtk.Events.concatenate([], sensor_size=(5, 5))) == 0


@pytest.mark.parametrize("layout", sorted(STRUCTURED_LAYOUTS))
def test_structured_round_trip(layout):
    ev = random_events(100, seed=5)
    arr = ev.to_structured(layout)
    assert arr.dtype == STRUCTURED_LAYOUTS[layout]
    assert evtk.Events.from_structured(arr, ev.sensor_size) == ev


def test_structured_layouts_match_the_peer_libraries():
    dv = pytest.importorskip("dv_processing")
    faery = pytest.importorskip("faery")
    store = dv.EventStore()
    store.push_back(5, 1, 2, True)
    assert store.numpy().dtype == STRUCTURED_LAYOUTS["dv"]
    assert np.dtype(faery.EVENTS_DTYPE) == STRUCTURED_LAYOUTS["faery"]
    got = evtk.Events.from_structured(store.numpy(), (4, 4))
    assert got.t.tolist() == [5] and got.x.tolist() == [1] and got.y.tolist() == [2] and got.p.tolist() == [1]


def test_structured_conversion_refuses_lossy_targets():
    ev = evtk.Events([-5], [0], [0], [1], (4, 4))
    with pytest.raises(evtk.EvtkError, match="unsigned"):
        ev.to_structured("faery")
    big = evtk.Events([0], [40000], [0], [1], (65536, 4))
    with pytest.raises(evtk.EvtkError, match="int16"):
        big.to_structured("dv")
    with pytest.raises(evtk.EvtkError, match="unknown layout"):
        ev.to_structured("nope")
    with pytest.raises(evtk.EvtkError, match="expected one of"):
        evtk.Events.from_structured(np.zeros(2, [("a", "i4")]), (4, 4))


def test_triggers():
    tr = evtk.Triggers([5, 1, 9], [evtk.TriggerKind.EXTERNAL_SIGNAL_RISING_EDGE, 2, 1])
    assert len(tr.between(2, 9)) == 1
    assert tr.of_kind(evtk.TriggerKind.EXTERNAL_SIGNAL_RISING_EDGE).t.tolist() == [5, 9]
    assert evtk.Triggers.concatenate([tr, tr])[3:] == tr
    with pytest.raises(evtk.EvtkError):
        evtk.Triggers([1, 2], [1])
    with pytest.raises(evtk.EvtkError):
        evtk.Triggers([1], [300])


def test_out_of_bounds_count():
    ev = evtk.Events([1, 2, 3], [0, 10, 5], [0, 0, 3], [0, 0, 0], (10, 3))
    assert ev.out_of_bounds() == 2


def test_sorted_is_a_stable_sort_and_free_when_already_sorted():
    rng = np.random.default_rng(4)
    n = 5000
    ev = evtk.Events(rng.integers(0, 50, n), rng.integers(0, 64, n), rng.integers(0, 48, n), rng.integers(0, 2, n),
                     (64, 48))
    s = ev.sorted()
    order = np.argsort(ev.t, kind="stable")
    assert s.is_sorted and np.array_equal(s.t, ev.t[order]) and np.array_equal(s.x, ev.x[order])
    assert np.array_equal(s.y, ev.y[order]) and np.array_equal(s.p, ev.p[order]) and s.sensor_size == ev.sensor_size
    assert s.sorted() is s
