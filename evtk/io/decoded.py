"""Formats decoded whole into memory: text events (CSV or whitespace) and the N-MNIST / N-Caltech101 binary.

Neither format has an index or blocks, and both are small in practice (a
text file a few million lines, an N-MNIST sample a few thousand events), so
the file is decoded once, on first use, after its size is checked against
the memory budget (:func:`evtk.limits.require_memory`); windows, streaming
(``iter_events``) and ``evtk info`` then work on the decoded columns.

Text events
    One event a line: time, x, y, polarity, separated by commas, tabs or
    spaces. An optional first line of column names (``t,x,y,p``,
    ``timestamp x y polarity``, faery's ``t,x@W,y@H,on``) sets the column
    order, and faery's names carry the sensor size. An optional first line
    of two integers gives the sensor size; which is width and which height
    is taken from the events (both orders are tried; when both fit, width
    first, as E2VID's ``events.txt`` writes it, with a warning). Times are
    seconds when most lines have a decimal point, else whole microseconds
    (a stray dot on one line does not rescale the file), unless
    ``time_unit`` says otherwise. Polarity 1 (or ``true``) is ON; 0, -1 (or
    ``false``) OFF.

N-MNIST binary (Orchard et al. 2015; N-Caltech101 and N-CARS' ``.bin`` too)
    Five bytes an event: x, y, then the polarity in bit 7 of the third byte
    and a 23-bit microsecond time stamp in the rest of the third, the fourth
    and the fifth (big-endian). An event with y = 240 is no event: it adds
    2**13 us to every later time stamp (the dataset's overflow marker). The
    files carry no sensor size: 34x34 (N-MNIST's) when every event fits,
    else the smallest size that holds them, with a note.
"""

from __future__ import annotations

import os
import re
import warnings
from collections.abc import Iterator, Sequence

import numpy as np

from ..errors import EvtkError, FormatError
from ..events import Events, Triggers
from ..limits import require_memory
from .base import BaseRecording, Damage, StreamInfo, sensor_dims

__all__ = ["DecodedRecording", "TextRecording", "NmnistRecording", "csv_lines", "sniff_text", "sniff_nmnist",
           "TIME_UNITS"]

#: microseconds per unit, for ``time_unit``
TIME_UNITS = {"s": 1_000_000.0, "ms": 1_000.0, "us": 1.0, "ns": 1e-3}
_MAX_TEXT_HEADER = 4096


class DecodedRecording(BaseRecording):
    """A recording decoded whole on first use; subclasses provide ``_decode() -> (Events, Triggers)``.

    Parameters
    ----------
    path : str or os.PathLike
        The file.
    salvage : bool
        Keep what decodes before the first damage instead of raising.
    sensor_size : tuple of (int, int), optional
        Overrides the size the file gives or its events imply.
    """

    def __init__(self, path: str | os.PathLike[str], salvage: bool = False,
                 sensor_size: tuple[int, int] | None = None) -> None:
        super().__init__(path, salvage)
        self._given_size = None if sensor_size is None else sensor_dims(sensor_size[0], sensor_size[1], None,
                                                                        "sensor_size")
        self._events: Events | None = None
        self._triggers = Triggers()
        self._file_bytes = os.path.getsize(self.path)

    def _decode(self) -> tuple[Events, Triggers]:  # pragma: no cover - overridden
        raise NotImplementedError

    def _stop(self, offset: int, reason: str):
        """Damage at ``offset``: raise, or (salvage) note it; the caller keeps what came before."""
        if not self.salvage:
            raise FormatError(self.path, offset, reason)
        if self.damage is None:
            self.damage = Damage(offset, reason)

    def _all(self) -> Events:
        self._check_open()
        if self._events is None:
            self._events, self._triggers = self._decode()
        return self._events

    @property
    def sensor_size(self):
        return self._all().sensor_size

    def events(self, t_start_us: int | None = None, t_end_us: int | None = None) -> Events:
        """Events with ``t_start_us <= t < t_end_us`` (None leaves a side open).

        Parameters
        ----------
        t_start_us, t_end_us : int, optional
            The window in microseconds.

        Returns
        -------
        Events
            The events of the window, in file order.
        """
        ev = self._all()
        if t_start_us is None and t_end_us is None:
            return ev
        return ev.between(t_start_us, t_end_us)

    def triggers(self, t_start_us: int | None = None, t_end_us: int | None = None) -> Triggers:
        """The file's trigger edges (text and N-MNIST files hold none).

        Parameters
        ----------
        t_start_us, t_end_us : int, optional
            The window in microseconds.

        Returns
        -------
        Triggers
            Empty for these formats.
        """
        self._all()
        return self._triggers.between(t_start_us, t_end_us)

    def iter_events(self, chunk_events: int = 1_000_000, t_start_us: int | None = None,
                    t_end_us: int | None = None) -> Iterator[Events]:
        """The events of a window, ``chunk_events`` at a time.

        Parameters
        ----------
        chunk_events : int
            Events per chunk (at least 1).
        t_start_us, t_end_us : int, optional
            The window in microseconds.

        Yields
        ------
        Events
            Consecutive chunks.
        """
        chunk_events = int(chunk_events)
        if chunk_events < 1:
            raise EvtkError(f"chunk_events must be at least 1, got {chunk_events}")
        ev = self.events(t_start_us, t_end_us)
        for k in range(0, len(ev), chunk_events):
            yield ev[k:k + chunk_events]

    @property
    def streams(self) -> list[StreamInfo]:
        ev = self._all()
        lo = int(ev.t.min()) if len(ev) else None
        hi = int(ev.t.max()) if len(ev) else None
        return [StreamInfo(0, "events", "EVTS", packets=1, count=len(ev), t_start_us=lo, t_end_us=hi,
                           sensor_size=ev.sensor_size)]


