"""Foreign HDF5 layouts as their writers make them (issue 20): Prophesee's relative index, event_utils' sizes."""

import h5py
import numpy as np
import pytest
from conftest import random_events

import evtk


def _prophesee_with_offset(path, ev, sign):
    """CD/events plus CD/indexes every ms, its times counted from the ``offset`` attribute (Prophesee's HDF5,
    whose sign we do not rely on)."""
    dt = np.dtype([("x", "<u2"), ("y", "<u2"), ("p", "<i2"), ("t", "<i8")])
    a = np.zeros(len(ev), dt)
    a["x"], a["y"], a["p"], a["t"] = ev.x, ev.y, ev.p, ev.t
    t0 = int(ev.t[0])
    grid = np.arange(t0, int(ev.t[-1]) + 1000, 1000)
    ids = np.searchsorted(ev.t, grid, side="left")
    idx = np.zeros(len(grid), [("id", "<i8"), ("ts", "<i8")])
    idx["id"], idx["ts"] = ids, grid - t0  # stored as t - t0; the attribute holds t0 or -t0, by writer
    with h5py.File(path, "w") as f:
        f.attrs["width"], f.attrs["height"] = ev.sensor_size
        f.create_dataset("CD/events", data=a, chunks=(1024,))
        d = f.create_dataset("CD/indexes", data=idx)
        d.attrs["offset"] = np.int64(t0 if sign > 0 else -t0)


@pytest.mark.parametrize("sign", [1, -1])
def test_prophesee_index_counted_from_its_offset_is_used(tmp_path, sign, monkeypatch):
    ev = random_events(200_000, seed=5, t0=7_000_000, span_us=2_000_000)
    path = tmp_path / "p.hdf5"
    _prophesee_with_offset(path, ev, sign)
    with evtk.open(path) as rec:
        lay = rec._layout
        reads = []
        orig = lay.read_t
        monkeypatch.setattr(lay, "read_t", lambda a, b: reads.append(b - a) or orig(a, b))
        got = rec.events(8_000_000, 8_010_000)
        assert got == ev.between(8_000_000, 8_010_000)
        assert not any("disagrees" in w for w in rec.warnings), rec.warnings
        # the index narrows each look-up to about one millisecond of events (~100 here), not a bisection
        assert max(reads) < 1000, reads


def test_event_utils_resolution_one_less_than_the_sensor_reads_with_a_warning(tmp_path):
    ev = random_events(5000, seed=6, sensor_size=(346, 260))
    path = tmp_path / "eu.h5"
    with h5py.File(path, "w") as f:
        f.create_dataset("events/xs", data=ev.x.astype(np.int16))
        f.create_dataset("events/ys", data=ev.y.astype(np.int16))
        f.create_dataset("events/ts", data=ev.t / 1e6)
        f.create_dataset("events/ps", data=ev.p.astype(np.int8))
        f.attrs["sensor_resolution"] = (int(ev.y.max()), int(ev.x.max()))  # the largest coordinates seen
    with evtk.open(path) as rec:
        got = rec.events()
        assert rec.sensor_size == (346, 260)
        assert any("sensor_resolution" in w for w in rec.warnings)
    assert np.array_equal(got.x, ev.x) and np.array_equal(got.y, ev.y) and np.array_equal(got.t, ev.t)
