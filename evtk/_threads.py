"""How many threads evtk's own parallel work uses (decompression pools, numba kernels): one place for every package."""

from __future__ import annotations

import os
from _thread import _local, allocate_lock  # threading's Lock and local (threading loads with a pool's first thread)
from _weakrefset import WeakSet  # weakref.WeakSet, loaded at every Python start (weakref is not)
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from _queue import SimpleQueue

#: The environment variable that sets the thread count (``evtk --threads N`` sets it).
ENV = "EVTK_THREADS"
#: Its older name, still read when :data:`ENV` is not set.
ALIAS = "EVTK_IO_THREADS"


def cores() -> int:
    """The cores this process may run on: its CPU affinity (``taskset``, cgroup cpusets), else the CPU count.

    Returns
    -------
    int
        At least 1.
    """
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


def workers() -> int:
    """Threads for evtk's parallel work: ``EVTK_THREADS`` (or its alias ``EVTK_IO_THREADS``) if set to a
    positive integer, else every core the process may run on (:func:`cores`).

    Returns
    -------
    int
        At least 1.
    """
    for name in (ENV, ALIAS):
        env = os.environ.get(name, "").strip()
        if env:
            try:
                return max(1, int(env))
            except ValueError:
                break  # not a number: the cores, as when unset
    return cores()


def switched_off(name: str) -> bool:
    """Whether the environment variable ``name`` turns something off: it says ``0``, ``false``, ``no`` or ``off``
    (any case, spaces around); unset or anything else leaves it on.

    Parameters
    ----------
    name : str
        The variable.

    Returns
    -------
    bool
        True when turned off.
    """
    return os.environ.get(name, "").strip().lower() in ("0", "false", "no", "off")


#: The share of a read's own arrays that its decoding threads' working memory may add: no more threads decode
#: than it pays for (issue 32: a whole read's peak within 1.1 times the arrays it returns, on any core count).
MEMORY_SHARE = 0.08


