"""A fresh process reading a whole AEDAT4 file: evtk against dv-processing, start to exit.

    python benchmarks/bench_fresh_read.py                       # 20 M events, 5 repeats
    python benchmarks/bench_fresh_read.py --events 2e6 --repeats 3
    git worktree add /tmp/evtk-base <commit>
    python benchmarks/bench_fresh_read.py --baseline /tmp/evtk-base       # and that evtk, alternated with these

What a user pays for one ``evtk`` command or one short script per recording:
each run is a new Python process that imports the reader, reads every event
of the file into arrays and exits, timed from outside (wall clock around the
process). evtk's and dv-processing's runs (and a baseline evtk's, given one)
alternate, after one untimed run of each (page cache, JIT caches); the
medians of ``--repeats`` runs are compared. On a loaded machine single runs
move by a third: alternating keeps the comparison fair, the medians settle it.

Two more figures come from ``--probes`` more processes per file (the median
one is reported):

* first-call overhead: the first ``read_events`` minus a second read of the
  same file (imports and set-up that the first read pays; the median of
  three later reads stands for the second);
* peak memory: the child's peak RSS after the read minus its peak once
  ``evtk`` and numpy are imported (the interpreter's baseline), against the
  bytes of the arrays returned (``VmHWM`` of ``/proc/self/status``, the
  process's own high-water mark: ``ru_maxrss`` can carry the parent's over
  fork and exec; ``ru_maxrss`` where there is no ``/proc``).

The files are made once in ``benchmarks/data/`` (git-ignored): written by
dv-processing's ``MonoCameraWriter`` (LZ4, 10,000-event packets: one
``push_back`` per event, slow, so kept), by faery (LZ4 frames with checksums)
and by evtk with ZSTD. The events are bench_aedat4's (uniform on 320x240).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
DATA = HERE / "data"
ROOT = HERE.parent
WRITERS = ("dv-lz4", "faery-lz4", "evtk-zstd")

# the whole program each timed process runs (the file and the expected count follow on the command line)
PROGRAMS = {
    "evtk": "import sys, evtk\n"
            "e = evtk.read_events(sys.argv[1])\n"
            "assert len(e) == int(sys.argv[2]), len(e)\n",
    "dv-processing": "import sys, numpy as np, dv_processing as dv\n"
                     "rec = dv.io.MonoCameraRecording(sys.argv[1])\n"
                     "parts = []\n"
                     "while True:\n"
                     "    b = rec.getNextEventBatch()\n"
                     "    if b is None:\n"
                     "        break\n"
                     "    parts.append(b.numpy())\n"
                     "e = np.concatenate(parts)\n"
                     "assert len(e) == int(sys.argv[2]), len(e)\n",
}

# one process: the baseline after the imports, the first read, its peak, a second read
PROBE = """
import json, resource, sys, time
import evtk, numpy
def rss_mib():
    # this process's own high-water mark (ru_maxrss can carry the parent's over fork and exec)
    try:
        with open("/proc/self/status") as f:
            return next(int(line.split()[1]) for line in f if line.startswith("VmHWM:")) / 1024
    except (OSError, StopIteration):
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
base = rss_mib()
t0 = time.perf_counter()
e = evtk.read_events(sys.argv[1])
t1 = time.perf_counter()
peak = rss_mib()
arrays = sum(a.nbytes for a in (e.t, e.x, e.y, e.p)) / 2**20
later = []
for _ in range(3):  # the second read, three times over: this machine's noise is not the first call's cost
    del e
    t2 = time.perf_counter()
    e = evtk.read_events(sys.argv[1])
    later.append(time.perf_counter() - t2)
print(json.dumps(dict(first_s=t1 - t0, second_s=sorted(later)[1], base_mib=base, peak_mib=peak, arrays_mib=arrays,
                      numba_loaded="numba" in sys.modules)))
"""


def data_file(n: int, writer: str) -> Path:
    return DATA / f"fresh_{n}_{writer}.aedat4"


def make_file(n: int, writer: str) -> Path:
    """The ``writer``'s file of ``n`` events, made once."""
    path = data_file(n, writer)
    if path.exists():
        return path
    sys.path.insert(0, str(HERE))
    from bench_aedat4 import make_events, write_faery

    DATA.mkdir(exist_ok=True)
    events = make_events(n)
    tmp = path.with_name(path.stem + ".partial.aedat4")  # dv-processing aborts on another extension
    print(f"writing {path.name} ...", file=sys.stderr, flush=True)
    if writer == "faery-lz4":
        write_faery(events, tmp, "lz4")
    elif writer == "evtk-zstd":
        import evtk

        evtk.write_events(tmp, events, compression="zstd", fmt="aedat4")
    else:
        import dv_processing as dv

        cfg = dv.io.MonoCameraWriter.DAVISConfig("DVXplorer_bench", tuple(events.sensor_size))
        cfg.compression = dv.CompressionType.LZ4
        w = dv.io.MonoCameraWriter(str(tmp), cfg)
        for lo in range(0, n, 10_000):
            hi = min(lo + 10_000, n)
            store = dv.EventStore()
            for t, x, y, p in zip(events.t[lo:hi].tolist(), events.x[lo:hi].tolist(), events.y[lo:hi].tolist(),
                                  events.p[lo:hi].tolist()):
                store.push_back(t, x, y, bool(p))
            w.writeEvents(store)
        del w
    os.replace(tmp, path)
    return path


