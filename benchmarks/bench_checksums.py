"""What verifying the checksums in faery's AEDAT4 files costs: a full read, checked and unchecked.

    python benchmarks/bench_checksums.py                       # 20 M events, best of 5
    python benchmarks/bench_checksums.py --events 2e6 --repeats 3
    python benchmarks/bench_checksums.py --baseline /tmp/old   # also an older tree (git archive REV evtk)

faery writes LZ4 frames with xxHash32 block and content checksums. The file
(``benchmarks/data/faery_<n>_lz4.aedat4``, made once by faery) is read whole
with ``evtk.read_events``, checksums verified (``verify_checksums=True``) and
left out (``False``), two ways each:

* fresh: a new process per read (imports and thread-pool start-up included,
  the file in the page cache), best of ``--repeats``;
* warm: ``--repeats`` reads in one process after one untimed read, best of them.

Wall time and CPU time (all threads) are both reported, each the least seen.

Best rather than median: the machine this runs on is shared, and the least
disturbed run is the closest to what the code costs. An evtk that predates
the ``verify_checksums`` argument is read with its default only.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from harness import child_runs

HERE = Path(__file__).resolve().parent
DATA = HERE / "data"


def data_file(n: int) -> Path:
    """The faery-written LZ4 file of ``n`` events, made on first use."""
    path = DATA / f"faery_{n}_lz4.aedat4"
    if not path.exists():
        import faery
        from bench_aedat4 import make_events
        from bench_formats import _faery_array

        DATA.mkdir(exist_ok=True)
        ev = make_events(n)
        tmp = path.with_suffix(".tmp.aedat4")
        faery.events_stream_from_array(_faery_array(ev), tuple(ev.sensor_size)).to_file(
            str(tmp), compression=("lz4", 1), zero_t0=False)
        tmp.rename(path)
    return path


def _read(path: Path, verify: str) -> int:
    """Events in ``path`` read whole; ``verify`` is "on", "off" or "default"."""
    import evtk

    if verify == "default":
        return len(evtk.read_events(path))
    with evtk.open(path, verify_checksums=verify == "on") as rec:
        return len(rec.events())


def child(path: Path, verify: str, repeats: int) -> dict:
    """One process: a timed first read, then ``repeats`` warm reads (wall and CPU seconds, all threads)."""
    def timed():
        w, c = time.perf_counter(), time.process_time()
        n = _read(path, verify)
        return n, time.perf_counter() - w, time.process_time() - c

    n, first, first_cpu = timed()
    warm = [timed()[1:] for _ in range(repeats)]
    return {"events": n, "first_s": first, "first_cpu_s": first_cpu,
            "warm_s": [w for w, _ in warm], "warm_cpu_s": [c for _, c in warm]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--events", type=float, default=20e6)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--baseline", metavar="DIR",
                    help="also time the evtk package found in DIR (e.g. an older commit's tree), interleaved")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--child", nargs=3, metavar=("PATH", "VERIFY", "REPEATS"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child(Path(args.child[0]), args.child[1], int(args.child[2]))))
        return
    n = int(args.events)
    path = data_file(n)
    print(f"{path.name}: {path.stat().st_size / 1e6:.0f} MB, best of {args.repeats}")
    variants = []  # (label, PYTHONPATH, mode)
    trees = [("this", os.environ.get("PYTHONPATH"))]
    if args.baseline:
        trees.append(("baseline", str(Path(args.baseline).resolve())))
    for label, pp in trees:
        for mode in _modes(pp):
            variants.append((f"{label} verify={mode}", pp, mode))
    fresh = {v[0]: [] for v in variants}
    warm = {v[0]: [] for v in variants}
    for _ in range(args.repeats):  # rounds, every variant once a round, so that load on the machine falls on all
        for label, pp, mode in variants:
            r = _run(pp, [path, mode, 0])
            fresh[label].append((r["first_s"], r["first_cpu_s"]))
    for _ in range(2):
        for label, pp, mode in variants:
            r = _run(pp, [path, mode, max(1, args.repeats // 2 + 1)])
            warm[label] += zip(r["warm_s"], r["warm_cpu_s"])
    results = {}
    for label, _, _ in variants:
        f, fc = (min(v) for v in zip(*fresh[label]))
        w, wc = (min(v) for v in zip(*warm[label]))
        results[label] = {"fresh_s": f, "fresh_cpu_s": fc, "warm_s": w, "warm_cpu_s": wc}
        print(f"{label:>24}: fresh {f:.3f} s ({n / f / 1e6:.0f} Mev/s, CPU {fc:.3f} s), "
              f"warm {w:.3f} s ({n / w / 1e6:.0f} Mev/s, CPU {wc:.3f} s)")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"events": n, "python": sys.version, "results": results}, indent=2))


def _modes(pythonpath):
    """The verify settings an evtk found on ``pythonpath`` takes: on and off, or its default only."""
    code = "import evtk, inspect; print('verify_checksums' in inspect.signature(evtk.open).parameters)"
    env = dict(os.environ)
    if pythonpath:
        env["PYTHONPATH"] = pythonpath
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    return ("on", "off") if out.stdout.strip() == "True" else ("default",)


def _run(pythonpath, args):
    saved = os.environ.get("PYTHONPATH")
    if pythonpath:
        os.environ["PYTHONPATH"] = pythonpath
    try:
        return child_runs(__file__, args)[0]
    finally:
        if saved is None:
            os.environ.pop("PYTHONPATH", None)
        else:
            os.environ["PYTHONPATH"] = saved


if __name__ == "__main__":
    main()
