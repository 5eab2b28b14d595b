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

# the writer (and with it evtk._atomic's tempfile, socket and hashlib) loads on first use: reading needs none of
# it. The header's parts (_DTP_FIELD, _header_xml, _io_header) are there for the hostile-file tests and fuzzers.
_WRITER_NAMES = ("Aedat4Writer", "write_aedat4", "_DTP_FIELD", "_header_xml", "_io_header")


def __getattr__(name: str):
    if name in _WRITER_NAMES:
        from . import writer

        return getattr(writer, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

__all__ = ["Recording", "Aedat4Writer", "write_aedat4", "MAGIC", "DEFAULT_PACKET_EVENTS", "DEFAULT_PACKET_US"]
