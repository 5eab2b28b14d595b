"""End-to-end reconstruction against a plain read of the same recording.

    python benchmarks/bench_reconstruct.py                  # >= 20 M events, 5 repeats
    python benchmarks/bench_reconstruct.py --events 2e6 --repeats 3

The recording is simulated once (paper configuration, signed 3x3 kernel and
16x16 features, default bench and sensor) with enough repeats to hold the
requested number of events, written as AEDAT4 with LZ4, and kept in
``benchmarks/data``. Timed in fresh processes after a warm-up on a small
recording: ``evtk.read_events`` (everything into memory) and
``evtk.reconstruct.reconstruct`` (schedule windows, streamed accumulation
over the response region with event times, linearisation, passes, 16x16,
sign), alternating so that the machine's slow and fast minutes hit both.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

from harness import child_runs

HERE = Path(__file__).resolve().parent
DATA = HERE / "data"


def _sim(n_captures_approx):
    import numpy as np

    from evtk.simulate import Simulation

    rng = np.random.default_rng(2024)
    k = rng.choice([-1, 1], (3, 3))
    f = rng.choice([-1, 1], (16, 16))
    return Simulation(k, f, repeat=max(1, n_captures_approx // 4), seed=1)


def make(n_events):
    path = DATA / f"sim_{n_events}.aedat4"
    if not path.exists():
        DATA.mkdir(exist_ok=True)
        per_capture = max(1, sum(len(e) for e in _sim(8).iter_events()) // 8)
        _sim(int(n_events / per_capture * 1.05) + 4).write(path)
    small = DATA / "sim_small.aedat4"
    if not small.exists():
        _sim(8).write(small)
    return path, small


def child(op, n_events):
    import evtk
    from evtk.reconstruct import reconstruct

    path, small = make(n_events)
    with evtk.open(small) as rec:
        reconstruct(rec)
    evtk.read_events(small)
    t0 = time.perf_counter()
    if op == "read":
        n = len(evtk.read_events(path))
    else:
        with evtk.open(path) as rec:
            r = reconstruct(rec)
            n = r.summary["events_used"]
    print(json.dumps({"seconds": time.perf_counter() - t0, "n": n}))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--events", type=float, default=20e6)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--child", help=argparse.SUPPRESS)
    a = ap.parse_args()
    n = int(a.events)
    if a.child:
        child(a.child, n)
        return
    path, _ = make(n)
    # read and reconstruct alternate, so that a slow minute of the machine hits both
    runs = {"read": [], "reconstruct": []}
    for _ in range(a.repeats):
        for op in runs:
            runs[op].append(child_runs(__file__, [op, "--events", n], 1)[0]["seconds"])
    ratios = [r / q for r, q in zip(runs["reconstruct"], runs["read"])]
    import evtk

    with evtk.open(path) as rec:
        total = rec.info()["events"]
    print(f"\n{path.name}: {total:,} events (LZ4 AEDAT4), median of {a.repeats} fresh processes, alternating\n")
    print("| operation | seconds | x read (median of the pairs' ratios) |")
    print("|---|---:|---:|")
    print(f"| read | {statistics.median(runs['read']):.3f} | 1.00 |")
    print(f"| reconstruct | {statistics.median(runs['reconstruct']):.3f} | {statistics.median(ratios):.2f} |")


if __name__ == "__main__":
    main()
