"""Apache Arrow tables and Parquet files of events.

Columns ``t`` (int64 µs), ``x``, ``y`` (uint16) and ``p`` (uint8); the sensor
size, evtk metadata and triggers travel in the schema's key-value metadata
(``docs/formats/parquet.md``).  Parquet files are cut into row groups by time, so
a window reads only the row groups whose ``t`` statistics overlap it.
"""

from __future__ import annotations

import os
import select
import signal
import time
from collections.abc import Iterator, Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from .._atomic import AtomicFile
from .._table import KEY_META, KEY_TRIGGERS, arrow_column, columns_to_table, events_schema, numpy_of, pyarrow_module, sensor_from
from ..errors import EvtkError, FormatError, one_line
from ..events import Events, Triggers
from ..limits import require_memory
from . import _parquet_footer as _footer
from ._checks import require_readable, scan_events, sorted_for_writing
from ._overlay import SplicedFile, close_at_exit
from .base import (
    BaseRecording,
    BaseWriter,
    Damage,
    StreamInfo,
    _event_columns,
    _put_events,
    load_json,
    sensor_dims,
    time_chunks,
    window_blocks,
)

if TYPE_CHECKING:
    import pyarrow as pa

__all__ = ["to_arrow", "from_arrow", "ParquetRecording", "write_parquet", "COMPRESSIONS"]

COMPRESSIONS = {"lz4": "lz4", "lz4_high": "lz4", "zstd": "zstd", "zstd_high": "zstd", "gzip": "gzip", "none": "none"}
ROW_GROUP_EVENTS = 1 << 16
ROW_GROUP_US = 50_000
#: A whole read gives Arrow's freed memory back to the system after each this many events (``release_unused``
#: takes about a millisecond, so not after every row group).
RELEASE_EVENTS = 1 << 19


PROBE_SECONDS = 10.0


def _first_fatal_row_group(pf, t_col):
    """Index of the first row group whose footer entry makes pyarrow abort the process.

    Some damaged footers make pyarrow throw a C++ exception nothing catches
    (for example a size-statistics histogram of the wrong length), which
    aborts the interpreter as soon as the row group's metadata is touched.
    A forked child touches each row group's metadata as the reader will,
    writing the index it is about to touch to a pipe; if the child dies of a
    signal, the last index is the culprit. Returns ``num_row_groups`` when
    all are safe, None when this cannot be checked (no ``fork``, or the
    child did not finish in time).
    """
    n = pf.metadata.num_row_groups
    if not hasattr(os, "fork") or n == 0:
        return None
    r, w = os.pipe()
    import warnings

    with warnings.catch_warnings():  # Python 3.12+ warns about fork with threads; the child only reads
        warnings.simplefilter("ignore", DeprecationWarning)
        pid = os.fork()
    if pid == 0:  # child: touch everything the reader touches, then leave without cleanup
        code = 0
        try:
            os.close(r)
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, 2)  # pyarrow's last words would reach the user's terminal
            import faulthandler

            faulthandler.disable()  # nor should a traceback dump of the expected abort
            md = pf.metadata
            expected = [md.schema.column(j).physical_type for j in range(md.num_columns)]
            for g in range(n):
                os.write(w, g.to_bytes(4, "little"))
                rg = md.row_group(g)
                cols = [rg.column(j) for j in range(rg.num_columns)]
                if [c.physical_type for c in cols] != expected:
                    break  # the reader stops here with an error of its own
                _ = cols[t_col].statistics  # reading them is the check
                str(cols[t_col].compression)
            os.write(w, b"DONE")
        except BaseException:  # noqa: BLE001 - a Python error is the reader's to report
            code = 1
        finally:
            os._exit(code)
    os.close(w)
    data = b""
    deadline = time.monotonic() + PROBE_SECONDS
    try:
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                os.kill(pid, signal.SIGKILL)
                os.waitpid(pid, 0)
                return None
            ready, _, _ = select.select([r], [], [], left)
            if ready:
                chunk = os.read(r, 4096)
                if not chunk:
                    break
                data += chunk
    finally:
        os.close(r)
    _, status = os.waitpid(pid, 0)
    if os.WIFSIGNALED(status) and not data.endswith(b"DONE") and len(data) >= 4:
        return int.from_bytes(data[-4:], "little")
    return n


