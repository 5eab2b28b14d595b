"""Prophesee RAW (EVT 2.0 and 3.0) and DAT (CD, version 2) recordings, read by content.

Both start with a text header of lines beginning with ``%``. EVT 2.0 then
holds little-endian 32-bit words whose top four bits give their type:
CD_OFF (0) and CD_ON (1) carry the six low bits of the time stamp, x (11
bits) and y (11 bits); EV_TIME_HIGH (8) carries the 28 high bits of the time
stamp; EXT_TRIGGER (10) carries the six low bits, a channel (5 bits) and the
edge (bit 0). DAT files follow the header with two bytes (event type 0x0C,
event size 8) and then 8-byte events: a 32-bit time stamp and a 32-bit word
with x (14 bits), y (14 bits) and the polarity (4 bits). EVT 3.0 holds 16-bit
words (type in the top four bits): y (0), a single x with its polarity (2),
the base x and polarity of a vector (3), 12- and 8-pixel vector masks (4, 5),
the low and high twelve bits of a 24-bit time stamp (6, 8) and triggers (10),
following Prophesee's documentation; the 24-bit time is unwrapped (public
decoders differ on some files' stamps: evtk follows the documented format). Time stamps are
microseconds as stored (faery also writes a ``% t0`` line and adds it back
when reading; Prophesee's tools and expelliarmus do not: evtk reports it in
``metadata`` and keeps the stamps as stored). Counters that wrap (EVT 2.0's
34-bit time, DAT's 32-bit one) are unwrapped.

A full read is one decoder call over the memory-mapped file. For windows the
reader makes its own block index in one counting pass (numba), so a window
decodes only the blocks it overlaps, and streaming holds one block at a time;
nothing in the index comes from the file's claims.
"""

from __future__ import annotations

import os
import re

import numpy as np
from numba import njit

from ..errors import EvtkError, FormatError
from ..events import Events, Triggers
from .base import BaseRecording, Damage, StreamInfo, sensor_dims

__all__ = ["PropheseeRecording", "EventStreamRecording", "sniff"]

BLOCK_WORDS = 1 << 20  # decoding unit: 4 MiB of EVT 2.0 words, 8 MiB of DAT events
_MAX_HEADER = 1 << 20

EVT2, EVT3, DAT = "evt2", "evt3", "dat"

ST_OK, ST_COORD, ST_TYPE, ST_FULL = 0, -1, -2, -3


def sniff(head: bytes) -> str | None:
    """'evt2', 'evt3', 'dat' or None from a file's first bytes (its header)."""
    if not head.startswith(b"%"):
        return None
    text = head[:4096].decode("latin-1").lower()
    if "% evt 2.0" in text or "format evt2" in text:
        return EVT2
    if "% evt 3.0" in text or "format evt3" in text:
        return EVT3
    if "% version 2" in text or "% version 1" in text or "% width" in text:
        return DAT
    if "% evt" in text:
        return "evt-other"
    return None


_TEXT_LINE = re.compile(rb"%[\x20-\x7e\t]*\r?\n\Z")


def _header(path):
    """(header lines without '%', data offset) of a Prophesee file. A line is header only if it is text ('%',
    printable ASCII, a line end): a first data word whose low byte is '%' is data, not header."""
    lines = []
    with open(path, "rb") as f:
        pos = 0
        while True:
            line = f.readline(_MAX_HEADER)
            if not _TEXT_LINE.match(line):
                break
            pos += len(line)
            if pos > _MAX_HEADER:
                raise FormatError(path, 0, "the text header runs past 1 MiB")
            text = line[1:].decode("utf-8", "replace").strip()
            if text == "end":  # OpenEB closes newer headers with '% end'
                break
            lines.append(text)
    return lines, pos


