"""evtk's optional compiled kernels (``evtk._ckernels``, built at install where a C compiler is present), behind
wrappers that check their arguments and say when the numpy route must be taken instead.

The kernels release the GIL, so parts of one piece of work run on several cores at once; numpy's scattered adds
(``np.add.at``), which the numpy route counts with, keep it. ``EVTK_NATIVE=0`` (read at each call) turns them off,
to compare the two routes; the results are the same to the last bit.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

_kernel_count_windows: Any
try:
    from ._ckernels import count_windows as _kernel_count_windows
except ImportError:  # built without a compiler: the numpy route
    _kernel_count_windows = None

#: Whether the install built the compiled kernels (a C compiler was present).
BUILT = _kernel_count_windows is not None

#: Every uint16 coordinate: the length of :func:`count_windows`' tables.
TABLE_SIZE = 1 << 16


def enabled() -> bool:
    """Whether the compiled kernels are present and not turned off by ``EVTK_NATIVE=0``.

    Returns
    -------
    bool
        True where :func:`count_windows` counts.
    """
    return BUILT and os.environ.get("EVTK_NATIVE", "").strip().lower() not in ("0", "false", "no",
                                                                                               "off")


def padded_table(values: np.ndarray, fill: int) -> np.ndarray:
    """A coordinate's look-up table over every uint16 coordinate: ``values`` (one per sensor column or row) as
    int64, then ``fill`` (where a coordinate off the sensor goes).

    Parameters
    ----------
    values : ndarray
        The table's first entries (integers, at most 65536 of them).
    fill : int
        The rest.

    Returns
    -------
    ndarray
        int64, 65536 entries.
    """
    table = np.full(TABLE_SIZE, fill, np.int64)
    table[:len(values)] = values
    return table


def count_windows(x: np.ndarray, y: np.ndarray, p: np.ndarray, where: slice | np.ndarray, at: np.ndarray,
                  ky: np.ndarray, kx: np.ndarray, on_step: int, limit: int, per_window: int, dump: int, net: bool,
                  out: np.ndarray) -> bool:
    """Count picked events into their windows' bins with the compiled kernel, the GIL released.

    Window ``w`` (``0 <= w < len(at) - 1``) holds the picks ``at[w]:at[w + 1]`` (of ``where``: a slice of the
    events, or their indices). An event's bin within its window is ``k = ky[y] + kx[x]`` (plus ``on_step`` when
    it is ON); it is counted in bin ``w * per_window + k`` of ``out`` when ``0 <= k < limit``, else in bin
    ``dump``. Each event adds 1, or with ``net`` its sign (+1 ON, -1 OFF), wrapping in the bins' type.

    Parameters
    ----------
    x, y : ndarray
        The events' coordinates (uint16).
    p : ndarray
        Their polarities (uint8, 0 OFF).
    where : slice or ndarray
        The picked events: a slice (step 1) or int64 indices into ``x``, ``y``, ``p``.
    at : ndarray
        Each window's first pick, then the end of the last window's (int64).
    ky, kx : ndarray
        Each coordinate's part of the bin (int64, 65536 entries: :func:`padded_table`).
    on_step : int
        Added to an ON event's bin.
    limit : int
        Bins within a window are ``0 .. limit - 1`` (at most ``per_window``).
    per_window : int
        Bins between one window's and the next's.
    dump : int
        The bin of events outside every window's ``limit``.
    net : bool
        Add signs instead of ones.
    out : ndarray
        The bins: int16 or int32, contiguous, writable, holding every window's bins and ``dump``.

    Returns
    -------
    bool
        True when counted; False (nothing counted) when the kernel is off or missing, or an argument is not in
        the form it takes: then the caller counts with numpy.
    """
    if not enabled() or out.dtype not in (np.int16, np.int32) or not out.flags.c_contiguous or not out.flags.writeable:
        return False
    cols = (x, y, p)
    if (any(not c.flags.c_contiguous for c in cols) or (x.dtype, y.dtype, p.dtype) != (np.uint16, np.uint16, np.uint8)
            or not len(x) == len(y) == len(p)):
        return False
    tables = (ky, kx, at)
    if any(t.dtype != np.int64 or not t.flags.c_contiguous for t in tables) or len(ky) != TABLE_SIZE or len(kx) != TABLE_SIZE:
        return False
    n_w = len(at) - 1
    if n_w < 1 or not 0 <= limit <= per_window or not 0 <= dump < out.size or n_w * per_window > out.size:
        return False
    if isinstance(where, slice):
        if where.step not in (None, 1):
            return False
        first, _, _ = where.indices(len(x))
        picks: Any = np.zeros(0, np.int64)
    else:
        if where.dtype != np.int64 or not where.flags.c_contiguous:
            return False
        first, picks = 0, where
    _kernel_count_windows(x, y, p, picks, not isinstance(where, slice), first, at, ky, kx, int(on_step), int(limit),
                            int(per_window), int(dump), bool(net), out, out.itemsize)
    return True
