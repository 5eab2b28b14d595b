"""Reconstruction accuracy against the ideal correlation, over random signed patterns.

    python benchmarks/bench_accuracy.py                      # 8 pattern draws
    python benchmarks/bench_accuracy.py --draws 3 --json benchmarks/results/accuracy.json

Each draw is a signed 3x3 kernel and signed 16x16 features (uniform +-1),
simulated at the default bench's nominal light with two flat-field captures
and reconstructed with ``evtk.reconstruct.reconstruct`` (16x16, schedule
windows). Rows vary the kernel sources (point-like or the default extended
ones, whose penumbra blurs by ``[1/8, 3/4, 1/8]``), the pixels (ideal: no
shot noise, no threshold mismatch, no background; mismatch: default 0.02
threshold spread, no noise; default: everything on) and the reconstruction
(with or without flat-field calibration and deblurring). Reported: mean and
worst correlation, RMS error over the ideal's RMS and over its range.
This is a measurement of accuracy, not of speed; it runs in one process.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile

import numpy as np


def run(draws):
    import evtk
    from evtk.optics import Bench
    from evtk.reconstruct import reconstruct
    from evtk.sensor import SensorModel
    from evtk.simulate import Simulation

    sensors = {
        "ideal": SensorModel(shot_noise=False, background_rate_hz=0.0, theta_mismatch=0.0),
        "mismatch": SensorModel(shot_noise=False, background_rate_hz=0.0),
        "default": SensorModel(),
    }
    variants = [("point", s, ff, False) for s in sensors for ff in (False, True)]
    variants += [("area", s, ff, db) for s in sensors for ff in (False, True) for db in (False, True)]
    rows = {v: [] for v in variants}
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "run.aedat4")
        for d in range(draws):
            rng = np.random.default_rng(1000 + d)
            k, f = rng.choice([-1, 1], (3, 3)), rng.choice([-1, 1], (16, 16))
            for src in ("point", "area"):
                for name, sensor in sensors.items():
                    Simulation(k, f, bench=Bench(source_extent=src), sensor=sensor, seed=d).write(path)
                    with evtk.open(path) as rec:
                        for v in variants:
                            if v[0] == src and v[1] == name:
                                e = reconstruct(rec, flat_field=v[2], deblur=v[3]).summary["error"]
                                rows[v].append((e["correlation"], e["nrmse"], e["nrmse_range"]))
    out = []
    for (src, name, ff, db), vals in rows.items():
        a = np.asarray(vals, dtype=np.float64)
        out.append({"sources": src, "pixels": name, "flat_field": ff, "deblur": db, "draws": len(a),
                    "correlation_mean": float(a[:, 0].mean()), "correlation_min": float(a[:, 0].min()),
                    "nrmse_rms": float(a[:, 1].mean()), "nrmse_range": float(a[:, 2].mean())})
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=8)
    ap.add_argument("--json", help="also write the results here")
    args = ap.parse_args()
    res = run(args.draws)
    print(f"{'sources':7s} {'pixels':9s} {'flat':5s} {'deblur':6s} {'corr mean':>9s} {'corr min':>8s} "
          f"{'RMSE/RMS':>8s} {'RMSE/range':>10s}")
    for r in res:
        print(f"{r['sources']:7s} {r['pixels']:9s} {str(r['flat_field']):5s} {str(r['deblur']):6s} "
              f"{r['correlation_mean']:9.4f} {r['correlation_min']:8.4f} {r['nrmse_rms']:8.1%} {r['nrmse_range']:10.1%}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"draws": args.draws, "results": res}, fh, indent=1)


if __name__ == "__main__":
    main()
