"""Reader speed on the files other tools write, side by side with the public reader of each format.

    python benchmarks/bench_formats.py                    # 4 M events, best of 3
    python benchmarks/bench_formats.py --events 1e6 --json benchmarks/results/formats.json

Files are written once into ``benchmarks/data/`` by their own tools: AEDAT4
by evtk, by dv-processing (MonoCameraWriter, LZ4 and ZSTD) and by faery (LZ4
with checksums, ZSTD); Prophesee EVT 2.0, EVT 3.0 and DAT and Event Stream by
faery; AEDAT 2.0 and 3.1 by evtk's test writers (jAER's and cAER's layouts;
no maintained tool writes them). Each reading runs in a fresh process (after
a warm-up read of the same file, so imports and numba's cache load are not
counted), best of ``--repeats``; the ratio is the peer's time over evtk's.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from harness import child_runs

HERE = Path(__file__).resolve().parent
DATA = HERE / "data"
sys.path.insert(0, str(HERE.parent / "tests"))


def events(n):
    from bench_aedat4 import make_events

    return make_events(n)


def _faery_array(ev):
    import faery

    a = np.zeros(len(ev), faery.EVENTS_DTYPE)
    a["t"], a["x"], a["y"], a["on"] = ev.t, ev.x, ev.y, ev.p.astype(bool)
    return a


def make(kind, path, n):
    """Write ``path`` with the tool named in ``kind``."""
    import evtk

    ev = events(n)
    if kind == "aedat4/evtk-lz4":
        evtk.write_events(path, ev, compression="lz4")
    elif kind == "aedat4/evtk-zstd":
        evtk.write_events(path, ev, compression="zstd")
    elif kind.startswith("aedat4/dv-"):
        import dv_processing as dv

        cfg = dv.io.MonoCameraWriter.EventOnlyConfig("DVXplorer_bench", tuple(ev.sensor_size))
        cfg.compression = getattr(dv.CompressionType, kind.split("-")[-1].upper())
        w = dv.io.MonoCameraWriter(str(path), cfg)
        for lo in range(0, n, 10_000):
            store = dv.EventStore()
            for t, x, y, p in zip(ev.t[lo:lo + 10_000].tolist(), ev.x[lo:lo + 10_000].tolist(),
                                  ev.y[lo:lo + 10_000].tolist(), ev.p[lo:lo + 10_000].tolist()):
                store.push_back(t, x, y, bool(p))
            w.writeEvents(store)
        del w
    elif kind.startswith("aedat4/faery-"):
        import faery

        comp = (kind.split("-")[-1], 1)
        faery.events_stream_from_array(_faery_array(ev), tuple(ev.sensor_size)).to_file(
            str(path), compression=comp, zero_t0=False)
    elif kind in ("evt2", "evt3", "dat"):
        import faery

        faery.events_stream_from_array(_faery_array(ev), tuple(ev.sensor_size)).to_file(
            str(path), version="dat2" if kind == "dat" else kind)
    elif kind == "es":
        import faery

        faery.events_stream_from_array(_faery_array(ev), tuple(ev.sensor_size)).to_file(str(path))
    elif kind == "aedat31":
        from test_aedat_legacy import write_aedat31

        write_aedat31(path, ev, packet=4096, other=False)
    elif kind == "aedat2":
        from test_aedat_legacy import write_aedat2_davis

        big = evtk.Events(ev.t, ev.x, ev.y, ev.p, (346, 260))
        write_aedat2_davis(path, big, 260)
    else:
        raise SystemExit(f"unknown kind {kind}")


FILES = {
    "aedat4/evtk-lz4": ".aedat4", "aedat4/evtk-zstd": ".aedat4", "aedat4/dv-lz4": ".aedat4",
    "aedat4/dv-zstd": ".aedat4", "aedat4/faery-lz4": ".aedat4", "aedat4/faery-zstd": ".aedat4",
    "evt2": ".raw", "evt3": ".raw", "dat": ".dat", "es": ".es", "aedat31": ".aedat", "aedat2": ".aedat",
}
PEERS = {
    "aedat4": ["dv-processing", "aedat", "faery"], "evt2": ["expelliarmus", "faery"],
    "evt3": ["expelliarmus", "faery"], "dat": ["expelliarmus", "faery"], "es": ["faery"],
    "aedat31": ["dv"], "aedat2": ["dv"],
}


def read(tool, path, kind):
    """Events read by ``tool`` (their count)."""
    if tool == "evtk":
        import evtk

        return len(evtk.read_events(path))
    if tool == "dv-processing":
        import dv_processing as dv

        rec = dv.io.MonoCameraRecording(str(path))
        parts = []
        while True:
            b = rec.getNextEventBatch()
            if b is None:
                break
            parts.append(b.numpy())
        return sum(len(p) for p in parts)
    if tool == "aedat":
        import aedat

        return sum(len(p["events"]) for p in aedat.Decoder(str(path)) if "events" in p)
    if tool == "faery":
        import faery

        return len(faery.events_stream_from_file(str(path)).to_array())
    if tool == "expelliarmus":
        import expelliarmus

        return len(expelliarmus.Wizard(encoding=kind).read(str(path)))
    if tool == "dv":
        import dv

        with dv.LegacyAedatFile(str(path)) as f:
            return sum(1 for _ in f)
    raise SystemExit(f"unknown tool {tool}")


def child(tool, path, kind):
    read(tool, path, kind)  # warm: imports, caches, page cache
    t0 = time.perf_counter()
    n = read(tool, path, kind)
    print(json.dumps({"seconds": time.perf_counter() - t0, "events": n}))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--events", type=float, default=4e6)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--legacy-events", type=float, default=2e5,
                    help="events in the AEDAT 2/3.1 files (dv's legacy reader yields one Python object an event)")
    ap.add_argument("--only", help="measure only the files whose kind starts with this (e.g. aedat4, evt)")
    ap.add_argument("--json", dest="json_out")
    ap.add_argument("--child", nargs=3, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        child(*args.child)
        return
    DATA.mkdir(exist_ok=True)
    rows = []
    for kind, ext in FILES.items():
        if args.only and not kind.startswith(args.only):
            continue
        n = int(args.legacy_events if kind.startswith("aedat2") or kind.startswith("aedat3") else args.events)
        path = DATA / f"fmt_{kind.replace('/', '_')}_{n}{ext}"
        if not path.exists():
            make(kind, path, n)
        fmt = kind.split("/")[0]
        times = {}
        for tool in ["evtk"] + PEERS[fmt]:
            try:
                runs = child_runs(__file__, [tool, path, fmt], repeats=args.repeats)
            except Exception as exc:  # noqa: BLE001 - a peer that cannot read the file is reported, not fatal
                print(f"{tool} on {kind}: {exc}", file=sys.stderr)
                continue
            if any(r["events"] != n for r in runs):
                print(f"{tool} on {kind}: read {runs[0]['events']} events of {n}", file=sys.stderr)
            times[tool] = min(r["seconds"] for r in runs)
        for tool, sec in times.items():
            rows.append({"file": kind, "tool": tool, "events": n, "seconds": sec, "mev_per_s": n / sec / 1e6,
                         "evtk_speedup": sec / times["evtk"] if "evtk" in times else None})
    print("\n| file (writer) | reader | M events/s | evtk speed-up |")
    print("|---|---|---:|---:|")
    for r in rows:
        print(f"| {r['file']} | {r['tool']} | {r['mev_per_s']:.1f} | {r['evtk_speedup']:.2f}x |")
    if args.json_out:
        Path(args.json_out).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
