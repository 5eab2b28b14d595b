"""evtk's thread count: every core the process may run on, ``EVTK_THREADS`` / ``--threads`` to override."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from conftest import random_events

import evtk
from evtk import _threads
from evtk.cli import main
from evtk.io import _compression as cz


def _clear(monkeypatch):
    monkeypatch.delenv(_threads.ENV, raising=False)
    monkeypatch.delenv(_threads.ALIAS, raising=False)


def test_workers_use_every_core_the_affinity_gives(monkeypatch):
    """Reads were capped at 4 threads whatever the machine: on 16 cores a read used a quarter of them."""
    _clear(monkeypatch)
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(16)), raising=False)
    assert _threads.workers() == 16
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {5}, raising=False)
    assert _threads.workers() == 1


def test_evtk_threads_overrides_and_the_old_name_still_works(monkeypatch):
    _clear(monkeypatch)
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(8)), raising=False)
    monkeypatch.setenv(_threads.ALIAS, "5")
    assert _threads.workers() == 5
    monkeypatch.setenv(_threads.ENV, "3")  # the new name wins over the alias
    assert _threads.workers() == 3
    monkeypatch.setenv(_threads.ENV, "many")  # not a number: the cores, as when unset
    assert _threads.workers() == 8


def test_a_pinned_process_reads_on_one_thread(tmp_path):
    """``taskset -c 0 python ...``: the affinity, not the machine's CPU count, sets the threads."""
    code = ("import os\n"
            "os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})\n"
            "from evtk._threads import workers\n"
            "print('THREADS', workers())\n")
    env = {k: v for k, v in os.environ.items() if k not in (_threads.ENV, _threads.ALIAS)}
    env["PYTHONPATH"] = str(Path(evtk.__file__).parents[1])
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env).stdout
    assert "THREADS 1" in out, out


def test_the_threads_option_sets_the_decode_threads_for_the_command_only(tmp_path, monkeypatch):
    """``evtk --threads 3 convert ...`` decodes on a pool of 3 threads; the environment is restored after."""
    _clear(monkeypatch)
    from evtk.io.aedat4 import reader

    monkeypatch.setattr(reader, "_THREAD_BYTES", 1)  # threads not bounded by this small file's memory
    ev = random_events(300_000, seed=3)
    src, out = tmp_path / "a.aedat4", tmp_path / "b.h5"
    evtk.write_events(src, ev)
    r = CliRunner().invoke(main, ["--threads", "3", "convert", str(src), str(out)])
    assert r.exit_code == 0, r.output
    assert cz._pool_size == 3  # the pool the read ran on
    assert _threads.ENV not in os.environ
    got = evtk.read_events(out)
    assert np.array_equal(got.t, ev.t) and np.array_equal(got.x, ev.x)
    r = CliRunner().invoke(main, ["--threads", "0", "info", str(src)])
    assert r.exit_code == 2 and "--threads" in r.output


@pytest.mark.parametrize("thread_kib,most", [(1, 4), (300, 2), (100_000, 1)])
def test_aedat4_decode_threads_are_bounded_by_the_events_memory(tmp_path, monkeypatch, thread_kib, most):
    """Issue 32 item 5 on many cores: no more AEDAT4 decode threads than 8 % of the events' memory pays for at
    a thread's buffers each (on 16 cores, one per core peaked at 1.13-1.15x the arrays): 300,000 events are
    3.9 MB, 8 % of it 312 KB, so 300 KiB a thread allows 1, 1 byte the four threads asked for."""
    import threading

    from evtk.io import _compression as cz
    from evtk.io.aedat4 import reader

    _clear(monkeypatch)
    monkeypatch.setenv("EVTK_THREADS", "4")
    monkeypatch.setattr(reader, "_THREAD_BYTES", thread_kib << 10)
    monkeypatch.setattr(reader, "BATCH_EVENTS", 2_000)  # many batches, so every thread that runs takes some
    ev = random_events(300_000, seed=5)
    path = tmp_path / "m.aedat4"
    evtk.write_events(path, ev, packet_events=1_000)
    names: set[str] = set()

    def spied(real):
        def spy(*args):
            names.add(threading.current_thread().name)
            time.sleep(0.0005)  # long enough that idle threads would take ranges
            return real(*args)
        return spy

    # a packet's decompression in Python, or a batch's start in evtk's compiled batches
    monkeypatch.setattr(cz, "lz4_into_at", spied(cz.lz4_into_at))
    monkeypatch.setattr(cz, "lz4f_addresses", spied(cz.lz4f_addresses))
    got = evtk.read_events(path)
    assert got == ev
    if most < 4:
        assert 1 <= len(names) <= most, names
    else:
        assert len(names) >= 2, names


