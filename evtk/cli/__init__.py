"""The ``evtk`` command: one sub-command per library entry point, one module per group of commands.

Each command parses its options and calls one library function; the shared
option types and helpers live in :mod:`evtk.cli._base`.
"""

from __future__ import annotations

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

__all__ = ["main", "_dumps"]
