"""evtk: event-camera I/O, simulation and reconstruction for an opto-electronic convolution accelerator."""

from ._version import __version__
from .errors import EvtkError, FormatError
from .io import detect_format, open, read_events, write_events

# loaded on first use (numba compiles and loads its caches when they are), so that the command line starts fast
_LAZY = {"Events": "events", "Triggers": "events", "TriggerKind": "events", "to_dask": "cluster", "Recording": "io",
         "load_reconstruction": "reconstruct.files", "save_reconstruction": "io.reconstruction",
         "reconstruct_recording": "workflow"}


def __getattr__(name):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

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
    "load_reconstruction",
    "save_reconstruction",
    "reconstruct_recording",
]
