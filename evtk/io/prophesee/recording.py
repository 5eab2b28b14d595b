"""Reading Prophesee RAW, DAT and Event Stream files: a block index, time windows, streaming and salvage."""

from __future__ import annotations

import os
from collections.abc import Iterator
from typing import Any

import numpy as np

from ...errors import EvtkError, FormatError
from ...events import Events, Triggers
from ...limits import require_memory
from ..base import BaseRecording, Damage, StreamInfo, _event_columns, _put_events, sensor_dims
from . import _whole
from .decoders import (
    _DAT_PREV,
    _DTYPE,
    _E21_LEGACY,
    _ES_LEFT,
    _ES_PHASE,
    _NO_OUT,
    _RUNNERS,
    _STATE_SIZE,
    _TYPES,
    BLOCK_WORDS,
    DAT,
    ES,
    ES_MAGIC,
    EVT2,
    EVT3,
    EVT21,
    ST_COORD,
    ST_FULL,
    ST_OK,
    ST_TIME,
    _header,
    _sensor_from_header,
    es_atis_run,
    evt21_legacy,
    sniff_lines,
    word_type,
)

__all__ = ["PropheseeRecording", "EventStreamRecording"]


def _evt3() -> Any:
    """The EVT 3.0 decoder module, imported on first use: a read of another encoding (Event Stream, EVT 2.0,
    DAT) never loads it, which spares a fresh process 1.5-5 ms."""
    from . import _evt3 as evt3

    return evt3


