"""Prophesee EVT 3.0 decoding: a slice decoder whose state carries from slice to slice (numpy, or the compiled
kernel where evtk's were built), and the scan and state update with which a whole read decodes its blocks on the
reader's threads (:data:`CODEC`, for :func:`evtk.io.prophesee._whole.read_whole`).

EVT 3.0 is 16-bit words, the type in the top four bits. EVT_ADDR_Y (0) sets y; EVT_ADDR_X (2) is one event at
its x with its polarity (bit 11); VECT_BASE_X (3) sets the x and polarity of the vectors after it; VECT_12 (4)
and VECT_8 (5) are events at base x + k for each set bit k of their 12 or 8 low bits, and move the base on by 12
or 8; EVT_TIME_LOW (6) and EVT_TIME_HIGH (8) set bits 0..11 and 12..23 of the time (a time high more than half
its range below the one before is a wrap of the 24-bit time: the epoch counts them); EXT_TRIGGER (10) holds the
edge in bit 0 and the channel in bits 8..11; 7, 14 and 15 carry no events; 1, 9, 11, 12 and 13 are no type.

Everything a word needs from the words before it (y, time, base x, polarity) is the value of the last word of
one type before it, plus, for the base, the vector steps since. So a block's state at its start follows from a
cheap scan of the blocks before it (:func:`scan`: their last words of each type, their time-high wraps and their
event counts), and the blocks then decode independently (the kernel, and numpy in its array operations, release
the GIL).
"""

from __future__ import annotations

import numpy as np

from ..._native import evt3_run as native_evt3_run
from ..._native import prophesee_scan
from ._whole import Codec
from .decoders import _NATIVE_STATUS, ST_COORD, ST_FULL, ST_OK, ST_TYPE, _sliced

#: Words each numpy pass takes at a time: its temporaries take some 40 bytes a word (a thread's whole working
#: memory about 5 MiB whatever the file). 32 K-word slices kept them in a core's cache, but each numpy call
#: releases and takes back the GIL, and with two threads those hand-overs made a read spend half again the CPU
#: time of one thread (two cores read 20 M events slower than one); 128 K words take a quarter of the calls.
SLICE_WORDS = 1 << 17
# decoder state (int64 arrays, updated in place): time high, time low, epoch (wraps of the 24-bit time), y,
# vector base x, polarity
E3_HIGH, E3_LOW, E3_EPOCH, E3_Y, E3_BASE, E3_POL = range(6)
#: Set bits of each 12-bit value (the events of a vector word): the values below 2**(k+1) are those below 2**k,
#: then the same with bit k set.
_POP12 = np.zeros(1, np.uint8)
for _ in range(12):
    _POP12 = np.concatenate((_POP12, _POP12 + 1))
_BITS: np.ndarray | None = None  # per 12-bit value, its set bits in order (row of 12), made when first needed


def _bits() -> np.ndarray:
    """The table of set-bit positions: row ``v`` holds the set bits of ``v``, lowest first (then zeros)."""
    global _BITS
    if _BITS is None:
        on = (np.arange(4096)[:, None] >> np.arange(12)) & 1
        table = np.zeros((4096, 12), np.uint8)
        rows, cols = np.nonzero(on)
        table[rows, np.arange(len(rows)) - (np.cumsum(_POP12, dtype=np.intp) - _POP12)[rows]] = cols
        _BITS = table.reshape(-1)
    return _BITS


def _first(mask: np.ndarray) -> int:
    """Index of the first nonzero of ``mask``, or -1."""
    i = int(np.argmax(mask)) if len(mask) else 0
    return i if len(mask) and mask[i] else -1


def _unknown_at(kind: np.ndarray) -> int:
    """Index of the first word of no EVT 3.0 type (1, 9, 11, 12, 13), or -1 (``kind``: the words' types)."""
    bad = (kind == 1) | (kind == 9) | ((kind - np.uint16(11)) < 3)
    return _first(bad) if bad.any() else -1


def _highs_epochs(highs: np.ndarray, high: int, epoch: int) -> np.ndarray:
    """The epoch after each time-high value in ``highs`` (int64), from the time high and epoch before them."""
    prev = np.empty(len(highs), np.int64)
    if len(highs):
        prev[0] = high
        prev[1:] = highs[:-1]
    return epoch + np.cumsum((highs < prev) & (prev - highs > 2048))


