"""What an HDF5 file is allowed to make evtk do: storage, links, chunk and time checks (one policy)."""

from __future__ import annotations

import os
import stat
import struct

import numpy as np

from ...errors import FormatError
from .common import _ECF_MISSING, _H5_ERRORS, PROPHESEE_ECF_FILTER, _h5


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


def blosc1_chunk_damage(raw: bytes | bytearray | memoryview, expected_nbytes: int) -> str | None:
    """Why a Blosc (v1) chunk would make c-blosc read outside it, or None if its layout is sound.

    c-blosc 1 trusts the sizes and offsets inside a chunk (the HDF5 filter
    does not even pass it the chunk's length), so a damaged chunk can crash
    the process. Checked here, from the chunk's own bytes: the 16-byte header
    (uncompressed size equal to the HDF5 chunk's, compressed size equal to
    the stored length), every block start, and every stream's length inside
    each block, split into ``typesize`` streams where c-blosc splits them.

    Parameters
    ----------
    raw : bytes-like
        The chunk as stored in the file (still compressed).
    expected_nbytes : int
        Its uncompressed size, as the dataset's chunk shape and dtype give it (bytes).

    Returns
    -------
    str or None
        What is wrong, in words naming the byte or block, or None when the layout is sound (the compressed
        streams themselves are left to the decoder).
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


def trust_external_by_default() -> bool:
    """Whether HDF5 files may read other files when the caller does not say: ``$EVTK_TRUST_EXTERNAL``
    (``evtk --trust-external`` sets it) set to anything but ``0``.

    Returns
    -------
    bool
        True to trust.
    """
    return os.environ.get("EVTK_TRUST_EXTERNAL", "") not in ("", "0")


def root_link(path: str | os.PathLike[str], name: str) -> bool:
    """Whether the HDF5 file ``path`` has a link ``name`` at its root; the link itself is looked at, nothing
    it points to (an external file is not opened).

    Parameters
    ----------
    path : str or os.PathLike
        The file.
    name : str
        A member of the root group.

    Returns
    -------
    bool
        False too when the file does not open as HDF5.
    """
    h5py = _h5()
    try:
        with h5py.File(path, "r") as f:
            return f.get(name, getlink=True) is not None
    except (OSError, ValueError, RuntimeError, KeyError):  # damaged metadata: h5py raises RuntimeError too
        return False


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
        return _external_problem(ds, plist, policy), None
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
        short = _raw_chunk_of_wrong_size(ds, plist, chunk_bytes)
        if short is not None:
            return short, None
    elif layout == h5d.CONTIGUOUS:
        if ds.id.get_offset() is None or ds.id.get_storage_size() < claimed:
            return f"{name} was never written (no storage for its {n} elements)", 0
    return None, None


def _raw_chunk_of_wrong_size(ds, plist, chunk_bytes: int) -> str | None:
    """Why a chunk stored without its filters cannot be read, or None.

    A chunk that no filter touched (the dataset has none, or the chunk's filter mask skips them all) holds exactly
    its chunk's bytes. When the chunk index or the filter pipeline message is damaged, it may claim fewer: libhdf5
    then fills the rest of the read from memory it never wrote, so the same read returns different values from one
    call to the next. Every chunk is checked once, from the chunk index (no data is read).
    """
    nfilters = plist.get_nfilters()
    every = (1 << nfilters) - 1
    found: list = []

    def visit(info) -> None:
        if not found and (nfilters == 0 or info.filter_mask & every == every) and info.size != chunk_bytes:
            found.append(info)

    if hasattr(ds.id, "chunk_iter"):
        ds.id.chunk_iter(visit)
    elif nfilters == 0:  # older HDF5: one call a chunk, for the datasets that can have such chunks
        for i in range(ds.id.get_num_chunks()):
            visit(ds.id.get_chunk_info(i))
    if not found:
        return None
    info = found[0]
    return (f"{ds.name}: the chunk at {tuple(int(v) for v in info.chunk_offset)} (byte {info.byte_offset}) is stored "
            f"unfiltered in {info.size} bytes, but a chunk holds {chunk_bytes}")


#: What HDF5 stores as the size of an external segment that runs to the end of its file.
_UNLIMITED = 2**64 - 1


def _external_problem(ds, plist, policy) -> str | None:
    """Why a trusted dataset's external storage cannot be read as declared, or None.

    Each file must be a regular file (not ``/dev/zero``, a FIFO or a device, which never end or never
    answer) that holds the part of its segment the dataset reads: the dataset's bytes are taken from the
    segments in order, and a file shorter than the part taken from it is refused. A segment that runs to
    the end of its file (declared unlimited) is bounded by the dataset's own size, so the bytes read
    never exceed what the files hold.
    """
    need = int(ds.size) * int(ds.dtype.itemsize)
    for i in range(plist.get_external_count()):
        raw, offset, size = plist.get_external(i)
        name = raw.decode("utf-8", "replace")
        for where in _candidates(policy, name):
            try:
                st = os.stat(where)
            except OSError:
                continue
            if not stat.S_ISREG(st.st_mode):
                return f"{ds.name} keeps its data in {where}, which is not a regular file"
            use = min(need, size if size != _UNLIMITED else need)
            if st.st_size < offset + use:
                return (f"{ds.name} reads {use} bytes at byte {offset} of external file {where}, which holds "
                        f"{st.st_size}")
        need -= min(need, size)
    if need > 0:
        return f"{ds.name}: its external files are declared {need} bytes short of its {ds.size} elements"
    return None


def _candidates(policy, name):
    """The paths HDF5 may read for an external file ``name``: beside the file, and as given."""
    beside = _source_path(policy, name)
    return [beside] if beside == name else [beside, name]


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
