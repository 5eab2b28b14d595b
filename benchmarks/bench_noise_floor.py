"""Where the calibrated route's error comes from: the counts' own noise, measured against repeats.

    python benchmarks/bench_noise_floor.py                  # repeats 1, 4, 16; 2 draws each
    python benchmarks/bench_noise_floor.py --repeats 1,4 --draws 1

Each draw simulates the accuracy table's default job (a signed 3x3 kernel on
signed 16x16 features, evtk's pixel, two flat fields, two dot grids, six level
captures; ``bench_physics.py``) with every capture repeated ``R`` times, and
reports the NRMSE (after the best positive scale) of

- **calibrated**: ``evtk.reconstruct_recording``, one capture at a time;
- **oracle**: the simulation's own pixel model and placement, one capture at a
  time (what knowing the physics exactly is worth);
- **ceiling**: the true light through the calibrated route's map and deblur
  (``bench_physics.ceiling``);
- **calibrated, mean of R**: the calibrated responses of each scene averaged
  over its ``R`` repeats, against the same ideal.

If the error were the linearisation's, the oracle would sit near the ceiling
and averaging would not help; if it is the counts' noise, the oracle sits with
the calibrated route and averaging repeats brings both down.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


def scene_means(result):
    """Each scene's responses averaged over its repeats, with one ideal per scene."""
    groups = result.groups()
    cells = np.stack([result.cells[idx].mean(axis=0) for idx in groups.values()])
    ideal = np.stack([result.ideal[idx[0]] for idx in groups.values()])
    return cells, ideal


def run(repeats, draws):
    from bench_physics import _scaled_error, ceiling

    import evtk
    from evtk.calibrate import calibrate
    from evtk.reconstruct.calibrated import schedule_of_record
    from evtk.simulate import Simulation
    from evtk.simulate.record import SimulationRecord

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "run.h5")
        for rep in repeats:
            got = []
            for d in range(draws):
                rng = np.random.default_rng(4000 + d)
                k, f = rng.choice([-1, 1], (3, 3)), rng.choice([-1, 1], (16, 16))
                sim = Simulation(k, f, seed=d, levels=6, calibration=2, repeat=rep)
                sim.write(path)
                with evtk.open(path) as rec:
                    cal = calibrate(rec, schedule_of_record(SimulationRecord.from_metadata(rec.metadata)))
                    res = evtk.reconstruct_recording(rec)
                    oracle = evtk.reconstruct_recording(rec, oracle=True)
                    got.append([_scaled_error(res.cells, res.ideal)["nrmse"],
                                _scaled_error(oracle.cells, oracle.ideal)["nrmse"],
                                _scaled_error(*ceiling(sim, res, cal))["nrmse"],
                                _scaled_error(*scene_means(res))["nrmse"]])
            m = np.mean(got, axis=0)
            rows.append({"repeats": rep, "calibrated": m[0], "oracle": m[1], "ceiling": m[2], "mean_of_repeats": m[3]})
            print(f"| {rep} | {m[0]:.3f} | {m[1]:.3f} | {m[2]:.3f} | {m[0] / m[2]:.1f}x | {m[3]:.3f} | "
                  f"{m[3] / m[2]:.1f}x |", flush=True)
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", default="1,4,16", help="comma-separated repeats per capture")
    ap.add_argument("--draws", type=int, default=2)
    args = ap.parse_args()
    print("| repeats | calibrated | oracle | ceiling | calibrated / ceiling | calibrated, mean of repeats | "
          "mean / ceiling |")
    print("|---|---|---|---|---|---|---|")
    run([int(v) for v in args.repeats.split(",")], args.draws)


if __name__ == "__main__":
    main()
