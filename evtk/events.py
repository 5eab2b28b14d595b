"""Columnar event streams and trigger lists.

An :class:`Events` holds four equally long columns, ``t`` (int64
microseconds), ``x`` and ``y`` (uint16 pixel coordinates, x to the right,
y down) and ``p`` (uint8, 1 for ON, 0 for OFF), plus the sensor size
``(width, height)`` they were recorded on.  :class:`Triggers` holds the
external-signal time stamps that the camera records beside the events.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from .errors import EvtkError

if TYPE_CHECKING:
    import numpy.typing as npt  # for the annotations only: a fresh process need not load it
    import pyarrow as pa

    from ._trigger_kind import TriggerKind

#: A sensor size as the API takes it: ``(width, height)`` in pixels, any two whole numbers (checked).
SensorSize = Sequence[int] | np.ndarray

__all__ = ["Events", "Triggers", "TriggerKind", "STRUCTURED_LAYOUTS"]

#: Structured dtypes of the event arrays other libraries use.
#: ``dv`` matches ``dv_processing.EventStore.numpy()`` (and the on-disk AEDAT4
#: event struct), ``faery`` matches ``faery.EVENTS_DTYPE``, ``tonic`` the
#: ``x, y, t, p`` layout of tonic's transforms.
STRUCTURED_LAYOUTS = {
    "dv": np.dtype(
        {
            "names": ["timestamp", "x", "y", "polarity"],
            "formats": ["<i8", "<i2", "<i2", "i1"],
            "offsets": [0, 8, 10, 12],
            "itemsize": 16,
        }
    ),
    "faery": np.dtype([("t", "<u8"), ("x", "<u2"), ("y", "<u2"), (("p", "on"), "?")]),
    "tonic": np.dtype([("x", "<i8"), ("y", "<i8"), ("t", "<i8"), ("p", "<i8")]),
}

_T_NAMES = ("t", "timestamp", "ts")
_P_NAMES = ("p", "polarity", "on")

#: The environment variable that chooses the trigger channel windows come from (``evtk --trigger-channel``).
TRIGGER_CHANNEL_ENV = "EVTK_TRIGGER_CHANNEL"

T_MIN_US = np.iinfo(np.int64).min
T_MAX_US = np.iinfo(np.int64).max


def __getattr__(name: str) -> Any:
    # TriggerKind lives in its own module, loaded on first use: making an enum class costs a fresh process 0.5 ms,
    # which a read of events alone need not pay
    if name == "TriggerKind":
        from ._trigger_kind import TriggerKind

        return TriggerKind
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | {"TriggerKind"})


def _as_sensor_size(sensor_size: SensorSize) -> tuple[int, int]:
    try:
        width, height = (int(v) for v in sensor_size)
    except (TypeError, ValueError):
        raise EvtkError(f"sensor_size must be (width, height), got {sensor_size!r}") from None
    if not (0 < width <= 65536 and 0 < height <= 65536):
        raise EvtkError(f"sensor_size must be positive and at most 65536, got {(width, height)}")
    return width, height


def _column(values, dtype, name: str, low=None, high=None) -> np.ndarray:
    """Convert ``values`` to a 1-D array of ``dtype`` without silent wrap-around."""
    arr = np.asarray(values)
    if arr.ndim != 1:
        raise EvtkError(f"column {name!r} must be one-dimensional, got shape {arr.shape}")
    if arr.dtype == dtype:
        return arr
    if arr.dtype.kind == "b":
        return arr.astype(dtype)
    if arr.dtype.kind == "f":
        if arr.size and not np.all(np.isfinite(arr)):
            raise EvtkError(f"column {name!r} holds NaN or infinite values")
        if arr.size and not np.array_equal(arr, np.round(arr)):
            raise EvtkError(f"column {name!r} holds non-integer values")
    elif arr.dtype.kind not in "iu":
        if arr.size == 0:
            return np.zeros(0, dtype)
        raise EvtkError(f"column {name!r} must be numeric, got dtype {arr.dtype}")
    info = np.iinfo(dtype)
    lo = info.min if low is None else low
    hi = info.max if high is None else high
    if arr.size:
        amin, amax = arr.min(), arr.max()
        if amin < lo or amax > hi:
            raise EvtkError(f"column {name!r} has values outside [{lo}, {hi}] (min {amin}, max {amax})")
    return arr.astype(dtype)


class Events:
    """An event stream as four columns plus the sensor size.

    Parameters
    ----------
    t, x, y, p : array_like
        Time stamps in microseconds, column, row and polarity (1 = ON).
        Converted to int64, uint16, uint16 and uint8; values that do not fit
        raise :class:`~evtk.EvtkError` rather than wrap around.
    sensor_size : tuple of (int, int)
        ``(width, height)`` of the sensor in pixels, each from 1 to 65536.

    Raises
    ------
    EvtkError
        When a column is not one-dimensional, not numeric, holds NaN, a fraction or a value outside its
        dtype's range (p outside 0 and 1), the columns differ in length, or the sensor size is not two
        positive whole numbers up to 65536.

    Examples
    --------
    >>> import evtk
    >>> ev = evtk.Events([10, 20, 30], [1, 2, 3], [0, 0, 1], [1, 0, 1], (320, 240))
    >>> len(ev.between(15, 31))
    2
    """

    __slots__ = ("t", "x", "y", "p", "sensor_size", "_sorted")

    def __init__(self, t: npt.ArrayLike, x: npt.ArrayLike, y: npt.ArrayLike, p: npt.ArrayLike,
                 sensor_size: SensorSize) -> None:
        self.sensor_size = _as_sensor_size(sensor_size)
        self.t = _column(t, np.int64, "t")
        self.x = _column(x, np.uint16, "x")
        self.y = _column(y, np.uint16, "y")
        self.p = _column(p, np.uint8, "p", 0, 1)
        n = len(self.t)
        if not (len(self.x) == len(self.y) == len(self.p) == n):
            raise EvtkError(
                f"event columns differ in length: t={n}, x={len(self.x)}, y={len(self.y)}, p={len(self.p)}"
            )
        self._sorted: bool | None = None

    # -- construction -----------------------------------------------------
    @classmethod
    def empty(cls, sensor_size: SensorSize) -> Events:
        """An event stream with no events.

        Parameters
        ----------
        sensor_size : tuple of (int, int)
            ``(width, height)`` of the sensor in pixels.

        Returns
        -------
        Events
            Zero-length columns of the usual dtypes.
        """
        return cls._trusted(
            np.zeros(0, np.int64), np.zeros(0, np.uint16), np.zeros(0, np.uint16), np.zeros(0, np.uint8), sensor_size
        )

    @classmethod
    def _trusted(cls, t, x, y, p, sensor_size, is_sorted=None) -> Events:
        """Wrap columns already of the right dtype and length (no copies, no checks)."""
        ev = object.__new__(cls)
        ev.t, ev.x, ev.y, ev.p = t, x, y, p
        ev.sensor_size = _as_sensor_size(sensor_size)
        ev._sorted = is_sorted
        return ev

    @classmethod
    def concatenate(cls, parts: Iterable[Events], sensor_size: SensorSize | None = None) -> Events:
        """Join event streams end to end.

        The sensor size is ``sensor_size`` if given, else that of the parts,
        which must then agree.

        Parameters
        ----------
        parts : iterable of Events
            The streams, in order (not sorted again: the result is in time order only when they are, one
            after the other).
        sensor_size : tuple of (int, int), optional
            ``(width, height)`` of the result.

        Returns
        -------
        Events
            Their events one after the other, in new arrays.

        Raises
        ------
        EvtkError
            When no ``sensor_size`` is given and the parts' sizes differ or there are no parts.
        """
        parts = list(parts)
        if sensor_size is None:
            sizes = {ev.sensor_size for ev in parts}
            if not sizes:
                raise EvtkError("no events to concatenate and no sensor_size given")
            if len(sizes) != 1:
                raise EvtkError(f"cannot concatenate events of different sensor sizes: {sorted(sizes)}")
            sensor_size = sizes.pop()
        if not parts:
            return cls.empty(sensor_size)
        return cls._trusted(
            np.concatenate([ev.t for ev in parts]),
            np.concatenate([ev.x for ev in parts]),
            np.concatenate([ev.y for ev in parts]),
            np.concatenate([ev.p for ev in parts]),
            sensor_size,
        )

    @classmethod
    def from_structured(cls, array: np.ndarray, sensor_size: SensorSize) -> Events:
        """Build from a structured array of another library.

        Its fields are named as dv-processing, faery or tonic name them (``t``/``timestamp``/``ts``, ``x``,
        ``y``, ``p``/``polarity``/``on``), of any integer (or boolean polarity) dtypes that fit evtk's.

        Parameters
        ----------
        array : numpy.ndarray
            One-dimensional structured array (see :data:`STRUCTURED_LAYOUTS`).
        sensor_size : tuple of (int, int)
            ``(width, height)`` of the sensor in pixels.

        Returns
        -------
        Events
            The events, in copied columns of evtk's dtypes.

        Raises
        ------
        EvtkError
            When a field is missing or a value does not fit (as :class:`Events`).
        """
        array = np.asarray(array)
        names = array.dtype.names or ()

        def pick(options):
            for name in options:
                if name in names:
                    return array[name]
            raise EvtkError(f"structured array has fields {list(names)}; expected one of {list(options)}")

        return cls(pick(_T_NAMES), pick(("x",)), pick(("y",)), pick(_P_NAMES), sensor_size)

    # -- conversion -------------------------------------------------------
    def to_structured(self, layout: str = "dv") -> np.ndarray:
        """Copy into the structured array of another library.

        Parameters
        ----------
        layout : {'dv', 'faery', 'tonic'}
            Which library's field names and dtypes to use, see
            :data:`STRUCTURED_LAYOUTS`.

        Returns
        -------
        numpy.ndarray
            A new structured array, one record per event, in this stream's order.

        Raises
        ------
        EvtkError
            For an unknown layout, negative time stamps for faery (unsigned), or coordinates above 32767
            for dv (int16).
        """
        try:
            dtype = STRUCTURED_LAYOUTS[layout]
        except KeyError:
            raise EvtkError(f"unknown layout {layout!r}; choose one of {sorted(STRUCTURED_LAYOUTS)}") from None
        if layout == "faery" and len(self) and self.t[0] < 0:
            raise EvtkError("faery stores unsigned time stamps; this stream has negative ones")
        if layout == "dv" and len(self) and max(int(self.x.max()), int(self.y.max())) > 32767:
            raise EvtkError("dv-processing stores int16 coordinates; this stream has coordinates above 32767")
        out = np.zeros(len(self), dtype=dtype)
        tname, pname = [n for n in (dtype.names or ()) if n not in ("x", "y")]
        out[tname] = self.t
        out["x"] = self.x
        out["y"] = self.y
        out[pname] = self.p
        return out

    def to_arrow(self, metadata: Mapping[str, Any] | None = None) -> pa.Table:
        """A ``pyarrow.Table`` with columns t, x, y, p and the sensor size in its schema metadata.

        Parameters
        ----------
        metadata : Mapping of str to object, optional
            Stored as JSON in the schema metadata too (:func:`evtk.io.table.columns_to_table`).

        Returns
        -------
        pyarrow.Table
            Columns ``t`` (int64, µs), ``x``, ``y`` (uint16) and ``p`` (uint8), sharing this stream's memory
            where Arrow can.
        """
        from ._table import columns_to_table

        return columns_to_table(self.t, self.x, self.y, self.p, self.sensor_size, metadata)

    @classmethod
    def from_arrow(cls, table: pa.Table, sensor_size: Sequence[int] | None = None) -> Events:
        """Events from a ``pyarrow.Table`` (sensor size from its metadata unless given).

        Parameters
        ----------
        table : pyarrow.Table
            Columns t, x, y, p (:func:`evtk.io.table.table_to_columns` names what it accepts).
        sensor_size : sequence of two int, optional
            ``(width, height)``; default: the one the table's metadata holds.

        Returns
        -------
        Events
            The events, checked as :class:`Events` checks them.

        Raises
        ------
        EvtkError
            When a column is missing or its values do not fit, or there is no sensor size.
        """
        from ._table import table_to_columns

        t, x, y, p, size = table_to_columns(table, sensor_size)
        return cls(t, x, y, p, size)

    # -- queries ----------------------------------------------------------
    def __len__(self) -> int:
        return len(self.t)

    def __repr__(self) -> str:
        span = f", t=[{self.t[0]}, {self.t[-1]}] us" if len(self) else ""
        return f"Events(n={len(self)}, sensor_size={self.sensor_size}{span})"

    def __getitem__(self, index) -> Events:
        if isinstance(index, (int, np.integer)):
            index = slice(index, index + 1 if index != -1 else None)
        # a run of stamps in order is in order; a run of stamps out of order may not be: not known
        sorted_hint = True if self._sorted and isinstance(index, slice) and index.step in (None, 1) else None
        return Events._trusted(self.t[index], self.x[index], self.y[index], self.p[index], self.sensor_size, sorted_hint)

    def __eq__(self, other) -> bool:
        if not isinstance(other, Events):
            return NotImplemented
        return (
            self.sensor_size == other.sensor_size
            and np.array_equal(self.t, other.t)
            and np.array_equal(self.x, other.x)
            and np.array_equal(self.y, other.y)
            and np.array_equal(self.p, other.p)
        )

    __hash__ = None  # type: ignore[assignment]  # mutable columns: not hashable

    @property
    def is_sorted(self) -> bool:
        """True when time stamps never decrease.

        Checked on first use and kept; a reader that compared the stamps as it decoded them (AEDAT4's compiled
        decoding) or a simulation that made them in order gives the answer with the events. The answer is the
        stamps' as they were then: stamps changed in place afterwards are not checked again (wrap them in a new
        :class:`Events` for that).
        """
        if self._sorted is None:
            self._sorted = bool(len(self.t) < 2 or np.all(self.t[1:] >= self.t[:-1]))
        return self._sorted

    def stamp_period_us(self, max_events: int = 200_000) -> float | None:
        """The spacing of the time stamps' grid: 1.0 for an asynchronous sensor, the readout period for one that
        reads its pixels in frames (the DVXplorer family), or None with fewer than 64 distinct stamps.

        Looks at the first ``max_events`` events. The grid is the greatest common divisor of the gaps between
        distinct stamps; when that is 1 but every gap is, within 5 %, a whole number of the shortest gap (a
        period that is not a whole number of microseconds, rounded), that gap's mean is returned.

        Parameters
        ----------
        max_events : int
            How many events, from the first, to look at.

        Returns
        -------
        float or None
            The period in µs (1.0: no grid), or None with fewer than 64 distinct stamps.

        Examples
        --------
        >>> t = np.arange(0, 20_000, 200)
        >>> Events(t, t % 7, t % 5, t % 2, (8, 8)).stamp_period_us()
        200.0
        """
        t = self.t[: int(max_events)]
        if t.size < 64:
            return None
        d = np.diff(t)
        if np.all(d >= 0):  # sorted stamps: the gaps between distinct ones are the positive differences
            gaps = d[d > 0]
        else:
            from ._arrays import distinct

            gaps = np.diff(distinct(t))
        if gaps.size < 63:  # fewer than 64 distinct stamps
            return None
        shortest = int(gaps.min())
        if shortest == 1:  # no grid (an asynchronous sensor's stamps), without the divisor of every gap
            return 1.0
        g = int(np.gcd.reduce(gaps))
        if g > 1:
            return float(g)
        if shortest > 2:
            period = float(gaps[gaps < 1.5 * shortest].mean())
            k = gaps / period
            if np.mean(np.abs(k - np.round(k)) < 0.05) >= 0.95:
                return period
        return 1.0

    def sorted(self) -> Events:
        """The events in time order: ``self`` when already sorted, else a stable-sorted copy.

        Events with equal time stamps keep their order.

        Returns
        -------
        Events
            Sorted by time (``is_sorted`` is True).

        Examples
        --------
        >>> ev = Events([5, 1, 5, 3], [0, 1, 2, 3], [0, 0, 0, 0], [1, 0, 0, 1], (4, 1))
        >>> s = ev.sorted()
        >>> s.t.tolist(), s.x.tolist(), s.is_sorted
        ([1, 3, 5, 5], [1, 3, 0, 2], True)
        """
        if self.is_sorted:
            return self
        order = np.argsort(self.t, kind="stable")
        return type(self)._trusted(self.t[order], self.x[order], self.y[order], self.p[order], self.sensor_size, True)

    @property
    def t_start_us(self):
        """First time stamp, or None for an empty stream."""
        return int(self.t.min()) if len(self) else None

    @property
    def t_end_us(self):
        """Last time stamp, or None for an empty stream."""
        return int(self.t.max()) if len(self) else None

    def between(self, t_start_us: int | None = None, t_end_us: int | None = None) -> Events:
        """Events with ``t_start_us <= t < t_end_us`` (None leaves a side open).

        Sorted streams are cut with a binary search and the result shares
        memory with this stream; unsorted ones are filtered with a mask.

        Parameters
        ----------
        t_start_us : int, optional
            First time kept (µs, inclusive).
        t_end_us : int, optional
            End of the span (µs, exclusive).

        Returns
        -------
        Events
            Those events, in this stream's order.
        """
        lo = T_MIN_US if t_start_us is None else int(t_start_us)
        if t_end_us is None:
            hi_open = True
            hi = T_MAX_US
        else:
            hi_open = False
            hi = int(t_end_us)
        if self.is_sorted:
            i0 = int(np.searchsorted(self.t, lo, side="left"))
            i1 = len(self.t) if hi_open else int(np.searchsorted(self.t, hi, side="left"))
            return self[i0 : max(i0, i1)]
        mask = self.t >= lo
        if not hi_open:
            mask &= self.t < hi
        # (those kept may be in order: checked when asked)
        return Events._trusted(self.t[mask], self.x[mask], self.y[mask], self.p[mask], self.sensor_size)

    def out_of_bounds(self) -> int:
        """Number of events whose coordinates fall outside the sensor.

        Returns
        -------
        int
            Events with ``x >= width`` or ``y >= height``.
        """
        w, h = self.sensor_size
        if not len(self):
            return 0
        return int(np.count_nonzero((self.x >= w) | (self.y >= h)))


class Triggers:
    """External trigger time stamps (int64 microseconds), their kinds and the input channel of each.

    Parameters
    ----------
    t : array_like
        Time stamps in microseconds.
    kind : array_like
        :class:`TriggerKind` codes (uint8).
    channel : array_like, optional
        The camera's trigger input each came from (uint8; Prophesee cameras
        number several). None: all from channel 0, as formats without
        channels (AEDAT4) give them.
    """

    __slots__ = ("t", "kind", "channel")

    def __init__(self, t: npt.ArrayLike = (), kind: npt.ArrayLike = (), channel: npt.ArrayLike | None = None) -> None:
        self.t = _column(t, np.int64, "t")
        self.kind = _column(kind, np.uint8, "kind", 0, 255)
        self.channel = np.zeros(len(self.t), np.uint8) if channel is None else _column(channel, np.uint8, "channel")
        if not (len(self.t) == len(self.kind) == len(self.channel)):
            raise EvtkError(f"trigger columns differ in length: t={len(self.t)}, kind={len(self.kind)}, "
                            f"channel={len(self.channel)}")

    @classmethod
    def concatenate(cls, parts: Iterable[Triggers]) -> Triggers:
        """Join trigger lists end to end.

        Parameters
        ----------
        parts : iterable of Triggers
            The lists, in order.

        Returns
        -------
        Triggers
            Their triggers one after the other.
        """
        parts = list(parts)
        if not parts:
            return cls()
        return cls(np.concatenate([p.t for p in parts]), np.concatenate([p.kind for p in parts]),
                   np.concatenate([p.channel for p in parts]))

    def __len__(self) -> int:
        return len(self.t)

    def __repr__(self) -> str:
        return f"Triggers(n={len(self)})"

    def __eq__(self, other) -> bool:
        if not isinstance(other, Triggers):
            return NotImplemented
        return (np.array_equal(self.t, other.t) and np.array_equal(self.kind, other.kind)
                and np.array_equal(self.channel, other.channel))

    __hash__ = None  # type: ignore[assignment]  # mutable columns: not hashable

    def _take(self, index) -> Triggers:
        return Triggers(self.t[index], self.kind[index], self.channel[index])

    def __getitem__(self, index) -> Triggers:
        if isinstance(index, (int, np.integer)):
            index = slice(index, index + 1 if index != -1 else None)
        return self._take(index)

    def between(self, t_start_us: int | None = None, t_end_us: int | None = None) -> Triggers:
        """Triggers with ``t_start_us <= t < t_end_us`` (None leaves a side open).

        Parameters
        ----------
        t_start_us : int, optional
            First time kept (µs, inclusive).
        t_end_us : int, optional
            End of the span (µs, exclusive).

        Returns
        -------
        Triggers
            Those triggers, in order, copied.
        """
        mask = np.ones(len(self), bool)
        if t_start_us is not None:
            mask &= self.t >= int(t_start_us)
        if t_end_us is not None:
            mask &= self.t < int(t_end_us)
        return self._take(mask)

    def of_kind(self, kind: int) -> Triggers:
        """Only the triggers of one :class:`TriggerKind`.

        Parameters
        ----------
        kind : TriggerKind or int
            The kind (its AEDAT4 code).

        Returns
        -------
        Triggers
            Those of that kind, in order, copied.
        """
        return self._take(self.kind == int(kind))

    @property
    def channels(self) -> list[int]:
        """The channels the triggers came from, in increasing order."""
        from ._arrays import distinct  # (here: the read path loads no more modules)

        return [int(c) for c in distinct(self.channel)]

    def of_channel(self, channel: int | None = None) -> Triggers:
        """The triggers of one input channel, so that windows come from one signal.

        Parameters
        ----------
        channel : int, optional
            The channel. None: the only channel there is (the triggers
            as they are); with more than one, an error that names them.

        Returns
        -------
        Triggers
            Those of ``channel``.

        Raises
        ------
        EvtkError
            ``channel`` is None and the triggers come from several channels,
            or no trigger comes from ``channel``.
        """
        found = self.channels
        if channel is None:
            if len(found) > 1:
                raise EvtkError(f"the triggers come from {len(found)} channels ({', '.join(map(str, found))}): "
                                "windows need one signal; choose its channel (evtk --trigger-channel N)")
            return self
        try:
            channel = int(channel)
        except (TypeError, ValueError):
            raise EvtkError(f"a trigger channel is a whole number, got {channel!r}") from None
        if channel not in found:
            listed = ", ".join(map(str, found)) if found else "none: there are no triggers"
            raise EvtkError(f"no trigger comes from channel {channel}; the channels are {listed}")
        return self._take(self.channel == channel)
