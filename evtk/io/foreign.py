"""Writing Prophesee RAW (EVT 2.0, EVT 2.1, EVT 3.0), DAT and Event Stream (DVS) files.

Each encoder turns time-ordered events (and, where the format holds them,
trigger edges) into the format's words with numpy alone, so a write needs no
compilation. The words are the inverse of what :mod:`evtk.io.prophesee.decoders`
reads, and the files are read back exactly by the public readers
(expelliarmus, evt3, faery, event_stream; tests/test_foreign_writers.py).

What each format holds:

- EVT 2.0: 32-bit words; x and y below 2048; any time from 0, the first below 2**34 us (a TIME_HIGH
  word is written whenever the time's upper 28 bits change, with extra ones
  across long gaps so that the 34-bit counter's wraps are never ambiguous);
  trigger edges with their channel (0-31).
- EVT 2.1: 64-bit words (one little-endian 64-bit value each, the layout
  OpenEB reads by default): EVT 2.0's, with a CD word for each run of
  consecutive events at one time, row and polarity whose x rise inside one
  group of 32 pixels (its base x a multiple of 32, a 32-bit mask of the
  pixels); x and y below 2048; trigger edges with their channel (0-31).
- EVT 3.0: 16-bit words; x and y below 2048; any time from 0, the first below 2**24 us (the 24-bit
  time's wraps likewise kept unambiguous); trigger edges with channels 0-15.
- DAT (CD events, version 2): x and y below 16384; 32-bit time stamps, so
  the first below 2**32 us and no gap between events reaching 2**31 us; no triggers.
- Event Stream 2.0.0 DVS: x and y below 65536, y stored from the bottom row;
  any time from 0 (a gap costs one byte per 127 us, at most 2**30 of them before the first event); no triggers.

A first time past those is refused (readers would take it modulo the counter's period):
``evtk.io.convert(..., time_from_zero=True)`` shifts a recording's times to start at 0.
"""

from __future__ import annotations

import datetime
import os
from collections.abc import Mapping
from typing import Any

import numpy as np

from .._atomic import AtomicFile
from ..errors import EvtkError
from ..events import Events, Triggers
from ..limits import require_memory
from .base import BaseWriter

__all__ = ["FOREIGN_FORMATS", "ForeignWriter", "encode_evt2", "encode_evt21", "encode_evt3", "encode_dat",
           "encode_es_dvs", "prophesee_header"]

#: format name -> (what it cannot hold, or None)
FOREIGN_FORMATS = {"evt2": None, "evt21": None, "evt3": None, "dat": "trigger edges", "es": "trigger edges",
                   "csv": "trigger edges"}

_BLOCK = 1 << 16  # records encoded at a time: each block's temporaries stay in the CPU's cache
_RISING = {1, 4}  # TriggerKind: external signal / generator rising edge
_EDGES = {1, 2, 4, 5}


def _trigger_columns(triggers: Triggers | None, max_channel: int, fmt: str):
    """(t, value, channel) of the edges a RAW format holds; other trigger kinds are refused by name."""
    if triggers is None or not len(triggers):
        return np.empty(0, np.int64), np.empty(0, np.int64), np.empty(0, np.int64)
    kinds = np.asarray(triggers.kind)
    bad = ~np.isin(kinds, list(_EDGES))
    if bad.any():
        raise EvtkError(f"{fmt} holds trigger edges only; {int(bad.sum())} triggers are of other kinds "
                        f"(first: {int(kinds[bad][0])}); write them to AEDAT4, HDF5 or Parquet")
    channel = getattr(triggers, "channel", None)
    channel = np.zeros(len(triggers), np.int64) if channel is None else np.asarray(channel, np.int64)
    if len(channel) and (channel.min() < 0 or channel.max() > max_channel):
        raise EvtkError(f"{fmt} holds trigger channels 0-{max_channel}; the triggers use up to {int(channel.max())}")
    value = np.isin(kinds, list(_RISING)).astype(np.int64)
    return np.asarray(triggers.t, np.int64), value, channel


def _merged(events: Events, tt: np.ndarray):
    """The order that interleaves events and triggers by time (stable: at equal times, triggers first), as
    (times, is_trigger, index into its own columns); without triggers, the events' own columns (no sort)."""
    if not len(tt):
        return np.asarray(events.t, np.int64), None, None
    t = np.concatenate([tt, np.asarray(events.t, np.int64)])
    is_trig = np.concatenate([np.ones(len(tt), bool), np.zeros(len(events), bool)])
    idx = np.concatenate([np.arange(len(tt)), np.arange(len(events))])
    order = np.argsort(t, kind="stable")
    return t[order], is_trig[order], idx[order]


