"""Capture windows: when each pattern was on, from a schedule, trigger edges or a fixed period."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import EvtkError
from ..events import TRIGGER_CHANNEL_ENV, TriggerKind, Triggers
from ..limits import require_memory, require_window_work

if TYPE_CHECKING:
    from ..plan import CaptureCounts, SimulationRecord
    from ..plan.schedule import Schedule

__all__ = ["Windows", "WindowCounts", "windows_from_schedule", "windows_from_triggers", "windows_periodic"]


_RISING = (TriggerKind.EXTERNAL_SIGNAL_RISING_EDGE, TriggerKind.EXTERNAL_GENERATOR_RISING_EDGE)


_FALLING = (TriggerKind.EXTERNAL_SIGNAL_FALLING_EDGE, TriggerKind.EXTERNAL_GENERATOR_FALLING_EDGE)

#: Largest time stamp: windows are int64 microseconds, and no window may end past it or be longer than it.
_T_MAX = int(np.iinfo(np.int64).max)


def _too_long(t_start_us, t_end_us):
    """Mask of windows longer than 2**63 - 1 us, whose length int64 arithmetic would wrap (starts before 0 only)."""
    return (t_start_us < 0) & (t_end_us > t_start_us + _T_MAX)


@dataclass
class Windows:
    """Half-open time windows ``[t_start_us, t_end_us)``, one per capture.

    ``capture`` is the schedule's capture index (or the window's own index
    when there is no schedule); ``dropped`` says, per reason, how many windows
    could not be formed.

    Parameters
    ----------
    t_start_us, t_end_us : ndarray of int
        Each window's start (inclusive) and end (exclusive), µs on the recording's clock; 1-D, of equal length,
        stored as contiguous int64. Every window must be non-empty and at most 2**63 - 1 µs long.
    capture : ndarray of int
        Each window's capture index (schedule row, or the window's own number), same length, stored as int64.
    source : str
        Where the windows came from: ``"schedule"``, ``"triggers"`` or ``"period"``.
    dropped : dict of str to int, optional
        How many windows could not be formed, per reason (empty by default).

    Raises
    ------
    EvtkError
        When the arrays are not 1-D of equal length, a window is empty or reversed, or one is longer than
        int64 time stamps can measure.
    """

    t_start_us: np.ndarray
    t_end_us: np.ndarray
    capture: np.ndarray
    source: str
    dropped: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.t_start_us = np.ascontiguousarray(self.t_start_us, dtype=np.int64)
        self.t_end_us = np.ascontiguousarray(self.t_end_us, dtype=np.int64)
        self.capture = np.ascontiguousarray(self.capture, dtype=np.int64)
        if not (self.t_start_us.shape == self.t_end_us.shape == self.capture.shape) or self.t_start_us.ndim != 1:
            raise EvtkError("window starts, ends and capture indices must be 1-D arrays of equal length")
        if np.any(self.t_end_us <= self.t_start_us):
            i = int(np.flatnonzero(self.t_end_us <= self.t_start_us)[0])
            raise EvtkError(f"window {i} is empty or reversed: [{self.t_start_us[i]}, {self.t_end_us[i]}) us")
        if np.any(_too_long(self.t_start_us, self.t_end_us)):
            i = int(np.flatnonzero(_too_long(self.t_start_us, self.t_end_us))[0])
            raise EvtkError(f"window {i} is longer than 2**63 - 1 us: [{self.t_start_us[i]}, {self.t_end_us[i]}) us")

    def __len__(self):
        return int(self.t_start_us.size)

    @property
    def length_us(self) -> np.ndarray:
        return self.t_end_us - self.t_start_us

    def __getitem__(self, index):
        """The windows at ``index`` (a slice or indices), as :class:`Windows` of the same source."""
        return Windows(self.t_start_us[index], self.t_end_us[index], self.capture[index], self.source,
                       dict(self.dropped))


@dataclass
class WindowCounts:
    """Event counts per window and pixel: ``on``/``off`` of shape (windows, y1 - y0, x1 - x0).

    ``region`` is (x0, x1, y0, y1) on the sensor; ``events_used`` counts the
    events that fell in a window and the region. ``on_first_us`` and
    ``on_last_us`` (int32, same shape, -1 where a window holds no ON event),
    when accumulated with ``times=True``, are the time stamps of each pixel's
    first and last ON event in the window, counted from the window's start.
    ``stamp_period_us`` is the spacing of the recording's time stamps
    (:meth:`evtk.Events.stamp_period_us`: 1 for an asynchronous sensor, the
    readout period of a frame-readout one), when accumulated with times.

    Parameters
    ----------
    on, off : ndarray
        ON and OFF event counts, shape (windows, y1 - y0, x1 - x0) (row-major: y then x), an integer dtype.
    windows : Windows
        The windows counted, one per leading index.
    region : tuple of int
        ``(x0, x1, y0, y1)``: the sensor pixels counted (half-open).
    events_used : int
        Events that fell in a window and the region.
    on_first_us, on_last_us : ndarray of int32, optional
        Each pixel's first and last ON event in each window, µs from the window's start, -1 where it has none;
        same shape as ``on``. None unless accumulated with ``times=True``.
    stamp_period_us : float, optional
        Spacing of the recording's time stamps, µs; None unless accumulated with ``times=True``.
    """

    on: np.ndarray
    off: np.ndarray
    windows: Windows
    region: tuple
    events_used: int
    on_first_us: np.ndarray | None = None
    on_last_us: np.ndarray | None = None
    stamp_period_us: float | None = None

    @classmethod
    def from_capture_counts(cls, cc: CaptureCounts) -> WindowCounts:
        """Window counts from the simulator's fast path (:meth:`evtk.simulate.Simulation.responses`).

        Parameters
        ----------
        cc : CaptureCounts
            The simulator's counts per capture and pixel, with their schedule and region.

        Returns
        -------
        WindowCounts
            The same counts, each capture's window its scheduled ``[t_on_us, t_off_us)`` (source
            ``"schedule"``), without event times.
        """
        s = cc.schedule
        win = Windows(s.t_on_us, s.t_off_us, s.capture, "schedule")
        return cls(cc.on, cc.off, win, tuple(cc.region), int(cc.on.sum() + cc.off.sum()))


def _trim(t_on, t_off, skip_us, length_us, what):
    """Each window's start delayed by ``skip_us`` and its length cut to ``length_us``, without int64 overflow."""
    skip_us = int(skip_us)
    if skip_us < 0:
        raise EvtkError(f"skip_us must be >= 0, not {skip_us}")
    t_on = np.asarray(t_on, np.int64)
    t_off = np.asarray(t_off, np.int64)
    if np.any(_too_long(t_on, t_off)):
        i = int(np.flatnonzero(_too_long(t_on, t_off))[0])
        raise EvtkError(f"{what} window {i} is longer than 2**63 - 1 us: [{t_on[i]}, {t_off[i]}) us")
    lengths = t_off - t_on  # exact: no window is longer than int64 holds
    if np.any(lengths <= skip_us):
        shortest = int(np.min(lengths)) if t_on.size else 0
        raise EvtkError(f"skip_us={skip_us} leaves nothing of the {what} windows (shortest: {shortest} us)")
    start = t_on + skip_us  # before each window's end: no overflow
    end = t_off.copy()
    if length_us is not None:
        length_us = int(length_us)
        if length_us < 1:
            raise EvtkError(f"length_us must be >= 1, not {length_us}")
        end = start + np.minimum(lengths - skip_us, length_us)
    return start, end