def _fill(values: np.ndarray, setters: np.ndarray, at: np.ndarray, n_words: int) -> np.ndarray:
    """``values[k]`` for each word position in ``at``, ``k`` the number of ``setters`` (sorted positions, none in
    ``at``) before it: a value set by a word, in effect until the next. Few setters: each value repeated over
    the words of its run; many: their running count (a repeat costs some 15 ns a run)."""
    if 8 * len(setters) <= len(at):
        counts = np.diff(np.searchsorted(at, setters), prepend=0, append=len(at))
        return np.repeat(values, counts)
    is_set = np.zeros(n_words, bool)
    is_set[setters] = True
    return values.take(np.cumsum(is_set, dtype=np.int32)[at])


#: The time high with its epoch (epoch << 12 | high) below which it packs with time low and y into an int64.
_H_LIMIT = 1 << 40


def _put_changes(packed: np.ndarray, at: np.ndarray, values: np.ndarray, before: int, shift: int) -> None:
    """Write into ``packed`` at the positions ``at`` each value's change from the one before (``before`` first),
    shifted left by ``shift``: their running sum is then the value in effect."""
    if len(values):
        v = values.astype(np.int64)
        d = np.empty_like(v)
        d[0] = v[0] - before
        np.subtract(v[1:], v[:-1], out=d[1:])  # in int64: a uint16 operand would take numpy's slow casting loop
        if shift:
            np.left_shift(d, shift, out=d)
        packed[at] = d