# -- text ---------------------------------------------------------------------------------------------------------

_NAMES = {"t": "t", "ts": "t", "time": "t", "timestamp": "t", "timestamps": "t", "t_us": "t", "t_s": "t",
          "x": "x", "y": "y", "p": "p", "pol": "p", "polarity": "p", "on": "p"}
_TEXT_BYTES = re.compile(rb"[^\x09\x0a\x0d\x20-\x7e]")


def sniff_text(head: bytes) -> bool:
    """Whether ``head`` (a file's first bytes) looks like text events: printable ASCII, and a first data line
    of four numbers (after an optional line of column names or of a sensor size).

    Parameters
    ----------
    head : bytes
        The file's first bytes (a few KiB).

    Returns
    -------
    bool
        True for text events.
    """
    if not head or _TEXT_BYTES.search(head):
        return False
    lines = [ln for ln in head.split(b"\n")[:4] if ln.strip()]
    for ln in lines[:3]:
        fields = [f for f in re.split(rb"[,\s]+", ln.strip()) if f]
        if len(fields) == 4 and all(_is_number(f) for f in fields):
            return True
    return False


def _is_number(text) -> bool:
    text = text.decode("ascii") if isinstance(text, bytes) else text
    try:
        float(text)
    except ValueError:
        return text.lower() in ("true", "false")
    return True


