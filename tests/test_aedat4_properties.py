"""Property tests: any event stream the format can hold survives a round trip."""

import numpy as np
import peers
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import evtk

I64 = np.iinfo(np.int64)


@st.composite
def event_streams(draw, max_n=300):
    w = draw(st.integers(1, 32768))
    h = draw(st.integers(1, 32768))
    n = draw(st.integers(0, max_n))
    kind = draw(st.sampled_from(["random", "equal", "near_max", "near_min", "sorted"]))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    if kind == "equal":
        t = np.full(n, draw(st.integers(I64.min, I64.max)), np.int64)
    elif kind == "near_max":
        t = np.sort(I64.max - rng.integers(0, 1000, n)).astype(np.int64)
    elif kind == "near_min":
        t = np.sort(I64.min + rng.integers(0, 1000, n)).astype(np.int64)
    elif kind == "sorted":
        t = np.sort(rng.integers(0, 2**40, n))
    else:
        t = rng.integers(I64.min, I64.max, n, dtype=np.int64, endpoint=True)
    x = rng.integers(0, w, n, dtype=np.uint16) if draw(st.booleans()) else np.full(n, w - 1, np.uint16)
    y = rng.integers(0, h, n, dtype=np.uint16) if draw(st.booleans()) else np.full(n, h - 1, np.uint16)
    p = rng.integers(0, 2, n, dtype=np.uint8)
    return evtk.Events(t, x, y, p, (w, h))


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(ev=event_streams(), compression=st.sampled_from(["lz4", "zstd", "none"]),
       packet_events=st.integers(1, 100), packet_us=st.one_of(st.none(), st.integers(1, 10**6)))
def test_round_trip(tmp_path, ev, compression, packet_events, packet_us):
    path = tmp_path / "rt.aedat4"
    trig = evtk.Triggers(ev.t[:3], np.arange(min(3, len(ev)), dtype=np.uint8))
    evtk.write_events(path, ev, trig, compression=compression, packet_events=packet_events, packet_us=packet_us)
    with evtk.open(path) as rec:
        assert rec.sensor_size == ev.sensor_size
        back = rec.events()
        assert back == ev
        assert rec.triggers() == evtk.Triggers(np.sort(trig.t, kind="stable"), trig.kind[np.argsort(trig.t, kind="stable")])
        if len(ev):
            lo, hi = int(np.min(ev.t)), int(np.max(ev.t))
            mid = lo // 2 + hi // 2
            assert rec.events(mid, hi) == ev.between(mid, hi)


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(ev=event_streams(max_n=50), compression=st.sampled_from(["lz4", "zstd", "none"]))
def test_round_trip_through_dv_processing(tmp_path, ev, compression):
    pytest.importorskip("dv_processing")
    path = tmp_path / "dv.aedat4"
    evtk.write_events(path, ev, compression=compression, packet_events=7)
    dv_ev, _ = peers.dv_read(path)
    assert dv_ev == ev
    again = tmp_path / "dv2.aedat4"
    # dv's EventStore refuses out-of-order events and negative time stamps
    if len(ev) and ev.is_sorted and ev.t[0] >= 0:
        peers.dv_write(again, ev, compression=compression, chunk=13)
        assert evtk.read_events(again) == ev


def test_empty_and_single_event_files(tmp_path):
    for n in (0, 1):
        ev = evtk.Events(np.arange(n), np.zeros(n), np.zeros(n), np.ones(n), (320, 240))
        path = tmp_path / f"n{n}.aedat4"
        evtk.write_events(path, ev)
        with evtk.open(path) as rec:
            assert rec.events() == ev
            info = rec.info()
            assert info["events"] == n
            assert info["t_start_us"] == (None if n == 0 else 0)