def _split(events: Events, is_trig, idx):
    """(positions of the events among the records, event columns in that order, trigger record mask, trigger
    indices); the identity when there are no triggers."""
    if is_trig is None:
        return slice(None), events.x, events.y, events.p, None, None
    ev = ~is_trig
    ei = idx[ev]
    return ev, events.x[ei], events.y[ei], events.p[ei], is_trig, idx[is_trig]


def _goes_back(t: np.ndarray) -> bool:
    """Whether any time is below the one before it (compared a block at a time)."""
    for a in range(0, len(t) - 1, _BLOCK):
        seg = t[a:a + _BLOCK + 1]
        if (seg[1:] < seg[:-1]).any():
            return True
    return False


def _check(events: Events, tt: np.ndarray, fmt: str, coord_limit: int):
    for name, col in (("events", np.asarray(events.t)), ("triggers", tt)):
        if not len(col):
            continue
        unordered = _goes_back(col)
        low = int(col.min()) if unordered else int(col[0])  # in time order, the first is the earliest
        if low < 0:
            raise EvtkError(f"{fmt} stores time from 0; the {name} start at {low} us "
                            "(shift them, e.g. events.t - events.t.min())")
        if unordered:
            raise EvtkError(f"{fmt} needs the {name} in time order (sort them first, or convert with --sort)")
    w, h = events.sensor_size
    if w > coord_limit or h > coord_limit:
        raise EvtkError(f"{fmt} holds coordinates below {coord_limit}; the sensor is {w}x{h}")


def _late_start(fmt: str, problem: str) -> EvtkError:
    """The error for a file whose first time ``fmt`` cannot hold (``problem`` says why), naming the remedies."""
    return EvtkError(f"{fmt} {problem}. Shift the times to start near 0 (evtk convert --time-from-zero; in Python, "
                     "evtk.Events(ev.t - t0, ev.x, ev.y, ev.p, ev.sensor_size)), or write AEDAT4, HDF5 or Parquet")


