"""What an AEDAT4 read knows of its events' time order (``Events._sorted``, which :attr:`evtk.Events.is_sorted`
answers from): the compiled range compares each stamp with the one before it as it splits a packet's events, and the
reader compares each packet's first stamp with the stamp before it. Counting windows trusts that answer instead of
checking the stamps again, so it must never say "in order" of stamps that are not: checked here against the
definition (each stamp no earlier than the one before) at every place a stamp can go back."""

from __future__ import annotations

import numpy as np
import pytest

import evtk
from evtk import _native
from evtk.io import _compression as cz

PACKET = 1000  # events a packet
CHUNK = 4000  # events a chunk of iter_events


def _columns(n: int, seed: int = 3) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(0, 50 * n, n)).astype(np.int64)
    x = rng.integers(0, 64, n).astype(np.uint16)
    y = rng.integers(0, 48, n).astype(np.uint16)
    p = rng.integers(0, 2, n).astype(np.uint8)
    return t, x, y, p


def _in_order(t: np.ndarray) -> bool:
    return all(int(b) >= int(a) for a, b in zip(t[:-1], t[1:]))  # the definition, in Python integers


def _write(path, t, x, y, p, compression="lz4", packet=PACKET):
    evtk.write_events(path, evtk.Events(t, x, y, p, (64, 48)), compression=compression, packet_events=packet,
                      packet_us=None)


def _compiled(compression: str) -> bool:
    if not _native.enabled():
        return False
    return compression == "lz4" or (_native.RANGE_ZSTD and cz.zstd_addresses(cz.Scratch()) is not None)


# a stamp one earlier than the stamp before it: at each of the first 17 places of a packet (the vector loop's first
# eight events, the next eight, the scalar rest), at a packet's last events, at a packet's first event (an edge), at
# a chunk's first event and at the very end
BACK_AT = list(range(1, 18)) + [PACKET - 2, PACKET - 1, PACKET, PACKET + 1, 3 * PACKET, CHUNK, CHUNK + 1,
                                 2 * CHUNK - 1, 20_000 - 1]


@pytest.mark.parametrize("compression", ["lz4", "zstd"])
@pytest.mark.parametrize("back", [None] + BACK_AT)
def test_the_reads_order_is_the_stamps_own(tmp_path, compression, back):
    t, x, y, p = _columns(20_000)
    if back is not None:
        t[back] = t[back - 1] - 1
    path = tmp_path / f"r.{compression}.aedat4"
    _write(path, t, x, y, p, compression)
    compiled = _compiled(compression)
    with evtk.open(path) as rec:
        ev = rec.events()
        assert np.array_equal(ev.t, t)
        if compiled:  # known from the decoding, and right
            assert ev._sorted is (back is None)
        else:
            assert ev._sorted in (None, back is None)
        assert ev.is_sorted is _in_order(t)
        chunks = list(rec.iter_events(CHUNK))
        assert np.array_equal(np.concatenate([c.t for c in chunks]), t)
        for c in chunks:
            if compiled:
                assert c._sorted is _in_order(c.t)
            else:
                assert c._sorted in (None, _in_order(c.t))


@pytest.mark.parametrize("stamps", [
    [-5, 3, 2**62, 2**63 - 1],  # rising across the sign: in order
    [2**63 - 1, -2**63],  # the greatest then the least: the difference overflows
    [-2**63, -2**63, -1, 0, 0, 1, 2**63 - 1, 2**63 - 1],
    [2**62, -2**62 - 5],  # down across the sign by more than 2**63
    [-2**62 - 5, 2**62],  # up across the sign by more than 2**63: in order
    [7, 7, 7, 6],
])
@pytest.mark.parametrize("repeat", [1, 5])
def test_stamps_near_the_int64_limits_are_compared_exactly(tmp_path, stamps, repeat):
    """Stamps of both signs whose differences leave int64 (where a subtraction alone would give the wrong sign),
    in vectors long enough for the vector loop and short ones."""
    t = np.array(stamps * repeat, np.int64)
    n = len(t)
    z = np.zeros(n, np.uint16)
    path = tmp_path / "limits.aedat4"
    _write(path, t, z, z, np.zeros(n, np.uint8), packet=1000)
    with evtk.open(path) as rec:
        ev = rec.events()
    assert np.array_equal(ev.t, t)
    assert ev.is_sorted is _in_order(t)
    if _compiled("lz4"):
        assert ev._sorted is _in_order(t)


def test_without_the_compiled_kernels_the_order_is_left_to_the_check(tmp_path, monkeypatch):
    """The Python loop does not compare stamps on the way: the order is not known until asked, then right."""
    t, x, y, p = _columns(9_000)
    t[4_500] = t[4_499] - 1
    path = tmp_path / "py.aedat4"
    _write(path, t, x, y, p)
    monkeypatch.setenv("EVTK_NATIVE", "0")
    with evtk.open(path) as rec:
        ev = rec.events()
        chunks = list(rec.iter_events(CHUNK))
    assert ev._sorted is None and ev.is_sorted is False
    assert [c._sorted for c in chunks] == [None] * len(chunks)
    assert [c.is_sorted for c in chunks] == [_in_order(c.t) for c in chunks]