def _sensor_from_header(lines, path):
    for line in lines:
        low = line.lower()
        if low.startswith("geometry"):
            parts = line.split(None, 1)[-1].lower().split("x")
            if len(parts) == 2:
                return sensor_dims(parts[0], parts[1], path, "the header's geometry")
        if low.startswith("format") and "width=" in low:
            fields = dict(p.split("=", 1) for p in line.split(None, 1)[-1].split(";") if "=" in p)
            if "width" in fields and "height" in fields:
                return sensor_dims(fields["width"], fields["height"], path, "the header's format line")
    keys = {line.split(None, 1)[0].lower(): line.split(None, 1)[-1] for line in lines if line.split()}
    if "width" in keys and "height" in keys:
        return sensor_dims(keys["width"], keys["height"], path, "the header's Width and Height")
    return None


# -- decoding (numba) -------------------------------------------------------------------------------------------


# decoder states (int64 arrays, updated in place so that a block goes on where the one before ended)
# EVT 2.0: time high, epoch (wraps of the 34-bit time); DAT: last raw time stamp, epoch (wraps of 32 bits)
_E2_HIGH, _E2_EPOCH = range(2)
_DAT_PREV, _DAT_EPOCH = range(2)


@njit(cache=True, nogil=True)
def _evt2_run(words, state, width, height, decode, t, x, y, p, tt, tk):
    """One pass over EVT 2.0 words: counts, or with ``decode`` the events and triggers. Returns (events,
    triggers, status, word index of the problem, min t, max t); the min and max only when counting."""
    high = state[_E2_HIGH]
    epoch = state[_E2_EPOCH]
    base = (epoch << 34) | (high << 6)
    n = 0
    m = 0
    t_min = np.int64(2**62)
    t_max = np.int64(-(2**62))
    status = ST_OK
    bad = -1
    for i in range(len(words)):
        w = np.int64(words[i])
        kind = w >> 28
        if kind <= 1:  # CD_OFF, CD_ON: most words
            xi = (w >> 11) & 0x7FF
            yi = w & 0x7FF
            if xi >= width or yi >= height:
                status = ST_COORD
                bad = i
                break
            tc = base | ((w >> 22) & 0x3F)
            if decode:
                t[n] = tc
                x[n] = xi
                y[n] = yi
                p[n] = kind
            else:
                t_min = min(t_min, tc)
                t_max = max(t_max, tc)
            n += 1
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
            m += 1
        elif kind != 14 and kind != 15:  # OTHERS and CONTINUED carry no events; no other type exists
            status = ST_TYPE
            bad = i
            break
    state[_E2_HIGH] = high
    state[_E2_EPOCH] = epoch
    return n, m, status, bad, t_min, t_max


