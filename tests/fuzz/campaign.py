"""Mutation campaign over valid AEDAT4, HDF5 and Parquet files.

    python tests/fuzz/campaign.py --cases 3000 --seed 1

Every outcome must be a read, an evtk.FormatError, or (salvage) a prefix
of the file's events, which info() must describe without failing and
scan() count exactly; anything else is reported as a crash with the seed
that reproduces it.  A truncated file must salvage to an exact prefix of
the original events (nothing before the cut was touched): a different
result is a crash too.  For the other mutations the salvaged events are
counted as an exact prefix or as altered (a flipped bit inside a payload
without a checksum reads back flipped).  Not collected by pytest (no
test_ prefix).
"""

from __future__ import annotations

import argparse
import collections
import faulthandler
import os
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


def sources(tmp: Path):
    ev = random_events(5000, seed=3, span_us=50_000)
    tr = evtk.Triggers([10, 20_000], [1, 2])
    out = {}
    for name, kw in (("a.aedat4", dict(packet_events=500, packet_us=None)),
                     ("z.aedat4", dict(compression="zstd", packet_events=700)),
                     ("n.aedat4", dict(compression="none", packet_events=900)), ("e.h5", dict(chunk_events=1024)),
                     ("p.parquet", dict(row_group_events=1000))):
        p = tmp / name
        evtk.write_events(p, ev, tr, **kw)
        out[name] = p
    # a foreign layout compressed with Blosc (v1), as DSEC ships it: c-blosc 1 trusts its chunks
    from test_hdf5_parquet import make_dsec

    dsec = random_events(5000, seed=4, sensor_size=(640, 480), span_us=50_000, t0=1000)
    make_dsec(tmp / "d.h5", dsec, t_offset=500)
    out["d.h5"] = tmp / "d.h5"
    fixtures = HERE.parent.parent / "fixtures"
    for f in fixtures.glob("*.aedat4"):
        out[f.name] = f
    # the formats evtk reads but does not write, as their own tools write them (faery) or as jAER and cAER
    # lay them out (the legacy AEDAT writers of the tests)
    try:
        import faery  # noqa: F401  (the writers below need it)
        from test_prophesee import _faery_write

        for version, name in (("evt2", "f2.raw"), ("evt3", "f3.raw"), ("dat2", "f.dat"), (None, "f.es")):
            _faery_write(tmp / name, ev, version)
            out[name] = tmp / name
    except ImportError:  # pragma: no cover - faery is in the test extra
        pass
    from test_aedat_legacy import write_aedat2_davis, write_aedat31

    big = evtk.Events(ev.t, ev.x, ev.y, ev.p, (346, 260))
    write_aedat2_davis(tmp / "l2.aedat", big, 260)
    write_aedat31(tmp / "l3.aedat", big, packet=700)
    out["l2.aedat"], out["l3.aedat"] = tmp / "l2.aedat", tmp / "l3.aedat"
    return out


def mutate(data: bytearray, rng):
    """A mutated copy and the mutation's kind."""
    kind = int(rng.integers(0, 5))
    if kind == 0:  # bit flips
        for _ in range(int(rng.integers(1, 8))):
            i = int(rng.integers(0, len(data)))
            data[i] ^= 1 << int(rng.integers(0, 8))
    elif kind == 1:  # truncation
        data = data[: int(rng.integers(0, len(data)))]
    elif kind == 2:  # a size-like field that lies
        i = int(rng.integers(0, max(1, len(data) - 4)))
        data[i : i + 4] = int(rng.choice([0, 1, 2**31 - 1, 2**32 - 1, len(data), 0x7FFF0000])).to_bytes(4, "little")
    elif kind == 3:  # duplicated span
        a = int(rng.integers(0, len(data)))
        b = min(len(data), a + int(rng.integers(1, 4096)))
        data = data[:b] + data[a:b] + data[b:]
    else:  # zeroed span
        a = int(rng.integers(0, len(data)))
        data[a : a + int(rng.integers(1, 512))] = bytes(min(len(data) - a, 512))[: len(data[a : a + 512])]
    return data, KINDS[kind]


