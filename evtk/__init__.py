"""evtk: event-camera I/O, simulation and reconstruction for an opto-electronic convolution accelerator."""

from ._version import __version__
from .errors import EvtkError, FormatError
from .events import Events, Triggers, TriggerKind
from .cluster import to_dask
from .io import Recording, detect_format, open, read_events, write_events

__all__ = [
    "__version__",
    "EvtkError",
    "FormatError",
    "Events",
    "Triggers",
    "TriggerKind",
    "Recording",
    "open",
    "read_events",
    "write_events",
    "detect_format",
    "to_dask",
]