def _unreadable(g, exc):
    """What to say of a row group pyarrow could not read (its message on one line)."""
    return f"row group {g} cannot be read ({one_line(exc)})"


def to_arrow(events: Events, metadata: Mapping[str, Any] | None = None,
             triggers: Triggers | None = None) -> pa.Table:
    """A ``pyarrow.Table`` sharing the event columns (no copy); :meth:`evtk.Events.to_arrow`.

    Parameters
    ----------
    events : Events
        The events.
    metadata : Mapping of str to object, optional
        Stored as JSON in the schema metadata (``evtk.metadata``).
    triggers : Triggers, optional
        Stored as JSON in the schema metadata (``evtk.triggers``).

    Returns
    -------
    pyarrow.Table
        Columns ``t`` (int64, µs), ``x``, ``y`` (uint16), ``p`` (uint8); the sensor size in the schema metadata.

    Raises
    ------
    EvtkError
        When ``metadata`` is not JSON-serialisable.
    """
    return columns_to_table(events.t, events.x, events.y, events.p, events.sensor_size, metadata, triggers)


def from_arrow(table: pa.Table, sensor_size: Sequence[int] | None = None) -> Events:
    """Events from a ``pyarrow.Table`` (or anything with columns t, x, y, p); :meth:`evtk.Events.from_arrow`.

    Parameters
    ----------
    table : pyarrow.Table
        Integer columns t, x, y, p without nulls.
    sensor_size : sequence of two int, optional
        ``(width, height)``; default: the table's ``evtk.sensor_size`` metadata.

    Returns
    -------
    Events
        The events, checked as :class:`evtk.Events` checks them.

    Raises
    ------
    EvtkError
        When there is no sensor size, or the columns are missing or do not fit.
    """
    return Events.from_arrow(table, sensor_size)


# =============================================================================
# Parquet
# =============================================================================


