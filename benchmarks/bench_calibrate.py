"""Time of the bench route: calibration and schedule-driven reconstruction, against a plain read.

    python benchmarks/bench_calibrate.py                  # 300 repeats of one kernel (3.8 M events), best of 5
    python benchmarks/bench_calibrate.py --repeat 40 --runs 3

A job (one 3x3 kernel on the bundled 16x16 features, two flat fields, two
dot-grid calibration captures) is simulated on the default 320x240 sensor and
written as AEDAT4 without its simulation record, as a camera would. Timed in
this process after a warm-up (numba's caches loaded): reading every event
(`evtk.read_events`), `evtk.calibrate.calibrate`, and
`evtk.reconstruct.reconstruct_bench` with that calibration. The ratio of the
reconstruction to the read is what the issue bounds (1.5x).
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time


def best(fn, runs):
    fn()
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeat", type=int, default=300)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--json", dest="json_out")
    args = ap.parse_args()

    import evtk
    from evtk.calibrate import calibrate
    from evtk.patterns import write_patterns
    from evtk.reconstruct import reconstruct_bench
    from evtk.simulate import Simulation, default_features

    with tempfile.TemporaryDirectory() as tmp:
        sim = Simulation([[0, 1, 0], [1, 1, 1], [0, 1, 0]], default_features(), repeat=args.repeat, calibration=2)
        write_patterns(sim, os.path.join(tmp, "p"))
        sim.write(os.path.join(tmp, "sim.aedat4"))
        with evtk.open(os.path.join(tmp, "sim.aedat4")) as rec:
            evtk.write_events(os.path.join(tmp, "cam.aedat4"), rec.events(), rec.triggers())
        cam, schedule = os.path.join(tmp, "cam.aedat4"), os.path.join(tmp, "p", "schedule.json")
        n = len(evtk.read_events(cam))
        rec = evtk.open(cam)
        cal = calibrate(rec, schedule)
        read_s = best(lambda: evtk.read_events(cam), args.runs)
        cal_s = best(lambda: calibrate(rec, schedule), args.runs)
        rec_s = best(lambda: reconstruct_bench(rec, schedule, cal.region, cal.origin_px), args.runs)
        rec.close()
    out = {"events": n, "captures": len(sim.schedule), "read_s": read_s, "calibrate_s": cal_s,
           "reconstruct_s": rec_s, "reconstruct_over_read": rec_s / read_s}
    print(f"{n:,} events, {len(sim.schedule)} captures on 320x240: read {read_s * 1e3:.1f} ms, calibrate "
          f"{cal_s * 1e3:.1f} ms, reconstruct with the calibration {rec_s * 1e3:.1f} ms "
          f"({rec_s / read_s:.2f}x the read)")
    if args.json_out:
        with open(args.json_out, "w") as fh:
            json.dump(out, fh, indent=1)


if __name__ == "__main__":
    main()
