"""Work split over threads, in parts that release the GIL: the counting (evtk's compiled kernel or numpy) and
summing of fixed windows, the counting of a schedule's windows and the timing solve (evtk's compiled kernels, else
``nogil`` numba kernels), the linearisation's look-ups; one shared pool for all of them.

Most numpy loops (ufuncs, ``take``, ``einsum``, reductions) release the GIL, so parts of one array handed to
several threads run on several cores; ``np.add.at`` and ``np.bincount`` keep it and stay serial among them, and
evtk's compiled counting (:mod:`evtk._native`) releases it.
The parts are always cut so that no two threads write the same memory and every integer result is the same
whatever the cut (each part's sums are added in integers afterwards).
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from ._threads import Pool, workers

#: Least work (elements) worth a part of its own: below it a thread's hand-over costs more than it saves.
MIN_PART = 1 << 16
#: Most parts one piece of work is cut into, whatever the cores. The counting's scatter-adds keep the GIL, and what
#: releases it (the sums, the block means) is short beside the decoding the other threads do meanwhile: on a
#: 16-core machine (issue 32, tenth round) ``evtk enob`` and ``evtk reconstruct -o`` ran no slower with two parts
#: than with eight, on 10-20 % less CPU time.
MOST_PARTS = 2

_lock = threading.Lock()
_pool: Pool | None = None
_pool_size = 0


def parts(work: int, gil_free: bool = False) -> int:
    """How many parts ``work`` elements are cut into: half of :func:`evtk._threads.workers` at most (the other
    half decode the next chunk of the recording meanwhile), each at least :data:`MIN_PART`, and at most
    :data:`MOST_PARTS` unless the work releases the GIL throughout.

    Parameters
    ----------
    work : int
        Elements of work.
    gil_free : bool
        The parts run code that holds no GIL (evtk's compiled counting, :mod:`evtk._native`): as many parts as
        half the threads, past :data:`MOST_PARTS`.

    Returns
    -------
    int
        At least 1.
    """
    most = workers() // 2 if gil_free else min(workers() // 2, MOST_PARTS)
    return max(1, min(most, int(work) // MIN_PART))


def cuts(weights: np.ndarray, n_parts: int) -> list[int]:
    """Cut items with ``weights`` into at most ``n_parts`` runs of about equal weight.

    Parameters
    ----------
    weights : ndarray
        Each item's weight (non-negative).
    n_parts : int
        Most runs.

    Returns
    -------
    list of int
        Increasing bounds from 0 to ``len(weights)``: run ``r`` is items ``bounds[r]:bounds[r + 1]`` (never empty).
    """
    n = len(weights)
    if n_parts <= 1 or n <= 1:
        return [0, n]
    cum = np.cumsum(weights, dtype=np.int64)
    total = int(cum[-1]) if n else 0
    if total <= 0:
        return [0, n]
    at = np.searchsorted(cum, np.arange(1, n_parts) * (total / n_parts), side="left") + 1
    return sorted({0, n, *(int(v) for v in at if 0 < v < n)})


def run(fn: Callable[..., Any], args: Sequence[tuple]) -> list:
    """``fn(*a)`` for each ``a`` of ``args``, on evtk's shared worker threads when more than one, in order (the
    calling thread does the first). ``fn`` must not itself call :func:`run` (the pool could run out of threads).

    Parameters
    ----------
    fn : callable
        The work of one part.
    args : sequence of tuple
        Each part's arguments.

    Returns
    -------
    list
        The results, in the order of ``args`` (the first exception raised, if any, is raised here).
    """
    if len(args) <= 1:
        return [fn(*a) for a in args]
    pool = _shared_pool()
    futures = [pool.submit(fn, *a) for a in args[1:]]
    first = fn(*args[0])  # this thread does a part too
    return [first] + [f.result() for f in futures]


def _shared_pool() -> Pool:
    """The worker threads :func:`run` hands parts to: one fewer than :func:`evtk._threads.workers` (the calling
    thread does a part), started as parts first need them, made again when the budget changes."""
    global _pool, _pool_size
    n = max(1, workers() - 1)
    with _lock:
        if _pool is None or _pool_size != n:
            if _pool is not None:
                _pool.shutdown()
            _pool, _pool_size = Pool(n, "evtk-part"), n
        return _pool
