"""evtk's compiled kernels, one tree against another: the counting of fixed windows and a warm whole read.

    python benchmarks/bench_kernels.py --trees OLD,. --file benchmarks/data/fmt_evt3_4000000.raw --rounds 7

Each tree (a folder holding an ``evtk`` package with its ``_ckernels`` built, e.g. ``git archive COMMIT evtk |
tar -x -C OLD`` and the extension compiled there; ``.`` is this checkout) runs in its own fresh processes,
the trees alternating round by round (every other round reversed), each process pinned to one thread
(``EVTK_THREADS=1``):

* ``counting``: ``evtk._native.count_windows`` adding the signs of 1 M random events of a 320x240 sensor into
  16 windows' int16 frames (as ``evtk enob`` counts), the best of 40 calls, in ns an event;
* ``read`` (with ``--file``): the least of 9 warm ``evtk.read_events`` of the file, after a first one.

Printed per tree: the median over the rounds of each process's best, and the range. On a shared or virtual
machine a whole process's memory can land in a slow or a fast mode (the same tree and file took 0.09 or
0.14 s a read here), so the minima of many calls, not means, compare the kernels.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys

CHILD = r"""
import os, sys, time
sys.path.insert(0, sys.argv[1])
import numpy as np
import evtk
assert os.path.realpath(evtk.__file__).startswith(os.path.realpath(sys.argv[1])), evtk.__file__
from evtk import _native
if sys.argv[2] == "counting":
    rng = np.random.default_rng(1)
    n, w, h, windows = 1_000_000, 320, 240, 16
    x = rng.integers(0, w, n, dtype=np.uint16)
    y = rng.integers(0, h, n, dtype=np.uint16)
    p = rng.integers(0, 2, n, dtype=np.uint8)
    frame = w * h
    dump = windows * frame
    ky = _native.padded_table((np.arange(h) * w).astype(np.int64), dump)
    kx = _native.padded_table(np.arange(w, dtype=np.int64), dump)
    at = np.linspace(0, n, windows + 1).astype(np.int64)
    out = np.zeros(dump + 1, np.int16)
    best = float("inf")
    for _ in range(40):
        out[:] = 0
        t = time.perf_counter()
        assert _native.count_windows(x, y, p, slice(0, n), at, ky, kx, 0, frame, frame, dump, True, out)
        best = min(best, time.perf_counter() - t)
    print(best / n * 1e9)
else:
    evtk.read_events(sys.argv[3])
    best = float("inf")
    for _ in range(9):
        t = time.perf_counter()
        evtk.read_events(sys.argv[3])
        best = min(best, time.perf_counter() - t)
    print(best)
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trees", required=True, help="comma-separated folders, each holding an evtk package")
    ap.add_argument("--file", help="also time warm whole reads of this recording")
    ap.add_argument("--rounds", type=int, default=7)
    args = ap.parse_args()
    trees = [os.path.abspath(t) for t in args.trees.split(",")]
    ops = ["counting"] + (["read"] if args.file else [])
    env = dict(os.environ, EVTK_THREADS="1")
    got: dict[tuple[str, str], list[float]] = {(t, o): [] for t in trees for o in ops}
    for r in range(args.rounds):
        for tree in trees if r % 2 == 0 else trees[::-1]:
            for op in ops:
                cmd = [sys.executable, "-c", CHILD, tree, op, os.path.abspath(args.file or "")]
                done = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=tree)
                if done.returncode:
                    sys.exit(f"{tree} {op} failed:\n{done.stderr[-2000:]}")
                got[(tree, op)].append(float(done.stdout))
    print(f"{args.rounds} rounds, trees alternating, one thread; medians of each process's best (range)")
    for op in ops:
        unit, scale = ("ns an event", 1.0) if op == "counting" else ("ms", 1e3)
        for tree in trees:
            v = [x * scale for x in got[(tree, op)]]
            print(f"  {op:9s} {tree}: {statistics.median(v):.3f} {unit} ({min(v):.3f}-{max(v):.3f})")


if __name__ == "__main__":
    main()