def windows_from_schedule(schedule: Schedule | SimulationRecord | dict, skip_us: int = 0,
                          length_us: int | None = None) -> Windows:
    """Windows of a simulated recording's captures.

    ``schedule`` is an :class:`evtk.simulate.Schedule`, a
    :class:`~evtk.simulate.SimulationRecord`, a recording's metadata dict
    (with a ``simulation`` record) or that record's dict.

    Parameters
    ----------
    schedule : Schedule, SimulationRecord or dict
        The captures: each one's window is its ``[t_on_us, t_off_us)``.
    skip_us : int
        Microseconds left out at the start of every window (the pixels' settling), >= 0.
    length_us : int, optional
        Keep at most this many microseconds of every window (after ``skip_us``), >= 1; None keeps all of it.

    Returns
    -------
    Windows
        Source ``"schedule"``, one window per capture, ``capture`` the schedule's capture numbers.

    Raises
    ------
    EvtkError
        When a dict holds no schedule, ``skip_us`` < 0 or leaves nothing of a window, or ``length_us`` < 1.
    """
    from ..plan.record import SimulationRecord
    from ..plan.schedule import METADATA_KEY, Schedule  # (here: fixed windows load no schedule, no settings)

    if isinstance(schedule, SimulationRecord):
        schedule = schedule.schedule
    elif isinstance(schedule, dict):
        rec = schedule.get(METADATA_KEY, schedule)
        if "schedule" not in rec:
            raise EvtkError("the recording carries no capture schedule; use its triggers or a period instead")
        schedule = Schedule.from_dict(rec["schedule"])
    start, end = _trim(schedule.t_on_us, schedule.t_off_us, skip_us, length_us, "scheduled")
    return Windows(start, end, schedule.capture, "schedule")


