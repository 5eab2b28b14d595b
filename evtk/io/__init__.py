"""Reading and writing event recordings, format chosen by content or extension.

Reading looks at a file's first bytes, so a misnamed file still opens;
writing goes by the extension of the target path.
"""

from __future__ import annotations

import builtins
import os
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from ..errors import EvtkError, FormatError

if TYPE_CHECKING:  # loaded lazily at run time (below)
    from ..events import Events, Triggers
    from .base import BaseRecording, BaseWriter

__all__ = ["open", "open_writer", "read_events", "write_events", "convert", "detect_format", "Recording", "BaseRecording",
           "WRITE_EXTENSIONS", "WRITE_FORMATS", "write_format"]

# the readers and writers (numba, h5py, pyarrow) load on first use: `evtk --version` and `--help` start fast
_LAZY = {"Recording": ("aedat4", "Recording"), "BaseRecording": ("base", "BaseRecording"),
         "convert": ("_convert", "convert")}


def __getattr__(name):
    if name in _LAZY:
        return _load(*_LAZY[name])
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))  # the names loaded on first use too


def _load(module: str, name: str) -> Any:
    """``name`` from the module ``evtk.io.<module>``, imported (on first use) with the garbage collector paused.

    A reader's first use imports its modules, some thousands of objects that live as long as the process. The
    collections their allocations set off meanwhile only scan objects that survive them: in a fresh process
    reading a small file they were about 3 ms of the 15 ms evtk added to numpy's import (issue 32, fifteenth
    round). The collector runs again afterwards if it was running, whether or not the import succeeded.

    Parameters
    ----------
    module : str
        The module's name inside :mod:`evtk.io` (``"aedat4"``, ``"prophesee"``, ...).
    name : str
        The attribute wanted.

    Returns
    -------
    Any
        The attribute.
    """
    import gc
    import importlib

    running = gc.isenabled()
    gc.disable()
    try:
        return getattr(importlib.import_module(f"{__name__}.{module}"), name)
    finally:
        if running:
            gc.enable()


#: Extension -> format name for writing.
WRITE_EXTENSIONS = {".aedat4": "aedat4", ".h5": "hdf5", ".hdf5": "hdf5", ".parquet": "parquet", ".pq": "parquet",
                    ".raw": "evt3", ".dat": "dat", ".es": "es", ".csv": "csv", ".txt": "csv"}
#: Every format evtk writes: the extension's, or one named by ``fmt=`` (``.raw`` is EVT 3.0 unless ``fmt="evt2"``).
WRITE_FORMATS = ("aedat4", "hdf5", "parquet", "evt2", "evt21", "evt3", "dat", "es", "csv")
#: What each format cannot hold, for the warning a conversion gives (None: everything evtk writes to it).
LOSES = {"aedat4": None, "hdf5": None, "parquet": None, "evt2": "metadata beyond text lines",
         "evt21": "metadata beyond text lines",
         "evt3": "metadata beyond text lines", "dat": "trigger edges", "es": "trigger edges and metadata",
         "csv": "trigger edges and metadata"}


def write_format(path: str | os.PathLike[str], fmt: str | None = None) -> str:
    """The format a write to ``path`` uses: ``fmt`` when given, else the one of its extension.

    Parameters
    ----------
    path : str or os.PathLike
        The target.
    fmt : str, optional
        One of :data:`WRITE_FORMATS`.

    Returns
    -------
    str
        The format's name.

    Raises
    ------
    EvtkError
        When ``fmt`` is not one of :data:`WRITE_FORMATS`, or the extension is not one evtk writes.
    """
    if fmt is not None:
        if fmt not in WRITE_FORMATS:
            raise EvtkError(f"evtk writes {', '.join(WRITE_FORMATS)}; not {fmt!r}")
        return fmt
    ext = os.path.splitext(os.fspath(path))[1].lower()
    found = WRITE_EXTENSIONS.get(ext)
    if found is None:
        raise EvtkError(f"cannot tell the format from the extension {ext!r}; use one of {sorted(WRITE_EXTENSIONS)}")
    return found

_SIGNATURES = (
    (b"#!AER-DAT4.0\r\n", "aedat4"),  # aedat4.MAGIC
    (b"#!AER-DAT", "aedat-other"),
    (b"\x89HDF\r\n\x1a\n", "hdf5"),
    (b"PAR1", "parquet"),
    (b"Event Stream", "event_stream"),
)


