"""The decoders taken where evtk's compiled kernels are not (:mod:`evtk._native`): numpy's for EVT 2.0, DAT and
Event Stream, numba's loop for Event Stream's dense stretches and ATIS streams, and numba's for EVT 2.1, which has
no compiled kernel. :mod:`.decoders` loads this module on first use: a read through the compiled kernels (the
default where evtk's were built) never does, which spares a fresh process its code and numba's lazy decorator
(about 0.5 ms of a small file's read; issue 32, eighteenth round)."""

from __future__ import annotations

import numpy as np

from ..._lazyjit import njit  # numba loads when one of these loops is first called
from .decoders import (
    _DAT_EPOCH,
    _DAT_PREV,
    _E2_EPOCH,
    _E2_HIGH,
    _E21_LEGACY,
    _ES_LEFT,
    _ES_PHASE,
    _ES_POL,
    _ES_T,
    _ES_X,
    _ES_Y,
    ST_COORD,
    ST_FULL,
    ST_OK,
    ST_TYPE,
    _first_stop,
    _sliced,
)


@_sliced
def _evt2_numpy_run(words, state, width, height, decode, t, x, y, p, tt, tk, tch):
    """One pass over EVT 2.0 words, vectorised with numpy: counts, or with ``decode`` the events and triggers.
    Returns (events, triggers, status, word index of the problem, min t, max t of the events). ``state`` (time
    high, epoch) carries over from the block before and is updated.

    Every word is 32 bits with its type in the top four: CD_OFF/CD_ON (0, 1) hold x in bits 11..21, y in
    0..10 and the six low time bits in 22..27; EV_TIME_HIGH (8) bits 6..33 of the time in its 28 low bits (a
    drop of more than half their range is a wrap: the epoch counts them); EXT_TRIGGER (10) the edge in bit 0
    and the channel in bits 8..12; OTHERS and CONTINUED (14, 15) carry no events. Decoding stops at the
    first word of another type (ST_TYPE) or the first event off the sensor (ST_COORD)."""
    words = np.asarray(words)
    kind = words >> 28
    cd = kind <= 1
    xs = (words >> 11) & 0x7FF
    ys = words & 0x7FF
    known = cd | (kind == 8) | (kind == 10) | (kind >= 14)
    bad, which = _first_stop(cd & ((xs >= width) | (ys >= height)), ~known)
    status = ST_OK if bad < 0 else (ST_COORD, ST_TYPE)[which]
    if bad >= 0:
        words, kind, cd, xs, ys = words[:bad], kind[:bad], cd[:bad], xs[:bad], ys[:bad]
    high, epoch = int(state[_E2_HIGH]), int(state[_E2_EPOCH])
    is_high = kind == 8
    new = (words[is_high] & 0xFFFFFFF).astype(np.int64)
    if len(new):
        before = np.concatenate(([high], new[:-1]))
        epochs = epoch + np.cumsum((new < before) & (before - new > (1 << 27)))
        state[_E2_HIGH], state[_E2_EPOCH] = new[-1], epochs[-1]
        # the time base of each word: the last time-high word at or before it (the block's start state first)
        bases = np.concatenate(([(epoch << 34) | (high << 6)], (epochs << 34) | (new << 6)))
        ordinal = np.cumsum(is_high)
    else:
        bases, ordinal = np.array([(epoch << 34) | (high << 6)], np.int64), None
    at = np.flatnonzero(cd)
    n = len(at)
    tc = bases[ordinal[at]] if ordinal is not None else np.full(n, bases[0])
    tc |= (words[at] >> 22) & 0x3F
    trig = np.flatnonzero(kind == 10)
    m = len(trig)
    if decode:
        t[:n] = tc
        x[:n] = xs[at]
        y[:n] = ys[at]
        p[:n] = kind[at]
        if m:
            wt = words[trig]
            tt[:m] = (bases[ordinal[trig]] if ordinal is not None else bases[0]) | ((wt >> 22) & 0x3F)
            tk[:m] = np.where(wt & 1, 1, 2)  # kind 1 rising, 2 falling (evtk's Triggers)
            tch[:m] = (wt >> 8) & 0x1F
    return n, m, status, bad, (int(tc.min()) if n else 2**62), (int(tc.max()) if n else -(2**62))


