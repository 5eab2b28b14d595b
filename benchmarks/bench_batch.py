"""Batch reconstruction serially and on local Dask clusters of one and two workers.

    python benchmarks/bench_batch.py                  # 20 recordings of about 1 M events, 3 rounds
    python benchmarks/bench_batch.py --recordings 8 --repeats 1 --rounds 1

The recordings are simulated once (signed random 3x3 kernel and 16x16
features, default bench and sensor, AEDAT4 LZ4) into ``benchmarks/data/batch``.
Each mode runs, in a fresh process of its own, ``evtk.batch.batch_reconstruct``
over all of them with ``force=True`` into a fresh folder; the cluster is started before the clock
and its start-up is reported apart. The four modes run one after the other in each of
``--rounds`` rounds, and the ratios are the medians of each round's ratios (the same
mode varies by a fifth from one minute to the next on a shared 2-core machine). The
per-recording overhead is ``(local:1 - serial) / recordings``.

Serial mode already uses both cores of a 2-core machine (evtk decodes
packets and solves the event-time fits on threads), so it also runs once
on one thread (``serial/1``): two workers can at best halve that, and
``N x serial / serial/1`` is the most ``local:N`` can gain over serial here (``--workers N``, 2 by default).
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


def make_one(i: int) -> str:
    """Recording ``i`` (simulated once; ``benchmarks/device_run.sh`` makes them in parallel processes)."""
    import numpy as np

    from evtk.simulate import Simulation

    DATA.mkdir(parents=True, exist_ok=True)
    path = DATA / f"rec{i:02d}.aedat4"
    if not path.exists():
        rng = np.random.default_rng(100 + i)
        Simulation(rng.choice([-1, 1], (3, 3)), rng.choice([-1, 1], (16, 16)), repeat=25, seed=i).write(path)
    return str(path)


def make(n):
    return [make_one(i) for i in range(n)]


def child(spec, n_recordings, repeats, fmt="h5"):
    """One mode in this (fresh) process: warm up, then time ``repeats`` batches; prints a JSON line."""
    from evtk.batch import batch_reconstruct
    from evtk.cluster import scheduler

    files = make(n_recordings)
    batch_reconstruct(files[:1], tempfile.mkdtemp(), fmt=fmt, force=True)  # warm this process's JIT caches
    t0 = time.perf_counter()
    with scheduler(spec) as client:
        start = time.perf_counter() - t0
        if client is not None:
            batch_reconstruct(files[:2], tempfile.mkdtemp(), fmt=fmt, client=client, force=True)  # warm the workers
        times, task_max, task_sum = [], [], []
        for _ in range(repeats):
            with tempfile.TemporaryDirectory() as out:
                t = time.perf_counter()
                m = batch_reconstruct(files, out, fmt=fmt, client=client, force=True)
                times.append(time.perf_counter() - t)
                secs = [e["seconds"] or 0.0 for e in m["inputs"]]
                task_max.append(max(secs))
                task_sum.append(sum(secs))
                if m["counts"]["ok"] != len(files):
                    raise SystemExit(f"not every recording was reconstructed: {m['counts']}, first error: "
                                     f"{next(e['error'] for e in m['inputs'] if e['status'] == 'error')}")
    # each recording's own seconds (its task's work, as the manifest records it): the slowest against the
    # batch's wall time shows what the scheduler and the waiting cost beyond the work
    print(json.dumps({"median_s": statistics.median(times), "start_s": start,
                      "task_max_s": statistics.median(task_max), "task_sum_s": statistics.median(task_sum)}))


def modes(workers: int):
    """(label, scheduler spec, one thread) of each mode: serial, serial on one thread, local:1 and local:N."""
    return (("serial", "serial", False), ("serial/1", "serial", True), ("local:1", "local:1", False),
            (f"local:{workers}", f"local:{workers}", False))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--recordings", type=int, default=20)
    ap.add_argument("--repeats", type=int, default=3, help="batches timed per mode and round (median)")
    ap.add_argument("--rounds", type=int, default=3, help="rounds of all four modes, one after the other")
    ap.add_argument("--fmt", default="h5", help="output format (npz where hdf5plugin is not installed)")
    ap.add_argument("--workers", type=int, default=2, help="N of the local:N mode (N workers, one thread each)")
    ap.add_argument("--json")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(args.child, args.recordings, args.repeats, args.fmt)
        return
    import evtk

    files = make(args.recordings)
    with evtk.open(files[0]) as rec:
        events = rec.info()["events"]
    res = {"recordings": len(files), "events_per_recording": events, "rounds": []}
    print(f"{len(files)} recordings of {events:,} events; seconds per batch (median of {args.repeats})")
    mode_list = modes(args.workers)
    big = f"local:{args.workers}"
    print("round   " + "".join(f"{label:>10s}" for label, _, _ in mode_list) + f"   {big}/serial  local:1/serial")
    for r in range(args.rounds):
        # each mode in a fresh process (no threads left over), the four modes side by side in time, so a
        # slow minute on a shared machine shows in all of a round's figures rather than in one mode's
        row = {}
        for label, spec, one in mode_list:
            row[label] = child_runs(__file__, [spec, "--recordings", args.recordings, "--repeats", args.repeats,
                                               "--fmt", args.fmt], single_thread=one)[0]
        res["rounds"].append(row)
        s, l1, l2 = (row[k]["median_s"] for k in ("serial", "local:1", big))
        print(f"{r + 1:5d}   " + "".join(f"{row[label]['median_s']:10.3f}" for label, _, _ in mode_list)
              + f"   {s / l2:13.2f}x  {l1 / s:14.2f}", flush=True)
    rounds = res["rounds"]

    def med(fn):
        return statistics.median(fn(row) for row in rounds)

    def t(row, k):
        return row[k]["median_s"]

    res["workers"] = args.workers
    res["speedup_local2"] = med(lambda r: t(r, "serial") / t(r, big))  # key kept for earlier results' readers
    res["speedup_local2_over_one_thread"] = med(lambda r: t(r, "serial/1") / t(r, big))
    res["ceiling_local2"] = med(lambda r: args.workers * t(r, "serial") / t(r, "serial/1"))
    res["local1_over_serial"] = med(lambda r: t(r, "local:1") / t(r, "serial"))
    res["overhead_ms_per_recording"] = med(lambda r: 1e3 * (t(r, "local:1") - t(r, "serial")) / len(files))
    res["cluster_start_s"] = med(lambda r: r[big]["start_s"])
    res["slowest_recording_s"] = {label: med(lambda r, k=label: r[k]["task_max_s"]) for label, _, _ in mode_list}
    res["recordings_sum_s"] = {label: med(lambda r, k=label: r[k]["task_sum_s"]) for label, _, _ in mode_list}
    print(f"medians over {len(rounds)} rounds: {big} is {res['speedup_local2']:.2f}x serial "
          f"({res['speedup_local2_over_one_thread']:.2f}x serial on one thread; at most "
          f"{res['ceiling_local2']:.2f}x serial on this machine); local:1 takes {res['local1_over_serial']:.2f}x "
          f"serial; overhead {res['overhead_ms_per_recording']:.1f} ms per recording; {big} starts in "
          f"{res['cluster_start_s']:.2f} s")
    print("the recordings' own seconds (manifest), per mode: slowest / sum: " + ", ".join(
        f"{k} {res['slowest_recording_s'][k] * 1e3:.0f} ms / {res['recordings_sum_s'][k]:.3f} s"
        for k in res["slowest_recording_s"]))
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(res, fh, indent=1)


if __name__ == "__main__":
    main()
