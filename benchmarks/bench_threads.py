"""A warm full read on 1, 2, ... cores: how evtk's readers scale with the cores they are given.

    python benchmarks/bench_threads.py                         # AEDAT4 (dv-processing LZ4, evtk LZ4), 1 and 2 cores
    python benchmarks/bench_threads.py --cores 1,2,4,8,16 --rounds 5
    python benchmarks/bench_threads.py --formats aedat4-dv,evt3,hdf5,parquet

Each measurement is its own process pinned with ``taskset -c 0..k-1`` (evtk
then uses k threads: :func:`evtk._threads.workers` follows the affinity). In
the process one untimed read warms the page cache and the imports, then
``--reads`` full reads of the file (``evtk.read_events``) are timed and their
median kept. The core counts alternate round by round (1, 2, 1, 2, ...) and
the medians over ``--rounds`` rounds are compared: on a machine shared with
other work a single process moves by a third, alternating keeps it fair.

Each child also reports the CPU time of its reads (all threads): on a machine
shared with other work the wall time moves with the load, the CPU time much
less, and a CPU time that grows with the threads is contention (page faults,
allocator locks) rather than a busy machine. The load average is printed
with every row; figures taken at a load above about 1 say little about
scaling.

Before the reads, the machine's own ceiling for each core count k: k
independent processes, one pinned to each core, each hashing the same
bytes held in its cache (SHA-256), and again each copying a 64 MiB buffer
to another (memory bandwidth), against one such process alone
(``--ceiling-rounds``, alternating; 0 leaves them out). On a
virtual machine whose vCPUs share physical cores on the host (hyperthread
siblings, or a host with more guests than cores) k cores do well under k
times one core's work however the work is divided; a read's speed-up is
bounded by that figure, not by k.

A second, in-process breakdown (``--phases``) times the stages of an AEDAT4
read on the threads of a process pinned to each core count: reading the
compressed bodies (into new buffers and into one reused buffer), reading and
decompressing them (into new buffers, as before issue 32, and into the
reused per-thread buffers the reader uses), and decoding the FlatBuffers
events of bodies already in memory into the columns, so the stages that do
not scale can be named. What limits the read (docs/performance.md, "Every
core"): the per-packet Python between the calls that release the GIL, some
15 us a packet, a tenth of the read at 10,000-event packets.

Files: the 20 M-event AEDAT4 files of ``bench_fresh_read.py`` (dv-processing's
``MonoCameraWriter``, LZ4, 10,000-event packets) and the same events written by
evtk with LZ4 and 10,000-event packets; the other formats are written by evtk
from the same events (``benchmarks/data/``, git-ignored, made once).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
DATA = HERE / "data"
sys.path.insert(0, str(HERE))

FORMATS = ("aedat4-dv", "aedat4-evtk", "aedat4-zstd", "evt2", "evt3", "hdf5", "parquet")


def data_file(n: int, fmt: str) -> Path:
    """The 20 M-event (``n``) file of ``fmt``, made once."""
    from bench_fresh_read import make_file

    if fmt == "aedat4-dv":
        return make_file(n, "dv-lz4")
    if fmt == "aedat4-zstd":
        return make_file(n, "evtk-zstd")
    ext = {"aedat4-evtk": "aedat4", "evt2": "raw", "evt3": "raw", "hdf5": "h5", "parquet": "parquet"}[fmt]
    path = DATA / f"threads_{n}_{fmt}.{ext}"
    if path.exists():
        return path
    from bench_aedat4 import make_events

    import evtk

    DATA.mkdir(exist_ok=True)
    events = make_events(n)
    print(f"writing {path.name} ...", file=sys.stderr, flush=True)
    if fmt == "aedat4-evtk":
        from evtk.io.aedat4 import write_aedat4

        write_aedat4(path, events, compression="lz4", packet_events=10_000)
    elif fmt in ("evt2", "evt3"):
        evtk.write_events(path, events, fmt=fmt)
    else:
        evtk.write_events(path, events)
    return path


def _apply(settings: list[str]) -> None:
    """Set module constants for an experiment (``--set evtk._threads.MEMORY_SHARE=1``): ``module.NAME=value``,
    the value a Python literal; the reader looks its constants up at each read, so they take effect."""
    import ast
    import importlib

    for item in settings:
        target, value = item.split("=", 1)
        module, name = target.rsplit(".", 1)
        mod = importlib.import_module(module)
        if not hasattr(mod, name):
            raise SystemExit(f"--set {item}: {module} has no {name}")
        setattr(mod, name, ast.literal_eval(value))


def _child(path: str, reads: int) -> None:
    import evtk
    from evtk._threads import workers

    e = evtk.read_events(path)  # the page cache, the imports, the pool
    n = len(e)
    del e
    times, cpu = [], []
    for _ in range(reads):
        t0, c0 = time.perf_counter(), time.process_time()
        e = evtk.read_events(path)
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
        del e
    print(json.dumps({"events": n, "threads": workers(), "median_s": statistics.median(times),
                      "cpu_s": statistics.median(cpu), "times": times}))


def _phases(path: str, repeats: int = 5) -> None:
    """Where an AEDAT4 read spends its time, each stage run over all packets on the threads the process has
    (``workers()``: the parent pins the process to 1, 2, ... cores), best of ``repeats``."""
    from concurrent.futures import ThreadPoolExecutor

    import numpy as np

    import evtk
    from evtk._threads import workers
    from evtk.io import _compression as cz
    from evtk.io import _fbpy

    nw = workers()
    with evtk.open(path) as rec, ThreadPoolExecutor(nw) as pool:
        s = rec._stream(None, "EVTS")
        idx = rec._index
        rows = np.flatnonzero(idx.stream == s.id)
        counts = idx.count[rows]
        starts = np.concatenate([[0], np.cumsum(counts)])
        total = int(starts[-1])
        bodies = [rec._body(i) for i in rows]
        cols = [np.empty(total, d) for d in (np.int64, np.uint16, np.uint16, np.uint8)]
        width, height = s.sensor_size

        def stage(name):
            def run(k0, k1):
                scratch = cz.Scratch()
                for k in range(k0, k1):
                    i = int(rows[k])
                    if name == "read compressed bodies":
                        rec._pread(int(idx.size[i]) + 8, int(idx.offset[i]) - 8)
                    elif name == "read compressed bodies into one buffer":
                        rec._pread_into(scratch.room(int(idx.size[i]) + 8), int(idx.offset[i]) - 8)
                    elif name == "read and decompress into new buffers":
                        rec._body(i)
                    elif name == "touch fresh columns":  # once per slice: the page faults of new arrays
                        pass
                    elif name == "read and decompress into one buffer":
                        rec._body(i, scratch)
                    else:  # decode bodies already in memory into columns already touched
                        _fbpy.decode_events(bodies[k], b"EVTS", *cols, int(starts[k]), int(counts[k]), width,
                                            height)
            cuts = np.linspace(0, len(rows), 4 * nw + 1).astype(int)
            if name == "touch fresh columns":
                fresh = [np.empty(total, c.dtype) for c in cols]
                edges = np.linspace(0, total, 4 * nw + 1).astype(int)
                t0 = time.perf_counter()
                list(pool.map(lambda ab: [c[ab[0]:ab[1]].fill(1) for c in fresh], zip(edges[:-1], edges[1:])))
                return time.perf_counter() - t0
            t0 = time.perf_counter()
            list(pool.map(lambda ab: run(*ab), zip(cuts[:-1], cuts[1:])))
            return time.perf_counter() - t0

        names = ["touch fresh columns", "read compressed bodies", "read compressed bodies into one buffer",
                 "read and decompress into new buffers", "read and decompress into one buffer", "decode"]
        best = {name: min(stage(name) for _ in range(repeats)) for name in names}
        evtk.read_events(path)
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            evtk.read_events(path)
            times.append(time.perf_counter() - t0)
        best["whole read_events"] = min(times)
    print(json.dumps({"events": total, "packets": len(rows), "threads": nw, "seconds": best}))


def _ceiling_child(kind: str) -> None:
    """One process of the machine's ceiling: the seconds it takes to hash 256 MiB of bytes held in the core's
    cache (``kind`` "cache"), or to copy 2 GiB from one 64 MiB buffer to another ("memory")."""
    if kind == "cache":
        import hashlib

        piece = bytes(range(256)) * 4096  # 1 MiB
        t0 = time.perf_counter()
        for _ in range(256):
            hashlib.sha256(piece).digest()
    else:
        src = bytearray(64 << 20)
        dst = bytearray(64 << 20)
        dst[:] = src  # the pages touched before the timing
        t0 = time.perf_counter()
        for _ in range(32):
            dst[:] = src
    print(json.dumps({"seconds": time.perf_counter() - t0}))


def ceiling(cpus: list[int], rounds: int, kind: str) -> float:
    """How many times one core's work ``len(cpus)`` independent processes do, one pinned to each of ``cpus``
    (:func:`_ceiling_child`'s ``kind`` of work): ``k`` x the median time of one alone over the median time of the
    ``k`` run together (``rounds`` of each, alternating)."""
    def start(cpu: int) -> subprocess.Popen:
        cmd = [sys.executable, __file__, "--ceiling-child", kind]
        if shutil.which("taskset"):
            cmd = ["taskset", "-c", str(cpu), *cmd]
        return subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True)

    def seconds(proc: subprocess.Popen) -> float:
        out, _ = proc.communicate()
        return float(json.loads(out.strip().splitlines()[-1])["seconds"])

    alone: list[float] = []
    together: list[float] = []
    for _ in range(rounds):
        alone.append(seconds(start(cpus[0])))
        procs = [start(c) for c in cpus]
        together.append(statistics.mean(seconds(p) for p in procs))
    return len(cpus) * statistics.median(alone) / statistics.median(together)


def env_without_threads() -> dict:
    """The environment, less evtk's thread settings (the children take their thread count from taskset)."""
    return {k: v for k, v in os.environ.items() if k not in ("EVTK_THREADS", "EVTK_IO_THREADS")}


def run(path: Path, cpus: str, reads: int, settings: list[str] | None = None) -> dict:
    cmd = [sys.executable, __file__, "--child", str(path), str(reads), *(f"--set={s}" for s in settings or [])]
    if shutil.which("taskset"):
        cmd = ["taskset", "-c", cpus, *cmd]
    res = subprocess.run(cmd, capture_output=True, text=True, env=env_without_threads())
    if res.returncode != 0:
        raise SystemExit(f"a child failed: {res.stderr.strip().splitlines()[-1:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--events", type=float, default=20e6)
    ap.add_argument("--formats", default="aedat4-dv,aedat4-evtk", help=f"comma-separated, of {', '.join(FORMATS)}")
    ap.add_argument("--cores", default="1,2", help="core counts to compare (CPUs 0..k-1)")
    ap.add_argument("--rounds", type=int, default=7, help="processes per core count, alternating")
    ap.add_argument("--reads", type=int, default=5, help="timed reads per process (their median)")
    ap.add_argument("--phases", action="store_true", help="also time the stages of an AEDAT4 read on one thread")
    ap.add_argument("--json", help="write the results here")
    ap.add_argument("--set", action="append", default=[], metavar="MODULE.NAME=VALUE",
                    help="an experiment: set a constant in every child (evtk._threads.MEMORY_SHARE=1, say)")
    ap.add_argument("--ceiling-rounds", type=int, default=3,
                    help="rounds of the machine's ceiling (k independent processes, one a core; 0: none)")
    ap.add_argument("--child", nargs=2, help=argparse.SUPPRESS)
    ap.add_argument("--phases-child", help=argparse.SUPPRESS)
    ap.add_argument("--ceiling-child", choices=["cache", "memory"], help=argparse.SUPPRESS)
    args = ap.parse_args()
    _apply(args.set)
    if args.ceiling_child:
        _ceiling_child(args.ceiling_child)
        return
    if args.child:
        _child(args.child[0], int(args.child[1]))
        return
    if args.phases_child:
        _phases(args.phases_child)
        return
    n = int(args.events)
    cores = [int(c) for c in args.cores.split(",")]
    have = len(os.sched_getaffinity(0))
    cpus = {k: ",".join(map(str, sorted(os.sched_getaffinity(0))[:k])) for k in cores if k <= have}
    print(f"{n:,} events, {args.rounds} rounds x {args.reads} warm reads, {have} cores here, "
          f"load {os.getloadavg()[0]:.1f}")
    ceilings: dict = {}
    kinds = (("cache", "SHA-256 of bytes in cache"), ("memory", "copies of 64 MiB"))
    for kind, what in kinds if args.ceiling_rounds > 0 and max(cpus) > 1 else ():
        ceilings[kind] = {k: ceiling(sorted(os.sched_getaffinity(0))[:k], args.ceiling_rounds, kind)
                          for k in cpus if k > 1}
        print(f"the machine's ceiling, k independent processes one a core ({what}), x one alone: "
              + ", ".join(f"{k} cores {v:.2f}x" for k, v in ceilings[kind].items()), flush=True)
    results = []
    for fmt in args.formats.split(","):
        path = data_file(n, fmt)
        times: dict = {k: [] for k in cpus}
        cpu: dict = {k: [] for k in cpus}
        loads = [os.getloadavg()[0]]
        for _ in range(args.rounds):
            for k, c in cpus.items():
                got = run(path, c, args.reads, args.set)
                times[k].append(got["median_s"])
                cpu[k].append(got["cpu_s"])
            loads.append(os.getloadavg()[0])
        med = {k: statistics.median(v) for k, v in times.items()}
        med_cpu = {k: statistics.median(v) for k, v in cpu.items()}
        base = med[min(med)]
        row = dict(format=fmt, events=n, median_s=med, cpu_s=med_cpu, runs=times, load=loads,
                   speedup={k: base / v for k, v in med.items()}, ceiling=ceilings)
        results.append(row)
        print(f"{fmt:<12}" + "  ".join(f"{k} core{'s' if k > 1 else ''} {med[k]:.3f} s ({base / med[k]:.2f}x, "
                                        f"CPU {med_cpu[k]:.3f} s)" for k in med),
              f" load {min(loads):.1f}-{max(loads):.1f}", flush=True)
        if args.phases and fmt.startswith("aedat4"):
            row["phases"] = {}
            for k, c in cpus.items():
                cmd = [sys.executable, __file__, "--phases-child", str(path), *(f"--set={s}" for s in args.set)]
                if shutil.which("taskset"):
                    cmd = ["taskset", "-c", c, *cmd]
                res = subprocess.run(cmd, capture_output=True, text=True, env=env_without_threads())
                ph = json.loads(res.stdout.strip().splitlines()[-1])
                row["phases"][k] = ph
                print(f"   {k} core{'s' if k > 1 else ''}: " + ", ".join(f"{n} {v:.3f} s" for n, v in
                                                                  ph["seconds"].items()), flush=True)
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