_LOW32 = np.uint64(0xFFFFFFFF)
_SHIFT32 = np.uint64(32)
# a set bit's index from the bit alone, by a de Bruijn sequence: (bit * _DEBRUIJN) mod 2**32 has a distinct top five
# bits for each of the 32 bits
_DEBRUIJN = 0x077CB531
_BIT_INDEX = np.zeros(32, np.int64)
_BIT_INDEX[[((1 << k) * _DEBRUIJN & 0xFFFFFFFF) >> 27 for k in range(32)]] = np.arange(32)


@njit(cache=True, nogil=True)
def _evt21_run(words, state, width, height, decode, t, x, y, p, tt, tk, tch):
    """One pass over EVT 2.1 words (uint64): counts, or with ``decode`` the events and triggers. Returns (events,
    triggers, status, word index of the problem, min t, max t); the min and max only when counting.

    A word's upper half (by the layout in ``state``) is an EVT 2.0 word (:func:`_evt2_run`'s types and time
    rules) whose CD types carry the base x of 32 pixels, its lower half their validity mask (bit k: the pixel at
    base x + k). A CD word whose events no longer fit the outputs stops with ST_FULL, for the caller to resume
    at it."""
    high = state[_E2_HIGH]
    epoch = state[_E2_EPOCH]
    legacy = state[_E21_LEGACY] != 0
    base = (epoch << 34) | (high << 6)
    n = 0
    m = 0
    t_min = np.int64(2**62)
    t_max = np.int64(-(2**62))
    status = ST_OK
    bad = -1
    for i in range(len(words)):
        if legacy:
            w = np.int64(words[i] & _LOW32)
            mask = np.int64(words[i] >> _SHIFT32)
        else:
            w = np.int64(words[i] >> _SHIFT32)
            mask = np.int64(words[i] & _LOW32)
        kind = w >> 28
        if kind <= 1:  # CD_OFF / EV_NEG, CD_ON / EV_POS: most words
            if decode and n + 32 > len(t):
                status = ST_FULL
                bad = i
                break
            yi = w & 0x7FF
            first = (w >> 11) & 0x7FF
            tc = base | ((w >> 22) & 0x3F)
            while mask:  # the set bits, lowest first
                low = mask & -mask
                mask ^= low
                xi = first + _BIT_INDEX[((low * _DEBRUIJN) & 0xFFFFFFFF) >> 27]
                if xi >= width or yi >= height:
                    status = ST_COORD
                    break
                if decode:
                    t[n] = tc
                    x[n] = xi
                    y[n] = yi
                    p[n] = kind
                else:
                    t_min = min(t_min, tc)
                    t_max = max(t_max, tc)
                n += 1
            if status != ST_OK:
                bad = i
                break
        elif kind == 8:
            new = w & 0xFFFFFFF
            if new < high and high - new > (1 << 27):  # the 28-bit counter wrapped
                epoch += 1
            high = new
            base = (epoch << 34) | (high << 6)
        elif kind == 10:
            if decode:
                tt[m] = base | ((w >> 22) & 0x3F)
                # the edge in bit 0, the channel in bits 8..12: kind 1 rising, 2 falling (evtk's Triggers)
                tk[m] = 1 if (w & 1) else 2
                tch[m] = (w >> 8) & 0x1F
            m += 1
        elif kind != 14 and kind != 15:  # OTHERS and CONTINUED carry no events; no other type exists
            status = ST_TYPE
            bad = i
            break
    state[_E2_HIGH] = high
    state[_E2_EPOCH] = epoch
    return n, m, status, bad, t_min, t_max


