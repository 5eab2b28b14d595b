"""AEDAT 1.0 and 2.0 (jAER) and AEDAT 3.1 (cAER, DV's predecessors) polarity events, read by content.

AEDAT 2.0: text header lines starting with ``#``, then 8-byte big-endian
records (32-bit address, 32-bit time stamp in microseconds, unwrapped when it
wraps: a step back from the counter's top half to its bottom half that is
shorter going forward, as jAER's 32-bit arithmetic takes it; any other step
back is damage, reported with its byte offset, never taken for a wrap). The
address layout depends on the camera, which the header's ``AEChip`` line
names: DAVIS cameras keep y in bits 22-30, x in bits 12-21, the polarity in
bit 11 and mark frame (APS) and IMU samples with bit 31 (left out, and
counted); the DVS128 keeps x in bits 1-7 (mirrored), y in bits 8-14 and OFF in
bit 0. jAER counts y from the bottom row; evtk counts it from the top, so y is
mirrored (``height - 1 - y``).

AEDAT 1.0: jAER's first format (DVS128 and its predecessor Tmpdiff128, files
often named ``.dat``), as 2.0 but with 6-byte records: a 16-bit big-endian
address in the DVS128's layout, then the 32-bit time stamp.

AEDAT 3.1: a text header ending ``#!END-HEADER``, then packets of a 28-byte
little-endian header (type, source, event size, time-stamp offset, overflow
counter, capacity, count, valid count) and their events. Polarity packets
(type 1) hold 8-byte events: a 32-bit word with the valid flag (bit 0), the
polarity (bit 1), y (bits 2-16) and x (bits 17-31), and a 31-bit time stamp
extended by the packet's overflow counter (a negative counter is damage). cAER counts y from the top, as
evtk does. Other packets (special, frame, IMU) are listed and left out.

Both are decoded with numpy a block at a time: windows and streaming hold one
block of events; the block index comes from reading the file once.
"""

from __future__ import annotations

import os
import re
import struct
from collections.abc import Iterator
from typing import cast

import numpy as np

from ..errors import EvtkError, FormatError
from ..events import Events
from .base import BaseRecording, Damage, StreamInfo, sensor_dims, text_header

__all__ = ["LegacyAedatRecording", "CHIP_SIZES", "LAYOUTS"]

#: The AEDAT 2.0 address layouts (``layout=``, ``evtk --layout``).
LAYOUTS = ("dvs128", "davis")
#: A sensor inferred from the coordinates narrower than this on a side is refused (a wrong layout's signature).
MIN_INFERRED_SIDE = 16

#: Sensor sizes of the cameras an AEDAT 2.0 header may name (its AEChip class, matched case-insensitively).
CHIP_SIZES = {"dvs128": (128, 128), "davis240": (240, 180), "davis346": (346, 260), "davis640": (640, 480),
              "davis208": (208, 192), "davis128": (128, 128), "dvs640": (640, 480)}
#: AEDAT 1.0's and 2.0's records, big-endian: a 16-bit (1.0: the DVS128's layout) or 32-bit address, then a
#: 32-bit time stamp.
_RECORDS = {"1.0": np.dtype([("address", ">u2"), ("t", ">u4")]), "2.0": np.dtype([("address", ">u4"), ("t", ">u4")])}
BLOCK_RECORDS = 1 << 20
_PACKET_HEADER = 28
_TYPE_NAMES = {0: "special", 1: "polarity", 2: "frame", 3: "imu6", 4: "imu9", 5: "sample", 6: "ear", 7: "config",
               8: "point1d", 9: "point2d", 10: "point3d", 11: "point4d", 12: "spike"}


#: The longest text header read (the largest jAER header among the real recordings evtk is checked
#: against is 175 KB: every preference of a DAVIS240 camera).
MAX_HEADER_BYTES = 4 << 20
_END_V3 = re.compile(rb"^#!END-HEADER", re.M)
_WRAP = 1 << 32  # AEDAT 2.0 time stamps are 32-bit counters
_WRAPS_MOST = (2**63 - 1) >> 32  # the most wraps whose times fit int64
_DIGITS = re.compile(r"\d+")


def _header_lines(path, v3):
    """Header lines and where the data starts (:func:`~evtk.io.base.text_header`: a line is header only if it
    is text, so a first record whose top byte is 0x23, '#', is not taken for one, as jAER's rule would)."""
    return text_header(path, b"#", MAX_HEADER_BYTES, _END_V3 if v3 else None)


