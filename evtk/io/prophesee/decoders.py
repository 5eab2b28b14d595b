"""Prophesee RAW (EVT 2.0, EVT 2.1, EVT 3.0), DAT and Event Stream: recognising them, their headers, and their
decoders: the compiled kernels where evtk's were built, else numpy's and numba's (``_fallbacks.py``, loaded on first
use; EVT 2.1's, which has no compiled kernel, always); EVT 3.0's in ``_evt3.py``."""

from __future__ import annotations

import functools
import os
import re
from collections.abc import Iterable

import numpy as np

from ..._native import dat_run as native_dat_run
from ..._native import es_run as native_es_run
from ..._native import evt2_run as native_evt2_run
from ..base import sensor_dims, text_header

__all__ = ["sniff", "sniff_lines", "word_type", "evt21_legacy"]


BLOCK_WORDS = 1 << 18  # decoding unit: 1 MiB of EVT 2.0 words, 2 MiB of DAT events
_MAX_HEADER = 1 << 20

EVT2, EVT21, EVT3, DAT = "evt2", "evt21", "evt3", "dat"

ST_OK, ST_COORD, ST_TYPE, ST_FULL, ST_TIME = 0, -1, -2, -3, -4  # ST_TIME: a time past int64 (see _within_int64)


# OpenEB closes newer headers with '% end' (compiled where a header is read, and then from re's cache: compiling
# it costs a fresh process 0.2 ms, which a read of an Event Stream file need not pay)
_END = rb"^%[ \t]*end[ \t\r]*$"


def _header(path):
    """(header lines without '%', data offset) of a Prophesee file: the lines at its start that begin with
    '%' and are text (:func:`~evtk.io.base.text_header`; a first data word whose low byte is '%' is data,
    not header), up to a closing '% end'. Nothing past the header is looked at: DAT's type and size bytes
    (0x0C, 8) are no text, so a DAT header ends before them."""
    lines, end = text_header(path, b"%", _MAX_HEADER, re.compile(_END, re.M))
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


# -- decoding (compiled; numpy and numba in _fallbacks.py; EVT 3.0 in _evt3.py) -------------------------------------------


# decoder states (int64 arrays, updated in place so that a block goes on where the one before ended)
# EVT 2.0: time high, epoch (wraps of the 34-bit time); DAT: last raw time stamp, epoch (wraps of 32 bits)
_E2_HIGH, _E2_EPOCH = range(2)
_DAT_PREV, _DAT_EPOCH = range(2)


def _first_stop(*masks) -> tuple[int, int]:
    """``(index, which)`` of the first True over ``masks`` (``which``: the mask's position), or ``(-1, -1)``."""
    best, which = -1, -1
    for k, mask in enumerate(masks):
        if len(mask):
            i = int(np.argmax(mask))
            if mask[i] and (best < 0 or i < best):
                best, which = i, k
    return best, which


#: Words each numpy pass takes at a time: its temporaries stay in the cache (and a few MiB whatever the file).
SLICE_WORDS = 1 << 16


def _sliced(core, words_per_item=1, slice_words=lambda: SLICE_WORDS):
    """A runner that applies ``core`` (a numpy runner) to :data:`SLICE_WORDS` words at a time (or
    ``slice_words()``), the state carried from slice to slice and each slice's events written after the last's:
    the same results as one call over all the words, with temporaries bounded by the slice. The problem's index
    counts items of ``words_per_item`` words (DAT: events of two)."""

    def run(words, state, width, height, decode, t, x, y, p, tt, tk, tch):
        n = m = 0
        t_min, t_max = 2**62, -(2**62)
        size = slice_words()
        for a in range(0, max(len(words), 1), size):
            k, j, status, bad, lo, hi = core(words[a:a + size], state, width, height, decode, t[n:], x[n:],
                                             y[n:], p[n:], tt[m:], tk[m:], tch[m:])
            n, m, t_min, t_max = n + k, m + j, min(t_min, lo), max(t_max, hi)
            if status != ST_OK:
                return n, m, status, a // words_per_item + bad, t_min, t_max
        return n, m, ST_OK, -1, t_min, t_max

    run.__doc__, run.__name__, run.__qualname__ = core.__doc__, core.__name__, core.__qualname__
    return run


# EVT 2.1 decoder state: EVT 2.0's (time high, epoch), and the word layout (1: OpenEB's "endianness=legacy", the
# IMX636's: the 32 bits with the type first in the file, the mask after them; 0: one little-endian 64-bit word)
_E21_LEGACY = 2


def _fallbacks():
    """The numpy and numba decoders (:mod:`._fallbacks`), loaded on first use: where evtk's compiled kernels were
    built, only EVT 2.1 and a damaged file's slow paths need them."""
    from . import _fallbacks

    return _fallbacks


def _evt21_run(words, state, width, height, decode, t, x, y, p, tt, tk, tch):
    """EVT 2.1 words through numba's loop (:func:`._fallbacks._evt21_run`: EVT 2.1 has no compiled kernel)."""
    return _fallbacks()._evt21_run(words, state, width, height, decode, t, x, y, p, tt, tk, tch)


#: The compiled kernels' outcomes, in their order (none, a word of no type, an event off the sensor, full outputs).
_NATIVE_STATUS = (ST_OK, ST_TYPE, ST_COORD, ST_FULL)


def _evt2_run(words, state, width, height, decode, t, x, y, p, tt, tk, tch):
    """EVT 2.0 words decoded or counted: :func:`._fallbacks._evt2_numpy_run`'s arguments and results, by the
    compiled kernel where evtk's were built (:func:`evtk._native.evt2_run`: one pass, the GIL released), else by
    numpy."""
    got = native_evt2_run(words, state, width, height, decode, t, x, y, p, tt, tk, tch, _NATIVE_STATUS)
    if got is not None:
        return got
    return _fallbacks()._evt2_numpy_run(words, state, width, height, decode, t, x, y, p, tt, tk, tch)


