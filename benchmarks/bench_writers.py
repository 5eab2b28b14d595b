"""Writer speed for the formats other tools read, side by side with faery's writer of the same format.

    python benchmarks/bench_writers.py                      # 2 M events, medians of 5
    python benchmarks/bench_writers.py --events 2e7 --repeats 7 --formats evt3,csv

Each write runs in a fresh process, twice: ``fresh`` is the whole first write
(imports and any compilation included, as ``evtk convert`` or a one-off script
pays them), ``warm`` the second write of the same events in that process. The
events are made in the parent and handed over as a ``.npy`` file (loading it is
not timed). evtk's and faery's processes alternate (which goes first swaps
from one repeat to the next), so a load on a shared machine falls on both; the
figures are medians. The ratio is faery's median time over evtk's: above 1,
evtk is faster.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from harness import child_runs

HERE = Path(__file__).resolve().parent
FORMATS = {"evt2": (".raw", "evt2"), "evt3": (".raw", "evt3"), "dat": (".dat", "dat2"), "es": (".es", None),
           "csv": (".csv", None)}


def _child(tool, fmt, npy, out_dir):
    arr = np.load(npy)
    size = (1280, 720)
    ext, version = FORMATS[fmt]
    times = []
    for k in range(2):
        path = str(Path(out_dir) / f"w{k}{ext}")
        t0 = time.perf_counter()
        if tool == "evtk":
            import evtk

            ev = evtk.Events(arr["t"], arr["x"], arr["y"], arr["p"], size)
            evtk.write_events(path, ev, fmt=fmt)
        else:
            import faery

            a = np.zeros(len(arr), faery.EVENTS_DTYPE)
            a["t"], a["x"], a["y"], a["on"] = arr["t"], arr["x"], arr["y"], arr["p"].astype(bool)
            stream = faery.events_stream_from_array(a, size)
            stream.to_file(path, **({"version": version} if version else {}))
        times.append(time.perf_counter() - t0)
    print(json.dumps({"fresh_s": times[0], "warm_s": times[1]}))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--events", type=float, default=2e6)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--formats", default=",".join(FORMATS), help="comma-separated subset of " + ",".join(FORMATS))
    ap.add_argument("--child", nargs=4)
    args = ap.parse_args()
    if args.child:
        _child(*args.child)
        return
    formats = [f for f in args.formats.split(",") if f]
    unknown = sorted(set(formats) - set(FORMATS))
    if unknown:
        ap.error(f"unknown formats {unknown}")
    n = int(args.events)
    rng = np.random.default_rng(0)
    arr = np.zeros(n, [("t", "<i8"), ("x", "<u2"), ("y", "<u2"), ("p", "u1")])
    arr["t"] = np.sort(rng.integers(0, n // 2, n))  # 2 events a microsecond: a busy camera
    arr["x"], arr["y"], arr["p"] = rng.integers(0, 1280, n), rng.integers(0, 720, n), rng.integers(0, 2, n)
    with tempfile.TemporaryDirectory() as tmp:
        npy = str(Path(tmp) / "events.npy")
        np.save(npy, arr)
        print(f"{n:,} events, medians of {args.repeats} fresh processes each, evtk's and faery's alternating; "
              "ratio = faery / evtk")
        print(f"{'format':8} {'evtk fresh':>11} {'faery fresh':>12} {'ratio':>6} {'evtk warm':>10} {'faery warm':>11} "
              f"{'ratio':>6}")
        for fmt in formats:
            runs: dict[str, list[dict]] = {"evtk": [], "faery": []}
            for k in range(args.repeats):
                for tool in (("evtk", "faery") if k % 2 == 0 else ("faery", "evtk")):
                    runs[tool] += child_runs(__file__, [tool, fmt, npy, tmp])
            e, f = ((statistics.median(r["fresh_s"] for r in runs[tool]),
                     statistics.median(r["warm_s"] for r in runs[tool])) for tool in ("evtk", "faery"))
            print(f"{fmt:8} {e[0]:10.3f}s {f[0]:11.3f}s {f[0] / e[0]:6.2f} {e[1]:9.3f}s {f[1]:10.3f}s {f[1] / e[1]:6.2f}")
            sys.stdout.flush()

if __name__ == "__main__":
    main()
