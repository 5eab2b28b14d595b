"""The calibrated route of bench_calibrate's job, an older checkout against this one in one process, interleaved.

    python benchmarks/ab_calibrate.py --old /tmp/calib-base      # git archive a617848 | tar -x -C /tmp/calib-base
    python benchmarks/ab_calibrate.py --old /tmp/calib-base --repeat 150 --rounds 15

The older checkout's ``evtk`` is copied as a package ``evtk_old`` (its imports are relative) and imported beside
this one. bench_calibrate's two runs (a calibration run and the job, ``--repeat`` repeats of one 3x3 kernel,
written as a camera would) are simulated once; then every round times, for each checkout in turn, a read of the
job (`read_events`), the calibrated route (`reconstruct(rec, plan)` with the calibration's pixel model and
placement) and the same with what is kept per calibration cleared first (the deblur's sampling matrices and the
flat field's light: a first reconstruction through a calibration). Medians over the rounds, wall and the process's
CPU time: on a loaded machine both checkouts see the same load, which separate processes minutes apart do not.
"""

from __future__ import annotations

import argparse
import importlib
import os
import shutil
import statistics
import sys
import tempfile
import time


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--old", required=True, help="an older checkout (its evtk/ is imported as evtk_old)")
    ap.add_argument("--repeat", type=int, default=150)
    ap.add_argument("--rounds", type=int, default=15)
    args = ap.parse_args()
    here = os.path.dirname(os.path.abspath(__file__))
    sys.path.insert(0, here)
    from bench_calibrate import camera_copy

    import evtk
    from evtk.patterns import write_patterns
    from evtk.simulate import Simulation, default_features

    with tempfile.TemporaryDirectory() as tmp:
        shutil.copytree(os.path.join(args.old, "evtk"), os.path.join(tmp, "pkg", "evtk_old"))
        sys.path.insert(0, os.path.join(tmp, "pkg"))
        evtk_old = importlib.import_module("evtk_old")
        kernel = [[0, 1, 0], [1, 1, 1], [0, 1, 0]]
        for name, extra in (("cal", {"calibration": 2, "levels": 6}), ("job", {})):
            sim = Simulation(kernel, default_features(), repeat=args.repeat, seed=1, **extra)
            write_patterns(sim, os.path.join(tmp, name))
            sim.write(os.path.join(tmp, f"{name}_sim.aedat4"))
            camera_copy(os.path.join(tmp, f"{name}_sim.aedat4"), os.path.join(tmp, f"{name}.aedat4"), "evtk")

        def setup(pkg):
            sub = {m: importlib.import_module(f"{pkg.__name__}.{m}") for m in ("calibrate", "plan", "reconstruct")}
            rec_cal, rec_job = pkg.open(os.path.join(tmp, "cal.aedat4")), pkg.open(os.path.join(tmp, "job.aedat4"))
            cal = sub["calibrate"].calibrate(rec_cal, os.path.join(tmp, "cal", "schedule.json"))
            plan = sub["plan"].as_plan(os.path.join(tmp, "job", "schedule.json")).replace(
                pixel_model=cal.pixel_model, region=cal.region, origin_px=cal.origin_px, cell_map=cal.cell_map(),
                blur_px=cal.blur_px)
            kept = [getattr(importlib.import_module(f"{pkg.__name__}.reconstruct.{m}"), name, None)
                    for m, name in (("deblur", "_systems"), ("linearize", "_flat_lights"))]

            def rebuilt():
                for held in kept:
                    if held is not None:
                        held.clear()
                return sub["reconstruct"].reconstruct(rec_job, plan)

            return {"read": lambda: pkg.read_events(os.path.join(tmp, "job.aedat4")),
                    "route": lambda: sub["reconstruct"].reconstruct(rec_job, plan), "route, rebuilt": rebuilt}

        runs = {"old": setup(evtk_old), "new": setup(evtk)}
        for fns in runs.values():
            for fn in fns.values():
                fn()
                fn()
        times = {(k, n): ([], []) for k in runs for n in runs[k]}
        for _ in range(args.rounds):
            for k, fns in runs.items():
                for n, fn in fns.items():
                    t0, c0 = time.perf_counter(), time.process_time()
                    fn()
                    times[(k, n)][0].append(time.perf_counter() - t0)
                    times[(k, n)][1].append(time.process_time() - c0)
    med = statistics.median
    for k in runs:
        read = med(times[(k, "read")][0])
        print(f"{k} ({args.old if k == 'old' else os.path.dirname(os.path.dirname(evtk.__file__))}):")
        for (kk, n), (wall, cpu) in times.items():
            if kk == k:
                print(f"  {n:15s} {med(wall) * 1e3:7.1f} ms ({min(wall) * 1e3:.1f}-{max(wall) * 1e3:.1f})  "
                      f"{med(wall) / read:5.2f}x read   cpu {med(cpu) * 1e3:5.0f} ms")


if __name__ == "__main__":
    main()
