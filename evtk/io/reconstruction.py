"""Reconstruction files: what ``evtk reconstruct`` writes, and reading them back.

The layout is specified in ``docs/formats/reconstruction.md``. One file holds the
responses of every capture (resampled, binary and on the response's own cell
grid), the windows they were counted in, the per-pixel ON/OFF counts, the
ideal responses when known, and the run's summary (parameters, errors) as
JSON. Two containers: evtk's HDF5 (``.h5``/``.hdf5``, arrays under
``/reconstruction``) and NumPy's ``.npz``.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from .._atomic import AtomicFile
from ..errors import EvtkError, FormatError
from .base import load_json, sensor_dims

if TYPE_CHECKING:  # zipfile (with shutil, bz2, lzma) loads where an NPZ is read: 8 ms of every `evtk info`
    import zipfile

__all__ = ["save_reconstruction", "read_reconstruction", "is_reconstruction", "describe_reconstruction",
           "LAYOUT_VERSION"]

#: Version of the layout, stored as ``layout_version`` in the summary JSON.
LAYOUT_VERSION = 1
_REQUIRED = ("responses", "binary", "cells", "window_start_us", "window_end_us", "on", "off")
_OPTIONAL = ("ideal", "pairs")
_I32_MAX = np.iinfo(np.int32).max
_I64_MAX = np.iinfo(np.int64).max


def save_reconstruction(path: str | os.PathLike[str], result: Any, sensor_size: Sequence[int],
                        metadata: Mapping[str, Any] | None = None) -> None:
    """Write a :class:`~evtk.reconstruct.Reconstruction` as ``.npz`` or evtk HDF5 (``.h5``/``.hdf5``), atomically.

    Arrays: ``responses``, ``binary``, ``cells``, ``ideal`` (when known),
    ``pairs``, ``window_start_us``/``window_end_us``, ``on``/``off`` counts;
    the summary (parameters, errors), the sensor size and ``metadata`` as
    JSON (``summary`` in NPZ, the ``/metadata`` dataset in HDF5). Read back
    with :func:`evtk.reconstruct.load_reconstruction`.

    Parameters
    ----------
    path : str or os.PathLike
        The target; its extension (``.npz``, ``.h5``, ``.hdf5``) picks the container. It appears only once
        complete.
    result : evtk.reconstruct.Reconstruction
        What :func:`evtk.reconstruct.reconstruct` (or ``evtk reconstruct``) returned.
    sensor_size : sequence of two int
        ``(width, height)`` of the recording's sensor, in pixels.
    metadata : Mapping of str to object, optional
        JSON-serialisable entries stored beside the summary (``source``: the recording's path, ...).

    Raises
    ------
    EvtkError
        When the extension is none of those, the metadata or summary is not JSON-serialisable, or the disk
        refuses the write.
    """
    arrays = {"responses": result.responses, "binary": result.binary, "cells": result.cells,
              "window_start_us": result.counts.windows.t_start_us, "window_end_us": result.counts.windows.t_end_us,
              "on": result.counts.on, "off": result.counts.off}
    if result.ideal is not None:
        arrays["ideal"] = result.ideal
    if result.pairs is not None:
        arrays["pairs"] = result.pairs
    meta = {**(metadata or {}), "reconstruction": dict(result.summary), "layout_version": LAYOUT_VERSION,
            "sensor_size": [int(v) for v in sensor_size]}
    ext = os.path.splitext(os.fspath(path))[1].lower()
    if ext == ".npz":
        with AtomicFile(path) as f:
            import json  # here: `evtk info` of a recording does not load it

            _write_npz(f.file, {"summary": np.array(json.dumps(meta)), **arrays})
    elif ext in (".h5", ".hdf5"):
        from .hdf5 import Hdf5Writer  # HDF5 (and its compiled checks) load only for .h5 outputs

        with Hdf5Writer(path, sensor_size, "lz4", meta) as w:
            for name, a in arrays.items():
                w.write_array(f"reconstruction/{name}", a)
    else:
        raise EvtkError(f"cannot tell the output format from {ext!r}: use .npz, .h5 or .hdf5")


#: zlib level of the NPZ members of a large output: 1 deflates the responses about 3x faster than numpy's
#: default (6), for a file about 1.4x larger. Any deflate level reads back with ``np.load``.
NPZ_COMPRESS_LEVEL = 1

#: Outputs whose arrays hold at most this many bytes are stored without compression: deflating 1000 windows of
#: 16x16 responses (4 MB) took 0.05 s at level 1, more than a fresh ``evtk reconstruct`` spends on anything
#: but its read (issue 32), to save 3 MB of disk. Larger outputs (every window's pixels) are deflated.
NPZ_STORE_BYTES = 16 << 20


def _write_npz(file: Any, arrays: Mapping[str, Any]) -> None:
    """An NPZ (a zip of ``.npy`` members: stored when they hold at most :data:`NPZ_STORE_BYTES` together, else
    deflated at :data:`NPZ_COMPRESS_LEVEL`) of ``arrays`` into an open binary file, as ``np.load`` reads it; no
    member is pickled."""
    arrays = {name: np.asanyarray(a) for name, a in arrays.items()}
    if sum(a.nbytes for a in arrays.values()) <= NPZ_STORE_BYTES:
        import io

        members = {}
        for name, a in arrays.items():
            buf = io.BytesIO()
            np.lib.format.write_array(buf, a, allow_pickle=False)
            members[f"{name}.npy"] = buf.getbuffer()
        _write_stored_zip(file, members)
        return
    import zipfile

    with zipfile.ZipFile(file, "w", zipfile.ZIP_DEFLATED, compresslevel=NPZ_COMPRESS_LEVEL, allowZip64=True) as z:
        for name, a in arrays.items():
            with z.open(f"{name}.npy", "w", force_zip64=True) as member:
                np.lib.format.write_array(member, a, allow_pickle=False)


def _write_stored_zip(file: Any, members: Mapping[str, Any]) -> None:
    """A zip archive of ``members`` (ASCII name -> bytes, together below 4 GiB) stored without compression into
    an open binary file at its start: what :mod:`zipfile` writes with ``ZIP_STORED``, without importing it
    (with pathlib and shutil, 9 ms of a fresh process: a fortieth of a 20 M-event read, issue 32)."""
    import struct
    import time
    import zlib

    now = time.localtime()
    stamp = ((now.tm_hour << 11) | (now.tm_min << 5) | (now.tm_sec // 2),
             ((max(now.tm_year, 1980) - 1980) << 9) | (now.tm_mon << 5) | now.tm_mday)  # MS-DOS time, date
    central, offset = [], 0
    for name, data in members.items():
        raw, crc, size = name.encode("ascii"), zlib.crc32(data), len(data)
        head = struct.pack("<4s5H3I2H", b"PK\x03\x04", 20, 0, 0, *stamp, crc, size, size, len(raw), 0)
        file.write(head)
        file.write(raw)
        file.write(data)
        central.append(struct.pack("<4s6H3I5H2I", b"PK\x01\x02", 20 | 3 << 8, 20, 0, 0, *stamp, crc, size, size,
                                   len(raw), 0, 0, 0, 0, 0o644 << 16, offset) + raw)
        offset += len(head) + len(raw) + size
    directory = b"".join(central)
    file.write(directory)
    file.write(struct.pack("<4s4H2IH", b"PK\x05\x06", 0, 0, len(central), len(central), len(directory), offset, 0))


def is_reconstruction(path: str | os.PathLike[str], trust_external: bool | None = None) -> bool:
    """Whether ``path`` is a reconstruction file: an NPZ with a summary, or an HDF5 file with a
    ``/reconstruction`` group and no events.

    A recording that also holds a ``/reconstruction`` group is a recording (its events win, for every
    command; reading it notes the group it leaves aside): :func:`evtk.reconstruct.load_reconstruction` still reads the group
    when asked by name.

    Parameters
    ----------
    path : str or os.PathLike
        The file.
    trust_external : bool, optional
        Let an HDF5 file's ``/reconstruction`` be an external link; None takes ``$EVTK_TRUST_EXTERNAL``.

    Returns
    -------
    bool
        True for a reconstruction file; False for anything else, unreadable files included.

    """
    path = os.fspath(path)
    try:
        with open(path, "rb") as f:
            head = f.read(8)
    except OSError:
        return False
    if head.startswith(_HDF5_MAGIC):
        return _hdf5_kind(path, trust_external) == "reconstruction"
    if head.startswith(b"PK"):
        import zipfile

        try:
            with zipfile.ZipFile(path) as z:
                return "summary.npy" in z.namelist()
        except (zipfile.BadZipFile, OSError, ValueError, NotImplementedError):  # a damaged header's "version 17.3"
            return False
    return False


def _hdf5_kind(path, trust_external) -> str | None:
    """"reconstruction" (a /reconstruction group, no events), "recording" (events, with or without such a
    group) or None (no /reconstruction link; not HDF5 evtk reads)."""
    from .hdf5 import Hdf5Recording, root_link

    if not root_link(path, "reconstruction"):  # the common case, without opening the file as a recording
        return None
    try:
        rec = Hdf5Recording(path, trust_external=_trusted(trust_external))
    except FormatError:  # opened as a recording, it says the same
        return None
    with rec:
        if rec.info()["events"]:
            return "recording"
        return "reconstruction" if rec.holds_group("reconstruction") else None


def _trusted(trust_external) -> bool:
    from .hdf5 import trust_external_by_default

    return trust_external_by_default() if trust_external is None else bool(trust_external)


def read_reconstruction(path: str | os.PathLike[str], trust_external: bool | None = None) -> tuple[dict, dict, tuple, int]:
    """Read and check the arrays and summary of a file written by :func:`save_reconstruction` (or ``evtk
    reconstruct``); :func:`evtk.reconstruct.load_reconstruction` makes a ``Reconstruction`` of them.

    The file is held to the policy event files are (``docs/formats/reconstruction.md``): an HDF5 file may
    not read other files unless trusted (external links, external storage, virtual datasets), nor claim
    more data than it can hold; an NPZ member may not claim more than the file can hold. What the arrays
    need in memory is checked against the budget (``evtk --memory-limit-mb``) before any is read.

    Parameters
    ----------
    path : str or os.PathLike
        An ``.npz``, ``.h5`` or ``.hdf5`` reconstruction file; an HDF5 recording that also holds a
        ``/reconstruction`` group gives that group.
    trust_external : bool, optional
        Let an HDF5 file read other files; None takes ``$EVTK_TRUST_EXTERNAL`` (``evtk --trust-external``).

    Returns
    -------
    arrays : dict
        ``responses``, ``binary``, ``cells``, ``window_start_us``, ``window_end_us``, ``on``, ``off`` and, when
        the file holds them, ``ideal`` and ``pairs``, each checked (shapes that agree, finite values, integer
        ranges).
    summary : dict
        The run's summary, with the file's ``metadata`` (``source``, ``sensor_size``) beside it.
    region : tuple of int
        ``(x0, x1, y0, y1)``: the sensor pixels the counts cover, within the sensor.
    events_used : int
        Events the counts hold.

    Raises
    ------
    FormatError
        When arrays are missing, inconsistent, of a type that is not numeric, or refused by the policy.
    EvtkError
        When the arrays would need more memory than the budget allows.
    """
    path = os.fspath(path)
    arrays, meta = _read(path, _trusted(trust_external))
    missing = [k for k in _REQUIRED if k not in arrays]
    if missing:
        raise FormatError(path, None, f"not a reconstruction file: no {', '.join(missing)}")
    n = arrays["responses"].shape[0] if arrays["responses"].ndim == 3 else -1
    for k in ("responses", "binary", "cells", "ideal"):
        if k in arrays and (arrays[k].ndim != 3 or arrays[k].shape[0] != n):
            raise FormatError(path, None, f"{k} must hold one 2-D response per capture ({n}), not shape "
                                          f"{arrays[k].shape}")
    if arrays["binary"].shape != arrays["responses"].shape:
        raise FormatError(path, None, "binary and responses differ in shape")
    if "pairs" in arrays and arrays["pairs"].shape != (n, 3):
        raise FormatError(path, None, f"pairs must be ({n}, 3), not {arrays['pairs'].shape}")
    if "ideal" in arrays and arrays["ideal"].shape != arrays["cells"].shape:
        raise FormatError(path, None, "ideal and cells differ in shape")
    for k in ("responses", "cells", "ideal"):
        if k in arrays and not np.all(np.isfinite(arrays[k])):
            raise FormatError(path, None, f"{k} holds NaN or infinite values")
    for k, lo, hi in (("binary", -1, 1), ("on", 0, _I32_MAX), ("off", 0, _I32_MAX), ("pairs", 0, _I64_MAX)):
        a = arrays.get(k)
        if a is None or a.size == 0:
            continue
        if a.dtype.kind not in "biu":
            raise FormatError(path, None, f"{k} must hold integers, not {a.dtype}")
        if int(a.min()) < lo or int(a.max()) > hi:
            raise FormatError(path, None, f"{k} holds values outside {lo}..{hi}")
    start, end = arrays["window_start_us"], arrays["window_end_us"]
    for k, a in (("window_start_us", start), ("window_end_us", end)):  # whole µs: never cast from NaN or 1.5
        if a.dtype.kind not in "iu":
            raise FormatError(path, None, f"{k} must hold whole microseconds (integers), not {a.dtype}")
        if a.size and a.dtype.kind == "u" and int(a.max()) > _I64_MAX:
            raise FormatError(path, None, f"{k} holds times beyond int64 microseconds")
    on, off = arrays["on"], arrays["off"]
    if (on.shape != off.shape or on.ndim != 3 or start.ndim != 1 or on.shape[0] != start.shape[0]
            or start.shape != end.shape):
        raise FormatError(path, None, f"window times {start.shape}/{end.shape} and counts {on.shape}/{off.shape} "
                                      "do not match")
    if start.size and np.any(end <= start):
        i = int(np.flatnonzero(end <= start)[0])
        raise FormatError(path, None, f"window times: window {i} is empty or reversed: [{start[i]}, {end[i]}) us")
    inner = meta.get("reconstruction") or {}
    if not isinstance(inner, dict):
        raise FormatError(path, None, "the summary's reconstruction entry must be a JSON object")
    summary = dict(inner)
    for k, v in meta.items():
        if k != "reconstruction":
            summary.setdefault(k, v)
    try:
        region = tuple(int(v) for v in summary.get("region", (0, on.shape[2], 0, on.shape[1])))
        events_used = int(summary.get("events_used", int(on.sum()) + int(off.sum())))
    except (TypeError, ValueError, OverflowError):
        raise FormatError(path, None, "the summary's region or events_used is not made of integers") from None
    if len(region) != 4:
        raise FormatError(path, None, f"the summary's region must be [x0, x1, y0, y1], not {list(region)}")
    size = summary.get("sensor_size")
    if not (isinstance(size, (list, tuple)) and len(size) == 2):
        raise FormatError(path, None, f"the summary's sensor_size must be [width, height], not {size!r}")
    summary["sensor_size"] = list(sensor_dims(size[0], size[1], path, "the summary's sensor_size"))
    w, h = summary["sensor_size"]
    x0, x1, y0, y1 = region
    # counts of (windows, 0, 0): the responses alone were kept (evtk reconstruct without --keep-pixels)
    pixels = tuple(on.shape[1:]) in ((y1 - y0, x1 - x0), (0, 0))
    if not (0 <= x0 < x1 <= w and 0 <= y0 < y1 <= h and pixels):
        raise FormatError(path, None, f"the summary's region {list(region)} is not the counts' "
                                      f"{on.shape[2]}x{on.shape[1]} pixels on the {w}x{h} sensor")
    return arrays, summary, region, events_used


_HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"
#: The dtype each array is converted to on reading (None: kept): what it may need in memory beside its own.
_AS = {"responses": np.float64, "cells": np.float64, "ideal": np.float64, "binary": np.int8, "on": np.int32,
       "off": np.int32}


def _plan(path, found: dict, file_bytes: int) -> None:
    """Refuse arrays ``found`` (name -> (shape, dtype)) that are not numeric or whose claims
    the file cannot back, and check what reading them needs against the memory budget, before any is read.

    What the arrays need, with the copies converting them takes, is bounded as an HDF5 dataset's claim is:
    :data:`~evtk.io.hdf5.checks.DATA_BUDGET_BYTES` plus :data:`~evtk.io.hdf5.checks.DATA_RATIO` times the
    file (responses and counts compress a few times; a zero-filled array a thousand times).
    """
    from ..limits import require_memory
    from .hdf5.checks import DATA_BUDGET_BYTES, DATA_RATIO

    need = 0
    claimed = 0
    for name, (shape, dtype) in found.items():
        if dtype.kind not in "biuf" or dtype.fields is not None or dtype.subdtype is not None:
            raise FormatError(path, None, f"{name} has dtype {dtype}, not a number type")
        nbytes = int(np.prod(shape, dtype=object)) * dtype.itemsize
        claimed += nbytes
        target = _AS.get(name)
        need += nbytes + (0 if target is None or np.dtype(target) == dtype
                          else int(np.prod(shape, dtype=object)) * np.dtype(target).itemsize)
    if need > DATA_BUDGET_BYTES + DATA_RATIO * file_bytes:
        raise FormatError(path, None, f"the arrays claim {claimed} bytes ({need} with their conversions), far "
                                      f"more than a file of {file_bytes} bytes can hold")
    require_memory(need, f"reading the reconstruction {path}")


def _read(path, trust_external):
    """``(arrays, metadata)`` of a reconstruction file in either container, checked before reading."""
    with open(path, "rb") as f:
        head = f.read(8)
    if head.startswith(_HDF5_MAGIC):
        return _read_hdf5(path, trust_external)
    if head.startswith(b"PK"):
        return _read_npz(path)
    raise FormatError(path, 0, "not a reconstruction file (neither HDF5 nor NPZ)")


def _read_hdf5(path, trust_external):
    from .hdf5 import Hdf5Recording  # not at the top: describing an .npz must not load HDF5

    with Hdf5Recording(path, trust_external=trust_external) as rec:
        if not rec.holds_group("reconstruction"):
            raise FormatError(path, None, "not a reconstruction file: no /reconstruction group")
        arrays = rec.read_arrays("reconstruction", _REQUIRED + _OPTIONAL,
                                 before=lambda found: _plan(path, found, os.path.getsize(path)))
        meta = dict(rec.metadata)
        if "sensor_size" not in meta and rec.sensor_size:  # the file's own (a group copied into a recording)
            meta["sensor_size"] = list(rec.sensor_size)
        return arrays, meta


def _read_npz(path):
    """An NPZ's arrays, each member's declared size and ``.npy`` header checked before it is read."""
    import zipfile
    import zlib

    names = ("summary",) + _REQUIRED + _OPTIONAL
    try:
        with zipfile.ZipFile(path) as z:
            members = {i.filename[:-4]: i for i in z.infolist() if i.filename.endswith(".npy")}
            if "summary" not in members:
                raise FormatError(path, None, "not a reconstruction file: the NPZ has no summary")
            _check_zip_layout(z, path)
            unknown = sorted(set(i.filename for i in z.infolist()) - {f"{k}.npy" for k in names})
            if unknown:  # evtk writes none: a member renamed (damage) would otherwise vanish without a word
                raise FormatError(path, None, f"members no reconstruction file has: {', '.join(unknown[:5])}")
            found, headers = {}, {}
            for name in names:
                info = members.get(name)
                if info is None:
                    continue
                with z.open(info) as f:
                    shape, dtype, start = _npy_header(path, name, f)
                if name == "summary":
                    if dtype.kind != "U" or shape != () or dtype.itemsize > info.file_size:
                        raise FormatError(path, info.header_offset, "the summary must be one string")
                    found[name] = ((dtype.itemsize,), np.dtype(np.uint8))
                else:
                    found[name] = (shape, dtype)
                nbytes = int(np.prod(shape, dtype=object)) * dtype.itemsize
                if start + nbytes != info.file_size:
                    raise FormatError(path, info.header_offset,
                                      f"{name}: its header gives {shape} of {dtype} ({nbytes} bytes) but the member "
                                      f"holds {info.file_size - start}")
                headers[name] = info
            _plan(path, found, os.path.getsize(path))
            arrays = {}
            for name, info in headers.items():
                with z.open(info) as f:
                    arrays[name] = np.lib.format.read_array(f, allow_pickle=False)
                    if f.read(1):  # (the member's CRC-32 is checked at its end)
                        raise FormatError(path, info.header_offset, f"{name}: bytes after the array")
    except FormatError:
        raise
    except (zipfile.BadZipFile, zlib.error, ValueError, OSError, EOFError, NotImplementedError,
            RuntimeError) as exc:
        raise FormatError(path, None, f"unreadable NPZ ({exc})") from None
    meta = load_json(str(arrays.pop("summary")), path, "the summary")
    if not isinstance(meta, dict):
        raise FormatError(path, None, "the summary must be a JSON object")
    return arrays, meta


def _check_zip_layout(z: zipfile.ZipFile, path) -> None:
    """Refuse an NPZ whose members do not tile its data: each member's local header and data must end where
    the next begins, and the last where the central directory starts. A damaged directory that lost a member
    (an optional array, which would then vanish without a word) leaves bytes no member names."""
    infos = sorted(z.infolist(), key=lambda i: i.header_offset)
    fp = z.fp
    assert fp is not None  # an open archive
    pos = 0
    for info in infos:
        if info.header_offset != pos:
            raise FormatError(path, pos, f"bytes {pos}..{info.header_offset} belong to no member of the NPZ "
                                         "(its directory is damaged)")
        fp.seek(info.header_offset)
        head = fp.read(30)
        if len(head) < 30 or head[:4] != b"PK\x03\x04":
            raise FormatError(path, info.header_offset, f"{info.filename}: no local header where the directory "
                                                        "points")
        name_len, extra_len = int.from_bytes(head[26:28], "little"), int.from_bytes(head[28:30], "little")
        pos = info.header_offset + 30 + name_len + extra_len + info.compress_size
        if info.flag_bits & 0x08:  # a data descriptor follows the data (signature optional)
            fp.seek(pos)
            pos += 16 if fp.read(4) == b"PK\x07\x08" else 12
    if pos != z.start_dir:
        raise FormatError(path, pos, f"bytes {pos}..{z.start_dir} belong to no member of the NPZ (its directory "
                                     "is damaged)")


def _npy_header(path, name, f):
    """``(shape, dtype, bytes before the data)`` of the ``.npy`` stream ``f``, from its header alone."""
    fmt = np.lib.format
    try:
        version = fmt.read_magic(f)
        if version == (1, 0):
            shape, fortran, dtype = fmt.read_array_header_1_0(f)
        elif version in ((2, 0), (3, 0)):
            shape, fortran, dtype = fmt.read_array_header_2_0(f)
        else:
            raise ValueError(f"unsupported .npy version {version}")
    except (ValueError, TypeError, SyntaxError, EOFError) as exc:
        raise FormatError(path, None, f"{name}: unreadable .npy header ({exc})") from None
    if dtype.hasobject:
        raise FormatError(path, None, f"{name} holds Python objects, which evtk does not load")
    return tuple(int(v) for v in shape), dtype, f.tell()


def describe_reconstruction(path: str | os.PathLike[str]) -> dict[str, Any]:
    """What ``evtk info`` says about a reconstruction file: its container, responses, windows, scenes and run.

    Parameters
    ----------
    path : str or os.PathLike
        A reconstruction file (read whole, as :func:`read_reconstruction` reads it).

    Returns
    -------
    dict
        JSON-ready: ``path``, ``format``, ``container`` ("npz" or "hdf5"), ``layout_version``, ``source``,
        ``sensor_size``, ``region``, ``responses`` (count), ``size`` (resampled response shape), ``cells``
        (cell-grid shape), ``windows``, ``window_source``, ``scenes``, ``most_repeats``, ``linearization``,
        ``binarize``, ``ideal`` (whether the ideal responses are stored) and ``error``.

    Raises
    ------
    FormatError
        When the file is not a readable reconstruction.
    EvtkError
        When its arrays would not fit the memory budget.
    """
    arrays, s, _, _ = read_reconstruction(path)
    pairs = arrays.get("pairs")
    n = int(arrays["responses"].shape[0])
    if pairs is None:  # every window a repeat of one scene
        repeats = [n]
    else:
        _, repeats_arr = np.unique(np.asarray(pairs)[:, :2], axis=0, return_counts=True)
        repeats = repeats_arr.tolist()
    return {
        "path": os.fspath(path),
        "format": "evtk reconstruction",
        "container": "npz" if os.fspath(path).lower().endswith(".npz") else "hdf5",
        "layout_version": s.get("layout_version"),
        "source": s.get("source"),
        "sensor_size": s.get("sensor_size"),
        "region": s.get("region"),
        "responses": n,
        "size": [int(v) for v in arrays["responses"].shape[1:]],
        "cells": [int(v) for v in arrays["cells"].shape[1:]],
        "windows": int(arrays["window_start_us"].shape[0]),
        "window_source": s.get("window_source"),
        "scenes": len(repeats),
        "most_repeats": max(repeats, default=0),
        "linearization": s.get("linearization"),
        "binarize": s.get("binarize"),
        "ideal": "ideal" in arrays,
        "error": s.get("error"),
    }


def human_description(d: dict) -> str:
    """:func:`describe_reconstruction` as aligned lines."""
    lines = [
        f"file         {d['path']}",
        f"format       {d['format']} ({d['container']}, layout {d['layout_version']})",
        f"source       {d['source'] or '-'}",
        f"responses    {d['responses']:,} of {d['size'][0]}x{d['size'][1]} (cells {d['cells'][0]}x{d['cells'][1]})",
        f"windows      {d['windows']:,} from {d['window_source'] or '-'}",
        f"scenes       {d['scenes']:,} (up to {d['most_repeats']} repeats each)",
        f"linearised   {d['linearization'] or '-'}; binarised by {d['binarize'] or '-'}",
    ]
    err = d.get("error")
    if err:
        corr = "-" if err.get("correlation") is None else f"{err['correlation']:.4f}"
        nrmse = "-" if err.get("nrmse") is None else f"{err['nrmse']:.4f}"
        lines.append(f"error        correlation {corr}, NRMSE {nrmse} against the ideal")
    return "\n".join(lines)
