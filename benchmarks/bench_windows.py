"""AEDAT4 time windows against a whole read of the same file: wall and CPU time, medians of 5.

    python benchmarks/bench_windows.py                        # benchmarks/data/fresh_20000000_dv-lz4.aedat4
    python benchmarks/bench_windows.py --file F.aedat4
    PYTHONPATH=/tmp/old python benchmarks/bench_windows.py    # an older checkout, to alternate with

Timed in one process after a warm-up: the whole read (`iter_events`, 4 M-event chunks); a fresh
`evtk.open` and one window of 1 % of the file (the first window of a recording scans every packet's stamps
once); a fresh open and a window over the whole span; twenty windows covering the file and the middle half,
on a recording that has scanned its packets. Each is given as a multiple of the whole read (wall, and the
process's CPU time, steadier on a loaded machine).
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np


def timed(fn, runs):
    """Median wall and CPU seconds of ``fn`` over ``runs`` calls, after one."""
    fn()
    wall, cpu = [], []
    for _ in range(runs):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return statistics.median(wall), statistics.median(cpu)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--file", default="benchmarks/data/fresh_20000000_dv-lz4.aedat4")
    ap.add_argument("--runs", type=int, default=5)
    args = ap.parse_args()
    import evtk

    path, runs = args.file, args.runs

    def count(rec, lo=None, hi=None):
        return sum(len(c) for c in rec.iter_events(chunk_events=4_000_000, t_start_us=lo, t_end_us=hi))

    def fresh(lo, hi):
        def read():
            with evtk.open(path) as r:
                return count(r, lo, hi)
        return read

    res = {}
    with evtk.open(path) as rec:
        info = rec.info()
        a, z = int(info["t_start_us"]), int(info["t_end_us"]) + 1
        res["whole read"] = timed(lambda: count(rec), runs)
        mid = a + (z - a) // 2
        res["open + 1 % window"] = timed(fresh(mid, mid + (z - a) // 100), runs)
        res["open + whole-span window"] = timed(fresh(a, z), runs)
        edges = np.linspace(a, z, 21).astype(np.int64).tolist()
        res["20 windows"] = timed(lambda: sum(count(rec, lo, hi) for lo, hi in zip(edges[:-1], edges[1:])), runs)
        res["middle half"] = timed(lambda: count(rec, a + (z - a) // 4, a + 3 * (z - a) // 4), runs)
    w0, c0 = res["whole read"]
    print(f"{info['events']:,} events, {evtk.__file__}")
    for name, (w, c) in res.items():
        print(f"  {name:26s} {w * 1e3:7.0f} ms  {w / w0:5.2f}x   cpu {c * 1e3:6.0f} ms  {c / c0:5.2f}x")


if __name__ == "__main__":
    main()
