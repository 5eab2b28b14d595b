"""AEDAT 2.0 (jAER) and AEDAT 3.1 (cAER, DV's predecessors) polarity events, read by content.

AEDAT 2.0: text header lines starting with ``#``, then 8-byte big-endian
records (32-bit address, 32-bit time stamp in microseconds, unwrapped when it
wraps). The address layout depends on the camera, which the header's
``AEChip`` line names: DAVIS cameras keep y in bits 22-30, x in bits 12-21,
the polarity in bit 11 and mark frame (APS) and IMU samples with bit 31 (left
out, and counted); the DVS128 keeps x in bits 1-7 (mirrored), y in bits 8-14
and OFF in bit 0. jAER counts y from the bottom row; evtk counts it from the
top, so y is mirrored (``height - 1 - y``).

AEDAT 3.1: a text header ending ``#!END-HEADER``, then packets of a 28-byte
little-endian header (type, source, event size, time-stamp offset, overflow
counter, capacity, count, valid count) and their events. Polarity packets
(type 1) hold 8-byte events: a 32-bit word with the valid flag (bit 0), the
polarity (bit 1), y (bits 2-16) and x (bits 17-31), and a 31-bit time stamp
extended by the packet's overflow counter. cAER counts y from the top, as
evtk does. Other packets (special, frame, IMU) are listed and left out.

Both are decoded with numpy a block at a time: windows and streaming hold one
block of events; the block index comes from reading the file once.
"""

from __future__ import annotations

import os
import re
import struct

import numpy as np

from ..errors import EvtkError, FormatError
from ..events import Events
from .base import BaseRecording, Damage, StreamInfo, sensor_dims

__all__ = ["LegacyAedatRecording", "CHIP_SIZES"]

#: Sensor sizes of the cameras an AEDAT 2.0 header may name (its AEChip class, matched case-insensitively).
CHIP_SIZES = {"dvs128": (128, 128), "davis240": (240, 180), "davis346": (346, 260), "davis640": (640, 480),
              "davis208": (208, 192), "davis128": (128, 128), "dvs640": (640, 480)}
BLOCK_RECORDS = 1 << 20
_PACKET_HEADER = 28
_TYPE_NAMES = {0: "special", 1: "polarity", 2: "frame", 3: "imu6", 4: "imu9", 5: "sample", 6: "ear", 7: "config",
               8: "point1d", 9: "point2d", 10: "point3d", 11: "point4d", 12: "spike"}


_TEXT = re.compile(rb"#[\x20-\x7e\t]*\r?\n\Z")


def _header_lines(path, v3):
    """Header lines and where the data starts. A line is header only if it is text: '#', printable ASCII and a
    line end (jAER's own rule, a leading '#', would take a first record whose top byte is 0x23 for text)."""
    lines, pos = [], 0
    with open(path, "rb") as f:
        while True:
            line = f.readline(1 << 16)
            if not _TEXT.match(line):
                break
            pos += len(line)
            if pos > 1 << 24:
                raise FormatError(path, 0, "the text header runs past 16 MiB")
            lines.append(line.decode("utf-8", "replace").strip())
            if v3 and line.startswith(b"#!END-HEADER"):
                break
    return lines, pos


