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

