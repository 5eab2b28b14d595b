"""HDF5 and Parquet: evtk side by side with plain h5py and pyarrow.

    python benchmarks/bench_hdf5.py                  # 20 M events over 10 s, 5 repeats
    python benchmarks/bench_hdf5.py --events 2e6 --repeats 3

For each HDF5 filter: write throughput, file size, full-read throughput and
the time to read a 10 ms window (evtk through its block index) against
reading everything; the same columns read with plain h5py (``f[name][...]``)
as the baseline.  Parquet through evtk against ``pyarrow.parquet.read_table``.
Each measurement runs in a fresh subprocess after a small warm-up; medians.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
DATA = HERE / "data"
sys.path.insert(0, str(HERE))
from bench_aedat4 import make_events  # noqa: E402
from harness import child_runs  # noqa: E402

H5_FILTERS = ("lz4", "zstd", "gzip", "none")
WINDOW_US = 10_000


def path_for(n, kind, comp):
    return DATA / f"bench_{n}_{comp}.{'h5' if kind == 'hdf5' else 'parquet'}"


def _window(n):
    mid = n // 4  # make_events spreads n events over n/2 us
    return mid, mid + WINDOW_US


def child(op, tool, kind, n, comp):
    import evtk

    src = path_for(n, kind, comp)
    lo, hi = _window(n)
    # warm up imports, numba caches and HDF5 filters on a small file
    warm = DATA / f"warm.{'h5' if kind == 'hdf5' else 'parquet'}"
    if tool == "evtk":
        evtk.read_events(warm)
    t0 = time.perf_counter()
    if op == "write":
        events = evtk.read_events(DATA / f"bench_{n}_lz4.aedat4")
        out = DATA / f"out.{'h5' if kind == 'hdf5' else 'parquet'}"
        t0 = time.perf_counter()
        evtk.write_events(out, events, compression=comp)
        seconds = time.perf_counter() - t0
        size = os.path.getsize(out)
        os.unlink(out)
        count = n
    elif tool == "evtk":
        rec = evtk.open(src)
        opened = time.perf_counter()
        ev = rec.events(lo, hi) if op == "window" else rec.events()
        done = time.perf_counter()
        rec.close()
        seconds = time.perf_counter() - t0
        count = len(ev)
        size = os.path.getsize(src)
        print(json.dumps({"seconds": seconds, "open_s": opened - t0, "read_s": done - opened, "count": count,
                          "bytes": size, "rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
        return
    elif tool == "h5py":
        import h5py
        import hdf5plugin  # noqa: F401

        with h5py.File(src, "r") as f:
            cols = [f["events"][c][...] for c in "txyp"]
        seconds = time.perf_counter() - t0
        count = len(cols[0])
        size = os.path.getsize(src)
    elif tool == "pyarrow":
        import pyarrow.parquet as pq

        if op == "window":
            table = pq.read_table(src, filters=[("t", ">=", lo), ("t", "<", hi)])
        else:
            table = pq.read_table(src)
        cols = [table.column(c).to_numpy() for c in "txyp"]
        seconds = time.perf_counter() - t0
        count = len(cols[0])
        size = os.path.getsize(src)
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(json.dumps({"seconds": seconds, "count": count, "bytes": size, "rss_mib": rss}))


def run(op, tool, kind, n, comp, repeats):
    runs = child_runs(__file__, [op, tool, kind, n, comp], repeats)
    med = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
    return med


def ensure(n):
    import evtk

    DATA.mkdir(exist_ok=True)
    src = DATA / f"bench_{n}_lz4.aedat4"
    events = None
    if not src.exists():
        events = make_events(n)
        evtk.write_events(src, events)
    small = make_events(10_000, seed=2)
    evtk.write_events(DATA / "warm.h5", small)
    evtk.write_events(DATA / "warm.parquet", small)
    for kind, comps in (("hdf5", H5_FILTERS), ("parquet", ("lz4", "zstd", "none"))):
        for comp in comps:
            p = path_for(n, kind, comp)
            if not p.exists():
                if events is None:
                    events = evtk.read_events(src)
                evtk.write_events(p, events, compression=comp)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--events", type=float, default=20e6)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--json", dest="json_out")
    ap.add_argument("--child", nargs=5, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        op, tool, kind, n, comp = args.child
        child(op, tool, kind, int(n), comp)
        return
    n = int(args.events)
    ensure(n)
    rows = []
    for kind, comps, peer in (("hdf5", H5_FILTERS, "h5py"), ("parquet", ("lz4", "zstd", "none"), "pyarrow")):
        for comp in comps:
            full = run("read", "evtk", kind, n, comp, args.repeats)
            base = run("read", peer, kind, n, comp, args.repeats)
            win = run("window", "evtk", kind, n, comp, args.repeats)
            pwin = run("window", peer, kind, n, comp, args.repeats) if peer == "pyarrow" else None
            wr = run("write", "evtk", kind, n, comp, args.repeats)
            rows.append({
                "format": kind, "compression": comp, "bytes_per_event": full["bytes"] / n,
                "write_mev_s": n / wr["seconds"] / 1e6,
                "read_mev_s": n / full["seconds"] / 1e6, "read_rss_mib": full["rss_mib"],
                "peer": peer, "peer_read_mev_s": n / base["seconds"] / 1e6,
                "open_ms": full["open_s"] * 1e3,
                "window_ms": win["read_s"] * 1e3, "window_events": win["count"],
                "window_share_of_full_read": win["read_s"] / full["read_s"],
                "peer_window_ms": pwin["seconds"] * 1e3 if pwin else None,
            })
    print(f"\n{n:,} events over {n / 2e6:.0f} s, 320x240; median of {args.repeats} runs in fresh processes\n")
    print("Read times include opening the file (as the peer's do); the window is read from an")
    print("open recording and compared with a full read from an open recording.\n")
    print("| format | compression | bytes/event | write M ev/s | read M ev/s (evtk) | read M ev/s (peer) | open (ms) "
          "| 10 ms window (ms) | window / full read |")
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        peer = f"{r['peer_read_mev_s']:.0f} ({r['peer']})"
        print(f"| {r['format']} | {r['compression']} | {r['bytes_per_event']:.2f} | {r['write_mev_s']:.0f} | "
              f"{r['read_mev_s']:.0f} | {peer} | {r['open_ms']:.2f} | {r['window_ms']:.2f} | "
              f"{100 * r['window_share_of_full_read']:.2f} % |")
    if args.json_out:
        Path(args.json_out).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