KINDS = ["bitflip", "truncation", "size_field", "duplicate", "zeroed"]


def _is_prefix(got, reference) -> bool:
    n = len(got)
    return n <= len(reference) and all(np.array_equal(getattr(got, c), getattr(reference, c)[:n]) for c in "txyp")


def run_case(path: Path, reference, kind):
    outcome = "read"
    try:
        with evtk.open(path) as rec:
            rec.info()
            rec.events()
            rec.events(1000, 2000)
            rec.triggers()
            sum(len(c) for c in rec.iter_events(chunk_events=700))
    except evtk.FormatError:
        outcome = "format_error"
    try:
        with evtk.open(path, salvage=True) as rec:
            got = rec.events()
        with evtk.open(path, salvage=True) as rec:  # scan() streams through iter_events
            rec.info()
            scanned = rec.scan(chunk_events=700)["events"]
        if scanned != len(got):
            raise AssertionError(f"salvage: iter_events (scan) gave {scanned} events, events() {len(got)}")
        if outcome != "read" and len(got):
            exact = _is_prefix(got, reference)
            if kind == "truncation" and not exact:
                raise AssertionError(f"salvage of a truncated file returned {len(got)} events that are not a prefix")
            outcome += "+salvaged" if exact else "+salvaged_altered"
    except evtk.FormatError:
        pass
    return outcome


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--cases", type=int, default=2000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--hang-seconds", type=float, default=20.0)
    ap.add_argument("--alloc-limit", type=float, default=64.0,
                    help="a case whose traced allocations (Python objects and NumPy arrays, through tracemalloc) "
                         "peak above 16 MiB + this many times the file's size is a crash; 0 turns tracing off")
    args = ap.parse_args(argv)
    if args.alloc_limit > 0:
        import tracemalloc

        tracemalloc.start()
    worst_alloc = (0.0, None)
    counts = collections.Counter()
    crashes = []
    slow = 0
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        srcs = sources(tmp)
        refs = {name: evtk.read_events(p) for name, p in srcs.items()}
        names = sorted(srcs)
        t_start = time.time()
        for case in range(args.cases):
            rng = np.random.default_rng([args.seed, case])
            name = names[case % len(names)]
            data, kind = mutate(bytearray(srcs[name].read_bytes()), rng)
            p = tmp / ("m" + Path(name).suffix)
            p.write_bytes(bytes(data))
            t0 = time.time()
            # a case stuck inside a C library cannot be interrupted: dump the
            # stacks and stop the campaign, naming the case
            sys.stderr.write(f"\rcase {case} {name}   ")
            faulthandler.dump_traceback_later(args.hang_seconds, exit=True)
            if args.alloc_limit > 0:
                base = tracemalloc.get_traced_memory()[0]
                tracemalloc.reset_peak()
            try:
                counts[run_case(p, refs[name], kind)] += 1
            except Exception as exc:  # a crash: anything but FormatError
                counts["crash"] += 1
                crashes.append((name, case, "".join(traceback.format_exception_only(type(exc), exc)).strip()))
            faulthandler.cancel_dump_traceback_later()
            if args.alloc_limit > 0:
                peak = tracemalloc.get_traced_memory()[1] - base
                worst_alloc = max(worst_alloc, (peak / 2**20, f"{name} case {case}, a {len(data):,}-byte file"))
                if peak > 16 * 2**20 + args.alloc_limit * len(data):
                    counts["crash"] += 1
                    crashes.append((name, case, f"allocated {peak / 2**20:.1f} MiB for a {len(data)}-byte file"))
            if time.time() - t0 > 1.0:
                slow += 1
            os.unlink(p)
    print(f"cases {args.cases} in {time.time() - t_start:.0f} s: {dict(counts)}; slower than 1 s: {slow}")
    if args.alloc_limit > 0:
        print(f"largest traced allocation peak: {worst_alloc[0]:.1f} MiB ({worst_alloc[1]})")
    for c in crashes[:20]:
        print("CRASH", c)
    return 1 if crashes else 0


if __name__ == "__main__":
    sys.exit(main())
