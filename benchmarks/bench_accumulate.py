"""Windowed accumulation: 20 M events into 1000 windows of 320x240, evtk against the usual ways.

    python benchmarks/bench_accumulate.py                    # 20 M events, 1000 windows, 5 repeats
    python benchmarks/bench_accumulate.py --events 2e6 --repeats 3

Each tool produces ON and OFF count frames (windows, 240, 320) for the same
back-to-back windows:

* evtk: ``evtk.reconstruct.accumulate`` on in-memory events, into a reused
  output buffer ("warm") or into fresh memory;
* evtk batches: ``accumulate_batches(..., reuse=True)``, the windows a batch
  at a time (batch size from the memory budget) into one reused buffer, each
  batch consumed (summed) before the next: what a streaming consumer such as
  ``evtk enob`` holds, never every window's frames at once;
* np.add.at: one call over all events with (window, y, x) indices from
  ``np.searchsorted``, per polarity, into a reused buffer or fresh memory;
* np.bincount: the same indices flattened, per polarity;
* dv-processing: ``dv.Accumulator`` fed each window's slice of an
  ``EventStore`` (built once, outside the timing), ``generateFrame`` per
  window; it yields one frame per window (a potential: ON adds 1, OFF
  subtracts 1, no decay), i.e. half the output of the others.

Every measurement runs in a fresh process after a warm-up; medians. The
events are the uniform random recording of ``bench_aedat4.py``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from bench_aedat4 import make_events  # noqa: E402
from harness import ChildFailed, child_runs  # noqa: E402

W, H = 320, 240


def _windows(ev, n):
    import numpy as np

    from evtk.reconstruct import Windows

    edges = np.linspace(int(ev.t[0]), int(ev.t[-1]) + 1, n + 1).astype(np.int64)
    return Windows(edges[:-1], edges[1:], np.arange(n), "bench")


def child(tool, n_events, n_windows):
    import numpy as np

    ev = make_events(n_events)
    win = _windows(ev, n_windows)
    small = make_events(20_000)
    # "warm": the output buffer exists already (a pipeline that reuses it, as dv's
    # accumulator reuses its frame); "cold": fresh memory, which on this machine is
    # slow to touch (about 0.5 GB/s) and dominates the cold figures
    warm = tool.endswith(" warm")
    buf = None
    if warm:
        buf = np.empty((2, n_windows, H, W), np.int32)
        buf.fill(0)
    if tool == "evtk batches":
        from evtk.reconstruct.accumulate import accumulate_batches

        region = (0, W, 0, H)
        for _ in accumulate_batches(small, _windows(small, 10), region, reuse=True):
            pass
        t0 = time.perf_counter()
        check = 0
        for _, c in accumulate_batches(ev, win, region, reuse=True):
            check += int(c.on.sum(dtype=np.int64) + c.off.sum(dtype=np.int64))
        seconds = time.perf_counter() - t0
    elif tool.startswith("evtk"):
        from evtk.reconstruct import accumulate

        accumulate(small, _windows(small, 10))
        if warm:  # steady state: the second pass over a reused buffer
            accumulate(ev, win, out=buf)
        t0 = time.perf_counter()
        r = accumulate(ev, win, out=buf)
        seconds = time.perf_counter() - t0
        check = int(r.on.sum() + r.off.sum())
    elif tool.startswith(("np.add.at", "np.bincount")):
        def op():
            w = np.searchsorted(win.t_start_us, ev.t, side="right") - 1
            flat = (w.astype(np.int64) * H + ev.y) * W + ev.x
            frames = []
            for pol in (1, 0):
                sel = ev.p == pol
                if tool.startswith("np.add.at"):
                    if warm:
                        out = buf[pol].reshape(-1)
                        out.fill(0)
                    else:
                        out = np.zeros(n_windows * H * W, np.int32)
                    np.add.at(out, flat[sel], 1)
                else:
                    out = np.bincount(flat[sel], minlength=n_windows * H * W).astype(np.int32)
                frames.append(out.reshape(n_windows, H, W))
            return frames

        if warm:  # steady state, as for evtk
            op()
        t0 = time.perf_counter()
        frames = op()
        seconds = time.perf_counter() - t0
        check = int(frames[0].sum() + frames[1].sum())
    elif tool == "dv-processing":
        import dv_processing as dv

        # the same events, read by dv-processing from an AEDAT4 copy (outside the timing)
        src = HERE / "data" / f"bench_acc_{n_events}.aedat4"
        if not src.exists():
            import evtk

            src.parent.mkdir(parents=True, exist_ok=True)
            evtk.write_events(src, ev)
        rec = dv.io.MonoCameraRecording(str(src))
        store = dv.EventStore()
        while rec.isRunning():
            batch = rec.getNextEventBatch()
            if batch is None:
                break
            store.add(batch)
        acc = dv.Accumulator((W, H), dv.Accumulator.Decay.NONE, 0.0, False, 1.0, 1e9, 0.0, 0.0, False)
        acc.accept(store.sliceTime(int(small.t[0]), int(small.t[-1])))  # warm-up
        for _rep in range(2):  # the second pass is timed (steady state)
            t0 = time.perf_counter()
            for a, b in zip(win.t_start_us.tolist(), win.t_end_us.tolist()):
                acc.clear()
                acc.accept(store.sliceTime(a, b))
                acc.getPotentialSurface()  # the frame, as a caller gets it
            seconds = time.perf_counter() - t0
        check = 0  # untimed: the frames again, summed
        for a, b in zip(win.t_start_us.tolist(), win.t_end_us.tolist()):
            acc.clear()
            acc.accept(store.sliceTime(a, b))
            check += int(np.abs(np.asarray(acc.getPotentialSurface())).sum())
    else:
        raise SystemExit(f"unknown tool {tool}")
    rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(json.dumps({"seconds": seconds, "check": check, "rss_mb": rss_mb}))


def run(tool, n_events, n_windows, repeats):
    try:
        out = child_runs(__file__, [tool, "--events", n_events, "--windows", n_windows], repeats)
    except ChildFailed as exc:
        return {"tool": tool, "error": str(exc)}
    return {"tool": tool, "seconds": statistics.median(r["seconds"] for r in out), "check": out[0]["check"],
            "rss_mb": max(r["rss_mb"] for r in out)}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--events", type=float, default=20e6)
    ap.add_argument("--windows", type=int, default=1000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--tools", default="evtk warm,evtk batches,np.add.at warm,dv-processing,evtk,np.add.at,np.bincount")
    ap.add_argument("--json")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    a = ap.parse_args()
    n = int(a.events)
    if a.child:
        child(a.child, n, a.windows)
        return
    rows = [run(t, n, a.windows, a.repeats) for t in a.tools.split(",")]
    base = next(r for r in rows if r["tool"].startswith("evtk"))
    print(f"\n{n:,} events into {a.windows} windows of {W}x{H}, median of {a.repeats} fresh processes\n")
    print("| tool | seconds | M events/s | x evtk time | peak RSS (MB) | check |")
    print("|---|---:|---:|---:|---:|---:|")
    for r in rows:
        if "error" in r:
            print(f"| {r['tool']} | failed: {r['error']} | | | | |")
            continue
        print(f"| {r['tool']} | {r['seconds']:.3f} | {n / r['seconds'] / 1e6:.0f} | "
              f"{r['seconds'] / base['seconds']:.1f} | {r['rss_mb']:.0f} | {r['check']:,} |")
    if a.json:
        os.makedirs(os.path.dirname(os.path.abspath(a.json)), exist_ok=True)
        with open(a.json, "w") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
