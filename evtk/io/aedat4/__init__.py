"""AEDAT4 reading and writing, byte-compatible with iniVation's dv-processing.

The layout evtk relies on is written down in ``docs/formats/aedat4.md``.  In
short: a magic line, a size-prefixed ``IOHeader`` FlatBuffer holding the
compression, the position of the data table and an XML description of the
streams, then packets (stream id, body size, compressed size-prefixed
FlatBuffer), then an optional ``FileDataTable`` indexing every packet.
"""

from __future__ import annotations

from .common import _IDENT, DEFAULT_PACKET_EVENTS, DEFAULT_PACKET_US, MAGIC  # noqa: F401  (_IDENT: the fuzzers)
from .reader import Recording

# the header's parts: the hostile-file tests and fuzzers build files from them
from .writer import _DTP_FIELD, Aedat4Writer, _header_xml, _io_header, write_aedat4  # noqa: F401

__all__ = ["Recording", "Aedat4Writer", "write_aedat4", "MAGIC", "DEFAULT_PACKET_EVENTS", "DEFAULT_PACKET_US"]