class ParquetRecording(BaseRecording):
    """A Parquet file of events; windows skip row groups by their ``t`` statistics.

    Parameters
    ----------
    path : str or os.PathLike
        The file.
    salvage : bool
        Return the complete row groups before the first damage instead of raising.
    sensor_size : tuple of (int, int), optional
        ``(width, height)`` in pixels, for files that do not record it (evtk's own record it).
    verify_checksums : bool
        Check the CRC-32 of every data page that carries one (pyarrow writes them with
        ``write_page_checksum=True``); a page that fails is a :class:`~evtk.FormatError`.
    """

    format = "parquet"

    def __init__(self, path: str | os.PathLike[str], salvage: bool = False, sensor_size: tuple[int, int] | None = None,
                 verify_checksums: bool = True) -> None:
        super().__init__(path, salvage)
        import pyarrow.parquet as pq

        self._overlay = None
        self._verify = bool(verify_checksums)
        try:
            self._pf = pq.ParquetFile(self.path, page_checksum_verification=self._verify)
        except Exception as exc:  # pyarrow raises ArrowInvalid / OSError subclasses
            self._pf = self._without_footer(pq, exc)
        schema = self._pf.schema_arrow
        missing = [c for c in ("t", "x", "y", "p") if c not in schema.names]
        if missing:
            raise FormatError(self.path, None, f"columns {missing} missing; found {schema.names}; expected t, x, y, p")
        for name in ("t", "x", "y", "p"):
            typ = schema.field(name).type
            if not (str(typ).startswith(("int", "uint")) or str(typ) == "bool"):
                raise FormatError(self.path, None, f"column {name!r} has type {typ}, expected an integer type")
        meta = schema.metadata or {}
        self._sensor = (sensor_dims(sensor_size[0], sensor_size[1], None, "sensor_size") if sensor_size
                        else sensor_from(meta, self.path))
        self._meta = {}
        if KEY_META in meta:
            self._meta = load_json(meta[KEY_META], self.path, "schema metadata evtk.metadata")
        self._triggers = Triggers()
        if KEY_TRIGGERS in meta:
            d = load_json(meta[KEY_TRIGGERS], self.path, "schema metadata evtk.triggers")
            try:
                self._triggers = Triggers(d["t"], d["kind"], d.get("channel"))
            except (ValueError, KeyError, TypeError, AttributeError, EvtkError):
                raise FormatError(self.path, None, "schema metadata evtk.triggers is malformed") from None
        self._t_col = schema.names.index("t")
        md = self._pf.metadata
        self._groups: list[tuple[int, int | None, int | None]] = []  # (rows, t_min, t_max); None: no statistics
        expected = [md.schema.column(j).physical_type for j in range(md.num_columns)]
        fatal = _first_fatal_row_group(self._pf, self._t_col)
        for g in range(md.num_row_groups):
            if fatal is not None and g >= fatal:
                problem = f"row group {g} of the footer is damaged: pyarrow cannot parse its metadata"
                if not self.salvage:
                    raise FormatError(self.path, None, problem)
                self.damage = Damage(None, problem)
                break
            rg = md.row_group(g)
            # a damaged footer can give a column chunk a type its schema column does not have;
            # pyarrow then aborts the process (an uncaught C++ exception) on its statistics
            # or data, so check before touching them
            found = [rg.column(j).physical_type for j in range(rg.num_columns)]
            damaged: str | None = None
            values = [rg.column(j).num_values for j in range(rg.num_columns)] if found == expected else []
            if found != expected:
                damaged = (f"row group {g} of the footer is damaged: column chunk types {found} "
                           f"do not match the schema's {expected}")
            elif any(v != rg.num_rows for v in values):  # the event columns have no nulls: one value a row
                damaged = (f"row group {g} of the footer is damaged: it counts {rg.num_rows} rows but its columns "
                           f"hold {values} values")
            if damaged is not None:
                if not self.salvage:
                    raise FormatError(self.path, None, damaged)
                self.damage = Damage(None, damaged)
                break
            st = rg.column(self._t_col).statistics
            if st is not None and st.has_min_max:
                self._groups.append((rg.num_rows, int(st.min), int(st.max)))
            else:
                self._groups.append((rg.num_rows, None, None))
        if self._sensor is None:
            self._infer_sensor_size()

    def _without_footer(self, pq, exc):
        """Open a file whose footer is missing or unreadable by writing a new one for its complete row groups
        (salvage only): what an interrupted writer leaves."""
        problem = f"not a readable Parquet file ({one_line(exc)})"
        try:
            with open(self.path, "rb") as f:
                head = f.read(4)
                size = f.seek(0, os.SEEK_END)
                f.seek(max(0, size - 4))
                tail = f.read(4)
        except OSError:
            head = tail = b""
            size = 0
        if head == b"PAR1" and (tail != b"PAR1" or size < 12):
            problem = ("the file ends without a Parquet footer: its writer did not finish (interrupted?); "
                       "salvage recovers its complete row groups")
        if not self.salvage or head != b"PAR1":
            raise FormatError(self.path, None, problem)
        cause = problem.split(";")[0]
        try:
            end, found, codec = _footer.find_row_groups(self.path)
        except (_footer.ThriftError, OSError) as err:
            raise FormatError(self.path, None, f"{cause}, and no row group can be recovered ({one_line(err)})") from None
        rows, groups = sum(r for r, _ in found), len(found)
        last = None
        for repetition in (_footer.OPTIONAL, _footer.REQUIRED):  # nullable columns (pyarrow's default) first
            try:
                overlay = SplicedFile(self.path, end, _footer.encode_footer(found, codec, repetition))
                try:
                    pf = pq.ParquetFile(overlay, page_checksum_verification=self._verify)
                    if groups:  # does the guessed repetition decode?
                        pf.read_row_group(0, columns=["t"])
                except BaseException:
                    overlay.close()
                    raise
            except Exception as err:  # noqa: BLE001 - pyarrow refusing the guessed repetition
                last = err
                continue
            self._overlay = overlay
            close_at_exit(self)
            self.damage = Damage(end, f"{cause}: recovered {rows} events in {groups} complete "
                                      "row group(s) by rebuilding the footer; the sensor size, metadata and "
                                      "triggers the footer held are lost")
            return pf
        raise FormatError(self.path, None, f"{cause}, and its row groups do not decode under a rebuilt footer "
                                           f"({one_line(last)})")

    def _close(self):
        try:
            self._pf.close()
        except AttributeError:  # pragma: no cover - older pyarrow
            pass
        if self._overlay is not None:
            self._overlay.close()

    def _infer_sensor_size(self):
        """The sensor size from the largest coordinates; with salvage, of the row groups before a damaged one."""
        w = h = 1
        for g in range(len(self._groups)):
            try:
                tab = self._pf.read_row_group(g, columns=["x", "y"])
                if tab.num_rows:
                    w = max(w, int(np.max(numpy_of(tab.column("x")))) + 1)
                    h = max(h, int(np.max(numpy_of(tab.column("y")))) + 1)
            except Exception as exc:  # pyarrow raises OSError, ArrowInvalid, ... on damaged pages
                problem = _unreadable(g, exc)
                if not self.salvage:
                    raise FormatError(self.path, None, problem) from None
                if self.damage is None:
                    self.damage = Damage(None, problem)
                break
        self._sensor = (w, h)
        self.warnings.append(f"the file does not record its sensor size; inferred {self._sensor} from the coordinates")

    @property
    def sensor_size(self):
        return self._sensor

    @property
    def metadata(self):
        return self._meta

    @property
    def compression(self):
        md = self._pf.metadata
        if md.num_row_groups == 0 or not self._groups:
            return None
        return str(md.row_group(0).column(self._t_col).compression).lower()

    def _rows(self, t_start_us, t_end_us):
        """The row groups a window needs: by their ``t`` statistics, checked at the edges against the stamps
        (:func:`~evtk.io.base.window_blocks`); every row group when the statistics are missing or lie."""
        every = list(range(len(self._groups)))
        if t_start_us is None and t_end_us is None:
            return every
        span = window_blocks([lo for _, lo, _ in self._groups], [hi for _, _, hi in self._groups],
                             t_start_us, t_end_us, self._group_span)
        if span is None:
            if any(lo is not None for _, lo, _ in self._groups):
                self._warn_once("the row groups' t statistics disagree with their time stamps or are out of order; "
                                "windows read every row group", "statistics")
            return every
        return every[span[0]:span[1]]

    def _group_span(self, g):
        """(first, last) time stamp of row group ``g``, or None when it is empty or unreadable."""
        try:
            t = numpy_of(self._pf.read_row_group(g, columns=["t"]).column(0))
        except Exception:  # noqa: BLE001 - pyarrow's errors on a damaged group; the full read reports it
            return None
        return (int(t[0]), int(t[-1])) if len(t) else None

    def _read_group(self, g, t_before, use_threads=True):
        """``(events, problem)`` of row group ``g``: its four columns decoded together on pyarrow's threads, or
        one after the other on this thread (less in flight: a column's decoding buffers are freed before the next
        column decodes)."""
        names = ("t", "x", "y", "p")
        try:
            if use_threads:
                table = self._pf.read_row_group(g, columns=list(names))
                tables = [table] * len(names)
            else:
                tables = [self._pf.read_row_group(g, columns=[name], use_threads=False) for name in names]
        except Exception as exc:
            return None, _unreadable(g, exc)
        cols = [arrow_column(tab, name, self.path) for tab, name in zip(tables, names)]
        del tables
        try:
            ev = Events(*cols, self._sensor)
        except EvtkError as exc:
            return None, f"row group {g} holds invalid values: {exc}"
        back, outside = scan_events(ev.t, ev.x, ev.y, self._sensor, t_before)
        first = min(i for i in (back, outside, len(ev)) if i >= 0)
        if first < len(ev):
            what = "time stamps go backwards" if first == back else f"an event lies outside the {self._sensor} sensor"
            start = sum(r for r, _, _ in self._groups[:g])
            return ev[:first], f"{what} at event index {start + first}"
        return ev, None

    def _groups_events(self, t_start_us, t_end_us, use_threads=True):
        before = None
        for g in self._rows(t_start_us, t_end_us):
            ev, problem = self._read_group(g, before, use_threads)
            if problem:
                if not self.salvage:
                    raise FormatError(self.path, None, problem)
                if self.damage is None:
                    self.damage = Damage(None, problem)
                if ev is not None and len(ev):
                    yield ev.between(t_start_us, t_end_us)
                return
            if len(ev):
                before = int(ev.t[-1])
                yield ev.between(t_start_us, t_end_us)

    def events(self, t_start_us: int | None = None, t_end_us: int | None = None) -> Events:
        """The events with ``t_start_us <= t < t_end_us``, read at once.

        Only the row groups whose ``t`` statistics overlap the window are read, together, on pyarrow's
        threads; with salvage, a window is cut from what the whole read recovers.

        Parameters
        ----------
        t_start_us : int, optional
            First time kept (µs, inclusive); None: from the start.
        t_end_us : int, optional
            End of the window (µs, exclusive); None: to the end.

        Returns
        -------
        Events
            The events, in file order.

        Raises
        ------
        FormatError
            At a damaged or unreadable row group, a failed page checksum, time going backwards or an event off
            the sensor, without salvage.
        """
        self._check_open()
        if self.salvage and (t_start_us is not None or t_end_us is not None):
            return self._salvaged_window(t_start_us, t_end_us)
        # a row group at a time into one set of columns sized by the groups' row counts: the peak is the events
        # plus one group (reading every group into one table and copying it out held the events twice). A group
        # decodes a column at a time on this thread (pyarrow's threads gain little on groups this size, and each
        # keeps freed pages of its own), and what Arrow's allocator has freed goes back to the system every
        # RELEASE_EVENTS events: mimalloc keeps freed pages for a second, in 2 MiB huge pages where the system
        # allows them, which held 15-20 MiB more than the events at the end of a 10 M-event read (1.17x them)
        declared = sum(max(0, self._groups[g][0]) for g in self._rows(t_start_us, t_end_us))
        # the columns, and the Arrow buffers of the row groups decoded since the last release (13 bytes an event each)
        require_memory(13 * (declared + min(declared, RELEASE_EVENTS)), "the events of the Parquet file")
        cols = _event_columns(declared)
        n = 0
        pool, held = pyarrow_module().default_memory_pool(), 0
        for ev in self._groups_events(t_start_us, t_end_us, use_threads=False):
            cols, n = _put_events(cols, n, ev)  # (a group holding more rows than the footer says: grown)
            held += len(ev)
            if held >= RELEASE_EVENTS:
                del ev
                pool.release_unused()
                held = 0
        t, x, y, p = (c[:n] for c in cols)
        return Events._trusted(t, x, y, p, self._sensor)

    def iter_events(self, chunk_events: int = 1_000_000, t_start_us: int | None = None,
                    t_end_us: int | None = None) -> Iterator[Events]:
        """The events with ``t_start_us <= t < t_end_us``, at most ``chunk_events`` at a time.

        One row group is read at a time (cut into chunks); a window skips row groups by their ``t``
        statistics.

        Parameters
        ----------
        chunk_events : int
            Most events a chunk holds (at least 1).
        t_start_us : int, optional
            First time kept (µs, inclusive); None: from the start.
        t_end_us : int, optional
            End of the window (µs, exclusive); None: to the end.

        Yields
        ------
        Events
            The next chunk, in file order; together, what ``events`` returns.

        Raises
        ------
        FormatError
            At damage, without salvage (with it, the chunks end there).
        """
        self._check_open()
        chunk_events = int(chunk_events)
        if chunk_events < 1:
            raise EvtkError(f"chunk_events must be at least 1, got {chunk_events}")
        windowed = t_start_us is not None or t_end_us is not None
        parts = [self._salvaged_window(t_start_us, t_end_us)] if self.salvage and windowed else \
            self._groups_events(t_start_us, t_end_us)
        for ev in parts:
            for i in range(0, len(ev), chunk_events):
                yield ev[i : i + chunk_events]

    def triggers(self, t_start_us: int | None = None, t_end_us: int | None = None) -> Triggers:
        """The trigger edges with ``t_start_us <= t < t_end_us``.

        Parquet keeps them in the schema metadata (``evtk.triggers``), read when the file was opened.

        Parameters
        ----------
        t_start_us : int, optional
            First time kept (µs, inclusive); None: from the start.
        t_end_us : int, optional
            End of the window (µs, exclusive); None: to the end.

        Returns
        -------
        Triggers
            Their times (µs), kinds and channels, in file order.
        """
        return self._triggers.between(t_start_us, t_end_us)

    @property
    def streams(self):
        known = [(lo, hi) for _, lo, hi in self._groups if lo is not None]
        first = min(lo for lo, _ in known) if known else None
        last = max(hi for _, hi in known) if known else None
        out = [StreamInfo(0, "events", "EVTS", packets=len(self._groups), count=sum(r for r, _, _ in self._groups),
                          t_start_us=first, t_end_us=last, sensor_size=self._sensor)]
        tr = self._triggers
        if len(tr):
            out.append(StreamInfo(1, "triggers", "TRIG", count=len(tr), t_start_us=int(tr.t.min()), t_end_us=int(tr.t.max())))
        return out

    def _extra_info(self):
        return {"row_groups": len(self._groups)}


