"""Reconstruction files: what ``evtk reconstruct`` writes, and reading them back.

The layout is specified in ``docs/formats/reconstruction.md``. One file holds the
responses of every capture (resampled, binary and on the response's own cell
grid), the windows they were counted in, the per-pixel ON/OFF counts, the
ideal responses when known, and the run's summary (parameters, errors) as
JSON. Two containers: evtk's HDF5 (``.h5``/``.hdf5``, arrays under
``/reconstruction``) and NumPy's ``.npz``.
"""

from __future__ import annotations

import json
import os
import zipfile

import numpy as np

from ..errors import EvtkError, FormatError
from ._atomic import AtomicFile
from .base import load_json

__all__ = ["save_reconstruction", "load_reconstruction", "is_reconstruction", "describe_reconstruction",
           "LAYOUT_VERSION"]

#: Version of the layout, stored as ``layout_version`` in the summary JSON.
LAYOUT_VERSION = 1
_REQUIRED = ("responses", "binary", "cells", "window_start_us", "window_end_us", "on", "off")
_OPTIONAL = ("ideal", "pairs")


def save_reconstruction(path, result, sensor_size, metadata=None):
    """Write a :class:`~evtk.reconstruct.Reconstruction` as ``.npz`` or evtk HDF5 (``.h5``/``.hdf5``), atomically.

    Arrays: ``responses``, ``binary``, ``cells``, ``ideal`` (when known),
    ``pairs``, ``window_start_us``/``window_end_us``, ``on``/``off`` counts;
    the summary (parameters, errors), the sensor size and ``metadata`` as
    JSON (``summary`` in NPZ, the ``/metadata`` dataset in HDF5). Read back
    with :func:`load_reconstruction`.
    """
    arrays = {"responses": result.responses, "binary": result.binary, "cells": result.cells,
              "window_start_us": result.counts.windows.t_start_us, "window_end_us": result.counts.windows.t_end_us,
              "on": result.counts.on, "off": result.counts.off}
    if result.ideal is not None:
        arrays["ideal"] = result.ideal
    if result.pairs is not None:
        arrays["pairs"] = result.pairs
    meta = {**(metadata or {}), "reconstruction": result.summary, "layout_version": LAYOUT_VERSION,
            "sensor_size": [int(v) for v in sensor_size]}
    ext = os.path.splitext(os.fspath(path))[1].lower()
    if ext == ".npz":
        with AtomicFile(path) as f:
            np.savez_compressed(f.file, summary=np.array(json.dumps(meta)), **arrays)
    elif ext in (".h5", ".hdf5"):
        from .hdf5 import Hdf5Writer  # HDF5 (and its compiled checks) load only for .h5 outputs

        with Hdf5Writer(path, sensor_size, "lz4", meta) as w:
            for name, a in arrays.items():
                w.write_array(f"reconstruction/{name}", a)
    else:
        raise EvtkError(f"cannot tell the output format from {ext!r}: use .npz, .h5 or .hdf5")


def is_reconstruction(path) -> bool:
    """Whether ``path`` is a reconstruction file (HDF5 with ``/reconstruction``, or an NPZ with a summary)."""
    path = os.fspath(path)
    try:
        with open(path, "rb") as f:
            head = f.read(8)
    except OSError:
        return False
    if head.startswith(b"\x89HDF\r\n\x1a\n"):
        import h5py

        try:
            with h5py.File(path, "r") as f:
                return f.get("reconstruction", getclass=True) is h5py.Group
        except (OSError, ValueError):
            return False
    if head.startswith(b"PK"):
        try:
            with zipfile.ZipFile(path) as z:
                return "summary.npy" in z.namelist()
        except (zipfile.BadZipFile, OSError):
            return False
    return False


