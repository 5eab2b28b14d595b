"""The memory budget, and the work bound, for work whose size follows from its input, checked before it starts.

A window period of 1 us over an hour-long recording, or a million repeats of a
simulated run, asks for more memory than a machine has; evtk estimates the
size first and refuses with one line that says how to raise the limit.

Memory is not the only cost a small file can ask for: two events stamped
2**40 us apart, cut into 1 ms windows, make a billion windows that a
streamed measurement (``evtk enob``, ``evtk flips``) would count one batch at
a time, in bounded memory but for hours. :func:`require_window_work` bounds
that work by what the input holds: windows times pixels may reach
:data:`BASE_WINDOW_WORK` for any input and grow by
:data:`WINDOW_WORK_PER_EVENT` with each event, so the time a command takes
stays proportional to the recording it is given.
"""

from __future__ import annotations

import os

from .errors import EvtkError

__all__ = ["memory_limit_bytes", "require_memory", "DEFAULT_LIMIT_MB", "LIMIT_ENV", "require_window_work",
           "window_work", "BASE_WINDOW_WORK", "WINDOW_WORK_PER_EVENT", "WINDOW_OVERHEAD_PX"]

#: Default budget for one estimated allocation, in MiB.
DEFAULT_LIMIT_MB = 8192
#: Environment variable that sets the budget (``evtk --memory-limit-mb`` sets it).
LIMIT_ENV = "EVTK_MEMORY_LIMIT_MB"
#: Work, in window-pixels, that any recording may ask for (a few seconds of counting and measuring).
BASE_WINDOW_WORK = 2**28
#: Window-pixels each event of the recording adds to the work it may ask for.
WINDOW_WORK_PER_EVENT = 1024
#: A window's fixed cost (its bookkeeping, reconstruction and measurement), counted as this many pixels.
WINDOW_OVERHEAD_PX = 256


def memory_limit_bytes() -> int:
    """The budget in bytes.

    Returns
    -------
    int
        ``$EVTK_MEMORY_LIMIT_MB`` MiB if set, else :data:`DEFAULT_LIMIT_MB` MiB.
    """
    text = os.environ.get(LIMIT_ENV, "").strip()
    if not text:
        return DEFAULT_LIMIT_MB << 20
    try:
        mb = float(text)
    except ValueError:
        mb = float("nan")
    if not mb > 0 or mb == float("inf"):
        raise EvtkError(f"{LIMIT_ENV} must be a positive number of MiB, not {text!r}")
    return int(mb * (1 << 20))


def require_memory(nbytes: float, what: str) -> None:
    """Refuse work whose estimated memory exceeds the budget.

    Parameters
    ----------
    nbytes : int or float
        The estimate, in bytes, made before anything is allocated (may be
        far beyond int64: Python integers do not overflow).
    what : str
        What the memory is for, as the error message names it.

    Raises
    ------
    EvtkError
        When ``nbytes`` exceeds :func:`memory_limit_bytes`.
    """
    limit = memory_limit_bytes()
    if nbytes > limit:
        raise EvtkError(f"{what} would need about {nbytes / 2**20:,.0f} MiB, more than the {limit / 2**20:,.0f} MiB "
                        f"allowed; raise the limit with evtk --memory-limit-mb or {LIMIT_ENV}")


def window_work(n_windows: int, pixels: int) -> int:
    """The work of counting, reconstructing and measuring ``n_windows`` windows of ``pixels`` pixels each.

    Parameters
    ----------
    n_windows : int
        How many windows.
    pixels : int
        Pixels counted in each window.

    Returns
    -------
    int
        Window-pixels, each window's fixed cost counted as
        :data:`WINDOW_OVERHEAD_PX` more pixels.
    """
    return int(n_windows) * (max(0, int(pixels)) + WINDOW_OVERHEAD_PX)


def require_window_work(n_windows: int, pixels: int, events: int, what: str) -> None:
    """Refuse more windows than the recording's events justify.

    The work may reach ``max(BASE_WINDOW_WORK, WINDOW_WORK_PER_EVENT * events)``
    window-pixels (:func:`window_work`): any recording a few seconds' worth,
    a large one in proportion to its events. A memory check alone would let
    a streamed measurement count billions of empty windows from a file of
    two events.

    Parameters
    ----------
    n_windows : int
        Windows the command would count.
    pixels : int
        Pixels of each window.
    events : int
        Events of the recording (in the windows' span, or in all).
    what : str
        The windows, as the error message names them (the window spec and
        the time span they were cut from).

    Raises
    ------
    EvtkError
        When the work exceeds the bound.
    """
    work = window_work(n_windows, pixels)
    allowed = max(BASE_WINDOW_WORK, WINDOW_WORK_PER_EVENT * max(0, int(events)))
    if work > allowed:
        of = f" of {int(pixels):,} pixels" if pixels > 0 else ""
        raise EvtkError(f"{what}: {int(n_windows):,} windows{of} for {int(events):,} events "
                        f"is more work than the recording holds (at most {allowed:,} window-pixels); use a longer "
                        "period or a region, or cut the recording to the span that holds its events")