def workers_within(output_bytes: int, thread_bytes: int, share: float = MEMORY_SHARE) -> int:
    """:func:`workers`, but no more threads than ``share`` (:data:`MEMORY_SHARE`) of ``output_bytes`` pays for
    at ``thread_bytes`` each (and at least one).

    Parameters
    ----------
    output_bytes : int
        The bytes of what the threads produce (the arrays a read returns).
    thread_bytes : int
        One thread's working memory (its buffers, its allocator arena).
    share : float
        The share of ``output_bytes`` the threads' memory may add.

    Returns
    -------
    int
        At least 1.
    """
    return min(workers(), max(1, int(share * output_bytes) // max(1, int(thread_bytes))))


class Task:
    """Work handed to a :class:`Pool`: its result once it has run.

    A lock taken at creation and let go when the work ends is what waiting
    costs: no condition variable, no callbacks.
    """

    __slots__ = ("_done", "_value", "_error")

    def __init__(self) -> None:
        self._done = allocate_lock()
        self._done.acquire()
        self._value: Any = None
        self._error: BaseException | None = None

    def result(self) -> Any:
        """Wait for the work to end.

        Returns
        -------
        object
            What the work returned.

        Raises
        ------
        BaseException
            Whatever the work raised, raised again here.
        """
        with self._done:  # free once the work has ended (every later call passes at once)
            pass
        if self._error is not None:
            raise self._error
        return self._value


def _new_queue() -> SimpleQueue:
    """A new job queue: ``queue``'s own C queue (``queue`` itself loads heapq and more for nothing here), its
    extension loaded with the first pool (0.4 ms a fresh process that reads a small file on one thread need not
    pay)."""
    from _queue import SimpleQueue

    return SimpleQueue()


class Pool:
    """Up to ``size`` worker threads taking work in the order it is handed in.

    evtk's decoding, counting and prefetching threads. The standard library's
    ``concurrent.futures`` does the same with more (futures with callbacks,
    cancellation, its ``logging``), and costs a fresh process 4-5 ms to
    import, a few percent of a short read. Threads start as work finds none
    idle, and are daemons: they hold no work of their own (every caller
    waits for its :class:`Task`). A process forked from one that had the pool
    starts its own threads (the parent's do not exist in the child, and a
    lock one of them held at the fork would stay held there).

    Parameters
    ----------
    size : int
        Most threads (at least 1).
    name : str
        Prefix of the threads' names.
    """

    def __init__(self, size: int, name: str) -> None:
        self.size = max(1, int(size))
        self.name = name
        self._jobs: SimpleQueue = _new_queue()
        self._lock = allocate_lock()
        self._threads = 0
        self._idle = 0
        self._closed = False
        _POOLS.add(self)

    def _forked(self) -> None:
        """In a forked child: no threads, no work, a lock nobody holds."""
        self._lock = allocate_lock()
        self._jobs = _new_queue()
        self._threads = self._idle = 0

    def submit(self, fn: Callable[..., Any], *args: Any) -> Task:
        """Run ``fn(*args)`` on one of the pool's threads.

        Parameters
        ----------
        fn : callable
            The work.
        *args
            Its arguments.

        Returns
        -------
        Task
            Its result, once :meth:`Task.result` is called.

        Raises
        ------
        RuntimeError
            After :meth:`shutdown`.
        """
        task = Task()
        with self._lock:
            if self._closed:
                raise RuntimeError(f"the {self.name} pool is shut down")
            self._jobs.put((task, fn, args))
            # _idle: idle threads less the work waiting for one (below 0 only once every thread is started)
            if self._idle <= 0 and self._threads < self.size:
                import threading

                self._threads += 1
                threading.Thread(target=self._work, name=f"{self.name}-{self._threads}", daemon=True).start()
            else:
                self._idle -= 1
        return task

    def _work(self) -> None:
        while True:
            job = self._jobs.get()
            if job is None:
                return
            task, fn, args = job
            try:
                task._value = fn(*args)
            except BaseException as exc:  # noqa: BLE001 - handed to whoever waits for the task
                task._error = exc
            finally:
                del job, fn, args
                task._done.release()
                del task
            with self._lock:
                self._idle += 1

    def shutdown(self) -> None:
        """Let the threads end once the work handed in so far is done (without waiting for it); no more work
        is taken."""
        with self._lock:
            self._closed = True
            for _ in range(self._threads):
                self._jobs.put(None)


_POOLS: WeakSet[Pool] = WeakSet()


def _after_fork_in_child() -> None:
    for pool in list(_POOLS):
        pool._forked()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_after_fork_in_child)


class Helpers:
    """Work offered to the thread that waits for it: the consumer of prefetched chunks decodes with the
    prefetching thread instead of waiting idle for it.

    While one thread counts a chunk, another decodes the next one; on two cores a third decoding thread only
    takes turns with them (and the GIL with them: every preempted holder stalls the others). A reader's split
    decode (the AEDAT4 reader's ranges of packets) offers its ranges here when it runs on a prefetching thread
    (:func:`helpers`), decodes them itself, and the consumer, once it has counted its chunk and would wait for
    the next, takes ranges too (:meth:`wait`). So there are as many busy threads as cores all along: the
    decoders less one while the consumer counts, all of them when it waits.

    The prefetching thread's own work must call :meth:`finish` when it ends (it wakes the waiting consumer).
    """

    __slots__ = ("_lock", "_bell", "_work", "_active", "_finished")

    def __init__(self) -> None:
        self._lock = allocate_lock()
        self._bell = allocate_lock()  # released ("rung") at each offer and at the end of the work
        self._bell.acquire()
        self._work: Callable[[], Any] | None = None
        self._active: list = []
        self._finished = False

    def _ring(self) -> None:
        try:
            self._bell.release()
        except RuntimeError:  # rung already: one wake-up is enough
            pass

    def start(self) -> None:
        """A new piece of the prefetching thread's work begins (before it is handed to the thread)."""
        self._finished = False

    def offer(self, fn: Callable[[], Any]) -> None:
        """Let a waiting consumer run ``fn`` too (any number of times, on any thread: it takes its own share of
        the work and returns when none is left).

        Parameters
        ----------
        fn : callable
            Work that several threads may run at once.
        """
        with self._lock:
            self._work = fn
        self._ring()

    def withdraw(self) -> None:
        """No new helper may start the offered work; waits for those running it to return."""
        with self._lock:
            self._work = None
            active, self._active = self._active, []
        for done in active:
            with done:
                pass

    def share(self, fn: Callable[[], Any]) -> None:
        """:meth:`offer` ``fn``, run it on this thread, then :meth:`withdraw` it (also when it raises).

        Parameters
        ----------
        fn : callable
            Work that several threads may run at once (each takes its own share, and returns when none is left).
        """
        self.offer(fn)
        try:
            fn()
        finally:
            self.withdraw()

    def finish(self) -> None:
        """The prefetching thread's current work has ended (its result is ready or about to be)."""
        self._finished = True
        self._ring()

    def _help(self) -> None:
        with self._lock:
            fn = self._work
            if fn is None:
                return
            done = allocate_lock()
            done.acquire()
            self._active.append(done)
        try:
            fn()
        finally:
            done.release()

    def wait(self) -> None:
        """Run what is offered until the prefetching thread's work has ended."""
        while True:
            self._help()
            if self._finished:
                return
            self._bell.acquire()  # the next offer, or the end


_HERE = _local()


def helpers() -> Helpers | None:
    """The :class:`Helpers` a split decode on this thread offers its work to (None: none, decode alone).

    Returns
    -------
    Helpers or None
        Set by :func:`use_helpers` on a prefetching thread.
    """
    return getattr(_HERE, "helpers", None)


def use_helpers(h: Helpers | None) -> None:
    """Make ``h`` this thread's :class:`Helpers` (None: none).

    Parameters
    ----------
    h : Helpers or None
        The helpers.
    """
    _HERE.helpers = h