def load_reconstruction(path):
    """Read a file written by :func:`save_reconstruction` (or ``evtk reconstruct``) back.

    Returns a :class:`~evtk.reconstruct.Reconstruction` whose ``counts``
    holds the windows and ON/OFF counts, and whose ``summary`` also carries
    the file's ``metadata`` (``source``, ``sensor_size``). Missing or
    inconsistent arrays are a :class:`~evtk.FormatError` naming them.

    Examples
    --------
    >>> import evtk, tempfile, os
    >>> from evtk.reconstruct import reconstruct
    >>> from evtk.simulate import Simulation
    >>> d = tempfile.mkdtemp()
    >>> _ = Simulation([[1, 0], [0, 1]], [[0, 1, 1], [1, 0, 1], [1, 1, 0]], repeat=2).write(os.path.join(d, "r.h5"))
    >>> with evtk.open(os.path.join(d, "r.h5")) as rec:
    ...     result = reconstruct(rec)
    >>> save_reconstruction(os.path.join(d, "out.npz"), result, (346, 260))
    >>> back = load_reconstruction(os.path.join(d, "out.npz"))
    >>> bool((back.responses == result.responses).all()), back.summary["sensor_size"]
    (True, [346, 260])
    """
    # here, not at the top: describing a file (evtk info) must not load the reconstruction's compiled stages
    from ..reconstruct import Reconstruction, WindowCounts, Windows

    path = os.fspath(path)
    arrays, meta = _read(path)
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
    start, end = arrays["window_start_us"], arrays["window_end_us"]
    on, off = arrays["on"], arrays["off"]
    if on.shape != off.shape or on.ndim != 3 or on.shape[0] != start.shape[0] or start.shape != end.shape:
        raise FormatError(path, None, f"window times {start.shape}/{end.shape} and counts {on.shape}/{off.shape} "
                                      "do not match")
    summary = dict(meta.get("reconstruction") or {})
    for k, v in meta.items():
        if k != "reconstruction":
            summary.setdefault(k, v)
    try:
        windows = Windows(start, end, np.arange(start.shape[0]), str(summary.get("window_source", "file")))
    except EvtkError as exc:
        raise FormatError(path, None, f"window times: {exc}") from None
    region = tuple(int(v) for v in summary.get("region", (0, on.shape[2], 0, on.shape[1])))
    counts = WindowCounts(on.astype(np.int32, copy=False), off.astype(np.int32, copy=False), windows, region,
                          int(summary.get("events_used", int(on.sum()) + int(off.sum()))))
    return Reconstruction(arrays["responses"].astype(np.float64, copy=False), arrays["binary"].astype(np.int8),
                          arrays.get("pairs"), arrays["cells"].astype(np.float64, copy=False), arrays.get("ideal"),
                          counts, summary)


def _read(path):
    """``(arrays, metadata)`` of a reconstruction file in either container."""

    with open(path, "rb") as f:
        head = f.read(8)
    names = _REQUIRED + _OPTIONAL
    if head.startswith(b"\x89HDF\r\n\x1a\n"):
        import h5py

        from .hdf5 import Hdf5Recording  # not at the top: describing an .npz must not load HDF5

        with Hdf5Recording(path) as rec:
            meta = rec.metadata
        with h5py.File(path, "r") as f:
            group = f.get("reconstruction")
            if not isinstance(group, h5py.Group):
                raise FormatError(path, None, "not a reconstruction file: no /reconstruction group")
            arrays = {k: group[k][...] for k in names if isinstance(group.get(k), h5py.Dataset)}
        return arrays, meta
    if head.startswith(b"PK"):
        try:
            with np.load(path, allow_pickle=False) as z:
                if "summary" not in z.files:
                    raise FormatError(path, None, "not a reconstruction file: the NPZ has no summary")
                meta = load_json(str(z["summary"]), path, "the summary")
                arrays = {k: z[k] for k in names if k in z.files}
        except (zipfile.BadZipFile, ValueError, OSError) as exc:
            raise FormatError(path, None, f"unreadable NPZ ({exc})") from None
        if not isinstance(meta, dict):
            raise FormatError(path, None, "the summary must be a JSON object")
        return arrays, meta
    raise FormatError(path, 0, "not a reconstruction file (neither HDF5 nor NPZ)")


def describe_reconstruction(path) -> dict:
    """What ``evtk info`` says about a reconstruction file: its container, responses, windows, scenes and run."""
    result = load_reconstruction(path)
    s = result.summary
    scenes = result.groups()
    return {
        "path": os.fspath(path),
        "format": "evtk reconstruction",
        "container": "npz" if os.fspath(path).lower().endswith(".npz") else "hdf5",
        "layout_version": s.get("layout_version"),
        "source": s.get("source"),
        "sensor_size": s.get("sensor_size"),
        "region": s.get("region"),
        "responses": int(result.responses.shape[0]),
        "size": [int(v) for v in result.responses.shape[1:]],
        "cells": [int(v) for v in result.cells.shape[1:]],
        "windows": int(len(result.counts.windows)),
        "window_source": s.get("window_source"),
        "scenes": len(scenes),
        "most_repeats": max((len(v) for v in scenes.values()), default=0),
        "linearization": s.get("linearization"),
        "binarize": s.get("binarize"),
        "ideal": result.ideal is not None,
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
