"""The fuzz campaign's targets: the files evtk reads, their truth, their mutations and their oracles.

Three kinds of target, each built once into a folder (:func:`build`) and
loaded by every worker (``load_*_targets``):

* event files (AEDAT4, evtk and DSEC HDF5, Parquet, legacy AEDAT 1.0/2.0/3.1,
  Prophesee EVT 2.0/EVT 2.1/EVT 3.0/DAT, Event Stream, text events, N-MNIST): the truth is the events
  written, checked at build time against the reader of the unmutated file;
* reconstruction files (``.h5`` and ``.npz`` from ``evtk.save_reconstruction``):
  the truth is every array and the summary;
* settings files (job TOML, ``schedule.json``, ``cal.toml``, the simulation
  record as JSON): the truth is what the unmutated file loads to, and a value
  that changed must still obey the physical rules in :data:`RULES`.

A case is one mutation of one target (byte flips, truncation, a lying 4-byte
field, a duplicated or zeroed span, or a structure-aware change that keeps
the container valid) and one oracle call, which returns an outcome:

``exact``      the read equals the truth;
``altered``    the read differs, as the format allows for the bytes changed
               (a payload without a checksum, a header value), and every read
               path agrees and every value is within its bounds;
``error``      a clean :class:`evtk.EvtkError`;
``wrong``      a read that succeeded with a result the oracle refutes
               (raised as :class:`Wrong`).

The runner (``campaign.py``) adds ``traceback`` (any other exception),
``hang``, ``memory`` and ``crash``.

What a mutation may change, per format (:func:`judge_events`):

* every event read: the full read, five windows, ``iter_events`` in chunks
  and in a window must agree (strict and salvage alike); coordinates outside
  the sensor, or negative stamps from a format whose stamps are unsigned,
  need a warning;
* a cut file reads as a prefix of the events written (or an error), strict
  or salvaged;
* a change inside the text header may change what the header says (sensor
  size, camera), so any consistent read is allowed;
* ``fixed`` formats (AEDAT 1.0/2.0/3.1 polarity events, DAT: one record per
  event, no checksum): ``k`` records changed in place may change, drop or add
  at most ``k`` events -- unless the later stamps moved by whole 32-bit wraps,
  each where the raw stamp steps back by more than half the range (what the
  wrap rule makes of a stamp flipped high); a wrap from a small backward step
  is silently wrong;
* ``text`` (CSV as evtk writes it, ``t x y p`` after a "H W" line): ``k``
  bytes changed in place after the first lines may change, drop or add at
  most one event for each line touched (a changed digit changes that
  event; a changed separator may leave a line that does not parse, a clean
  error), and never the sensor size;
* ``nmnist`` (5-byte records): a record changed in place may change its
  event, or become (or stop being) an overflow marker, which moves every
  later stamp by 2**13 us; every other event keeps its values;
* ``checksummed`` (faery's AEDAT4, LZ4 frames with xxHash32): after the
  header, nothing but the events written or an error;
* ``stateful`` formats (EVT 2.0/2.1/3.0, Event Stream, where a time-high word or
  an overflow code moves every later event): any consistent, bounded read;
* ``container`` formats (evtk's AEDAT4, HDF5, Parquet; no checksum on the
  payload): a byte change may alter events; a structure-aware change that
  touches no event payload (``structured.py``) must read exactly or fail.

Reconstruction files: the arrays and summary as written, or an error; a
value change may load only if the counts stay whole and non-negative, the
responses finite, windows end after they start and the summary's sensor size
and region are sane; links, external storage and sizes must be refused; an
NPZ member is CRC-checked, so a byte change must be an error or nothing.
Settings: the values as written, an error, or values obeying :data:`RULES`
(finite; durations, sizes and rates of the right sign; patterns of -1/0/1;
captures in order; a region inside the sensor; a non-singular matrix).
"""

from __future__ import annotations

import collections
import dataclasses
import io
import json
import math
import os
import re
import struct
import zipfile
from pathlib import Path

import numpy as np

import evtk

HERE = Path(__file__).resolve().parent


class Wrong(AssertionError):
    """A read succeeded and gave a result the oracle refutes (silently wrong)."""


# --------------------------------------------------------------------------------------------------- mutations
BYTE_KINDS = ("bitflip", "truncation", "size_field", "duplicate", "zeroed")


def byte_mutation(data: bytes, rng, lo: int = 0):
    """One byte-level mutation of ``data`` at or after ``lo``: ``(bytes, kind, touched, in_place)``;
    ``touched`` lists the ``[a, b)`` byte ranges changed (for an insertion or a cut, from there to the end)."""
    data = bytearray(data)
    n = len(data)
    lo = min(lo, max(0, n - 1))
    kind = BYTE_KINDS[int(rng.integers(0, len(BYTE_KINDS)))]
    if kind == "bitflip":
        touched = []
        for _ in range(int(rng.integers(1, 8))):
            i = int(rng.integers(lo, n))
            data[i] ^= 1 << int(rng.integers(0, 8))
            touched.append((i, i + 1))
        return bytes(data), kind, touched, True
    if kind == "truncation":
        cut = int(rng.integers(0, n))
        return bytes(data[:cut]), kind, [(cut, n)], False
    if kind == "size_field":
        i = int(rng.integers(lo, max(lo + 1, n - 4)))
        v = int(rng.choice([0, 1, 2**31 - 1, 2**32 - 1, n, 0x7FFF0000]))
        data[i:i + 4] = v.to_bytes(4, "little")
        return bytes(data[:n]), kind, [(i, i + 4)], True
    if kind == "duplicate":
        a = int(rng.integers(lo, n))
        b = min(n, a + int(rng.integers(1, 4096)))
        return bytes(data[:b] + data[a:b] + data[b:]), kind, [(b, n)], False
    a = int(rng.integers(lo, n))
    b = min(n, a + int(rng.integers(1, 512)))
    data[a:b] = bytes(b - a)
    return bytes(data), kind, [(a, b)], True


HOSTILE = [0, -1, -3, 1, 2**31, 2**63, -(2**63), 10**18, 1e308, -1e308, float("inf"), float("-inf"), float("nan"),
           0.5, -0.5, 99.9, 60000, "ab", "", True, [], [[]], [1, 2, 3], {}, None]


def _leaves(obj, path=()):
    """Every (path, value) of a JSON-like tree (lists and dicts), leaves and containers alike."""
    yield path, obj
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _leaves(v, path + (k,))
    elif isinstance(obj, list) and len(obj) <= 64:
        for i, v in enumerate(obj):
            yield from _leaves(v, path + (i,))


def _set(obj, path, value):
    for k in path[:-1]:
        obj = obj[k]
    obj[path[-1]] = value


def value_mutation(doc: dict, rng):
    """A copy of ``doc`` with one value replaced by a hostile one (or a key dropped or added); ``(doc, kind)``."""
    doc = json.loads(json.dumps(doc))
    spots = [p for p, _ in _leaves(doc) if p]
    what = int(rng.integers(0, 10))
    path = spots[int(rng.integers(0, len(spots)))]
    if what == 0 and isinstance(path[-1], str):
        parent = doc
        for k in path[:-1]:
            parent = parent[k]
        del parent[path[-1]]
        return doc, "value/drop"
    if what == 1:
        doc["unknown_" + str(int(rng.integers(0, 100)))] = 1
        return doc, "value/unknown_key"
    v = HOSTILE[int(rng.integers(0, len(HOSTILE)))]
    _set(doc, path, json.loads(json.dumps(v)) if isinstance(v, (list, dict)) else v)
    return doc, "value/" + type(v).__name__


def toml_text(doc: dict) -> str:
    """``doc`` as TOML, hostile values included (inf and nan as TOML writes them; big integers as they are,
    which TOML may refuse)."""

    def val(v):
        if v is None:
            return '"None"'  # TOML has no null: a string where a number belongs
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, float):
            return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf") if math.isinf(v) else repr(v)
        if isinstance(v, int):
            return str(v)
        if isinstance(v, str):
            return json.dumps(v)
        if isinstance(v, list):
            return "[" + ", ".join(val(x) for x in v) + "]"
        if isinstance(v, dict):
            return "{" + ", ".join(f"{json.dumps(k)} = {val(x)}" for k, x in v.items()) + "}"
        raise TypeError(v)

    top = "".join(f"{k} = {val(v)}\n" for k, v in doc.items() if not isinstance(v, dict))
    tables = "".join(f"\n[{k}]\n" + "".join(f"{kk} = {val(vv)}\n" for kk, vv in v.items())
                     for k, v in doc.items() if isinstance(v, dict))
    return top + tables


