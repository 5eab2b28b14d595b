"""The ``evtk`` command: one sub-command per library entry point, one module per group of commands.

Each command parses its options and calls one library function; the shared
option types and helpers live in :mod:`evtk.cli._base`.
"""

from __future__ import annotations

import gc
from collections.abc import Sequence

from ._base import _dumps, _LazyCommands, main

#: Which module registers each command: a command's module loads when the command is first asked for by name
#: (``evtk reconstruct`` loads no other command's module); listing the commands loads them all.
COMMAND_MODULES = {
    "batch": "reconstruct", "reconstruct": "reconstruct",
    "calibrate": "simulate", "demo": "simulate", "patterns": "simulate", "simulate": "simulate",
    "classify": "experiments", "recover": "experiments", "robustness": "experiments",
    "convert": "files", "info": "files",
    "enob": "noise", "flips": "noise", "tradeoff": "noise",
}

main.commands = _LazyCommands({name: f"{__name__}.{module}" for name, module in COMMAND_MODULES.items()})


def console(args: Sequence[str] | None = None) -> None:
    """The ``evtk`` program (the installed command and ``python -m evtk.cli``): :func:`main` in a process of its
    own, which it ends.

    After the command, whatever its outcome, the objects still alive are frozen out of the garbage collector
    (:func:`gc.freeze`): the interpreter's exit then skips its last full collections over every object that
    the imports made (some tens of thousands: numpy's, click's, evtk's), 30-40 ms of a fresh ``evtk enob``.
    Nothing is lost by it: the files a command writes are closed by then, and Python never promised finalizers
    at exit. In a process that goes on after the command (a notebook, a test runner, a script that imports
    :func:`main`), call :func:`main`, which leaves the collector alone.

    Parameters
    ----------
    args : sequence of str, optional
        The command line after ``evtk`` (default: ``sys.argv[1:]``).

    Raises
    ------
    SystemExit
        Always, with the command's exit status.
    """
    try:
        main(args)
    finally:
        gc.freeze()


__all__ = ["main", "console", "_dumps"]
