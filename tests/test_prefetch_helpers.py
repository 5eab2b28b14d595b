"""The consumer of prefetched chunks decodes beside the prefetching thread instead of waiting idle for it
(``evtk._threads.Helpers``, issue 32: on two cores a third decoding thread only took turns with the others, 480-500
involuntary context switches in one ``evtk enob`` of 20 M events, 5-12 with the consumer helping). What it decodes
must be what the reader alone decodes, damage must be named as before, and nothing may hang."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from test_aedat4_batches import move_off_sensor

import evtk
from evtk._threads import Helpers, Pool, helpers, use_helpers
from evtk.io.aedat4 import reader as a4r
from evtk.reconstruct import windows_periodic
from evtk.reconstruct.fixed import net_count_batches


def _split(help_: Helpers, n_ranges: int, seconds: float, log: list) -> None:
    """What a split decode on a prefetching thread does: offer the ranges, take them too, withdraw."""
    ranges = iter(range(n_ranges))

    def runner() -> None:
        for r in ranges:
            time.sleep(seconds)
            log.append((r, threading.get_ident()))

    help_.offer(runner)
    try:
        runner()
    finally:
        help_.withdraw()


def _produce(help_: Helpers, work):
    use_helpers(help_)
    try:
        return work()
    finally:
        use_helpers(None)
        help_.finish()


def test_the_waiting_consumer_takes_offered_ranges():
    help_, log = Helpers(), []
    pool = Pool(1, "test-prefetch")
    help_.start()
    task = pool.submit(_produce, help_, lambda: _split(help_, 40, 0.002, log))
    help_.wait()
    task.result()
    pool.shutdown()
    assert sorted(r for r, _ in log) == list(range(40))  # every range once
    assert threading.get_ident() in {who for _, who in log}  # the consumer took some
    assert len({who for _, who in log}) == 2


def test_withdraw_waits_for_a_helper_inside_its_range():
    """The producer's split must not return (and its results be read) while the consumer still decodes a range."""
    help_ = Helpers()
    ended: list[str] = []
    ranges = iter(range(2))

    def runner() -> None:
        for r in ranges:
            if threading.current_thread() is threading.main_thread():
                time.sleep(0.1)  # the consumer's range is the slow one
            ended.append(f"range {r}")

    def produce() -> None:
        help_.offer(runner)
        while not help_._active:  # until the consumer has joined (its range takes 0.1 s)
            time.sleep(0.001)
        runner()  # the other range, at once
        help_.withdraw()
        ended.append("withdrawn")

    pool = Pool(1, "test-prefetch")
    help_.start()
    task = pool.submit(_produce, help_, produce)
    help_.wait()
    task.result()
    pool.shutdown()
    assert ended == ["range 1", "range 0", "withdrawn"]


def test_the_wait_ends_with_the_work_when_nothing_is_offered():
    help_ = Helpers()
    pool = Pool(1, "test-prefetch")
    for _ in range(3):  # a helper reused chunk after chunk
        help_.start()
        task = pool.submit(_produce, help_, lambda: time.sleep(0.01) or 7)
        help_.wait()
        assert task.result() == 7
    help_.start()
    task = pool.submit(_produce, help_, lambda: 1 / 0)
    help_.wait()
    with pytest.raises(ZeroDivisionError):
        task.result()
    pool.shutdown()
    assert helpers() is None  # the consumer's thread never had one


def _recording(tmp_path, n=1_200_000, seed=5):
    rng = np.random.default_rng(seed)
    ev = evtk.Events(np.sort(rng.integers(0, 2_000_000, n)), rng.integers(0, 64, n).astype(np.uint16),
                     rng.integers(0, 48, n).astype(np.uint16), rng.integers(0, 2, n).astype(np.uint8), (64, 48))
    path = tmp_path / "helped.aedat4"
    evtk.write_events(path, ev, packet_events=5_000, packet_us=None)
    return path, ev


def _slow_batches(monkeypatch, rec, decoded_on: set, most: list | None = None):
    """Each batch of packets decoded a little slower, and by whom: the consumer counts faster than the file
    decodes, so it waits for every chunk and takes ranges of it. Every chunk is split among the threads (a
    thread's buffers counted as a byte: the small test chunks would pay for one thread). With ``most``, its
    first item becomes the most threads other than this (the consumer's) one seen decoding at once."""
    monkeypatch.setattr(a4r, "_THREAD_BYTES", 1)
    make = rec._batcher
    lock, busy, consumer = threading.Lock(), set(), threading.get_ident()

    def batcher(*args):
        batch = make(*args)
        if batch is None:
            return None

        def slow(*a):
            me = threading.get_ident()
            decoded_on.add(me)
            with lock:
                busy.add(me)
                if most is not None:
                    most[0] = max(most[0], len(busy - {consumer}))
            time.sleep(0.003)
            try:
                return batch(*a)
            finally:
                with lock:
                    busy.discard(me)

        return slow

    monkeypatch.setattr(rec, "_batcher", batcher)