class ParquetWriter(BaseWriter):
    """Stream events into a Parquet file (atomically), row groups cut by time.

    Triggers and metadata go in the schema, so they are given up front.
    """

    def __init__(self, path, sensor_size, compression="lz4", metadata=None, triggers=None,
                 row_group_events=ROW_GROUP_EVENTS, row_group_us=ROW_GROUP_US):
        import pyarrow.parquet as pq

        codec = COMPRESSIONS.get(str(compression).lower())
        if codec is None:
            raise EvtkError(f"unknown Parquet compression {compression!r}; choose one of {sorted(COMPRESSIONS)}")
        self.sensor_size = (int(sensor_size[0]), int(sensor_size[1]))
        self.events_schema = events_schema(self.sensor_size, metadata, triggers)
        self._rg_events, self._rg_us = int(row_group_events), row_group_us
        self._atomic = AtomicFile(path, keep_open=False)
        self.path = self._atomic.path
        self._rows = 0
        self._last_t = None
        try:
            # dictionary pages (pyarrow's default, made explicit) start every column chunk: salvage finds
            # the chunks of a file whose footer was never written by them
            self._w = pq.ParquetWriter(self._atomic.tmp_path, self.events_schema, compression=codec, use_dictionary=True)
        except BaseException:
            self._atomic.discard()
            raise
        self._closed = False

    def write_events(self, events: Events):
        self._check_open()
        if tuple(events.sensor_size) != self.sensor_size:
            raise EvtkError(f"events are for a {events.sensor_size} sensor, the file for {self.sensor_size}")
        require_readable(events, self.sensor_size, self._last_t, self._rows, "Parquet")
        if len(events):
            self._last_t = int(events.t[-1])
        pa = pyarrow_module()
        table = pa.Table.from_arrays(
            [pa.array(events.t), pa.array(events.x), pa.array(events.y), pa.array(events.p)], schema=self.events_schema
        )
        bounds = time_chunks(events.t, self._rg_events, self._rg_us, events.is_sorted)
        for a, b in zip(bounds[:-1], bounds[1:]):
            self._w.write_table(table.slice(int(a), int(b - a)), row_group_size=int(b - a))
        self._rows += len(events)

    # -- finishing (BaseWriter's close and abort) --------------------------------------
    def _finish(self):
        if self._rows == 0:
            self._w.write_table(self.events_schema.empty_table())
        self._w.close()

    def _commit(self):
        self._atomic.commit()

    def _discard(self):
        try:
            self._w.close()
        except Exception:  # a writer that failed may fail again on closing; the file goes either way
            pass
        finally:
            self._atomic.discard()


