"""HDF5 event recordings: evtk's own layout and the common foreign ones.

evtk's layout (``docs/formats/hdf5.md``) stores the four columns separately,
chunked and compressed, plus a block index so that a time window reads only
the chunks that overlap it.  :class:`Hdf5Recording` also reads the DSEC,
Prophesee and event_utils layouts, recognised by their structure.
"""

from __future__ import annotations

import contextlib
import json
import os
import struct

import numpy as np

from .._version import __version__
from ..errors import EvtkError, FormatError, one_line
from ..events import Events, Triggers
from ._atomic import AtomicFile, FailSafeFile
from ._checks import require_readable, scan_events, sorted_for_writing
from ._overlay import SplicedFile, close_at_exit
from .base import BaseRecording, BaseWriter, Damage, StreamInfo, load_json, sensor_dims

__all__ = ["Hdf5Recording", "Hdf5Writer", "write_hdf5", "COMPRESSIONS", "EVTK_FORMAT"]

EVTK_FORMAT = "evtk.events"
FORMAT_VERSION = 1
INTERRUPTED = "evtk_writing"  # root attribute present while a writer has the file open
# fill values of the event datasets: what a chunk the index does not reach reads as (after an interrupted
# flush), chosen to fail the reader's checks (time going backwards, a coordinate outside the sensor)
_FILL = {"t": np.iinfo(np.int64).min, "x": 65535, "y": 65535, "p": 255}
DEFAULT_CHUNK = 65536
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


# =============================================================================
# Reading
# =============================================================================


class _Layout:
    """How one HDF5 layout maps onto columns, an optional time index and metadata."""

    name = "?"

    def __init__(self, f, path):
        self.f = f
        self.path = path
        self.sensor_size = None
        self.metadata = {}
        self.index_t = None  # index: index_t[k] <= t of event index_id[k] ...
        self.index_id = None  # ... and every event before index_id[k] is earlier than index_t[k]
        self.short_size = None  # where a stored size that may be the largest coordinate came from (then fitted)

    def __len__(self):
        return self.n

    def read(self, i0, i1):  # pragma: no cover - overridden
        raise NotImplementedError

    def triggers(self) -> Triggers:
        return Triggers()

    def compression(self):
        return None


def _fixed_text(obj, name):
    """A fixed-length string attribute, or None.

    Variable-length strings live in HDF5's global heap, which the library can
    loop on forever when a file is damaged; evtk writes and trusts only
    fixed-length ones.
    """
    if name not in obj.attrs:
        return None
    aid = obj.attrs.get_id(name)
    if aid.dtype.kind != "S" or aid.shape not in ((), (1,)):
        return None
    value = obj.attrs[name]
    if isinstance(value, np.ndarray):
        value = value.reshape(-1)[0]
    return value.decode("utf-8", "replace") if isinstance(value, bytes) else str(value)


def _need(f, path, names, layout):
    missing = [n for n in names if n not in f]
    if missing:
        raise FormatError(path, None, f"{layout} layout: dataset(s) {', '.join('/' + m for m in missing)} missing")
    return [f[n] for n in names]


def _check_int(ds, path, what, kinds="iu"):
    if ds.dtype.kind not in kinds:
        raise FormatError(path, None, f"dataset {ds.name} ({what}) has dtype {ds.dtype}, expected an integer type")


def _check_lengths(path, datasets, equal=True):
    lengths = {d.name: d.shape[0] if d.shape else None for d in datasets}
    if any(d.ndim != 1 for d in datasets):
        bad = [d.name for d in datasets if d.ndim != 1]
        raise FormatError(path, None, f"dataset(s) {', '.join(bad)} must be one-dimensional")
    if equal and len(set(lengths.values())) != 1:
        detail = ", ".join(f"{k}={v}" for k, v in lengths.items())
        raise FormatError(path, None, f"event datasets differ in length: {detail}")
    return next(iter(lengths.values()))


def _describe_filters(ds):
    """Filter ids of a dataset's pipeline."""
    plist = ds.id.get_create_plist()
    return [plist.get_filter(i)[0] for i in range(plist.get_nfilters())]


BLOSC1_FILTER = 32001
_BLOSC_FILTERS = {BLOSC1_FILTER: "Blosc", 32026: "Blosc2"}
_BLOSC_MEMCPYED, _BLOSC_DONT_SPLIT = 0x02, 0x10
_BLOSC_MAX_SPLITS, _BLOSC_MIN_BUFFERSIZE = 16, 128