def detect_format(path: str | os.PathLike[str]) -> str:
    """Name the format of ``path`` from its first bytes.

    Parameters
    ----------
    path : str or os.PathLike
        The file; only its start is read (16 bytes, more to tell text events and N-MNIST binaries apart).

    Returns
    -------
    str
        ``"aedat4"``, ``"aedat-other"`` (AEDAT 1.0, 2.0 or 3.1), ``"hdf5"``, ``"parquet"``, ``"event_stream"``,
        ``"prophesee"`` (RAW or DAT), ``"text"`` or ``"nmnist"``.

    Raises
    ------
    FormatError
        When the file is empty or of none of these formats.
    EvtkError
        When it is missing, a directory or unreadable.
    """
    path = os.fspath(path)
    try:
        with builtins.open(path, "rb") as f:
            head = f.read(16)
    except FileNotFoundError:
        raise EvtkError(f"no such file: {path}") from None
    except IsADirectoryError:
        raise EvtkError(f"{path} is a directory, not a recording") from None
    except OSError as exc:
        raise EvtkError(f"cannot read {path}: {exc.strerror}") from None
    if not head:
        raise FormatError(path, 0, "the file is empty")
    for sig, name in _SIGNATURES:
        if head.startswith(sig):
            return name
    if head.startswith(b"%"):
        from .prophesee import sniff

        if sniff(path):  # the header lines only, never the events after them
            return "prophesee"
    from .decoded import sniff_nmnist, sniff_text

    with builtins.open(path, "rb") as f:
        if sniff_text(f.read(4096)):
            return "text"
    if sniff_nmnist(path):
        return "nmnist"
    raise FormatError(path, 0, "unrecognised file: not AEDAT4 (#!AER-DAT4.0), HDF5, Parquet, Prophesee "
                               "RAW/DAT (a '%' header), Event Stream, text events (t x y p lines) or an "
                               "N-MNIST binary")


#: Environment variables of ``evtk --sensor-size WxH`` and ``evtk --layout dvs128|davis`` (every command that reads).
SENSOR_SIZE_ENV, LAYOUT_ENV = "EVTK_SENSOR_SIZE", "EVTK_LAYOUT"


def _sensor_size_from_env():
    text = os.environ.get(SENSOR_SIZE_ENV, "").strip().lower()
    if not text:
        return None
    parts = text.split("x")
    if len(parts) != 2 or not all(p.strip().isdigit() for p in parts):
        raise EvtkError(f"{SENSOR_SIZE_ENV} (--sensor-size) must be WIDTHxHEIGHT, e.g. 640x480, not {text!r}")
    return int(parts[0]), int(parts[1])