class PropheseeRecording(BaseRecording):
    """A Prophesee RAW (EVT 2.0, 2.1 or 3.0) or DAT recording.

    Parameters
    ----------
    path : str or os.PathLike
        The ``.raw`` or ``.dat`` file.
    salvage : bool
        Read what is intact before damage (an event off the sensor, a file
        cut inside an event) instead of raising.
    sensor_size : tuple of (int, int), optional
        ``(width, height)`` in pixels, for files whose header does not give it (else from the header's
        geometry, its system ID, or, for DAT, the events' extent with a warning).
    """

    format = "prophesee"
    legacy_layout = False

    def __init__(self, path: str | os.PathLike[str], salvage: bool = False,
                 sensor_size: tuple[int, int] | None = None) -> None:
        super().__init__(path, salvage)
        self._lines, self._start = _header(self.path)
        kind = sniff_lines(self._lines)
        if kind not in (EVT2, EVT21, EVT3, DAT):
            raise FormatError(self.path, 0, "not a Prophesee EVT 2.0, EVT 2.1, EVT 3.0 or DAT file (no recognised % "
                                            "header)")
        self.encoding = kind
        if kind == EVT3:  # its decoder loads with the file, not inside the first read's memory and time
            _evt3()
        #: EVT 2.1 only: the IMX636's word layout (OpenEB's ``endianness=legacy``)
        self.legacy_layout = kind == EVT21 and evt21_legacy(self._lines)
        size = _sensor_from_header(self._lines, self.path)
        #: where the sensor size came from: the header, the system ID, the events or the caller
        self.size_source = "the header"
        if size is None:
            from .sensors import sensor_from_system_id

            by_id = sensor_from_system_id(self._lines)
            if by_id is not None:  # older headers name the camera board only, as Prophesee's reader takes it
                size, board = by_id
                self.size_source = f"the header's system ID ({board})"
        if sensor_size is not None:
            size = sensor_dims(sensor_size[0], sensor_size[1], None, "sensor_size")
            self.size_source = "the caller"
        from_events = size is None and kind == DAT
        if size is None and not from_events:
            raise FormatError(self.path, 0, "the header gives no sensor size (geometry, format, Width/Height or a "
                                            "known system_ID); pass --sensor-size WxH (sensor_size=(width, height))")
        self._size = (1 << 14, 1 << 14) if from_events else size  # DAT coordinates have 14 bits
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
        if kind == EVT21:
            item = 8
        self._item = item
        body = self._file_bytes - self._start
        self._count = body // item
        if body % item:
            where = self._start + self._count * item
            problem = f"the file ends inside an event ({body % item} of {item} bytes)"
            if not self.salvage:
                raise FormatError(self.path, where, problem + "; salvage reads the events before it")
            self.damage = Damage(where, problem)
        self._blocks: list[tuple[Any, int, int, int, int]] | None = None  # per block: start state, events, triggers, min t, max t
        self._triggers: Triggers | None = None
        if from_events:  # N-CARS and other DAT files without a size: the smallest sensor that holds the events
            ev = self._whole()
            self._size = (int(ev.x.max()) + 1, int(ev.y.max()) + 1) if len(ev) else (1, 1)
            self.size_source = "the events"
            self.warnings.append(f"the header gives no sensor size: {self._size[0]}x{self._size[1]}, the smallest "
                                 "that holds the events (pass --sensor-size WxH for the camera's own)")

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
        if self.encoding == EVT21:
            state[_E21_LEGACY] = int(self.legacy_layout)
        return state

    def _codec(self) -> Any:
        """How :func:`_whole.read_whole` takes this file's words (EVT 3.0, EVT 2.0 or DAT)."""
        if self.encoding == EVT3:
            return _evt3().CODEC
        return _whole.EVT2_CODEC if self.encoding == EVT2 else _whole.DAT_CODEC

    def _runner(self):
        """The decoder of this file's encoding."""
        return _evt3().run if self.encoding == EVT3 else _RUNNERS[self.encoding]

    def _index(self):
        """One counting pass over the file: every block's decoder state at its start, its event and trigger
        counts and its time range."""
        if self._blocks is None and self.encoding == EVT3:  # counted on the reader's threads
            width, height = self._size
            got = _whole.read_whole(str(self.path), self._start, self._count, self._per_block(), width, height,
                                    self._initial_state(), self._codec(), decode=False)
            if got["status"] != ST_OK:
                self._stop(self._word_problem(np.array([got["word"]], np.uint16), got["status"], 0, got["bad"]))
            self._blocks = got["rows"]
        if self._blocks is None:
            run = self._runner()
            rows = []
            state = self._initial_state()
            for b in range(self._n_blocks()):
                start = state.copy()
                words = self._words(b)
                n_ev, n_tr, st, bad, lo, hi = run(words, state, 1 << 16, 1 << 16, False, *_NO_OUT)
                rows.append((start, int(n_ev), int(n_tr), int(lo), int(hi)))
                if st != ST_OK:  # the later blocks' states would follow a stop: the index ends here (salvage)
                    self._stop(self._word_problem(words, st, bad, b * self._per_block()))
                    break
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
        memory); EVT 3.0 and 2.1, with up to 12 and 32 events a word, go on where a whole vector no longer fits,
        each further output checked against the memory budget first."""
        run = self._runner()
        w, h = self._size
        size = len(words)
        cap = {EVT2: size, EVT21: size + 32, EVT3: size + 12, DAT: size // 2, ES: size // 5 + 1}[self.encoding]
        cap_tr = cap if self.encoding in (EVT2, EVT21, EVT3) else 0
        evs, trs, pos, held = [], [], 0, 0
        while True:
            if evs:  # a further output (ST_FULL): what is held, this one, and their join
                held += len(evs[-1])
                require_memory(2 * 13 * (held + cap), f"decoding the events of {self.path}")
            t, x, y, p = (np.empty(cap, np.int64), np.empty(cap, np.uint16), np.empty(cap, np.uint16),
                          np.empty(cap, np.uint8))
            tt, tk, tc = np.empty(cap_tr, np.int64), np.empty(cap_tr, np.uint8), np.empty(cap_tr, np.uint8)
            n, m, st, bad, _, _ = run(words[pos:], state, w, h, True, t, x, y, p, tt, tk, tc)
            evs.append(Events._trusted(t[:n], x[:n], y[:n], p[:n], self._size))
            trs.append(Triggers(tt[:m], tk[:m], tc[:m]))
            if st != ST_FULL:
                break
            pos += bad
        problem = None if st == ST_OK else self._word_problem(words, st, pos + bad, first)
        ev = evs[0] if len(evs) == 1 else Events.concatenate(evs, sensor_size=self._size)
        tr = trs[0] if len(trs) == 1 else Triggers.concatenate(trs)
        return ev, tr, problem

    def _word_problem(self, words, st, bad, first):
        """``(byte offset, why)`` of the word ``words[bad]`` (item ``first + bad`` of the file) that stopped a
        decoder with status ``st``."""
        at = self._start + self._item * (first + bad)
        if st == ST_COORD:
            w, h = self._size
            return at, f"an event lies outside the {w}x{h} sensor"
        if st == ST_TIME:
            return at, ("the time passes 2**63 - 1 us (int64) here, after more wraps of the time counter than any "
                        "recording holds: the file is damaged or crafted")
        kind = word_type(self.encoding, int(words[bad]), self.legacy_layout)
        return at, f"word of unknown type {kind} ({_TYPES[self.encoding][1]})"

    def _decode_block(self, b):
        """(Events, Triggers, problem) of block ``b``, from its state in the index; a problem stops salvage."""
        return self._decode(self._words(b), self._index()[b][0].copy(), b * self._per_block())

    def _through(self):
        """Yield ``(events, triggers, problem)`` block by block in one pass, without the index; the index rows
        it sees are kept, and become the index when the pass reaches the end without a problem."""
        state = self._initial_state()
        rows = []
        if self.encoding == EVT3:
            _whole._keep_temporaries_mapped()
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
        out: dict[str, Any] = {"encoding": self.encoding, "header": list(self._lines), "sensor_size_from": self.size_source}
        if self.encoding == EVT21:
            out["evt21_layout"] = "legacy" if self.legacy_layout else "64-bit"
        for line in self._lines:
            parts = line.split()
            if len(parts) == 2 and parts[0].lower() == "t0" and parts[1].lstrip("-").isdigit():
                out["header_t0_us"] = int(parts[1])
        return out

    def iter_events(self, chunk_events: int = 1_000_000, t_start_us: int | None = None,
                    t_end_us: int | None = None) -> Iterator[Events]:
        """The events with ``t_start_us <= t < t_end_us``, at most ``chunk_events`` at a time.

        The file is cut into blocks of whole events (indexed on the first pass); a window decodes only the
        blocks it overlaps. Also what :class:`EventStreamRecording` gives.

        Parameters
        ----------
        chunk_events : int
            Most events a chunk holds (at least 1).
        t_start_us : int, optional
            First time kept (µs, inclusive); None: from the start.
        t_end_us : int, optional
            End of the window (µs, exclusive); None: to the end.

        Yields
        ------
        Events
            The next chunk, in file order; together, what ``events`` returns.

        Raises
        ------
        FormatError
            At damage (an event off the sensor, a file cut inside an event, time going backwards in Event
            Stream), without salvage (with it, the chunks end there).
        EvtkError
            When ``chunk_events`` is below 1.
        """
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

    def events(self, t_start_us: int | None = None, t_end_us: int | None = None) -> Events:
        """The events with ``t_start_us <= t < t_end_us``, read at once.

        The whole file is decoded in one pass over its memory map once its event count is known;
        a window decodes only the blocks it overlaps.

        Parameters
        ----------
        t_start_us : int, optional
            First time kept (µs, inclusive); None: from the start.
        t_end_us : int, optional
            End of the window (µs, exclusive); None: to the end.

        Returns
        -------
        Events
            The events, in file order.

        Raises
        ------
        FormatError
            At damage (an event off the sensor, a file cut inside an event), without salvage.
        """
        self._check_open()
        if t_start_us is None and t_end_us is None and self._count:
            return self._whole()
        parts = list(self.iter_events(1 << 62, t_start_us, t_end_us))
        return Events.concatenate(parts, sensor_size=self._size) if parts else Events.empty(self._size)

    def _whole(self) -> Events:
        """Every event, block by block (:meth:`_through`, which leaves the index behind) into one set of columns
        sized by what the file's words can hold (pages never written cost no memory), so that the peak is the
        events plus one block's decoding, not the events twice. EVT 3.0 decodes its blocks on the reader's threads
        into exact-size columns (:func:`_whole.read_whole`), and so do EVT 2.0 and DAT where a second thread pays;
        on one thread they decode straight into their columns (:meth:`_whole_in_place`)."""
        if self.encoding == EVT3:
            return self._whole_threaded()
        if self.encoding in (EVT2, DAT):  # on threads where the events' memory (an event an item at most) pays for two
            threaded = _whole.threads_for(self._n_blocks(), 13 * self._count) > 1
            return self._whole_threaded() if threaded else self._whole_in_place()
        cap = {EVT21: self._count, ES: self._count // 5 + 1}[self.encoding]
        cols = _event_columns(cap)
        n = 0
        trs = []
        problem = None
        for ev, tr, problem in self._through():
            if n + len(ev) > len(cols[0]):  # EVT 2.1 vectors hold up to 32 events a word: grown
                grown = max(2 * len(cols[0]), n + len(ev))
                require_memory(13 * (grown + len(cols[0])), f"decoding the events of {self.path}")
            cols, n = _put_events(cols, n, ev)
            if len(tr):  # copied out: a view would keep the block's whole trigger buffers alive
                trs.append(Triggers(tr.t.copy(), tr.kind.copy(), tr.channel.copy()))
            if problem:
                self._stop(problem)
                break
        if self._triggers is None and not problem:
            self._triggers = Triggers.concatenate(trs)
        t, x, y, p = (c[:n] for c in cols)
        return Events._trusted(t, x, y, p, self._size)

    def _whole_in_place(self) -> Events:
        """:meth:`_whole` of an EVT 2.0 or DAT file on one thread, where a word (an item) holds one event at most: each
        block is decoded straight into its place in one set of columns as long as the file's words (no block's own
        columns, no copy from them, and no counting pass first: a third less time than :meth:`_whole_threaded` on one
        thread). The index rows, the triggers and a problem are those :meth:`_through` leaves."""
        run = self._runner()
        width, height = self._size
        per = self._per_block()
        t, x, y, p = _event_columns(self._count)
        cap_tr = min(per, self._count) if self.encoding == EVT2 else 0  # DAT holds no triggers
        tt, tk, tc = np.empty(cap_tr, np.int64), np.empty(cap_tr, np.uint8), np.empty(cap_tr, np.uint8)
        state = self._initial_state()
        rows, trs, problem, n = [], [], None, 0
        for b in range(self._n_blocks()):
            start, words = state.copy(), self._words(b)
            k, m, st, bad, lo, hi = run(words, state, width, height, True, t[n:], x[n:], y[n:], p[n:], tt, tk, tc)
            k, m = int(k), int(m)
            rows.append((start, k, m, int(lo) if k else 0, int(hi) if k else -1))
            if m:  # copied out: the buffers serve the next block
                trs.append(Triggers(tt[:m].copy(), tk[:m].copy(), tc[:m].copy()))
            n += k
            if st != ST_OK:  # ST_FULL cannot be: the columns hold an event a word
                problem = self._word_problem(words, st, int(bad), b * per)
                break
        if problem:
            self._stop(problem)
        else:
            if self._blocks is None:
                self._blocks = rows
            if self._triggers is None:
                self._triggers = Triggers.concatenate(trs)
        return Events._trusted(t[:n], x[:n], y[:n], p[:n], self._size)

    def _whole_threaded(self) -> Events:
        """:meth:`_whole` of an EVT 3.0, EVT 2.0 or DAT file, its blocks on the reader's threads
        (:func:`_whole.read_whole`): the events; the triggers and the index are kept when no problem stopped the
        read."""
        width, height = self._size
        got = _whole.read_whole(str(self.path), self._start, self._count, self._per_block(), width, height,
                                self._initial_state(), self._codec())
        if got["status"] != ST_OK:
            word = np.array([got["word"]], _DTYPE[self.encoding])
            self._stop(self._word_problem(word, got["status"], 0, got["bad"]))
        else:
            self._blocks = got["rows"]
            if self._triggers is None:
                self._triggers = Triggers(got["tt"], got["tk"], got["tch"])
        return Events._trusted(got["t"], got["x"], got["y"], got["p"], self._size)

    def triggers(self, t_start_us: int | None = None, t_end_us: int | None = None) -> Triggers:
        """The trigger edges with ``t_start_us <= t < t_end_us``.

        EVT 2.0 and 3.0 interleave the external trigger edges with the events, with their channel; DAT
        and Event Stream hold none (empty). Decoded once, then kept.

        Parameters
        ----------
        t_start_us : int, optional
            First time kept (µs, inclusive); None: from the start.
        t_end_us : int, optional
            End of the window (µs, exclusive); None: to the end.

        Returns
        -------
        Triggers
            Their times (µs), kinds and channels, in file order.
        """
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
    """An Event Stream (.es) recording of DVS or ATIS events (version 2.x), as Sepia, Tonic, event_stream and faery
    write them.

    The header is the text ``Event Stream``, the version (three bytes), the
    event type (1: DVS, 2: ATIS) and the sensor's width and height (16 bits
    each); events follow as a byte stream (see :func:`._fallbacks._es_dvs_run` and
    :func:`._fallbacks._es_atis_run`). y is stored from the bottom row up and read as
    evtk's rows from the top. An ATIS stream's events are its change-detection
    events; its threshold crossings (exposure measurements) are counted, in
    ``info()["left_out"]``, and left out. Generic and colour streams are
    named and refused.

    Parameters
    ----------
    path : str or os.PathLike
        The ``.es`` file.
    salvage : bool
        Read what is intact before damage instead of raising.
    sensor_size : tuple of (int, int), optional
        ``(width, height)`` in pixels, replacing the header's.
    """

    format = "event_stream"

    def __init__(self, path: str | os.PathLike[str], salvage: bool = False,  # noqa: D107 - the class says it
                 sensor_size: tuple[int, int] | None = None) -> None:
        BaseRecording.__init__(self, path, salvage)
        with open(self.path, "rb") as f:
            head = f.read(20)
        if not head.startswith(ES_MAGIC) or len(head) < 16:
            raise FormatError(self.path, 0, "not an Event Stream file (no 'Event Stream' header)")
        major = head[12]
        kind = head[15]
        if major != 2:
            raise FormatError(self.path, 12, f"Event Stream version {major}.{head[13]}.{head[14]}; evtk reads 2.x")
        if kind not in (1, 2):
            names = {0: "generic", 3: "display", 4: "colour"}  # as the format and event_stream number them
            raise FormatError(self.path, 15, f"Event Stream of {names.get(kind, f'type {kind}')} events; evtk reads "
                                             "DVS and ATIS events (types 1 and 2)")
        self.atis = kind == 2
        self._left_out: int | None = None  # ATIS: the threshold crossings left out, once a pass has counted them
        if len(head) < 20:
            raise FormatError(self.path, 16, "the file ends inside the Event Stream header")
        w, h = int.from_bytes(head[16:18], "little"), int.from_bytes(head[18:20], "little")
        self._size = sensor_dims(w, h, self.path, "the Event Stream header")
        self.size_source = "the header"
        if sensor_size is not None:
            self._size = sensor_dims(sensor_size[0], sensor_size[1], None, "sensor_size")
            self.size_source = "the caller"
        self.encoding = ES
        self._lines = [f"version {major}.{head[13]}.{head[14]}", "type atis" if self.atis else "type dvs"]
        self._start = 20
        self._item = 1
        self._file_bytes = os.path.getsize(self.path)
        self._count = self._file_bytes - self._start
        self._blocks = None
        self._triggers = None

    def _runner(self):
        """The ATIS decoder for an ATIS stream (evtk's compiled kernel, else numba's loop), else the DVS one."""
        return es_atis_run if self.atis else super()._runner()

    def _check_es_end(self, state):
        """:meth:`PropheseeRecording._check_es_end`, and an ATIS stream's count of threshold crossings left out."""
        if self.atis:
            self._left_out = int(state[_ES_LEFT])
        super()._check_es_end(state)

    def _extra_info(self):
        out = super()._extra_info()
        if self.atis:
            out["event_type"] = "atis"
            if self._left_out is not None:
                out["left_out"] = {"threshold crossings": self._left_out}
        return out

    def _whole(self) -> Events:
        """Every event, block by block straight into one set of columns: an Event Stream's events are at most a
        fifth of its bytes, so the columns hold them all and a block's events need no buffers of their own nor a
        copy out of them (a third of a whole read's time). The index and the end check are
        :meth:`PropheseeRecording._whole`'s."""
        t, x, y, p = _event_columns(self._count // 5 + 1)
        w, h = self._size
        run, none = self._runner(), _NO_OUT[4:]
        state = self._initial_state()
        rows, n = [], 0
        per = self._per_block()
        buf = bytearray(min(per, self._count))  # every block read into one buffer, the file opened once
        room = memoryview(buf)
        with open(self.path, "rb") as f:
            f.seek(self._start)
            for b in range(self._n_blocks()):
                start = state.copy()
                words = np.frombuffer(buf, np.uint8, f.readinto(room[:min(per, self._count - b * per)]))
                k, _, st, bad, lo, hi = run(words, state, w, h, True, t[n:], x[n:], y[n:], p[n:], *none)
                k = int(k)
                rows.append((start, k, 0, int(lo) if k else 0, int(hi) if k else -1))
                n += k
                if st != ST_OK:
                    self._stop(self._word_problem(words, st, bad, b * self._per_block()))
                    break
            else:
                if self._blocks is None:
                    self._blocks = rows
                    self._check_es_end(state)
                if self._triggers is None:
                    self._triggers = Triggers.concatenate([])
        return Events._trusted(t[:n], x[:n], y[:n], p[:n], self._size)