def test_a_chunk_of_a_chunked_read_takes_the_threads_its_batches_memory_pays_for(tmp_path, monkeypatch):
    """A chunked read's threads are bounded by the buffers of the chunk's own batches, which a chunk of a quarter
    million events keeps to a sixteenth of it (15 k events, about 0.6 MB a thread), not by full batches' (2.6 MB,
    which held such a chunk to one thread while the windows' counting waited for it): it decodes on several."""
    import threading

    from evtk.io import _compression as cz

    _clear(monkeypatch)
    monkeypatch.setenv("EVTK_THREADS", "4")
    ev = random_events(500_000, seed=7)
    path = tmp_path / "c.aedat4"
    evtk.write_events(path, ev, packet_events=10_000)
    names: set[str] = set()
    real = cz.lz4f_addresses

    def spy(*args):
        names.add(threading.current_thread().name)
        time.sleep(0.002)  # long enough that idle threads would take ranges
        return real(*args)

    monkeypatch.setattr(cz, "lz4f_addresses", spy)
    with evtk.open(path) as rec:
        chunks = list(rec.iter_events(chunk_events=250_000))
    assert [len(c) for c in chunks] == [250_000, 250_000]
    assert np.array_equal(np.concatenate([c.t for c in chunks]), ev.t)
    assert np.array_equal(np.concatenate([c.x for c in chunks]), ev.x)
    assert len(names) >= 2, names


# -- evtk's own thread pool (issue 32: concurrent.futures and its logging were 4-5 ms of a fresh process) --------


def test_the_pool_returns_each_result_and_raises_each_error_where_it_is_awaited():
    pool = _threads.Pool(3, "test-pool")
    tasks = [pool.submit(divmod, 100 + i, 7) for i in range(50)]
    bad = pool.submit(divmod, 1, 0)
    assert [t.result() for t in tasks] == [divmod(100 + i, 7) for i in range(50)]
    with pytest.raises(ZeroDivisionError):
        bad.result()
    with pytest.raises(ZeroDivisionError):  # awaited again: the same error, not a hang
        bad.result()
    assert 1 <= pool._threads <= 3
    pool.shutdown()
    with pytest.raises(RuntimeError, match="shut down"):
        pool.submit(divmod, 1, 1)


def test_the_pool_runs_work_side_by_side_up_to_its_size():
    """Three pieces of work that each wait for all three to have started finish only if three threads run them."""
    import threading

    pool = _threads.Pool(3, "test-side")
    barrier = threading.Barrier(3, timeout=10)
    tasks = [pool.submit(barrier.wait) for _ in range(3)]
    assert sorted(t.result() for t in tasks) == [0, 1, 2]
    pool.shutdown()