def open(path: str | os.PathLike[str], salvage: bool = False,  # noqa: A001
         sensor_size: tuple[int, int] | None = None, sort: bool = False,
         trust_external: bool | None = None, verify_checksums: bool | None = None,
         layout: str | None = None) -> BaseRecording:
    """Open a recording for reading; the format is found from the file's first bytes.

    Parameters
    ----------
    path : str or os.PathLike
        An AEDAT4, HDF5 (evtk, DSEC, Prophesee or event_utils layout),
        Parquet, Prophesee RAW (EVT 2.0 or 3.0) or DAT, Event Stream, or
        AEDAT 1.0/2.0/3.1 file.
    salvage : bool
        Recover what is intact before damage instead of raising
        :class:`~evtk.FormatError`; ``recording.damage`` says where it stopped.
    sensor_size : tuple of (int, int), optional
        ``(width, height)`` in pixels, for files that do not record it: HDF5, Parquet, Prophesee RAW with
        neither a geometry nor a known system ID, DAT, text and N-MNIST
        files, legacy AEDAT without a known camera (otherwise sized as each
        format's page says: from the system ID, or the events' extent with a
        warning). None takes ``$EVTK_SENSOR_SIZE`` (``evtk --sensor-size WxH``).
    sort : bool
        HDF5 only: sort events whose time stamps go backwards instead of
        refusing the file.
    trust_external : bool, optional
        HDF5 only: follow external links, external storage and virtual
        datasets into other files. Refused by default (a file could make
        evtk read any file); None takes ``$EVTK_TRUST_EXTERNAL`` (set by
        ``evtk --trust-external``).
    verify_checksums : bool, optional
        Check the checksums a file carries: in AEDAT4 the xxHash32 block and
        content checksums of LZ4 packet bodies (faery writes them; DV and
        dv-processing do not; Zstandard frames' content checksums are checked
        either way), in Parquet the CRC-32 of data pages that have one
        (HDF5's Fletcher-32 filter is always checked by libhdf5). On by
        default: a body or page that fails one raises
        :class:`~evtk.FormatError`. False reads such files unchecked (the
        frames' structure is still checked). None takes
        ``$EVTK_VERIFY_CHECKSUMS`` (``0`` turns it off; set by
        ``evtk --no-verify-checksums`` and ``evtk --verify-checksums``).
    layout : {"dvs128", "davis"}, optional
        AEDAT 2.0 only: the address layout, where the header names no camera
        or names it wrongly (by default the header's ``AEChip``, else found
        from the addresses' bits). None takes ``$EVTK_LAYOUT``
        (``evtk --layout``).

    Returns
    -------
    BaseRecording
        The open recording (a context manager).

    Raises
    ------
    FormatError
        When the file is empty, of no format evtk reads, or damaged where its header is read (without
        ``salvage``; damage in the events is met as they are read).
    EvtkError
        When the file is missing, a directory or unreadable, or ``$EVTK_SENSOR_SIZE`` is malformed.

    Examples
    --------
    >>> import evtk, tempfile, os
    >>> path = os.path.join(tempfile.mkdtemp(), "r.aedat4")
    >>> evtk.write_events(path, evtk.Events([1, 2], [0, 1], [0, 0], [1, 0], (320, 240)))
    >>> with evtk.open(path) as rec:
    ...     print(rec.sensor_size, len(rec.events()))
    (320, 240) 2
    """
    fmt = detect_format(path)
    if sensor_size is None:
        sensor_size = _sensor_size_from_env()
    if layout is None:
        layout = os.environ.get(LAYOUT_ENV, "").strip().lower() or None
    if verify_checksums is None and fmt in ("aedat4", "parquet"):  # only these carry checksums: the codecs'
        verify_checksums = _load("_compression", "verify_by_default")()  # module (lz4, threads) loads for them alone
    if fmt == "aedat-other":
        return _load("aedat_legacy", "LegacyAedatRecording")(path, salvage=salvage, sensor_size=sensor_size, layout=layout)
    if fmt == "aedat4":
        return _load("aedat4", "Recording")(path, salvage=salvage, verify_checksums=bool(verify_checksums))
    if fmt == "prophesee":
        return _load("prophesee", "PropheseeRecording")(path, salvage=salvage, sensor_size=sensor_size)
    if fmt == "event_stream":
        return _load("prophesee", "EventStreamRecording")(path, salvage=salvage, sensor_size=sensor_size)
    if fmt in ("text", "nmnist"):
        cls = _load("decoded", "TextRecording" if fmt == "text" else "NmnistRecording")
        return cls(path, salvage=salvage, sensor_size=sensor_size)
    if fmt == "hdf5":
        if trust_external is None:
            trust_external = _load("hdf5", "trust_external_by_default")()
        return _load("hdf5", "Hdf5Recording")(path, salvage=salvage, sensor_size=sensor_size, sort=sort,
                                              trust_external=trust_external)
    return _load("arrow", "ParquetRecording")(path, salvage=salvage, sensor_size=sensor_size,
                                              verify_checksums=bool(verify_checksums))


def read_events(path: str | os.PathLike[str], t_start_us: int | None = None, t_end_us: int | None = None) -> Events:
    """All events of ``path`` with ``t_start_us <= t < t_end_us``.

    Parameters
    ----------
    path : str or os.PathLike
        A recording in any format :func:`open` reads (opened with its defaults).
    t_start_us : int, optional
        First time kept (µs, inclusive); None: from the start.
    t_end_us : int, optional
        End of the window (µs, exclusive); None: to the end.

    Returns
    -------
    Events
        The events, in file order.
    """
    with open(path) as rec:
        return rec.events(t_start_us, t_end_us)