def _size_from_header(text):
    """``(width, height)`` digits from the first ``dvssizex`` ... ``dvssizey`` pair in the lowered, joined
    header, or None: the values following each name, y named after x. Linear: each name is looked for once
    (when the first x or y has no digits after it, no later one has)."""
    i = text.find("dvssizex")
    if i < 0:
        return None
    mx = _DIGITS.search(text, i + 8)
    if mx is None:
        return None
    j = text.find("dvssizey", mx.end())
    if j < 0:
        return None
    my = _DIGITS.search(text, j + 8)
    return None if my is None else (mx.group(), my.group())


def _unwrap(ts, state):
    """AEDAT 2.0's 32-bit time stamps ``ts`` as 64-bit microseconds, given ``state`` = (wraps so far, the raw
    stamp before ``ts[0]`` or -1).

    A step back is a wrap of the counter only when going on past 2**32 is the shorter way, that is when the
    stamp moves from the counter's top half to its bottom half by less than 2**31 us forward, as jAER's
    32-bit time arithmetic takes it; any other step back is an error, not a wrap (jAER reports such steps
    as non-monotonic time).

    Returns
    -------
    t : numpy.ndarray
        The stamps unwrapped (int64).
    state : tuple of int
        (wraps, last raw stamp) after ``ts`` or, when one steps back, before the first that does.
    bad : int or None
        The index of the first stamp that steps back without wrapping, or whose wrap takes the time past
        2**63 - 1 µs (after 2**31 wraps, 32 GiB of records at the least: no recording runs that long).
    past : bool
        Whether ``bad`` is such a wrap.
    """
    epoch, prev = state
    if not len(ts):
        return ts, state, None, False
    before = np.empty(len(ts), np.int64)
    before[0] = prev
    before[1:] = ts[:-1]
    step = ts - before
    back = step < 0
    if prev < 0:
        back[0] = False
    wrap = back & (step + _WRAP < _WRAP >> 1)
    wrong = np.flatnonzero(back & ~wrap)
    bad = int(wrong[0]) if len(wrong) else None
    if bad is not None:
        ts, wrap = ts[:bad], wrap[:bad]
    wraps = np.cumsum(wrap) + epoch
    past = bool(len(wraps)) and int(wraps[-1]) > _WRAPS_MOST
    if past:
        bad = int(np.argmax(wraps > _WRAPS_MOST))
        ts, wraps = ts[:bad], wraps[:bad]
    t = ts + (wraps << 32)
    if bad is not None:
        return t, ((int(wraps[-1]) if len(ts) else epoch), int(ts[-1]) if len(ts) else prev), bad, past
    return t, (int(wraps[-1]), int(ts[-1])), None, False


