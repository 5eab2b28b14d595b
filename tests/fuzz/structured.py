"""Structure-aware fuzzing: valid containers around lying contents, every read compared with the truth.

    python tests/fuzz/structured.py --cases 3000 --seed 1

Byte flips rarely survive a compressed frame, so this campaign mutates what
lies inside and then packages it properly:

* AEDAT4: a packet's FlatBuffer (root and vtable offsets, table sizes, vector
  length, identifier, or the event structs themselves) is mutated and
  recompressed into a valid LZ4 or ZSTD frame; or the data table's counts,
  offsets and times lie while the packets are intact; or a packet is a valid
  frame that inflates to 256 MiB (or says it holds 1.9 GB).
* HDF5 (evtk layout): a column resized, retyped or made sparse, the time
  index shifted or shuffled, a soft or external link, a virtual dataset or
  external storage put in a column's place, the sensor size changed.
* Parquet: a row group's ``t`` statistics moved in the footer.

Every case is read strictly, with windows and in chunks. The outcome must be
a FormatError, or events equal to the original ones -- except where the
mutation changed event payload bytes no checksum covers, where a difference
is expected and counted as ``altered_payload``. A window must equal the
full read cut to the window ("silent wrong window" otherwise); anything else
raised is a crash. Not collected by pytest (no test_ prefix).
"""

from __future__ import annotations

import argparse
import collections
import faulthandler
import os
import struct
import sys
import tempfile
import time
import traceback
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from conftest import random_events  # noqa: E402

import evtk  # noqa: E402
from evtk.io import _compression as cz  # noqa: E402
from evtk.io import _fb, _fbpy  # noqa: E402
from evtk.io import aedat4 as a4  # noqa: E402

WINDOWS = [(0, 10_000), (20_000, 20_500), (33_333, 49_999), (-5, 1)]


def _aedat4_parts(path):
    """(header bytes, [(stream, decompressed body)], code) of an evtk AEDAT4 file."""
    with evtk.open(path) as rec:
        idx = rec._index
        bodies = [(int(idx.stream[i]), rec._body(i).tobytes()) for i in range(len(idx))]
        code, start = rec._code, rec._data_start
    return path.read_bytes()[:start], bodies, code


_BOMBS = {}


def _bomb(code, rng):
    """A valid frame that inflates far past what its packet may (256 MiB), or claims to (ZSTD, 1.9 GB)."""
    import lz4.frame
    import zstandard

    if code in (cz.LZ4, cz.LZ4_HIGH):
        if "lz4" not in _BOMBS:
            _BOMBS["lz4"] = lz4.frame.compress(bytes(256 << 20), store_size=False)
        return _BOMBS["lz4"]
    if rng.integers(0, 2):  # a header that claims 1.9 GB around one raw block
        return b"\x28\xb5\x2f\xfd" + bytes([0b11100000]) + struct.pack("<Q", 1_900_000_000) + \
            struct.pack("<I", (64 << 3) | 1)[:3] + bytes(64)
    if "zstd" not in _BOMBS:
        _BOMBS["zstd"] = zstandard.ZstdCompressor(level=1, write_content_size=False).compress(bytes(256 << 20))
    return _BOMBS["zstd"]


def _assemble(header, bodies, code, table=None, raw=None):
    """An AEDAT4 file of the bodies, compressed into valid frames (``raw`` maps a packet to the frame to
    store instead), with a data table (or ``table`` lies)."""
    out = bytearray(header)
    struct.pack_into("<q", out, a4._DTP_FIELD, -1)
    rows = []
    for k, (sid, body) in enumerate(bodies):
        blob = (raw or {}).get(k) or cz.compress(code, body)
        rows.append((len(out) + 8, sid, len(blob)))
        out += struct.pack("<ii", sid, len(blob)) + blob
    if table is not None:
        cols = table(rows, bodies)
        buf = np.empty(_fb.data_table_size(len(cols[0])), np.uint8)
        size = _fb.encode_data_table(*cols, buf)
        struct.pack_into("<q", out, a4._DTP_FIELD, len(out))
        out += cz.compress(code, buf[:size].tobytes())
    return bytes(out)


