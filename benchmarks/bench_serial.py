"""What part of a warm read holds the GIL: the share that runs one thread at a time however many cores there are.

    python benchmarks/bench_serial.py                                  # the 20 M-event dv-processing LZ4 file
    python benchmarks/bench_serial.py --file benchmarks/data/threads_20000000_evt3.raw --rounds 5

Each child process is pinned to one core (``taskset -c 0``, ``EVTK_THREADS=1``) and times ``--reads`` warm full
reads (``evtk.read_events``) after an untimed one, with every compiled kernel of :mod:`evtk._native` and
``os.preadv`` wrapped by a timer, and so are zstandard's decompressions (a ZSTD AEDAT4 file's packets, one call each
from Python): all release the GIL, so the rest of the read's wall time, which the interpreter runs, is what several
threads cannot share. Only those calls are timed: where a read reads through Python's file objects (the Prophesee
and Event Stream readers' blocks) or copies large arrays in numpy (a ZSTD batch's bodies into its staging buffer,
its columns out of it), which release the GIL too, that time counts as held, and the figure is an upper bound. It
is exact for LZ4 AEDAT4 files, whose reads are all ``pread`` and compiled kernels.

Amdahl's law then bounds the read on ``N`` threads at ``1 / (s + (1 - s) / N)`` for a share ``s`` (printed for 16
threads), before memory bandwidth or the cores' shared clock bound it further. With an AEDAT4 LZ4 file, a second
mode turns the reader's range kernel off (``decode_lz4_range``: a thread's batches in one call) so that each batch
goes through one kernel call of its own and the Python loop between them, as before the sixteenth round of issue 32;
the two modes alternate round by round, and the medians of the rounds' medians are printed.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from harness import child_runs  # noqa: E402

DEFAULT = HERE / "data" / "fresh_20000000_dv-lz4.aedat4"


def child(path: str, reads: int, mode: str) -> None:
    """Time ``reads`` warm reads of ``path`` in this process; print one JSON line of medians."""
    import gc
    import os
    import time

    os.environ["EVTK_THREADS"] = "1"
    import evtk
    from evtk import _native

    inside = [0.0]

    def timed(fn):
        def call(*args):
            t0 = time.perf_counter()
            try:
                return fn(*args)
            finally:
                inside[0] += time.perf_counter() - t0
        return call

    for name in [n for n in vars(_native) if n.startswith("_kernel_")]:
        if getattr(_native, name) is not None:
            setattr(_native, name, timed(getattr(_native, name)))
    _native._SCANS = {k: (None if fn is None else timed(fn), dtype) for k, (fn, dtype) in _native._SCANS.items()}
    if mode == "batch":
        _native._kernel_decode_lz4_range = None
    os.preadv = timed(os.preadv)
    try:  # zstandard's decompressor, as the reader makes it (evtk.io._compression.decompress), its calls timed
        import zstandard

        class _TimedZstd:
            def __init__(self, *args, **kwargs):
                self._d = _real_zstd(*args, **kwargs)
                self.decompress = timed(self._d.decompress)

            def stream_reader(self, *args, **kwargs):
                reader = self._d.stream_reader(*args, **kwargs)
                return type("_TimedReader", (), {"read": staticmethod(timed(reader.read))})()

        _real_zstd = zstandard.ZstdDecompressor
        zstandard.ZstdDecompressor = _TimedZstd
    except ImportError:
        pass
    n = len(evtk.read_events(path))
    gc.collect()
    walls, held = [], []
    for _ in range(reads):
        inside[0] = 0.0
        t0 = time.perf_counter()
        ev = evtk.read_events(path)
        wall = time.perf_counter() - t0
        walls.append(wall)
        held.append(wall - inside[0])
        del ev
        gc.collect()
    print(json.dumps({"events": n, "wall_s": statistics.median(walls), "held_s": statistics.median(held)}))


def _lz4_aedat4(path: str) -> bool:
    """Whether ``path`` is an AEDAT4 file of LZ4 packets (the range kernel's): the only files of the second mode."""
    if not path.endswith(".aedat4"):
        return False
    import evtk

    with evtk.open(path) as rec:
        return str(rec.info().get("compression", "")).startswith("lz4")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--file", default=str(DEFAULT))
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--reads", type=int, default=9)
    ap.add_argument("--child", nargs=3, metavar=("PATH", "READS", "MODE"), help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.child:
        child(a.child[0], int(a.child[1]), a.child[2])
        return
    path = str(Path(a.file).resolve())
    modes = ["range", "batch"] if _lz4_aedat4(path) else ["range"]
    got: dict[str, list[dict]] = {m: [] for m in modes}
    for r in range(a.rounds):
        for mode in (modes if r % 2 == 0 else modes[::-1]):
            got[mode] += child_runs(Path(__file__), [path, a.reads, mode], pin_cpu=True)
    print(f"{Path(path).name}: one core, {a.rounds} rounds x {a.reads} warm reads, medians")
    print("  (held: the read's wall time outside evtk's compiled kernels, os.preadv and zstandard's decompressions; "
          "an upper bound where the reader also reads through file objects or copies in numpy)")
    for mode, rows in got.items():
        wall = statistics.median(r["wall_s"] for r in rows)
        held = statistics.median(r["held_s"] for r in rows)
        share = held / wall
        label = {"range": "as evtk reads it", "batch": "one call a batch (range kernel off)"}[mode]
        print(f"  {label:38s} read {wall * 1e3:7.1f} ms, GIL held {held * 1e3:6.1f} ms ({share:5.1%}): "
              f"at most {1 / (share + (1 - share) / 16):4.1f}x on 16 threads")


if __name__ == "__main__":
    main()
