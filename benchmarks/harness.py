"""What every benchmark script shares: its measurements run in fresh child processes."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time


class ChildFailed(RuntimeError):
    """A measurement process exited with an error; the message is its last stderr line."""


def child_runs(script, args, repeats=1, pin_cpu=False, single_thread=False) -> list[dict]:
    """Run ``python script --child ARGS`` ``repeats`` times; the JSON object each prints last.

    ``pin_cpu`` pins the child to CPU 0 (Linux, with taskset);
    ``single_thread`` also caps evtk's decode threads, numba's and OpenMP's threads at one.
    """
    cmd = [sys.executable, str(script), "--child", *[str(a) for a in args]]
    if pin_cpu and sys.platform.startswith("linux") and shutil.which("taskset"):
        cmd = ["taskset", "-c", "0", *cmd]
    env = dict(os.environ)
    if single_thread:
        env.update(EVTK_IO_THREADS="1", NUMBA_NUM_THREADS="1", OMP_NUM_THREADS="1")
    out = []
    for _ in range(int(repeats)):
        res = subprocess.run(cmd, capture_output=True, text=True, env=env)
        if res.returncode != 0:
            lines = res.stderr.strip().splitlines()
            raise ChildFailed(lines[-1] if lines else f"exit status {res.returncode}")
        out.append(json.loads(res.stdout.strip().splitlines()[-1]))
    return out


def whole_process(args, tree, stdout=False) -> tuple:
    """Wall seconds, peak RSS (MB) and CPU seconds (user + system) of one whole process ``python ARGS`` with the
    evtk tree ``tree`` first on the path, under GNU time.

    Run in ``tree``: ``python -c`` and ``-m`` put the working folder before PYTHONPATH, so run from another
    checkout a baseline tree's rows would time that checkout's evtk. File arguments must be absolute paths.
    With ``stdout``, the process's standard output comes fourth.
    """
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in (str(tree), os.environ.get("PYTHONPATH")) if p))
    t0 = time.perf_counter()
    done = subprocess.run(["/usr/bin/time", "-f", "%M %U %S", sys.executable, *args], capture_output=True,
                          text=True, env=env, cwd=str(tree))
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        lines = done.stderr.strip().splitlines()
        raise ChildFailed(lines[-2] if len(lines) > 1 else f"exit status {done.returncode}")
    peak_kb, user_s, sys_s = done.stderr.split()[-3:]
    if stdout:
        return wall, int(peak_kb) / 1024, float(user_s) + float(sys_s), done.stdout
    return wall, int(peak_kb) / 1024, float(user_s) + float(sys_s)
