"""Reading an HDF5 recording of any layout: windows by index, streaming, salvage."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Iterator

import numpy as np

from ...errors import EvtkError, FormatError, one_line
from ...events import Events, Triggers
from .._checks import scan_events
from .._overlay import SplicedFile, close_at_exit
from ..base import BaseRecording, Damage, StreamInfo, sensor_dims
from .checks import _CheckedGroup, _Policy
from .common import _H5_ERRORS, READ_CHUNK_CACHE_BYTES, _h5
from .layouts import _EXPECTED, _LAYOUTS, _inventory, _Layout
from .writer import _superblock_eoa


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
        The ``.h5`` / ``.hdf5`` file.
    salvage : bool
        Return the events before the first out-of-order or out-of-sensor
        event instead of raising.
    sensor_size : tuple of (int, int), optional
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

    def __init__(self, path: str | os.PathLike[str], salvage: bool = False,
                 sensor_size: tuple[int, int] | None = None, sort: bool = False,
                 trust_external: bool = False) -> None:
        super().__init__(path, salvage)
        h5py = _h5()
        self._spliced = None
        try:
            self._f = h5py.File(self.path, "r", rdcc_nbytes=READ_CHUNK_CACHE_BYTES)
        except OSError as exc:
            self._f = self._open_truncated(h5py, exc)
        try:
            self._policy = _Policy(self.path, trust_external, self.salvage, os.path.getsize(self.path))
            self._root = _CheckedGroup(self._f, self._policy)
            self._layout = _guard(Hdf5Recording._detect)(self)
            self._clip_unwritten()
            if self._layout.n and self._links_to("reconstruction"):
                self.warnings.append(
                    f"the file also holds a /reconstruction group, left aside: it is read as the recording of its "
                    f"{self._layout.n} events (evtk.load_reconstruction reads the group)")
            if getattr(self._layout, "interrupted", False):
                self._interrupted()
            if getattr(self._layout, "index_problem", None):
                if not self.salvage:
                    raise FormatError(self.path, None, self._layout.index_problem)
                self.warnings.append(self._layout.index_problem + "; reading without it")
            if sensor_size is not None:
                self._layout.sensor_size = sensor_dims(sensor_size[0], sensor_size[1], None, "sensor_size")
            self._sort = bool(sort)
            self._sorted_cache: Events | None = None
            self._intact = None
            self._checked = False
            if self._layout.sensor_size is None:
                _guard(Hdf5Recording._infer_sensor_size)(self)
            elif self._layout.short_size and sensor_size is None:
                _guard(Hdf5Recording._fit_sensor_size)(self)
        except BaseException:
            self._f.close()
            raise

    @_guard
    def _links_to(self, name: str) -> bool:
        """Whether the file has a link named ``name`` (damaged metadata: a FormatError, not h5py's error)."""
        return self._f.get(name, getlink=True) is not None

    @_guard
    def holds_group(self, name: str) -> bool:
        """Whether the file holds the group ``name`` (reached by the file's policy: a link out of the file
        that is not trusted is a :class:`~evtk.FormatError`).

        Parameters
        ----------
        name : str
            Path of the group in the file.

        Returns
        -------
        bool
            True when ``name`` exists and is a group.
        """
        if self._f.get(name, getlink=True) is None:  # the link alone: nothing followed yet
            return False
        return isinstance(self._root[name], _CheckedGroup)

    @_guard
    def read_arrays(self, group: str, names: Iterable[str],
                    before: Callable[[dict[str, tuple[tuple[int, ...], np.dtype]]], object] | None = None,
                    ) -> dict[str, np.ndarray]:
        """The datasets ``names`` of ``group`` that exist, read whole, each checked by the file's policy first:
        links and storage out of the file unless trusted, virtual datasets, chunk sizes and the data a
        dataset claims against the file's size (``evtk.io.hdf5.checks``).

        Parameters
        ----------
        group : str
            Path of the group.
        names : iterable of str
            The members wanted.
        before : callable, optional
            Called with ``{name: (shape, dtype)}`` of the members found, before any is read (to refuse them,
            or check what they need against the memory budget).

        Returns
        -------
        dict
            Name to NumPy array, for the members present.

        Raises
        ------
        FormatError
            When ``group`` is not a group, a member is not a dataset, or the policy refuses one.
        """
        h5py = _h5()
        if not self.holds_group(group):
            raise FormatError(self.path, None, f"no /{group} group")
        g = self._root[group]
        found = {}
        for name in names:
            if g.get(name, getlink=True) is None:
                continue
            ds = g[name]
            if not isinstance(getattr(ds, "_ds", ds), h5py.Dataset):
                raise FormatError(self.path, None, f"/{group}/{name} is not a dataset")
            found[name] = ds
        if before is not None:
            before({k: (ds.shape, ds.dtype) for k, ds in found.items()})
        return {k: np.asarray(ds[()]) for k, ds in found.items()}

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
            f = h5py.File(spliced, "r", rdcc_nbytes=READ_CHUNK_CACHE_BYTES)
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
            t, x, y, p = (c[:good] for c in out)
            return Events._trusted(t, x, y, p, self.sensor_size)
        try:
            ev = Events(cols[0], cols[1], cols[2], cols[3], self.sensor_size)
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
            ev = Events(best[0], best[1], best[2], best[3], self.sensor_size)
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
    def events(self, t_start_us: int | None = None, t_end_us: int | None = None) -> Events:
        """Events with ``t_start_us <= t < t_end_us``; reads only the blocks the window needs.

        The window is found through the layout's time index where it has one (evtk's, DSEC's ``ms_to_idx``),
        else by bisecting the stored time stamps; with ``sort`` the whole file is read and sorted once.

        Parameters
        ----------
        t_start_us : int, optional
            First time kept (µs, inclusive); None: from the start.
        t_end_us : int, optional
            End of the window (µs, exclusive); None: to the end.

        Returns
        -------
        Events
            The events, in file order (time order with ``sort``).

        Raises
        ------
        FormatError
            When time goes backwards (without ``sort``), an event lies off the sensor, or a dataset is damaged
            or refused by the file's policy, without salvage.
        EvtkError
            When the events would not fit the memory budget.
        """
        self._check_open()
        if self._sort:
            return self._all_sorted().between(t_start_us, t_end_us)
        if self.salvage and (t_start_us is not None or t_end_us is not None):
            return self._salvaged_window(t_start_us, t_end_us)
        i0, i1, before = self._span(t_start_us, t_end_us)
        ev = self._load(i0, i1, before)
        if self.damage is not None and (t_start_us is not None or t_end_us is not None):
            ev = ev.between(t_start_us, t_end_us)
        return ev

    @_guard_gen
    def iter_events(self, chunk_events: int = 1_000_000, t_start_us: int | None = None,
                    t_end_us: int | None = None) -> Iterator[Events]:
        """Yield events in order, ``chunk_events`` at a time (memory bounded by the chunk).

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
            The next chunk; together, what :meth:`events` returns.

        Raises
        ------
        FormatError
            At damage, without salvage (with it, the chunks end there).
        EvtkError
            When ``chunk_events`` is below 1.
        """
        self._check_open()
        chunk_events = int(chunk_events)
        if chunk_events < 1:
            raise EvtkError(f"chunk_events must be at least 1, got {chunk_events}")
        if self._sort or (self.salvage and (t_start_us is not None or t_end_us is not None)):
            ev = (self._all_sorted().between(t_start_us, t_end_us) if self._sort
                  else self._salvaged_window(t_start_us, t_end_us))
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
    def triggers(self, t_start_us: int | None = None, t_end_us: int | None = None) -> Triggers:
        """The trigger edges with ``t_start_us <= t < t_end_us``.

        As the file's layout keeps them: evtk's ``/triggers`` group, Prophesee's ``/EXT_TRIGGER/events``
(polarity 1 a rising edge, 0 a falling one); the other layouts hold none (empty).

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
        """A dataset stored beside the events (for example reconstructed responses), read whole.

        Parameters
        ----------
        name : str
            Its path in the file.

        Returns
        -------
        numpy.ndarray
            Its values, checked by the file's policy first (links, storage and sizes).

        Raises
        ------
        EvtkError
            When there is no such dataset.
        FormatError
            When the policy refuses it or it cannot be read.
        """
        self._check_open()
        if name not in self._f:
            raise EvtkError(f"{self.path}: no dataset {name!r}")
        return self._root[name][...]