def _core(words, state, width, height, decode, t, x, y, p, tt, tk, tch):
    """One pass over EVT 3.0 words (uint16): counts, or with ``decode`` the events and triggers. ``state``
    (:data:`E3_HIGH` ...) carries over from the words before and is updated to the state after the words decoded.
    Returns (events, triggers, status, word index of the problem, min t, max t).

    Decoding stops at a word of no type (ST_TYPE), at the first event off the sensor (ST_COORD: the events of
    that word before it are kept) or, decoding, at the first event word whose events no longer fit ``t``, or
    trigger that no longer fits ``tt`` (ST_FULL, for the caller to resume at it)."""
    w = np.asarray(words).astype(np.uint16, copy=False)
    kind = w >> 12
    status, stop = ST_OK, _unknown_at(kind)
    if stop >= 0:
        status, w, kind = ST_TYPE, w[:stop], kind[:stop]
    n_words = len(w)
    is_vec = (kind - np.uint16(4)) < 2  # the vector words (types 4 and 5)
    has_vec = bool(is_vec.any())
    e = np.flatnonzero((kind == 2) | is_vec if has_vec else kind == 2)  # the event words (types 2, 4 and 5)
    we = w[e]
    if has_vec:
        ke = we >> 12
        is_xe = ke == 2
        mask_e = np.where(is_xe, 1, np.where(ke == 4, we & 0xFFF, we & 0xFF))
        cnt_e = _POP12[mask_e]
        n_all = int(cnt_e.sum(dtype=np.int64))
    else:
        n_all = len(e)
    is_tr = kind == 10
    n_tr = int(np.count_nonzero(is_tr))
    if decode and (n_all > len(t) or n_tr > len(tt)):
        full = n_words
        if n_all > len(t):
            over = np.cumsum(cnt_e, dtype=np.int64) > len(t) if has_vec else np.arange(1, len(e) + 1) > len(t)
            full = int(e[_first(over)])
        if n_tr > len(tt):
            full = min(full, int(np.flatnonzero(is_tr)[len(tt)]))
        res = _core(w[:full], state, width, height, decode, t, x, y, p, tt, tk, tch)
        return res if res[2] != ST_OK else (res[0], res[1], ST_FULL, full, res[4], res[5])
    # y and time in effect at each event word: the values of the last words before it that set them (else the
    # state's), packed as H << 23 | low << 11 | y (H = epoch << 12 | high) and carried by one running sum of their
    # changes, a word at a time: t = packed >> 11
    at_hi = np.flatnonzero(kind == 8)
    highs = w[at_hi].astype(np.int64) & 0xFFF
    hv = np.empty(len(highs) + 1, np.int64)
    hv[0] = (int(state[E3_EPOCH]) << 12) | int(state[E3_HIGH])
    hv[1:] = (_highs_epochs(highs, int(state[E3_HIGH]), int(state[E3_EPOCH])) << 12) | highs
    packed = np.zeros(n_words, np.int64)
    at_y = np.flatnonzero(kind == 0)
    _put_changes(packed, at_y, w[at_y] & 0x7FF, int(state[E3_Y]), 0)
    at_lo = np.flatnonzero(kind == 6)
    _put_changes(packed, at_lo, w[at_lo] & 0xFFF, int(state[E3_LOW]), 11)
    whole = int(hv[-1]) < _H_LIMIT  # else the time high's part is added apart (2**27 wraps of the 24-bit time)
    if whole:
        _put_changes(packed, at_hi, hv[1:], int(hv[0]), 23)
    if n_words:
        packed[0] += (int(hv[0]) << 23 if whole else 0) | (int(state[E3_LOW]) << 11) | int(state[E3_Y])
    np.cumsum(packed, out=packed)

    def time_at(pos):
        """The times in effect at the word positions ``pos`` (sorted)."""
        if whole:
            return packed[pos] >> 11
        return (_fill(hv, at_hi, pos, n_words) << 12) | ((packed[pos] >> 11) & 0xFFF)

    pk = packed[e]
    n = len(e)
    done = n_words  # the words whose effects stand: those before the stop
    if not has_vec:  # one event a word (EVT_ADDR_X): written straight into the outputs when decoding
        if decode:
            et, ex, ey = t[:n], x[:n], y[:n]
            np.right_shift(pk, 11, out=et) if whole else np.copyto(et, time_at(e))
            np.bitwise_and(pk, 0x7FF, out=ey, casting="unsafe")
            np.bitwise_and(we, 0x7FF, out=ex)
            np.bitwise_and(we >> 11, 1, out=p[:n], casting="unsafe")
        else:
            et, ex, ey = (pk >> 11 if whole else time_at(e)), we & 0x7FF, pk & 0x7FF
        if n and (int(ex.max()) >= width or int(ey.max()) >= height):
            bad = _first((ex >= width) | (ey >= height))
            if bad >= 0:
                n, status = bad, ST_COORD
                stop = done = int(e[bad])
        et = et[:n]
    else:
        bpos = np.flatnonzero(kind == 3)
        t_e = pk >> 11 if whole else time_at(e)
        y_e = (pk & 0x7FF).astype(np.uint16)
        # vector base x and polarity: the last VECT_BASE_X word's, moved on by the vectors since
        steps_e = np.where(ke == 4, 12, np.where(ke == 5, 8, 0))
        moved_e = np.cumsum(steps_e) - steps_e  # the vector steps in the slice before each event word
        kb = _fill(np.arange(len(bpos) + 1), bpos, e, n_words)  # base words before each event word
        bval = np.empty(len(bpos) + 1, np.int64)
        bval[0] = state[E3_BASE]
        bval[1:] = w[bpos] & 0x7FF
        bpol = np.empty(len(bpos) + 1, np.uint8)
        bpol[0] = state[E3_POL]
        bpol[1:] = (w[bpos] >> 11) & 1
        moved_b = np.zeros(len(bpos) + 1, np.int64)  # the steps before each base word (only its users read it)
        firsts = np.flatnonzero(np.diff(kb, prepend=-1))
        moved_b[kb[firsts]] = moved_e[firsts]
        moved_b[0] = 0
        xw = np.where(is_xe, we & 0x7FF, bval[kb] + moved_e - moved_b[kb])
        pw = np.where(is_xe, (we >> 11) & 1, bpol[kb]).astype(np.uint8)
        rows = np.repeat(np.arange(len(e)), cnt_e)
        first_ev = np.cumsum(cnt_e, dtype=np.intp) - cnt_e
        ex = xw[rows] + _bits()[mask_e[rows].astype(np.intp) * 12 + (np.arange(len(rows)) - first_ev[rows])]
        ey = y_e[rows]
        n = len(ex)
        bad = _first((ex >= width) | (ey >= height))
        if bad >= 0:
            n, status = bad, ST_COORD
            stop = done = int(e[rows[bad]])
        et = t_e[rows[:n]]
        if decode:
            t[:n] = et
            x[:n] = ex[:n]
            y[:n] = ey[:n]
            p[:n] = pw[rows[:n]]
    trig = np.flatnonzero(is_tr[:done]) if n_tr else e[:0]
    m = len(trig)
    if decode and m:
        wt = w[trig]
        tt[:m] = time_at(trig)
        tk[:m] = np.where(wt & 1, 1, 2)
        tch[:m] = (wt >> 8) & 0xF
    if done:  # the state after the words decoded
        last = int(packed[done - 1])
        state[E3_Y], state[E3_LOW] = last & 0x7FF, (last >> 11) & 0xFFF
        h = int(hv[np.searchsorted(at_hi, done)])
        state[E3_EPOCH], state[E3_HIGH] = h >> 12, h & 0xFFF
        if has_vec:
            nb = int(np.searchsorted(bpos, done))  # base words before the stop
            since = int(bpos[nb - 1]) if nb else -1
        else:
            since = _last(kind[:done], 3)
        if since >= 0:
            state[E3_BASE], state[E3_POL] = int(w[since]) & 0x7FF, (int(w[since]) >> 11) & 1
        if has_vec:
            a, b = np.searchsorted(e, since, side="right"), np.searchsorted(e, done)
            state[E3_BASE] += int(steps_e[a:b].sum())
    return n, m, status, (stop if status != ST_OK else -1), (int(et.min()) if n else 2**62), \
        (int(et.max()) if n else -(2**62))


