"""The memory budget for work whose size follows from its parameters, checked before anything is allocated.

A window period of 1 us over an hour-long recording, or a million repeats of a
simulated run, asks for more memory than a machine has; evtk estimates the
size first and refuses with one line that says how to raise the limit.
"""

from __future__ import annotations

import os

from .errors import EvtkError

__all__ = ["memory_limit_bytes", "require_memory", "DEFAULT_LIMIT_MB", "LIMIT_ENV"]

#: Default budget for one estimated allocation, in MiB.
DEFAULT_LIMIT_MB = 8192
#: Environment variable that sets the budget (``evtk --memory-limit-mb`` sets it).
LIMIT_ENV = "EVTK_MEMORY_LIMIT_MB"


def memory_limit_bytes() -> int:
    """The budget: ``$EVTK_MEMORY_LIMIT_MB`` MiB if set, else :data:`DEFAULT_LIMIT_MB`."""
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


def require_memory(nbytes, what: str):
    """Raise :class:`~evtk.EvtkError` when ``nbytes`` (an estimate) exceeds the budget."""
    limit = memory_limit_bytes()
    if nbytes > limit:
        raise EvtkError(f"{what} would need about {nbytes / 2**20:,.0f} MiB, more than the {limit / 2**20:,.0f} MiB "
                        f"allowed; raise the limit with evtk --memory-limit-mb or {LIMIT_ENV}")
