"""Time of the bench route: calibration and schedule-driven reconstruction, against a plain read.

    python benchmarks/bench_calibrate.py                  # 300 repeats of one kernel (3.8 M events), best of 5
    python benchmarks/bench_calibrate.py --repeat 40 --runs 3
    python benchmarks/bench_calibrate.py --writer dv       # the camera's files written by dv-processing

Two runs of one 3x3 kernel on the bundled 16x16 features are simulated on
the default 320x240 sensor and written as AEDAT4 without their simulation
record, as a camera would: a calibration run (two flat fields, two dot-grid
captures, six level captures, then the repeats) and the job itself (two flat
fields and the repeats). Timed in this process after a warm-up (numba's
caches loaded):

- reading every event (`evtk.read_events`) of each run;
- `evtk.calibrate.calibrate` on the calibration run (placement and the
  pixel model's fit);
- `evtk.reconstruct.reconstruct` (the calibrated route) on the job with that
  calibration (what `evtk reconstruct --schedule S --calibration C` runs:
  the fitted model, event times, flat field, passes, grid);
- the same on the calibration run itself, which fits its own model;
- `evtk.reconstruct.reconstruct` with `linearization="exp(n theta)"` (no model) on the job.

The ratio of a reconstruction to the read of the same file is what the
issue bounds (1.5x).

``--fresh N`` times the same route as a user runs it, in whole fresh processes
(start Python, import, work, exit), alternating N rounds after one untimed
round: ``python -c "import evtk, sys; evtk.read_events(sys.argv[1])" job``
against ``evtk reconstruct job --schedule S --calibration C -o x.npz``, where
``C`` comes from ``evtk calibrate`` on the calibration run; medians of wall
and CPU time (user + system) and of the rounds' ratios to the read, peak RSS.
``--baseline DIR`` also runs the reconstruction with another evtk tree
(``git archive COMMIT evtk | tar -x -C DIR``), alternating; ``--keep DIR``
writes (or reuses) the runs there instead of a temporary folder.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
import time
from pathlib import Path

from harness import whole_process

HERE = Path(__file__).resolve().parent


def camera_copy(sim_path, out, writer):
    """The run as the camera software would have written it: events and trigger edges, no evtk record.

    ``writer`` "evtk" (evtk's AEDAT4 writer) or "dv" (dv-processing's
    MonoCameraWriter, packets of 10,000 events, LZ4, as DV records).
    """
    import evtk

    with evtk.open(sim_path) as rec:
        ev, tr = rec.events(), rec.triggers()
    if writer == "evtk":
        evtk.write_events(out, ev, tr)
        return
    import dv_processing as dv

    cfg = dv.io.MonoCameraWriter.DAVISConfig("DVXplorer_bench", tuple(ev.sensor_size))
    cfg.compression = dv.CompressionType.LZ4
    w = dv.io.MonoCameraWriter(str(out), cfg)
    t, x, y, p = ev.t.tolist(), ev.x.tolist(), ev.y.tolist(), ev.p.tolist()
    for lo in range(0, len(t), 10_000):
        store = dv.EventStore()
        for i in range(lo, min(lo + 10_000, len(t))):
            store.push_back(t[i], x[i], y[i], bool(p[i]))
        w.writeEvents(store)
    packet = dv.TriggerPacket()
    for tt, k in zip(tr.t.tolist(), tr.kind.tolist()):
        packet.elements.append(dv.Trigger(int(tt), dv.TriggerType(int(k))))
    w.writeTriggerPacket(packet)
    del w


def dv_read(path):
    """Every event of ``path`` through dv-processing (the peer's plain read)."""
    import dv_processing as dv

    rec = dv.io.MonoCameraRecording(str(path))
    n = 0
    while True:
        b = rec.getNextEventBatch()
        if b is None:
            return n
        n += len(b.numpy())


def best(fn, runs):
    fn()
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def fresh_commands(d: Path) -> dict:
    """The two processes ``--fresh`` times on the runs kept in ``d``: a read of the job, and the calibrated route
    (``python`` arguments; bench_env.py times them too)."""
    job = str(d / "job.aedat4")
    return {"read": ["-c", "import evtk, sys; evtk.read_events(sys.argv[1])", job],
            "evtk reconstruct --calibration": ["-m", "evtk.cli", "reconstruct", job, "--schedule",
                                               str(d / "job" / "schedule.json"), "--calibration",
                                               str(d / "cal.toml"), "-o", str(d / "x.npz")]}


def fresh(rounds, writer, keep=None, baseline=None):
    """The calibrated route against a read of the same file, in whole fresh processes (module docstring)."""
    from evtk.patterns import write_patterns
    from evtk.simulate import Simulation, default_features

    kernel = [[0, 1, 0], [1, 1, 1], [0, 1, 0]]
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(keep or tmp).resolve()
        d.mkdir(parents=True, exist_ok=True)
        for name, extra in (("cal", {"calibration": 2, "levels": 6}), ("job", {})):
            if not (d / f"{name}.aedat4").exists():
                sim = Simulation(kernel, default_features(), repeat=150, seed=1, **extra)
                write_patterns(sim, str(d / name))
                sim.write(str(d / f"{name}_sim.aedat4"))
                camera_copy(str(d / f"{name}_sim.aedat4"), str(d / f"{name}.aedat4"), writer)
        if not (d / "cal.toml").exists():
            whole_process(["-m", "evtk.cli", "calibrate", str(d / "cal.aedat4"), "--schedule",
                           str(d / "cal" / "schedule.json"), "-o", str(d / "cal.toml")], HERE.parent)
        job = str(d / "job.aedat4")
        cmds = fresh_commands(d)
        route = cmds["evtk reconstruct --calibration"]
        plan = [(name, args, HERE.parent) for name, args in cmds.items()]
        if baseline:
            plan.append(("base: evtk reconstruct --calibration", route, Path(baseline).resolve()))
        for _, args, tree in plan:  # untimed: page cache, numba's cache if any
            whole_process(args, tree)
        runs: dict = {name: [] for name, _, _ in plan}
        for r in range(rounds):  # alternating, every other round reversed
            for name, args, tree in (plan if r % 2 == 0 else plan[::-1]):
                runs[name].append(whole_process(args, tree))
        # the same route warm in one process (a session reading and reconstructing; numpy's paths until the
        # counting done in numpy passes evtk.reconstruct.accumulate's threshold, then numba's, as in any session),
        # best of rounds, against the read warm in that process
        child = ("import sys, time, json\nimport evtk\nfrom evtk.calibrate import load_calibration\n"
                 "from evtk.plan import as_plan\nfrom evtk.reconstruct import reconstruct\n"
                 "job, sched, cal, n = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4])\n"
                 "c = load_calibration(cal)\n"
                 "plan = as_plan(sched).replace(pixel_model=c.pixel_model, region=c.region, origin_px=c.origin_px, "
                 "cell_map=c.cell_map(), blur_px=c.blur_px)\n"
                 "def best(fn):\n    fn()\n    out = []\n    for _ in range(n):\n"
                 "        t0 = time.perf_counter(); fn(); out.append(time.perf_counter() - t0)\n    return min(out)\n"
                 "with evtk.open(job) as rec:\n    r = best(lambda: evtk.read_events(job))\n"
                 "    q = best(lambda: reconstruct(rec, plan))\n"
                 "print(json.dumps({'read': r, 'route': q, 'numba': 'numba' in sys.modules}))\n")
        warm = whole_process(["-c", child, job, str(d / "job" / "schedule.json"), str(d / "cal.toml"),
                              str(max(rounds, 5))], HERE.parent, stdout=True)
    load = " ".join(f"{v:.2f}" for v in os.getloadavg())
    print(f"\nbench job ({writer}'s AEDAT4), whole fresh processes, median of {rounds}, alternating; "
          f"{os.cpu_count()} CPUs, load average {load} at the end\n")
    print("| operation | wall (s) | x read, wall | CPU (s) | x read, CPU | peak RSS (MB) |")
    print("|---|---:|---:|---:|---:|---:|")
    for name, got in runs.items():
        wall = statistics.median(a[0] / b[0] for a, b in zip(got, runs["read"]))
        cpu = statistics.median(a[2] / b[2] for a, b in zip(got, runs["read"]))
        print(f"| {name} | {statistics.median(g[0] for g in got):.3f} | {wall:.2f} | "
              f"{statistics.median(g[2] for g in got):.3f} | {cpu:.2f} | {max(g[1] for g in got):.0f} |")
    w = json.loads(warm[3].strip().splitlines()[-1])
    print(f"\nwarm, one process (numba loaded by the end: {w['numba']}; it is where evtk's compiled kernels are "
          f"not built, once the process has counted more than numpy's share), best of {max(rounds, 5)}: read "
          f"{w['read'] * 1e3:.1f} ms, calibrated route {w['route'] * 1e3:.1f} ms ({w['route'] / w['read']:.2f}x the read)")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeat", type=int, default=300)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--json", dest="json_out")
    ap.add_argument("--writer", choices=["evtk", "dv"], default="evtk",
                    help="who writes the camera's files: evtk, or dv-processing as DV would")
    ap.add_argument("--fresh", type=int, metavar="N", help="N rounds of whole fresh processes (see above)")
    ap.add_argument("--keep", help="--fresh: write or reuse the runs in this folder")
    ap.add_argument("--baseline", help="--fresh: another evtk tree to run the reconstruction with, alternately")
    args = ap.parse_args()
    if args.fresh:
        fresh(args.fresh, args.writer, args.keep, args.baseline)
        return

    import evtk
    from evtk.calibrate import calibrate
    from evtk.patterns import write_patterns
    from evtk.plan import as_plan
    from evtk.reconstruct import reconstruct
    from evtk.simulate import Simulation, default_features

    kernel = [[0, 1, 0], [1, 1, 1], [0, 1, 0]]
    with tempfile.TemporaryDirectory() as tmp:
        files = {}
        for name, extra in (("cal", {"calibration": 2, "levels": 6}), ("job", {})):
            sim = Simulation(kernel, default_features(), repeat=args.repeat, seed=1, **extra)
            write_patterns(sim, os.path.join(tmp, name))
            sim.write(os.path.join(tmp, f"{name}_sim.aedat4"))
            camera_copy(os.path.join(tmp, f"{name}_sim.aedat4"), os.path.join(tmp, f"{name}.aedat4"), args.writer)
            files[name] = (os.path.join(tmp, f"{name}.aedat4"), os.path.join(tmp, name, "schedule.json"),
                           len(sim.schedule))
        (cal_path, cal_sched, cal_caps), (job_path, job_sched, job_caps) = files["cal"], files["job"]
        n_cal, n_job = len(evtk.read_events(cal_path)), len(evtk.read_events(job_path))
        with evtk.open(cal_path) as rec_cal, evtk.open(job_path) as rec_job:
            cal = calibrate(rec_cal, cal_sched)
            read_cal = best(lambda: evtk.read_events(cal_path), args.runs)
            read_job = best(lambda: evtk.read_events(job_path), args.runs)
            cal_s = best(lambda: calibrate(rec_cal, cal_sched), args.runs)
            placed = {"region": cal.region, "origin_px": cal.origin_px, "cell_map": cal.cell_map(),
                      "blur_px": cal.blur_px}
            job_plan = as_plan(job_sched).replace(pixel_model=cal.pixel_model, **placed)
            cal_plan = as_plan(cal_sched).replace(**placed)
            job_s = best(lambda: reconstruct(rec_job, job_plan), args.runs)
            fit_s = best(lambda: reconstruct(rec_cal, cal_plan), args.runs)
            plain_s = best(lambda: reconstruct(rec_job, job_plan.replace(pixel_model=None, cell_map=None, blur_px=0.0),
                                               linearization="exp(n theta)"), args.runs)
            dv_s = best(lambda: dv_read(job_path), args.runs)
    out = {"writer": args.writer, "dv_read_job_s": dv_s, "events_job": n_job, "events_calibration_run": n_cal,
           "captures_job": job_caps,
           "captures_calibration_run": cal_caps, "read_job_s": read_job, "read_calibration_run_s": read_cal,
           "calibrate_s": cal_s, "reconstruct_job_s": job_s, "reconstruct_job_over_read": job_s / read_job,
           "reconstruct_fitting_s": fit_s, "reconstruct_fitting_over_read": fit_s / read_cal,
           "reconstruct_exp_s": plain_s, "reconstruct_exp_over_read": plain_s / read_job}
    print(f"job: {n_job:,} events, {job_caps} captures on 320x240: read {read_job * 1e3:.1f} ms, reconstruct with "
          f"the calibration's model {job_s * 1e3:.1f} ms ({job_s / read_job:.2f}x the read), exp(n theta) "
          f"{plain_s * 1e3:.1f} ms ({plain_s / read_job:.2f}x); dv-processing reads it in {dv_s * 1e3:.1f} ms "
          f"(the calibrated reconstruction is {dv_s / job_s:.2f}x as fast as dv-processing's plain read)")
    print(f"calibration run: {n_cal:,} events: read {read_cal * 1e3:.1f} ms, calibrate (dots and pixel model) "
          f"{cal_s * 1e3:.1f} ms, reconstruct fitting its own model {fit_s * 1e3:.1f} ms "
          f"({fit_s / read_cal:.2f}x the read)")
    if args.json_out:
        with open(args.json_out, "w") as fh:
            json.dump(out, fh, indent=1)


if __name__ == "__main__":
    main()