class TextRecording(DecodedRecording):
    """Text events, one ``t x y p`` a line (CSV, tab- or space-separated), as cameras' tools, the Event Camera
    Dataset, E2VID and faery write them (see the module's description for the variants read).

    Parameters
    ----------
    path : str or os.PathLike
        The file.
    salvage : bool
        Keep the lines before the first that does not parse.
    sensor_size : tuple of (int, int), optional
        Overrides the size from the file's first line or from the events.
    time_unit : {"s", "ms", "us", "ns"}, optional
        The time column's unit; by default seconds when it has a decimal point, else microseconds.
    """

    format = "text"

    def __init__(self, path: str | os.PathLike[str], salvage: bool = False,
                 sensor_size: tuple[int, int] | None = None, time_unit: str | None = None) -> None:
        super().__init__(path, salvage, sensor_size)
        if time_unit is not None and time_unit not in TIME_UNITS:
            raise EvtkError(f"time_unit must be one of {sorted(TIME_UNITS)}, not {time_unit!r}")
        self.time_unit = time_unit
        self._notes: list[str] = []

    def _decode(self) -> tuple[Events, Triggers]:
        require_memory(10 * self._file_bytes, f"decoding the text events of {self.path}")
        with open(self.path, "rb") as f:
            data = f.read()
        binary = _TEXT_BYTES.search(data[:1 << 20])
        if binary is not None:
            raise FormatError(self.path, binary.start(), "a byte that is not text")
        order, size, start = self._header(data)
        body = data[start:]
        cols, bad_at = self._parse(body)
        if bad_at is not None:
            keep = body.rfind(b"\n", 0, bad_at) + 1  # the bad line's start
            line_no = body.count(b"\n", 0, keep) + 1 + data.count(b"\n", 0, start)
            line = body[keep:body.find(b"\n", keep) if b"\n" in body[keep:] else len(body)]
            self._stop(start + keep, f"line {line_no} is not four numbers: {line[:60].decode('ascii', 'replace')!r}")
            cols, _ = self._parse(body[:keep])
        t_raw, x, y, p = (cols[:, order[k]] for k in range(4))
        t = self._times(t_raw, body)
        if len(x) and (np.any(x < 0) or np.any(y < 0) or np.any(x != np.floor(x)) or np.any(y != np.floor(y))):
            raise FormatError(self.path, start, "x and y must be whole numbers from 0")
        pol = np.where(p > 0, 1, 0).astype(np.uint8)
        if len(p) and not np.all(np.isin(p, (-1, 0, 1))):
            raise FormatError(self.path, start, "polarity must be 1 (ON) or 0 / -1 (OFF)")
        size = self._size(size, x, y)
        xi, yi = x.astype(np.int64), y.astype(np.int64)
        if len(xi) and (xi.max() >= size[0] or yi.max() >= size[1]):
            k = int(np.flatnonzero((xi >= size[0]) | (yi >= size[1]))[0])
            raise FormatError(self.path, start, f"event {k} at ({xi[k]}, {yi[k]}) lies off the "
                                                f"{size[0]}x{size[1]} sensor")
        ev = Events(t, xi.astype(np.uint16), yi.astype(np.uint16), pol, size)
        for note in self._notes:
            self._warn_once(note, self.path)
        return ev, Triggers()

    def _header(self, data: bytes):
        """(column order t, x, y, p -> index; sensor size or None; offset of the first event line)."""
        order = [0, 1, 2, 3]
        size = None
        start = 0
        for _ in range(2):
            end = data.find(b"\n", start, start + _MAX_TEXT_HEADER)
            line = data[start:end if end >= 0 else len(data)].strip()
            fields = [f for f in re.split(rb"[,\s]+", line) if f]
            if len(fields) == 4 and all(_is_number(f) for f in fields):
                break
            if len(fields) == 2 and all(f.isdigit() for f in fields):
                size = ("either", int(fields[0]), int(fields[1]))
            elif len(fields) == 4:
                names = []
                for f in fields:
                    name, _, dim = f.decode("ascii").lower().partition("@")
                    names.append(_NAMES.get(name))
                    if dim:
                        if not dim.isdigit():
                            raise FormatError(self.path, start, f"column {f.decode()!r}: the size after @ is not a number")
                        size = (size or ("named", 0, 0))
                        size = ("named", int(dim), size[2]) if name == "x" else ("named", size[1], int(dim))
                if sorted(n or "?" for n in names) != ["p", "t", "x", "y"]:
                    raise FormatError(self.path, start, f"the first line names columns {line.decode()!r}; evtk reads "
                                                        "t (or timestamp), x, y and p (or polarity, on)")
                order = [names.index(k) for k in "txyp"]
            else:
                raise FormatError(self.path, start, f"the line {line[:60].decode()!r} is neither column names, a "
                                                    "sensor size (two numbers) nor an event (four numbers)")
            if end < 0:
                start = len(data)
                break
            start = end + 1
        return order, size, start

    def _parse(self, body: bytes):
        """(columns as float64 (n, 4), offset of the first line that is not four numbers, or None)."""
        text = body.replace(b",", b" ").replace(b"\t", b" ").replace(b"\r", b" ")
        if re.search(rb"(?i)true|false", text):
            text = re.sub(rb"(?i)\btrue\b", b"1   ", re.sub(rb"(?i)\bfalse\b", b"0    ", text))
        arr = np.frombuffer(text, np.uint8)
        gap = (arr == 32) | (arr == 10)
        starts = np.flatnonzero(~gap & np.concatenate(([True], gap[:-1])))  # where each field begins
        line_of = np.searchsorted(np.flatnonzero(arr == 10), starts)  # the line each field is on
        per_line = np.bincount(line_of) if len(starts) else np.empty(0, np.int64)
        try:
            with warnings.catch_warnings():  # older numpy warns and stops where a field is no number
                warnings.simplefilter("ignore")
                values = np.fromstring(text, dtype=np.float64, sep=" ") if len(starts) else np.empty(0)
        except ValueError:  # newer numpy refuses: find the first field that is no number, line by line
            values = self._numbers_before_bad(text)
        bad = []
        odd = np.flatnonzero((per_line != 0) & (per_line != 4))
        if len(odd):
            bad.append(int(starts[np.searchsorted(line_of, odd[0])]))
        if len(values) < len(starts):
            bad.append(int(starts[len(values)]))
        if bad:
            return values[:len(values) - len(values) % 4].reshape(-1, 4), min(bad)
        return values.reshape(-1, 4), None

    @staticmethod
    def _numbers_before_bad(text: bytes) -> np.ndarray:
        """The fields of ``text`` up to the first one that is not a number (the slow path, for damage only)."""
        out: list[float] = []
        for field in text.split():
            try:
                out.append(float(field))
            except ValueError:
                break
        return np.asarray(out, np.float64)

    def _times(self, t_raw: np.ndarray, body: bytes) -> np.ndarray:
        unit = self.time_unit
        if unit is None:  # seconds when most lines have a decimal point: one stray dot does not rescale the file
            unit = "s" if 2 * _dotted_lines(body) > max(1, len(t_raw)) else "us"
        scaled = np.rint(t_raw * TIME_UNITS[unit])
        if len(scaled) and not np.all(np.abs(scaled) < 2.0**62):
            raise FormatError(self.path, 0, f"time stamps in {unit} beyond what int64 microseconds hold")
        return scaled.astype(np.int64)

    def _size(self, size, x: np.ndarray, y: np.ndarray) -> tuple[int, int]:
        if self._given_size is not None:
            return self._given_size
        mx = int(x.max()) + 1 if len(x) else 1
        my = int(y.max()) + 1 if len(y) else 1
        if size is None:
            self._notes.append(f"no sensor size in the file: {mx}x{my} from the events (pass --sensor-size WxH)")
            return sensor_dims(mx, my, self.path, "the events' extent")
        kind, a, b = size
        if kind == "named":
            return sensor_dims(a, b, self.path, "the column names")
        fits_wh, fits_hw = mx <= a and my <= b, mx <= b and my <= a
        if fits_wh and fits_hw and a != b:
            self._notes.append(f"the first line gives {a} {b}; both orders hold the events: read as width {a}, "
                               f"height {b} (pass --sensor-size WxH if not)")
        if fits_wh:
            return sensor_dims(a, b, self.path, "the first line")
        if fits_hw:
            return sensor_dims(b, a, self.path, "the first line (height width)")
        raise FormatError(self.path, 0, f"the first line gives a {a}x{b} sensor, but events reach x={mx - 1}, "
                                        f"y={my - 1}")


