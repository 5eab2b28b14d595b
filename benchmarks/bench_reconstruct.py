"""End-to-end reconstruction against a plain read of the same recording.

    python benchmarks/bench_reconstruct.py                  # >= 20 M events, 5 repeats
    python benchmarks/bench_reconstruct.py --events 2e6 --repeats 3
    python benchmarks/bench_reconstruct.py --fixed          # windows without a schedule, whole processes

``--fixed``: ``reconstruct(rec, window=("period", 10000))`` on bench_aedat4's uniform
recording (320x240, 2 M events/s: 1000 windows for 20 M events, no
simulation record), keeping every window's pixels (the default) and keeping
the responses only (``keep_pixels=False``), against a plain read; each timed
as a whole process (start Python, import, work, exit), alternating, medians
and the median of the per-round ratios, with each process's peak RSS; also
``evtk reconstruct -o`` (the responses alone; with ``--counts``: net counts; with ``--keep-pixels``: every
window's pixels too) and ``evtk enob`` on the same file, and the machine's load average (other work on it
skews every figure). ``--file F`` measures a given recording instead (bench_fresh_read's dv-processing file,
say); ``--ops "a;b"`` picks the operations. ``--baseline DIR``
runs every operation also with another evtk tree first on the path
(``git archive COMMIT | tar -x -C DIR``), alternating with this one.

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

from harness import child_runs, whole_process

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


def _fixed_file(n_events):
    import sys

    sys.path.insert(0, str(HERE))
    path = DATA / f"uniform_{n_events}.aedat4"
    if not path.exists():
        from bench_aedat4 import make_events

        import evtk

        DATA.mkdir(exist_ok=True)
        evtk.write_events(path, make_events(n_events))
    return path


_FIXED = {
    "read": ["-c", "import evtk; evtk.read_events({p!r})"],
    "reconstruct, pixels kept": ["-c", "import evtk; from evtk.reconstruct import reconstruct\n"
                                 "with evtk.open({p!r}) as r: reconstruct(r, window=('period', 10000))"],
    "reconstruct, responses only": ["-c", "import evtk; from evtk.reconstruct import reconstruct\n"
                                    "with evtk.open({p!r}) as r: reconstruct(r, window=('period', 10000), keep_pixels=False)"],
    "evtk reconstruct -o x.npz": ["-m", "evtk.cli", "reconstruct", "{p}", "--window", "period:10000", "-o", "{out}"],
    "evtk reconstruct --counts -o x.npz": ["-m", "evtk.cli", "reconstruct", "{p}", "--window", "period:10000",
                                           "--counts", "-o", "{out}"],
    "evtk reconstruct --keep-pixels -o x.npz": ["-m", "evtk.cli", "reconstruct", "{p}", "--window", "period:10000",
                                                "--keep-pixels", "-o", "{out}"],
    "evtk enob": ["-m", "evtk.cli", "enob", "{p}", "--window", "period:10000"],
}


def fixed(n, repeats, ops, baseline=None, file=None):
    import os
    import tempfile

    path = Path(file).resolve() if file else _fixed_file(n)
    trees = {"": HERE.parent}
    if baseline:
        trees["base: "] = Path(baseline).resolve()
    plan = [(label + op, [a.format(p=str(path), out=str(Path(tempfile.gettempdir()) / "bench_rec.npz"))
                          for a in _FIXED[op]], tree) for op in ops for label, tree in trees.items()]
    plan.insert(0, ("read", [a.format(p=str(path)) for a in _FIXED["read"]], HERE.parent))
    for _, args, tree in plan:  # untimed: page cache, numba's cache
        whole_process(args, tree)
    runs: dict = {name: [] for name, _, _ in plan}
    rss: dict = {name: [] for name, _, _ in plan}
    for r in range(repeats):  # alternating, so that a slow minute hits every one; every other round reversed,
        for name, args, tree in (plan if r % 2 == 0 else plan[::-1]):  # so that no one always follows another
            wall, peak, _ = whole_process(args, tree)
            runs[name].append(wall)
            rss[name].append(peak)
    load = " ".join(f"{v:.2f}" for v in os.getloadavg())
    print(f"\n{path.name}: --window period:10000, whole processes, median of {repeats}, alternating; "
          f"{os.cpu_count()} CPUs, load average {load} (1, 5, 15 min) at the end\n")
    print("| operation | seconds | x read (median of the rounds' ratios) | peak RSS (MB) |")
    print("|---|---:|---:|---:|")
    for name in runs:
        ratio = statistics.median(a / b for a, b in zip(runs[name], runs["read"]))
        print(f"| {name} | {statistics.median(runs[name]):.3f} | {ratio:.2f} | {max(rss[name]):.0f} |")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--events", type=float, default=20e6)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--fixed", action="store_true", help="windows without a schedule (see above)")
    ap.add_argument("--ops", default=";".join(list(_FIXED)[1:]), help="--fixed: which operations, separated by ;")
    ap.add_argument("--baseline", help="--fixed: another evtk tree (git archive of a commit) to run alternately")
    ap.add_argument("--file", help="--fixed: this recording instead of the generated one (e.g. bench_fresh_read's "
                                   "dv-processing file)")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    a = ap.parse_args()
    n = int(a.events)
    if a.fixed:
        fixed(n, a.repeats, [op for op in a.ops.split(";") if op != "read"], a.baseline, a.file)
        return
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
