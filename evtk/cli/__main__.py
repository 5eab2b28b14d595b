"""``python -m evtk.cli``."""

from . import console

console()
