"""Convert a recording to another file (format from the target's extension), keeping what the target can hold."""

from __future__ import annotations

import itertools
import os
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any, cast

from .._atomic import refuse_overwriting_inputs
from ..errors import EvtkError
from ..events import Events, Triggers
from . import LOSES, open_writer, write_format
from . import open as open_recording
from ._checks import sorted_for_writing

if TYPE_CHECKING:
    from .aedat4 import Aedat4Writer, Recording

__all__ = ["convert"]

# targets that hold trigger edges but not their channels (all read back as channel 0)
_NO_CHANNELS = {"aedat4"}
# attributes the AEDAT4 writer sets itself for every stream
_OWN_KEYS = {"compression", "originalModuleName", "originalOutputName", "typeDescription", "typeIdentifier"}


def convert(source: str | os.PathLike[str], target: str | os.PathLike[str], compression: str = "lz4",
            salvage: bool = False, sort: bool = False, chunk_events: int = 4_000_000, events_only: bool = False,
            fmt: str | None = None, time_from_zero: bool = False) -> dict[str, Any]:
    """Write the recording ``source`` to ``target``, streaming the events ``chunk_events`` at a time.

    AEDAT4 to AEDAT4 also copies the other streams (frames, IMU, ...) packet
    by packet and keeps the camera's name (the ``source`` attribute). A target
    that cannot hold them gets the events, the triggers and the metadata (with
    the camera's name as ``source``), and the result's ``left_out`` names what
    was not copied, unless ``events_only`` asks for exactly that.

    Prophesee RAW (EVT 2.0 and 3.0), HDF5 and Parquet keep trigger edges
    with their channels; AEDAT4 keeps the edges but not their channels (those
    lost are listed in ``channels_lost``); DAT, Event Stream and CSV hold no
    triggers, so they are left out and named in ``left_out``. ``fmt`` names
    the target's format where the extension does not (``.raw`` is EVT 3.0
    unless ``fmt="evt2"``).

    Parameters
    ----------
    source : str or os.PathLike
        A recording in any format :func:`evtk.io.open` reads.
    target : str or os.PathLike
        The file to write; it appears only once complete, and may not be the source (by any name).
    compression : str
        AEDAT4, HDF5 and Parquet targets: the codec.
    salvage : bool
        Convert what is intact before damage in the source instead of raising at it.
    sort : bool
        Read all events and sort them by time (stably) first, in memory, for a source out of order.
    chunk_events : int
        Events read and written at a time, without ``sort``.
    events_only : bool
        AEDAT4 to AEDAT4: copy only the events and triggers, not the other streams.
    fmt : str, optional
        One of :data:`evtk.io.WRITE_FORMATS`, overriding the target's extension.
    time_from_zero : bool
        Subtract the earliest time of the events and triggers from every time, and keep it as the metadata
        key ``time_offset_us``: for the formats whose time counts from 0 in a counter that wraps (EVT 3.0, DAT),
        which cannot hold time stamps in Unix microseconds (DV's) at the start of a file. Not with the other
        streams of an AEDAT4 target (their packets are copied as they are): add ``events_only``.

    Returns
    -------
    dict
        ``events``, ``triggers`` (written), ``copied`` (stream name -> packets copied), ``left_out``
        (stream name -> packets; ``"trigger edges"`` -> count; ``"metadata keys"`` -> count),
        ``channels_lost`` (the non-zero trigger channels the target cannot hold, in increasing order;
        empty when none) and ``time_offset_us`` (what ``time_from_zero`` subtracted; 0 without it).

    Raises
    ------
    EvtkError
        When the target's format is unknown, the target is the source, or the events do not fit the target's
        format (time going backwards for a format that needs order, without ``sort``).
    FormatError
        Damage in the source, without ``salvage``.
    """

    fmt = write_format(target, fmt)
    refuse_overwriting_inputs(target, [source])
    with open_recording(source, salvage=salvage) as rec:
        streams = rec.streams
        triggers = rec.triggers() if any(s.type == "TRIG" for s in streams) else None
        others = [] if events_only else list(getattr(rec, "other_streams", lambda: [])())
        main = next((s for s in streams if s.type == "EVTS"), None)
        camera = (main.attributes.get("source") if main is not None else None) or None
        if camera == "evtk":  # evtk's own name as a writer, not a camera's
            camera = None
        metadata = dict(rec.metadata or {})
        copied, left_out = {}, {}
        chunks: Iterator[Events] = iter([sorted_for_writing(rec.events(), True, fmt)]) if sort else \
            rec.iter_events(chunk_events=chunk_events)
        offset = 0
        if time_from_zero:
            if fmt == "aedat4" and others:
                raise EvtkError(f"--time-from-zero shifts the events and triggers, not the packets of {source}'s "
                                "other streams: add --events-only to leave those out")
            first = next(chunks, None)
            starts = [int(c.t.min()) for c in (first, triggers) if c is not None and len(c)]
            offset = min(starts, default=0)
            chunks = itertools.chain([] if first is None else [first], chunks)
            chunks = (Events._trusted(c.t - offset, c.x, c.y, c.p, c.sensor_size) for c in chunks)
            if triggers is not None:
                triggers = Triggers(triggers.t - offset, triggers.kind, triggers.channel)
            metadata["time_offset_us"] = str(offset)
        channels_lost = []
        if triggers is not None and fmt in _NO_CHANNELS:
            channels_lost = [c for c in triggers.channels if c != 0]
        if fmt == "aedat4":  # the camera's name and the other streams go along
            extra = [(s.name, s.type, {k: v for k, v in s.attributes.items() if k not in _OWN_KEYS}) for s in others]
            writer = open_writer(target, rec.sensor_size, compression, metadata or None, triggers,
                                 source=str(camera or "evtk"), extra_streams=extra)
        else:
            if camera:
                metadata.setdefault("source", str(camera))
            left_out = {s.name: s.packets for s in others}
            others = []
            if triggers is not None and len(triggers) and "trigger" in (LOSES[fmt] or ""):
                left_out["trigger edges"] = len(triggers)
                triggers = None
                channels_lost = []  # the edges themselves are named as left out
            if metadata and "metadata" in (LOSES[fmt] or "") and fmt in ("es", "csv"):
                left_out["metadata keys"] = len(metadata)
            writer = open_writer(target, rec.sensor_size, compression, metadata or None, triggers, fmt=fmt)
        n = 0
        with writer:
            for chunk in chunks:  # (with sort: all events, read and sorted by time in memory)
                writer.write_events(chunk)
                n += len(chunk)
            for s in others:
                k = 0
                aedat_writer = cast("Aedat4Writer", writer)  # (AEDAT4 to AEDAT4 only)
                for body, count, t0, t1 in cast("Recording", rec).packets(s.id):
                    aedat_writer.write_packet(s.name, body, count, t0 if t0 is not None else 0, t1 if t1 is not None else 0)
                    k += 1
                copied[s.name] = k
    return {"events": n, "triggers": 0 if triggers is None else len(triggers), "copied": copied,
            "left_out": left_out, "channels_lost": channels_lost, "time_offset_us": offset}