def write_parquet(path: str | os.PathLike[str], events: Events, triggers: Triggers | None = None,
                  compression: str = "lz4", metadata: Mapping[str, Any] | None = None,
                  row_group_events: int = ROW_GROUP_EVENTS, row_group_us: int | None = ROW_GROUP_US,
                  sort: bool = False) -> None:
    """Write events as Parquet (atomically), one row group per time slice.

    Events out of time order are an error unless ``sort`` (the reader requires them in order).

    Parameters
    ----------
    path : str or os.PathLike
        The target (``.parquet``); it appears only once complete.
    events : Events
        The events, in time order (or any order with ``sort``).
    triggers : Triggers, optional
        Stored in the schema metadata.
    compression : str
        The codec, one of ``COMPRESSIONS`` (``"lz4"``, ``"zstd"``, ``"gzip"``, ``"none"``, ...).
    metadata : Mapping of str to object, optional
        JSON-serialisable; stored in the schema metadata.
    row_group_events : int
        Most events in a row group.
    row_group_us : int or None
        Longest time a row group spans (µs), so a short window reads few of them; None: by count only.
    sort : bool
        Sort the events by time (stably) before writing, instead of refusing them.

    Raises
    ------
    EvtkError
        For an unknown codec, time going backwards (without ``sort``), events off the sensor, or metadata
        that is not JSON-serialisable; no file is left under ``path`` then.
    """
    events = sorted_for_writing(events, sort, "Parquet")
    with ParquetWriter(path, events.sensor_size, compression, metadata, triggers, row_group_events, row_group_us) as w:
        w.write_events(events)
