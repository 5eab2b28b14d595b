"""Where a windowed command's time goes between its two sides: the decoding of each chunk and the counting of it.

    python benchmarks/bench_pipeline.py --file benchmarks/data/fresh_20000000_dv-lz4.aedat4 --op enob --runs 3

``evtk enob`` and ``evtk reconstruct -o`` (``--op``; ``--window period:10000``) read a recording in chunks: one
thread decodes the next chunk while the consumer counts and sums this one, then decodes beside it
(``evtk.reconstruct.accumulate._prefetched``). This script runs the command in one process (``--runs`` times
after a first, untimed run) with that function wrapped, and stamps each chunk's decoding (on the prefetching
thread, from its start to its end), the consumer's wait for it (which includes the decoding it helps with) and
the consumer's work on it (from the chunk's hand-over to the request for the next). Printed per run: the chunks,
the medians of those three a chunk, their sums, and the pipeline's wall time beside the process's CPU time over
it. A consumer that waits little and decodes long chunks alone says the decoding bounds the command (the
balance that the consumer's helping strikes); a consumer busier than the decoding says the counting and sums
do. On a many-core machine it shows which side more threads should go to.
"""

from __future__ import annotations

import argparse
import importlib
import statistics
import sys
import threading
import time

_END = object()


def _instrument(log: list) -> None:
    acc = importlib.import_module("evtk.reconstruct.accumulate")
    original = acc._prefetched

    def timed(chunks):
        def produced():
            while True:
                a = time.perf_counter()
                item = next(chunks, _END)
                log.append(("decode", a, time.perf_counter(), threading.get_ident()))
                if item is _END:
                    return
                yield item

        inner = original(produced())
        try:
            while True:
                a = time.perf_counter()
                item = next(inner, _END)
                b = time.perf_counter()
                log.append(("wait", a, b, threading.get_ident()))
                if item is _END:
                    return
                yield item
                log.append(("consume", b, time.perf_counter(), threading.get_ident()))
        finally:
            inner.close()

    acc._prefetched = timed


def _report(log: list, cpu_s: float, wall_s: float, label: str) -> None:
    def of(kind: str) -> list[float]:
        return [1e3 * (b - a) for k, a, b, _ in log if k == kind]

    decode, wait, consume = of("decode"), of("wait"), of("consume")
    start = min(a for _, a, _, _ in log)
    end = max(b for _, _, b, _ in log)
    chunks = len(consume)
    print(f"{label}: {chunks} chunks over {1e3 * (end - start):.0f} ms of pipeline ({1e3 * wall_s:.0f} ms for the "
          f"command, {1e3 * cpu_s:.0f} ms of CPU)")
    for name, values in (("decode (prefetching thread)", decode), ("consumer waits and helps", wait),
                         ("consumer counts and sums", consume)):
        if values:
            print(f"    {name:28s} median {statistics.median(values):6.1f} ms a chunk, {sum(values):7.1f} ms in all")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--file", required=True)
    ap.add_argument("--op", choices=("enob", "reconstruct"), default="enob")
    ap.add_argument("--window", default="period:10000")
    ap.add_argument("--runs", type=int, default=3)
    args = ap.parse_args()
    log: list = []
    _instrument(log)
    from click.testing import CliRunner

    from evtk.cli import main as cli

    argv = [args.op, args.file, "--window", args.window]
    if args.op == "reconstruct":
        argv += ["-o", "bench_pipeline_out.npz"]
    runner = CliRunner()
    for run in range(args.runs + 1):
        log.clear()
        cpu, wall = time.process_time(), time.perf_counter()
        result = runner.invoke(cli, argv)
        cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
        if result.exit_code != 0:
            sys.exit(f"evtk {' '.join(argv)} failed: {result.output}")
        if run:
            _report(log, cpu, wall, f"run {run}")
    if args.op == "reconstruct":
        import os

        os.remove("bench_pipeline_out.npz")


if __name__ == "__main__":
    main()
