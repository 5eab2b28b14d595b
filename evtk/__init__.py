"""evtk: event-camera I/O, simulation and reconstruction for an opto-electronic convolution accelerator."""

from typing import TYPE_CHECKING

from . import _openblas_env  # noqa: F401 - first: OpenBLAS reads its settings as numpy loads
from ._version import __version__
from .errors import EvtkError, FormatError
from .io import detect_format, open, read_events, write_events

if TYPE_CHECKING:  # for type checkers; at run time these load on first use (below)
    from .cluster import to_dask
    from .events import Events, TriggerKind, Triggers
    from .io import Recording
    from .io.reconstruction import save_reconstruction
    from .reconstruct.files import load_reconstruction
    from .workflow import reconstruct_recording

# loaded on first use (numba compiles and loads its caches when they are), so that the command line starts fast
_LAZY = {"Events": "events", "Triggers": "events", "TriggerKind": "events", "to_dask": "cluster", "Recording": "io",
         "load_reconstruction": "reconstruct.files", "save_reconstruction": "io.reconstruction",
         "reconstruct_recording": "workflow"}


def __getattr__(name):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))  # the names loaded on first use too


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
