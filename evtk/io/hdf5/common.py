"""Constants, the HDF5 library and the compression filters evtk's HDF5 files use."""

from __future__ import annotations

import numpy as np

from ...errors import EvtkError

EVTK_FORMAT = "evtk.events"
FORMAT_VERSION = 1
INTERRUPTED = "evtk_writing"  # root attribute present while a writer has the file open
# fill values of the event datasets: what a chunk the index does not reach reads as (after an interrupted
# flush), chosen to fail the reader's checks (time going backwards, a coordinate outside the sensor)
_FILL = {"t": np.iinfo(np.int64).min, "x": 65535, "y": 65535, "p": 255}
DEFAULT_CHUNK = 65536
#: Bytes of decoded chunks HDF5 keeps per open dataset (its chunk cache) while evtk reads a file. HDF5 2.0 made it
#: 8 MiB, which a whole read of four event columns kept resident on top of the events (1.30x their size at 10 M
#: events); 1 MiB, the HDF5 1.x size, still holds an evtk chunk (65536 events, 512 KiB of time stamps) so that
#: reads cut inside a chunk decode it once.
READ_CHUNK_CACHE_BYTES = 1 << 20
PROPHESEE_ECF_FILTER = 36559
_ECF_MISSING = ("is compressed with Prophesee's ECF codec (HDF5 filter 36559), which is not installed; install the "
                "ECF HDF5 plugin from Prophesee's OpenEB and point HDF5_PLUGIN_PATH at it")


def _h5():
    """h5py with the hdf5plugin filters registered."""
    import h5py

    try:
        import hdf5plugin  # noqa: F401  (registers Blosc, LZ4, Zstd, ... with HDF5)
    except ImportError:  # pragma: no cover - hdf5plugin is a dependency
        pass
    return h5py


def _filter(name: str) -> dict:
    """h5py dataset keywords for a compression name (see docs/formats/hdf5.md)."""
    import hdf5plugin

    # Blosc2 rather than Blosc (v1): c-blosc 1 trusts the compressed stream and
    # crashes the process on a damaged chunk (found by the fuzz campaign)
    shuffle = hdf5plugin.Blosc2.SHUFFLE
    table = {
        "lz4": lambda: dict(**hdf5plugin.Blosc2(cname="lz4", clevel=5, filters=shuffle)),
        "lz4_high": lambda: dict(**hdf5plugin.Blosc2(cname="lz4hc", clevel=9, filters=shuffle)),
        "zstd": lambda: dict(**hdf5plugin.Blosc2(cname="zstd", clevel=3, filters=shuffle)),
        "zstd_high": lambda: dict(**hdf5plugin.Blosc2(cname="zstd", clevel=9, filters=shuffle)),
        "gzip": lambda: dict(compression="gzip", compression_opts=1, shuffle=True),
        "none": lambda: {},
    }
    try:
        return table[name]()
    except KeyError:
        raise EvtkError(f"unknown HDF5 compression {name!r}; choose one of {sorted(COMPRESSIONS)}") from None


#: Compression names accepted for HDF5 (Blosc2 with byte shuffle unless gzip/none).
COMPRESSIONS = ("lz4", "lz4_high", "zstd", "zstd_high", "gzip", "none")

_H5_ERRORS = (OSError, KeyError, ValueError, TypeError, RuntimeError, IndexError, AttributeError)