#: Decode or count EVT 3.0 words with numpy :data:`SLICE_WORDS` at a time (temporaries in the cache), the state
#: carried from slice to slice: :func:`_core`'s arguments and results, over all the words.
_numpy_run = _sliced(_core, slice_words=lambda: SLICE_WORDS)


def run(words, state, width, height, decode, t, x, y, p, tt, tk, tch):
    """Decode or count EVT 3.0 words: :func:`_core`'s arguments and results, over all the words.

    Where evtk's compiled kernels were built (:func:`evtk._native.evt3_run`), one call decodes the words a word at
    a time without the GIL (some 2-4 ns a word against numpy's 14-17, and threads decoding blocks run at once);
    else numpy, :data:`SLICE_WORDS` at a time. The results are the same.
    """
    got = native_evt3_run(words, state, width, height, decode, t, x, y, p, tt, tk, tch, _NATIVE_STATUS)
    if got is not None:
        return got
    return _numpy_run(words, state, width, height, decode, t, x, y, p, tt, tk, tch)


def _scan_slice(w: np.ndarray) -> tuple[int, int, int, tuple[int, ...]]:
    """:func:`scan` of one slice."""
    kind = w >> 12
    stop = _unknown_at(kind)
    if stop >= 0:
        w, kind = w[:stop], kind[:stop]
    n_x = int(np.count_nonzero(kind == 2))
    v12 = np.compress(kind == 4, w) & 0xFFF
    v8 = np.compress(kind == 5, w) & 0xFF
    n_ev = n_x + int(_POP12[v12].sum(dtype=np.int64)) + int(_POP12[v8].sum(dtype=np.int64))
    n_tr = int(np.count_nonzero(kind == 10))
    at_y, at_low, at_base = _last(kind, 0), _last(kind, 6), _last(kind, 3)
    highs = np.compress(kind == 8, w).astype(np.int64) & 0xFFF
    wraps = int(_highs_epochs(highs[1:], int(highs[0]), 0)[-1]) if len(highs) > 1 else 0
    steps = 0
    if len(v12) or len(v8):
        rest = kind[at_base + 1:]
        steps = 12 * int(np.count_nonzero(rest == 4)) + 8 * int(np.count_nonzero(rest == 5))
    effect = (int(w[at_y]) & 0x7FF if at_y >= 0 else -1, int(w[at_low]) & 0xFFF if at_low >= 0 else -1,
              int(highs[0]) if len(highs) else -1, int(highs[-1]) if len(highs) else -1, wraps,
              int(w[at_base]) & 0xFFF if at_base >= 0 else -1, steps)
    return n_ev, n_tr, stop, effect


def _then(a: tuple[int, ...], b: tuple[int, ...]) -> tuple[int, ...]:
    """The effect of words with effect ``a`` followed by words with effect ``b`` (see :func:`scan`)."""
    y_a, low_a, first_a, last_a, wraps_a, base_a, steps_a = a
    y_b, low_b, first_b, last_b, wraps_b, base_b, steps_b = b
    wraps = wraps_a + wraps_b + int(last_a >= 0 and first_b >= 0 and first_b < last_a and last_a - first_b > 2048)
    return (y_b if y_b >= 0 else y_a, low_b if low_b >= 0 else low_a, first_a if first_a >= 0 else first_b,
            last_b if last_b >= 0 else last_a, wraps, base_b if base_b >= 0 else base_a,
            steps_b if base_b >= 0 else steps_a + steps_b)