def _high_changes(high: np.ndarray, prev: int | None, step: int, fmt: str, mask: int, unit_us: int):
    """The records of a block whose time high differs from the record's before (the first compared with ``prev``,
    the last high written; None at a file's start), the high before each, and how many intermediate time-high
    words go before its own: across a long gap they advance by at most ``step``, less than half the counter's
    period, so a reader sees each wrap of the counter as a drop.

    A file's first time high must fit the counter (``mask``; ``fmt`` and ``unit_us``, the time high's unit, name
    it in the error): readers take it as the time high of the counter's first period (evtk's, and the evt3
    package's, which counts no wraps before the first event), so a later first time read back modulo the period
    (a recording stamped in Unix microseconds, as DV's are, lost its hours and days, with no warning)."""
    chg = np.flatnonzero(high[1:] != high[:-1]) + 1
    if len(high) and (prev is None or high[0] != prev):
        chg = np.concatenate(([0], chg))
    if prev is None and len(high) and int(high[0]) > mask:
        period = (mask + 1) * unit_us
        raise _late_start(fmt, f"counts its time from 0 in a counter that wraps every {period:,} us, and readers "
                               f"take the first time in the file for one of the first period: the first record, at "
                               f"{int(high[0]) * unit_us:,} us or up to {unit_us - 1} us later, would read back "
                               f"modulo {period:,} us")
    before = high[chg - 1]
    if len(chg) and chg[0] == 0:
        before[0] = high[0] if prev is None else prev  # a file's first high: no intermediate words
    gap = high[chg] - before
    fillers = np.where(gap > step, (gap - 1) // step, 0)
    return chg, before, fillers


def _fillers_before(chg, before, fillers, step: int, type_bits: int, mask: int):
    """For the changes with intermediate time-high words: their records (repeated once a word) and the words, in
    order (each ``step`` past the one before)."""
    at = np.flatnonzero(fillers)
    cnt = fillers[at]
    first = np.cumsum(cnt) - cnt
    k = np.arange(int(cnt.sum())) - np.repeat(first, cnt)  # 0, 1, ... within each gap
    words = type_bits | ((np.repeat(before[at], cnt) + (k + 1) * step) & mask)
    return np.repeat(chg[at], cnt), words


def _blocks(n: int):
    """The (start, stop) of each block of ``n`` records."""
    return ((a, min(a + _BLOCK, n)) for a in range(0, n, _BLOCK))


class _Columns:
    """A block's t, x, y and p as aligned, contiguous arrays: the events' own where they are (views, no copy),
    else copied into buffers made once (a structured array's fields are strided and unaligned, which makes every
    operation on them several times slower)."""

    def __init__(self, events: Events, n: int):
        self.cols = (events.t, events.x, events.y, events.p)
        m = min(n, _BLOCK)
        self.bufs = [None if _plain(col) is not None else np.empty(m, col.dtype) for col in self.cols]

    def __call__(self, a: int, b: int) -> list[np.ndarray]:
        out = []
        for col, buf in zip(self.cols, self.bufs):
            if buf is None:
                out.append(col[a:b])
            else:
                np.copyto(buf[:b - a], col[a:b])
                out.append(buf[:b - a])
        return out


def _plain(col: np.ndarray):
    """``col`` itself where it is contiguous and aligned, else None."""
    return col if col.flags.c_contiguous and col.flags.aligned else None


def _evt2_event_words(t, x, y, p, out: np.ndarray, tmp: np.ndarray) -> np.ndarray:
    """``p << 28 | (t & 63) << 22 | x << 11 | y`` into ``out`` (uint32), with ``tmp`` as scratch."""
    np.copyto(out, t, casting="unsafe")  # the low 32 bits
    out &= 0x3F
    out <<= 22
    np.copyto(tmp, x)
    tmp <<= 11
    out |= tmp
    np.copyto(tmp, y)
    out |= tmp
    np.copyto(tmp, p)
    tmp &= 1
    tmp <<= 28
    out |= tmp
    return out


def _raw_records(events: Events, triggers: Triggers | None, max_channel: int, fmt: str):
    """A RAW chunk's records, checked: their times, events and trigger edges interleaved (see :func:`_merged`),
    and the edges' values and channels."""
    tt, tv, tc = _trigger_columns(triggers, max_channel, fmt)
    _check(events, tt, fmt, 2048)
    t, is_trig, idx = _merged(events, tt)
    return t, is_trig, idx, tv, tc


def _evt2_blocks(events: Events, triggers: Triggers | None, state: dict):
    """The EVT 2.0 words of a chunk, a block at a time (each array valid until the next is made)."""
    t, is_trig, idx, tv, tc = _raw_records(events, triggers, 31, "EVT 2.0")
    n = len(t)
    m = min(n, _BLOCK)
    buf, tmp = np.empty(m, np.uint32), np.empty(m, np.uint32)
    own_all: np.ndarray | None = None
    cols = _Columns(events, n if is_trig is None else 0)
    if is_trig is not None:  # records in time order: events and edges interleaved (the whole chunk at once)
        ev, x, y, p, trig, ti = _split(events, is_trig, idx)
        own_all = np.empty(n, np.uint32)
        te = t[ev]
        own_all[ev] = _evt2_event_words(te, x, y, p, np.empty(len(te), np.uint32), np.empty(len(te), np.uint32))
        own_all[trig] = ((10 << 28) | (t[trig] & 0x3F) << 22 | tc[ti] << 8 | tv[ti]).astype(np.uint32)
    for a, b in _blocks(n):
        if own_all is None:
            tb, xb, yb, pb = cols(a, b)
            own = _evt2_event_words(tb, xb, yb, pb, buf[:b - a], tmp[:b - a])
        else:
            tb, own = t[a:b], own_all[a:b]
        high = tb >> 6
        chg, before, fillers = _high_changes(high, state.get("high"), 1 << 26, "EVT 2.0", 0xFFFFFFF, 64)
        state["high"] = int(high[-1])
        if not len(chg):
            yield own
            continue
        at, words = chg, (8 << 28) | (high[chg] & 0xFFFFFFF)  # an EVT_TIME_HIGH before each change
        if fillers.any():  # long gaps (rare): intermediate highs before the record's own
            f_at, f_words = _fillers_before(chg, before, fillers, 1 << 26, 8 << 28, 0xFFFFFFF)
            order = np.argsort(np.concatenate([f_at, chg]), kind="stable")
            at, words = np.concatenate([f_at, chg])[order], np.concatenate([f_words, words])[order]
        require_memory(4 * (len(own) + len(at)) * 2, "the EVT 2.0 words")
        yield np.insert(own, at, words.astype(np.uint32))


def encode_evt2(events: Events, triggers: Triggers | None = None, state: dict | None = None) -> bytes:
    """EVT 2.0 words (little-endian uint32) for time-ordered ``events`` and trigger edges.

    Parameters
    ----------
    events : Events
        Time-ordered events, times from 0, x and y below 2048.
    triggers : Triggers, optional
        Rising and falling edges (kinds 1, 2, 4, 5), channels 0-31.
    state : dict, optional
        Carries the last TIME_HIGH value from one call to the next when a
        file is written in chunks (updated in place).

    Returns
    -------
    bytes
        The words, ready to follow the file's text header.
    """
    return b"".join(w.astype("<u4", copy=False).tobytes()
                    for w in _evt2_blocks(events, triggers, {} if state is None else state))


def _evt3_blocks(events: Events, triggers: Triggers | None, state: dict):
    """The EVT 3.0 words of a chunk, a block at a time (each array valid until the next is made)."""
    t, is_trig, idx, tv, tc = _raw_records(events, triggers, 15, "EVT 3.0")
    n = len(t)
    m = min(n, _BLOCK)
    # a row a record: [EVT_TIME_HIGH, EVT_TIME_LOW, EVT_ADDR_Y, the record's own word], kept where needed, then
    # read out row by row in one pass; the fillers of long gaps (rare) go in before their records' rows
    rows, keep = np.empty((m, 4), np.uint16), np.zeros((m, 4), bool)
    keep[:, 3] = True  # a record's own word, always
    cols = _Columns(events, n if is_trig is None else 0)
    by_record = None  # with triggers: each record's own word, row and whether the row is new
    if is_trig is not None:  # records in time order: events and edges interleaved (the whole chunk at once)
        ev, x, y, p, trig, ti = _split(events, is_trig, idx)
        own_all, y_all, y_new_all = np.empty(n, np.uint16), np.zeros(n, np.uint16), np.zeros(n, bool)
        own_all[ev] = (2 << 12) | (p.astype(np.uint16) & 1) << 11 | x.astype(np.uint16)
        own_all[trig] = ((10 << 12) | tc[ti] << 8 | tv[ti]).astype(np.uint16)
        y_all[ev] = y
        if len(y):
            y_chg = np.empty(len(y), bool)
            y_chg[0] = int(y[0]) != state.get("y", -1)
            np.not_equal(y[1:], y[:-1], out=y_chg[1:])
            y_new_all[ev] = y_chg
            state["y"] = int(y[-1])
        by_record = (own_all, y_all, y_new_all)
    last_chg = np.zeros(0, np.intp)
    for a, b in _blocks(n):
        r, k = rows[:b - a], keep[:b - a]
        if by_record is None:
            tb, xb, yb, pb = cols(a, b)
        else:
            tb = t[a:b]
        high = tb >> 12
        chg, before, fillers = _high_changes(high, state.get("high"), 2047, "EVT 3.0", 0xFFF, 4096)
        keep[last_chg, 0] = False  # the last block's EVT_TIME_HIGH marks
        k[chg, 0] = True
        last_chg = chg
        r[chg, 0] = (8 << 12) | (high[chg] & 0xFFF)
        np.copyto(r[:, 1], tb, casting="unsafe")  # the low 16 bits
        r[:, 1] &= 0xFFF
        r[:, 1] |= 6 << 12
        k[0, 1] = int(tb[0]) != state.get("t", -1)
        np.not_equal(tb[1:], tb[:-1], out=k[1:, 1])
        k[chg, 1] = True
        if by_record is None:
            r[:, 2] = yb  # EVT_ADDR_Y (type 0)
            k[0, 2] = int(yb[0]) != state.get("y", -1)
            np.not_equal(yb[1:], yb[:-1], out=k[1:, 2])
            own = r[:, 3]
            np.left_shift(pb, 11, out=own, dtype=np.uint16)
            own &= 1 << 11
            own |= xb
            own |= 2 << 12
            state["y"] = int(yb[-1])
        else:
            own_all, y_all, y_new_all = by_record
            r[:, 2], k[:, 2], r[:, 3] = y_all[a:b], y_new_all[a:b], own_all[a:b]
        state["high"], state["t"] = int(high[-1]), int(tb[-1])
        out = np.compress(k.reshape(-1), r.reshape(-1))  # faster than r[k] where the kept words vary
        if fillers.any():  # long gaps (rare): intermediate highs before the record's row
            f_at, f_words = _fillers_before(chg, before, fillers, 2047, 8 << 12, 0xFFF)
            per_row = k.sum(axis=1)
            starts = np.cumsum(per_row) - per_row  # where each record's row begins in out
            out = np.insert(out, starts[f_at], f_words.astype(np.uint16))
        yield out


def encode_evt3(events: Events, triggers: Triggers | None = None, state: dict | None = None) -> bytes:
    """EVT 3.0 words (little-endian uint16) for time-ordered ``events`` and trigger edges.

    One EVT_ADDR_X word a event, an EVT_ADDR_Y word where the row changes, and
    EVT_TIME_LOW / EVT_TIME_HIGH words where the time does (readers take the
    event's time from the last two).

    Parameters
    ----------
    events : Events
        Time-ordered events, times from 0, x and y below 2048.
    triggers : Triggers, optional
        Rising and falling edges, channels 0-15.
    state : dict, optional
        Carries the last time and row between chunks (updated in place).

    Returns
    -------
    bytes
        The words, ready to follow the file's text header.
    """
    return b"".join(w.astype("<u2", copy=False).tobytes()
                    for w in _evt3_blocks(events, triggers, {} if state is None else state))


def _dat_blocks(events: Events, state: dict):
    """The DAT events of a chunk, a block at a time (each array valid until the next is made)."""
    _check(events, np.empty(0, np.int64), "DAT", 16384)
    t = events.t
    n = len(t)
    if not n:
        return
    if "t" not in state and int(t[0]) >= 1 << 32:  # a reader takes the first stamp as the time: no wrap before it
        raise _late_start("DAT", f"time stamps are 32 bits from 0: the first event, at {int(t[0]):,} us, lies past "
                                 "2**32 us, where a reader would take it modulo 2**32")
    prev = state.get("t", int(t[0]))
    if int(t[-1]) - prev >= 1 << 31:  # some gap may be too long for the 32-bit stamps: find the longest
        gaps = np.diff(t, prepend=prev)
        if gaps.max() >= 1 << 31:
            k = int(np.argmax(gaps))
            raise EvtkError(f"DAT's 32-bit time stamps cannot hold a gap of {int(gaps[k])} us (before event {k}); "
                            "write EVT 2.0, EVT 3.0 or AEDAT4")
    state["t"] = int(t[-1])
    m = min(n, _BLOCK)
    out, tmp = np.empty((m, 2), "<u4"), np.empty(m, np.uint32)
    cols = _Columns(events, n)
    for a, b in _blocks(n):
        o, tm = out[:b - a], tmp[:b - a]
        tb, xb, yb, pb = cols(a, b)
        np.copyto(o[:, 0], tb, casting="unsafe")  # the low 32 bits
        w = o[:, 1]
        np.copyto(w, yb)
        w <<= 14
        w |= xb
        np.left_shift(pb, 28, out=tm, dtype=np.uint32)
        tm &= 1 << 28
        w |= tm
        yield o


def encode_dat(events: Events, state: dict | None = None) -> bytes:
    """DAT CD events (8 bytes each: uint32 time stamp, uint32 x | y << 14 | polarity << 28).

    Parameters
    ----------
    events : Events
        Time-ordered events, times from 0, x and y below 16384; no two
        consecutive events 2**31 us or more apart (the 32-bit stamp's wraps
        would be ambiguous).
    state : dict, optional
        Carries the last time between chunks (updated in place).

    Returns
    -------
    bytes
        The events, ready to follow the header and its two type/size bytes.
    """
    return b"".join(o.tobytes() for o in _dat_blocks(events, {} if state is None else state))


_ES_EVENT = np.dtype([("b", "u1"), ("x", "<u2"), ("y", "<u2")])  # packed: 5 bytes an event
#: Most bytes of silence (0xFF, 127 us each) an Event Stream file may begin with: 1 GiB, 38 hours
_ES_LEAD_MOST = 1 << 30


def _es_blocks(events: Events, state: dict):
    """The Event Stream DVS bytes of a chunk, a block at a time (each array valid until the next is made)."""
    _check(events, np.empty(0, np.int64), "Event Stream", 65536)
    t = events.t
    n = len(t)
    if n and "t" not in state and int(t[0]) // 127 > _ES_LEAD_MOST:
        raise _late_start("Event Stream", f"counts its time from 0, a byte for each 127 us of a gap: the first "
                                          f"event, at {int(t[0]):,} us, would need {int(t[0]) // 127:,} bytes before it")
    m = min(n, _BLOCK)
    rec, gap, tmp = np.empty(m, _ES_EVENT), np.empty(m, np.int64), np.empty(m, np.uint16)
    top = events.sensor_size[1] - 1
    cols = _Columns(events, n)
    for a, b in _blocks(n):
        r, g, tm = rec[:b - a], gap[:b - a], tmp[:b - a]
        tb, xb, yb, pb = cols(a, b)
        g[0] = int(tb[0]) - state.get("t", 0)
        np.subtract(tb[1:], tb[:-1], out=g[1:])
        state["t"] = int(tb[-1])
        over = None
        if int(g.max()) >= 127:  # gaps of 127 us or more: a 0xFF byte for each whole 127 us
            over, g = np.divmod(g, 127)
        low = g.astype(np.uint8)
        low <<= 1
        low |= pb & 1
        r["b"] = low
        r["x"] = xb
        np.subtract(top, yb, out=tm, dtype=np.uint16, casting="unsafe")  # y from the bottom row
        r["y"] = tm
        flat = r.view(np.uint8)
        if over is None or not over.any():
            yield flat
            continue
        size = 5 * len(tb) + int(over.sum())
        require_memory(3 * size, "the Event Stream bytes")
        ends = 5 * np.arange(1, len(tb) + 1) + np.cumsum(over)  # where each event's five bytes end
        edge = np.zeros(size + 1, np.int8)
        edge[ends - 5] += 1
        edge[ends] -= 1
        out = np.full(size, 0xFF, np.uint8)
        out[np.cumsum(edge[:size], dtype=np.int8).view(bool)] = flat
        yield out


def encode_es_dvs(events: Events, state: dict | None = None) -> bytes:
    """Event Stream 2.0.0 DVS bytes: per event, 0xFF bytes for each whole 127 us of the gap, then
    ``gap % 127 << 1 | polarity``, x and y (little-endian uint16, y from the bottom row).

    Parameters
    ----------
    events : Events
        Time-ordered events, times from 0.
    state : dict, optional
        Carries the last time between chunks (updated in place).

    Returns
    -------
    bytes
        The event bytes, ready to follow the 20-byte header.
    """
    return b"".join(o.tobytes() for o in _es_blocks(events, {} if state is None else state))


def prophesee_header(fmt: str, sensor_size: tuple[int, int], metadata: Mapping[str, Any] | None = None) -> bytes:
    """The text header of an EVT 2.0, EVT 2.1, EVT 3.0 or DAT file for a ``sensor_size`` (width, height) sensor.

    Parameters
    ----------
    fmt : str
        ``"evt2"``, ``"evt21"``, ``"evt3"`` or ``"dat"``.
    sensor_size : (int, int)
        Width and height.
    metadata : dict, optional
        Extra ``% key value`` lines (single-line text values).

    Returns
    -------
    bytes
        The header, ending where the data begins.
    """
    w, h = sensor_size
    date = datetime.datetime.now().strftime("%Y-%m-%d %H:%M:%S")
    extra = []
    for k, v in (metadata or {}).items():
        if not isinstance(v, (str, int, float)) or str(k).lower() in ("header", "encoding", "header_t0_us"):
            continue  # a source's own header lines are not carried over: this header is the file's own
        text = f"{k} {v}"
        if all(32 <= ord(c) < 127 for c in text) and not str(k).lower().startswith(("evt", "format", "geometry", "end")):
            extra.append(f"% {text}")
    if fmt == "dat":
        lines = ["% Data file containing CD events.", "% Version 2", f"% Date {date}", f"% Height {h}",
                 f"% Width {w}", *extra]
    else:
        name = {"evt2": ("2.0", "EVT2"), "evt21": ("2.1", "EVT21"), "evt3": ("3.0", "EVT3")}[fmt]
        lines = [f"% date {date}", f"% evt {name[0]}", f"% format {name[1]};height={h};width={w}",
                 f"% geometry {w}x{h}", "% integrator_name evtk", *extra, "% end"]
    return ("\n".join(lines) + "\n").encode("ascii")


def es_header(sensor_size: tuple[int, int]) -> bytes:
    """The 20-byte header of an Event Stream 2.0.0 DVS file.

    Parameters
    ----------
    sensor_size : (int, int)
        Width and height.

    Returns
    -------
    bytes
        ``Event Stream``, version 2.0.0, type 1 (DVS), width and height (uint16 LE).
    """
    w, h = sensor_size
    return b"Event Stream" + bytes([2, 0, 0, 1]) + int(w).to_bytes(2, "little") + int(h).to_bytes(2, "little")


# -- EVT 2.1 -------------------------------------------------------------------------------------------------------


def encode_evt21(events: Events, triggers: Triggers | None = None, state: dict | None = None) -> bytes:
    """EVT 2.1 words (little-endian uint64) for time-ordered ``events`` and trigger edges.

    A word's upper 32 bits are an EVT 2.0 word (:func:`encode_evt2` makes
    them, with the time-high words between), its lower 32 bits the mask of a
    CD word: each run of consecutive events at one time, row and polarity
    whose x rise inside one 32-pixel group becomes one CD word with the
    group's first x as its base and bit ``x % 32`` set for each event, so a
    reader gives the events back in their order.

    Parameters
    ----------
    events : Events
        Time-ordered events, times from 0, x and y below 2048.
    triggers : Triggers, optional
        Rising and falling edges (kinds 1, 2, 4, 5), channels 0-31.
    state : dict, optional
        Carries the last time-high value between chunks (updated in place).

    Returns
    -------
    bytes
        The words, ready to follow the file's text header.
    """
    tt = _trigger_columns(triggers, 31, "EVT 2.1")[0]
    _check(events, tt, "EVT 2.1", 2048)
    n = len(events)
    require_memory(64 * n + 48 * len(tt), "the EVT 2.1 words")
    t = np.asarray(events.t, np.int64)
    x = events.x.astype(np.int32)
    key = events.y.astype(np.int32) << 7 | (events.p.astype(np.int32) & 1) << 6 | x >> 5  # row, polarity, group
    new = np.ones(n, bool)  # where a CD word begins
    if n > 1:
        new[1:] = (t[1:] != t[:-1]) | (key[1:] != key[:-1]) | (x[1:] <= x[:-1])
    bits = np.left_shift(np.uint32(1), (x & 31).astype(np.uint32))
    if new.all():  # no two events share a word
        masks, groups = bits, Events._trusted(t, (x & ~31).astype(np.uint16), events.y, events.p, events.sensor_size)
    else:
        starts = np.flatnonzero(new)
        masks = np.bitwise_or.reduceat(bits, starts)
        groups = Events._trusted(t[starts], (x[starts] & ~31).astype(np.uint16), events.y[starts], events.p[starts],
                                 events.sensor_size)
    upper = np.frombuffer(encode_evt2(groups, triggers, state), "<u4")
    out = np.zeros((len(upper), 2), "<u4")  # each word: the mask (low half), then the EVT 2.0 word (high half)
    out[:, 1] = upper
    out[(upper >> 28) <= 1, 0] = masks  # the CD words, in the events' order
    return out.tobytes()


class ForeignWriter(BaseWriter):
    """A streaming writer of EVT 2.0, EVT 2.1, EVT 3.0, DAT, Event Stream or CSV files (``evtk.io.open_writer`` makes one).

    Events arrive in time order, a chunk at a time; trigger edges (EVT 2.0,
    2.1 and 3.0) are given once, when the writer is made, and are interleaved
    with the events by time. The file appears under its name only when
    :meth:`close` runs.

    Parameters
    ----------
    path : str or os.PathLike
        The target.
    fmt : str
        ``"evt2"``, ``"evt21"``, ``"evt3"``, ``"dat"``, ``"es"`` or ``"csv"``.
    sensor_size : tuple of (int, int)
        Width and height in pixels.
    metadata : Mapping of str to object, optional
        Written as header lines (RAW and DAT).
    triggers : Triggers, optional
        Trigger edges (RAW only; DAT and Event Stream refuse them: leave them out, as
        :func:`evtk.io.convert` does with a warning).
    """

    def __init__(self, path: str | os.PathLike[str], fmt: str, sensor_size: tuple[int, int],
                 metadata: Mapping[str, Any] | None = None, triggers: Triggers | None = None) -> None:
        if fmt not in FOREIGN_FORMATS:
            raise EvtkError(f"no foreign writer for {fmt!r}")
        self.path = os.fspath(path)
        self.fmt = fmt
        self.sensor_size = (int(sensor_size[0]), int(sensor_size[1]))
        if triggers is not None and len(triggers) and FOREIGN_FORMATS[fmt]:
            raise EvtkError(f"{fmt} files hold no {FOREIGN_FORMATS[fmt]}; leave the triggers out")
        if triggers is not None and len(triggers):
            triggers = triggers[np.argsort(triggers.t, kind="stable")]
        self._triggers = triggers if triggers is not None and len(triggers) else None
        self._state: dict = {}
        self._last_t: int | None = None
        self._file = AtomicFile(self.path)
        self._closed = False
        try:
            if fmt == "csv":  # faery's header: the columns, with the sensor's size on x and y
                self._file.write(f"t,x@{self.sensor_size[0]},y@{self.sensor_size[1]},on\n".encode("ascii"))
            elif fmt == "es":
                self._file.write(es_header(self.sensor_size))
            else:
                self._file.write(prophesee_header(fmt, self.sensor_size, metadata))
                if fmt == "dat":
                    self._file.write(bytes([0x0C, 8]))
        except BaseException:
            self._file.discard()
            raise

    def write_events(self, events: Events) -> None:
        """Append a chunk of events (time-ordered, continuing the last chunk).

        Parameters
        ----------
        events : Events
            The chunk; its sensor size must be the writer's.
        """
        self._check_open()
        if tuple(events.sensor_size) != self.sensor_size:
            raise EvtkError(f"{self.path}: events of a {events.sensor_size} sensor for a {self.sensor_size} file")
        if not len(events):
            return
        if self._last_t is not None and int(events.t[0]) < self._last_t:
            raise EvtkError(f"{self.path}: events go back in time between chunks ({int(events.t[0])} us after "
                            f"{self._last_t} us)")
        triggers, rest = None, self._triggers
        if self._triggers is not None:  # the edges up to this chunk's last event go in with it
            cut = int(np.searchsorted(self._triggers.t, int(events.t[-1]), side="right"))
            triggers, rest = self._triggers[:cut], (self._triggers[cut:] if cut < len(self._triggers) else None)
        self._write(events, triggers)
        self._triggers = rest
        self._last_t = int(events.t[-1])

    def _encode(self, events: Events, triggers: Triggers | None):
        """The chunk's bytes, a block at a time (each array valid until the next is made)."""
        if self.fmt == "evt2":
            return _evt2_blocks(events, triggers, self._state)
        if self.fmt == "evt3":
            return _evt3_blocks(events, triggers, self._state)
        if self.fmt == "evt21":
            return encode_evt21(events, triggers, self._state)
        if self.fmt == "dat":
            return _dat_blocks(events, self._state)
        if self.fmt == "csv":  # a block of lines at a time bounds the text held
            from .decoded import csv_lines

            return (csv_lines([p.t, p.x, p.y, p.p]) for p in
                    (events[k:k + _BLOCK] for k in range(0, len(events), _BLOCK)))
        return _es_blocks(events, self._state)

    def _write(self, events: Events, triggers: Triggers | None) -> None:
        """Encode and write a chunk, a block at a time; a chunk that fails part-way (a block over the memory
        budget, an interrupt) is taken back whole, so the writer goes on from before it."""
        f = self._file.file
        start, state = f.tell(), dict(self._state)
        try:
            blocks = self._encode(events, triggers)
            for block in ([blocks] if isinstance(blocks, bytes) else blocks):  # an encoder's bytes, or its blocks
                f.write(block.data.cast("B") if isinstance(block, np.ndarray) else block)
        except BaseException:
            f.seek(start)
            f.truncate()
            self._state = state
            raise

    def _finish(self):
        if self._triggers is not None:  # edges after the last event
            empty = Events(np.empty(0, np.int64), np.empty(0, np.uint16), np.empty(0, np.uint16),
                           np.empty(0, np.uint8), self.sensor_size)
            self._write(empty, self._triggers)
            self._triggers = None

    def _commit(self):
        self._file.commit()

    def _discard(self):
        self._file.discard()
