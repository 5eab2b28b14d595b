"""How many threads evtk's own parallel work uses (decompression pools, numba kernels): one place for every package."""

from __future__ import annotations

import os


def workers() -> int:
    """Threads for evtk's parallel work: ``EVTK_IO_THREADS`` if set, else the usable cores, at most 4.

    Returns
    -------
    int
        At least 1.
    """
    env = os.environ.get("EVTK_IO_THREADS")
    if env:
        try:
            return max(1, int(env))
        except ValueError:
            pass
    try:
        n = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        n = os.cpu_count() or 1
    return max(1, min(4, n))