def plain_env() -> dict:
    """The environment, less ``PYTHONDONTWRITEBYTECODE``: with it every fresh process compiles evtk's modules
    again (0.08-0.1 s on the development machine), which no installed package pays; the untimed first run
    writes the bytecode."""
    return {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}


def evtk_env(checkout) -> dict:
    """The environment that puts ``checkout``'s evtk first."""
    paths = [str(Path(checkout).resolve()), os.environ.get("PYTHONPATH", "")]
    return dict(plain_env(), PYTHONPATH=os.pathsep.join(p for p in paths if p))


def run_child(program: str, args, env: dict) -> subprocess.CompletedProcess:
    # from the data folder: ``python -c`` puts the working directory first on sys.path, and a checkout there
    # would shadow the one PYTHONPATH names
    res = subprocess.run([sys.executable, "-c", program, *map(str, args)], env=env, cwd=DATA, capture_output=True,
                         text=True)
    if res.returncode != 0:
        raise SystemExit(f"a child failed: {res.stderr.strip().splitlines()[-1:]}")
    return res


def timed_process(program: str, path: Path, n: int, env: dict) -> float:
    """Wall seconds of one process: start Python, import, read every event into arrays, exit."""
    t0 = time.perf_counter()
    run_child(program, (path, n), env)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--events", type=float, default=20e6)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--writers", default=",".join(WRITERS), help=f"comma-separated, of {', '.join(WRITERS)}")
    ap.add_argument("--evtk-path", default=str(ROOT), help="the evtk checkout to time (put first on PYTHONPATH)")
    ap.add_argument("--baseline", help="another evtk checkout (say, a git worktree of an older commit), timed in "
                                       "the same alternation and reported as 'base'")
    ap.add_argument("--probes", type=int, default=3, help="processes that measure the first call and the peak "
                                                          "memory (the median one is reported)")
    ap.add_argument("--json", help="write the results here")
    args = ap.parse_args()
    n = int(args.events)
    runners = {"evtk": (PROGRAMS["evtk"], evtk_env(args.evtk_path))}
    if args.baseline:
        runners["base"] = (PROGRAMS["evtk"], evtk_env(args.baseline))
    runners["dv"] = (PROGRAMS["dv-processing"], plain_env())
    results = []
    print(f"{n:,} events, {args.repeats} repeats, evtk from {args.evtk_path}"
          f"{f', base from {args.baseline}' if args.baseline else ''}, {os.cpu_count()} CPUs, "
          f"load {os.getloadavg()[0]:.1f}")
    print(f"{'file':<11}{'evtk':<6}{'s':>7}{'dv s':>8}{'dv/evtk':>9}{'1st call s':>12}{'peak/arrays':>13}")
    for writer in args.writers.split(","):
        path = make_file(n, writer)
        for program, env in runners.values():  # untimed: page cache, JIT caches
            timed_process(program, path, n, env)
        times = {name: [] for name in runners}
        for _ in range(args.repeats):
            for name, (program, env) in runners.items():
                times[name].append(timed_process(program, path, n, env))
        med = {name: statistics.median(v) for name, v in times.items()}
        for name in runners:
            if name == "dv":
                continue
            probes = [json.loads(run_child(PROBE, (path,), runners[name][1]).stdout.strip().splitlines()[-1])
                      for _ in range(args.probes)]
            p = sorted(probes, key=lambda q: q["first_s"] - q["second_s"])[len(probes) // 2]
            row = dict(file=writer, evtk=name, events=n, evtk_s=med[name], dv_s=med["dv"],
                       dv_over_evtk=med["dv"] / med[name], times=times[name], dv_times=times["dv"],
                       first_call_overhead_s=p["first_s"] - p["second_s"],
                       peak_over_arrays=(p["peak_mib"] - p["base_mib"]) / p["arrays_mib"], probe=p)
            results.append(row)
            print(f"{writer:<11}{name:<6}{row['evtk_s']:>7.3f}{row['dv_s']:>8.3f}{row['dv_over_evtk']:>9.2f}"
                  f"{row['first_call_overhead_s']:>12.3f}{row['peak_over_arrays']:>13.3f}"
                  f"   (read {p['first_s']:.3f} then {p['second_s']:.3f} s; peak {p['peak_mib'] - p['base_mib']:.0f}"
                  f" of {p['arrays_mib']:.0f} MiB; numba {'loaded' if p['numba_loaded'] else 'not loaded'})",
                  flush=True)
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
