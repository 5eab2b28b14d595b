"""The AEDAT4 constants, and the compiled FlatBuffers encoders the writer loads on first use."""

from __future__ import annotations

import numpy as np

from .. import _fbpy
from ..base import StreamInfo

MAGIC = b"#!AER-DAT4.0\r\n"
_HEADER_START = len(MAGIC)
_IDENT = {name: np.frombuffer(name.encode(), np.uint8) for name in ("EVTS", "TRIG", "IMUS", "FRME", "FTAB", "IOHE")}


def _jit():
    """The FlatBuffers encoders (:mod:`evtk.io._fb`, numpy; loaded on first use: only writing needs them,
    reading decodes with :mod:`evtk.io._fbpy`)."""
    from .. import _fb

    return _fb
# types whose element count is the length of the root table's first vector
_VECTOR_TYPES = {"EVTS", "TRIG", "IMUS"}
# ... and the element size of those whose vector holds structs (which then ends the packet)
_STRUCT_SIZE = {"EVTS": _fbpy.EVENT_STRUCT}
_TYPE_NAMES = StreamInfo.KINDS

DEFAULT_PACKET_EVENTS = 8192
DEFAULT_PACKET_US = 10_000

def _status(code) -> str:
    return _fbpy.STATUS_TEXT.get(int(code), f"status {int(code)}")
