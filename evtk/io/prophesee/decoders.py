"""Prophesee RAW (EVT 2.0, EVT 2.1, EVT 3.0), DAT and Event Stream: recognising them, their headers, and the numba
decoders."""

from __future__ import annotations

import os
import re
from collections.abc import Iterable

import numpy as np
from numba import njit

from ..base import sensor_dims, text_header

__all__ = ["sniff", "sniff_lines", "word_type", "evt21_legacy"]


BLOCK_WORDS = 1 << 20  # decoding unit: 4 MiB of EVT 2.0 words, 8 MiB of DAT events
_MAX_HEADER = 1 << 20

EVT2, EVT21, EVT3, DAT = "evt2", "evt21", "evt3", "dat"

ST_OK, ST_COORD, ST_TYPE, ST_FULL = 0, -1, -2, -3


_END = re.compile(rb"^%[ \t]*end[ \t\r]*$", re.M)  # OpenEB closes newer headers with '% end'


def _header(path):
    """(header lines without '%', data offset) of a Prophesee file: the lines at its start that begin with
    '%' and are text (:func:`~evtk.io.base.text_header`; a first data word whose low byte is '%' is data,
    not header), up to a closing '% end'. Nothing past the header is looked at: DAT's type and size bytes
    (0x0C, 8) are no text, so a DAT header ends before them."""
    lines, end = text_header(path, b"%", _MAX_HEADER, _END)
    lines = [line[1:].strip() for line in lines]
    if lines and lines[-1] == "end":
        lines.pop()
    return lines, end


def sniff_lines(lines: Iterable[str]) -> str | None:
    """'evt2', 'evt21', 'evt3', 'dat', 'evt-other' or None from a Prophesee header's lines (without the '%').

    Parameters
    ----------
    lines : iterable of str
        The header's lines, as :func:`_header` gives them.

    Returns
    -------
    str or None
        The encoding the header names, or None when it names none.
    """
    low = [" ".join(line.lower().split()) for line in lines]
    for line in low:
        named = line[7:].split(";")[0].strip() if line.startswith("format ") else None
        if line == "evt 2.0" or named == "evt2":
            return EVT2
        if line == "evt 2.1" or named == "evt21":
            return EVT21
        if line == "evt 3.0" or named == "evt3":
            return EVT3
    if any(line in ("version 1", "version 2") or line.startswith("width ") for line in low):
        return DAT
    if any(line.startswith("evt") for line in low):
        return "evt-other"
    return None


def sniff(path: str | os.PathLike[str]) -> str | None:
    """'evt2', 'evt21', 'evt3', 'dat', 'evt-other' or None from a file's '%' header (its header lines only).

    Parameters
    ----------
    path : str or os.PathLike
        The file.

    Returns
    -------
    str or None
        What :func:`sniff_lines` says of the header's lines.
    """
    return sniff_lines(_header(path)[0])


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


# EVT 2.1 decoder state: EVT 2.0's (time high, epoch), and the word layout (1: OpenEB's "endianness=legacy", the
# IMX636's: the 32 bits with the type first in the file, the mask after them; 0: one little-endian 64-bit word)
_E21_LEGACY = 2
_LOW32 = np.uint64(0xFFFFFFFF)
_SHIFT32 = np.uint64(32)
# a set bit's index from the bit alone, by a de Bruijn sequence: (bit * _DEBRUIJN) mod 2**32 has a distinct top five
# bits for each of the 32 bits
_DEBRUIJN = 0x077CB531
_BIT_INDEX = np.zeros(32, np.int64)
_BIT_INDEX[[((1 << k) * _DEBRUIJN & 0xFFFFFFFF) >> 27 for k in range(32)]] = np.arange(32)