class LegacyAedatRecording(BaseRecording):
    """An AEDAT 2.0 or 3.1 file's polarity events.

    Parameters
    ----------
    path : str or os.PathLike
    salvage : bool
        Read what is intact before damage instead of raising.
    sensor_size : (int, int), optional
        For files whose header names no known camera (else inferred from
        the largest coordinates, with a warning).
    """

    format = "aedat-legacy"

    def __init__(self, path, salvage=False, sensor_size=None):
        super().__init__(path, salvage)
        with open(self.path, "rb") as f:
            first = f.readline(64)
        m = re.match(rb"#!AER-DAT(\d)\.(\d)", first)
        if not m:
            raise FormatError(self.path, 0, "not an AEDAT 2.0 or 3.x file (no '#!AER-DAT' line)")
        self.version = f"{m.group(1).decode()}.{m.group(2).decode()}"
        if self.version not in ("2.0", "3.0", "3.1"):
            raise FormatError(self.path, 0, f"AEDAT version {self.version} is not read (evtk reads 2.0, 3.1 and 4.0)")
        self._v3 = self.version.startswith("3")
        self._lines, self._start = _header_lines(self.path, self._v3)
        if self._v3 and not (self._lines and self._lines[-1].startswith("#!END-HEADER")):
            raise FormatError(self.path, self._start, f"the AEDAT {self.version} header never ends (no #!END-HEADER line)")
        self._file_bytes = os.path.getsize(self.path)
        text = "\n".join(self._lines).lower()
        self.chip = None
        for name in sorted(CHIP_SIZES, key=len, reverse=True):
            if name in text.replace("_", ""):
                self.chip = name
                break
        size = None
        found = re.search(r"dvssizex[^0-9]*(\d+).*?dvssizey[^0-9]*(\d+)", text, re.S)
        if found:
            size = sensor_dims(found.group(1), found.group(2), self.path, "the header's dvsSizeX/dvsSizeY")
        elif self.chip:
            size = CHIP_SIZES[self.chip]
        if sensor_size is not None:
            size = sensor_dims(sensor_size[0], sensor_size[1], None, "sensor_size")
        self._size = size
        self.skipped = {}  # what was left out: {"frame": n, "imu6": n, ...}
        self._block_stats = None
        self._blocks = self._index_blocks()
        if self._size is None:
            self._infer_size()

    # -- layout ---------------------------------------------------------------------------------------------
    def _index_blocks(self):
        """Blocks of records (2.0) or of polarity packets (3.1): a list of byte ranges per block."""
        if not self._v3:
            body = self._file_bytes - self._start
            n = body // 8
            if body % 8:
                self._problem(self._start + 8 * n, f"the file ends inside a record ({body % 8} of 8 bytes)")
            return [[(self._start + 8 * a, 8 * min(BLOCK_RECORDS, n - a))] for a in range(0, n, BLOCK_RECORDS)]
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

    def _read_block(self, k, epoch=0):
        """(t, x, y, p) of block ``k`` as stored (y not yet mirrored), the records left out of it, and (2.0)
        how often the 32-bit time had wrapped by its end, given ``epoch`` wraps before it."""
        parts = []
        with open(self.path, "rb") as f:
            for rng in self._blocks[k]:
                f.seek(rng[0])
                parts.append((f.read(rng[1]), rng[2] if len(rng) > 2 else None))
        if not self._v3:
            raw = np.frombuffer(parts[0][0], ">u4")
            addr = raw[0::2].astype(np.int64)
            ts = raw[1::2].astype(np.int64)
            wraps = np.cumsum(np.diff(np.concatenate([[self._prev_ts(k)], ts])) < 0) + epoch
            t = ts + (wraps << 32)
            if self.chip == "dvs128":
                keep = np.ones(len(addr), bool)
                x = 127 - ((addr >> 1) & 0x7F)
                yraw = (addr >> 8) & 0x7F
                p = 1 - (addr & 1)
            else:
                keep = (addr >> 31) == 0  # bit 31: an APS or IMU sample
                x = (addr >> 12) & 0x3FF
                yraw = (addr >> 22) & 0x1FF
                p = (addr >> 11) & 1
            end = int(wraps[-1]) if len(wraps) else epoch
            return t[keep], x[keep], yraw[keep], p[keep], int(np.count_nonzero(~keep)), end
        ts_parts, d_parts = [], []
        for raw, overflow in parts:
            a = np.frombuffer(raw, "<u4")
            d_parts.append(a[0::2].astype(np.int64))
            ts_parts.append((a[1::2].astype(np.int64) & 0x7FFFFFFF) | (np.int64(overflow) << 31))
        d = np.concatenate(d_parts) if d_parts else np.zeros(0, np.int64)
        t = np.concatenate(ts_parts) if ts_parts else np.zeros(0, np.int64)
        keep = (d & 1) == 1  # the valid flag
        return t[keep], (d[keep] >> 17) & 0x7FFF, (d[keep] >> 2) & 0x7FFF, (d[keep] >> 1) & 1, 0, 0

    def _prev_ts(self, k):
        """AEDAT 2.0: the raw time stamp before block ``k`` (to carry the wrap count over)."""
        if k == 0:
            return -1
        at = self._blocks[k][0][0] - 4
        with open(self.path, "rb") as f:
            f.seek(at)
            return int.from_bytes(f.read(4), "big")

    def _infer_size(self):
        mx, my = self._stats()[1]
        self._size = (mx + 1, my + 1)
        self.warnings.append(f"the header names no known camera; the sensor size {self._size} is inferred from the "
                             "coordinates" + ("" if self._v3 else " (y is mirrored about that height)"))

    def _stats(self):
        """One pass, on first use: per block (events, min t, max t, time wraps before it), and the largest
        (x, y) stored; the records left out are counted on the way."""
        if self._block_stats is None:
            rows, epoch, mx, my = [], 0, 0, 0
            for k in range(len(self._blocks)):
                t, x, y, _, left_out, end = self._read_block(k, epoch)
                if left_out:
                    self.skipped["aps/imu samples"] = self.skipped.get("aps/imu samples", 0) + left_out
                rows.append((len(t), int(t.min()) if len(t) else 0, int(t.max()) if len(t) else -1, epoch))
                if len(x):
                    mx, my = max(mx, int(x.max())), max(my, int(y.max()))
                epoch = end
            self._block_stats = rows, (mx, my)
        return self._block_stats

    def _decode(self, k):
        """Events of block ``k`` in evtk's convention, or a FormatError / salvage stop."""
        t, x, y, p, _, _ = self._read_block(k, self._stats()[0][k][3])
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

    def iter_events(self, chunk_events: int = 1_000_000, t_start_us=None, t_end_us=None):
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

    def events(self, t_start_us=None, t_end_us=None) -> Events:
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