def _dotted_lines(body: bytes) -> int:
    """Number of lines of ``body`` with a decimal point."""
    arr = np.frombuffer(body, np.uint8)
    dots = np.flatnonzero(arr == 46)
    if not len(dots):
        return 0
    return len(np.unique(np.searchsorted(np.flatnonzero(arr == 10), dots)))


def _magnitudes(values: np.ndarray):
    """(magnitudes, as uint32 where they fit; the mask of negative values, or None; the widest magnitude's digits;
    the text width, a sign included) of integers."""
    v = np.asarray(values, np.int64)
    below = v < 0
    neg = below if below.any() else None
    mag = (np.abs(v) if neg is not None else v).astype(np.uint64)
    top = int(mag.max()) if len(v) else 0
    digits = len(str(top))  # the widest number's digits: the loops below run no further
    if top < 1 << 32:
        mag = mag.astype(np.uint32)  # whole-number division is faster in 32 bits
    return mag, neg, digits, digits + (neg is not None)


def _put_digits(mag: np.ndarray, neg, digits: int, text: np.ndarray, keep, start: int, width: int) -> np.ndarray:
    """Write the numbers of :func:`_magnitudes` right-aligned into columns ``start:start + width`` of the (n, W)
    byte matrix ``text``, and the mask of the bytes used into ``keep`` (unless None); return each one's length."""
    nd = np.ones(len(mag), np.int8)
    for k in range(1, digits):
        nd += mag >= 10**k
    if neg is not None:
        nd += neg
    rest = mag
    ten = rest.dtype.type(10)
    for col in range(start + width - 1, start + width - 1 - digits, -1):
        quot = rest // ten
        digit = rest - quot * ten  # one division a digit, not two
        digit += 48
        text[:, col] = digit
        rest = quot
    if neg is not None:
        text[neg, start + width - nd[neg]] = ord("-")
    if keep is not None:
        np.greater_equal(np.arange(width, dtype=np.int8)[None, :], (width - nd)[:, None], out=keep[:, start:start + width])
    return nd