def scan(words) -> tuple[int, int, int, tuple[int, ...]]:
    """Count the events and triggers of EVT 3.0 words without decoding them, and sum up their effect on the
    decoder's state (up to any word of no type): ``(events, triggers, index of a word of no type or -1, effect)``
    (``effect`` for :func:`advance`). Events off the sensor are counted (the decoder finds them). The compiled
    kernel takes all the words in one call (:func:`evtk._native.prophesee_scan`); numpy :data:`SLICE_WORDS` at a
    time."""
    got = prophesee_scan("evt3", words)
    if got is not None:
        return got
    w = np.asarray(words).astype(np.uint16, copy=False)
    n_ev = n_tr = 0
    effect: tuple[int, ...] = (-1, -1, -1, -1, 0, -1, 0)
    for a in range(0, len(w), SLICE_WORDS):
        k, j, stop, part = _scan_slice(w[a:a + SLICE_WORDS])
        n_ev, n_tr, effect = n_ev + k, n_tr + j, _then(effect, part)
        if stop >= 0:
            return n_ev, n_tr, a + stop, effect
    return n_ev, n_tr, -1, effect


def advance(state: np.ndarray, effect: tuple[int, ...]) -> None:
    """Move ``state`` on over words whose :func:`scan` gave ``effect`` (as decoding them would)."""
    y, low, first_high, last_high, wraps, base, steps = effect
    if y >= 0:
        state[E3_Y] = y
    if low >= 0:
        state[E3_LOW] = low
    if first_high >= 0:
        high = int(state[E3_HIGH])
        state[E3_EPOCH] += int(first_high < high and high - first_high > 2048) + wraps
        state[E3_HIGH] = last_high
    if base >= 0:
        state[E3_BASE], state[E3_POL] = base & 0x7FF, base >> 11
    state[E3_BASE] += steps


def _last(kind: np.ndarray, typ: int) -> int:
    """Index of the last word of type ``typ``, or -1, looking back from the end a little at a time."""
    end = len(kind)
    step = 256
    while end > 0:
        a = max(0, end - step)
        hit = np.flatnonzero(kind[a:end] == typ)
        if len(hit):
            return a + int(hit[-1])
        end, step = a, step * 8
    return -1


def _time_range(words: np.ndarray, state: np.ndarray) -> tuple[int, int] | None:
    """The first and last time (min and max) of the events of EVT 3.0 words decoded from ``state``, without
    decoding them: the time after each time word, kept where events follow it. ``(2**62, -(2**62))`` without
    events; None where a vector could reach x = 65536 (the counting sensor's edge: decode to find the stop)."""
    w = np.asarray(words).astype(np.uint16, copy=False)
    kind = w >> 12
    is_v12, is_v8 = kind == 4, kind == 5
    steps = 12 * int(np.count_nonzero(is_v12)) + 8 * int(np.count_nonzero(is_v8))
    if steps and max(int(state[E3_BASE]), 0x7FF) + steps + 11 >= 1 << 16:
        return None
    has_ev = (kind == 2) | (is_v12 & ((w & 0xFFF) != 0)) | (is_v8 & ((w & 0xFF) != 0))
    ev_before = np.cumsum(has_ev, dtype=np.int32)
    if not len(w) or not ev_before[-1]:
        return 2**62, -(2**62)
    at_t = np.flatnonzero((kind == 6) | (kind == 8))
    tw = w[at_t]
    hi_t = (tw >> 12) == 8
    highs = np.compress(hi_t, tw).astype(np.int64) & 0xFFF
    hv = np.empty(len(highs) + 1, np.int64)
    hv[0] = (int(state[E3_EPOCH]) << 24) | (int(state[E3_HIGH]) << 12)
    hv[1:] = (_highs_epochs(highs, int(state[E3_HIGH]), int(state[E3_EPOCH])) << 24) | (highs << 12)
    lv = np.empty(len(tw) - len(highs) + 1, np.int64)
    lv[0] = state[E3_LOW]
    lv[1:] = np.compress(~hi_t, tw) & 0xFFF
    tval = np.empty(len(tw) + 1, np.int64)  # the time in effect after each time word (the start's first)
    tval[0] = hv[0] | lv[0]
    tval[1:] = hv[np.cumsum(hi_t, dtype=np.intp)] | lv[np.cumsum(~hi_t, dtype=np.intp)]
    ends = np.empty(len(at_t) + 1, np.int64)  # event words up to each time word, then up to the end
    ends[:-1] = ev_before[at_t]
    ends[-1] = ev_before[-1]
    used = tval[np.diff(ends, prepend=0) > 0]
    return int(used.min()), int(used.max())


#: How :func:`evtk.io.prophesee._whole.read_whole` takes EVT 3.0 files: 16-bit words, scanned and advanced as
#: above, decoded by :func:`run`; their index (the blocks' time ranges) counted by :func:`_time_range`.
CODEC = Codec("<u2", 1, scan, advance, run, _time_range)