def test_a_forked_child_gets_threads_of_its_own():
    """A child forked from a process whose pool had threads (a Dask or multiprocessing worker forked after a read)
    found none of them: work handed to the pool waited forever. It now starts its own."""
    if not hasattr(os, "fork"):
        pytest.skip("no fork here")
    code = ("import os, sys\n"
            "from evtk import _threads\n"
            "pool = _threads.Pool(2, 'p')\n"
            "assert pool.submit(abs, -3).result() == 3\n"
            "pid = os.fork()\n"
            "if pid == 0:\n"
            "    os._exit(0 if pool.submit(abs, -4).result() == 4 else 1)\n"
            "_, status = os.waitpid(pid, 0)\n"
            "sys.exit(os.waitstatus_to_exitcode(status))\n")
    env = dict(os.environ, PYTHONPATH=str(Path(evtk.__file__).parents[1]))
    done = subprocess.run([sys.executable, "-c", code], env=env, timeout=60, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]


def test_a_prefetch_closed_early_finishes_the_chunk_under_way_first():
    """Closing the counting early (an error, a break) must not let go of the recording while a thread still reads
    its next chunk."""
    from evtk.reconstruct.accumulate import _prefetched

    log = []

    def chunks():
        for i in range(5):
            time.sleep(0.05)
            log.append(f"made {i}")
            yield i

    it = _prefetched(chunks())
    assert next(it) == 0  # chunk 1 is now being made on the prefetch thread
    it.close()
    log.append("closed")
    assert log == ["made 0", "made 1", "closed"]


def test_a_prefetch_raises_the_sources_error_in_the_caller():
    from evtk.reconstruct.accumulate import _prefetched

    def chunks():
        yield 1
        raise evtk.EvtkError("bad packet at byte 12")

    it = _prefetched(chunks())
    assert next(it) == 1
    with pytest.raises(evtk.EvtkError, match="byte 12"):
        next(it)


def test_threaded_reads_and_counts_load_no_concurrent_futures(tmp_path):
    """A multi-threaded read and a fixed-window count in a fresh process use evtk's pool: concurrent.futures,
    with the logging it imports, cost 4-5 ms of every such process."""
    from conftest import modules_after

    path = tmp_path / "big.aedat4"
    evtk.write_events(path, random_events(400_000, seed=2), packet_events=5_000)
    loaded = modules_after("import os\nos.environ['EVTK_THREADS'] = '2'\nimport evtk\n"
                           f"from evtk.cli import main\n"
                           f"assert len(evtk.read_events({str(path)!r})) == 400_000\n"
                           f"try:\n    main(['enob', {str(path)!r}, '--window', 'period:1000'])\n"
                           "except SystemExit as exc:\n    assert not exc.code, exc.code\n")
    assert "evtk.reconstruct.fixed" in loaded and "threading" in loaded  # the count ran, on threads
    assert not {"concurrent.futures", "logging"} & set(loaded)


def test_a_read_in_a_forked_child_after_a_threaded_read_in_the_parent(tmp_path):
    """A multiprocessing worker forked after a multi-threaded read (Linux's default start method) hung on its
    own first multi-threaded read: the executor it inherited counted the parent's idle thread as its own."""
    if not hasattr(os, "fork"):
        pytest.skip("no fork here")
    path = tmp_path / "big.aedat4"
    evtk.write_events(path, random_events(400_000, seed=3), packet_events=5_000)
    code = ("import os, sys, time\nos.environ['EVTK_THREADS'] = '2'\nimport evtk\n"
            "from evtk.io.aedat4 import reader\n"
            "reader._THREAD_BYTES = 1024  # two decode threads for a small file\n"
            f"n = len(evtk.read_events({str(path)!r}))\n"
            "assert sum(t.name.startswith('evtk-io') for t in __import__('threading').enumerate()) == 2\n"
            "time.sleep(0.1)  # the parent's decode threads idle\n"
            "pid = os.fork()\n"
            "if pid == 0:\n"
            f"    os._exit(0 if len(evtk.read_events({str(path)!r})) == n else 1)\n"
            "_, status = os.waitpid(pid, 0)\n"
            "sys.exit(os.waitstatus_to_exitcode(status))\n")
    env = dict(os.environ, PYTHONPATH=str(Path(evtk.__file__).parents[1]))
    done = subprocess.run([sys.executable, "-c", code], env=env, timeout=60, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
