"""Fresh-process reads of the real recordings in ``../shared/real-files``: evtk against the fastest public reader.

    python benchmarks/bench_real_files.py                        # every file, 5 alternating runs each
    python benchmarks/bench_real_files.py --repeats 7 --only evt3,es --json benchmarks/results/real.json
    python benchmarks/bench_real_files.py --commands             # also evtk info / info --check / convert
    python benchmarks/bench_real_files.py --only aedat4,es --inside   # and what evtk adds inside the process
    python benchmarks/bench_real_files.py --file evt3=benchmarks/data/threads_20000000_evt3.raw   # any file

Each run is a whole process, timed from outside: start Python, import the
reader, read every event of the file into numpy arrays, exit. evtk's run
(``evtk.read_events``) and the peer's alternate after one untimed run of
each (page cache), which of them goes first swapping from round to round,
and the medians of ``--repeats`` runs are compared, in
wall time and in CPU time (user and system, every thread of the process: it
moves less with the machine's load). The peers, per format (each the fastest
public reader of it installed here):

* AEDAT4: aedat (``aedat.Decoder``, the event packets concatenated);
* EVT 2.0 and DAT: expelliarmus (``Wizard(encoding).read``);
* EVT 3.0: evt3 (``evt3.decode_file``);
* Event Stream (DVS): event_stream (``Decoder``, its chunks concatenated);
* AEDAT 2.0: tonic (``read_davis_346`` for DAVIS files; for DVS128 files
  ``get_aer_events_from_file`` and ``read_dvs_128``'s bit masks, as
  ``read_dvs_128`` itself fails in tonic 1.7.0);
* N-MNIST: tonic (``read_mnist_file``).

With ``--inside``, each file also gets as many rounds of the two scripts with ``import numpy`` first and a
clock read inside the process from then to the end of the read: the median of the rounds' differences (evtk's
time minus the peer's, ms) is what evtk's imports and read add over the peer's, free of the process's start and
exit, which on a small file move by more than that from one minute to the next on a shared machine (issue 32,
eighteenth round).

With ``--commands``, ``evtk info``, ``evtk info --check``, ``evtk convert F
out.h5`` and ``evtk convert F out.aedat4`` are timed the same way (fresh
processes, median) on the largest file of each format. Both sides run
without ``PYTHONDONTWRITEBYTECODE`` (evtk's modules are then compiled once, as
an installation does; with it set every evtk process compiles them again).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
# beside the checkout (../shared/real-files), or beside its parent (a git worktree one level further down)
REAL = next((d for d in (ROOT.parent / "shared" / "real-files", ROOT.parent.parent / "shared" / "real-files")
             if d.is_dir()), ROOT.parent / "shared" / "real-files")

EVTK = "import sys, evtk\ne = evtk.read_events(sys.argv[1])\nprint(len(e))\n"

PEERS = {
    "aedat4": ("aedat", "import sys, numpy as np, aedat\n"
                        "parts = [p['events'] for p in aedat.Decoder(sys.argv[1]) if 'events' in p]\n"
                        "print(len(np.concatenate(parts)))\n"),
    "evt2": ("expelliarmus", "import sys\nfrom expelliarmus import Wizard\n"
                             "print(len(Wizard(encoding='evt2').read(sys.argv[1])))\n"),
    "dat": ("expelliarmus", "import sys\nfrom expelliarmus import Wizard\n"
                            "print(len(Wizard(encoding='dat').read(sys.argv[1])))\n"),
    "evt3": ("evt3", "import sys, evt3\nprint(len(evt3.decode_file(sys.argv[1]).timestamp))\n"),
    "es": ("event_stream", "import sys, numpy as np, event_stream\n"
                           "print(len(np.concatenate(list(event_stream.Decoder(sys.argv[1])))))\n"),
    "aedat2-davis": ("tonic", "import sys, tonic.io as tio\nprint(len(tio.read_davis_346(sys.argv[1])[2]))\n"),
    "aedat2-dvs128": ("tonic", "import sys, numpy as np, tonic.io as tio\n"
                               "version, start = tio.read_aedat_header_from_file(sys.argv[1])[:2]\n"
                               "ev = tio.get_aer_events_from_file(sys.argv[1], version, start)\n"
                               "a = ev['address'].astype(np.int64)\n"
                               "x, y, p, t = (a >> 8) & 0x7F, (a >> 1) & 0x7F, a & 1, ev['timeStamp']\n"
                               "print(len(t))\n"),
    "nmnist": ("tonic", "import sys, numpy as np, tonic.io as tio\n"
                        "dt = np.dtype([('x', np.int16), ('y', np.int16), ('t', np.int64), ('p', np.int8)])\n"
                        "print(len(tio.read_mnist_file(sys.argv[1], dt)))\n"),
}


def files(only=None) -> list[tuple[str, Path]]:
    """``(format, path)`` of every real file evtk reads, from ``refs.json`` (DVS Event Stream only)."""
    refs = json.loads((REAL / "refs.json").read_text())
    out = []
    for name, ref in sorted(refs.items()):
        fmt = ref.get("format", "")
        if fmt == "aedat2-unknown-chip":
            fmt = "aedat2-dvs128"  # jAER's DVS128 rules are its reference
        if name.endswith(".bin"):
            fmt = "nmnist"
        if fmt == "es" and ref.get("error") or (fmt == "es" and not ref.get("readers", {}).get("event_stream 1.6.3", {})
                                                .get("events")):
            continue
        if fmt not in PEERS:
            continue
        if only and fmt.split("-")[0] not in only and fmt not in only:
            continue
        out.append((fmt, REAL / name))
    return out


def plain_env() -> dict:
    """The environment, less ``PYTHONDONTWRITEBYTECODE``: with it every fresh process compiles evtk's modules
    again (0.08-0.1 s here), which no installed package pays; the untimed first run writes the bytecode."""
    return {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}


def env_for(checkout) -> dict:
    paths = [str(Path(checkout).resolve()), os.environ.get("PYTHONPATH", "")]
    return dict(plain_env(), PYTHONPATH=os.pathsep.join(p for p in paths if p))


def timed(argv, env, cwd) -> tuple[float, str]:
    return timed_cpu(argv, env, cwd)[::2]


def timed_cpu(argv, env, cwd) -> tuple[float, float, str]:
    """Wall seconds, CPU seconds (user + system, every thread of the child) and the output of one run."""
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    res = subprocess.run(argv, env=env, cwd=cwd, capture_output=True, text=True)
    dt = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    if res.returncode != 0:
        raise SystemExit(f"{argv[:4]} failed: {res.stderr.strip().splitlines()[-1:]}")
    return dt, (r1.ru_utime + r1.ru_stime) - (r0.ru_utime + r0.ru_stime), res.stdout.strip()


INSIDE = "import time, numpy\n_t0 = time.perf_counter()\n{program}\nprint('INSIDE', time.perf_counter() - _t0)\n"


def inside_ms(runs: dict, envs: dict, work: Path, repeats: int) -> float:
    """The median over ``repeats`` alternating rounds of evtk's time minus the peer's, in ms, each read inside its
    process from after ``import numpy`` to the end of the read (the scripts of ``runs`` with that clock around
    them)."""
    diffs = []
    for r in range(repeats):
        got = {}
        for k in (("evtk", "peer") if r % 2 == 0 else ("peer", "evtk")):
            argv = [*runs[k][:2], INSIDE.format(program=runs[k][2]), *runs[k][3:]]
            out = timed(argv, envs[k], work)[1]
            got[k] = float(out.rsplit("INSIDE", 1)[1])
        diffs.append(got["evtk"] - got["peer"])
    return 1e3 * statistics.median(diffs)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--only", help="comma-separated formats (aedat4, evt2, evt3, dat, es, aedat2, nmnist)")
    ap.add_argument("--evtk-path", default=str(ROOT))
    ap.add_argument("--commands", action="store_true", help="also time evtk info / info --check / convert")
    ap.add_argument("--file", action="append", default=[], metavar="FORMAT=PATH",
                    help="read this file instead of the real ones (repeatable), e.g. a large one another tool wrote: "
                         "evt3=benchmarks/data/threads_20000000_evt3.raw")
    ap.add_argument("--inside", action="store_true",
                    help="also the paired in-process time after numpy's import (evtk minus the peer, ms)")
    ap.add_argument("--json")
    args = ap.parse_args()
    only = set(args.only.split(",")) if args.only else None
    chosen = [(fmt, Path(path).resolve()) for fmt, _, path in (f.partition("=") for f in args.file)]
    if any(fmt not in PEERS for fmt, _ in chosen):
        ap.error(f"--file takes FORMAT=PATH, FORMAT one of {', '.join(PEERS)}")
    env = env_for(args.evtk_path)
    peer_env = plain_env()
    work = Path(tempfile.mkdtemp(prefix="evtk-real-"))  # cwd: no checkout shadows PYTHONPATH's
    py = sys.executable
    print(f"{args.repeats} alternating fresh processes per file, load {os.getloadavg()[0]:.1f}")
    print(f"{'file':<62}{'format':<14}{'events':>9}{'evtk s':>8}{'peer':>14}{'peer s':>8}{'peer/evtk':>10}"
          f"{'cpu ratio':>10}" + (f"{'inside ms':>11}" if args.inside else ""))
    rows = []
    for fmt, path in (chosen or files(only)):
        peer, program = PEERS[fmt]
        runs = {"evtk": [py, "-c", EVTK, str(path)], "peer": [py, "-c", program, str(path)]}
        envs = {"evtk": env, "peer": peer_env}
        n = {k: timed(v, envs[k], work)[1] for k, v in runs.items()}  # untimed: page cache
        times: dict = {"evtk": [], "peer": []}
        cpu: dict = {"evtk": [], "peer": []}  # CPU time of the whole process: it moves less with the load
        for r in range(args.repeats):
            # who goes first alternates from round to round: the one run just after the other found the CPU's
            # caches and clock as the other left them (evtk always first read 0.93-0.94, swapped 0.96-0.97)
            for k in (("evtk", "peer") if r % 2 == 0 else ("peer", "evtk")):
                wall, used, _ = timed_cpu(runs[k], envs[k], work)
                times[k].append(wall)
                cpu[k].append(used)
        med = {k: statistics.median(v) for k, v in times.items()}
        med_cpu = {k: statistics.median(v) for k, v in cpu.items()}
        row = dict(file=path.name, format=fmt, events=int(n["evtk"]), peer=peer, peer_events=int(n["peer"]),
                   evtk_s=med["evtk"], peer_s=med["peer"], peer_over_evtk=med["peer"] / med["evtk"], runs=times,
                   evtk_cpu_s=med_cpu["evtk"], peer_cpu_s=med_cpu["peer"],
                   peer_over_evtk_cpu=med_cpu["peer"] / med_cpu["evtk"], cpu_runs=cpu)
        if args.inside:
            row["inside_evtk_minus_peer_ms"] = inside_ms(runs, envs, work, args.repeats)
        rows.append(row)
        print(f"{path.name[:61]:<62}{fmt:<14}{row['events']:>9}{med['evtk']:>8.3f}{peer:>14}{med['peer']:>8.3f}"
              f"{row['peer_over_evtk']:>10.2f}{row['peer_over_evtk_cpu']:>10.2f}"
              + (f"{row['inside_evtk_minus_peer_ms']:>+11.1f}" if args.inside else ""), flush=True)
    by_fmt: dict = {}
    for r in rows:
        by_fmt.setdefault(r["format"], []).append((r["peer_over_evtk"], r["peer_over_evtk_cpu"]))
    print("\nper format: median of the files' peer/evtk ratios (min-max), wall and CPU time")
    for fmt, v in by_fmt.items():
        w, c = [a for a, _ in v], [b for _, b in v]
        print(f"  {fmt:<14}{statistics.median(w):6.2f}  ({min(w):.2f}-{max(w):.2f}, {len(v)} files)"
              f"   cpu {statistics.median(c):.2f}  ({min(c):.2f}-{max(c):.2f})")
    commands = []
    if args.commands:
        largest: dict = {}
        for fmt, path in (chosen or files(only)):
            if fmt not in largest or path.stat().st_size > largest[fmt].stat().st_size:
                largest[fmt] = path
        print(f"\n{'file':<62}{'info':>7}{'--check':>9}{'->h5':>7}{'->aedat4':>10}  (s, median of {args.repeats})")
        for fmt, path in largest.items():
            cmds = {"info": ["info", str(path)], "check": ["info", "--check", str(path)],
                    "h5": ["convert", str(path), str(work / "out.h5")],
                    "aedat4": ["convert", str(path), str(work / "out.aedat4")]}
            med = {}
            for key, cli in cmds.items():
                argv = [py, "-m", "evtk.cli", *cli]
                ts = []
                for _ in range(args.repeats):
                    for out in work.glob("out.*"):
                        out.unlink()
                    ts.append(timed(argv, env, work)[0])
                med[key] = statistics.median(ts)
            commands.append(dict(file=path.name, format=fmt, **{f"{k}_s": v for k, v in med.items()}))
            print(f"{path.name[:61]:<62}{med['info']:>7.3f}{med['check']:>9.3f}{med['h5']:>7.3f}{med['aedat4']:>10.3f}",
                  flush=True)
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps({"reads": rows, "commands": commands}, indent=1))


if __name__ == "__main__":
    main()
