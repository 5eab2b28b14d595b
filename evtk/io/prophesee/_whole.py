"""A whole Prophesee file (EVT 3.0; EVT 2.0 and DAT where a second thread pays) decoded on the reader's threads,
straight into one set of exact-size columns, with evtk's compiled kernels where the install built them, else numpy.

Everything a word needs from the words before it (the time base; for EVT 3.0 also y, the vector base and the
polarity) is a short state that a block's words change in a way a cheap scan sums up (its time words' last values,
its wraps). So a first pass counts each block's events and triggers and sums up its effect; each block's start state
and its place in the columns follow in order; and the blocks then decode independently, on as many threads as the
memory rule pays for. Each encoding brings its own scan, state update and decoder (:class:`Codec`).
"""

from __future__ import annotations

import os
from _thread import get_ident  # threading itself is a module more for a fresh read
from collections.abc import Callable
from typing import Any

import numpy as np

from ..._native import prophesee_scan
from ..._threads import workers_within
from ...limits import require_memory
from .decoders import ST_OK, ST_TYPE, _dat_run, _evt2_run, _first_stop


class Codec:
    """How :func:`read_whole` takes one encoding's words (a plain class: a ``NamedTuple`` costs a fresh read
    0.5 ms to create).

    Attributes
    ----------
    dtype : str
        The words' numpy type as stored (``"<u2"``, ``"<u4"``).
    item_words : int
        Words an item takes (the unit of counts and offsets: a DAT event is two words).
    scan : callable
        ``scan(words) -> (events, triggers, index of a word of no type or -1, effect)``: the counts up to that word
        (events off the sensor included) and the words' effect on the state.
    advance : callable
        ``advance(state, effect)``: the state moved on over words whose scan gave ``effect``.
    run : callable
        The decoder: ``run(words, state, width, height, decode, t, x, y, p, tt, tk, tch)``.
    time_range : callable or None
        ``time_range(words, state) -> (min t, max t)`` of a block's events without decoding them (None where it
        cannot tell); None where the encoding has none (the index then counts with ``run``).
    """

    __slots__ = ("dtype", "item_words", "scan", "advance", "run", "time_range")

    def __init__(self, dtype: str, item_words: int, scan: Callable[[np.ndarray], tuple[int, int, int, tuple[int, ...]]],
                 advance: Callable[[np.ndarray, tuple[int, ...]], None], run: Callable[..., tuple[int, int, int, int, int, int]],
                 time_range: Callable[[np.ndarray, np.ndarray], tuple[int, int] | None] | None = None) -> None:
        self.dtype, self.item_words, self.scan, self.advance, self.run = dtype, item_words, scan, advance, run
        self.time_range = time_range


def _keep_temporaries_mapped() -> None:
    """Let the allocator keep the decoder's temporaries between slices. glibc returns the free memory at the top
    of its heap to the system once it passes a threshold, which it raises to twice the largest mapped block it has
    freed: left at its start, each slice's few MiB of temporaries are returned and faulted in again, some 300 k
    page faults and 0.4 s of system time on a file of 50 M words. Freeing one untouched 8 MiB array (no memory is
    used: its pages are never written) raises the threshold past them. Elsewhere, a no-op."""
    np.empty(8 << 20, np.uint8)


#: Files of fewer blocks than this (4 M EVT 3.0 or EVT 2.0 words, 2 M DAT events) decode on the calling thread: the
#: pool's imports and start (about 10 ms of a fresh process) cost more than the threads save on fewer.
THREADED_BLOCKS = 16
#: A decoding thread's working memory (its slices' temporaries, its block's words, its allocator arena), measured
#: (a 20 M-event read on two threads peaked 5 MiB above one thread's).
THREAD_BYTES = 6 << 20


def threads_for(n_blocks: int, memory_bytes: int) -> int:
    """The threads a pass over ``n_blocks`` blocks takes: one below :data:`THREADED_BLOCKS`, else as many as
    ``memory_bytes`` (the columns it fills, or the file) pays for at :data:`THREAD_BYTES` each
    (:func:`evtk._threads.workers_within`).

    Parameters
    ----------
    n_blocks : int
        Blocks of the file.
    memory_bytes : int
        The memory whose share pays for the threads.

    Returns
    -------
    int
        At least 1.
    """
    return workers_within(memory_bytes, THREAD_BYTES) if n_blocks >= THREADED_BLOCKS else 1


