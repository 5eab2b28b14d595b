"""HDF5 event recordings: evtk's own layout and the common foreign ones.

evtk's layout (``docs/formats/hdf5.md``) stores the four columns separately,
chunked and compressed, plus a block index so that a time window reads only
the chunks that overlap it.  :class:`Hdf5Recording` also reads the DSEC,
Prophesee and event_utils layouts, recognised by their structure.
"""

from __future__ import annotations

from .checks import blosc1_chunk_damage, root_link, trust_external_by_default
from .common import COMPRESSIONS, DEFAULT_CHUNK, EVTK_FORMAT, FORMAT_VERSION, INTERRUPTED
from .reader import Hdf5Recording
from .writer import Hdf5Writer, write_hdf5

__all__ = ["Hdf5Recording", "Hdf5Writer", "write_hdf5", "COMPRESSIONS", "EVTK_FORMAT", "FORMAT_VERSION",
           "DEFAULT_CHUNK", "INTERRUPTED", "blosc1_chunk_damage", "root_link", "trust_external_by_default"]
