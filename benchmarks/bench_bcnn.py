"""Binary CNN: bit-packed XNOR correlation against scipy on floats, and optimisation steps per second.

    python benchmarks/bench_bcnn.py            # 140 images of 16x16, 3x3 kernel, median of 7
    python benchmarks/bench_bcnn.py --json benchmarks/results/bcnn.json

Times, in one process after a warm-up, median of ``--repeats``:
``evtk.bcnn.binary_correlate`` on a batch of +-1 images against
``scipy.signal.correlate2d`` (mode "full") on the same images as float64,
one call per image (it takes 2-D arrays). Then layerwise annealing steps per second on the FNF training set, digital
and optical backends (600 steps per layer, 3 layers, 1 run each).
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import numpy as np


def _median_time(fn, repeats):
    fn()
    out = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t)
    return statistics.median(out)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--images", type=int, default=140)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--json")
    args = ap.parse_args()
    from scipy import signal

    from evtk.bcnn import BCNN, DigitalBackend, OpticalBackend, binary_correlate
    from evtk.datasets import face_not_face
    from evtk.optimize import train_layerwise

    rng = np.random.default_rng(0)
    x = rng.choice(np.array([-1, 1], np.int8), (args.images, 16, 16))
    k = rng.choice(np.array([-1, 1], np.int8), (3, 3))
    xf, kf = x.astype(np.float64), k.astype(np.float64)
    t_evtk = _median_time(lambda: binary_correlate(x, k), args.repeats)
    t_scipy = _median_time(lambda: [signal.correlate2d(im, kf, "full") for im in xf], args.repeats)
    res = {"images": args.images, "evtk_s": t_evtk, "scipy_s": t_scipy, "ratio": t_scipy / t_evtk}
    print(f"binary correlation of {args.images} 16x16 images with a 3x3 kernel: evtk {1e3 * t_evtk:.3f} ms, "
          f"scipy.signal.correlate2d {1e3 * t_scipy:.3f} ms ({t_scipy / t_evtk:.1f}x)")
    d = face_not_face()
    for backend in (DigitalBackend(), OpticalBackend(seed=0)):
        model = BCNN.random(seed=0)
        rec = train_layerwise(model, backend, d.x_train, d.y_train, steps=600, seed=0)
        rate = rec["steps"] / rec["seconds"]
        res[f"{backend.name}_steps_per_s"] = rate
        evals = sum(layer["kernel_evaluations"] for layer in rec["layers"])
        print(f"annealing, {backend.name} backend: {rate:.0f} steps/s ({rec['steps']} steps, {evals} kernel "
              f"evaluations over the 140 training images, {rec['seconds']:.1f} s)")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(res, fh, indent=1)


if __name__ == "__main__":
    main()