# --------------------------------------------------------------------------------------------------- event files
@dataclasses.dataclass
class EventTarget:
    """An event file and what its mutations may change.

    ``family``: ``fixed`` (one fixed-size record per event in ``regions``: a flipped record changes that event
    only), ``stateful`` (a word can change every later event: EVT 2.0/3.0, Event Stream), ``checksummed`` (every
    byte after ``data_start`` is covered by a checksum) or ``container`` (AEDAT4, HDF5, Parquet, with their own
    structure-aware mutations).
    """

    name: str
    path: Path
    truth: object  # Events
    family: str
    data_start: int
    regions: list  # [(start, end, record_bytes)]: event records, in file order
    unsigned_t: bool
    structured: str | None = None  # "aedat4", "hdf5", "parquet", or a word layout for the legacy formats


def _windows(truth):
    t = truth.t
    if not len(t):
        return [(0, 10)]
    a, b = int(t.min()), int(t.max())
    q = [a + (b - a) * k // 7 for k in range(8)]
    return [(q[1], q[3]), (q[2], q[2] + 1), (q[5], b + 1), (a - 5, a + 1), (b, b + 10**12)]


def read_every_way(path, salvage=False):
    """(events, triggers, warnings, info) after reading ``path`` in full, in windows and in chunks, with a
    :class:`Wrong` if the read paths disagree; where evtk's compiled kernels were built, the full read is taken
    again on the numpy route (``EVTK_NATIVE=0``), which must end the same way: the same events and triggers (and
    no warning the compiled route did not give), or an error of the same class."""
    try:
        got = _read_every_way(path, salvage)
    except evtk.EvtkError as exc:
        _numpy_route_agrees(path, salvage, exc)
        raise
    except Wrong as exc:
        if salvage:
            raise Wrong(f"salvage: {exc}") from None
        raise
    _numpy_route_agrees(path, salvage, got)
    return got


def _numpy_route_agrees(path, salvage, compiled) -> None:
    """Raise :class:`Wrong` unless a full read on the numpy route ends as ``compiled`` (the compiled route's
    ``(events, triggers, warnings, info)``, or its :class:`evtk.EvtkError`)."""
    from evtk import _native

    if not _native.enabled():
        return
    before = os.environ.get("EVTK_NATIVE")
    os.environ["EVTK_NATIVE"] = "0"
    try:
        with evtk.open(path, salvage=salvage) as rec:
            numpy_route = (rec.events(), rec.triggers(), list(rec.warnings))
    except evtk.EvtkError as exc:
        numpy_route = exc
    finally:
        if before is None:
            del os.environ["EVTK_NATIVE"]
        else:
            os.environ["EVTK_NATIVE"] = before
    where = "salvage: " if salvage else ""
    if isinstance(compiled, BaseException) or isinstance(numpy_route, BaseException):
        if type(compiled) is not type(numpy_route):
            raise Wrong(f"{where}the compiled route ended in {compiled!r:.300}, the numpy route in "
                        f"{numpy_route!r:.300}")
        return
    for name, a, b in zip(("events", "triggers"), compiled[:2], numpy_route[:2]):
        if a != b:
            raise Wrong(f"{where}the compiled and numpy routes read different {name}: {a!r:.200} against "
                        f"{b!r:.200}")
    unsaid = [w for w in numpy_route[2] if w not in compiled[2]]  # the compiled route also read windows, chunks
    if unsaid:
        raise Wrong(f"{where}the numpy route warned {unsaid[0]!r:.200}, the compiled route did not")


def _read_every_way(path, salvage):
    with evtk.open(path, salvage=salvage) as rec:
        info = rec.info()
        got = rec.events()
        for lo, hi in _windows(got):
            w = rec.events(lo, hi)
            if w != got.between(lo, hi):
                raise Wrong(f"window [{lo}, {hi}) has {len(w)} events, the full read {len(got.between(lo, hi))}")
        chunks = list(rec.iter_events(chunk_events=97))
        streamed = evtk.Events.concatenate(chunks, sensor_size=got.sensor_size) if chunks else got[:0]
        if streamed != got:
            raise Wrong(f"iter_events gave {len(streamed)} events that differ from events() ({len(got)})")
        lo, hi = _windows(got)[0]
        part = [c for c in rec.iter_events(chunk_events=53, t_start_us=lo, t_end_us=hi)]
        part = evtk.Events.concatenate(part, sensor_size=got.sensor_size) if part else got[:0]
        if part != got.between(lo, hi):
            raise Wrong(f"iter_events in [{lo}, {hi}) gave {len(part)} events, the full read "
                        f"{len(got.between(lo, hi))}")
        tr = rec.triggers()
        warnings = list(rec.warnings)
        if salvage:
            scanned = rec.scan(chunk_events=700)["events"]
            if scanned != len(got):
                raise Wrong(f"salvage: scan() counts {scanned} events, events() gives {len(got)}")
    return got, tr, warnings, info


def _columns_equal(a, b):
    return len(a) == len(b) and all(np.array_equal(getattr(a, c), getattr(b, c)) for c in "txyp")


def _is_prefix(got, ref):
    n = len(got)
    return n <= len(ref) and all(np.array_equal(getattr(got, c), getattr(ref, c)[:n]) for c in "txyp")


def _multiset_diff(a, b):
    """(events of a not in b, events of b not in a), as multisets."""
    ca = collections.Counter(zip(a.t.tolist(), a.x.tolist(), a.y.tolist(), a.p.tolist()))
    cb = collections.Counter(zip(b.t.tolist(), b.x.tolist(), b.y.tolist(), b.p.tolist()))
    return sum((ca - cb).values()), sum((cb - ca).values())


def _records_touched(target, touched):
    """Number of event records the byte ranges touch, or None if any byte lies outside every record region."""
    n = 0
    for a, b in touched:
        for lo, hi, size in target.regions:
            if lo <= a and b <= hi:
                n += (b - 1 - lo) // size - (a - lo) // size + 1
                break
        else:
            return None
    return n


def _touched_indices(target, touched):
    """Event indices of the records the byte ranges touch (records counted over the regions in file order)."""
    out, base = set(), 0
    for lo, hi, size in target.regions:
        for a, b in touched:
            a, b = max(a, lo), min(b, hi)
            if a < b:
                out.update(range(base + (a - lo) // size, base + (b - 1 - lo) // size + 1))
        base += (hi - lo) // size
    return sorted(out)


def _wrap_consistent(got, truth, touched_idx) -> bool:
    """Whether ``got`` is the truth with the touched records changed and later stamps moved by whole 32-bit
    wraps, each where the raw stamp steps back by more than half the range: what a 32-bit stamp's wrap rule
    makes of a stamp flipped high (a small step back is no wrap)."""
    if len(got) != len(truth):
        return False
    keep = np.ones(len(truth), bool)
    keep[[i for i in touched_idx if i < len(truth)]] = False
    same = (got.x == truth.x) & (got.y == truth.y) & (got.p == truth.p) & ((got.t - truth.t) % 2**32 == 0)
    if not same[keep].all() or (len(got) and int(got.t.min()) < 0):
        return False
    raw, wraps = got.t % 2**32, got.t // 2**32
    step = np.diff(wraps)
    if np.any(step < 0) or np.any(step > 1):
        return False
    at = np.flatnonzero(step) + 1
    return bool(np.all(raw[at - 1] - raw[at] > 2**31))


def _bounds(got, warnings, target):
    w, h = got.sensor_size
    if len(got) and not warnings:
        if int(got.x.max()) >= w or int(got.y.max()) >= h:
            raise Wrong(f"{got.out_of_bounds()} events lie outside the {w}x{h} sensor, with no warning")
        if target.unsigned_t and int(got.t.min()) < 0:
            raise Wrong(f"negative time stamps ({int(got.t.min())} us) from a format whose stamps are unsigned")


def check_events(target: EventTarget, path, mutation) -> str:
    """Outcome of reading a mutated event file (see the module docstring); ``mutation`` is a dict with
    ``kind``, ``touched`` (byte ranges), ``in_place`` and ``payload_only`` (structure-aware)."""
    truth = target.truth
    try:
        got, _, warnings, _ = read_every_way(path)
    except evtk.EvtkError:
        outcome = "error"
        got = None
    if got is not None:
        _bounds(got, warnings, target)
        if target.family == "nmnist":
            mutation = dict(mutation, data=Path(path).read_bytes())
        outcome = judge_events(target, got, mutation)
    # salvage: never a traceback, read paths agree, a truncated file gives a prefix
    try:
        sal, _, swarn, _ = read_every_way(path, salvage=True)
    except evtk.EvtkError:
        return outcome
    _bounds(sal, swarn, target)
    if mutation["kind"] == "truncation" and not _is_prefix(sal, truth) and mutation["touched"][0][0] >= \
            target.data_start:
        raise Wrong(f"salvage of a file cut at byte {mutation['touched'][0][0]} gave {len(sal)} events that are "
                    "not a prefix of the events written")
    return outcome


def judge_events(target, got, mutation) -> str:
    """``exact`` or ``altered`` for a strict read that succeeded, or :class:`Wrong`."""
    truth = target.truth
    if got == truth:
        return "exact"
    kind, touched = mutation["kind"], mutation["touched"]
    if mutation.get("structured"):
        if not mutation.get("payload_only"):
            raise Wrong(f"{kind}: a strict read gave {len(got)} events that differ from the {len(truth)} written, "
                        "though no event payload changed")
        return "altered"
    first = min(a for a, _ in touched)
    if kind == "truncation":
        if first >= target.data_start and not _is_prefix(got, truth):
            raise Wrong(f"the file cut at byte {first} read as {len(got)} events that are not a prefix")
        return "altered"
    if max(b for _, b in touched) <= target.data_start:
        return "altered"  # a header value changed (sensor size, chip): within bounds, read paths agreeing
    if target.family == "checksummed":
        raise Wrong(f"{kind} after byte {target.data_start}, which a checksum covers: a read of {len(got)} events "
                    f"that differ from the {len(truth)} written")
    if target.family == "text" and mutation["in_place"] and first >= target.data_start:
        k = len(_text_lines_touched(target, touched))
        if got.sensor_size != truth.sensor_size:
            raise Wrong(f"the sensor size changed to {got.sensor_size} with only event lines touched")
        lost, added = _multiset_diff(truth, got)
        if lost > k or added > k:
            raise Wrong(f"{k} event line(s) changed, yet {lost} events written are missing and {added} events read "
                        "were not written (a change that spread past the lines touched)")
        return "altered"
    if target.family == "nmnist" and mutation["in_place"]:
        _judge_nmnist(target, got, touched, mutation["data"])
        return "altered"
    if kind.endswith("/mask") and target.structured in ("evt21", "evt21l"):
        _judge_evt21_mask(target, got, touched)
        return "altered"
    if target.family == "fixed" and mutation["in_place"]:
        k = _records_touched(target, touched)
        if k is not None:
            if not _columns_equal(got, truth) and got.sensor_size != truth.sensor_size:
                raise Wrong(f"the sensor size changed to {got.sensor_size} with only event records touched")
            lost, added = _multiset_diff(truth, got)
            if (lost > k or added > k) and not _wrap_consistent(got, truth, _touched_indices(target, touched)):
                raise Wrong(f"{k} event record(s) changed, yet {lost} events written are missing and {added} "
                            "events read were not written (a change that spread past the records touched)")
    return "altered"


def _text_lines_touched(target, touched) -> set:
    """Indices of the source file's lines (from ``data_start``) that the byte ranges touch; a separator's line
    counts, and a changed line end also counts the line after it."""
    data = target.path.read_bytes()
    ends = np.flatnonzero(np.frombuffer(data, np.uint8) == 10)
    out = set()
    for a, b in touched:
        first, last = np.searchsorted(ends, [a, b - 1])
        out.update(range(int(first), int(last) + 1))
        if last < len(ends) and ends[last] == b - 1:
            out.add(int(last) + 1)  # a line end changed: the next line may join this one
    return out


def _judge_evt21_mask(target, got, touched) -> None:
    """EVT 2.1, one word's 32-bit mask changed in place: a CD word's events become the pixels of the new mask, at
    the word's time, row and polarity, in rising x; every other event keeps its values (a mask changes no
    state). A mask of a word of another type changes nothing."""
    data = target.path.read_bytes()
    words = np.frombuffer(data[target.data_start:], "<u4").reshape(-1, 2)
    upper, mask = (words[:, 0], words[:, 1]) if target.structured == "evt21l" else (words[:, 1], words[:, 0])
    counts = np.unpackbits(mask.astype("<u4").view(np.uint8)).reshape(-1, 32).sum(axis=1) * ((upper >> 28) <= 1)
    k = (touched[0][0] - target.data_start) // 8
    truth = target.truth
    a, b = int(counts[:k].sum()), int(counts[:k + 1].sum())
    if (upper[k] >> 28) > 1:
        raise Wrong(f"the mask of word {k}, of type {int(upper[k] >> 28)}, changed the events read")
    new = len(got) - (len(truth) - (b - a))
    if new < 0 or not _columns_equal(got[:a], truth[:a]) or not _columns_equal(got[a + new:], truth[b:]):
        raise Wrong(f"the mask of word {k} (events {a}..{b}) changed, yet other events differ")
    part = got[a:a + new]
    ref = truth[a:b]
    base = int(ref.x[0]) & ~31
    if new and (np.any(part.t != ref.t[0]) or np.any(part.y != ref.y[0]) or np.any(part.p != ref.p[0])
                or np.any(np.diff(part.x.astype(np.int64)) <= 0) or int(part.x[0]) < base or int(part.x[-1]) >= base + 32):
        raise Wrong(f"the mask of word {k} changed, and its events moved in time, row or polarity, or off its group")


def _judge_nmnist(target, got, touched, mutated: bytes) -> None:
    """N-MNIST, records changed in place: each touched record may change its event (or become or stop being an
    overflow marker); every untouched event keeps x, y and p, and its stamp moves by 2**13 us for each marker
    gained before it (less each one lost). :class:`Wrong` otherwise."""
    src = np.frombuffer(target.path.read_bytes(), np.uint8)
    n = len(src) // 5
    old_marker = src[1:5 * n:5] == 240
    new_y = np.frombuffer(mutated[:5 * n], np.uint8)[1::5]
    new_marker = new_y == 240
    hit = np.zeros(n, bool)
    for a, b in touched:
        hit[a // 5:min(n, (b - 1) // 5 + 1)] = True
    if len(got) != int((~new_marker).sum()):
        raise Wrong(f"{len(got)} events read from {int((~new_marker).sum())} records that are not overflow markers")
    keep = ~hit & ~old_marker
    old_pos = np.cumsum(~old_marker) - 1
    new_pos = np.cumsum(~new_marker) - 1
    shift = (np.cumsum(new_marker) - np.cumsum(old_marker)) * 8192
    truth = target.truth
    i, j = old_pos[keep], new_pos[keep]
    ok = ((got.x[j] == truth.x[i]) & (got.y[j] == truth.y[i]) & (got.p[j] == truth.p[i])
          & (got.t[j] - truth.t[i] == shift[keep]))
    if not ok.all():
        k = int(np.flatnonzero(~ok)[0])
        raise Wrong(f"{int(hit.sum())} record(s) changed, yet the untouched event {int(i[k])} reads as "
                    f"t={int(got.t[j[k]])} ({int(got.x[j[k]])}, {int(got.y[j[k]])}), written t={int(truth.t[i[k]])} "
                    f"({int(truth.x[i[k]])}, {int(truth.y[i[k]])}), marker shift {int(shift[keep][k])} us")


# --------------------------------------------------------------------------------------------------- word mutations
def header_mutation(data: bytes, start: int, rng):
    """A text header's number replaced, a line dropped or repeated, or a long line added; ``(bytes, touched_end)``
    where the event bytes (from ``start``) are moved but unchanged."""
    head, body = data[:start], data[start:]
    lines = head.splitlines(keepends=True)
    what = int(rng.integers(0, 4))
    if what == 0:
        nums = [(i, m) for i, ln in enumerate(lines) for m in re.finditer(rb"\d+", ln)]
        if nums:
            i, m = nums[int(rng.integers(0, len(nums)))]
            v = str(rng.choice([0, 1, 7, 65535, 65536, 2**31, 2**32 + 5, 10**30])).encode()
            lines[i] = lines[i][:m.start()] + v + lines[i][m.end():]
    elif what == 1 and len(lines) > 1:
        del lines[int(rng.integers(1, len(lines)))]
    elif what == 2:
        i = int(rng.integers(0, len(lines)))
        lines.insert(i, lines[i])
    else:
        i = int(rng.integers(1, max(2, len(lines))))
        marker = lines[-1][:1] if lines else b"#"
        lines.insert(i, marker + b" " + b"x" * int(rng.choice([100, 70_000, 300_000])) + b"\r\n")
    new_head = b"".join(lines)
    return new_head + body, len(new_head)


def word_mutation(target: EventTarget, data: bytes, rng):
    """A record-aware change for the legacy and Prophesee formats: ``(bytes, kind, touched, in_place)``."""
    fmt = target.structured
    if fmt == "text":
        return _text_mutation(target, data, rng)
    if fmt == "nmnist":
        return _nmnist_mutation(data, rng)
    text_end = 0 if fmt == "es" else target.data_start - 2 if fmt == "dat" else target.data_start
    if rng.integers(0, 4) == 0 and text_end > 0:
        out, end = header_mutation(data, text_end, rng)
        return out, "header", [(0, end)], False
    data = bytearray(data)
    lo, hi, size = target.regions[int(rng.integers(0, len(target.regions)))]
    n_rec = (hi - lo) // size
    i = int(rng.integers(0, n_rec))
    at = lo + i * size
    prev_at = at - size if i else at
    what = int(rng.integers(0, 4))
    kind = f"{fmt}/word{what}"
    if fmt == "aedat2":  # big-endian address, time stamp
        if what == 0:  # a backward step of the stamp (no wrap)
            t_prev = struct.unpack_from(">I", data, prev_at + 4)[0]
            struct.pack_into(">I", data, at + 4, max(0, t_prev - int(rng.integers(1, 5000))))
        elif what == 1:
            struct.pack_into(">I", data, at + 4, int(rng.choice([0, 2**31, 2**32 - 1])))
        elif what == 2:
            data[at] |= 0x80  # an APS/IMU sample
        else:
            struct.pack_into(">I", data, at, int(rng.integers(0, 2**32)))
    elif fmt == "aedat1":  # 16-bit address, 32-bit stamp
        if what in (0, 1):
            t_prev = struct.unpack_from(">I", data, prev_at + 2)[0]
            v = max(0, t_prev - int(rng.integers(1, 5000))) if what == 0 else int(rng.choice([0, 2**32 - 1]))
            struct.pack_into(">I", data, at + 2, v)
        else:
            struct.pack_into(">H", data, at, int(rng.integers(0, 2**16)))
    elif fmt == "aedat31":  # the packet header (28 bytes before each region) or an event
        if what in (0, 1):
            field = int(rng.integers(0, 8))
            ph = lo - 28
            fmt_field = "<h" if field < 2 else "<i"
            off = ph + [0, 2, 4, 8, 12, 16, 20, 24][field]
            struct.pack_into(fmt_field, data, off, int(rng.choice([-1, 0, 1, 2, 8, n_rec + 1, 2**15 - 1]))
                             if field < 2 else int(rng.choice([-1, -(2**31), 0, 1, n_rec + 1, 2**31 - 1, 10**9])))
            return bytes(data), f"aedat31/packet_field{field}", [(off, off + 4)], True
        if what == 2:
            data[at] &= 0xFE  # the valid flag
        else:
            t_prev = struct.unpack_from("<I", data, prev_at + 4)[0]
            struct.pack_into("<I", data, at + 4, int(rng.choice([max(0, t_prev - 100), 2**31 - 1, 2**32 - 1])))
    elif fmt == "dat":  # 32-bit stamp, then x (14 bits), y (14 bits), polarity (4 bits)
        if what == 0:
            t_prev = struct.unpack_from("<I", data, prev_at)[0]
            struct.pack_into("<I", data, at, max(0, t_prev - int(rng.integers(1, 5000))))
        elif what == 1:
            struct.pack_into("<I", data, at + 4, int(rng.integers(0, 2**32)))
        elif what == 2:
            struct.pack_into("<I", data, at, int(rng.choice([0, 2**31, 2**32 - 1])))
        else:  # the event type and size bytes before the records
            j = lo - 2 + int(rng.integers(0, 2))
            data[j] = int(rng.integers(0, 256))
            return bytes(data), "dat/type_size", [(j, j + 1)], True
    elif fmt == "evt2":  # 32-bit words, type in the top 4 bits
        w = struct.unpack_from("<I", data, at)[0]
        if what == 0:
            w = (0x8 << 28) | int(rng.integers(0, 1 << 28))  # a TIME_HIGH from nowhere
        elif what == 1:
            w = (int(rng.choice([0x2, 0x3, 0x5, 0x7, 0x9, 0xA, 0xE, 0xF])) << 28) | (w & 0x0FFFFFFF)
        elif what == 2:
            w = (w & 0xF0000000) | int(rng.choice([0, 0x0FFFFFFF, 0x003FFFFF, 0x0FFFF800]))
        else:  # a word removed
            del data[at:at + 4]
            return bytes(data), "evt2/removed", [(at, len(data))], False
        struct.pack_into("<I", data, at, w)
    elif fmt == "evt3":  # 16-bit words, type in the top 4 bits
        at = lo + 2 * int(rng.integers(0, (hi - lo) // 2))
        w = struct.unpack_from("<H", data, at)[0]
        if what == 0:
            w = (int(rng.choice([0x8, 0x6])) << 12) | int(rng.choice([0, 0xFFF, int(rng.integers(0, 4096))]))
        elif what == 1:
            w = (int(rng.choice([0x1, 0x5, 0x7, 0x9, 0xB, 0xD, 0xF])) << 12) | (w & 0xFFF)
        elif what == 2:
            w = (int(rng.choice([0x0, 0x2, 0x3, 0x4, 0x5])) << 12) | 0xFFF
        else:
            del data[at:at + 2]
            return bytes(data), "evt3/removed", [(at, len(data))], False
        struct.pack_into("<H", data, at, w)
        return bytes(data), kind, [(at, at + 2)], True
    elif fmt in ("evt21", "evt21l"):  # 64-bit words: the half with the type, and a 32-pixel mask
        legacy = fmt == "evt21l"
        up_at, mask_at = (at, at + 4) if legacy else (at + 4, at)
        w = struct.unpack_from("<I", data, up_at)[0]
        if what == 0:
            w = (0x8 << 28) | int(rng.choice([0, 0x0FFFFFFF, int(rng.integers(0, 1 << 28))]))  # a TIME_HIGH
        elif what == 1:
            w = (int(rng.choice([0x0, 0x1, 0x2, 0x5, 0x9, 0xA, 0xE, 0xF])) << 28) | (w & 0x0FFFFFFF)
        elif what == 2:  # base x, y or the mask at their extremes
            field = int(rng.integers(0, 3))
            if field == 2:
                struct.pack_into("<I", data, mask_at, int(rng.choice([0, 0xFFFFFFFF, 1 << 31, 1])))
                return bytes(data), f"{fmt}/mask", [(mask_at, mask_at + 4)], True
            w = (w & ~(0x7FF << (11 * (1 - field)))) | (int(rng.choice([0x7FF, 0x7E0, 0])) << (11 * (1 - field)))
        else:  # a word removed
            del data[at:at + 8]
            return bytes(data), f"{fmt}/removed", [(at, len(data))], False
        struct.pack_into("<I", data, up_at, w)
        return bytes(data), kind, [(up_at, up_at + 4)], True
    else:  # es: a byte of the variable-length stream set to an overflow, reset or plain code
        at = lo + int(rng.integers(0, hi - lo))
        data[at] = int(rng.choice([0xFF, 0xFE, 0xFD, 0x00, 0x80, 0x7F, int(rng.integers(0, 256))]))
        return bytes(data), kind, [(at, at + 1)], True
    return bytes(data), kind, [(at, at + size)], True


def _text_mutation(target: EventTarget, data: bytes, rng):
    """A text event file's change: a digit of an event line replaced by another, a separator replaced (by another
    separator, a dot, a letter), a line dropped or repeated, or (where there is one) the first lines changed."""
    start = target.data_start
    if rng.integers(0, 4) == 0 and start > 0:
        out, end = header_mutation(data, start, rng)
        return out, "text/header", [(0, end)], False
    body = data[start:]
    what = int(rng.integers(0, 3))
    if what == 0:
        spots = [m.start() for m in re.finditer(rb"\d", body)]
        at = start + spots[int(rng.integers(0, len(spots)))]
        new = bytes([48 + int(rng.integers(0, 10))])
        return data[:at] + new + data[at + 1:], "text/digit", [(at, at + 1)], True
    if what == 1:
        spots = [m.start() for m in re.finditer(rb"[,\t ]+", body)]
        at = start + spots[int(rng.integers(0, len(spots)))]
        new = bytes([rng.choice(list(b",; \t.:|x-"))])
        return data[:at] + new + data[at + 1:], "text/separator", [(at, at + 1)], True
    ends = [m.end() for m in re.finditer(rb"\n", body)]
    i = int(rng.integers(0, len(ends)))
    a, b = start + (ends[i - 1] if i else 0), start + ends[i]
    if rng.integers(0, 2):
        return data[:a] + data[b:], "text/line_dropped", [(a, len(data))], False
    return data[:b] + data[a:b] + data[b:], "text/line_repeated", [(b, len(data) + b - a)], False


def _nmnist_mutation(data: bytes, rng):
    """An N-MNIST record changed: made an overflow marker (y = 240), a marker made an event, its stamp set
    back or far ahead, or its x, y and polarity byte set at random."""
    data = bytearray(data)
    n = len(data) // 5
    markers = [k for k in range(n) if data[5 * k + 1] == 240]
    what = int(rng.integers(0, 4))
    i = int(rng.integers(0, n))
    if what == 1 and markers:
        i = markers[int(rng.integers(0, len(markers)))]
    at = 5 * i
    if what == 0:
        data[at + 1] = 240
    elif what == 1:
        data[at + 1] = int(rng.integers(0, 34))
    elif what == 2:
        t = int(rng.choice([0, 2**23 - 1, int(rng.integers(0, 2**23))]))
        data[at + 2] = (data[at + 2] & 0x80) | (t >> 16)
        data[at + 3:at + 5] = (t & 0xFFFF).to_bytes(2, "big")
    else:
        data[at:at + 3] = bytes(int(v) for v in rng.integers(0, 256, 3))
    return bytes(data), f"nmnist/record{what}", [(at, at + 5)], True


def nmnist_bytes(ev) -> bytes:
    """``ev`` as N-MNIST records (x, y, polarity in bit 7 and a 23-bit big-endian stamp), with no marker."""
    raw = np.zeros((len(ev), 5), np.uint8)
    t = ev.t.astype(np.int64)
    raw[:, 0], raw[:, 1] = ev.x, ev.y
    raw[:, 2] = (ev.p.astype(np.int64) << 7) | ((t >> 16) & 0x7F)
    raw[:, 3], raw[:, 4] = (t >> 8) & 0xFF, t & 0xFF
    return raw.tobytes()


# --------------------------------------------------------------------------------------------------- writers
def write_aedat1(path, ev):
    """AEDAT 1.0 as jAER's DVS128 writes it: 16-bit big-endian address (OFF in bit 0, x mirrored in bits 1-7, y
    from the bottom in bits 8-14) and 32-bit big-endian time stamp."""
    head = (b"#!AER-DAT1.0\r\n# This is a raw AE data file - do not edit\r\n"
            b"# AEChip: ch.unizh.ini.jaer.chip.retina.DVS128\r\n")
    addr = ((127 - ev.y.astype(np.uint32)) << 8) | ((127 - ev.x.astype(np.uint32)) << 1) | (1 - ev.p.astype(np.uint32))
    rec = np.zeros(len(ev), np.dtype([("a", ">u2"), ("t", ">u4")]))
    rec["a"], rec["t"] = addr, ev.t
    Path(path).write_bytes(head + rec.tobytes())
    return len(head)


def _aedat31_regions(data):
    head = data.index(b"#!END-HEADER\r\n") + 14
    regions, at = [], head
    while at + 28 <= len(data):
        typ, _, size, _, _, cap, _, _ = struct.unpack_from("<hhiiiiii", data, at)
        if typ == 1:
            regions.append((at + 28, at + 28 + size * cap, size))
        at += 28 + size * cap
    return head, regions


def _dat_start(data):
    at = 0
    while data[at:at + 1] == b"%":
        at = data.index(b"\n", at) + 1
    return at + 2  # event type and size bytes


def _evt_start(data):
    at = 0
    while data[at:at + 1] == b"%":
        at = data.index(b"\n", at) + 1
    return at


def _es_start(data):
    # Event Stream: "Event Stream" magic, version (3 bytes), type (1 byte), width and height (2 + 2 for DVS)
    return 12 + 3 + 1 + 4


def build(folder, files=True, runs=True) -> None:
    """Write the source files and their truth into ``folder`` (done once, by the runner's parent): the event
    files (``files``), and the simulated run with its reconstruction files and settings files (``runs``)."""
    import sys

    sys.path.insert(0, str(HERE.parent))
    from conftest import event_stream_atis_file, random_events
    from test_aedat_legacy import write_aedat2_davis, write_aedat31

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    if runs:
        _build_reconstruction(folder)
        _build_settings(folder)
    if not files:
        (folder / "events.json").write_text("{}")
        return
    ev = random_events(1200, seed=3, span_us=50_000)
    tr = evtk.Triggers([10, 20_000], [1, 2])
    meta = {}

    def add(name, family, data_start=0, regions=(), unsigned_t=True, structured=None, truth=None):
        meta[name] = dict(family=family, data_start=data_start, regions=[list(r) for r in regions],
                          unsigned_t=unsigned_t, structured=structured)
        t = truth if truth is not None else evtk.read_events(folder / name)
        np.savez(folder / (name + ".truth.npz"), t=t.t, x=t.x, y=t.y, p=t.p, size=np.array(t.sensor_size))

    for name, kw in (("l.aedat4", dict(compression="lz4", packet_events=250, packet_us=None)),
                     ("z.aedat4", dict(compression="zstd", packet_events=300, packet_us=None)),
                     ("e.h5", dict(chunk_events=256)), ("p.parquet", dict(row_group_events=300))):
        evtk.write_events(folder / name, ev, tr, **kw)
        add(name, "container", unsigned_t=False,
            structured="aedat4" if name.endswith("aedat4") else "hdf5" if name.endswith("h5") else "parquet",
            truth=ev)
    from test_hdf5_parquet import make_dsec

    dsec = random_events(1200, seed=4, sensor_size=(640, 480), span_us=50_000, t0=1000)
    make_dsec(folder / "d.h5", dsec, t_offset=500)
    add("d.h5", "container", unsigned_t=False)
    big = evtk.Events(ev.t, ev.x, ev.y, ev.p, (346, 260))
    write_aedat2_davis(folder / "l2.aedat", big, 260)
    data = (folder / "l2.aedat").read_bytes()
    start = len(data) - 8 * len(big)
    add("l2.aedat", "fixed", start, [(start, len(data), 8)], structured="aedat2", truth=big)
    write_aedat31(folder / "l3.aedat", big, packet=300, other=True)
    start, regions = _aedat31_regions((folder / "l3.aedat").read_bytes())
    add("l3.aedat", "fixed", start, regions, structured="aedat31", truth=big)
    small = evtk.Events(ev.t, ev.x % 128, ev.y % 128, ev.p, (128, 128))
    start = write_aedat1(folder / "l1.aedat", small)
    n = (folder / "l1.aedat").stat().st_size
    try:  # a reader of AEDAT 1.0 decides the DVS128's orientation; the stamps and polarities are the file's
        read = evtk.read_events(folder / "l1.aedat")
        if len(read) == len(small) and np.array_equal(read.t, small.t) and np.array_equal(read.p, small.p):
            small = read
    except evtk.EvtkError:  # not read at all: every case is a clean error
        pass
    add("l1.aedat", "fixed", start, [(start, n, 6)], structured="aedat1", truth=small)
    try:  # the Prophesee and Event Stream files as faery writes them
        from test_prophesee import _faery_write
    except ImportError:  # pragma: no cover - faery is in the test extra
        _faery_write = None
    if _faery_write is not None:
        for version, name in (("evt2", "f2.raw"), ("evt3", "f3.raw"), ("dat2", "f.dat"), (None, "f.es")):
            _faery_write(folder / name, ev, version)
            data = (folder / name).read_bytes()
            got = evtk.read_events(folder / name)
            ref_t = ev.t - ev.t[0] if name == "f.es" else ev.t
            assert np.array_equal(got.x, ev.x) and np.array_equal(got.y, ev.y) and np.array_equal(got.p, ev.p)
            assert np.array_equal(got.t - got.t[0], ref_t - ref_t[0]), name
            if name == "f.dat":
                s = _dat_start(data)
                add(name, "fixed", s, [(s, len(data), 8)], structured="dat", truth=got)
            elif name == "f.es":
                s = _es_start(data)
                add(name, "stateful", s, [(s, len(data), 1)], structured="es", truth=got)
            else:
                s = _evt_start(data)
                add(name, "stateful", s, [(s, len(data), 4 if name == "f2.raw" else 2)],
                    structured="evt2" if name == "f2.raw" else "evt3", truth=got)
        # an AEDAT4 file as faery writes it: LZ4 frames with content checksums
        _faery_write(folder / "f.aedat4", ev, None)
        with evtk.open(folder / "f.aedat4") as rec:
            s = rec._data_start
        add("f.aedat4", "checksummed", s, unsigned_t=False, structured="aedat4")
    _build_decoded(folder, ev, add)
    _build_evt21(folder, ev, add)
    _build_atis(folder, ev, add, event_stream_atis_file)
    (folder / "events.json").write_text(json.dumps(meta))


def _build_decoded(folder, ev, add) -> None:
    """The formats evtk decodes whole: text events as evtk writes them (CSV, with faery's column names), as
    the DVS tools write them (a "H W" line, then ``t x y p`` with runs of spaces), and an N-MNIST binary
    (34x34, with an overflow marker in the middle)."""
    evtk.write_events(folder / "t.csv", ev, fmt="csv")
    data = (folder / "t.csv").read_bytes()
    add("t.csv", "text", data.index(b"\n") + 1, unsigned_t=False, structured="text", truth=ev)
    small = evtk.Events(ev.t, ev.x % 240, ev.y % 180, ev.p, (240, 180))
    lines = ["180 240"] + [f"{t} {x:3d} {y:3d} {p}" for t, x, y, p in zip(small.t, small.x, small.y, small.p)]
    (folder / "t.txt").write_text("\n".join(lines) + "\n")
    add("t.txt", "text", len(lines[0]) + 1, unsigned_t=False, structured="text", truth=small)
    digit = evtk.Events(ev.t, ev.x % 34, ev.y % 34, ev.p, (34, 34))
    body = nmnist_bytes(digit)
    mid = 5 * (len(digit) // 2)
    marker = bytes([0, 240]) + body[mid + 2:mid + 5]  # no event: 2**13 us more for every later one
    (folder / "n.bin").write_bytes(body[:mid] + marker + body[mid:])
    later = np.arange(len(digit)) >= len(digit) // 2
    truth = evtk.Events(digit.t + later * 8192, digit.x, digit.y, digit.p, (34, 34))
    add("n.bin", "nmnist", 0, [(0, len(body) + 5, 5)], structured="nmnist", truth=truth)
    for name in ("t.csv", "t.txt", "n.bin"):
        assert evtk.read_events(folder / name) == (small if name == "t.txt" else truth if name == "n.bin" else ev)


def _build_evt21(folder, ev, add) -> None:
    """EVT 2.1 as evtk writes it (one little-endian 64-bit word each), and the same words in the IMX636's layout
    (OpenEB's ``endianness=legacy``: the two 32-bit halves swapped); events in runs at one time and row, so
    that words hold vectors of several pixels, and trigger edges on three channels."""
    t = ev.t // 2000 * 2000
    y, x = ev.y % 3, ev.x % 96
    order = np.lexsort((x, ev.p, y, t))
    vec = evtk.Events(t[order], x[order], y[order], ev.p[order], ev.sensor_size)
    tr = evtk.Triggers([10, 20_000, 30_000], [1, 2, 1], [0, 5, 31])
    evtk.write_events(folder / "f21.raw", vec, tr, fmt="evt21")
    data = (folder / "f21.raw").read_bytes()
    s = _evt_start(data)
    words = np.frombuffer(data[s:], "<u4").reshape(-1, 2)
    assert len(words) < len(vec) // 2  # vectors of several pixels
    head = data[:s].replace(b"% format EVT21;", b"% format EVT21;endianness=legacy;")
    (folder / "f21l.raw").write_bytes(head + words[:, ::-1].tobytes())
    for name, fmt in (("f21.raw", "evt21"), ("f21l.raw", "evt21l")):
        start = _evt_start((folder / name).read_bytes())
        add(name, "stateful", start, [(start, (folder / name).stat().st_size, 8)], structured=fmt, truth=vec)
        with evtk.open(folder / name) as rec:
            got = rec.triggers()
            assert rec.events() == vec and got.channel.tolist() == [0, 5, 31] and got.t.tolist() == tr.t.tolist()


def _build_atis(folder, ev, add, event_stream_atis_file) -> None:
    """An ATIS Event Stream as event_stream (the format's library) writes it: the events, a third of them
    threshold crossings (which evtk counts and leaves out), with gaps long enough for overflow bytes."""
    try:
        import event_stream
    except ImportError:  # pragma: no cover - event_stream is in the test extra
        return
    rec = np.zeros(len(ev), event_stream.atis_dtype)
    rec["t"] = ev.t + np.arange(len(ev)) * 40  # gaps of 40 us and more: overflow bytes between some events
    rec["x"], rec["y"] = ev.x, ev.sensor_size[1] - 1 - ev.y.astype(np.int64)
    rec["exposure"], rec["polarity"] = np.arange(len(ev)) % 3 == 2, ev.p.astype(bool)
    event_stream_atis_file(folder / "a.es", rec, *ev.sensor_size)  # in a child process (see its docstring)
    cd = ~rec["exposure"]
    truth = evtk.Events(rec["t"][cd].astype(np.int64), ev.x[cd], ev.y[cd], ev.p[cd], ev.sensor_size)
    add("a.es", "stateful", _es_start(b""), [(_es_start(b""), (folder / "a.es").stat().st_size, 1)],
        structured="es", truth=truth)
    assert evtk.read_events(folder / "a.es") == truth


def load_event_targets(folder) -> dict:
    folder = Path(folder)
    meta = json.loads((folder / "events.json").read_text())
    out = {}
    for name, m in meta.items():
        z = np.load(folder / (name + ".truth.npz"))
        truth = evtk.Events(z["t"], z["x"], z["y"], z["p"], tuple(int(v) for v in z["size"]))
        out[name] = EventTarget(name, folder / name, truth, m["family"], m["data_start"],
                                [tuple(r) for r in m["regions"]], m["unsigned_t"], m["structured"])
    return out


# --------------------------------------------------------------------------------------------------- reconstruction
JOB = """kernels = ["010111010"]
features = ["1001011001101001"]
repeat = 1
flat_field = 2
calibration = 2
dot_spacing = 4
window_us = 1000
seed = 3
[bench]
origin_px = [60, 50]
"""


def _build_reconstruction(folder):
    from evtk.patterns import job_simulation, write_patterns
    from evtk.reconstruct import reconstruct

    (folder / "job.toml").write_text(JOB)
    sim = job_simulation(folder / "job.toml")
    write_patterns(sim, folder / "patterns")
    sim.write(folder / "sim.h5")
    with evtk.open(folder / "sim.h5") as rec:
        result = reconstruct(rec)
        record = rec.metadata["simulation"]
    evtk.save_reconstruction(folder / "r.h5", result, (320, 240), {"source": "sim.h5"})
    evtk.save_reconstruction(folder / "r.npz", result, (320, 240), {"source": "sim.h5"})
    (folder / "record.json").write_text(json.dumps(record))


RECON_ARRAYS = ("responses", "binary", "cells", "ideal", "pairs", "window_start_us", "window_end_us", "on", "off")


def reconstruction_state(path) -> dict:
    """Every array of a loaded reconstruction file and its summary, for comparison."""
    r = evtk.load_reconstruction(path)
    out = {"responses": r.responses, "binary": r.binary, "cells": r.cells, "ideal": r.ideal, "pairs": r.pairs,
           "window_start_us": r.counts.windows.t_start_us, "window_end_us": r.counts.windows.t_end_us,
           "on": r.counts.on, "off": r.counts.off,
           "summary": json.dumps(r.summary.to_dict(), sort_keys=True, default=str)}
    return out


def _recon_valid(state) -> list:
    """What a loaded reconstruction breaks of the format's rules (empty when nothing)."""
    bad = []
    for k in ("responses", "cells", "ideal"):
        a = state[k]
        if a is not None and (a.dtype.kind not in "fiub" or not np.all(np.isfinite(a))):
            bad.append(f"{k} not finite real numbers ({a.dtype})")
    for k in ("on", "off"):
        if state[k].dtype.kind not in "iu" or (state[k].size and int(state[k].min()) < 0):
            bad.append(f"{k} counts negative or not whole")
    s, e = state["window_start_us"], state["window_end_us"]
    if len(s) and not np.all(e > s):
        bad.append("a window ends before it starts")
    summary = json.loads(state["summary"])
    size = summary.get("sensor_size")
    if not (isinstance(size, list) and len(size) == 2 and all(isinstance(v, int) and 0 < v < 2**16 for v in size)):
        bad.append(f"sensor_size {size!r}")
    region = summary.get("region")
    if region is not None:
        ok = (isinstance(region, list) and len(region) == 4 and all(isinstance(v, int) for v in region)
              and 0 <= region[0] < region[1] and 0 <= region[2] < region[3])
        if not ok:
            bad.append(f"region {region!r}")
    return bad


def _same_state(a, b) -> bool:
    for k in RECON_ARRAYS:
        x, y = a[k], b[k]
        if (x is None) != (y is None) or (x is not None and (x.shape != y.shape or not np.array_equal(x, y))):
            return False
    return a["summary"] == b["summary"]


def mutate_recon_h5(src: Path, dst: Path, other: Path, rng):
    """A structure-aware change of a reconstruction ``.h5``: ``(kind, values_only)``."""
    import h5py

    dst.write_bytes(src.read_bytes())
    what = int(rng.integers(0, 8))
    with h5py.File(dst, "a") as f:
        g = f["reconstruction"]
        name = RECON_ARRAYS[int(rng.integers(0, len(RECON_ARRAYS)))]
        if name not in g:
            name = "responses"
        data = g[name][...]
        if what == 0:  # a hostile value in place
            del g[name]
            new = data.astype(np.float64) if data.dtype.kind == "f" else data.copy()
            if new.size:
                v = rng.choice([np.nan, np.inf, -1, 2**40, -(2**31)]) if new.dtype.kind == "f" else \
                    rng.choice([-1, np.iinfo(new.dtype).max, np.iinfo(new.dtype).min])
                new.flat[int(rng.integers(0, new.size))] = v
            g.create_dataset(name, data=new)
        elif what == 1:  # another shape
            del g[name]
            g.create_dataset(name, data=np.resize(data, tuple(int(rng.integers(0, 4)) for _ in range(data.ndim))))
        elif what == 2:  # a huge declared shape, nothing written (sparse)
            del g[name]
            g.create_dataset(name, shape=(10**5,) + tuple(max(1, s) * 50 for s in data.shape[1:]),
                             dtype=data.dtype, chunks=True)
        elif what == 3:  # an external link to another file
            del g[name]
            g[name] = h5py.ExternalLink(str(other), "/events/t")
        elif what == 4:  # storage in another file's bytes
            del g[name]
            g.create_dataset(name, shape=data.shape, dtype=data.dtype,
                             external=[(str(other), 0, max(1, data.size * data.dtype.itemsize))])
        elif what == 5:  # a virtual dataset
            del g[name]
            layout = h5py.VirtualLayout(shape=(16,), dtype=np.int64)
            layout[:] = h5py.VirtualSource(str(other), "/events/t", shape=(16,))
            g.create_virtual_dataset(name, layout)
        elif what == 6:  # another dtype
            del g[name]
            g.create_dataset(name, data=data.astype(rng.choice([np.float16, np.int8, np.uint64, np.complex64,
                                                                  np.bool_])))
        else:  # the metadata JSON: one value hostile
            meta = json.loads(bytes(f["metadata"][()]).decode() if "metadata" in f else f.attrs["metadata"])
            doc, _ = value_mutation(meta, rng)
            text = json.dumps(doc)
            if "metadata" in f:
                del f["metadata"]
                f.create_dataset("metadata", data=np.frombuffer(text.encode(), np.uint8))
            else:
                f.attrs["metadata"] = text
    names = ["value", "shape", "sparse", "external_link", "external_storage", "virtual", "dtype", "metadata"]
    return f"recon_h5/{names[what]}", what in (0, 1, 6, 7)


def mutate_recon_npz(src: Path, rng):
    """A structure-aware change of a reconstruction ``.npz``: ``(bytes, kind, values_only)``."""
    with np.load(src, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    what = int(rng.integers(0, 7))
    name = [k for k in arrays if k != "summary"][int(rng.integers(0, len(arrays) - 1))]
    a = arrays[name]
    extra = {}
    if what == 0:
        new = a.astype(np.float64) if a.dtype.kind == "f" else a.copy()
        if new.size:
            new.flat[int(rng.integers(0, new.size))] = rng.choice([np.nan, np.inf, -1.0]) if new.dtype.kind == "f" \
                else -1
        arrays[name] = new
    elif what == 1:
        arrays[name] = np.resize(a, tuple(int(rng.integers(0, 4)) for _ in range(max(1, a.ndim))))
    elif what == 2:  # zero-filled and huge: a few hundred kB compressed
        arrays[name] = np.zeros((int(rng.choice([1000, 40_000])),) + a.shape[1:], a.dtype)
    elif what == 3:  # an object array (a pickle)
        arrays[name] = np.array([{"a": 1}, None], dtype=object)
    elif what == 4:
        del arrays[name]
    elif what == 5:
        doc, _ = value_mutation(json.loads(str(arrays["summary"])), rng)
        arrays["summary"] = np.array(json.dumps(doc))
    else:  # a member twice (a zip may hold two of a name)
        extra = {name: np.resize(a, (1,) * a.ndim)}
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for k, v in {**arrays}.items():
            b = io.BytesIO()
            np.lib.format.write_array(b, v, allow_pickle=True)
            zf.writestr(k + ".npy", b.getvalue())
        for k, v in extra.items():
            b = io.BytesIO()
            np.lib.format.write_array(b, v)
            import warnings

            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                zf.writestr(k + ".npy", b.getvalue())
    names = ["value", "shape", "zero_bomb", "pickle", "missing", "summary", "duplicate"]
    # an optional array left out is a valid file without it; a required one left out must be an error
    return buf.getvalue(), f"recon_npz/{names[what]}", what in (0, 1, 4, 5)


def check_reconstruction(truth: dict, path, values_only: bool, checksummed: bool) -> str:
    """Outcome of loading a mutated reconstruction file (and describing it, as ``evtk info`` does)."""
    from evtk.io.reconstruction import describe_reconstruction

    try:
        state = reconstruction_state(path)
        describe_reconstruction(path)
    except evtk.EvtkError:
        return "error"
    if _same_state(state, truth):
        return "exact"
    bad = _recon_valid(state)
    if bad:
        raise Wrong("a reconstruction file loaded with " + "; ".join(bad))
    if checksummed:
        raise Wrong("a reconstruction NPZ (CRC-checked members) loaded with other arrays than written")
    if not values_only:
        raise Wrong("a structural change (link, external storage, size) loaded as other arrays, not an error")
    return "altered"


# --------------------------------------------------------------------------------------------------- settings
def _build_settings(folder):
    from evtk.calibrate import Calibration, save_calibration

    cal = Calibration(matrix=[[2.0, 0.0, 60.0], [0.0, 2.0, 50.0], [0.0, 0.0, 1.0]], origin_px=[60.0, 50.0],
                      step_px=2.0, region=[58, 70, 48, 60], residual_rms_px=0.1, residual_max_px=0.3,
                      dots_expected=9, dots_found=9, inliers=9, sensor_size=[320, 240], response_shape=[6, 6],
                      k1=0.01, background_rate_hz=0.2, blur_px=0.5)
    save_calibration(folder / "cal.toml", cal)
    # the job as TOML (built by the reconstruction step), the schedule written with the patterns


_POSITIVE = ("window_us", "repeat", "dot_spacing", "decimation", "dmd_cols", "dmd_rows", "sensor_width",
             "sensor_height", "feature_upsample", "kernel_upsample", "u_mm", "z_mm", "mirror_pitch_um",
             "sensor_pitch_um", "kernel_hz", "features_hz", "wavelength_nm", "step_px", "tau_min_us")
_NON_NEGATIVE = ("settle_us", "flat_field", "calibration", "levels", "light_delay_us", "power_mw", "efficiency",
                 "stray_light", "psf_sigma_um", "pixel_latency_us", "blur_px", "dark_current_e_per_s",
                 "background_rate_hz", "hot_pixel_rate_hz", "refractory_us", "gain_e_per_s_per_unit",
                 "blank_rate_e_per_s", "residual_rms_px", "residual_max_px", "dots_expected", "dots_found", "inliers",
                 "theta_on", "theta_off", "start_us", "end_us")
_FRACTIONS = ("hot_pixel_fraction", "noise_step_fraction")

#: The rules a loaded settings value must obey (names as the files spell them).
RULES = {"positive": _POSITIVE, "non_negative": _NON_NEGATIVE, "fraction": _FRACTIONS}


def _plain(obj):
    """A loaded settings object as plain data (dataclasses, arrays and tuples unpacked)."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: _plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def settings_violations(plain) -> list:
    """Every value of a loaded settings object that breaks :data:`RULES` or is not finite."""
    bad = []
    for path, v in _leaves(plain):
        key = next((k for k in reversed(path) if isinstance(k, str)), "")
        if isinstance(v, float) and not math.isfinite(v):
            bad.append(f"{'/'.join(map(str, path))} = {v}")
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not path or not isinstance(path[-1], str):
            continue
        if key in _POSITIVE and not v > 0:
            bad.append(f"{key} = {v!r} (must be > 0)")
        elif key in _NON_NEGATIVE and not v >= 0:
            bad.append(f"{key} = {v!r} (must be >= 0)")
        elif key in _FRACTIONS and not 0 <= v <= 1:
            bad.append(f"{key} = {v!r} (must be within 0 and 1)")
    return bad


def _check_patterns(plain, bad):
    for k in ("kernels", "features"):
        a = plain.get(k)
        if a is not None:
            arr = np.asarray(a)
            if arr.ndim != 3 or arr.size == 0 or not np.isin(arr, (-1, 0, 1)).all():
                bad.append(f"{k} not a non-empty stack of -1/0/1 patterns")


def _load_job(path):
    from evtk.patterns import job_simulation

    sim = job_simulation(path)
    plain = {k: _plain(getattr(sim, k)) for k in ("bench", "sensor", "kernels", "features", "window_us",
                                                    "settle_us", "repeat", "dot_spacing", "flat_field",
                                                    "calibration", "levels", "light_delay_us") if hasattr(sim, k)}
    rec = sim.record()  # the record a run would write: every value derived from the job
    plain["record"] = _plain(rec.to_dict())
    bad = []
    _check_patterns(plain, bad)
    return plain, bad


def _load_schedule(path):
    from evtk.reconstruct.bench import load_schedule

    s = load_schedule(path)  # a Plan: the schedule's entries as attributes
    plain = {k: _plain(getattr(s, k)) for k in ("schedule", "kernels", "features", "bench", "window_us", "settle_us",
                                               "dot_spacing")}
    bad = []
    _check_patterns(plain, bad)
    sched = plain["schedule"]
    on, off = np.asarray(sched.get("t_on_us", [])), np.asarray(sched.get("t_off_us", []))
    if on.size and (not np.all(off > on) or not np.all(np.diff(on) > 0)):
        bad.append("captures that end before they start or are out of order")
    return plain, bad


def _load_calibration(path):
    from evtk.calibrate import load_calibration

    cal = load_calibration(path)
    plain = _plain(cal)
    bad = []
    m = np.asarray(plain["matrix"], dtype=np.float64)
    if m.shape == (3, 3) and np.all(np.isfinite(m)) and abs(np.linalg.det(m)) < 1e-12:
        bad.append("a singular matrix")
    w, h = plain["sensor_size"]
    if not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in (w, h)):
        bad.append(f"sensor_size {plain['sensor_size']!r}")
    r = plain["region"]
    if not (all(isinstance(v, int) and not isinstance(v, bool) for v in r) and 0 <= r[0] < r[1] and
            0 <= r[2] < r[3]):
        bad.append(f"region {r!r}")
    if not (isinstance(plain["response_shape"], list) and len(plain["response_shape"]) == 2 and
            all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in plain["response_shape"])):
        bad.append(f"response_shape {plain['response_shape']!r}")
    cal.cell_map()  # what reconstruct builds from it
    return plain, bad


def _load_record(path):
    from evtk.settings import read_table
    from evtk.simulate.record import SimulationRecord

    rec = SimulationRecord.from_dict(read_table(path, "simulation record"))
    plain = _plain(rec.to_dict())
    bad = []
    _check_patterns(plain, bad)
    sched = plain["schedule"]
    for k in ("kernel_id", "features_id"):
        ids = np.asarray(sched.get(k, []))
        n = len(plain["kernels" if k == "kernel_id" else "features"])
        if ids.size and int(ids.max()) >= n:
            bad.append(f"{k} {int(ids.max())} names no pattern ({n})")
    if plain["end_us"] < plain["start_us"]:
        bad.append("end_us before start_us")
    reg = plain["response_region"]
    if not (len(reg) == 4 and reg[0] < reg[1] and reg[2] < reg[3] and min(reg) >= 0):
        bad.append(f"response_region {reg!r}")
    rec.placement  # noqa: B018 - what the oracle reconstruction reads
    return plain, bad


@dataclasses.dataclass
class SettingsTarget:
    name: str
    path: Path
    loader: object
    toml: bool
    truth: object = None


def load_settings_targets(folder) -> dict:
    folder = Path(folder)
    out = {"job.toml": SettingsTarget("job.toml", folder / "job.toml", _load_job, True),
           "schedule.json": SettingsTarget("schedule.json", folder / "patterns" / "schedule.json", _load_schedule,
                                           False),
           "cal.toml": SettingsTarget("cal.toml", folder / "cal.toml", _load_calibration, True),
           "record.json": SettingsTarget("record.json", folder / "record.json", _load_record, False)}
    for t in out.values():
        plain, bad = t.loader(t.path)
        assert not bad and not settings_violations(plain), (t.name, bad, settings_violations(plain))
        t.truth = json.dumps(plain, sort_keys=True)
    return out


def parse_settings(target: SettingsTarget, text: bytes) -> dict:
    if target.toml:
        import tomllib

        return tomllib.loads(text.decode())
    return json.loads(text)


def check_settings(target: SettingsTarget, path) -> str:
    """Outcome of loading a mutated settings file: an error, the same values, or values that obey the rules."""
    try:
        plain, bad = target.loader(path)
    except evtk.EvtkError:
        return "error"
    if json.dumps(plain, sort_keys=True) == target.truth:
        return "exact"
    bad = bad + settings_violations(plain)
    if bad:
        raise Wrong(f"{target.name} loaded with " + "; ".join(bad[:3]))
    return "altered"
