"""The HDF5 layouts evtk reads: its own, DSEC, Prophesee and event_utils, recognised by structure."""

from __future__ import annotations

import numpy as np

from ...errors import EvtkError, FormatError, one_line
from ...events import Triggers
from ..base import load_json, sensor_dims
from .checks import _T_MAX, _as_us, _check_int, _check_lengths, _describe_filters, _fixed_text, _need, _seconds_as_us
from .common import EVTK_FORMAT, INTERRUPTED


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

    def read(self, i0, i1) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover
        raise NotImplementedError

    def triggers(self) -> Triggers:
        return Triggers()

    def compression(self):
        return None


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
        channel = None  # no dataset (files of channel 0 only, and those written before channels were kept)
        if "channel" in self.f["triggers"]:
            c = self.f["triggers/channel"]
            if c.shape != t.shape:
                raise FormatError(self.path, None, "datasets /triggers/t and /triggers/channel differ in length")
            channel = c[...]
        try:
            return Triggers(t[...], k[...], channel)
        except EvtkError as exc:
            raise FormatError(self.path, None, f"the triggers cannot be read: {exc}") from None

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


#: Records of Prophesee's /CD/events a read copies into columns at a time (4-4.5 MiB of records).
RECORD_BLOCK = 1 << 18


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
        """Events ``i0..i1`` as contiguous columns, copied out of the records :data:`RECORD_BLOCK` at a time (the
        fields of one read of the records are strided views that would keep every record, 14-16 bytes an event,
        alive in what is returned): t as int64 microseconds, x and y in their fields' types, and p as uint8 when
        every value is 0 or 1 (else in its field's type, for the events' check to name)."""
        i1 = min(i1, self.ds.shape[0])
        i0 = min(i0, i1)
        dt = self.ds.dtype
        t = np.empty(i1 - i0, np.int64)
        x, y = (np.empty(i1 - i0, dt[name]) for name in ("x", "y"))
        p_ok = dt["p"].kind in "iub"
        p = np.empty(i1 - i0, np.uint8 if p_ok else dt["p"])
        for a in range(i0, i1, RECORD_BLOCK):
            b = min(i1, a + RECORD_BLOCK)
            rec = self.ds[a:b]
            t[a - i0:b - i0] = _as_us(rec["t"], self.path, self.ds.name + "/t")
            x[a - i0:b - i0], y[a - i0:b - i0] = rec["x"], rec["y"]
            pb = rec["p"]
            if p_ok and len(pb) and (pb.min() < 0 or pb.max() > 1):
                p_ok = False
                p = self.ds.fields("p")[i0:i1]  # as stored: the events' check names the values
            if p_ok:
                p[a - i0:b - i0] = pb
        return t, x, y, p

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