def _dat_run(raw, state, width, height, decode, t, x, y, p, tt, tk, tch):
    """DAT events decoded or counted: :func:`._fallbacks._dat_numpy_run`'s arguments and results, by the compiled
    kernel where evtk's were built (:func:`evtk._native.dat_run`), else by numpy."""
    got = native_dat_run(raw, state, width, height, decode, t, x, y, p, _NATIVE_STATUS)
    if got is not None:
        return got
    return _fallbacks()._dat_numpy_run(raw, state, width, height, decode, t, x, y, p, tt, tk, tch)


def _within_int64(run, epoch_slot: int, shift: int, item_words: int = 1):
    """``run`` (a decoder with :func:`_evt2_numpy_run`'s arguments and results) that stops with ``ST_TIME`` at the
    first item whose time would pass 2**63 - 1 µs, instead of wrapping.

    The time is ``epoch << shift`` plus bits below (EVT 2.0 and 2.1: 34; DAT: 32), so the last epoch that fits
    is ``(2**63 - 1) >> shift``: 2**29 wraps of EVT 2.0's time (4 GiB of words at the least), 2**31 of DAT's.
    Past it, numpy's route would raise Python's OverflowError and the kernels' unsigned arithmetic would wrap.
    When a call leaves the epoch past its last, the item that took it there is found by bisection over counting
    runs (from the call's start state; only then) and the words before it are decoded again: the events before
    it, the stop at it, and the state before it. A call from a state already past (a block after the stop,
    decoded from its scanned state) stops at its first item.
    """
    most = (2**63 - 1) >> shift

    @functools.wraps(run)
    def capped(words, state, width, height, decode, t, x, y, p, tt, tk, tch):
        if state[epoch_slot] > most:
            return 0, 0, ST_TIME, 0, 2**62, -(2**62)
        start = state.copy()
        got = run(words, state, width, height, decode, t, x, y, p, tt, tk, tch)
        if state[epoch_slot] <= most:
            return got
        lo, hi = 0, len(words) // item_words  # words[:lo] stay within, words[:hi] pass: the item hi - 1 passes
        while hi - lo > 1:
            mid = (lo + hi) // 2
            trial = start.copy()
            run(words[:mid * item_words], trial, width, height, False, *_NO_OUT)
            lo, hi = (lo, mid) if trial[epoch_slot] > most else (mid, hi)
        state[:] = start
        n, m, _, _, t_lo, t_hi = run(words[:lo * item_words], state, width, height, decode, t, x, y, p, tt, tk, tch)
        return n, m, ST_TIME, lo, t_lo, t_hi

    return capped


_evt2_run = _within_int64(_evt2_run, _E2_EPOCH, 34)
_dat_run = _within_int64(_dat_run, _DAT_EPOCH, 32, item_words=2)


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


# Event Stream decoder state: time, position inside an event (0: at its first byte), x, y, polarity (ATIS: the
# polarity in bit 1 and the threshold-crossing flag in bit 0), and (ATIS) the threshold crossings left out so far
_ES_T, _ES_PHASE, _ES_X, _ES_Y, _ES_POL, _ES_LEFT = range(6)
ES = "es"
ES_MAGIC = b"Event Stream"


def _es_run(data, state, width, height, decode, t, x, y, p, tt, tk, tch):
    """Event Stream DVS bytes decoded or counted: :func:`._fallbacks._es_dvs_run`'s arguments and results, by the
    compiled kernel where evtk's were built (:func:`evtk._native.es_run`), else by numpy
    (:func:`._fallbacks._es_dvs_np`)."""
    got = native_es_run(data, state, width, height, decode, False, t, x, y, p, _NATIVE_STATUS)
    if got is not None:
        return got
    return _fallbacks()._es_np_run(data, state, width, height, decode, t, x, y, p, tt, tk, tch)


def es_atis_run(data, state, width, height, decode, t, x, y, p, tt, tk, tch):
    """Event Stream ATIS bytes decoded or counted: :func:`._fallbacks._es_atis_run`'s arguments and results, by
    the compiled kernel where evtk's were built, else by numba's loop."""
    got = native_es_run(data, state, width, height, decode, True, t, x, y, p, _NATIVE_STATUS)
    if got is not None:
        return got
    return _fallbacks()._es_atis_run(data, state, width, height, decode, t, x, y, p, tt, tk, tch)


_RUNNERS = {EVT2: _evt2_run, EVT21: _within_int64(_evt21_run, _E2_EPOCH, 34), DAT: _dat_run,
            ES: _es_run}  # EVT 3.0: _evt3.run
_STATE_SIZE = {EVT2: 2, EVT21: 3, EVT3: 6, DAT: 2, ES: 6}
_DTYPE = {EVT2: "<u4", EVT21: "<u8", EVT3: "<u2", DAT: "<u4", ES: "u1"}
# where a word's type sits, and the types a format has (for the message about a word of another type)
_TYPES = {EVT2: (28, "EVT 2.0 has 0, 1, 8, 10, 14 and 15"), EVT21: (60, "EVT 2.1 has 0, 1, 8, 10, 14 and 15"),
          EVT3: (12, "EVT 3.0 has 0, 2-8, 10, 14 and 15")}
_NO_OUT = (np.empty(0, np.int64), np.empty(0, np.uint16), np.empty(0, np.uint16), np.empty(0, np.uint8),
           np.empty(0, np.int64), np.empty(0, np.uint8), np.empty(0, np.uint8))
