"""The ``evtk`` command: one sub-command per library entry point, one module per group of commands.

Each command parses its options and calls one library function; the shared
option types and helpers live in :mod:`evtk.cli._base`.
"""

from __future__ import annotations

from . import experiments, files, noise, reconstruct, simulate  # noqa: F401  (each registers its commands)
from ._base import _dumps, main

__all__ = ["main", "_dumps"]
