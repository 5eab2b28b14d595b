"""AEDAT4 read and write throughput: evtk side by side with dv-processing, aedat and faery.

    python benchmarks/bench_aedat4.py                 # 20 M events, 5 repeats
    python benchmarks/bench_aedat4.py --events 2e6 --repeats 3

Every measurement runs in a fresh subprocess (so peak memory is that of the
one operation, and no tool profits from another's warm caches beyond the
shared page cache), repeats ``--repeats`` times, and reports the median time,
the throughput, the child's peak RSS and the ratio to evtk.  Files are made
once in ``benchmarks/data/`` (written by evtk, checked by dv-processing).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from harness import child_runs

HERE = Path(__file__).resolve().parent
DATA = HERE / "data"
COMPRESSIONS = ("lz4", "zstd", "none")


def make_events(n: int, seed: int = 1):
    """Sorted uniform events on a 320x240 sensor at 2 M events/s."""
    import evtk

    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(0, int(n / 2), n)).astype(np.int64)
    x = rng.integers(0, 320, n, dtype=np.uint16)
    y = rng.integers(0, 240, n, dtype=np.uint16)
    p = rng.integers(0, 2, n, dtype=np.uint8)
    return evtk.Events(t, x, y, p, (320, 240))


def data_file(n: int, compression: str) -> Path:
    return DATA / f"bench_{n}_{compression}.aedat4"


# -- single operations (run inside the child process) -------------------------------

def read_evtk(path):
    import evtk

    return len(evtk.read_events(path))


def read_dv(path):
    import dv_processing as dv

    rec = dv.io.MonoCameraRecording(str(path))
    parts = []
    while True:
        batch = rec.getNextEventBatch()
        if batch is None:
            break
        parts.append(batch.numpy())
    return len(np.concatenate(parts))


def read_aedat(path):
    import aedat

    parts = [packet["events"] for packet in aedat.Decoder(str(path)) if "events" in packet]
    return len(np.concatenate(parts))


def read_faery(path):
    import faery

    return len(faery.events_stream_from_file(path, t0=faery.Time(microseconds=0)).to_array())


def write_evtk(events, path, compression):
    import evtk

    evtk.write_events(path, events, compression=compression)


def write_faery(events, path, compression):
    import faery

    array = events.to_structured("faery")
    comp = None if compression == "none" else (compression, 1)
    faery.events_stream_from_array(array, dimensions=events.sensor_size).to_file(
        path, compression=comp, zero_t0=False
    )


READERS = {"evtk": read_evtk, "dv-processing": read_dv, "aedat": read_aedat, "faery": read_faery}
WRITERS = {"evtk": write_evtk, "faery": write_faery}


def child(op: str, tool: str, n: int, compression: str) -> None:
    src = data_file(n, compression)
    # warm up the tool on a small file first: imports, JIT caches and thread
    # pools are paid once per process and are not what is measured here
    warm = DATA / f"warm_{compression}.aedat4"
    READERS[tool](warm) if op == "read" else WRITERS[tool](_small_events(), DATA / f"warm_{tool}.aedat4", compression)
    if op == "read":
        t0 = time.perf_counter()
        count = READERS[tool](src)
        seconds = time.perf_counter() - t0
        if count != n:
            raise SystemExit(f"{tool} read {count} events, expected {n}")
    else:
        import evtk

        events = evtk.read_events(data_file(n, "lz4"))
        out = DATA / f"out_{tool}_{compression}.aedat4"
        t0 = time.perf_counter()
        WRITERS[tool](events, out, compression)
        seconds = time.perf_counter() - t0
        os.unlink(out)
    rss_kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    print(json.dumps({"seconds": seconds, "rss_mib": rss_kib / 1024}))


def _small_events():
    return make_events(10_000, seed=2)


def run_child(op, tool, n, compression):
    return child_runs(__file__, [op, tool, n, compression])[0]


def ensure_data(n: int) -> None:
    DATA.mkdir(exist_ok=True)
    import evtk

    for c in COMPRESSIONS:
        warm = DATA / f"warm_{c}.aedat4"
        if not warm.exists():
            evtk.write_events(warm, _small_events(), compression=c)
    missing = [c for c in COMPRESSIONS if not data_file(n, c).exists()]
    if not missing:
        return
    events = make_events(n)
    for c in missing:
        evtk.write_events(data_file(n, c), events, compression=c)
        print(f"made {data_file(n, c)}", file=sys.stderr)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--events", type=float, default=20e6)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--json", dest="json_out", help="also write the results here")
    ap.add_argument("--child", nargs=4, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        op, tool, n, compression = args.child
        child(op, tool, int(n), compression)
        return
    n = int(args.events)
    ensure_data(n)
    run_child("read", "evtk", n, "lz4")  # warm numba's cache and the page cache
    rows = []
    for op, tools in (("read", READERS), ("write", WRITERS)):
        for compression in COMPRESSIONS:
            results = {}
            for tool in tools:
                runs = []
                try:
                    for _ in range(args.repeats):
                        runs.append(run_child(op, tool, n, compression))
                except subprocess.CalledProcessError as exc:
                    print(f"{tool} {op} {compression} failed: {exc.stderr.strip()[-300:]}", file=sys.stderr)
                    continue
                results[tool] = {
                    "seconds": statistics.median(r["seconds"] for r in runs),
                    "rss_mib": statistics.median(r["rss_mib"] for r in runs),
                }
            base = results.get("evtk")
            for tool, r in results.items():
                rows.append({
                    "op": op, "compression": compression, "tool": tool,
                    "seconds": r["seconds"], "mev_per_s": n / r["seconds"] / 1e6, "rss_mib": r["rss_mib"],
                    "evtk_speedup": (r["seconds"] / base["seconds"]) if base else None,
                })
    print(f"\n{n:,} events, 320x240, median of {args.repeats} runs, each in a fresh process\n")
    print("| op | compression | tool | time (s) | M events/s | peak RSS (MiB) | evtk speed-up |")
    print("|---|---|---|---:|---:|---:|---:|")
    for r in rows:
        print(
            f"| {r['op']} | {r['compression']} | {r['tool']} | {r['seconds']:.3f} | {r['mev_per_s']:.1f} | "
            f"{r['rss_mib']:.0f} | {r['evtk_speedup']:.2f}x |"
        )
    if args.json_out:
        Path(args.json_out).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
