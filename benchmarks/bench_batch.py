"""Batch reconstruction serially and on local Dask clusters of one and two workers.

    python benchmarks/bench_batch.py                  # 20 recordings of about 1 M events, median of 3
    python benchmarks/bench_batch.py --recordings 8 --repeats 1

The recordings are simulated once (signed random 3x3 kernel and 16x16
features, default bench and sensor, AEDAT4 LZ4) into ``benchmarks/data/batch``.
Each mode runs, in a fresh process of its own, ``evtk.batch.batch_reconstruct``
over all of them with ``force=True`` into a fresh folder; the cluster is started before the clock
and its start-up is reported apart. The per-task overhead is
``(local:1 - serial) / recordings``.

Serial mode already uses both cores of a 2-core machine (evtk decodes
packets and solves the event-time fits on threads), so it also runs once
on one thread (``serial/1``): two workers can at best halve that, and
``2 x serial / serial/1`` is the most ``local:2`` can gain over serial here.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
DATA = HERE / "data" / "batch"
sys.path.insert(0, str(HERE))
from harness import child_runs  # noqa: E402


def make(n):
    import numpy as np

    from evtk.simulate import Simulation

    DATA.mkdir(parents=True, exist_ok=True)
    files = []
    for i in range(n):
        path = DATA / f"rec{i:02d}.aedat4"
        if not path.exists():
            rng = np.random.default_rng(100 + i)
            Simulation(rng.choice([-1, 1], (3, 3)), rng.choice([-1, 1], (16, 16)), repeat=25, seed=i).write(path)
        files.append(str(path))
    return files


def child(spec, n_recordings, repeats):
    """One mode in this (fresh) process: warm up, then time ``repeats`` batches; prints a JSON line."""
    from evtk.batch import batch_reconstruct
    from evtk.cluster import scheduler

    files = make(n_recordings)
    batch_reconstruct(files[:1], tempfile.mkdtemp(), force=True)  # warm this process's JIT caches
    t0 = time.perf_counter()
    with scheduler(spec) as client:
        start = time.perf_counter() - t0
        if client is not None:
            batch_reconstruct(files[:2], tempfile.mkdtemp(), client=client, force=True)  # warm the workers
        times = []
        for _ in range(repeats):
            with tempfile.TemporaryDirectory() as out:
                t = time.perf_counter()
                m = batch_reconstruct(files, out, client=client, force=True)
                times.append(time.perf_counter() - t)
                assert m["counts"]["ok"] == len(files)
    print(json.dumps({"median_s": statistics.median(times), "start_s": start}))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--recordings", type=int, default=20)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(args.child, args.recordings, args.repeats)
        return
    import evtk

    files = make(args.recordings)
    with evtk.open(files[0]) as rec:
        events = rec.info()["events"]
    res = {"recordings": len(files), "events_per_recording": events}
    # each mode in a fresh process: no threads left over
    for label, spec, one in (("serial", "serial", False), ("serial/1", "serial", True), ("local:1", "local:1", False),
                             ("local:2", "local:2", False)):
        run = child_runs(__file__, [spec, "--recordings", args.recordings, "--repeats", args.repeats],
                         single_thread=one)[0]
        res[label] = run
        print(f"{label:8s} {run['median_s']:6.2f} s for {len(files)} recordings of {events:,} events "
              f"(cluster start {run['start_s']:.2f} s)", flush=True)
    s, s1, l1, l2 = (res[k]["median_s"] for k in ("serial", "serial/1", "local:1", "local:2"))
    res["speedup_local2"] = s / l2
    res["speedup_local2_over_one_thread"] = s1 / l2
    res["ceiling_local2"] = 2 * s / s1
    res["local1_over_serial"] = l1 / s
    res["overhead_ms_per_task"] = 1e3 * (l1 - s) / len(files)
    print(f"local:2 is {s / l2:.2f}x serial ({s1 / l2:.2f}x serial on one thread; at most {2 * s / s1:.2f}x "
          f"serial on this machine); local:1 takes {l1 / s:.2f}x serial; "
          f"overhead {res['overhead_ms_per_task']:.1f} ms per task")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(res, fh, indent=1)


if __name__ == "__main__":
    main()
