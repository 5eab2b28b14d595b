"""How reconstruction error depends on knowing the pixels: oracle, mismatched model, and the bench path.

    python benchmarks/bench_sensitivity.py                   # 4 pattern draws
    python benchmarks/bench_sensitivity.py --draws 2 --json benchmarks/results/sensitivity.json

Each draw simulates a signed 3x3 kernel on signed 16x16 features (default
bench, default pixels: shot noise, threshold spread, background; two flat
fields, two dot-grid captures, six level captures) with one pixel parameter changed from the default by the factor in
the row (the *true* camera). Three reconstructions of the same events:

- **oracle**: `reconstruct`, inverting the simulation record's pixel model,
  which is the true one (the inverse crime: what a perfectly calibrated model
  gives);
- **assumed default**: the same pipeline, but the record's pixel model is the
  default one, not the true one (a model calibrated on another camera);
- **bench, exp(n theta)**: `reconstruct(..., linearization="exp(n theta)")` from the schedule alone
  (trigger windows, `exp(n theta)`, model-free flat field), knowing nothing
  of the pixels;
- **calibrated**: `evtk.reconstruct_recording` with the schedule, what
  `evtk reconstruct --schedule S` runs: the same windows, placement and
  defocus from the run's own dot-grid captures, a pixel model fitted to its
  six level captures (`evtk.reconstruct.fit`), then the oracle's stages on
  it, deblurring regularised by the run's measured noise.

The bench column places the response by `evtk.calibrate.calibrate` on the
run's own dot-grid captures (not the simulation's answer).

Reported: mean correlation with the ideal correlation, and mean NRMSE after
the best scale (the bench path's responses are relative intensity).
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile

import numpy as np

ROWS = [  # (parameter, factor applied to the true camera)
    ("none", 1.0),
    ("tau_min_us", 1.3),
    ("tau_electrons", 1.3),
    ("refractory_us", 20.0),
    ("dark_current_e_per_s", 2.0),
    ("theta_on", 1.15),
    ("readout_period_us", 200.0),  # a DVXplorer-like frame readout (the default camera reads asynchronously)
]


def _scaled_error(got, ideal):
    from evtk.reconstruct import response_error

    got, ideal = np.asarray(got, float), np.asarray(ideal, float)
    scale = float(np.sum(got * ideal) / np.sum(got * got)) if np.any(got) else 1.0
    return response_error(got * scale, ideal)


def run(draws, levels=6):
    import evtk
    from evtk.calibrate import calibrate
    from evtk.patterns import write_patterns
    from evtk.plan import as_plan
    from evtk.reconstruct import (
        accumulate,
        plan,
        reconstruct,
        reconstruct_counts,
        wants_times,
    )
    from evtk.sensor import SensorModel
    from evtk.simulate import Simulation

    default = SensorModel().to_dict()
    out = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, factor in ROWS:
            acc = {"oracle": [], "assumed default": [], "bench": [], "calibrated": []}
            for d in range(draws):
                rng = np.random.default_rng(2000 + d)
                k, f = rng.choice([-1, 1], (3, 3)), rng.choice([-1, 1], (16, 16))
                true = dict(default)
                if name != "none":
                    true[name] = default[name] * factor if default[name] else factor
                    if name == "theta_on":
                        true["theta_off"] = default["theta_off"] * factor
                sim = Simulation(k, f, sensor=SensorModel(**true), seed=d, repeat=1, calibration=2, levels=levels)
                path = os.path.join(tmp, "run.aedat4")
                sim.write(path)
                write_patterns(sim, os.path.join(tmp, "p"))
                with evtk.open(path) as rec:
                    record, win, region = plan(rec)
                    counts = accumulate(rec, win, region, times=wants_times(record))
                    oracle = reconstruct_counts(counts, record)
                    assumed_record = record.replace(sensor=SensorModel(**default))
                    assumed = reconstruct_counts(counts, assumed_record)
                    schedule = os.path.join(tmp, "p", "schedule.json")
                    cal = calibrate(rec, schedule)
                    bench = reconstruct(rec, as_plan(schedule).replace(region=cal.region, origin_px=cal.origin_px),
                                        linearization="exp(n theta)")
                    fitted = evtk.reconstruct_recording(rec, schedule=schedule)  # what evtk reconstruct runs
                for key, r in (("oracle", oracle), ("assumed default", assumed), ("bench", bench),
                               ("calibrated", fitted)):
                    e = _scaled_error(r.cells, r.ideal)
                    acc[key].append((e["correlation"], e["nrmse"]))
            row = {"parameter": name, "factor": factor}
            for key, vals in acc.items():
                row[key] = {"correlation": float(np.mean([v[0] for v in vals])),
                            "nrmse_scaled": float(np.mean([v[1] for v in vals]))}
            out.append(row)
            print(_line(row), flush=True)
    return out


def _line(r):
    cells = " | ".join(f"{r[k]['correlation']:.3f} / {r[k]['nrmse_scaled']:.2f}"
                       for k in ("oracle", "assumed default", "bench", "calibrated"))
    label = ("none (default camera)" if r["parameter"] == "none" else
             f"`{r['parameter']}` {r['factor']:g}" if r["parameter"] == "readout_period_us" else
             f"`{r['parameter']}` x{r['factor']:g}")
    return f"| {label} | {cells} |"


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--draws", type=int, default=4)
    ap.add_argument("--json", dest="json_out")
    ap.add_argument("--levels", type=int, default=6, help="level captures in each run (the pixel model's fit)")
    args = ap.parse_args()
    print("| true camera differs in | oracle: correlation / NRMSE | assumed default model | bench, exp(n theta) | "
          "calibrated (fitted pixel model) |")
    print("|---|---|---|---|---|")
    rows = run(args.draws, args.levels)
    if args.json_out:
        with open(args.json_out, "w") as fh:
            json.dump({"draws": args.draws, "rows": rows}, fh, indent=1)


if __name__ == "__main__":
    main()
