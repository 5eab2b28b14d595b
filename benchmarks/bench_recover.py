"""Kernel recovery success rate and time per recovery against laser power (the issue's curves).

    python benchmarks/bench_recover.py                       # 100 trials per power, 3x3 brute, 4x4 and 5x5 search
    python benchmarks/bench_recover.py --trials 20 --json benchmarks/results/recover.json

Each trial draws a random non-zero binary kernel and random 16x16 binary
features, captures the target on the simulated device (default bench and
sensor, fast path, flat-field calibrated) and recovers the kernel with
``evtk.recover.success_rate``: 3x3 by brute force over all 512 candidates,
each captured on the device; 4x4 and 5x5 by the proven search on the
device's linear model. Both cell weightings (relative, plain MSE) are run.
Times are per recovery, excluding the target's capture and including the
candidates' capture for brute force. One process, one core's worth of work.
"""

from __future__ import annotations

import argparse
import json


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=100)
    ap.add_argument("--powers", default="0.05,0.2,1,5,20")
    ap.add_argument("--json", help="also write the rows here")
    args = ap.parse_args()
    from evtk.recover import success_rate

    powers = [float(p) for p in args.powers.split(",")]
    rows = []
    for size in (3, 4, 5):
        for weights in ("relative", None):
            rows += success_rate(powers, size=size, trials=args.trials, weights=weights)
    print(f"{'size':4s} {'method':6s} {'weights':8s} {'power mW':>8s} {'exact %':>7s} {'shift %':>7s} "
          f"{'recovered %':>11s} {'median s':>8s} {'max s':>6s} {'proven %':>8s}")
    for r in rows:
        print(f"{r['size']}x{r['size']} {r['method']:6s} {str(r['weights']):8s} {r['power_mw']:8g} "
              f"{r['exact_pct']:7.1f} {r['shift_pct']:7.1f} {r['recovered_pct']:11.1f} {r['median_s']:8.3f} "
              f"{r['max_s']:6.3f} {r['proven_pct']:8.0f}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"trials": args.trials, "rows": rows}, fh, indent=1)


if __name__ == "__main__":
    main()
