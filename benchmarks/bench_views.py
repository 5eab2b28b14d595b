"""Reconstruction error through the camera's view: pose, lens and defocus, oracle beside the calibrated route.

    python benchmarks/bench_views.py                         # both readouts, 2 draws
    python benchmarks/bench_views.py --draws 3 --json benchmarks/results/views.json

Each draw simulates a signed 3x3 kernel on signed 16x16 features (default
bench and pixels, shot noise on; two flat fields, two dot grids, six level
captures) seen through one camera of the table, on the asynchronous readout
and on a 200 us frame readout. Three reconstructions of the same events:

- **oracle**: ``evtk.reconstruct.reconstruct``, the simulation record's own
  pixel model, placement and defocus;
- **calibrated**: ``evtk.reconstruct_recording`` (what ``evtk reconstruct``
  runs): placement, lens and defocus from the run's dot grids, the pixel
  model from its level captures, deblurring regularised by its measured noise;
- **calibrated, not deblurred**: the same with ``deblur=False`` (cells
  sampled through the fitted map).

Reported: mean NRMSE (RMS error over the ideal's RMS) over the draws, and the
calibrated route's over the oracle's.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile

import numpy as np

CAMERAS = [
    ("nominal view", None),
    ("rotation 1°", {"rotation_deg": 1.0}),
    ("rotation 3°", {"rotation_deg": 3.0}),
    ("defocus 0.6 px", {"defocus_px": 0.6}),
    ("defocus 1.0 px", {"defocus_px": 1.0}),
    ("rotation 3°, defocus 0.6 px", {"rotation_deg": 3.0, "defocus_px": 0.6}),
    ("a pose: 1.5°, tilt, offset, scale, k1, vignetting, 0.3 px defocus",
     {"rotation_deg": 1.5, "tilt": (0.03, -0.02), "offset_px": (1.3, -0.6), "scale": 1.02, "k1": 0.03,
      "vignetting": 0.2, "defocus_px": 0.3}),
]


def run(draws, readouts):
    import evtk
    from evtk.reconstruct import reconstruct
    from evtk.sensor import SensorModel
    from evtk.simulate import Simulation

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "run.h5")
        for readout in readouts:
            for name, camera in CAMERAS:
                acc = {"oracle": [], "calibrated": [], "not deblurred": []}
                for d in range(draws):
                    rng = np.random.default_rng(3000 + d)
                    k, f = rng.choice([-1, 1], (3, 3)), rng.choice([-1, 1], (16, 16))
                    Simulation(k, f, seed=d, levels=6, calibration=2, camera=camera,
                               sensor=SensorModel(readout_period_us=readout)).write(path)
                    with evtk.open(path) as rec:
                        acc["oracle"].append(reconstruct(rec).summary["error"]["nrmse"])
                        acc["calibrated"].append(evtk.reconstruct_recording(rec).summary["error"]["nrmse"])
                        acc["not deblurred"].append(
                            evtk.reconstruct_recording(rec, deblur=False).summary["error"]["nrmse"])
                row = {"camera": name, "readout_us": readout, **{k: float(np.mean(v)) for k, v in acc.items()}}
                rows.append(row)
                print(f"| {'asynchronous' if readout == 0 else f'frames, {readout:g} us'} | {name} | "
                      f"{row['oracle']:.3f} | {row['calibrated']:.3f} ({row['calibrated'] / row['oracle']:.2f}x) | "
                      f"{row['not deblurred']:.3f} |", flush=True)
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--draws", type=int, default=2)
    ap.add_argument("--readout", type=float, action="append", help="readout period(s) in us (0: asynchronous)")
    ap.add_argument("--json", dest="json_out")
    args = ap.parse_args()
    readouts = args.readout or [0.0, 200.0]
    print("| readout | camera | oracle NRMSE | calibrated (over the oracle) | calibrated, not deblurred |")
    print("|---|---|---:|---:|---:|")
    rows = run(args.draws, readouts)
    if args.json_out:
        with open(args.json_out, "w") as fh:
            json.dump({"draws": args.draws, "rows": rows}, fh, indent=1)


if __name__ == "__main__":
    main()
