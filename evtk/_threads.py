"""How many threads evtk's own parallel work uses (decompression pools, numba kernels): one place for every package."""

from __future__ import annotations

import os

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