@pytest.mark.parametrize("back", [PACKET, 5])
def test_counting_refuses_a_stamp_going_back_at_a_packet_edge_or_inside_one(tmp_path, back):
    """One stamp out of order, at a packet's first event (each packet in order by itself) or inside the first
    packet: counting windows refuses the file, naming it, as it did when it checked every chunk's stamps itself."""
    from evtk.reconstruct.fixed import net_count_batches
    from evtk.reconstruct.windows import windows_periodic

    t, x, y, p = _columns(20_000)
    t[back] = t[back - 1] - 1
    path = tmp_path / "edge.aedat4"
    _write(path, t, x, y, p)
    win = windows_periodic(0, int(t[-1]) + 1, 10_000)
    with evtk.open(path) as rec, pytest.raises(evtk.EvtkError, match="edge.aedat4: its events are not in time order"):
        for _ in net_count_batches(rec, win, (0, 64, 0, 48)):
            pass


@pytest.mark.parametrize("native", [True, False])
@pytest.mark.parametrize("chunk", [1_500, 700])
@pytest.mark.parametrize("back", [None, 1_000, 1_200, 1_400, 1_500, 1_501, 1_700, 2_000, 2_300, 3_000, 3_100])
def test_chunks_cut_inside_packets_know_their_order(tmp_path, monkeypatch, back, chunk, native):
    """Chunks of 1,500 events over packets of 1,000 (as the counting's chunks of 2**20 events over dv-processing's
    packets of 10,000), and of 700: a packet that does not fit whole in what is left of a chunk is decoded alone and
    copied in parts; each part's first stamp is compared with the chunk's stamps before it. A stamp going back inside
    such a packet, at its first event or at the next packet's first event is found in the chunk that holds it.
    Without the compiled kernels no chunk's order is known until asked."""
    t, x, y, p = _columns(6_000)
    if back is not None:
        t[back] = t[back - 1] - 1
    path = tmp_path / "cut.aedat4"
    _write(path, t, x, y, p)
    if not native:
        monkeypatch.setenv("EVTK_NATIVE", "0")
    with evtk.open(path) as rec:
        chunks = list(rec.iter_events(chunk))
    assert np.array_equal(np.concatenate([c.t for c in chunks]), t)
    for c in chunks:
        if not native:
            assert c._sorted is None
        else:
            assert c._sorted is _in_order(c.t) if _compiled("lz4") else c._sorted in (None, _in_order(c.t))
        assert c.is_sorted is _in_order(c.t)
    assert sum(not _in_order(c.t) for c in chunks) == (back is not None and back % chunk != 0)


def test_a_run_or_a_window_of_stamps_out_of_order_may_be_in_order():
    """Events known to be out of order: a slice or a time window of them may hold only stamps in order (found by
    a random search over files with stamps out of order: a window's one-event chunk said "out of order"), so its
    order is left to be checked; a slice of events known in order stays known."""
    t = np.array([5, 6, 7, 3, 8, 9], np.int64)
    z = np.zeros(len(t), np.uint16)
    ev = evtk.Events(t, z, z, np.zeros(len(t), np.uint8), (4, 4))
    assert ev.is_sorted is False
    assert ev[0:3]._sorted is None and ev[0:3].is_sorted is True
    assert ev[2:4].is_sorted is False
    assert ev[4].is_sorted is True
    assert ev.between(4, 10)._sorted is None and ev.between(4, 10).is_sorted is True
    assert ev.between(0, 10).is_sorted is False
    ordered = evtk.Events(np.sort(t), z, z, np.zeros(len(t), np.uint8), (4, 4))
    assert ordered.is_sorted is True and ordered[1:4]._sorted is True


def test_a_window_of_a_recording_in_order_counts_though_the_rest_is_not(tmp_path):
    """A stamp going back just past a time window's end, in the packet that the window's end cuts: the window's
    chunks are in order, and counting the window's events is not refused."""
    from evtk.reconstruct.fixed import net_count_batches
    from evtk.reconstruct.windows import windows_periodic

    t, x, y, p = _columns(20_000)
    t[9_500] = t[9_499] - 1
    path = tmp_path / "outside.aedat4"
    _write(path, t, x, y, p)
    end = int(t[9_200])
    win = windows_periodic(0, end, 10_000)
    with evtk.open(path) as rec:
        chunks = list(rec.iter_events(1_500, t_start_us=0, t_end_us=end))
        got = [net.copy() for _, net, _ in net_count_batches(rec, win, (0, 64, 0, 48))]
    assert all(c.is_sorted for c in chunks)
    assert all(c._sorted in (True, None) for c in chunks)
    keep = t < end
    inside = evtk.Events(t[keep], x[keep], y[keep], p[keep], (64, 48))
    want = [net.copy() for _, net, _ in net_count_batches(inside, win, (0, 64, 0, 48))]
    assert len(got) == len(want) and all(np.array_equal(a, b) for a, b in zip(got, want))


def test_a_window_that_leaves_out_the_stamp_going_back_is_in_order(tmp_path):
    """The window starts at a stamp whose follower goes back before it: the window keeps the events around the one
    left out (not one run of the packet's events), and they are in order."""
    t, x, y, p = _columns(20_000)
    t[5_500] = t[5_499] - 1
    path = tmp_path / "start.aedat4"
    _write(path, t, x, y, p)
    start = int(t[5_499])
    with evtk.open(path) as rec:
        chunks = list(rec.iter_events(1_500, t_start_us=start, t_end_us=int(t[8_000])))
    kept = np.concatenate([c.t for c in chunks])
    assert 5_500 not in np.flatnonzero(np.isin(t, kept)) and kept[0] == start and _in_order(kept)
    assert all(c._sorted in (True, None) and c.is_sorted for c in chunks)