class LegacyAedatRecording(BaseRecording):
    """An AEDAT 1.0, 2.0 or 3.1 file's polarity events.

    Parameters
    ----------
    path : str or os.PathLike
        The ``.aedat`` file (``#!AER-DAT1.0``, ``#!AER-DAT2.0`` or ``#!AER-DAT3.1``).
    salvage : bool
        Read what is intact before damage instead of raising.
    sensor_size : tuple of (int, int), optional
        For files whose header names no known camera (else inferred from
        the largest coordinates, with a warning).
    layout : {"dvs128", "davis"}, optional
        AEDAT 2.0: the address layout, overriding the header's ``AEChip``
        and the layout found from the addresses' bits. AEDAT 1.0's 16-bit
        addresses are the DVS128's only.
    """

    format = "aedat-legacy"

    def __init__(self, path: str | os.PathLike[str], salvage: bool = False,
                 sensor_size: tuple[int, int] | None = None, layout: str | None = None) -> None:
        super().__init__(path, salvage)
        with open(self.path, "rb") as f:
            first = f.readline(64)
        m = re.match(rb"#!AER-DAT(\d)\.(\d)", first)
        if not m:
            raise FormatError(self.path, 0, "not an AEDAT 1.0, 2.0 or 3.x file (no '#!AER-DAT' line)")
        self.version = f"{m.group(1).decode()}.{m.group(2).decode()}"
        if self.version not in ("1.0", "2.0", "3.0", "3.1"):
            raise FormatError(self.path, 0, f"AEDAT version {self.version} is not read (evtk reads 1.0, 2.0, 3.1 and "
                                            "4.0)")
        self._v3 = self.version.startswith("3")
        self._record = _RECORDS[self.version].itemsize if self.version in _RECORDS else 0  # 3.x: packets
        self._lines, self._start = _header_lines(self.path, self._v3)
        if self._v3 and not (self._lines and self._lines[-1].startswith("#!END-HEADER")):
            raise FormatError(self.path, self._start, f"the AEDAT {self.version} header never ends (no #!END-HEADER line)")
        self._file_bytes = os.path.getsize(self.path)
        text = "\n".join(self._lines).lower()
        bare = text.replace("_", "")
        self.chip = next((name for name in sorted(CHIP_SIZES, key=len, reverse=True) if name in bare), None)
        if layout is not None and layout not in LAYOUTS:
            raise EvtkError(f"layout must be one of {', '.join(LAYOUTS)}, not {layout!r}")
        if self.version == "1.0":  # 16-bit addresses: the DVS128's (and the Tmpdiff128's, its predecessor's)
            if layout == "davis":
                raise EvtkError(f"{self.path}: AEDAT 1.0 holds 16-bit addresses, a DVS128's; it has no DAVIS layout")
            self.chip = "dvs128"
        elif layout is not None and not self._v3:
            self.chip = "dvs128" if layout == "dvs128" else (self.chip if self.chip not in (None, "dvs128") else
                                                             "davis")
        elif self.chip is None and not self._v3:
            self.chip = self._chip_from_addresses()
        size = None
        found = _size_from_header(text)
        if found:
            size = sensor_dims(found[0], found[1], self.path, "the header's dvsSizeX/dvsSizeY")
        elif self.chip in CHIP_SIZES:
            size = CHIP_SIZES[self.chip]
        if sensor_size is not None:
            size = sensor_dims(sensor_size[0], sensor_size[1], None, "sensor_size")
        self._size: tuple[int, int] = cast("tuple[int, int]", size)  # None only until _infer_size, below, sets it
        self.skipped: dict[str, int] = {}  # what was left out: {"frame": n, "imu6": n, ...}
        self._block_stats = None
        self._blocks = self._index_blocks()
        if self._size is None:
            self._infer_size()

    def _chip_from_addresses(self):
        """AEDAT 2.0 without a named camera: "dvs128" when no address of the first records uses a bit above
        14 (the DVS128 keeps x, y and the polarity in bits 0-14; a DAVIS's x and y start at bit 12 and 22),
        else "davis". The choice is noted in :attr:`warnings`."""
        with open(self.path, "rb") as f:
            f.seek(self._start)
            raw = f.read(8 * 65536)
        addr = np.frombuffer(raw[:len(raw) - len(raw) % 8], ">u4")[0::2]
        if len(addr) and int(addr.max()) < (1 << 15) and int(addr.max()) > 0:
            self.warnings.append("the header names no camera; every address fits in bits 0-14, as a DVS128's do: "
                                 "read as a 128x128 DVS128 (--layout davis to read it as a DAVIS)")
            return "dvs128"
        return "davis" if len(addr) else None

    # -- layout ---------------------------------------------------------------------------------------------
    def _index_blocks(self):
        """Blocks of records (1.0, 2.0) or of polarity packets (3.1): a list of byte ranges per block."""
        if not self._v3:
            body, size = self._file_bytes - self._start, self._record
            n = body // size
            if body % size:
                self._problem(self._start + size * n, f"the file ends inside a record ({body % size} of {size} bytes)")
            return [[(self._start + size * a, size * min(BLOCK_RECORDS, n - a))] for a in range(0, n, BLOCK_RECORDS)]
        blocks, cur, held = [], [], 0
        pos = self._start
        with open(self.path, "rb") as f:
            while pos < self._file_bytes:
                f.seek(pos)
                head = f.read(_PACKET_HEADER)
                if len(head) < _PACKET_HEADER:
                    self._problem(pos, "the file ends inside a packet header")
                    break
                typ, _src, size, _off, overflow, capacity, number, _valid = struct.unpack("<hhiiiiii", head)
                if size <= 0 or capacity < 0 or number < 0 or number > capacity or size > 1 << 20:
                    self._problem(pos, f"packet header is damaged (type {typ}, event size {size}, capacity "
                                       f"{capacity}, count {number})")
                    break
                length = size * capacity
                if pos + _PACKET_HEADER + length > self._file_bytes:
                    self._problem(pos, f"the packet claims {length} bytes but only "
                                       f"{self._file_bytes - pos - _PACKET_HEADER} remain")
                    break
                if typ == 1:
                    if overflow < 0:
                        self._problem(pos + 12, f"polarity packet with a negative time-stamp overflow counter "
                                                f"({overflow}): its time stamps would be negative")
                        break
                    if size != 8:
                        self._problem(pos, f"polarity events of {size} bytes (8 expected)")
                        break
                    cur.append((pos + _PACKET_HEADER, 8 * number, overflow))
                    held += number
                    if held >= BLOCK_RECORDS:
                        blocks.append(cur)
                        cur, held = [], 0
                else:
                    name = _TYPE_NAMES.get(typ, f"type {typ}")
                    self.skipped[name] = self.skipped.get(name, 0) + number
                pos += _PACKET_HEADER + length
        if cur:
            blocks.append(cur)
        return blocks

    def _problem(self, at, reason):
        if not self.salvage:
            raise FormatError(self.path, at, reason + "; salvage reads what comes before")
        if self.damage is None:
            self.damage = Damage(at, reason)

    #: The 2.0 time state before the first record: no wraps yet, no stamp before it.
    _TIME_START = (0, -1)

    def _read_block(self, k, state):
        """Block ``k``'s events as stored (y not yet mirrored) from ``state``, the (2.0) time state before it.

        Returns ``(t, x, y, p, left_out, state_after, problem)``: ``left_out`` counts the records left out
        (APS and IMU samples), ``state`` is ``(wraps of the 32-bit time, last raw stamp or -1)`` and
        ``problem`` is None or ``(byte offset, reason)`` of a time stamp that steps back without wrapping;
        the columns then stop before that event.
        """
        parts = []
        with open(self.path, "rb") as f:
            for rng in self._blocks[k]:
                f.seek(rng[0])
                parts.append((f.read(rng[1]), rng[2] if len(rng) > 2 else None))
        if not self._v3:
            rec = np.frombuffer(parts[0][0], _RECORDS[self.version])
            addr, stamps = rec["address"].astype(np.int64), rec["t"].astype(np.int64)
            if self.chip == "dvs128":
                keep = np.ones(len(addr), bool)
            else:
                keep = (addr >> 31) == 0  # bit 31: an APS or IMU sample
            rows = np.flatnonzero(keep)
            addr = addr[rows]
            t, state, bad, past = _unwrap(stamps[rows], state)
            problem = None
            if bad is not None:
                at = self._blocks[k][0][0] + self._record * int(rows[bad]) + self._record - 4
                problem = (at, f"the time passes 2**63 - 1 us (int64) here, after {_WRAPS_MOST + 1} wraps of the "
                               "32-bit time stamp: no recording runs that long, so the file is damaged or crafted"
                           if past else f"the time stamp steps back from {int(state[1])} to "
                           f"{int(stamps[rows[bad]])} us, which is no 32-bit wrap (a wrap goes from the "
                           "top half of the counter to the bottom half)")
                addr, t = addr[:bad], t[:bad]
            if self.chip == "dvs128":
                x = 127 - ((addr >> 1) & 0x7F)
                yraw = (addr >> 8) & 0x7F
                p = 1 - (addr & 1)
            else:
                x = (addr >> 12) & 0x3FF
                yraw = (addr >> 22) & 0x1FF
                p = (addr >> 11) & 1
            return t, x, yraw, p, len(keep) - len(rows), state, problem
        ts_parts, d_parts = [], []
        for raw, overflow in parts:
            a = np.frombuffer(raw, "<u4")
            d_parts.append(a[0::2].astype(np.int64))
            ts_parts.append((a[1::2].astype(np.int64) & 0x7FFFFFFF) | (np.int64(overflow) << 31))
        d = np.concatenate(d_parts) if d_parts else np.zeros(0, np.int64)
        t = np.concatenate(ts_parts) if ts_parts else np.zeros(0, np.int64)
        keep = (d & 1) == 1  # the valid flag
        return t[keep], (d[keep] >> 17) & 0x7FFF, (d[keep] >> 2) & 0x7FFF, (d[keep] >> 1) & 1, 0, state, None

    def _infer_size(self):
        mx, my = self._stats()[1]
        if mx + 1 < MIN_INFERRED_SIDE or my + 1 < MIN_INFERRED_SIDE:
            raise FormatError(self.path, self._start, f"the events' addresses span only {mx + 1}x{my + 1} pixels "
                                                      f"as {self.chip or 'DAVIS'} addresses: no camera has such a "
                                                      "sensor; name the layout (--layout dvs128|davis) or the size "
                                                      "(--sensor-size WxH)")
        self._size = (mx + 1, my + 1)
        self.warnings.append(f"the header names no known camera; the sensor size {self._size} is inferred from the "
                             "coordinates" + ("" if self._v3 else " (y is mirrored about that height)"))

    def _stats(self):
        """One pass, on first use: per block (events, min t, max t, the 2.0 time state before it), and the
        largest (x, y) stored; the records left out are counted on the way. A time stamp that steps back
        without wrapping raises, or with salvage ends the recording before it."""
        if self._block_stats is None:
            rows, state, mx, my = [], self._TIME_START, 0, 0
            for k in range(len(self._blocks)):
                t, x, y, _, left_out, after, problem = self._read_block(k, state)
                if left_out:
                    self.skipped["aps/imu samples"] = self.skipped.get("aps/imu samples", 0) + left_out
                rows.append((len(t), int(t.min()) if len(t) else 0, int(t.max()) if len(t) else -1, state))
                if len(x):
                    mx, my = max(mx, int(x.max())), max(my, int(y.max()))
                state = after
                if problem:
                    self._problem(*problem)
                    del self._blocks[k + 1:]
                    break
            self._block_stats = rows, (mx, my)
        return self._block_stats

    def _decode(self, k):
        """Events of block ``k`` in evtk's convention, or a FormatError / salvage stop."""
        t, x, y, p, _, _, _ = self._read_block(k, self._stats()[0][k][3])
        w, h = self._size
        if not self._v3:
            y = (h - 1) - y
        bad = np.flatnonzero((x >= w) | (y < 0) | (y >= h))
        problem = None
        if len(bad):
            problem = f"an event lies outside the {w}x{h} sensor (event {int(bad[0])} of block {k})"
            t, x, y, p = t[:bad[0]], x[:bad[0]], y[:bad[0]], p[:bad[0]]
        ev = Events(t, x.astype(np.uint16), y.astype(np.uint16), p.astype(np.uint8), self._size)
        return ev, problem

    # -- interface ----------------------------------------------------------------------------------------------
    @property
    def sensor_size(self):
        return self._size

    @property
    def metadata(self) -> dict:
        return {"aedat_version": self.version, "chip": self.chip, "header": list(self._lines)}

    def iter_events(self, chunk_events: int = 1_000_000, t_start_us: int | None = None,
                    t_end_us: int | None = None) -> Iterator[Events]:
        """The events with ``t_start_us <= t < t_end_us``, at most ``chunk_events`` at a time.

        The file is read in blocks of whole events; a window skips blocks that end before it or begin
        after it.

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
            At damage (a file cut inside an event, time going backwards), without salvage (with it, the
            chunks end there).
        EvtkError
            When ``chunk_events`` is below 1.
        """
        self._check_open()
        chunk_events = int(chunk_events)
        if chunk_events < 1:
            raise EvtkError(f"chunk_events must be at least 1, got {chunk_events}")
        pending, held = [], 0
        for k, (n, lo, hi, _) in enumerate(self._stats()[0]):
            if n and ((t_start_us is not None and hi < t_start_us) or (t_end_us is not None and lo >= t_end_us)):
                continue
            ev, problem = self._decode(k)
            if t_start_us is not None or t_end_us is not None:
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

    def _stop(self, reason):
        if not self.salvage:
            raise FormatError(self.path, None, reason)
        if self.damage is None:
            self.damage = Damage(None, reason)

    def events(self, t_start_us: int | None = None, t_end_us: int | None = None) -> Events:
        """The events with ``t_start_us <= t < t_end_us``, read at once.

        The polarity events only (AEDAT 3.1's other event types and APS samples are skipped).

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
            At damage (a file cut inside an event, time going backwards), without salvage.
        """
        parts = list(self.iter_events(1 << 62, t_start_us, t_end_us))
        return Events.concatenate(parts, sensor_size=self._size) if parts else Events.empty(self._size)

    @property
    def streams(self):
        stats = self._stats()[0]
        n = sum(s[0] for s in stats)
        lo = min((s[1] for s in stats if s[0]), default=None)
        hi = max((s[2] for s in stats if s[0]), default=None)
        out = [StreamInfo(0, "events", "EVTS", packets=len(stats), count=n, t_start_us=lo, t_end_us=hi,
                          sensor_size=self._size)]
        for i, (name, count) in enumerate(sorted(self.skipped.items()), start=1):
            out.append(StreamInfo(i, name, name.upper()[:4], count=count))
        return out

    def _extra_info(self):
        return {"aedat_version": self.version, "chip": self.chip, "left_out": dict(self.skipped)}
