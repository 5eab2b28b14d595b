"""Assembling simulated events into time order (a counting sort, numba)."""

from __future__ import annotations

import math

import numba
import numpy as np

__all__ = []


def _sorted_events(t_rel, local, pol, span, base, x_of, y_of):
    """:func:`_assemble`, or for a batch spanning more than ``_COUNTING_SORT_MAX_US`` (very long settles) a
    stable argsort, whose memory does not grow with the span."""
    if span <= _COUNTING_SORT_MAX_US and t_rel.size < 2**31:
        return _assemble(t_rel, local, pol, span, base, x_of, y_of)
    k = np.clip(np.floor(t_rel), 0, span - 1).astype(np.int64)
    order = np.argsort(k, kind="stable")
    local = local[order]
    return base + k[order], x_of[local], y_of[local], pol[order]


_COUNTING_SORT_MAX_US = 1 << 26  # 64 s of bins (0.25 GiB of counts at most)


@numba.njit(cache=True)
def _assemble(t_rel, local, pol, span, base, x_of, y_of):
    """Events from (float us since ``base``, pixel, polarity), sorted by whole us; pixel ``local[i]`` sits
    at ``(x_of[local[i]], y_of[local[i]])``.

    A stable counting sort over the ``span`` microseconds of the batch: O(n + span).
    """
    n = t_rel.size
    key = np.empty(n, np.int32)  # spans are at most _COUNTING_SORT_MAX_US
    counts = np.zeros(span + 1, np.int32)  # fewer than 2^31 events (see _sorted_events)
    for i in range(n):
        k = int(math.floor(t_rel[i]))
        k = min(max(k, 0), span - 1)
        key[i] = k
        counts[k + 1] += 1
    for i in range(span):
        counts[i + 1] += counts[i]
    t = np.empty(n, np.int64)
    x = np.empty(n, np.uint16)
    y = np.empty(n, np.uint16)
    p = np.empty(n, np.uint8)
    for i in range(n):
        k = np.int64(key[i])  # int64 as compiled; in Python (NUMBA_DISABLE_JIT) int32 + base would overflow
        j = counts[k]
        counts[k] += 1
        t[j] = base + k
        q = local[i]
        x[j] = x_of[q]
        y[j] = y_of[q]
        p[j] = pol[i]
    return t, x, y, p