def _dat_numpy_run(raw, state, width, height, decode, t, x, y, p, tt, tk, tch):
    """One pass over DAT CD events (pairs of uint32: time stamp, data), vectorised, with :func:`_evt2_run`'s
    arguments and results (DAT files hold no triggers). The data word holds x in bits 0..13, y in 14..27 and
    the polarity in 28..31 (any bit set: ON); a time stamp more than half the 32-bit range below the one
    before is a wrap of the counter."""
    raw = np.asarray(raw)
    k = len(raw) // 2
    ts = raw[0:2 * k:2].astype(np.int64)
    d = raw[1:2 * k:2]
    xs = d & 0x3FFF
    ys = (d >> 14) & 0x3FFF
    bad, _ = _first_stop((xs >= width) | (ys >= height))
    status = ST_OK if bad < 0 else ST_COORD
    prev, epoch = int(state[_DAT_PREV]), int(state[_DAT_EPOCH])
    seen = ts if bad < 0 else ts[:bad + 1]  # the event off the sensor still moves the clock, as it is read
    if len(seen):
        before = np.concatenate(([prev], seen[:-1]))
        epochs = epoch + np.cumsum((seen < before) & (before - seen > (1 << 31)))
        state[_DAT_PREV], state[_DAT_EPOCH] = seen[-1], epochs[-1]
    else:
        epochs = np.zeros(0, np.int64)
    n = k if bad < 0 else bad
    tc = (epochs[:n] << 32) | ts[:n]
    if decode:
        t[:n] = tc
        x[:n] = xs[:n]
        y[:n] = ys[:n]
        np.not_equal(d[:n] >> 28, 0, out=p[:n].view(np.bool_))
    return n, 0, status, bad, (int(tc.min()) if n else 2**62), (int(tc.max()) if n else -(2**62))


_dat_numpy_run = _sliced(_dat_numpy_run, words_per_item=2)


@njit(cache=True, nogil=True)
def _es_loop(data, state, width, height, decode, atis, t, x, y, p):
    """One pass over Event Stream 2.x bytes, DVS or (``atis``) ATIS, one byte at a time.

    DVS: 0xFF adds 127 us, 0xFE is a reset (nothing), any other first byte adds its top seven bits to the time
    and gives the polarity in bit 0. ATIS: 0xFC is a reset, 0xFD to 0xFF add 63 us times their two low bits, any
    other first byte adds its top six bits to the time and gives the polarity in bit 1 and the threshold-crossing
    flag in bit 0. Four bytes follow (x, then y counted from the bottom row, little-endian). An ATIS threshold
    crossing (half an exposure measurement) is checked against the sensor like an event, then counted in
    ``state[_ES_LEFT]`` and left out. :func:`_evt2_run`'s results (no triggers); ``state`` carries over between
    blocks."""
    tc = state[_ES_T]
    phase = state[_ES_PHASE]
    xi = state[_ES_X]
    yi = state[_ES_Y]
    flags = state[_ES_POL]
    left = state[_ES_LEFT]
    n = 0
    t_min = np.int64(2**62)
    t_max = np.int64(-(2**62))
    for i in range(len(data)):
        b = np.int64(data[i])
        if phase == 0:
            if atis and b >= 0xFC:
                tc += 63 * (b & 3)
            elif atis:
                tc += b >> 2
                flags = b & 3
                phase = 1
            elif b == 0xFF:
                tc += 127
            elif b != 0xFE:
                tc += b >> 1
                flags = b & 1
                phase = 1
        elif phase == 1:
            xi = b
            phase = 2
        elif phase == 2:
            xi |= b << 8
            phase = 3
        elif phase == 3:
            yi = b
            phase = 4
        else:
            yi |= b << 8
            phase = 0
            if xi >= width or yi >= height:
                state[_ES_T] = tc
                state[_ES_PHASE] = phase
                state[_ES_LEFT] = left
                return n, 0, ST_COORD, i, t_min, t_max
            if atis and flags & 1:
                left += 1
                continue
            if decode:
                t[n] = tc
                x[n] = xi
                y[n] = height - 1 - yi  # stored from the bottom row up; evtk counts y down
                p[n] = flags >> 1 if atis else flags
            n += 1
            if tc < t_min:
                t_min = tc
            if tc > t_max:
                t_max = tc
    state[_ES_T] = tc
    state[_ES_PHASE] = phase
    state[_ES_X] = xi
    state[_ES_Y] = yi
    state[_ES_POL] = flags
    state[_ES_LEFT] = left
    return n, 0, ST_OK, -1, t_min, t_max


def _es_dvs_run(data, state, width, height, decode, t, x, y, p, tt, tk, tch):
    """Event Stream 2.x DVS bytes through numba's loop (:func:`_es_loop`): :func:`_evt2_run`'s arguments and
    results (no triggers)."""
    return _es_loop(data, state, width, height, decode, False, t, x, y, p)


def _es_atis_run(data, state, width, height, decode, t, x, y, p, tt, tk, tch):
    """Event Stream 2.x ATIS bytes through numba's loop (:func:`_es_loop`): change detections as events,
    threshold crossings counted and left out."""
    return _es_loop(data, state, width, height, decode, True, t, x, y, p)