def _honest_table(rows, bodies):
    offset, stream, size, count, t0, t1 = ([] for _ in range(6))
    for (off, sid, n), (_, body) in zip(rows, bodies):
        b = np.frombuffer(body, np.uint8)
        k = _fbpy.vector_length(b, a4._IDENT["EVTS" if sid == 0 else "TRIG"], 0)
        offset.append(off)
        stream.append(sid)
        size.append(n)
        count.append(max(k, 0))
        if sid == 0 and 0 < k and 32 + 16 * k <= len(body):
            t = np.frombuffer(body, np.int64, count=2 * k, offset=32)[::2]
            t0.append(int(t[0]))
            t1.append(int(t[-1]))
        else:
            t0.append(0)
            t1.append(0)
    return [np.asarray(c, np.int64) for c in (offset, stream, size, count, t0, t1)]


def mutate_aedat4(parts, rng):
    """(file bytes, kind, payload_only): one structural lie inside valid frames."""
    header, bodies, code = parts
    bodies = list(bodies)
    events = [i for i, (sid, _) in enumerate(bodies) if sid == 0]
    k = events[int(rng.integers(0, len(events)))]
    sid, body = bodies[k]
    b = bytearray(body)
    what = int(rng.integers(0, 10))
    payload_only = False
    if what == 0:  # the root offset
        struct.pack_into("<I", b, 4, int(rng.choice([0, 2, 8, 4096, 2**31])))
    elif what == 1:  # the vtable offset of the root table
        struct.pack_into("<i", b, 20, int(rng.choice([-4096, 0, 1, 6000, 2**31 - 1])))
    elif what == 2:  # vtable / table sizes
        struct.pack_into("<HH", b, 14, int(rng.integers(0, 65536)), int(rng.integers(0, 65536)))
    elif what == 3:  # the vector length
        n = struct.unpack_from("<I", b, 28)[0]
        struct.pack_into("<I", b, 28, int(rng.choice([0, 1, n - 1, n + 1, 2 * n, 2**32 - 1])) % 2**32)
    elif what == 4:  # the identifier
        b[8:12] = bytes(rng.integers(0, 256, 4, dtype=np.uint8))
    elif what == 5:  # event structs: time stamps, coordinates, polarity (no checksum covers them)
        n = struct.unpack_from("<I", b, 28)[0]
        for _ in range(int(rng.integers(1, 6))):
            at = 32 + 16 * int(rng.integers(0, max(1, n))) + int(rng.choice([0, 7, 8, 9, 10, 11, 12]))
            if at < len(b):
                b[at] ^= 1 << int(rng.integers(0, 8))
        payload_only = True
    elif what == 6:  # the body cut or padded (inside a valid frame)
        cut = int(rng.integers(0, len(b)))
        b = b[:cut] if rng.integers(0, 2) else b + bytes(int(rng.integers(1, 64)))
    elif what == 7:  # the vector offset field
        struct.pack_into("<I", b, 24, int(rng.choice([0, 1, 3, 4096, 2**32 - 1])))
    bodies[k] = (sid, bytes(b))
    table = None
    if what == 8:  # intact packets, a data table that lies
        lie = int(rng.integers(0, 4))

        def table(rows, bodies, lie=lie):
            cols = _honest_table(rows, bodies)
            j = int(rng.integers(0, len(rows)))
            if lie == 0:
                cols[3][j] = int(rng.choice([0, cols[3][j] + 1, 2**40]))
            elif lie == 1:
                cols[4][j:] += int(rng.choice([-10_000, 10_000, 10**9]))
                cols[5][j:] += int(rng.choice([-10_000, 10_000, 10**9]))
            elif lie == 2:
                cols[0][j] += int(rng.choice([-8, 8, 10**6]))
            else:
                cols[4], cols[5] = cols[4][::-1].copy(), cols[5][::-1].copy()
            return cols
    elif rng.integers(0, 2):
        table = _honest_table
    raw = {k: _bomb(code, rng)} if what == 9 else None
    names = ["root", "vtable", "sizes", "vector_length", "ident", "payload", "body_length", "vector_offset",
             "table", "bomb"]
    return _assemble(header, bodies, code, table, raw), f"aedat4/{names[what]}", payload_only