def blosc1_chunk_damage(raw, expected_nbytes) -> str | None:
    """Why a Blosc (v1) chunk would make c-blosc read outside it, or None if its layout is sound.

    c-blosc 1 trusts the sizes and offsets inside a chunk (the HDF5 filter
    does not even pass it the chunk's length), so a damaged chunk can crash
    the process. Checked here, from the chunk's own bytes: the 16-byte header
    (uncompressed size equal to the HDF5 chunk's, compressed size equal to
    the stored length), every block start, and every stream's length inside
    each block, split into ``typesize`` streams where c-blosc splits them.
    """
    n = len(raw)
    if n < 16:
        return f"{n} bytes, shorter than the 16-byte header"
    flags, typesize = raw[2], raw[3]
    nbytes, blocksize, ctbytes = struct.unpack_from("<iii", raw, 4)
    if ctbytes != n:
        return f"the header gives {ctbytes} compressed bytes, the chunk has {n}"
    if nbytes != expected_nbytes:
        return f"the header gives {nbytes} uncompressed bytes, the chunk holds {expected_nbytes}"
    if flags & _BLOSC_MEMCPYED:
        return None if ctbytes == nbytes + 16 else f"a stored (uncompressed) chunk of {ctbytes} bytes for {nbytes}"
    if nbytes == 0:
        return None
    if blocksize <= 0 or blocksize > nbytes or typesize == 0:
        return f"block size {blocksize} (type size {typesize}) for {nbytes} bytes"
    nblocks, leftover = divmod(nbytes, blocksize)
    nblocks += leftover > 0
    first = 16 + 4 * nblocks
    if first > n:
        return f"{nblocks} block starts do not fit in {n} bytes"
    starts = struct.unpack_from(f"<{nblocks}i", raw, 16)
    for b, start in enumerate(starts):
        last = b == nblocks - 1 and leftover > 0
        split = (not flags & _BLOSC_DONT_SPLIT and typesize <= _BLOSC_MAX_SPLITS
                 and blocksize // typesize >= _BLOSC_MIN_BUFFERSIZE and not last)
        streams = typesize if split else 1
        pos = start
        if not first <= pos <= n:
            return f"block {b} starts at byte {pos}, outside {first}..{n}"
        for k in range(streams):
            if pos + 4 > n:
                return f"stream {k} of block {b} has no length (byte {pos})"
            (cbytes,) = struct.unpack_from("<i", raw, pos)
            if cbytes < 0 or pos + 4 + cbytes > n:  # (snappy's streams may exceed their raw size)
                return f"stream {k} of block {b} claims {cbytes} bytes at byte {pos}, past the chunk's {n}"
            pos += 4 + cbytes
    return None


class _Blosc1Checked:
    """A Blosc (v1) dataset whose chunks are checked (:func:`blosc1_chunk_damage`) before HDF5 decodes them.

    Reads along the first axis check only the chunks they touch, each once
    (the chunks at the start of the other axes: event columns are 1-D);
    a damaged chunk raises OSError naming its dataset, index and byte offset
    (readers turn that into a FormatError, or salvage what comes before it).
    """

    def __init__(self, ds, position):
        self._ds = ds
        self._position = position  # the filter's place in the pipeline: a chunk may skip it
        self._last = position == ds.id.get_create_plist().get_nfilters() - 1
        self._len = ds.chunks[0]
        self._nbytes = int(np.prod(ds.chunks)) * ds.dtype.itemsize
        self._ndim = ds.ndim
        self._n = ds.shape[0] if ds.ndim else 0
        self._ok = set()
        try:
            self._file_bytes = int(ds.file.id.get_filesize())
        except (OSError, ValueError, AttributeError):  # pragma: no cover - a file object without a size
            self._file_bytes = None

    def __getattr__(self, name):
        return getattr(self._ds, name)

    def __len__(self):
        return len(self._ds)

    def __getitem__(self, key):
        self._check(key)
        return self._ds[key]

    def fields(self, names):
        return _CheckedFields(self, names)

    def _check(self, key):
        ds = self._ds
        if not self._last or self._ndim == 0:  # another filter comes after Blosc on disk: not Blosc's bytes
            return
        n = self._n
        first = key[0] if isinstance(key, tuple) and key else key
        if isinstance(first, slice):
            start, stop, _ = first.indices(n)
        elif isinstance(first, (int, np.integer)):
            start = int(first) % n if n else 0
            stop = start + 1
        else:  # Ellipsis, (), lists: the whole axis
            start, stop = 0, n
        if stop <= start:
            return
        zeros = (0,) * (self._ndim - 1)
        for c in range(start // self._len, (stop - 1) // self._len + 1):
            if c in self._ok:
                continue
            offset = (c * self._len,) + zeros
            try:  # h5py allocates the size the chunk index claims before libhdf5 checks it against the file
                stored = ds.id.get_chunk_info_by_coord(offset).size
            except (OSError, ValueError, AttributeError):
                stored = None
            if stored is not None and self._file_bytes is not None and stored > self._file_bytes:
                raise OSError(f"chunk {c} of {ds.name} claims {stored} bytes, more than the whole file "
                              f"({self._file_bytes})")
            try:
                mask, raw = ds.id.read_direct_chunk(offset)
            except (OSError, ValueError):  # not written (HDF5 gives the fill value), or unreadable: HDF5 says
                self._ok.add(c)
                continue
            if not mask & (1 << self._position):
                why = blosc1_chunk_damage(memoryview(raw), self._nbytes)
                if why:
                    at = ds.id.get_chunk_info_by_coord(offset).byte_offset
                    raise OSError(f"Blosc chunk {c} of {ds.name} (byte {at}) is damaged: {why}")
            self._ok.add(c)


class _CheckedFields:
    def __init__(self, checked, names):
        self._checked = checked
        self._names = names

    def __getitem__(self, key):
        self._checked._check(key)
        return self._checked._ds.fields(self._names)[key]


class _Policy:
    """What a reader allows a file to do: follow links out of it, and how much data its datasets may claim."""

    def __init__(self, path, trust_external=False, salvage=False, file_bytes=None):
        self.path = path
        self.trust_external = bool(trust_external)
        self.salvage = bool(salvage)
        self.file_bytes = file_bytes
        self.unwritten = {}  # salvage: dataset name -> (elements before its first unwritten chunk, why)


#: Largest uncompressed HDF5 chunk evtk decodes: every read of one element decodes its whole chunk.
MAX_CHUNK_BYTES = 64 << 20
#: What a dataset may claim beyond a fixed budget, as a multiple of the whole file's size (event columns
#: compress 2-6x): a dataset claiming more is a decompression bomb or a lie, not a recording.
DATA_BUDGET_BYTES = 256 << 20
DATA_RATIO = 64
_TRUST_HINT = "evtk does not read outside a file unless told to trust it (trust_external=True, --trust-external)"


def _source_path(policy, name):
    """Where HDF5 looks for a file another one names (its directory first, then the working directory)."""
    if name in (".", ""):
        return policy.path
    if os.path.isabs(name):
        return name
    beside = os.path.join(os.path.dirname(os.path.abspath(policy.path)), name)
    return beside if os.path.exists(beside) else name


def _check_links(group, name, policy, depth=0):
    """Refuse an external link anywhere along ``name`` (soft links are followed, within the file)."""
    h5py = _h5()
    if depth > 16:
        raise FormatError(policy.path, None, f"soft links around {name} loop")
    g = group.file if name.startswith("/") else group
    parts = [p for p in name.split("/") if p and p != "."]
    for k, part in enumerate(parts):
        link = g.get(part, getlink=True)
        where = (g.name.rstrip("/") + "/" + part) if g.name else part
        if link is None:
            return
        if isinstance(link, h5py.ExternalLink):
            target = f"{link.filename}:{link.path}"
            if not policy.trust_external:
                raise FormatError(policy.path, None, f"{where} is an external link to {target}; {_TRUST_HINT}")
            if not os.path.exists(_source_path(policy, link.filename)):
                raise FormatError(policy.path, None, f"{where} is an external link to {target}, which does not exist")
        elif isinstance(link, h5py.SoftLink):
            _check_links(g.file, link.path, policy, depth + 1)
        if k < len(parts) - 1:
            g = g[part]


def _storage_problem(ds, policy) -> tuple[str | None, int | None]:
    """``(why the dataset cannot be trusted, elements written along axis 0 when some chunks are not)``.

    Refused: storage in other files and virtual datasets (unless trusted; a missing source always), chunks
    larger than :data:`MAX_CHUNK_BYTES`, more data than :data:`DATA_BUDGET_BYTES` plus :data:`DATA_RATIO`
    times the file, and elements never written (HDF5 would return fill values for them).
    """
    h5d = _h5().h5d
    name = ds.name
    plist = ds.id.get_create_plist()
    if ds.is_virtual:
        sources = [(v.file_name, v.dset_name) for v in ds.virtual_sources()]
        listed = ", ".join(f"{f}:{d}" for f, d in sources[:4]) + (" ..." if len(sources) > 4 else "")
        if not policy.trust_external:
            return f"{name} is a virtual dataset reading {listed}; {_TRUST_HINT}", None
        missing = [f for f, _ in sources if not os.path.exists(_source_path(policy, f))]
        if missing:
            return f"{name} is a virtual dataset whose source file {missing[0]} does not exist", None
        return None, None
    externals = plist.get_external_count()
    if externals:
        files = [plist.get_external(i)[0].decode("utf-8", "replace") for i in range(externals)]
        if not policy.trust_external:
            return f"{name} keeps its data in external file(s) {', '.join(files[:4])}; {_TRUST_HINT}", None
        missing = [f for f in files if not os.path.exists(_source_path(policy, f))]
        if missing:
            return f"{name} keeps its data in external file {missing[0]}, which does not exist", None
        return None, None
    n = int(ds.size)
    item = int(ds.dtype.itemsize)
    if n == 0:
        return None, None
    claimed = n * item
    if policy.file_bytes is not None and claimed > DATA_BUDGET_BYTES + DATA_RATIO * policy.file_bytes:
        return (f"{name} claims {n} elements ({claimed} bytes), far more than a file of {policy.file_bytes} "
                "bytes can hold"), None
    layout = plist.get_layout()
    if layout == h5d.CHUNKED:
        chunks = ds.chunks
        chunk_bytes = int(np.prod(chunks, dtype=np.int64)) * item
        if chunk_bytes > MAX_CHUNK_BYTES:
            return f"{name} has chunks of {chunk_bytes} bytes, more than the {MAX_CHUNK_BYTES} evtk decodes", None
        needed = 1
        for size, c in zip(ds.shape, chunks):
            needed *= -(-size // c)
        written = ds.id.get_num_chunks()
        if written < needed:
            return (f"{name} has {written} of its {needed} chunks written (the rest would read as fill values)",
                    _written_prefix(ds) if ds.ndim == 1 else 0)
    elif layout == h5d.CONTIGUOUS:
        if ds.id.get_offset() is None or ds.id.get_storage_size() < claimed:
            return f"{name} was never written (no storage for its {n} elements)", 0
    return None, None


def _written_prefix(ds) -> int:
    """Elements of a 1-D chunked dataset before its first chunk that was never written."""
    c = ds.chunks[0]
    have = set()
    for i in range(ds.id.get_num_chunks()):
        have.add(ds.id.get_chunk_info(i).chunk_offset[0] // c)
    k = 0
    while k in have:
        k += 1
    return min(int(ds.shape[0]), k * c)


def _checked(node, policy):
    """``node`` itself, or for a Blosc (v1) dataset a :class:`_Blosc1Checked` view; groups stay groups
    whose members are checked the same way. A dataset the policy refuses (:func:`_storage_problem`) or a
    Blosc or Blosc2 pipeline with too few parameters raises before any read. In salvage mode a dataset with
    unwritten chunks is noted in ``policy.unwritten``, with how many of its elements can be read."""
    h5py = _h5()
    if isinstance(node, h5py.Dataset):
        try:
            plist = node.id.get_create_plist()
            pipeline = [plist.get_filter(i) for i in range(plist.get_nfilters())]
        except Exception:
            return node
        ids = [f[0] for f in pipeline]
        for fid, _flags, values, _name in pipeline:
            # the Blosc filters read their type and chunk sizes from parameters 2 and 3 without checking
            # that there are that many: a damaged pipeline message with fewer crashed the process
            if fid in _BLOSC_FILTERS and len(values) < 4:
                raise OSError(f"{node.name}: the filter pipeline is damaged ({_BLOSC_FILTERS[fid]} with "
                              f"{len(values)} parameters, at least 4 expected)")
            if fid == PROPHESEE_ECF_FILTER and not h5py.h5z.filter_avail(fid):
                raise FormatError(policy.path, None, f"{node.name} {_ECF_MISSING}")
        try:
            why, written = _storage_problem(node, policy)
        except _H5_ERRORS:
            if not policy.salvage:
                raise
            why = written = None  # a damaged chunk index: salvage reads what it can reach
        if why is not None:
            if not (policy.salvage and written is not None):
                raise FormatError(policy.path, None, why)
            policy.unwritten[node.name] = (written, why)
        if BLOSC1_FILTER in ids and node.chunks:
            return _Blosc1Checked(node, ids.index(BLOSC1_FILTER))
        return node
    if isinstance(node, h5py.Group):
        return _CheckedGroup(node, policy)
    return node


class _CheckedGroup:
    """An HDF5 group (or file) whose members come back checked (:func:`_checked`), reached only through
    links that stay inside the file unless the policy trusts it (:func:`_check_links`)."""

    def __init__(self, group, policy):
        self._g = group
        self._policy = policy

    def __getattr__(self, name):
        return getattr(self._g, name)

    def __contains__(self, name):
        return name in self._g

    def __iter__(self):
        return iter(self._g)

    def __len__(self):
        return len(self._g)

    def __getitem__(self, name):
        _check_links(self._g, name, self._policy)
        return _checked(self._g[name], self._policy)


_T_MAX = np.iinfo(np.int64).max


def _as_us(raw, path, name, offset=0) -> np.ndarray:
    """Time stamps as int64 microseconds (``raw`` plus ``offset``), or a FormatError naming the dataset when
    one does not fit: uint64 stamps at or above 2**63 would wrap negative, an offset could overflow."""
    if not len(raw):
        return np.zeros(0, np.int64)
    if raw.dtype.kind == "u" and raw.dtype.itemsize == 8 and int(raw.max()) > _T_MAX:
        raise FormatError(path, None, f"{name} holds time stamp {int(raw.max())}, beyond int64 microseconds")
    if offset:
        lo, hi = int(raw.min()) + offset, int(raw.max()) + offset
        if not -_T_MAX <= lo <= hi <= _T_MAX:
            raise FormatError(path, None, f"{name} plus the time offset {offset} leaves int64 microseconds")
        return raw.astype(np.int64) + np.int64(offset)
    return raw.astype(np.int64, copy=False)


def _seconds_as_us(raw, path, name) -> np.ndarray:
    """event_utils time stamps (float seconds) as int64 microseconds; NaN, infinities and values beyond
    int64 microseconds are a FormatError naming the dataset."""
    if raw.dtype.kind != "f":
        return _as_us(raw, path, name)
    us = np.round(raw.astype(np.float64) * 1e6)
    bad = ~(np.abs(us) < 2.0**63)
    if bad.any():
        i = int(np.argmax(bad))
        raise FormatError(path, None, f"{name}[{i}] = {raw[i]!r} seconds is not a time evtk can hold")
    return us.astype(np.int64)


class _EvtkLayout(_Layout):
    name = "evtk"

    def __init__(self, f, path):
        super().__init__(f, path)
        g = f["events"]
        self.t, self.x, self.y, self.p = _need(g, path, ["t", "x", "y", "p"], "evtk")
        for ds, what in ((self.t, "time"), (self.x, "x"), (self.y, "y"), (self.p, "polarity")):
            _check_int(ds, path, what, "iub" if what == "polarity" else "iu")
        # set by the writer until it closes: a file that still has it was left by an interrupted writer, whose
        # columns may have been flushed to different lengths
        self.interrupted = INTERRUPTED in f.attrs
        if self.interrupted:
            _check_lengths(path, [self.t, self.x, self.y, self.p], equal=False)
            self.n = min(int(d.shape[0]) for d in (self.t, self.x, self.y, self.p))
        else:
            self.n = _check_lengths(path, [self.t, self.x, self.y, self.p])
        size = f.attrs.get("sensor_size")
        if size is None or len(size) != 2:
            raise FormatError(path, None, "evtk layout: root attribute 'sensor_size' [width, height] missing")
        self.sensor_size = sensor_dims(size[0], size[1], path, "root attribute sensor_size")
        if "metadata" in f:
            ds = f["metadata"]
            if ds.dtype != np.uint8 or ds.ndim != 1:
                raise FormatError(path, None, "/metadata must be a 1-D uint8 dataset of UTF-8 JSON")
            self.metadata = load_json(ds[...].tobytes(), path, "/metadata")
        self.index_problem = None  # why the index cannot be used (a reader may go on without it)
        try:
            if "index_t_us" in g:
                stride = int(g["index_t_us"].attrs.get("stride", 0))
                index = g["index_t_us"][...]
                if stride <= 0 or len(index) != (self.n + stride - 1) // stride:
                    raise FormatError(path, None, "the block index /events/index_t_us does not match /events/t")
                self.index_t = index.astype(np.int64)
                self.index_id = np.arange(len(index), dtype=np.int64) * stride
        except (OSError, KeyError, ValueError, TypeError, RuntimeError) as exc:  # libhdf5 on a damaged object
            self.index_problem = f"the block index /events/index_t_us cannot be read ({one_line(exc)})"

    def read(self, i0, i1):
        return _as_us(self.t[i0:i1], self.path, self.t.name), self.x[i0:i1], self.y[i0:i1], self.p[i0:i1]

    def read_t(self, i0, i1):
        return _as_us(self.t[i0:i1], self.path, self.t.name)

    def triggers(self):
        if "triggers" not in self.f:
            return Triggers()
        t, k = _need(self.f["triggers"], self.path, ["t", "kind"], "evtk")
        if t.shape != k.shape:
            raise FormatError(self.path, None, "datasets /triggers/t and /triggers/kind differ in length")
        return Triggers(t[...], k[...])

    def compression(self):
        ids = _describe_filters(self.t)
        names = {32001: "blosc", 32004: "lz4", 32015: "zstd", 32026: "blosc2", 1: "gzip", 2: "shuffle"}
        parts = [names.get(i, str(i)) for i in ids if i != 2]
        return "+".join(parts) if parts else "none"


class _DsecLayout(_Layout):
    """DSEC: /events/{x,y,t,p}, /ms_to_idx, /t_offset (t relative to t_offset)."""

    name = "dsec"

    def __init__(self, f, path):
        super().__init__(f, path)
        g = f["events"]
        self.t, self.x, self.y, self.p = _need(g, path, ["t", "x", "y", "p"], "DSEC")
        for ds in (self.t, self.x, self.y, self.p):
            _check_int(ds, path, ds.name.rsplit("/", 1)[-1], "iub")
        self.n = _check_lengths(path, [self.t, self.x, self.y, self.p])
        self.offset = 0
        if "t_offset" in f:
            off = f["t_offset"][()]
            if np.ndim(off) != 0 or np.asarray(off).dtype.kind not in "iu":
                raise FormatError(path, None, "/t_offset must be one integer (microseconds)")
            self.offset = int(off)
            if not -_T_MAX <= self.offset <= _T_MAX:
                raise FormatError(path, None, f"/t_offset {self.offset} is beyond int64 microseconds")
        ms_ds = f["ms_to_idx"]
        _check_int(ms_ds, path, "index", "iu")
        ms = _as_us(ms_ds[...].reshape(-1), path, ms_ds.name)
        if len(ms) and 1000 * (len(ms) - 1) > _T_MAX - max(self.offset, 0):
            raise FormatError(path, None, "/ms_to_idx spans more milliseconds than int64 microseconds hold")
        self.index_t = self.offset + 1000 * np.arange(len(ms), dtype=np.int64)
        self.index_id = np.clip(ms, 0, self.n)

    def read(self, i0, i1):
        return self.read_t(i0, i1), self.x[i0:i1], self.y[i0:i1], self.p[i0:i1]

    def read_t(self, i0, i1):
        return _as_us(self.t[i0:i1], self.path, self.t.name, self.offset)


class _PropheseeLayout(_Layout):
    """Prophesee: /CD/events compound (x, y, p, t) and /CD/indexes (id, ts)."""

    name = "prophesee"

    def __init__(self, f, path):
        super().__init__(f, path)
        ds = f["CD/events"]  # (refused when compressed with a filter that is not installed)
        names = ds.dtype.names or ()
        missing = [c for c in ("x", "y", "p", "t") if c not in names]
        if missing:
            raise FormatError(path, None, f"/CD/events lacks field(s) {missing}; it has {list(names)}")
        if ds.ndim != 1:
            raise FormatError(path, None, "/CD/events must be one-dimensional")
        self.ds = ds
        self.n = ds.shape[0]
        w = f.attrs.get("width", f["CD"].attrs.get("width"))
        h = f.attrs.get("height", f["CD"].attrs.get("height"))
        geometry = f.attrs.get("geometry")
        if w is not None and h is not None:
            self.sensor_size = sensor_dims(w, h, path, "attributes width and height")
        elif geometry is not None:
            text = geometry.decode("utf-8", "replace") if isinstance(geometry, bytes) else str(geometry)
            parts = text.lower().split("x")
            if len(parts) == 2:
                self.sensor_size = sensor_dims(parts[0], parts[1], path, "attribute geometry")
        if "CD/indexes" in f:
            idx = f["CD/indexes"][...]
            if idx.dtype.names and {"id", "ts"} <= set(idx.dtype.names):
                ts = _as_us(idx["ts"], path, "/CD/indexes/ts")
                ok = idx["id"] >= 0  # Prophesee marks empty leading slots with -1
                self.index_t = ts[ok]
                self.index_id = np.clip(idx["id"][ok].astype(np.int64), 0, self.n)
                offset = f["CD/indexes"].attrs.get("offset")
                if offset is not None and np.ndim(offset) == 0 and len(self.index_t):
                    self.index_t = self._with_offset(self.index_t, self.index_id, int(offset))

    def _with_offset(self, index_t, index_id, offset):
        """Prophesee's index times are counted from an ``offset`` attribute: the sign that agrees with the
        stamps of an indexed event (checked where the index reaches an event); as stored when neither does
        (the reader then finds it disagrees and reads without it)."""
        inside = np.flatnonzero((index_id > 0) & (index_id < self.n))
        if not len(inside):
            return index_t
        k = int(inside[len(inside) // 2])
        i = int(index_id[k])
        before, at = (int(v) for v in _as_us(self.ds.fields("t")[i - 1:i + 1], self.path, "/CD/events/t"))
        for cand in (offset, -offset):
            t = int(index_t[k]) + cand
            if before < t <= at:
                return index_t + np.int64(cand)
        return index_t

    def read(self, i0, i1):
        a = self.ds[i0:i1]
        return _as_us(a["t"], self.path, self.ds.name + "/t"), a["x"], a["y"], a["p"]

    def triggers(self):
        """EXT_TRIGGER events: polarity 1 is a rising edge, 0 a falling one."""
        if "EXT_TRIGGER/events" not in self.f:
            return Triggers()
        a = self.f["EXT_TRIGGER/events"][...]
        if not a.dtype.names or not {"p", "t"} <= set(a.dtype.names):
            raise FormatError(self.path, None, "/EXT_TRIGGER/events lacks fields p and t")
        kind = np.where(a["p"] > 0, 1, 2).astype(np.uint8)
        return Triggers(_as_us(a["t"], self.path, "/EXT_TRIGGER/events/t"), kind)

    def read_t(self, i0, i1):
        return _as_us(self.ds.fields("t")[i0:i1], self.path, self.ds.name + "/t")


class _EventUtilsLayout(_Layout):
    """event_utils / E2VID: /events/{xs,ys,ts,ps}, ts in seconds (float)."""

    name = "event_utils"

    def __init__(self, f, path):
        super().__init__(f, path)
        g = f["events"]
        self.xs, self.ys, self.ts, self.ps = _need(g, path, ["xs", "ys", "ts", "ps"], "event_utils")
        for ds in (self.xs, self.ys):
            _check_int(ds, path, ds.name, "iuf")
        if self.ts.dtype.kind not in "fiu":
            raise FormatError(path, None, f"dataset {self.ts.name} has dtype {self.ts.dtype}, expected seconds as float")
        self.n = _check_lengths(path, [self.xs, self.ys, self.ts, self.ps])
        res = f.attrs.get("sensor_resolution")
        if res is not None and len(res) == 2:
            self.sensor_size = sensor_dims(res[1], res[0], path, "attribute sensor_resolution")  # (height, width)
            # some writers store the largest coordinate seen (one less than the sensor): the reader checks
            self.short_size = "attribute sensor_resolution"

    def _t(self, raw):
        return _seconds_as_us(raw, self.path, self.ts.name)

    def read(self, i0, i1):
        p = self.ps[i0:i1]
        return self._t(self.ts[i0:i1]), self.xs[i0:i1], self.ys[i0:i1], (p > 0).astype(np.uint8)

    def read_t(self, i0, i1):
        return self._t(self.ts[i0:i1])


_LAYOUTS = (
    ("evtk", lambda f: _fixed_text(f, "evtk_format") == EVTK_FORMAT and "events" in f, _EvtkLayout),
    ("dsec", lambda f: "events/t" in f and "events/x" in f and "ms_to_idx" in f, _DsecLayout),
    ("prophesee", lambda f: "CD/events" in f, _PropheseeLayout),
    ("event_utils", lambda f: "events/ts" in f and "events/xs" in f, _EventUtilsLayout),
)

_EXPECTED = (
    "evtk (root attribute evtk_format='evtk.events', /events/{t,x,y,p}), "
    "DSEC (/events/{x,y,t,p}, /ms_to_idx, /t_offset), "
    "Prophesee (/CD/events, /CD/indexes) or event_utils (/events/{xs,ys,ts,ps})"
)


def _inventory(f, limit=12):
    names = []

    def visit(name, obj):
        if len(names) < limit:
            names.append("/" + name + ("/" if not hasattr(obj, "shape") else ""))

    f.visititems(visit)
    return names


_H5_ERRORS = (OSError, KeyError, ValueError, TypeError, RuntimeError, IndexError, AttributeError)


def _guard(method):
    """Turn whatever h5py raises on a damaged file into a FormatError naming it."""
    import functools

    @functools.wraps(method)
    def wrapper(self, *args, **kwargs):
        try:
            return method(self, *args, **kwargs)
        except EvtkError:
            raise
        except _H5_ERRORS as exc:
            raise FormatError(self.path, None, f"damaged HDF5 data ({type(exc).__name__}: {exc})") from None

    return wrapper


def _guard_gen(method):
    import functools

    @functools.wraps(method)
    def wrapper(self, *args, **kwargs):
        try:
            yield from method(self, *args, **kwargs)
        except EvtkError:
            raise
        except _H5_ERRORS as exc:
            raise FormatError(self.path, None, f"damaged HDF5 data ({type(exc).__name__}: {exc})") from None

    return wrapper


class Hdf5Recording(BaseRecording):
    """An HDF5 event recording (evtk, DSEC, Prophesee or event_utils layout).

    Parameters
    ----------
    path : str or os.PathLike
    salvage : bool
        Return the events before the first out-of-order or out-of-sensor
        event instead of raising.
    sensor_size : (int, int), optional
        For foreign files that do not record it; otherwise inferred from the
        largest coordinates (with a warning).
    sort : bool
        Sort events by time on reading instead of refusing a file whose
        time stamps go backwards.
    trust_external : bool
        Follow external links, external storage and virtual datasets into
        other files. Off by default: a file could otherwise make evtk read
        (and ``convert`` copy) any file this process can read.
    """

    format = "hdf5"

    def __init__(self, path, salvage=False, sensor_size=None, sort=False, trust_external=False):
        super().__init__(path, salvage)
        h5py = _h5()
        self._spliced = None
        try:
            self._f = h5py.File(self.path, "r")
        except OSError as exc:
            self._f = self._open_truncated(h5py, exc)
        try:
            self._policy = _Policy(self.path, trust_external, self.salvage, os.path.getsize(self.path))
            self._root = _CheckedGroup(self._f, self._policy)
            self._layout = _guard(Hdf5Recording._detect)(self)
            self._clip_unwritten()
            if getattr(self._layout, "interrupted", False):
                self._interrupted()
            if getattr(self._layout, "index_problem", None):
                if not self.salvage:
                    raise FormatError(self.path, None, self._layout.index_problem)
                self.warnings.append(self._layout.index_problem + "; reading without it")
            if sensor_size is not None:
                self._layout.sensor_size = sensor_dims(sensor_size[0], sensor_size[1], None, "sensor_size")
            self._sort = bool(sort)
            self._sorted_cache = None
            self._intact = None
            self._checked = False
            if self._layout.sensor_size is None:
                _guard(Hdf5Recording._infer_sensor_size)(self)
            elif self._layout.short_size and sensor_size is None:
                _guard(Hdf5Recording._fit_sensor_size)(self)
        except BaseException:
            self._f.close()
            raise

    def _close(self):
        try:
            self._f.close()
        finally:
            if self._spliced is not None:
                self._spliced.close()

    def _open_truncated(self, h5py, exc):
        """A file shorter than its superblock records (a truncated copy) opens, with salvage, with the missing
        end reading as zeros: the datasets whose metadata lies before the cut read up to their first chunk
        that was cut off."""
        problem = f"HDF5 library cannot open the file ({one_line(exc)})"
        try:
            size = os.path.getsize(self.path)
            eoa = _superblock_eoa(self.path)
        except OSError:
            eoa = None
        if eoa is None or eoa <= size:
            raise FormatError(self.path, None, problem) from None
        problem = f"the file is truncated: it ends at byte {size} of the {eoa} its superblock records"
        if not self.salvage:
            raise FormatError(self.path, None, problem + "; salvage recovers the events before the cut") from None
        spliced = SplicedFile(self.path, size, size=eoa)
        try:
            f = h5py.File(spliced, "r")
        except Exception as err:  # noqa: BLE001 - libhdf5 reports any failure as OSError or ValueError
            spliced.close()
            raise FormatError(self.path, None, f"{problem}, and what is left does not open "
                                               f"({one_line(err)})") from None
        self._spliced = spliced
        close_at_exit(self)
        self.damage = Damage(size, problem + " (the missing end reads as zeros)")
        return f

    def _interrupted(self):
        """A file its writer never closed: an error, or with salvage what the writer's last flush recorded."""
        if not self.salvage:
            raise FormatError(self.path, None, "the file was never closed by its writer (interrupted?); salvage "
                                               "recovers the events it had flushed")
        self.damage = Damage(None, f"the file was never closed by its writer (interrupted?): it holds the "
                                   f"{self._layout.n} events of its last flush; the triggers and the time index, "
                                   "written on closing, are missing")

    def _detect(self) -> _Layout:
        for _name, test, cls in _LAYOUTS:
            try:
                hit = test(self._f)
            except Exception:
                hit = False
            if hit:
                return cls(self._root, self.path)
        found = _inventory(self._f)
        raise FormatError(
            self.path, None,
            f"unrecognised HDF5 layout: found {found or 'no datasets'}; expected {_EXPECTED}",
        )

    def _clip_unwritten(self):
        """Salvage of a file with chunks never written: the events before the first one (strict reads refused
        the file when its datasets were checked)."""
        lay = self._layout
        if self._policy.unwritten:
            written, why = min(self._policy.unwritten.values())
            if written < lay.n:
                lay.n = int(written)
                self.damage = Damage(None, f"{why}: the {lay.n} events before its first unwritten chunk are read")

    @property
    def layout(self) -> str:
        """Which layout the file uses: 'evtk', 'dsec', 'prophesee' or 'event_utils'."""
        return self._layout.name

    @property
    def sensor_size(self):
        return self._layout.sensor_size

    @property
    def metadata(self) -> dict:
        return self._layout.metadata

    @property
    @_guard
    def compression(self):
        return self._layout.compression()

    def _coordinate_extent(self):
        """``(width, height, events scanned)`` the coordinates need: one pass a block at a time; with salvage,
        over the events before the first unreadable block."""
        w = h = 0
        lay = self._layout
        i0 = 0
        while i0 < lay.n:
            i1 = min(lay.n, i0 + (1 << 22))
            try:
                cols, n = lay.read(i0, i1), i1 - i0
            except (OSError, ValueError, KeyError, TypeError):
                if not self.salvage:
                    raise
                n, cols, _ = self._readable_prefix(i0, i1)
            if n:
                w, h = max(w, int(np.max(cols[1])) + 1), max(h, int(np.max(cols[2])) + 1)
            i0 += n
            if i0 < i1:  # the rest cannot be read
                break
        return w, h, i0

    def _infer_sensor_size(self):
        """From the largest coordinates; with salvage, from those before the first unreadable block."""
        lay = self._layout
        w, h, i0 = self._coordinate_extent()
        lay.sensor_size = (max(w, 1), max(h, 1))
        self.warnings.append(f"the file does not record its sensor size; inferred {lay.sensor_size} from the coordinates"
                             + (f" of the first {i0} events (the rest cannot be read)" if i0 < lay.n else ""))

    def _fit_sensor_size(self):
        """A stored size the coordinates pass (the largest coordinate stored, not the sensor): they decide."""
        lay = self._layout
        sw, sh = lay.sensor_size
        w, h, _ = self._coordinate_extent()
        if w > sw or h > sh:
            fit = sensor_dims(max(w, sw), max(h, sh), self.path, "the coordinates")
            self.warnings.append(f"the {lay.short_size} gives {sw}x{sh} but the coordinates reach ({w - 1}, {h - 1}); "
                                 f"read as a {fit[0]}x{fit[1]} sensor")
            lay.sensor_size = fit

    # -- events -----------------------------------------------------------------
    @_guard
    def _find(self, t_us) -> int:
        """Index of the first event with t >= t_us."""
        lay = self._layout
        n = lay.n
        if lay.index_t is not None and len(lay.index_t):
            k = int(np.searchsorted(lay.index_t, t_us, side="left"))
            lo = int(lay.index_id[k - 1]) if k > 0 else 0
            hi = int(lay.index_id[k]) if k < len(lay.index_t) else n
            lo, hi = min(lo, n), min(max(hi, lo), n)
        else:  # bisect on the stored time stamps, a block at a time
            lo, hi = 0, n
            while hi - lo > 4096:
                mid = (lo + hi) // 2
                if int(lay.read_t(mid, mid + 1)[0]) < t_us:
                    lo = mid + 1
                else:
                    hi = mid
        t = lay.read_t(lo, hi)
        i = lo + int(np.searchsorted(t, t_us, side="left"))
        if lay.index_t is not None and not self._position_ok(i, t_us):
            # an index that lies, or a foreign one that does not mean what we assume: do without it (the check
            # is exact for time-ordered stamps, which every read verifies)
            self.warnings.append("the file's time index disagrees with its time stamps; it is ignored")
            lay.index_t = lay.index_id = None
            return self._find(t_us)
        return i

    def _position_ok(self, i, t_us) -> bool:
        lay = self._layout
        if i > 0 and int(lay.read_t(i - 1, i)[0]) >= t_us:
            return False
        if i < lay.n and int(lay.read_t(i, i + 1)[0]) < t_us:
            return False
        return True

    def _check(self, ev: Events, first_index, t_before) -> int:
        """Number of leading events that are in order and on the sensor.

        Raises FormatError in strict mode; in salvage mode records the damage.
        """
        back, outside = scan_events(ev.t, ev.x, ev.y, self.sensor_size, t_before)
        if self._sort:
            back = -1
        bad = [i for i in (back, outside) if i >= 0]
        if not bad:
            return len(ev)
        first = min(bad)
        if first == back:
            reason = "time stamps go backwards"
        else:
            w, h = self.sensor_size
            reason = f"event lies outside the {w}x{h} sensor"
        self._bad(first_index + first, reason)
        return first

    def _bad(self, index, reason):
        msg = f"{reason} at event index {index}"
        if not self.salvage:
            extra = " (open with sort=True to sort them)" if "backwards" in reason else ""
            raise FormatError(self.path, None, msg + extra)
        if self.damage is None:
            self.damage = Damage(None, msg)

    def _load(self, i0, i1, t_before) -> Events:
        """Events i0..i1, validated; one read per column in the common case."""
        try:
            cols = self._layout.read(i0, i1)
        except (OSError, ValueError, KeyError, TypeError) as exc:
            if not self.salvage:
                raise FormatError(self.path, None, f"events {i0}..{i1} cannot be read ({exc})") from None
            n = i1 - i0
            out = (np.empty(n, np.int64), np.empty(n, np.uint16), np.empty(n, np.uint16), np.empty(n, np.uint8))
            good = self._salvage_block(i0, i1, out, 0, t_before)
            return Events._trusted(*(c[:good] for c in out), self.sensor_size)
        try:
            ev = Events(*cols, self.sensor_size)
        except EvtkError as exc:
            raise FormatError(self.path, None, f"event datasets hold invalid values: {exc}") from None
        good = self._check(ev, i0, t_before)
        return ev if good == len(ev) else ev[:good]

    def _readable_prefix(self, a, b):
        """``(n, columns, reason)``: the longest prefix of events ``a..b`` that reads (bisection: any read
        touching a damaged chunk fails), its columns (None when empty) and why the rest does not."""
        lo, hi = 0, b - a
        reason = "unreadable"
        best = None
        while hi - lo > 1:
            mid = (lo + hi) // 2
            try:
                cols = self._layout.read(a, a + mid)
                lo, best = mid, cols
            except (OSError, ValueError, KeyError, TypeError) as exc:
                hi = mid
                reason = exc
        return lo, best, reason

    def _salvage_block(self, a, b, out, o, t_before) -> int:
        """A block whose read failed: the longest readable prefix (found by bisection, as
        any read touching a damaged chunk fails), then validated; returns how many events
        are intact. The same prefix is found whatever block sizes the caller reads in.
        Reads go through the same path as a normal read (the columns' own dtypes)."""
        lo, best, reason = self._readable_prefix(a, b)
        if self.damage is None:
            self.damage = Damage(None, f"events from index {a + lo} cannot be read ({reason})")
        if best is None:
            return 0
        try:
            ev = Events(*best, self.sensor_size)
        except EvtkError as exc:
            self.damage = Damage(None, f"events from index {a} hold invalid values ({exc})")
            return 0
        for col, src in zip(out, (ev.t, ev.x, ev.y, ev.p)):
            col[o : o + lo] = src
        return self._check(ev, a, t_before)

    def _span(self, t_start_us, t_end_us):
        lay = self._layout
        try:
            i0 = 0 if t_start_us is None else self._find(int(t_start_us))
            i1 = lay.n if t_end_us is None else self._find(int(t_end_us))
            before = int(lay.read_t(i0 - 1, i0)[0]) if i0 > 0 else None
        except (OSError, ValueError) as exc:
            raise FormatError(self.path, None, f"time stamps cannot be read ({exc})") from None
        return i0, max(i0, i1), before

    def _all_sorted(self) -> Events:
        if self._sorted_cache is None:
            self._sorted_cache = self._load(0, self._layout.n, None).sorted()
        return self._sorted_cache

    @_guard
    def events(self, t_start_us=None, t_end_us=None) -> Events:
        """Events with ``t_start_us <= t < t_end_us``; reads only the blocks the window needs."""
        self._check_open()
        if self._sort:
            return self._all_sorted().between(t_start_us, t_end_us)
        i0, i1, before = self._span(t_start_us, t_end_us)
        ev = self._load(i0, i1, before)
        if self.damage is not None and (t_start_us is not None or t_end_us is not None):
            ev = ev.between(t_start_us, t_end_us)
        return ev

    @_guard_gen
    def iter_events(self, chunk_events: int = 1_000_000, t_start_us=None, t_end_us=None):
        """Yield events in order, ``chunk_events`` at a time (memory bounded by the chunk)."""
        self._check_open()
        chunk_events = int(chunk_events)
        if chunk_events < 1:
            raise EvtkError(f"chunk_events must be at least 1, got {chunk_events}")
        if self._sort:
            ev = self._all_sorted().between(t_start_us, t_end_us)
            for i in range(0, len(ev), chunk_events):
                yield ev[i : i + chunk_events]
            return
        i0, i1, before = self._span(t_start_us, t_end_us)
        for a in range(i0, i1, chunk_events):
            b = min(i1, a + chunk_events)
            ev = self._load(a, b, before)
            if len(ev):
                yield ev
                before = int(ev.t[-1])
            if len(ev) < b - a:
                return

    @_guard
    def triggers(self, t_start_us=None, t_end_us=None) -> Triggers:
        self._check_open()
        tr = self._layout.triggers()
        if t_start_us is not None or t_end_us is not None:
            tr = tr.between(t_start_us, t_end_us)
        return tr

    @property
    @_guard
    def streams(self):
        lay = self._layout
        n, first, last = lay.n, None, None
        if n:
            try:
                if self.salvage:  # every column's first and last event, whose chunk indexes salvage also needs
                    first, last = int(lay.read(0, 1)[0][0]), int(lay.read(n - 1, n)[0][0])
                else:
                    first, last = int(lay.read_t(0, 1)[0]), int(lay.read_t(n - 1, n)[0])
            except _H5_ERRORS:
                if not self.salvage:
                    raise
                n, first, last = self._intact_span()
        out = [StreamInfo(0, "events", "EVTS", count=n, t_start_us=first, t_end_us=last, sensor_size=self.sensor_size)]
        try:
            tr = lay.triggers()
            listed = "triggers" in self._f
        except _H5_ERRORS as exc:
            if not self.salvage:
                raise
            self._warn_once("the triggers cannot be read; none counted", f"{type(exc).__name__}: {exc}")
            return out
        if len(tr) or listed:
            out.append(
                StreamInfo(1, "triggers", "TRIG", count=len(tr),
                           t_start_us=int(tr.t.min()) if len(tr) else None,
                           t_end_us=int(tr.t.max()) if len(tr) else None)
            )
        return out

    def _intact_span(self):
        """Salvage, when the first or last event cannot be read: the number of events
        :meth:`iter_events` recovers and their first and last time (one pass, a chunk at a time)."""
        if self._intact is None:
            self._intact = self._read_span()
        return self._intact

    def _extra_info(self):
        return {"layout": self.layout}

    # -- extra arrays (responses, schedules) --------------------------------------
    @_guard
    def read_array(self, name: str) -> np.ndarray:
        """A dataset stored beside the events (for example reconstructed responses)."""
        self._check_open()
        if name not in self._f:
            raise EvtkError(f"{self.path}: no dataset {name!r}")
        return self._root[name][...]


# =============================================================================
# Writing
# =============================================================================


def _superblock_eoa(path):
    """The end-of-file address an HDF5 superblock records (absolute), or None when none is found.

    The superblock sits at byte 0 or after a user block of 512, 1024, 2048, ... bytes.  Versions 0 and 1
    keep the address after four fixed fields; versions 2 and 3 right after the base and extension addresses.
    """
    with open(path, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        at = 0
        while at + 64 <= size:
            f.seek(at)
            head = f.read(64)
            if head[:8] == b"\x89HDF\r\n\x1a\n":
                version = head[8]
                if version in (0, 1):
                    width = head[13]
                    start = 24 if version == 0 else 28
                else:
                    width = head[9]
                    start = 12
                if width not in (2, 4, 8):
                    return None
                base = int.from_bytes(head[start : start + width], "little")
                eoa = int.from_bytes(head[start + 2 * width : start + 3 * width], "little")
                return base + eoa if base + eoa < 1 << 62 else None
            at = 512 if at == 0 else at * 2
    return None


def _copy(ev: Events) -> Events:
    return Events._trusted(ev.t.copy(), ev.x.copy(), ev.y.copy(), ev.p.copy(), ev.sensor_size, True)


class Hdf5Writer(BaseWriter):
    """Stream events into evtk's HDF5 layout, atomically.

    Events must arrive in time order (call :meth:`write_events` as often as
    needed); the block index is built on the way.  Nothing appears under
    ``path`` until :meth:`close`.

    Parameters
    ----------
    path : str or os.PathLike
    sensor_size : (int, int)
    compression : str
        One of :data:`COMPRESSIONS`; default Blosc2-LZ4 with byte shuffle
        (chosen by measurement and robustness, see ``docs/formats/hdf5.md``).
    metadata : dict, optional
        JSON-serialisable, stored in the root attribute ``metadata``.
    chunk_events : int
        HDF5 chunk length, and the stride of the time index.
    """

    def __init__(self, path, sensor_size, compression="lz4", metadata=None, chunk_events=DEFAULT_CHUNK):
        h5py = _h5()
        self.sensor_size = (int(sensor_size[0]), int(sensor_size[1]))
        self.chunk = int(chunk_events)
        if self.chunk < 1:
            raise EvtkError("chunk_events must be positive")
        kw = _filter(str(compression).lower())
        try:
            meta_text = json.dumps(metadata or {}, sort_keys=True)
        except (TypeError, ValueError) as exc:
            raise EvtkError(f"metadata must be JSON-serialisable: {exc}") from None
        self._atomic = AtomicFile(path)
        self.path = self._atomic.path
        # libhdf5 writes through a Python file object that turns into a sink once the disk fails: a failed
        # write is then one error, and the library still closes (it crashed the process at exit otherwise)
        self._sink = FailSafeFile(self._atomic.file)
        try:
            self._f = h5py.File(self._sink, "w")
            f = self._f
            f.attrs["evtk_format"] = np.bytes_(EVTK_FORMAT)
            f.attrs["evtk_format_version"] = FORMAT_VERSION
            f.attrs["evtk_version"] = np.bytes_(__version__)
            f.attrs["sensor_size"] = np.asarray(self.sensor_size, np.int64)
            f.attrs["time_unit"] = np.bytes_("us")
            f.attrs[INTERRUPTED] = np.uint8(1)
            f.create_dataset("metadata", data=np.frombuffer(meta_text.encode("utf-8"), np.uint8))
            g = f.create_group("events")
            self._cols = {}
            for name, dtype in (("t", np.int64), ("x", np.uint16), ("y", np.uint16), ("p", np.uint8)):
                self._cols[name] = g.create_dataset(name, shape=(0,), maxshape=(None,), dtype=dtype, chunks=(self.chunk,),
                                                    fillvalue=_FILL[name], **kw)
            self._cols["t"].attrs["unit"] = np.bytes_("us")
            self._index = []
            self._n = 0  # events accepted ...
            self._stored = 0  # ... of which in the datasets (whole chunks until close)
            self._tail = []  # the rest, fewer than a chunk
            self._last_t = None
            self._trig = []
            self._closed = False
            f.flush()  # from here on the partial file opens (and salvages) as an interrupted evtk file
        except BaseException:
            self._discard()
            raise

    def write_events(self, events: Events):
        """Append time-ordered events."""
        self._check_open()
        if tuple(events.sensor_size) != self.sensor_size:
            raise EvtkError(f"events are for a {events.sensor_size} sensor, the file for {self.sensor_size}")
        n = len(events)
        if n == 0:
            return
        require_readable(events, self.sensor_size, self._last_t, self._n, "HDF5")
        a, b = self._n, self._n + n
        first_block = -(-a // self.chunk)
        starts = np.arange(first_block * self.chunk, b, self.chunk)
        if len(starts):
            self._index.append(events.t[starts - a])
        self._n = b
        self._last_t = int(events.t[-1])
        self._tail.append(events)
        whole = (b // self.chunk) * self.chunk
        if whole > self._stored:
            with self._disk():
                self._store(whole)
                self._f.flush()  # the file on disk is complete up to here: a kill loses at most the events since
        else:  # keep our own copy: the caller may reuse its arrays
            self._tail[-1] = _copy(events)

    def _store(self, upto):
        """Move the buffered events up to index ``upto`` into the datasets.

        Only whole chunks are stored before :meth:`close`, so a stored chunk is never rewritten: after a kill
        every chunk the last flush recorded is still where it was.
        """
        pending = Events.concatenate(self._tail, sensor_size=self.sensor_size) if len(self._tail) > 1 else self._tail[0]
        a, k = self._stored, upto - self._stored
        for name in ("t", "x", "y", "p"):
            ds = self._cols[name]
            ds.resize((upto,))
            ds[a:upto] = getattr(pending, name)[:k]
        self._tail = [_copy(pending[k:])] if k < len(pending) else []
        self._stored = upto

    def write_triggers(self, triggers: Triggers):
        self._check_open()
        self._trig.append(triggers)

    def write_array(self, name: str, data, attrs=None):
        """Store an extra dataset (responses, schedule, parameters) in the same file."""
        self._check_open()
        if name.strip("/").split("/")[0] in ("events", "triggers"):
            raise EvtkError(f"{name!r} is reserved for evtk's event layout")
        with self._disk():
            ds = self._f.create_dataset(name, data=np.asarray(data))
            for k, v in (attrs or {}).items():
                ds.attrs[k] = v

    @contextlib.contextmanager
    def _disk(self):
        """A write that the disk refused (full, over quota, too large) becomes one EvtkError, with the partial
        file removed; any previous file under the name is untouched."""
        try:
            yield
        except EvtkError:
            raise
        except Exception:
            failure = self._sink.failure
            if failure is None:
                raise
            self._closed = True
            self._discard()
            raise EvtkError(f"cannot write {self.path}: {failure.strerror or failure} (nothing was written "
                            "under that name)") from None

    # -- finishing (BaseWriter's close and abort) --------------------------------------
    def _finish(self):
        with self._disk():
            self._finish_file()

    def _commit(self):
        self._atomic.commit()

    def _finish_file(self):
        """Store what is buffered, the time index and the triggers, and close the HDF5 file."""
        if self._stored < self._n:
            self._store(self._n)
        g = self._f["events"]
        index = np.concatenate(self._index) if self._index else np.zeros(0, np.int64)
        ds = g.create_dataset("index_t_us", data=index.astype(np.int64))
        ds.attrs["stride"] = self.chunk
        if self._trig:
            tr = Triggers.concatenate(self._trig)
            order = np.argsort(tr.t, kind="stable")
            tg = self._f.create_group("triggers")
            tg.create_dataset("t", data=tr.t[order])
            tg.create_dataset("kind", data=tr.kind[order])
        del self._f.attrs[INTERRUPTED]
        self._f.close()

    def _discard(self):
        try:
            self._f.close()
        except Exception:
            pass
        self._atomic.discard()


def write_hdf5(path, events: Events, triggers: Triggers | None = None, compression="lz4", metadata=None, sort=False, **kwargs):
    """Write a whole recording in evtk's HDF5 layout (atomically)."""
    events = sorted_for_writing(events, sort, "HDF5")
    with Hdf5Writer(path, events.sensor_size, compression, metadata, **kwargs) as w:
        for a in range(0, len(events), 1 << 22):
            w.write_events(events[a : a + (1 << 22)])
        if triggers is not None:
            w.write_triggers(triggers)
