"""The same evtk commands in whole fresh processes under several environments, alternating.

    python benchmarks/bench_env.py --file F.aedat4 --env "base=" --env "blas1=OPENBLAS_NUM_THREADS=1" \
        --env "t4=EVTK_THREADS=4" --rounds 5

Each command (``--ops``, separated by ``;``: ``read``, ``reconstruct`` for ``evtk reconstruct F --window
period:10000 -o x.npz``, ``enob`` for ``evtk enob F --window period:10000``, or ``calibrated`` for the calibrated
route of bench_calibrate's job with ``--keep DIR`` holding it) runs once untimed per environment, then ``--rounds``
times, every environment and command in turn (every other round reversed), so that a slow minute of the machine
hits all of them. Printed: the median wall and CPU seconds (user + system) of each, and each one's ratio to the
read under the same environment and to the same command under the first environment (medians of the rounds'
ratios). Made for the many-core questions of issue 32: which of the machine's threads (evtk's, the BLAS
library's) a short process pays for, and how much faster each command is on more cores:

    python benchmarks/bench_env.py --file F.aedat4 --env "1 core=CPUS=0" --env "2 cores=CPUS=0-1" \
        --ops "read;reconstruct;enob;calibrated" --keep DIR --rounds 9
"""

from __future__ import annotations

import argparse
import os
import statistics
from pathlib import Path

from harness import whole_process

HERE = Path(__file__).resolve().parent


def _commands(path: str, keep: str | None) -> dict:
    """The operations' ``python`` arguments: bench_reconstruct's for the recording, bench_calibrate's for the
    bench job kept in ``keep``."""
    from bench_calibrate import fresh_commands
    from bench_reconstruct import _FIXED

    out = str(Path(path).with_suffix(".env.npz"))
    cmds = {op: [a.format(p=path, out=out) for a in _FIXED[name]] for op, name in
            (("read", "read"), ("reconstruct", "evtk reconstruct -o x.npz"), ("enob", "evtk enob"))}
    if keep:
        job = fresh_commands(Path(keep).resolve())
        cmds["read job"], cmds["calibrated"] = job["read"], job["evtk reconstruct --calibration"]
    return cmds


def _cpus(spec: str) -> set[int]:
    """The CPUs of ``CPUS=`` (``0``, ``0+1``, ``0-3``: ``+`` joins, as ``,`` separates the variables), none for
    an empty one."""
    cpus: set[int] = set()
    for part in filter(None, spec.split("+")):
        lo, _, hi = part.partition("-")
        cpus.update(range(int(lo), int(hi or lo) + 1))
    return cpus


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--file", required=True, help="the recording (absolute or relative path)")
    ap.add_argument("--env", action="append", default=[],
                    help="LABEL=K=V,K=V (LABEL= for the environment as is; TREE=DIR runs another evtk tree; "
                         "CPUS=0 or CPUS=0-3 runs on those CPUs only, as taskset -c does)")
    ap.add_argument("--ops", default="read;reconstruct;enob")
    ap.add_argument("--keep", help="bench_calibrate.py --keep folder (for the op 'calibrated')")
    ap.add_argument("--rounds", type=int, default=5)
    a = ap.parse_args()
    cmds = _commands(str(Path(a.file).resolve()), a.keep)
    ops = [o for o in a.ops.split(";") if o]
    if "calibrated" in ops and "read job" not in ops:
        ops.insert(0, "read job")
    envs = {}
    for spec in a.env or ["base="]:
        label, _, pairs = spec.partition("=")
        envs[label] = dict(p.split("=", 1) for p in pairs.split(",") if p)
    saved = dict(os.environ)
    # (affinity is Linux's: asked for only where an environment sets CPUS)
    everywhere = os.sched_getaffinity(0) if any("CPUS" in e for e in envs.values()) else set()
    plan = [(e, o) for e in envs for o in ops]

    def run(e: str, o: str) -> tuple:
        env = dict(envs[e])
        tree = Path(env.pop("TREE", HERE.parent)).resolve()  # another evtk tree (git archive COMMIT evtk)
        cpus = _cpus(env.pop("CPUS", ""))  # the child inherits the affinity, as under taskset
        os.environ.clear()
        os.environ.update(saved, **env)
        if cpus:
            os.sched_setaffinity(0, cpus)
        try:
            return whole_process(cmds[o], tree)
        finally:
            os.environ.clear()
            os.environ.update(saved)
            if cpus:
                os.sched_setaffinity(0, everywhere)

    for e, o in plan:  # untimed: page cache, compiled caches
        run(e, o)
    got: dict = {k: [] for k in plan}
    for r in range(a.rounds):
        for k in (plan if r % 2 == 0 else plan[::-1]):
            got[k].append(run(*k))
    print(f"\n{Path(a.file).name}: whole fresh processes, median of {a.rounds}, alternating; {os.cpu_count()} CPUs, "
          f"load {os.getloadavg()[0]:.2f}\n")
    first = next(iter(envs))
    print(f"| environment | operation | wall s | CPU s | x read, wall | {first}'s wall / this | peak MB |")
    print("|---|---|---:|---:|---:|---:|---:|")
    for e, o in plan:
        runs = got[(e, o)]
        base = got.get((e, "read job" if o in ("calibrated", "read job") else "read"), runs)
        ratio = statistics.median(g[0] / b[0] for g, b in zip(runs, base))
        speed = statistics.median(f[0] / g[0] for f, g in zip(got[(first, o)], runs))
        print(f"| {e} | {o} | {statistics.median(g[0] for g in runs):.3f} | "
              f"{statistics.median(g[2] for g in runs):.3f} | {ratio:.2f} | {speed:.2f} | "
              f"{max(g[1] for g in runs):.0f} |")


if __name__ == "__main__":
    main()