@njit(cache=True, nogil=True)
def _dat_run(raw, state, width, height, decode, t, x, y, p, tt, tk):
    """One pass over DAT CD events (pairs of uint32: time stamp, data), with :func:`_evt2_run`'s arguments
    and results (DAT files hold no triggers)."""
    prev = state[_DAT_PREV]
    epoch = state[_DAT_EPOCH]
    n = 0
    t_min = np.int64(2**62)
    t_max = np.int64(-(2**62))
    status = ST_OK
    bad = -1
    for i in range(len(raw) // 2):
        ts = np.int64(raw[2 * i])
        d = np.int64(raw[2 * i + 1])
        if ts < prev and prev - ts > (1 << 31):  # the 32-bit counter wrapped
            epoch += 1
        prev = ts
        xi = d & 0x3FFF
        yi = (d >> 14) & 0x3FFF
        if xi >= width or yi >= height:
            status = ST_COORD
            bad = i
            break
        tc = (epoch << 32) | ts
        if decode:
            t[n] = tc
            x[n] = xi
            y[n] = yi
            p[n] = 1 if (d >> 28) & 0xF else 0
        else:
            t_min = min(t_min, tc)
            t_max = max(t_max, tc)
        n += 1
    state[_DAT_PREV] = prev
    state[_DAT_EPOCH] = epoch
    return n, 0, status, bad, t_min, t_max


# EVT 3.0 decoder state: time high, time low, epoch (wraps of the 24-bit time), y, vector base x, polarity
_E3_HIGH, _E3_LOW, _E3_EPOCH, _E3_Y, _E3_BASE, _E3_POL = range(6)


@njit(cache=True, nogil=True)
def _evt3_run(words, state, width, height, decode, t, x, y, p, tt, tk):
    """One pass over EVT 3.0 words (16 bits, type in the top four): counts, or with ``decode`` the events
    and triggers. ``state`` (:data:`_E3_HIGH` ...) carries over from the previous block and is updated.
    Returns (events, triggers, status, word index of the problem, min t, max t)."""
    high = state[_E3_HIGH]
    low = state[_E3_LOW]
    epoch = state[_E3_EPOCH]
    yy = state[_E3_Y]
    base = state[_E3_BASE]
    pol = state[_E3_POL]
    n = 0
    m = 0
    t_min = np.int64(2**62)
    t_max = np.int64(-(2**62))
    status = ST_OK
    bad = -1
    for i in range(len(words)):
        w = np.int64(words[i])
        kind = w >> 12
        v = w & 0xFFF
        if kind == 0:  # EVT_ADDR_Y
            yy = v & 0x7FF
        elif kind == 2 or kind == 4 or kind == 5:  # EVT_ADDR_X, VECT_12, VECT_8
            if decode and n + 12 > len(t):  # no room for a whole vector: the caller resumes at this word
                status = ST_FULL
                bad = i
                break
            if kind == 2:
                first, mask, step = v & 0x7FF, np.int64(1), 0
                ep = (v >> 11) & 1
            else:
                first, mask, step = base, v if kind == 4 else v & 0xFF, 12 if kind == 4 else 8
                ep = pol
            tcur = (epoch << 24) | (high << 12) | low
            for k in range(12):
                if (mask >> k) & 1:
                    xi = first + k
                    if xi >= width or yy >= height:
                        status = ST_COORD
                        bad = i
                        break
                    if decode:
                        t[n] = tcur
                        x[n] = xi
                        y[n] = yy
                        p[n] = ep
                    n += 1
                    if tcur < t_min:
                        t_min = tcur
                    if tcur > t_max:
                        t_max = tcur
            if status != ST_OK:
                break
            base += step
        elif kind == 3:  # VECT_BASE_X
            base = v & 0x7FF
            pol = (v >> 11) & 1
        elif kind == 6:  # EVT_TIME_LOW
            low = v
        elif kind == 8:  # EVT_TIME_HIGH
            if v < high and high - v > 2048:  # the 24-bit time wrapped
                epoch += 1
            high = v
        elif kind == 10:  # EXT_TRIGGER: the edge in bit 0, the channel in bits 8..11
            if decode and m >= len(tt):
                status = ST_FULL
                bad = i
                break
            if decode:
                tt[m] = (epoch << 24) | (high << 12) | low
                tk[m] = 1 if (v & 1) else 2
            m += 1
        elif kind != 7 and kind != 14 and kind != 15:  # CONTINUED_4, OTHERS, CONTINUED_12
            status = ST_TYPE
            bad = i
            break
    state[_E3_HIGH] = high
    state[_E3_LOW] = low
    state[_E3_EPOCH] = epoch
    state[_E3_Y] = yy
    state[_E3_BASE] = base
    state[_E3_POL] = pol
    return n, m, status, bad, t_min, t_max


# Event Stream (DVS) decoder state: time, position inside an event (0: at its first byte), x, y, polarity
_ES_T, _ES_PHASE, _ES_X, _ES_Y, _ES_POL = range(5)
ES = "es"
ES_MAGIC = b"Event Stream"


@njit(cache=True, nogil=True)
def _es_dvs_run(data, state, width, height, decode, t, x, y, p, tt, tk):
    """One pass over Event Stream 2.x DVS bytes: 0xFF adds 127 us, 0xFE is a reset (nothing), any other
    first byte adds its top seven bits to the time and gives the polarity in bit 0; four bytes follow (x,
    then y counted from the bottom row, little-endian). :func:`_evt2_run`'s arguments and results (no
    triggers); ``state`` carries over between blocks."""
    tc = state[_ES_T]
    phase = state[_ES_PHASE]
    xi = state[_ES_X]
    yi = state[_ES_Y]
    pol = state[_ES_POL]
    n = 0
    t_min = np.int64(2**62)
    t_max = np.int64(-(2**62))
    for i in range(len(data)):
        b = np.int64(data[i])
        if phase == 0:
            if b == 0xFF:
                tc += 127
            elif b != 0xFE:
                tc += b >> 1
                pol = b & 1
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
                return n, 0, ST_COORD, i, t_min, t_max
            if decode:
                t[n] = tc
                x[n] = xi
                y[n] = height - 1 - yi  # stored from the bottom row up; evtk counts y down
                p[n] = pol
            n += 1
            if tc < t_min:
                t_min = tc
            if tc > t_max:
                t_max = tc
    state[_ES_T] = tc
    state[_ES_PHASE] = phase
    state[_ES_X] = xi
    state[_ES_Y] = yi
    state[_ES_POL] = pol
    return n, 0, ST_OK, -1, t_min, t_max


_RUNNERS = {EVT2: _evt2_run, EVT3: _evt3_run, DAT: _dat_run, ES: _es_dvs_run}
_STATE_SIZE = {EVT2: 2, EVT3: 6, DAT: 2, ES: 5}
_DTYPE = {EVT2: "<u4", EVT3: "<u2", DAT: "<u4", ES: "u1"}
# where a word's type sits, and the types a format has (for the message about a word of another type)
_TYPES = {EVT2: (28, "EVT 2.0 has 0, 1, 8, 10, 14 and 15"), EVT3: (12, "EVT 3.0 has 0, 2-8, 10, 14 and 15")}
_NO_OUT = (np.empty(0, np.int64), np.empty(0, np.uint16), np.empty(0, np.uint16), np.empty(0, np.uint8),
           np.empty(0, np.int64), np.empty(0, np.uint8))


class PropheseeRecording(BaseRecording):
    """A Prophesee RAW (EVT 2.0 or 3.0) or DAT recording.

    Parameters
    ----------
    path : str or os.PathLike
    salvage : bool
        Read what is intact before damage (an event off the sensor, a file
        cut inside an event) instead of raising.
    sensor_size : (int, int), optional
        For files whose header does not give it.
    """

    format = "prophesee"

    def __init__(self, path, salvage=False, sensor_size=None):
        super().__init__(path, salvage)
        with open(self.path, "rb") as f:
            kind = sniff(f.read(4096))
        if kind not in (EVT2, EVT3, DAT):
            raise FormatError(self.path, 0, "not a Prophesee EVT 2.0, EVT 3.0 or DAT file (no recognised % header)")
        self.encoding = kind
        self._lines, self._start = _header(self.path)
        size = _sensor_from_header(self._lines, self.path)
        if sensor_size is not None:
            size = sensor_dims(sensor_size[0], sensor_size[1], None, "sensor_size")
        if size is None:
            raise FormatError(self.path, 0, "the header gives no sensor size (geometry, format or Width/Height); "
                                            "pass sensor_size=(width, height)")
        self._size = size
        self._file_bytes = os.path.getsize(self.path)
        item = 4
        if kind == DAT:
            with open(self.path, "rb") as f:
                f.seek(self._start)
                head = f.read(2)
            if len(head) < 2:
                raise FormatError(self.path, self._start, "the file ends before the event type and size bytes")
            if head[1] != 8:
                raise FormatError(self.path, self._start + 1, f"DAT events of {head[1]} bytes; evtk reads 8-byte events")
            if head[0] not in (0x0C, 0x00):
                raise FormatError(self.path, self._start, f"DAT event type {head[0]:#x}; evtk reads CD events (0x0c)")
            self._start += 2
            item = 8
        if kind == EVT3:
            item = 2
        self._item = item
        body = self._file_bytes - self._start
        self._count = body // item
        if body % item:
            where = self._start + self._count * item
            problem = f"the file ends inside an event ({body % item} of {item} bytes)"
            if not self.salvage:
                raise FormatError(self.path, where, problem + "; salvage reads the events before it")
            self.damage = Damage(where, problem)
        self._blocks = None  # per block: start state, events, triggers, min t, max t
        self._triggers = None

    # -- raw access ---------------------------------------------------------------------------------------------
    def _per_block(self):
        """Items (words, DAT events) in a block."""
        return BLOCK_WORDS // 2 if self.encoding == DAT else BLOCK_WORDS

    def _words(self, b):
        """Words of block ``b``: uint32 (DAT: pairs of them), uint16 for EVT 3.0, bytes for Event Stream."""
        per = self._per_block()
        a = b * per
        n = min(per, self._count - a)
        with open(self.path, "rb") as f:
            f.seek(self._start + a * self._item)
            raw = f.read(n * self._item)
        return np.frombuffer(raw, _DTYPE[self.encoding])

    def _n_blocks(self):
        return -(-self._count // self._per_block())

    def _initial_state(self):
        """The decoder's state before the first word (:data:`_E2_HIGH` ..., :data:`_E3_HIGH` ..., ...)."""
        state = np.zeros(_STATE_SIZE[self.encoding], np.int64)
        if self.encoding == DAT:
            state[_DAT_PREV] = -1
        return state

    def _index(self):
        """One counting pass over the file: every block's decoder state at its start, its event and trigger
        counts and its time range."""
        if self._blocks is None:
            run = _RUNNERS[self.encoding]
            rows = []
            state = self._initial_state()
            for b in range(self._n_blocks()):
                start = state.copy()
                n_ev, n_tr, _, _, lo, hi = run(self._words(b), state, 1 << 16, 1 << 16, False, *_NO_OUT)
                rows.append((start, int(n_ev), int(n_tr), int(lo), int(hi)))
            self._blocks = rows
            self._check_es_end(state)
        return self._blocks

    def _check_es_end(self, state):
        """An Event Stream whose last event is cut: an error, or with salvage a note."""
        if self.encoding == ES and self._count and state[_ES_PHASE] != 0 and self.damage is None:
            where = self._start + self._count
            problem = f"the file ends inside an event ({int(state[_ES_PHASE])} of its 5 bytes)"
            if not self.salvage:
                raise FormatError(self.path, where, problem + "; salvage reads the events before it")
            self.damage = Damage(where, problem)

    def _decode(self, words, state, first):
        """Decode ``words`` (item ``first`` of the file onwards) from ``state``, which is updated: ``(events,
        triggers, problem)``. Outputs are sized by what the words could hold (pages never written cost no
        memory); EVT 3.0, with up to 12 events a word, goes on where a whole vector no longer fits."""
        run = _RUNNERS[self.encoding]
        w, h = self._size
        size = len(words)
        cap = {EVT2: size, EVT3: size + 12, DAT: size // 2, ES: size // 5 + 1}[self.encoding]
        cap_tr = cap if self.encoding in (EVT2, EVT3) else 0
        evs, trs, pos = [], [], 0
        while True:
            t, x, y, p = (np.empty(cap, np.int64), np.empty(cap, np.uint16), np.empty(cap, np.uint16),
                          np.empty(cap, np.uint8))
            tt, tk = np.empty(cap_tr, np.int64), np.empty(cap_tr, np.uint8)
            n, m, st, bad, _, _ = run(words[pos:], state, w, h, True, t, x, y, p, tt, tk)
            evs.append(Events._trusted(t[:n], x[:n], y[:n], p[:n], self._size))
            trs.append(Triggers(tt[:m], tk[:m]))
            if st != ST_FULL:
                break
            pos += bad
        problem = None
        if st != ST_OK:
            at = self._start + self._item * (first + pos + bad)
            if st == ST_COORD:
                problem = (at, f"an event lies outside the {w}x{h} sensor")
            else:
                shift, known = _TYPES[self.encoding]
                problem = (at, f"word of unknown type {int(words[pos + bad]) >> shift} ({known})")
        ev = evs[0] if len(evs) == 1 else Events.concatenate(evs, sensor_size=self._size)
        tr = trs[0] if len(trs) == 1 else Triggers.concatenate(trs)
        return ev, tr, problem

    def _decode_block(self, b):
        """(Events, Triggers, problem) of block ``b``, from its state in the index; a problem stops salvage."""
        return self._decode(self._words(b), self._index()[b][0].copy(), b * self._per_block())

    def _through(self):
        """Yield ``(events, triggers, problem)`` block by block in one pass, without the index; the index rows
        it sees are kept, and become the index when the pass reaches the end without a problem."""
        state = self._initial_state()
        rows = []
        for b in range(self._n_blocks()):
            start = state.copy()
            ev, tr, problem = self._decode(self._words(b), state, b * self._per_block())
            n = len(ev)
            rows.append((start, n, len(tr), int(ev.t.min()) if n else 0, int(ev.t.max()) if n else -1))
            yield ev, tr, problem
            if problem:
                return
        if self._blocks is None:
            self._blocks = rows
            self._check_es_end(state)

    def _stop(self, problem):
        at, reason = problem
        if not self.salvage:
            raise FormatError(self.path, at, reason)
        if self.damage is None or (self.damage.offset is not None and at < self.damage.offset):
            self.damage = Damage(at, reason)

    # -- interface ----------------------------------------------------------------------------------------------
    @property
    def sensor_size(self):
        return self._size

    @property
    def metadata(self) -> dict:
        out = {"encoding": self.encoding, "header": list(self._lines)}
        for line in self._lines:
            parts = line.split()
            if len(parts) == 2 and parts[0].lower() == "t0" and parts[1].lstrip("-").isdigit():
                out["header_t0_us"] = int(parts[1])
        return out

    def iter_events(self, chunk_events: int = 1_000_000, t_start_us=None, t_end_us=None):
        self._check_open()
        chunk_events = int(chunk_events)
        if chunk_events < 1:
            raise EvtkError(f"chunk_events must be at least 1, got {chunk_events}")
        pending, held = [], 0
        windowed = t_start_us is not None or t_end_us is not None
        if windowed or self._blocks is not None:
            blocks = self._windowed(t_start_us, t_end_us)
        else:  # straight through: one pass, and the index comes with it
            blocks = self._through()
        for ev, _, problem in blocks:
            if windowed:
                ev = ev.between(t_start_us, t_end_us)
            if len(ev):
                pending.append(ev)
                held += len(ev)
            while held >= chunk_events:
                joined = Events.concatenate(pending, sensor_size=self._size)
                yield joined[:chunk_events]
                rest = joined[chunk_events:]
                pending, held = ([rest] if len(rest) else []), len(rest)
            if problem:
                self._stop(problem)
                break
        if held:
            yield Events.concatenate(pending, sensor_size=self._size)

    def _windowed(self, t_start_us, t_end_us):
        """Yield ``(events, triggers, problem)`` of the blocks whose time range (by the index) meets the window."""
        for b, (_, n_ev, _, lo, hi) in enumerate(self._index()):
            if n_ev and ((t_start_us is not None and hi < t_start_us) or (t_end_us is not None and lo >= t_end_us)):
                continue
            yield self._decode_block(b)

    def events(self, t_start_us=None, t_end_us=None) -> Events:
        self._check_open()
        if t_start_us is None and t_end_us is None and self._count:
            return self._whole()
        parts = list(self.iter_events(1 << 62, t_start_us, t_end_us))
        return Events.concatenate(parts, sensor_size=self._size) if parts else Events.empty(self._size)

    def _whole(self) -> Events:
        """Every event in one decoder call over the memory-mapped file: no blocks to join."""
        n_words = self._count * (2 if self.encoding == DAT else 1)
        words = np.memmap(self.path, dtype=_DTYPE[self.encoding], mode="r", offset=self._start, shape=(n_words,))
        state = self._initial_state()
        ev, tr, problem = self._decode(words, state, 0)
        del words
        if problem:
            self._stop(problem)
        else:
            self._check_es_end(state)
            if self._triggers is None:
                self._triggers = tr
        return ev

    def triggers(self, t_start_us=None, t_end_us=None) -> Triggers:
        self._check_open()
        if self._triggers is None:
            parts = []
            for b, (_, _, n_tr, _, _) in enumerate(self._index()):
                if n_tr:
                    parts.append(self._decode_block(b)[1])
            self._triggers = Triggers.concatenate(parts)
        tr = self._triggers
        return tr.between(t_start_us, t_end_us) if (t_start_us is not None or t_end_us is not None) else tr

    @property
    def streams(self):
        rows = self._index()
        n = sum(r[1] for r in rows)
        lo = min((r[3] for r in rows if r[1]), default=None)
        hi = max((r[4] for r in rows if r[1]), default=None)
        out = [StreamInfo(0, "events", "EVTS", packets=len(rows), count=n, t_start_us=lo, t_end_us=hi,
                          sensor_size=self._size)]
        n_tr = sum(r[2] for r in rows)
        if n_tr:
            out.append(StreamInfo(1, "triggers", "TRIG", packets=len(rows), count=n_tr))
        return out

    def _extra_info(self):
        return {"encoding": self.encoding}


class EventStreamRecording(PropheseeRecording):
    """An Event Stream (.es) recording of DVS events (version 2.x), as Sepia, Tonic and faery write them.

    The header is the text ``Event Stream``, the version (three bytes), the
    event type (1: DVS) and the sensor's width and height (16 bits each);
    events follow as a byte stream (see :func:`_es_dvs_run`). y is stored
    from the bottom row up and read as evtk's rows from the top. Generic,
    ATIS and colour streams are named and refused.
    """

    format = "event_stream"

    def __init__(self, path, salvage=False, sensor_size=None):  # noqa: D107 - the class says it
        BaseRecording.__init__(self, path, salvage)
        with open(self.path, "rb") as f:
            head = f.read(20)
        if not head.startswith(ES_MAGIC) or len(head) < 16:
            raise FormatError(self.path, 0, "not an Event Stream file (no 'Event Stream' header)")
        major = head[12]
        kind = head[15]
        if major != 2:
            raise FormatError(self.path, 12, f"Event Stream version {major}.{head[13]}.{head[14]}; evtk reads 2.x")
        if kind != 1:
            names = {0: "generic", 2: "ATIS", 3: "colour"}
            raise FormatError(self.path, 15, f"Event Stream of {names.get(kind, f'type {kind}')} events; evtk reads "
                                             "DVS events (type 1)")
        if len(head) < 20:
            raise FormatError(self.path, 16, "the file ends inside the Event Stream header")
        w, h = int.from_bytes(head[16:18], "little"), int.from_bytes(head[18:20], "little")
        self._size = sensor_dims(w, h, self.path, "the Event Stream header")
        if sensor_size is not None:
            self._size = sensor_dims(sensor_size[0], sensor_size[1], None, "sensor_size")
        self.encoding = ES
        self._lines = [f"version {major}.{head[13]}.{head[14]}", "type dvs"]
        self._start = 20
        self._item = 1
        self._file_bytes = os.path.getsize(self.path)
        self._count = self._file_bytes - self._start
        self._blocks = None
        self._triggers = None