def _ascii_digits(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Decimal digits of integers as a (n, width) byte matrix, right-aligned, and the mask of the bytes used
    (a leading '-' for negative values)."""
    mag, neg, digits, width = _magnitudes(values)
    mat, used = np.zeros((len(mag), width), np.uint8), np.empty((len(mag), width), bool)
    _put_digits(mag, neg, digits, mat, used, 0, width)
    return mat, used


#: uint64 words whose last k + 1 bytes in memory are 1 (k = 0..8): a k-digit number's mask and its separator's
_KEEP_LAST = np.array([sum(1 << (8 * (7 - b)) for b in range(k + 1)) for k in range(8)] + [(1 << 64) - 1], np.uint64)
_SMALL_TEXT: list = []  # text of 0..65535 as uint64: digits and a separator in the top bytes; the kept bytes' mask


def _small_tables() -> list:
    """(text ending in ',', text ending in a line feed, mask of the bytes kept) for 0..65535: uint64 each, the
    number's digits and its separator in the word's top bytes (its last bytes in memory), made once."""
    if not _SMALL_TEXT:
        mat, used = _ascii_digits(np.arange(1 << 16))
        text, mask = np.zeros((1 << 16, 8), np.uint8), np.zeros((1 << 16, 8), np.uint8)
        text[:, 7 - mat.shape[1]:7], mask[:, 7 - mat.shape[1]:7] = mat, used
        mask[:, 7] = 1
        text[:, 7] = ord(",")
        comma = text.view(np.uint64).ravel().copy()
        text[:, 7] = ord("\n")
        _SMALL_TEXT[:] = [comma, text.view(np.uint64).ravel(), mask.view(np.uint64).ravel()]
    return _SMALL_TEXT


def _csv_block(cols: list) -> bytes:
    """:func:`csv_lines` of one block: each line's numbers right-aligned in fixed-width fields of an (n, W) byte
    matrix, the padding masked out when the lines are read out. A number below 65,536 and its separator come from
    a table as one 8-byte word, written where the field ends; fields are written from the last to the first, so the
    bytes such a word covers before its field are overwritten by the fields they belong to."""
    m = len(cols[0])
    # (width, magnitudes or None for a table-read column)
    fields: list[tuple[int, tuple[np.ndarray, np.ndarray | None, int] | None]] = []
    for col in cols:
        small = col.dtype.kind in "ub" and col.dtype.itemsize <= 2
        if not small and col.dtype.kind in "iu" and int(col.min()) >= 0 and int(col.max()) < 1 << 16:
            small = True
        if small:
            fields.append((len(str(int(col.max()))), None))
        else:
            mag, neg, digits, width = _magnitudes(col)
            fields.append((width, (mag, neg, digits)))
    starts, at = [], 0
    for width, _ in fields:
        starts.append(at)
        at += width + 1
    margin = max([0] + [7 - width - start for (width, _), start in zip(fields, starts) if width < 8])
    row = margin + at
    text, keep = np.empty((m, row), np.uint8), np.empty((m, row), bool)
    if margin:
        keep[:, :margin] = False
    comma, line_feed, mask = _small_tables()
    for i in range(len(cols) - 1, -1, -1):
        (width, wide), end = fields[i], margin + starts[i] + fields[i][0]  # end: the separator's byte
        if wide is not None:
            nd = _put_digits(*wide, text, None if width < 8 else keep, end - width, width)
            text[:, end] = ord("," if i < len(cols) - 1 else "\n")
            if width >= 8:
                keep[:, end] = True
                continue
            word = np.ndarray((m,), np.uint64, buffer=keep, offset=end - 7, strides=(row,))  # unaligned: ends at end
            word[...] = _KEEP_LAST.take(nd.astype(np.intp))  # the number's bytes and its separator
            continue
        idx = cols[i].astype(np.intp, copy=False)
        for dst, table in ((text, comma if i < len(cols) - 1 else line_feed), (keep, mask)):
            word = np.ndarray((m,), np.uint64, buffer=dst, offset=end - 7, strides=(row,))  # unaligned: ends at end
            word[...] = table.take(idx)
    return np.compress(keep.reshape(-1), text.reshape(-1)).tobytes()  # faster than text[keep]


_CSV_BLOCK = 1 << 16  # lines formatted at a time: the temporaries stay in the CPU's cache


def csv_lines(columns: Sequence[np.ndarray]) -> bytes:
    """``a,b,c,...`` lines (one a row, ``\\n`` ended) of integer columns, formatted with numpy alone.

    Parameters
    ----------
    columns : sequence of numpy.ndarray
        Integer columns of equal length.

    Returns
    -------
    bytes
        The lines, ASCII.
    """
    columns = [np.asarray(col) for col in columns]
    n = len(columns[0])
    return b"".join(_csv_block([col[a:a + _CSV_BLOCK] for col in columns]) for a in range(0, n, _CSV_BLOCK))


# -- N-MNIST ------------------------------------------------------------------------------------------------------

_NMNIST_OVERFLOW_Y = 240
_NMNIST_OVERFLOW_US = 1 << 13


def sniff_nmnist(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` looks like an N-MNIST binary: a whole number of 5-byte events (or a ``.bin`` file cut
    inside its last one) whose first thousand have time stamps that never go back (after the overflow markers)
    and do not all stand still; with fewer than 16 events, only a ``.bin`` file.

    Parameters
    ----------
    path : str or os.PathLike
        The file.

    Returns
    -------
    bool
        True when the content fits the format.
    """
    size = os.path.getsize(path)
    if size < 5 or (size % 5 and not os.fspath(path).lower().endswith(".bin")):  # a cut .bin: read, then refused
        return False
    with open(path, "rb") as f:
        data = f.read(5000)
    head = np.frombuffer(data[:len(data) - len(data) % 5], np.uint8).reshape(-1, 5)
    t = _nmnist_times(head)
    real = head[:, 1] != _NMNIST_OVERFLOW_Y
    if not real.any() or np.any(np.diff(t[real]) < 0) or t[real][0] == t[real][-1]:
        return False  # time going back, or no time passing (a file of zeros), is no N-MNIST recording
    # a handful of events could be anything: then only a file named as the datasets name theirs
    return bool(real.sum() >= 16 or os.fspath(path).lower().endswith(".bin"))


def _nmnist_times(raw: np.ndarray) -> np.ndarray:
    t = ((raw[:, 2].astype(np.int64) & 0x7F) << 16) | (raw[:, 3].astype(np.int64) << 8) | raw[:, 4]
    overflow = (raw[:, 1] == _NMNIST_OVERFLOW_Y).astype(np.int64)
    return t + np.cumsum(overflow) * _NMNIST_OVERFLOW_US


class NmnistRecording(DecodedRecording):
    """An N-MNIST / N-Caltech101 binary file (5 bytes an event; see the module's description).

    Parameters
    ----------
    path : str or os.PathLike
        The file.
    salvage : bool
        Keep the whole events before a cut last one instead of raising.
    sensor_size : tuple of (int, int), optional
        Overrides the size taken from the events.
    """

    format = "nmnist"

    def _decode(self) -> tuple[Events, Triggers]:
        n = self._file_bytes // 5
        if self._file_bytes % 5:
            self._stop(5 * n, f"the file ends inside an event ({self._file_bytes % 5} of its 5 bytes)")
        require_memory(27 * n, f"decoding the N-MNIST events of {self.path}")
        raw = np.fromfile(self.path, np.uint8, count=5 * n).reshape(-1, 5)
        t = _nmnist_times(raw)
        real = raw[:, 1] != _NMNIST_OVERFLOW_Y
        raw, t = raw[real], t[real]
        back = np.flatnonzero(np.diff(t) < 0)
        if len(back):
            self._stop(5 * int(np.flatnonzero(real)[back[0] + 1]), "a time stamp goes back: not an N-MNIST file, "
                                                                   "or a damaged one")
            raw, t = raw[:back[0] + 1], t[:back[0] + 1]
        x, y = raw[:, 0].astype(np.uint16), raw[:, 1].astype(np.uint16)
        if self._given_size is not None:
            size = self._given_size
            if len(x) and (x.max() >= size[0] or y.max() >= size[1]):
                raise FormatError(self.path, 0, f"events reach ({int(x.max())}, {int(y.max())}), off the given "
                                                f"{size[0]}x{size[1]} sensor")
        elif not len(x) or (x.max() < 34 and y.max() < 34):
            size = (34, 34)
        else:
            size = (int(x.max()) + 1, int(y.max()) + 1)
            self._warn_once("no sensor size in the file", f"{size[0]}x{size[1]} from the events; pass --sensor-size")
        return Events(t, x, y, (raw[:, 2] >> 7).astype(np.uint8), size), Triggers()