def windows_from_triggers(triggers: Triggers, skip_us: int = 0, length_us: int | None = None,
                          channel: int | None = None) -> Windows:
    """Windows from the DMD's trigger edges: each rising edge to the next falling edge.

    The edges come from one trigger input (:meth:`evtk.Triggers.of_channel`): ``channel``, else
    ``$EVTK_TRIGGER_CHANNEL`` (set by ``evtk --trigger-channel``), else the only one there is; triggers
    from several channels and none chosen are refused, since two signals' edges would make wrong windows.

    Edge cases are defined, and counted in ``Windows.dropped``: a rising edge
    while a window is open (its falling edge is missing: that window is
    dropped), a falling edge with no open window (ignored), and a window still
    open when the triggers end (the recording ends mid-window: dropped).
    Triggers of other kinds are ignored.

    Parameters
    ----------
    triggers : Triggers
        The recording's trigger edges (time stamps in µs).
    skip_us : int
        Microseconds left out at the start of every window (the pixels' settling), >= 0.
    length_us : int, optional
        Keep at most this many microseconds of every window (after ``skip_us``), >= 1; None keeps all of it.
    channel : int, optional
        The trigger input to read; None: ``$EVTK_TRIGGER_CHANNEL``, else the only one there is.

    Returns
    -------
    Windows
        Source ``"triggers"``, captures numbered from 0 in time order, ``dropped`` counting the edge cases
        above (only the reasons that occurred).

    Raises
    ------
    EvtkError
        When no rising edge is followed by a falling edge, triggers of several channels come without a
        choice, or ``skip_us``/``length_us`` leave nothing of a window.
    """
    # the environment's choice is text: of_channel checks that it is a whole number
    chosen: Any = channel if channel is not None else (os.environ.get(TRIGGER_CHANNEL_ENV) or None)
    triggers = triggers.of_channel(chosen)
    order = np.argsort(triggers.t, kind="stable")
    t = triggers.t[order]
    kind = triggers.kind[order]
    rising = np.isin(kind, _RISING)
    falling = np.isin(kind, _FALLING)
    starts, ends = [], []
    dropped = {"missing falling edge": 0, "falling edge without rising edge": 0, "recording ends mid-window": 0}
    open_at = None
    for ti, r, f in zip(t.tolist(), rising.tolist(), falling.tolist()):
        if r:
            if open_at is not None:
                dropped["missing falling edge"] += 1
            open_at = ti
        elif f:
            if open_at is None:
                dropped["falling edge without rising edge"] += 1
            elif ti > open_at:
                starts.append(open_at)
                ends.append(ti)
                open_at = None
            else:  # rising and falling at the same microsecond: nothing was shown
                dropped.setdefault("zero-length window", 0)
                dropped["zero-length window"] += 1
                open_at = None
    if open_at is not None:
        dropped["recording ends mid-window"] += 1
    if not starts:
        raise EvtkError("no complete window in the triggers: no rising edge followed by a falling edge "
                        f"({int(rising.sum())} rising, {int(falling.sum())} falling)")
    t_on = np.array(starts, np.int64)
    t_off = np.array(ends, np.int64)
    start, end = _trim(t_on, t_off, skip_us, length_us, "triggered")
    return Windows(start, end, np.arange(t_on.size), "triggers", {k: v for k, v in dropped.items() if v})


def windows_periodic(t_start_us: int | None, t_end_us: int | None, period_us: int, skip_us: int = 0,
                     length_us: int | None = None, events: int | None = None) -> Windows:
    """Back-to-back windows of ``period_us`` from ``t_start_us``; a last partial period is dropped.

    The number of windows follows from the time span, not from the file's
    size, so it is checked before anything is allocated: against the memory
    budget (:func:`evtk.limits.require_memory`) and, given the recording's
    ``events``, against the work they justify
    (:func:`evtk.limits.require_window_work`), both naming the period and
    the span. Windows that would end past the largest int64 time stamp are
    dropped (and counted).

    Parameters
    ----------
    t_start_us, t_end_us : int or None
        The span to cut (half-open); None when the recording has no events.
    period_us : int
        Length of each window, µs, >= 1.
    skip_us : int
        Microseconds left out at the start of every window, >= 0.
    length_us : int, optional
        Keep at most this many microseconds of every window (after ``skip_us``); None keeps all of it.
    events : int, optional
        Events of the recording, to bound the work (unchecked when None).

    Returns
    -------
    Windows
        Source ``"period"``, captures numbered from 0.

    Raises
    ------
    EvtkError
        No span, a span shorter than one period, or more windows than the
        memory budget or the events allow.
    """
    period_us = int(period_us)
    if period_us < 1:
        raise EvtkError(f"period_us must be >= 1, not {period_us}")
    if t_start_us is None or t_end_us is None:
        raise EvtkError("the recording has no events, so no time span to cut into periods")
    t0, t1 = int(t_start_us), int(t_end_us)
    n = (t1 - t0) // period_us if t1 > t0 else 0  # Python integers: a span of 2**64 us does not wrap
    if n < 1:
        raise EvtkError(f"the recording ({t0} .. {t1} us) is shorter than one period of {period_us} us")
    past = max(0, n - (_T_MAX - t0) // period_us)  # windows that would end past the largest int64 stamp
    n -= past
    if n < 1:
        raise EvtkError(f"a period of {period_us} us from {t0} us ends past the largest time stamp (2**63 - 1 us)")
    span = f"--window period:{period_us} over {t0:,} .. {t1:,} us"
    require_memory(n * 40, f"{span}: {n:,} windows of {period_us} us")
    if events is not None:
        require_window_work(n, 0, events, span)
    t_on = t0 + period_us * np.arange(n, dtype=np.int64)
    start, end = _trim(t_on, t_on + period_us, skip_us, length_us, "periodic")
    dropped = {"partial last period": 1} if t0 + (n + past) * period_us < t1 else {}
    if past:
        dropped["ends past the largest time stamp"] = past
    return Windows(start, end, np.arange(n), "period", dropped)