def read_whole(path: str, start: int, count: int, block_words: int, width: int, height: int,
               state: np.ndarray, codec: Codec, decode: bool = True) -> dict[str, Any]:
    """Decode every word of a Prophesee file into exact-size columns, its blocks on the reader's threads.

    A first pass (``codec.scan``) counts each block's events and triggers and sums up its effect on the state, so
    that each block's start state and place in the columns are known; the second decodes each block from that
    state straight into its place. Both run on :func:`evtk._threads.workers` threads (the compiled kernels and
    numpy's array operations release the GIL), the decoding on no more than :data:`evtk._threads.MEMORY_SHARE` of
    the columns' memory pays for (:data:`THREAD_BYTES` each), so that the peak is the columns and a few MiB.
    Without ``decode``, the blocks are counted only (their time ranges too), on the sensor of 65536 x 65536 the
    reader's index takes: the index.

    Parameters
    ----------
    path : str
        The file.
    start : int
        Byte offset of the first word.
    count : int
        Items (words; DAT: events) in the file.
    block_words : int
        Items per block (the reader's index unit).
    width, height : int
        The sensor, in pixels.
    state : numpy.ndarray
        The state before the first word (int64), left as it is.
    codec : Codec
        The encoding's words, scan, state update and decoder.
    decode : bool
        Decode the events and triggers; else only the index.

    Returns
    -------
    dict
        ``t``, ``x``, ``y``, ``p`` (the events), ``tt``, ``tk``, ``tch`` (the triggers), ``status`` and
        ``bad`` (the first stop and its word index in the file; ST_OK and -1 when none), ``word`` (the word
        there) and ``rows`` (per block up to the stop: start state, events, triggers, min t, max t: the reader's
        index); without ``decode``, the columns are empty and the events and triggers those counted.
    """
    n_blocks = -(-count // block_words)
    # threads while counting: as many as the file's own size pays for (its events take at least as much memory
    # as its words unless it is mostly time words); while decoding, as many as the events' memory pays for
    threads = threads_for(n_blocks, 2 * count)
    dtype = np.dtype(codec.dtype)
    item = dtype.itemsize * codec.item_words  # bytes an item
    _keep_temporaries_mapped()
    fd = os.open(path, os.O_RDONLY)
    try:
        buffers: dict[int, np.ndarray] = {}  # each thread reads its blocks into one buffer of its own

        def words_of(b):
            a = b * block_words
            size = item * min(block_words, count - a)
            if not hasattr(os, "preadv"):
                raw = os.pread(fd, size, start + item * a)
                return np.frombuffer(raw, dtype, len(raw) // dtype.itemsize)
            buf = buffers.get(get_ident())
            if buf is None:
                buf = buffers[get_ident()] = np.empty(item * block_words, np.uint8)
            got = os.preadv(fd, [buf[:size]], start + item * a)
            return buf[:got - got % dtype.itemsize].view(dtype)

        def each(fn, n):
            """``[fn(b) for b in range(n)]``, on ``threads`` threads that each take the next block when done."""
            if threads < 2 or n < 2:
                return [fn(b) for b in range(n)]
            from .._compression import pool

            blocks, out = iter(range(n)), [None] * n

            def work():
                for b in blocks:  # a range iterator hands each block to one thread (its next holds the GIL)
                    out[b] = fn(b)

            for job in [pool().submit(work) for _ in range(min(threads, n))]:
                job.result()
            return out

        scans = each(lambda b: codec.scan(words_of(b)), n_blocks)
        starts, offs, toffs = [], [0], [0]
        cur = state.copy()
        for b, (n_ev, n_tr, stop, effect) in enumerate(scans):
            starts.append(cur.copy())
            codec.advance(cur, effect)
            offs.append(offs[-1] + n_ev)
            toffs.append(toffs[-1] + n_tr)
            if stop >= 0:  # nothing after a word of no type is read
                n_blocks = b + 1
                break
        if decode:
            out_bytes = 13 * offs[-1] + 10 * toffs[-1]
            require_memory(out_bytes, f"decoding the events of {path}")
            threads = threads_for(n_blocks, out_bytes)
        else:  # counting: no columns; the sensor the index counts on
            offs, toffs = [0] * (n_blocks + 1), [0] * (n_blocks + 1)
            width = height = 1 << 16
        t, x, y, p = (np.empty(offs[-1], np.int64), np.empty(offs[-1], np.uint16), np.empty(offs[-1], np.uint16),
                      np.empty(offs[-1], np.uint8))
        tt, tk, tch = np.empty(toffs[-1], np.int64), np.empty(toffs[-1], np.uint8), np.empty(toffs[-1], np.uint8)

        def decode_block(b):
            a0, a1, m0, m1 = offs[b], offs[b + 1], toffs[b], toffs[b + 1]
            words = words_of(b)
            if not decode and codec.time_range is not None:  # the counts are the scan's, the time range a cheaper
                n_ev, n_tr, stop, _ = scans[b]  # pass's, unless it cannot tell (EVT 3.0: x could pass 65535)
                timed = codec.time_range(words[:stop] if stop >= 0 else words, starts[b])
                if timed is not None:
                    return (n_ev, n_tr, ST_TYPE if stop >= 0 else ST_OK, stop), timed[0], timed[1], \
                        (int(words[stop]) if stop >= 0 else -1)
            res = codec.run(words, starts[b].copy(), width, height, decode, t[a0:a1], x[a0:a1], y[a0:a1],
                            p[a0:a1], tt[m0:m1], tk[m0:m1], tch[m0:m1])
            n, where = int(res[0]), int(res[3])
            lo, hi = (int(res[4]), int(res[5])) if n or not decode else (0, -1)
            return res[:4], lo, hi, (int(words[where]) if where >= 0 else -1)

        decoded = each(decode_block, n_blocks)
    finally:
        os.close(fd)
    status, bad, word, rows = ST_OK, -1, -1, []
    n_ev = n_tr = 0
    for b, ((n, m, st, where), lo, hi, at) in enumerate(decoded):
        rows.append((starts[b], n, m, lo, hi))
        n_ev, n_tr = offs[b] + n, toffs[b] + m
        if st != ST_OK:
            status, bad, word = st, b * block_words + where, at
            break
    return {"t": t[:n_ev], "x": x[:n_ev], "y": y[:n_ev], "p": p[:n_ev], "tt": tt[:n_tr], "tk": tk[:n_tr],
            "tch": tch[:n_tr], "status": status, "bad": bad, "word": word, "rows": rows}


# -- EVT 2.0 and DAT ---------------------------------------------------------------------------------------------


def _clock_effect(values: np.ndarray, half: int) -> tuple[int, int, int]:
    """A scan's effect on a counter's state: its first and last value (int64; -1 without any) and the wraps between
    them (drops of more than ``half``)."""
    if not len(values):
        return -1, -1, 0
    wraps = np.count_nonzero((values[1:] < values[:-1]) & (values[:-1] - values[1:] > half))
    return int(values[0]), int(values[-1]), int(wraps)


def _evt2_scan(words: np.ndarray) -> tuple[int, int, int, tuple[int, ...]]:
    """:class:`Codec` scan of EVT 2.0 words: the compiled kernel's (:func:`evtk._native.prophesee_scan`), else
    numpy's. Events are the CD words (0, 1) up to the first word of no type; the effect is the time highs'."""
    got = prophesee_scan("evt2", words)
    if got is not None:
        return got
    kind = words >> 28
    stop, _ = _first_stop(~((kind <= 1) | (kind == 8) | (kind == 10) | (kind >= 14)))
    if stop >= 0:
        words, kind = words[:stop], kind[:stop]
    highs = (words[kind == 8] & 0xFFFFFFF).astype(np.int64)
    return (int(np.count_nonzero(kind <= 1)), int(np.count_nonzero(kind == 10)), stop,
            _clock_effect(highs, EVT2_HALF))


def _dat_scan(words: np.ndarray) -> tuple[int, int, int, tuple[int, ...]]:
    """:class:`Codec` scan of DAT events (pairs of words): the compiled kernel's, else numpy's. Every event counts;
    the effect is the time stamps'."""
    got = prophesee_scan("dat", words)
    if got is not None:
        return got
    k = len(words) // 2
    return k, 0, -1, _clock_effect(words[0:2 * k:2].astype(np.int64), DAT_HALF)


def _clock_advance(state: np.ndarray, effect: tuple[int, ...], half: int) -> None:
    """Move a ``[last value, epoch]`` state on over words whose scan gave ``effect`` (:func:`_clock_effect`)."""
    first, last, wraps = effect
    if first >= 0:
        before = int(state[0])
        state[1] += int(first < before and before - first > half) + wraps
        state[0] = last


#: A drop of the EVT 2.0 time high (28 bits) or the DAT time stamp (32 bits) by more than this is a wrap.
EVT2_HALF, DAT_HALF = 1 << 27, 1 << 31

#: How :func:`read_whole` takes EVT 2.0 and DAT files (32-bit words; a DAT event is two).
EVT2_CODEC = Codec("<u4", 1, _evt2_scan, lambda state, effect: _clock_advance(state, effect, EVT2_HALF), _evt2_run)
DAT_CODEC = Codec("<u4", 2, _dat_scan, lambda state, effect: _clock_advance(state, effect, DAT_HALF), _dat_run)