def write_events(path: str | os.PathLike[str], events: Events, triggers: Triggers | None = None,
                 compression: str = "lz4", metadata: Mapping[str, Any] | None = None, fmt: str | None = None,
                 **kwargs: Any) -> None:
    """Write ``events`` (and triggers) to ``path``; the extension (or ``fmt``) picks the format.

    ``.aedat4``, ``.h5``/``.hdf5`` (evtk's layout), ``.parquet``, ``.raw``
    (Prophesee EVT 3.0, or EVT 2.0 with ``fmt="evt2"``), ``.dat`` (Prophesee
    DAT), ``.es`` (Event Stream) or ``.csv``/``.txt`` (text events). The file
    appears under its name only once complete. Extra keywords go to the
    format's writer (for example ``packet_events`` for AEDAT4, ``sort`` and
    ``chunk_events`` for HDF5, ``row_group_events`` for Parquet). DAT, Event
    Stream and CSV hold no triggers: passing some is an error there.

    Parameters
    ----------
    path : str or os.PathLike
        The target.
    events : Events
        The events (in time order for every format but AEDAT4 and Parquet).
    triggers : Triggers, optional
        Trigger edges, for the formats that hold them.
    compression : str
        AEDAT4, HDF5 and Parquet: the codec.
    metadata : Mapping of str to object, optional
        JSON-ready metadata, for the formats that hold it.
    fmt : str, optional
        One of :data:`WRITE_FORMATS`, overriding the extension.
    **kwargs : Any
        The format writer's own options.

    Raises
    ------
    EvtkError
        When the format is unknown, ``events`` is not :class:`~evtk.Events`, triggers are given to a format
        without them, or the writer refuses the events; no file is left under ``path`` then.
    """
    fmt = write_format(path, fmt)
    from ..events import Events

    if not isinstance(events, Events):
        raise EvtkError(f"events must be evtk.Events, got {type(events).__name__}")
    if fmt in ("evt2", "evt21", "evt3", "dat", "es", "csv"):
        with open_writer(path, events.sensor_size, metadata=metadata, triggers=triggers, fmt=fmt) as w:
            w.write_events(events)
        return
    if fmt == "aedat4":
        from . import aedat4

        aedat4.write_aedat4(path, events, triggers, compression=compression, metadata=metadata, **kwargs)
    elif fmt == "hdf5":
        from .hdf5 import write_hdf5

        write_hdf5(path, events, triggers, compression=compression, metadata=metadata, **kwargs)
    else:
        from .arrow import write_parquet

        write_parquet(path, events, triggers, compression=compression, metadata=metadata, **kwargs)


def open_writer(path: str | os.PathLike[str], sensor_size: tuple[int, int], compression: str = "lz4",
                metadata: Mapping[str, Any] | None = None, triggers: Triggers | None = None, fmt: str | None = None,
                **kwargs: Any) -> BaseWriter:
    """A streaming writer for ``path`` (format from the extension, or ``fmt``).

    Call ``write_events`` as often as needed, then ``close`` (or use it as a
    context manager, which discards the partial file on an exception).
    Triggers are written first (RAW files interleave them by time); HDF5,
    RAW, DAT, Event Stream and CSV need events in time order. Extra keywords
    go to the format's writer (for AEDAT4 ``source`` and ``extra_streams``,
    see :class:`evtk.io.aedat4.Aedat4Writer`).

    Parameters
    ----------
    path : str or os.PathLike
        The target.
    sensor_size : tuple of (int, int)
        Width and height in pixels.
    compression : str
        AEDAT4, HDF5 and Parquet: the codec.
    metadata : Mapping of str to object, optional
        JSON-ready metadata, for the formats that hold it.
    triggers : Triggers, optional
        Trigger edges, for the formats that hold them.
    fmt : str, optional
        One of :data:`WRITE_FORMATS`, overriding the extension.
    **kwargs : Any
        The format writer's own options.

    Returns
    -------
    BaseWriter
        The writer, a context manager.
    """
    fmt = write_format(path, fmt)
    if fmt in ("evt2", "evt21", "evt3", "dat", "es", "csv"):
        from .foreign import ForeignWriter

        return ForeignWriter(path, fmt, sensor_size, metadata, triggers)
    if fmt == "aedat4":
        import numpy as np

        from ..events import Triggers
        from . import aedat4

        w = aedat4.Aedat4Writer(path, sensor_size, compression, triggers=triggers is not None, metadata=metadata,
                                **kwargs)
        if triggers is not None and len(triggers):
            order = np.argsort(triggers.t, kind="stable")
            w.write_triggers(Triggers(triggers.t[order], triggers.kind[order]))
        return w
    if fmt == "hdf5":
        from .hdf5 import Hdf5Writer

        h5 = Hdf5Writer(path, sensor_size, compression, metadata, **kwargs)
        if triggers is not None:
            h5.write_triggers(triggers)
        return h5
    from .arrow import ParquetWriter

    return ParquetWriter(path, sensor_size, compression, metadata, triggers, **kwargs)