@pytest.mark.parametrize("threads", ["2", "3"])
def test_net_counts_decoded_with_the_consumer_equal_the_events_in_memory(tmp_path, monkeypatch, threads):
    monkeypatch.setenv("EVTK_THREADS", threads)
    path, ev = _recording(tmp_path)
    win = windows_periodic(0, 2_000_000, 10_000)
    want = [(i, net.copy(), most) for i, net, most in net_count_batches(ev, win, (0, 64, 0, 48), 16)]
    decoded_on: set = set()
    with evtk.open(path) as rec:
        _slow_batches(monkeypatch, rec, decoded_on)
        got = [(i, net.copy(), most) for i, net, most in net_count_batches(rec, win, (0, 64, 0, 48), 16)]
    assert threading.get_ident() in decoded_on  # the consumer decoded too
    assert len(got) == len(want)
    for (i, a, m), (j, b, k) in zip(got, want):
        assert i == j and m == k and np.array_equal(a, b)


def test_a_damaged_packet_met_while_the_consumer_helps_is_named(tmp_path, monkeypatch):
    """Strict: the fault of the damaged packet, at its offset, whichever thread decoded it; nothing hangs."""
    monkeypatch.setenv("EVTK_THREADS", "2")
    rng = np.random.default_rng(6)
    n = 600_000
    ev = evtk.Events(np.sort(rng.integers(0, 2_000_000, n)), rng.integers(0, 64, n).astype(np.uint16),
                     rng.integers(0, 48, n).astype(np.uint16), rng.integers(0, 2, n).astype(np.uint8), (64, 48))
    path = tmp_path / "damaged.aedat4"
    evtk.write_events(path, ev, compression="none", packet_events=5_000, packet_us=None)
    k = 90  # its first event moved off the 64-pixel-wide sensor
    offsets = move_off_sensor(path, [k], 5_000)
    win = windows_periodic(0, 2_000_000, 10_000)
    decoded_on: set = set()
    with evtk.open(path) as rec:
        _slow_batches(monkeypatch, rec, decoded_on)
        with pytest.raises(evtk.FormatError) as err:
            for _ in net_count_batches(rec, win, (0, 64, 0, 48), 16):
                pass
    assert f"at byte {offsets[k]}" in str(err.value), str(err.value)
    assert threading.get_ident() in decoded_on


@pytest.mark.parametrize("where", [None, 1, (1 << 16) - 1, 1 << 16, (1 << 16) + 1, 5 * (1 << 16), -1])
def test_the_shared_time_order_check_agrees_with_events_own(where):
    """The prefetching thread's time-order check, cut in pieces that the consumer takes too: a stamp going back
    at a piece's edge or at the very end is found as :attr:`Events.is_sorted` finds it."""
    import importlib

    acc = importlib.import_module("evtk.reconstruct.accumulate")
    rng = np.random.default_rng(8)
    t = np.sort(rng.integers(0, 10**9, 6 * (1 << 16) + 5))
    if where is not None:
        t[where] = t[where - 1] - 1 if where != -1 else t[-2] - 1
    help_ = Helpers()
    pool = Pool(1, "test-prefetch")
    help_.start()
    task = pool.submit(_produce, help_, lambda: acc._sorted_shared(t, help_))
    help_.wait()
    got = task.result()
    pool.shutdown()
    assert got == bool(np.all(t[1:] >= t[:-1])) == (where is None)
    assert acc._sorted_shared(t, Helpers()) == got  # with no consumer taking pieces: the same


def test_a_consumer_that_stops_early_leaves_nothing_running(tmp_path, monkeypatch):
    """The consumer stops after its first batch while the next chunk is being decoded with its help offered:
    the prefetching thread finishes that chunk alone and the read closes; the counting of a second read is
    whole (a withdrawn offer or a stale wake-up would hang it or lose ranges)."""
    monkeypatch.setenv("EVTK_THREADS", "2")
    path, ev = _recording(tmp_path, seed=7)
    win = windows_periodic(0, 2_000_000, 10_000)
    want = [net.copy() for _, net, _ in net_count_batches(ev, win, (0, 64, 0, 48), 16)]
    done: list = []

    def stop_early_then_count() -> None:
        with evtk.open(path) as rec:
            _slow_batches(monkeypatch, rec, set())
            for _ in net_count_batches(rec, win, (0, 64, 0, 48), 16):
                break
            done.append([net.copy() for _, net, _ in net_count_batches(rec, win, (0, 64, 0, 48), 16)])

    worker = threading.Thread(target=stop_early_then_count, daemon=True)
    worker.start()
    worker.join(120)
    assert not worker.is_alive(), "the read hung"
    assert len(done) == 1 and len(done[0]) == len(want)
    assert all(np.array_equal(a, b) for a, b in zip(done[0], want))


def test_a_prefetched_chunk_is_decoded_by_a_few_threads_on_many_cores(tmp_path, monkeypatch):
    """On 16 threads, no more than PREFETCH_THREADS decode a prefetched chunk at once, the consumer aside (issue
    32, tenth round: more only took turns for the GIL on a 16-core machine); the counts are unchanged."""
    monkeypatch.setenv("EVTK_THREADS", "16")
    path, ev = _recording(tmp_path)
    win = windows_periodic(0, 2_000_000, 10_000)
    want = [(i, net.copy()) for i, net, _ in net_count_batches(ev, win, (0, 64, 0, 48), 16)]
    most = [0]
    with evtk.open(path) as rec:
        _slow_batches(monkeypatch, rec, set(), most)
        got = [(i, net.copy()) for i, net, _ in net_count_batches(rec, win, (0, 64, 0, 48), 16)]
    assert 2 <= most[0] <= a4r.PREFETCH_THREADS
    assert [i for i, _ in got] == [i for i, _ in want]
    for (_, a), (_, b) in zip(got, want):
        np.testing.assert_array_equal(a, b)