def mutate_hdf5(src: Path, dst: Path, rng):
    import h5py

    dst.write_bytes(src.read_bytes())
    what = int(rng.integers(0, 9))
    with h5py.File(dst, "a") as f:
        g = f["events"]
        if what == 0:  # one column shorter or longer
            name = "txyp"[int(rng.integers(0, 4))]
            n = g[name].shape[0]
            data = g[name][...]
            del g[name]
            m = int(rng.choice([0, n - 1, n + 1, 2 * n]))
            new = np.resize(data, m)
            g.create_dataset(name, data=new, chunks=True, maxshape=(None,))
        elif what == 1:  # a column retyped
            name = "txyp"[int(rng.integers(0, 4))]
            data = g[name][...]
            del g[name]
            g.create_dataset(name, data=data.astype(rng.choice([np.float32, np.int8, np.uint64, np.int16])))
        elif what == 2:  # the index shifted, shuffled or zeroed
            idx = g["index_t_us"][...]
            choice = int(rng.integers(0, 3))
            g["index_t_us"][...] = (idx + int(rng.choice([-50_000, 7, 50_000])) if choice == 0
                                   else rng.permutation(idx) if choice == 1 else np.zeros_like(idx))
        elif what == 3:  # a column replaced by a soft link to another one
            name = "xyp"[int(rng.integers(0, 3))]
            del g[name]
            g[name] = h5py.SoftLink("/events/" + "xyp".replace(name, "")[0])
        elif what == 4:  # an external link in a column's place
            name = "txyp"[int(rng.integers(0, 4))]
            del g[name]
            g[name] = h5py.ExternalLink(str(src), f"/events/{name}")
        elif what == 5:  # a column claiming more elements than it holds
            name = "txyp"[int(rng.integers(0, 4))]
            ds = g[name]
            data = ds[...]
            del g[name]
            big = g.create_dataset(name, shape=(len(data) * 1000,), maxshape=(None,), chunks=(1024,),
                                   dtype=data.dtype)
            big[: len(data)] = data
        elif what == 6:  # the sensor size changed (smaller than the coordinates, or larger)
            f.attrs["sensor_size"] = np.array([int(rng.integers(1, 400)), int(rng.integers(1, 300))])
        elif what == 7:  # a column turned into a virtual dataset reading the original file
            name = "txyp"[int(rng.integers(0, 4))]
            n, dtype = g[name].shape[0], g[name].dtype
            del g[name]
            layout = h5py.VirtualLayout(shape=(n,), dtype=dtype)
            layout[:] = h5py.VirtualSource(str(src), f"/events/{name}", shape=(n,))
            g.create_virtual_dataset(name, layout)
        else:  # a column whose storage is the original file's bytes
            name = "txyp"[int(rng.integers(0, 4))]
            n, dtype = g[name].shape[0], g[name].dtype
            del g[name]
            g.create_dataset(name, shape=(n,), dtype=dtype, external=[(str(src), 0, n * dtype.itemsize)])
    # a retyped column, one linked to another or a larger sensor is a valid file holding other values: like a
    # payload change
    names = ["length", "dtype", "index", "soft_link", "external_link", "sparse", "sensor_size", "virtual",
             "external_storage"]
    return f"hdf5/{names[what]}", what in (1, 3, 6)


def mutate_parquet(src: Path, rng):
    import pyarrow.parquet as pq

    md = pq.ParquetFile(src).metadata
    data = bytearray(src.read_bytes())
    footer_at = len(data) - 8 - struct.unpack("<i", data[-8:-4])[0]
    g = int(rng.integers(0, md.num_row_groups))
    st = md.row_group(g).column(0).statistics
    shift = int(rng.choice([-20_000, -1, 1, 20_000, 10**9]))
    for v in (st.min, st.max) if rng.integers(0, 2) else (int(rng.choice([st.min, st.max])),):
        raw = struct.pack("<q", v)
        at = data.find(raw, footer_at)
        while at >= 0:
            data[at:at + 8] = struct.pack("<q", v + shift)
            at = data.find(raw, at + 8)
    return bytes(data), "parquet/statistics"


def check(path: Path, reference, kind, payload_only, counts):
    """Read ``path`` every way; raise AssertionError for a wrong result (a crash is any other exception)."""
    try:
        with evtk.open(path) as rec:
            rec.info()
            got = rec.events()
            for lo, hi in WINDOWS:
                w = rec.events(lo, hi)
                if w != got.between(lo, hi):
                    raise AssertionError(f"silent wrong window [{lo}, {hi}): {len(w)} events, the full read "
                                         f"has {len(got.between(lo, hi))}")
                if w != reference.between(lo, hi) and not payload_only:
                    raise AssertionError(f"window [{lo}, {hi}) differs from the original events")
            chunks = list(rec.iter_events(chunk_events=700))
            streamed = evtk.Events.concatenate(chunks, sensor_size=got.sensor_size) if chunks else got[:0]
            if streamed != got:
                raise AssertionError("iter_events differs from events()")
    except evtk.FormatError:
        counts["format_error"] += 1
        return
    if got == reference:
        counts["read_exact"] += 1
    elif payload_only:
        counts["altered_payload"] += 1
    else:
        raise AssertionError(f"{kind}: a strict read returned {len(got)} events that differ from the "
                             f"{len(reference)} written, outside any payload")