@njit(cache=True, nogil=True)
def _evt2x_run(words, state, width, height, decode, t, x, y, p, tt, tk, tch, wide):
    """One pass over EVT 2.0 words (uint32) or, with ``wide``, EVT 2.1 words (uint64): counts, or with
    ``decode`` the events and triggers. Returns (events, triggers, status, word index of the problem, min t,
    max t); the min and max only when counting.

    An EVT 2.1 word's upper half (by the layout in ``state``) is an EVT 2.0 word whose CD types carry the base
    x of 32 pixels, its lower half their validity mask (bit k: the pixel at base x + k); an EVT 2.0 CD word is
    the one pixel at its x. A CD word whose events no longer fit the outputs stops with ST_FULL, for the
    caller to resume at it."""
    high = state[_E2_HIGH]
    epoch = state[_E2_EPOCH]
    legacy = wide and state[_E21_LEGACY] != 0
    room = 32 if wide else 1
    base = (epoch << 34) | (high << 6)
    n = 0
    m = 0
    t_min = np.int64(2**62)
    t_max = np.int64(-(2**62))
    status = ST_OK
    bad = -1
    for i in range(len(words)):
        if not wide:
            w = np.int64(words[i])
            mask = np.int64(1)
        elif legacy:
            w = np.int64(words[i] & _LOW32)
            mask = np.int64(words[i] >> _SHIFT32)
        else:
            w = np.int64(words[i] >> _SHIFT32)
            mask = np.int64(words[i] & _LOW32)
        kind = w >> 28
        if kind <= 1:  # CD_OFF / EV_NEG, CD_ON / EV_POS: most words
            if decode and n + room > len(t):
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


@njit(cache=True, nogil=True)
def _evt2_run(words, state, width, height, decode, t, x, y, p, tt, tk, tch):
    """:func:`_evt2x_run` over EVT 2.0 words."""
    return _evt2x_run(words, state, width, height, decode, t, x, y, p, tt, tk, tch, False)


@njit(cache=True, nogil=True)
def _evt21_run(words, state, width, height, decode, t, x, y, p, tt, tk, tch):
    """:func:`_evt2x_run` over EVT 2.1 words."""
    return _evt2x_run(words, state, width, height, decode, t, x, y, p, tt, tk, tch, True)


@njit(cache=True, nogil=True)
def _dat_run(raw, state, width, height, decode, t, x, y, p, tt, tk, tch):
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


def word_type(encoding: str, word: int, legacy: bool = False) -> int:
    """The type (top four bits) of a RAW word, for messages about a word of an unknown type.

    Parameters
    ----------
    encoding : str
        ``"evt2"``, ``"evt21"`` or ``"evt3"``.
    word : int
        The word as read (EVT 2.1: the 64-bit little-endian value).
    legacy : bool
        EVT 2.1 in the IMX636's layout (the type in bits 28..31).

    Returns
    -------
    int
        The type, 0 to 15.
    """
    shift = 28 if legacy else _TYPES[encoding][0]
    return (int(word) >> shift) & 0xF


def evt21_legacy(lines: list[str]) -> bool:
    """Whether an EVT 2.1 header names OpenEB's ``endianness=legacy`` layout on its ``format`` line.

    Parameters
    ----------
    lines : list of str
        The header's lines without their leading ``%``.

    Returns
    -------
    bool
        True for the IMX636's layout (each 64-bit word as two little-endian
        32-bit halves, the half with the type first); False for one
        little-endian 64-bit word (the default, and GenX320's).
    """
    for line in lines:
        low = "".join(line.lower().split())
        if low.startswith("format") and "endianness=legacy" in low.split(";"):
            return True
    return False


# EVT 3.0 decoder state: time high, time low, epoch (wraps of the 24-bit time), y, vector base x, polarity
_E3_HIGH, _E3_LOW, _E3_EPOCH, _E3_Y, _E3_BASE, _E3_POL = range(6)


@njit(cache=True, nogil=True)
def _evt3_run(words, state, width, height, decode, t, x, y, p, tt, tk, tch):
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
                tch[m] = (v >> 8) & 0xF
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
def _es_dvs_run(data, state, width, height, decode, t, x, y, p, tt, tk, tch):
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


_RUNNERS = {EVT2: _evt2_run, EVT21: _evt21_run, EVT3: _evt3_run, DAT: _dat_run, ES: _es_dvs_run}
_STATE_SIZE = {EVT2: 2, EVT21: 3, EVT3: 6, DAT: 2, ES: 5}
_DTYPE = {EVT2: "<u4", EVT21: "<u8", EVT3: "<u2", DAT: "<u4", ES: "u1"}
# where a word's type sits, and the types a format has (for the message about a word of another type)
_TYPES = {EVT2: (28, "EVT 2.0 has 0, 1, 8, 10, 14 and 15"), EVT21: (60, "EVT 2.1 has 0, 1, 8, 10, 14 and 15"),
          EVT3: (12, "EVT 3.0 has 0, 2-8, 10, 14 and 15")}
_NO_OUT = (np.empty(0, np.int64), np.empty(0, np.uint16), np.empty(0, np.uint16), np.empty(0, np.uint8),
           np.empty(0, np.int64), np.empty(0, np.uint8), np.empty(0, np.uint8))
