"""AEDAT4 time-window reads: the packets that meet a window, found from the data table and each packet's stamps
(scanned once, on the I/O threads), decoded on the I/O threads and cut to the window exactly, equal reading
everything and filtering, damage included."""

import threading

import numpy as np
import pytest
from conftest import random_events

import evtk
from evtk.io import _compression as cz
from evtk.io import _fb

PACKET = 1000
N = 300 * PACKET  # above the size the reader splits over its threads


def _write(path, ev, compression="lz4"):
    evtk.write_events(path, ev, compression=compression, packet_events=PACKET, packet_us=None)
    return path


def _dv_table(path, t):
    """Rewrite the data table as DV writes it: each packet's first and last stamp (not its least and greatest)."""
    with evtk.open(path) as rec:
        idx, dtp = rec._index, rec._data_table_pos
        cols = [idx.offset, idx.stream, idx.size, idx.count, idx.t0.copy(), idx.t1.copy()]
    cols[4][:] = t[::PACKET]
    cols[5][:] = t[PACKET - 1::PACKET]
    buf = np.empty(_fb.data_table_size(len(cols[0])), np.uint8)
    size = _fb.encode_data_table(*cols, buf)
    data = bytearray(path.read_bytes())
    data[dtp:dtp + size] = buf[:size].tobytes()
    path.write_bytes(bytes(data))


def _off_sensor(path, packet, event):
    """Put event ``event`` of packet ``packet`` (an uncompressed file) off the sensor; returns the packet's offset."""
    with evtk.open(path) as rec:
        off, size = int(rec._index.offset[packet]), int(rec._index.size[packet])
    data = bytearray(path.read_bytes())
    pos = off + size - PACKET * 16 + event * 16 + 8  # x of that event: the event vector ends the body
    data[pos:pos + 2] = (60000).to_bytes(2, "little")
    path.write_bytes(bytes(data))
    return off


def _windows(t):
    """Windows at packet boundaries, inside packets, empty, before and after the data, and the whole."""
    first, last = int(t.min()), int(t.max())
    edge = [int(v) for v in t[::PACKET][1:]]
    out = [(None, None), (first, last + 1), (None, edge[3]), (edge[-4], None), (first - 100, first - 1),
           (last + 1, last + 100), (edge[10], edge[10]), (edge[10], edge[10] + 1), (edge[5], edge[9]),
           (edge[5] + 1, edge[9] - 1), (edge[100] - 1, edge[200] + 1), (edge[150] + 3, edge[150] + 40),
           (5, 6), (0, 100), (first, first + 1)]
    return out


def _check(path, want, chunk_events=(777, 50_000, 4_000_000), **open_args):
    for a, z in _windows(want.t):
        expected = want.between(a, z)
        with evtk.open(path, **open_args) as rec:
            assert rec.events(a, z) == expected, (a, z)
        for chunk in chunk_events:
            with evtk.open(path, **open_args) as rec:
                got = list(rec.iter_events(chunk, a, z))
                assert all(0 < len(c) <= chunk for c in got)
                joined = evtk.Events.concatenate(got, sensor_size=want.sensor_size) if got else want[0:0]
                assert joined == expected, (a, z, chunk)


@pytest.mark.parametrize("compression", ["lz4", "none", "zstd"])
def test_windows_equal_reading_everything_and_filtering(tmp_path, compression, monkeypatch):
    monkeypatch.setenv("EVTK_THREADS", "2")
    ev = random_events(N, seed=31, span_us=3_000_000)
    _check(_write(tmp_path / "w.aedat4", ev, compression), ev)


def test_windows_of_packets_with_stamps_out_of_order(tmp_path, monkeypatch):
    """Stamps out of order inside packets and across them, with the table giving each packet's first and last
    stamp: a window holds every event of the file in it, wherever its packet lies."""
    monkeypatch.setenv("EVTK_THREADS", "2")
    ev = random_events(N, seed=32, span_us=3_000_000)
    t = ev.t.copy()
    t[150 * PACKET + 500] = 5  # long before its packet
    t[200 * PACKET + 100] = int(t[-1])  # long after its packet
    rng = np.random.default_rng(2)
    rng.shuffle(t[50 * PACKET:60 * PACKET])  # ten packets shuffled together
    ev = evtk.Events(t, ev.x, ev.y, ev.p, ev.sensor_size)
    path = _write(tmp_path / "ooo.aedat4", ev, "none")
    _dv_table(path, t)
    _check(path, ev, chunk_events=(777, 4_000_000))


def test_first_window_scans_the_packets_on_the_io_threads(tmp_path, monkeypatch):
    """The first window of a recording reads every packet's stamps once (to find those out of order): on the
    I/O threads, not packet by packet on the calling thread (which made a window cost 2.5 whole reads)."""
    monkeypatch.setenv("EVTK_THREADS", "2")
    ev = random_events(N, seed=33, span_us=3_000_000)
    path = _write(tmp_path / "w.aedat4", ev)
    calls: list[str] = []
    real = cz.decompress_into

    def spy(*args, **kwargs):
        calls.append(threading.current_thread().name)
        return real(*args, **kwargs)

    monkeypatch.setattr(cz, "decompress_into", spy)
    a, z = int(ev.t[150 * PACKET + 10]), int(ev.t[151 * PACKET + 10])
    with evtk.open(path) as rec:
        assert rec.events(a, z) == ev.between(a, z)
    on_caller = sum(name == threading.current_thread().name for name in calls)
    assert len(calls) >= 300  # every packet scanned once
    assert on_caller <= 2  # at most the window's own two packets decoded here


def test_damage_outside_a_window_is_reported_as_a_whole_read_reports_it(tmp_path, monkeypatch):
    """The first window reads every packet: damage anywhere raises as the whole read raises (strict), or ends
    what is read there (salvage: a window never holds events from beyond it); of two damaged packets the first
    is reported, whichever thread meets it."""
    monkeypatch.setenv("EVTK_THREADS", "2")
    ev = random_events(N, seed=34, span_us=3_000_000)
    path = _write(tmp_path / "d.aedat4", ev, "none")
    first = _off_sensor(path, 120, 6)
    _off_sensor(path, 260, 0)
    a, z = int(ev.t[10 * PACKET]), int(ev.t[20 * PACKET])
    with evtk.open(path) as rec, pytest.raises(evtk.FormatError) as whole:
        rec.events()
    with evtk.open(path) as rec, pytest.raises(evtk.FormatError) as window:
        rec.events(a, z)
    assert str(window.value) == str(whole.value) and f"byte {first}" in str(window.value)
    with evtk.open(path, salvage=True) as rec:
        assert rec.events(a, z) == ev.between(a, z)
        assert rec.damage is not None and rec.damage.offset == first
        assert "event 6 of the packet" in rec.damage.reason
        assert len(rec.events(int(ev.t[200 * PACKET]), None)) == 0  # beyond the damage
        before = rec.events(None, int(ev.t[150 * PACKET]))
        assert before == ev[:120 * PACKET].between(None, int(ev.t[150 * PACKET]))