#: Event Stream slices with more bytes of 0xFE or 0xFF than this fraction (long silences: one 0xFF per 127 us
#: without events) go to :func:`_es_dvs_run`: the numpy decoder takes a Python step per run of such bytes.
ES_MARKER_SHARE = 1 / 64


def _es_dvs_np(data, state, width, height, decode, t, x, y, p, tt, tk, tch):
    """:func:`_es_dvs_run` with numpy: the same arguments, results and state. An event's five bytes start at a
    byte below 0xFE read where an event may start; a 0xFF there adds 127 us, a 0xFE nothing. The starts are found
    a stride of five at a time between such bytes, then the times are one cumulative sum over the events and the
    0xFF bytes between them, the coordinates one gather. Bytes that complete an event begun in the slice before,
    and the last few of the slice, go byte by byte. Slices dense in 0xFE/0xFF bytes go to :func:`_es_dvs_run`."""
    # bisect's C half (the module bisect itself is 0.1 ms more), loaded here: a shared library to load (0.4 ms of a
    # fresh process) that a read through the compiled kernel never uses
    from _bisect import bisect_left

    data = np.asarray(data)
    nb = len(data)
    hi = np.flatnonzero(data >= 0xFE)  # every 0xFE/0xFF byte of the slice (few, or the numba loop takes it)
    if len(hi) > ES_MARKER_SHARE * nb:
        return _es_dvs_run(data, state, width, height, decode, t, x, y, p, tt, tk, tch)
    st = [int(v) for v in state]  # _ES_T, _ES_PHASE, _ES_X, _ES_Y, _ES_POL
    t_min, t_max = 2**62, -(2**62)
    n = 0

    def step(i0, i1):
        """Bytes i0..i1 one at a time (at most a few); returns (status, index) of an event off the sensor."""
        nonlocal n, t_min, t_max
        for i in range(i0, i1):
            b = int(data[i])
            ph = st[_ES_PHASE]
            if ph == 0:
                if b == 0xFF:
                    st[_ES_T] += 127
                elif b != 0xFE:
                    st[_ES_T] += b >> 1
                    st[_ES_POL] = b & 1
                    st[_ES_PHASE] = 1
            elif ph == 1:
                st[_ES_X], st[_ES_PHASE] = b, 2
            elif ph == 2:
                st[_ES_X] |= b << 8
                st[_ES_PHASE] = 3
            elif ph == 3:
                st[_ES_Y], st[_ES_PHASE] = b, 4
            else:
                st[_ES_Y] |= b << 8
                st[_ES_PHASE] = 0
                if st[_ES_X] >= width or st[_ES_Y] >= height:
                    return ST_COORD, i
                if decode:
                    t[n], x[n], y[n], p[n] = st[_ES_T], st[_ES_X], height - 1 - st[_ES_Y], st[_ES_POL]
                n += 1
                t_min, t_max = min(t_min, st[_ES_T]), max(t_max, st[_ES_T])
        return ST_OK, -1

    def finish(status, bad, keep_xyp):
        state[_ES_T], state[_ES_PHASE] = st[_ES_T], st[_ES_PHASE]
        if keep_xyp:
            state[_ES_X], state[_ES_Y], state[_ES_POL] = st[_ES_X], st[_ES_Y], st[_ES_POL]
        return n, 0, status, bad, t_min, t_max

    cur = 0
    if st[_ES_PHASE]:  # the end of an event the slice before began
        cur = min(nb, 5 - st[_ES_PHASE])
        status, bad = step(0, cur)
        if status != ST_OK:
            return finish(status, bad, False)
    # the items from ``cur``: event starts and runs of 0xFE/0xFF bytes, in order. Every such byte of the slice
    # (few: ES_MARKER_SHARE), the end of the run each one is in, and by position modulo 5 (the grid of starts)
    cut = np.flatnonzero(np.diff(hi) != 1)
    run_end = np.append(hi[cut] + 1, hi[-1:] + 1)[np.concatenate(([0], np.cumsum(np.diff(hi) != 1)))] \
        if len(hi) else hi
    hi_list = hi.tolist()
    on_grid = [hi[hi % 5 == k].tolist() for k in range(5)]
    starts, ends, runs = [], [], []  # event starts: range(starts[i], ends[i], 5), run i of such bytes after it
    while cur + 5 <= nb:
        grid = on_grid[cur % 5]
        k = bisect_left(grid, cur)
        q = grid[k] if k < len(grid) else nb  # the first such byte where an event may start
        if q + 5 > nb:  # none before the slice's last whole event: events to there
            q = cur + 5 * ((nb - cur) // 5)
            starts.append(cur)
            ends.append(q)
            cur = q
            break
        starts.append(cur)
        ends.append(q)
        j = bisect_left(hi_list, q)
        r = int(run_end[j])  # the run of such bytes from q, each read where an event may start
        runs.append(hi[j:j + r - q])
        cur = r
    ff = np.concatenate(runs) if runs else np.zeros(0, np.int64)
    ff = ff[data[ff] == 0xFF]
    counts = [(e - a) // 5 for a, e in zip(starts, ends)]
    m = sum(counts)
    if m:
        # every event's five bytes, one row each: the ranges' own rows (views) joined
        rec = np.concatenate([data[a:e].reshape(-1, 5) for a, e in zip(starts, ends)])
        xy = rec[:, 1:5].view("<u2")  # x and y, little-endian 16 bits each (a view)
        xs, ys = xy[:, 0], xy[:, 1]
        # times: one cumulative sum, straight into the time column, of every event's increment, with the start
        # state's time and 127 for every 0xFF between two ranges added at the first event after them (the times
        # never go back, so the first and last are the least and greatest)
        tcs = t[n:n + m] if decode else np.empty(m, np.int64)
        np.right_shift(rec[:, 0], 1, out=tcs)
        tcs[0] += st[_ES_T]
        ff_after = len(ff)  # 0xFF bytes after the last event: they move the clock of the slice after
        if len(ff):
            cn = np.asarray(counts)
            kept = cn > 0  # ranges with events (one may be empty: a run right where the one before ends)
            before = np.searchsorted(ff, np.asarray(starts)[kept])  # 0xFF bytes before each such range
            tcs[(np.cumsum(cn) - cn)[kept]] += 127 * np.diff(before, prepend=0)
            ff_after -= int(before[-1])
        np.cumsum(tcs, out=tcs)
        if int(xs.max()) >= width or int(ys.max()) >= height:  # two reductions: cheaper than the mask below
            off = (xs >= np.uint32(width)) | (ys >= np.uint32(height))
            k = int(np.argmax(off))  # the clock moves to the event off the sensor (and the 0xFF bytes before it)
            st[_ES_T] = int(tcs[k])
            st[_ES_PHASE] = 0
            if decode:
                x[n:n + k] = xs[:k]
                np.subtract(height - 1, ys[:k], out=y[n:n + k], casting="unsafe")
                np.bitwise_and(rec[:k, 0], 1, out=p[n:n + k])
            if k:
                t_min, t_max = min(t_min, int(tcs[0])), max(t_max, int(tcs[k - 1]))
            n += k
            i = int(np.searchsorted(np.cumsum(counts), k, side="right"))  # the range of event k
            return finish(ST_COORD, starts[i] + 5 * (k - sum(counts[:i])) + 4, False)
        if decode:
            x[n:n + m] = xs
            np.subtract(height - 1, ys, out=y[n:n + m], casting="unsafe")
            np.bitwise_and(rec[:, 0], 1, out=p[n:n + m])
        t_min, t_max = min(t_min, int(tcs[0])), max(t_max, int(tcs[-1]))
        n += m
        st[_ES_X], st[_ES_Y], st[_ES_POL] = int(xs[-1]), int(ys[-1]), int(rec[-1, 0] & 1)
        st[_ES_T] = int(tcs[-1]) + 127 * ff_after
    else:
        st[_ES_T] += 127 * len(ff)
    status, bad = step(cur, nb)  # the last bytes: a few 0xFE/0xFF, an event cut by the slice's end
    return finish(status, bad, status == ST_OK)


#: Event Stream bytes each numpy pass takes (a whole block): the times go straight into the column, so a slice's
#: temporaries are about twice its bytes; 64 KiB slices took 25-30 % longer on the real files (a slice's fixed cost).
ES_SLICE_BYTES = 1 << 18

_es_np_run = _sliced(_es_dvs_np, slice_words=lambda: ES_SLICE_BYTES)
