"""Simulator throughput in the paper's configuration, on one core.

    python benchmarks/bench_simulate.py                 # 512 captures, 5 repeats
    python benchmarks/bench_simulate.py --captures 2048 --repeats 7 --json out.json

Configuration: signed (+-1) random 3x3 kernel and 16x16 features (four passes
per pair), default bench and sensor (320x240, shot noise on), seed fixed.
Measured, each in a fresh subprocess pinned to one CPU after a warm-up run:

* event path: ``Simulation.iter_events`` (all events of the whole sensor,
  sorted) - events/s and captures/s;
* event path written to AEDAT4 (LZ4) through ``Simulation.write``;
* fast path: ``Simulation.responses`` (counts per window, no events) from
  the count table, built within the timed run ("cold") or already built for
  the same bench and sensor ("warm", as in an optimisation loop), and with
  ``method="exact"`` (the pixel model run per capture);
* the same without shot noise.

The reference is the bench itself: it captures at most ``1/e_min`` (eq. 7)
patterns per second, and at ``1/(window + settle)`` on the default schedule.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import tempfile
import time

from harness import child_runs


def _sim(captures, noise):
    import numpy as np

    from evtk.sensor import SensorModel
    from evtk.simulate import Simulation

    rng = np.random.default_rng(2024)
    k = rng.choice([-1, 1], (3, 3))
    f = rng.choice([-1, 1], (16, 16))
    sensor = SensorModel(shot_noise=noise)
    return Simulation(k, f, sensor=sensor, repeat=max(1, captures // 4), seed=1)


def child(op, captures, noise):
    sim = _sim(8, noise)  # warm-up: JIT caches, imports
    list(sim.iter_events())
    sim.responses()
    sim = _sim(captures, noise)
    n_events = 0
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        if op == "events":
            for ev in sim.iter_events():
                n_events += len(ev)
        elif op == "write":
            n_events = sim.write(os.path.join(tmp, "run.aedat4"))["events"]
        else:
            import evtk.simulate.table as es

            if op == "table_cold":
                es._TABLES.clear()
            method = "exact" if op == "exact" else "table"
            r = sim.responses(method=method)
            n_events = int(r.on.sum() + r.off.sum())
        seconds = time.perf_counter() - t0
    rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(json.dumps({"seconds": seconds, "events": n_events, "captures": len(sim.schedule), "rss_mb": rss_mb,
                      "window_us": sim.window_us, "settle_us": sim.settle_us,
                      "e_min_us": sim.bench.min_window_us}))


def run(op, captures, noise, repeats):
    args = [op, "--captures", captures] + ([] if noise else ["--no-noise"])
    out = child_runs(__file__, args, repeats, pin_cpu=True, single_thread=True)
    secs = statistics.median(r["seconds"] for r in out)
    r0 = out[0]
    return {"op": op, "noise": noise, "seconds": secs, "events": r0["events"], "captures": r0["captures"],
            "events_per_s": r0["events"] / secs, "captures_per_s": r0["captures"] / secs,
            "rss_mb": max(r["rss_mb"] for r in out), "window_us": r0["window_us"], "settle_us": r0["settle_us"],
            "e_min_us": r0["e_min_us"]}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--captures", type=int, default=512)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--json", help="Also write the results here.")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ap.add_argument("--no-noise", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.child:
        child(a.child, a.captures, not a.no_noise)
        return
    rows = []
    for noise in (True, False):
        for op in ("events", "write", "table_cold", "table_warm", "exact"):
            rows.append(run(op, a.captures, noise, a.repeats))
    r0 = rows[0]
    bench_eq7 = 1e6 / r0["e_min_us"]
    bench_sched = 1e6 / (r0["window_us"] + r0["settle_us"])
    print(f"\n{r0['captures']} captures (3x3 signed kernel, 16x16 signed features, 320x240), one core, "
          f"median of {a.repeats} fresh processes")
    print(f"bench: at most {bench_eq7:,.0f} captures/s by eq. 7 (e_min {r0['e_min_us']:g} us); "
          f"{bench_sched:,.1f} captures/s on the default schedule (window {r0['window_us']} + settle "
          f"{r0['settle_us']} us)\n")
    print("| path | shot noise | M events/s | captures/s | x eq. 7 bench | x scheduled bench | peak RSS (MB) |")
    print("|---|---|---:|---:|---:|---:|---:|")
    names = {"events": "event path", "write": "event path -> AEDAT4 (LZ4)",
             "table_cold": "fast path, count table built in the run", "table_warm": "fast path, count table reused",
             "exact": "fast path, pixel model per capture"}
    for r in rows:
        print(f"| {names[r['op']]} | {'on' if r['noise'] else 'off'} | {r['events_per_s'] / 1e6:.1f} | "
              f"{r['captures_per_s']:,.0f} | {r['captures_per_s'] / bench_eq7:.2f} | "
              f"{r['captures_per_s'] / bench_sched:.0f} | {r['rss_mb']:.0f} |")
    if a.json:
        os.makedirs(os.path.dirname(os.path.abspath(a.json)), exist_ok=True)
        with open(a.json, "w") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
