"""evtk: event-camera I/O, simulation and reconstruction for an opto-electronic convolution accelerator."""

import os as _os
import sys as _sys

# First, before numpy loads (OpenBLAS reads its settings once, as it loads): OpenBLAS (numpy's and scipy's BLAS)
# starts a thread a core and each busy-waits for work about 0.1 s before it sleeps, at start and after every call.
# evtk's own BLAS work is small matrices on one thread (evtk._blas), so that spinning only took cores from its
# decoding threads: 1.2-1.9 s of CPU time in every fresh process of a 16-core machine, about 0.1 s on two (issue
# 32, tenth round). At OpenBLAS's least timeout (2**4 cycles) idle threads sleep at once and are woken for work as
# before; results and thread counts do not change. Set only where the user has not set it; child processes
# inherit it. (Here rather than in a module of its own: a module more is 0.15 ms of every fresh process.)
if "numpy" not in _sys.modules:
    _os.environ.setdefault("OPENBLAS_THREAD_TIMEOUT", "4")
del _os, _sys

from typing import TYPE_CHECKING  # noqa: E402

from .errors import EvtkError, FormatError  # noqa: E402
from .io import detect_format, open, read_events, write_events  # noqa: E402

if TYPE_CHECKING:  # for type checkers; at run time these load on first use (below)
    from ._version import __version__
    from .cluster import to_dask
    from .events import Events, TriggerKind, Triggers
    from .io import Recording
    from .io.reconstruction import save_reconstruction
    from .reconstruct.files import load_reconstruction
    from .workflow import reconstruct_recording

# loaded on first use (numba compiles and loads its caches when they are), so that the command line starts fast;
# __version__ too (its module is one more a fresh read would load for nothing: the writers and the CLI load it)
_LAZY = {"__version__": "_version", "Events": "events", "Triggers": "events", "TriggerKind": "events",
         "to_dask": "cluster", "Recording": "io", "load_reconstruction": "reconstruct.files",
         "save_reconstruction": "io.reconstruction", "reconstruct_recording": "workflow"}


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
