"""Reconstruction accuracy against the ideal correlation, over random signed patterns.

    python benchmarks/bench_accuracy.py                      # 8 pattern draws
    python benchmarks/bench_accuracy.py --draws 3 --json benchmarks/results/accuracy.json

Each draw is a signed 3x3 kernel and signed 16x16 features (uniform +-1),
simulated at the default bench's nominal light with two flat-field captures
and reconstructed with ``evtk.reconstruct.reconstruct`` (16x16, schedule
windows). Rows vary the kernel sources (point-like or the default extended
ones, whose penumbra blurs by ``[1/8, 3/4, 1/8]``), the pixels (ideal: no
shot noise, no threshold mismatch, no background; noise off:
``SensorModel(shot_noise=False)``, i.e. default 0.02 threshold spread and
background activity; default: everything on) and the reconstruction: counts
alone without calibration, counts with flat-field calibration (and
deblurring for extended sources), and the default, which adds the event
times (``linearize_by_timing``). Reported: mean and worst correlation, RMS
error over the ideal's RMS and over its range (mean and worst).
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
        "noise off": SensorModel(shot_noise=False),
        "default": SensorModel(),
    }
    # (flat field, deblur, timing); deblur None: the default (on when calibrated)
    methods = [(False, False, False), (True, None, False), (True, None, None)]
    rows = {(src, name, m): [] for src in ("point", "area") for name in sensors for m in methods}
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "run.aedat4")
        for d in range(draws):
            rng = np.random.default_rng(1000 + d)
            k, f = rng.choice([-1, 1], (3, 3)), rng.choice([-1, 1], (16, 16))
            for src in ("point", "area"):
                for name, sensor in sensors.items():
                    Simulation(k, f, bench=Bench(source_extent=src), sensor=sensor, seed=d).write(path)
                    with evtk.open(path) as rec:
                        for m in methods:
                            r = reconstruct(rec, flat_field=m[0], deblur=m[1], timing=m[2])
                            e = r.summary["error"]
                            rows[(src, name, m)].append((e["correlation"], e["nrmse"], e["nrmse_range"],
                                                         r.summary["deblurred"]))
    out = []
    for (src, name, (ff, _, timing)), vals in rows.items():
        a = np.asarray([v[:3] for v in vals], dtype=np.float64)
        out.append({"sources": src, "pixels": name, "flat_field": ff, "deblur": bool(vals[0][3]),
                    "timing": timing is not False, "draws": len(a),
                    "correlation_mean": float(a[:, 0].mean()), "correlation_min": float(a[:, 0].min()),
                    "nrmse_rms": float(a[:, 1].mean()), "nrmse_rms_max": float(a[:, 1].max()),
                    "nrmse_range": float(a[:, 2].mean()), "nrmse_range_max": float(a[:, 2].max())})
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=8)
    ap.add_argument("--json", help="also write the results here")
    args = ap.parse_args()
    res = run(args.draws)
    print(f"{'sources':7s} {'pixels':9s} {'flat':5s} {'deblur':6s} {'timing':6s} {'corr mean':>9s} {'corr min':>8s} "
          f"{'RMSE/RMS':>8s} {'(max)':>6s} {'RMSE/range':>10s} {'(max)':>6s}")
    for r in res:
        print(f"{r['sources']:7s} {r['pixels']:9s} {str(r['flat_field']):5s} {str(r['deblur']):6s} "
              f"{str(r['timing']):6s} {r['correlation_mean']:9.4f} {r['correlation_min']:8.4f} "
              f"{r['nrmse_rms']:8.1%} {r['nrmse_rms_max']:6.1%} {r['nrmse_range']:10.1%} {r['nrmse_range_max']:6.1%}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"draws": args.draws, "results": res}, fh, indent=1)


if __name__ == "__main__":
    main()
