"""Writing Prophesee RAW (EVT 2.0, EVT 2.1, EVT 3.0), DAT and Event Stream (DVS) files.

Each encoder turns time-ordered events (and, where the format holds them,
trigger edges) into the format's words with numpy alone, so a write needs no
compilation. The words are the inverse of what :mod:`evtk.io.prophesee.decoders`
reads, and the files are read back exactly by the public readers
(expelliarmus, evt3, faery, event_stream; tests/test_foreign_writers.py).

What each format holds:

- EVT 2.0: 32-bit words; x and y below 2048; any time from 0 (a TIME_HIGH
  word is written whenever the time's upper 28 bits change, with extra ones
  across long gaps so that the 34-bit counter's wraps are never ambiguous);
  trigger edges with their channel (0-31).
- EVT 2.1: 64-bit words (one little-endian 64-bit value each, the layout
  OpenEB reads by default): EVT 2.0's, with a CD word for each run of
  consecutive events at one time, row and polarity whose x rise inside one
  group of 32 pixels (its base x a multiple of 32, a 32-bit mask of the
  pixels); x and y below 2048; trigger edges with their channel (0-31).
- EVT 3.0: 16-bit words; x and y below 2048; any time from 0 (the 24-bit
  time's wraps likewise kept unambiguous); trigger edges with channels 0-15.
- DAT (CD events, version 2): x and y below 16384; 32-bit time stamps, so
  no gap between events may reach 2**31 us; no triggers.
- Event Stream 2.0.0 DVS: x and y below 65536, y stored from the bottom row;
  any time from 0 (a gap costs one byte per 127 us); no triggers.
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


def _check(events: Events, tt: np.ndarray, fmt: str, coord_limit: int):
    for name, col in (("events", np.asarray(events.t)), ("triggers", tt)):
        if len(col) and int(col.min()) < 0:
            raise EvtkError(f"{fmt} stores time from 0; the {name} start at {int(col.min())} us "
                            "(shift them, e.g. events.t - events.t.min())")
        if len(col) > 1 and np.any(np.diff(col) < 0):
            raise EvtkError(f"{fmt} needs the {name} in time order (sort them first, or convert with --sort)")
    w, h = events.sensor_size
    if w > coord_limit or h > coord_limit:
        raise EvtkError(f"{fmt} holds coordinates below {coord_limit}; the sensor is {w}x{h}")


def _time_words(high: np.ndarray, prev: int | None, step: int):
    """For each record, how many time-high words precede it (0 when its high equals the last one's), how many
    of those are fillers, and the previous high: across a long gap, consecutive high words advance by at most
    ``step``, less than half the counter's period, so a reader sees each wrap of the counter as a drop."""
    n = len(high)
    n_pre = np.zeros(n, np.int64)
    fillers = np.zeros(n, np.int64)
    if not n:
        return n_pre, fillers, high
    first_prev = -1 if prev is None else prev
    changed = np.empty(n, bool)
    changed[0] = high[0] != first_prev
    np.not_equal(high[1:], high[:-1], out=changed[1:])
    n_pre += changed
    gap = np.empty(n, np.int64)
    gap[0] = high[0] - first_prev if first_prev >= 0 else 0
    np.subtract(high[1:], high[:-1], out=gap[1:])
    long = np.flatnonzero(gap > step)  # rare: a gap of more than half the counter's period
    prev_high = high  # read only at the long gaps (the record before each), made below when there are any
    if len(long):
        prev_high = np.concatenate([[first_prev], high[:-1]])
        fillers[long] = (gap[long] - 1) // step
        n_pre[long] += fillers[long]
    return n_pre, fillers, prev_high


def _filler_words(prev_high: np.ndarray, fillers: np.ndarray, step: int, type_bits: int, mask: int, dtype):
    """The records that follow a long gap, and the intermediate time-high words that go before each of them, in
    order (each ``step`` past the one before, as :func:`_time_words` counts them)."""
    long = np.flatnonzero(fillers)
    values = [type_bits | ((int(prev_high[i]) + (k + 1) * step) & mask) for i in long for k in range(int(fillers[i]))]
    return long, np.asarray(values, dtype)


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
    state = {} if state is None else state
    tt, tv, tc = _trigger_columns(triggers, 31, "EVT 2.0")
    _check(events, tt, "EVT 2.0", 2048)
    t, is_trig, idx = _merged(events, tt)
    high = t >> 6
    n_pre, fillers, prev_high = _time_words(high, state.get("high"), 1 << 26)
    n = len(t)
    extra = int(n_pre.sum())
    require_memory(4 * (n + extra) * 2, "the EVT 2.0 words")
    low = (t & 0x3F).astype(np.uint32) << 22
    ev, x, y, p, trig, ti = _split(events, is_trig, idx)
    words = np.empty(n, np.uint32)  # one word a record, in time order; the time-high words go in before
    words[ev] = (p.astype(np.uint32) & 1) << 28 | low[ev] | x.astype(np.uint32) << 11 | y.astype(np.uint32)
    if trig is not None:
        words[trig] = ((10 << 28) | low[trig] | tc[ti] << 8 | tv[ti]).astype(np.uint32)
    own = n_pre > fillers  # records whose time high differs from the last: their EVT_TIME_HIGH goes before them
    highs = ((8 << 28) | (high[own] & 0xFFFFFFF)).astype(np.uint32)
    out = np.insert(words, np.flatnonzero(own), highs) if extra else words
    long, vals = _filler_words(prev_high, fillers, 1 << 26, 8 << 28, 0xFFFFFFF, np.uint32)
    if len(long):  # long gaps (rare): intermediate highs before the record's own, at most 2**26 apart
        own_at = np.arange(n) + np.cumsum(own) - 1  # where each record's own time-high word now stands
        out = np.insert(out, np.repeat(own_at[long], fillers[long]), vals)
    if n:
        state["high"] = int(high[-1])
    return out.astype("<u4", copy=False).tobytes()


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
    state = {} if state is None else state
    tt, tv, tc = _trigger_columns(triggers, 15, "EVT 3.0")
    _check(events, tt, "EVT 3.0", 2048)
    t, is_trig, idx = _merged(events, tt)
    n = len(t)
    high = t >> 12
    n_high, fillers, prev_high = _time_words(high, state.get("high"), 2047)
    low_new = np.empty(n, bool)
    if n:
        low_new[0] = t[0] != state.get("t", -1)
        np.not_equal(t[1:], t[:-1], out=low_new[1:])
        low_new |= n_high > 0
    ev, x, y, p, trig, ti = _split(events, is_trig, idx)
    y_ev = np.asarray(y)
    y_new = np.zeros(n, bool)
    if len(y_ev):
        y_chg = np.empty(len(y_ev), bool)
        y_chg[0] = int(y_ev[0]) != state.get("y", -1)
        np.not_equal(y_ev[1:], y_ev[:-1], out=y_chg[1:])
        y_new[ev] = y_chg
    require_memory(16 * n, "the EVT 3.0 words")
    # a row a record: [EVT_TIME_HIGH, EVT_TIME_LOW, EVT_ADDR_Y, the record's own word], kept where needed, then
    # read out row by row in one pass; the fillers of long gaps (rare) go in before their records' rows
    rows = np.empty((n, 4), np.uint16)
    keep = np.empty((n, 4), bool)
    rows[:, 0] = (8 << 12) | (high & 0xFFF).astype(np.uint16)
    keep[:, 0] = n_high > 0
    rows[:, 1] = (6 << 12) | (t & 0xFFF).astype(np.uint16)
    keep[:, 1] = low_new
    keep[:, 2] = y_new
    keep[:, 3] = True
    if trig is None:
        rows[:, 2] = y_ev.astype(np.uint16)  # EVT_ADDR_Y (type 0)
        rows[:, 3] = (2 << 12) | (p.astype(np.uint16) & 1) << 11 | x.astype(np.uint16)
    else:
        rows[ev, 2] = y_ev.astype(np.uint16)
        rows[ev, 3] = (2 << 12) | (p.astype(np.uint16) & 1) << 11 | x.astype(np.uint16)
        rows[trig, 3] = ((10 << 12) | tc[ti] << 8 | tv[ti]).astype(np.uint16)
    out = rows[keep]
    long, vals = _filler_words(prev_high, fillers, 2047, 8 << 12, 0xFFF, np.uint16)
    if len(long):
        per_row = keep.sum(axis=1)
        starts = np.cumsum(per_row) - per_row  # where each record's row begins in out
        out = np.insert(out, np.repeat(starts[long], fillers[long]), vals)
    if n:
        state["high"], state["t"] = int(high[-1]), int(t[-1])
    if len(y_ev):
        state["y"] = int(y_ev[-1])
    return out.astype("<u2", copy=False).tobytes()


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
    state = {} if state is None else state
    _check(events, np.empty(0, np.int64), "DAT", 16384)
    t = np.asarray(events.t, np.int64)
    if len(t):
        gaps = np.diff(t, prepend=state.get("t", t[0]))
        if gaps.max() >= 1 << 31:
            k = int(np.argmax(gaps))
            raise EvtkError(f"DAT's 32-bit time stamps cannot hold a gap of {int(gaps[k])} us (before event {k}); "
                            "write EVT 2.0, EVT 3.0 or AEDAT4")
        state["t"] = int(t[-1])
    require_memory(8 * len(t), "the DAT events")
    out = np.empty((len(t), 2), "<u4")
    out[:, 0] = t & 0xFFFFFFFF
    out[:, 1] = (events.x.astype(np.uint32) | events.y.astype(np.uint32) << 14
                 | (events.p.astype(np.uint32) & 1) << 28)
    return out.tobytes()


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
    state = {} if state is None else state
    _check(events, np.empty(0, np.int64), "Event Stream", 65536)
    t = np.asarray(events.t, np.int64)
    if not len(t):
        return b""
    gaps = np.diff(t, prepend=state.get("t", 0))
    over = gaps // 127
    n_over = int(over.sum())
    require_memory(5 * len(t) + n_over, "the Event Stream bytes")
    rows = np.empty((len(t), 5), np.uint8)  # each event's five bytes; the 0xFF bytes go in before them
    rows[:, 0] = (gaps % 127).astype(np.uint8) << 1 | (events.p.astype(np.uint8) & 1)
    x = events.x
    y = (events.sensor_size[1] - 1) - events.y.astype(np.int32)
    rows[:, 1] = x.astype(np.uint8)  # the low byte (a cast keeps the low bits)
    rows[:, 2] = (x >> 8).astype(np.uint8)
    rows[:, 3] = y.astype(np.uint8)
    rows[:, 4] = (y >> 8).astype(np.uint8)
    out = rows.reshape(-1)
    if n_over:
        out = np.insert(out, np.repeat(np.arange(len(t)) * 5, over), np.uint8(0xFF))
    state["t"] = int(t[-1])
    return out.tobytes()


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
        triggers = None
        if self._triggers is not None:  # the edges up to this chunk's last event go in with it
            cut = int(np.searchsorted(self._triggers.t, int(events.t[-1]), side="right"))
            triggers, self._triggers = self._triggers[:cut], (self._triggers[cut:] if cut < len(self._triggers)
                                                               else None)
        self._file.write(self._encode(events, triggers))
        self._last_t = int(events.t[-1])

    def _encode(self, events: Events, triggers: Triggers | None) -> bytes:
        if self.fmt == "evt2":
            return encode_evt2(events, triggers, self._state)
        if self.fmt == "evt3":
            return encode_evt3(events, triggers, self._state)
        if self.fmt == "evt21":
            return encode_evt21(events, triggers, self._state)
        if self.fmt == "dat":
            return encode_dat(events, self._state)
        if self.fmt == "csv":  # a million lines at a time bounds the text held
            from .decoded import csv_lines

            return b"".join(csv_lines([p.t, p.x, p.y, p.p]) for p in
                            (events[k:k + (1 << 20)] for k in range(0, len(events), 1 << 20)))
        return encode_es_dvs(events, self._state)

    def _finish(self):
        if self._triggers is not None:  # edges after the last event
            empty = Events(np.empty(0, np.int64), np.empty(0, np.uint16), np.empty(0, np.uint16),
                           np.empty(0, np.uint8), self.sensor_size)
            self._file.write(self._encode(empty, self._triggers))
            self._triggers = None

    def _commit(self):
        self._file.commit()

    def _discard(self):
        self._file.discard()