def check_cli(path: Path, tmp: Path):
    """``evtk info --check`` and ``evtk convert`` on the case: exit 0 or 1, and one line on error."""
    from click.testing import CliRunner

    from evtk.cli import main as cli

    out = tmp / "converted.h5"
    for args in (["info", "--check", "--json", str(path)], ["convert", str(path), str(out)]):
        r = CliRunner().invoke(cli, args)
        if r.exit_code not in (0, 1) or (r.exit_code == 1 and len(r.output.strip().splitlines()) != 1):
            raise AssertionError(f"evtk {args[0]}: exit {r.exit_code}, output {r.output[-300:]!r}, "
                                 f"exception {r.exception!r}")
        if out.exists():
            out.unlink()


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--cases", type=int, default=3000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--start", type=int, default=0, help="first case number (to split a campaign over processes)")
    ap.add_argument("--hang-seconds", type=float, default=20.0)
    ap.add_argument("--cli-every", type=int, default=10, help="run the CLI on every Nth case (0: never)")
    ap.add_argument("--alloc-limit", type=float, default=64.0,
                    help="a case whose traced allocations peak above 16 MiB + this many times the file's size "
                         "is a crash; 0 turns tracing off")
    args = ap.parse_args(argv)
    if args.alloc_limit > 0:
        import tracemalloc

        tracemalloc.start()
    worst = (0.0, None)
    counts = collections.Counter()
    kinds = collections.Counter()
    crashes = []
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        ev = random_events(4000, seed=3, span_us=50_000)
        srcs = {}
        for name, kw in (("l.aedat4", dict(compression="lz4", packet_events=500, packet_us=None)),
                         ("z.aedat4", dict(compression="zstd", packet_events=700, packet_us=None)),
                         ("e.h5", dict(chunk_events=512)), ("p.parquet", dict(row_group_events=600))):
            srcs[name] = tmp / name
            evtk.write_events(srcs[name], ev, **kw)
        parts = {n: _aedat4_parts(p) for n, p in srcs.items() if n.endswith(".aedat4")}
        names = sorted(srcs)
        t_start = time.time()
        for case in range(args.start, args.start + args.cases):
            rng = np.random.default_rng([args.seed, case])
            name = names[case % len(names)]
            p = tmp / ("m" + Path(name).suffix)
            payload_only = False
            if name.endswith(".aedat4"):
                data, kind, payload_only = mutate_aedat4(parts[name], rng)
                p.write_bytes(data)
            elif name.endswith(".h5"):
                kind, payload_only = mutate_hdf5(srcs[name], p, rng)
            else:
                data, kind = mutate_parquet(srcs[name], rng)
                p.write_bytes(data)
            kinds[kind] += 1
            faulthandler.dump_traceback_later(args.hang_seconds, exit=True)
            if args.alloc_limit > 0:
                base = tracemalloc.get_traced_memory()[0]
                tracemalloc.reset_peak()
            try:
                check(p, ev, kind, payload_only, counts)
                if args.cli_every and case % args.cli_every == 0:
                    check_cli(p, tmp)
            except Exception as exc:  # noqa: BLE001 - anything but FormatError, or a wrong result
                counts["crash"] += 1
                crashes.append((kind, case, "".join(traceback.format_exception_only(type(exc), exc)).strip()))
            faulthandler.cancel_dump_traceback_later()
            if args.alloc_limit > 0:
                size = p.stat().st_size
                peak = tracemalloc.get_traced_memory()[1] - base
                worst = max(worst, (peak / 2**20, f"{kind} case {case}, a {size:,}-byte file"))
                if peak > 16 * 2**20 + args.alloc_limit * size:
                    counts["crash"] += 1
                    crashes.append((kind, case, f"allocated {peak / 2**20:.1f} MiB for a {size}-byte file"))
            os.unlink(p)
    print(f"cases {args.cases} in {time.time() - t_start:.0f} s: {dict(counts)}")
    if args.alloc_limit > 0:
        print(f"largest traced allocation peak: {worst[0]:.1f} MiB ({worst[1]})")
    print(f"mutations: {dict(sorted(kinds.items()))}")
    for c in crashes[:20]:
        print("CRASH", c)
    return 1 if crashes else 0


if __name__ == "__main__":
    sys.exit(main())
