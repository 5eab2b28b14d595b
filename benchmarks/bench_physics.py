"""The calibrated route on physics it does not assume: evtk's pixel, a v2e-style pixel, a log-node pixel, a frame
readout, a mirrored or turned camera, clock drift, a light that rises; beside the ceiling and two baselines.

    python benchmarks/bench_physics.py                       # 2 draws per physics
    python benchmarks/bench_physics.py --draws 3 --json benchmarks/results/physics.json

Each draw simulates a signed 3x3 kernel on signed 16x16 features (default
bench; two flat fields, two dot grids, six level captures) with one physics
of the table (:class:`evtk.sensor.SensorModel`'s ``pixel``, ``frame_compare``
and ``clock_drift_ppm``; :class:`evtk.optics.camera.Camera`'s ``mirror`` and
``rotation_deg``; the simulation's ``light_rise_us`` and ``light_delay_us``),
then reconstructs the same events by each route:

- **calibrated**: ``evtk.reconstruct_recording`` (what ``evtk reconstruct``
  runs): placement from the run's dot grids, a pixel model fitted to its level
  captures, deblurred;
- **model** and **table**: the same route with its linearisation forced
  (``reconstruct(..., linearization=...)``): the fitted pixel
  model (falling back to exp(n theta) when it misreads the level captures;
  the route before the held-out choice), or the level captures' monotone
  table (:func:`evtk.reconstruct.linearize.level_curve`), both deblurred;
  **calibrated** chooses between them by how well each reads the level
  captures (the table's on levels left out of it);
- **calibrated, not deblurred**: the calibrated route with ``deblur=False``;
- **exp(n theta)**: ``reconstruct(..., linearization="exp(n theta)")`` at the calibration's placement and map (no
  pixel model);
- **level table**: each pixel's ON count minus its OFF count through a
  monotone table from the level captures' mean net counts over the
  interior to their known light (no model), sampled onto the cells
  through the calibration's map, not deblurred;
- **oracle**: ``evtk reconstruct --oracle``, the simulation's own pixel
  model and placement: what knowing the physics is worth (the counts'
  own noise and quantisation are left);
- **ceiling**: the true light each pixel received (the simulated optics,
  no pixel at all) through the calibrated route's map and its deblur, at
  the same regularisation: what a perfect linearisation would give.

Reported per physics and route: mean correlation with the ideal correlation
(signed: an inverted response scores negative) and mean NRMSE after the best
*positive* scale (a negative least-squares scale is clipped to 0, so an
inverted result scores 1 or worse, never better). Runs whose route fails
print the error's first words. Which physics any choice of the route was
tuned on is the ``tuned`` column; the others judge it.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile

import numpy as np

HOT = 12 / (320 * 240)  # about a dozen hot pixels on the default sensor

PHYSICS = [  # (name, SensorModel fields, Simulation keywords, tuned on it)
    ("evtk pixel (default)", {}, {}, True),
    ("v2e pixel: knee at 80 us, leak, shot events, hot pixels",
     {"pixel": "v2e", "tau_min_us": 80.0, "theta_mismatch": 0.008, "leak_rate_hz": 0.5, "shot_event_rate_hz": 1.0,
      "hot_pixel_fraction": HOT, "hot_pixel_rate_hz": 2000.0}, {}, True),
    ("v2e pixel, no hot pixels", {"pixel": "v2e", "tau_min_us": 80.0, "theta_mismatch": 0.008, "leak_rate_hz": 0.5,
                                  "shot_event_rate_hz": 1.0}, {}, False),
    ("log-node pixel (ESIM-like), 3 us rise", {"pixel": "log-node", "theta_mismatch": 0.008}, {"light_rise_us": 3.0},
     False),
    ("frame readout, 150 us, one event per frame", {"readout_period_us": 150.0, "frame_compare": True}, {}, False),
    ("camera mirrored", {}, {"camera": {"mirror": True}}, False),
    ("camera turned 180°", {}, {"camera": {"rotation_deg": 180.0}}, False),
    ("clock drift 50 ppm", {"clock_drift_ppm": 50.0}, {}, False),
    ("light rise 5 us, delay 10 us", {}, {"light_rise_us": 5.0, "light_delay_us": 10}, False),
    ("all at once: v2e pixel, a pose (1.5°, tilt, k1, vignetting, 0.5 px defocus), drift, rise, delay",
     {"pixel": "v2e", "tau_min_us": 80.0, "theta_mismatch": 0.008, "leak_rate_hz": 0.5, "shot_event_rate_hz": 1.0,
      "hot_pixel_fraction": HOT, "hot_pixel_rate_hz": 2000.0, "clock_drift_ppm": 50.0},
     {"camera": {"rotation_deg": 1.5, "tilt": (0.03, -0.02), "k1": 0.03, "vignetting": 0.2, "defocus_px": 0.5},
      "light_rise_us": 5.0, "light_delay_us": 10}, False),
]

ROUTES = ("calibrated", "model", "table", "not deblurred", "exp(n theta)", "level table", "oracle", "ceiling")


def _scaled_error(got, ideal):
    """:func:`evtk.reconstruct.response_error` after the best scale, clipped at 0 (never a sign flip)."""
    from evtk.reconstruct import response_error

    got, ideal = np.asarray(got, float), np.asarray(ideal, float)
    scale = max(float(np.sum(got * ideal) / np.sum(got * got)), 0.0) if np.any(got) else 1.0
    e = response_error(got * scale, ideal)
    e["correlation"] = response_error(got, ideal)["correlation"]
    return e


def _view(cal, shape, bench):
    """The calibration's map as the pipeline takes it: a scale and shift where it is one."""
    from evtk.optics.camera import CellMap

    placement = cal.cell_map()
    aligned = placement.axis_aligned(shape)
    if aligned is None:
        return placement
    return CellMap.scale_shift(aligned[0], aligned[1], (bench.sensor_width, bench.sensor_height))


def _valid(combined, kshape, fshape):
    kh, kw = kshape
    fh, fw = fshape
    return combined[:, kh - 1:fh, kw - 1:fw]


def ceiling(sim, result, cal):
    """The true light of each capture through the calibrated route's map and deblur (same regularisation)."""
    from evtk.optics import glow_response
    from evtk.reconstruct.deblur import sampling_matrix, solve_cells
    from evtk.reconstruct.grid import combine_passes

    region = tuple(int(v) for v in result.counts.region)
    x0, x1, y0, y1 = region
    kshape, fshape = sim.kernels.shape[1:], sim.features.shape[1:]
    shape = (fshape[0] + kshape[0] - 1, fshape[1] + kshape[1] - 1)
    dark = float(glow_response(np.zeros(kshape), sim.bench))
    values = np.stack([sim.pass_response(c, region) - dark for c in range(len(sim.schedule))])
    on_pixels, pairs = combine_passes(values, sim.schedule)
    view = _view(cal, shape, sim.bench)
    a_mat = sampling_matrix(sim.bench, view.to_cells, region, shape, cal.blur_px)
    lam = result.summary.get("deblur_regularisation") or 0.0
    solved, _ = solve_cells(on_pixels.reshape(len(pairs), -1), a_mat, lam)
    return _valid(solved.reshape((len(pairs),) + shape), kshape, fshape), result.ideal


def level_table(sim, result, cal):
    """Net counts through a monotone table from the level captures' mean net counts to their light."""
    from evtk.reconstruct.fit import interior_pixels
    from evtk.reconstruct.grid import combine_passes, sample_response_grid
    from evtk.reconstruct.linearize import level_table_values
    from evtk.simulate import LEVEL_ID

    counts = result.counts
    region = tuple(int(v) for v in counts.region)
    s = sim.schedule
    kshape, fshape = sim.kernels.shape[1:], sim.features.shape[1:]
    shape = (fshape[0] + kshape[0] - 1, fshape[1] + kshape[1] - 1)
    view = _view(cal, shape, sim.bench)
    inside = interior_pixels(region, cal.origin_px, 1.0, kshape, fshape, cell_map=view)
    net = counts.on.astype(float) - counts.off
    is_level = s.kernel_id[counts.windows.capture] == LEVEL_ID
    values = level_table_values(net, net[is_level][:, inside].mean(axis=1),
                                s.level[counts.windows.capture][is_level].astype(float))
    cells = sample_response_grid(values, region, view, shape)
    combined, _ = combine_passes(cells, s.take(counts.windows.capture))
    return _valid(combined, kshape, fshape), result.ideal


def run(draws, physics=None):
    import evtk
    from evtk.calibrate import calibrate
    from evtk.patterns import write_patterns
    from evtk.plan import as_plan
    from evtk.reconstruct import reconstruct, schedule_of_record
    from evtk.sensor import SensorModel
    from evtk.simulate import Simulation
    from evtk.simulate.record import SimulationRecord

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "run.h5")
        for name, sensor, extra, tuned in PHYSICS:
            if physics and not any(p in name for p in physics):
                continue
            acc = {k: [] for k in ROUTES}
            errors = {}
            for d in range(draws):
                rng = np.random.default_rng(4000 + d)
                k, f = rng.choice([-1, 1], (3, 3)), rng.choice([-1, 1], (16, 16))
                sim = Simulation(k, f, sensor=SensorModel(**sensor), seed=d, levels=6, calibration=2, **extra)
                sim.write(path)
                write_patterns(sim, os.path.join(tmp, "p"))
                with evtk.open(path) as rec:
                    sched = schedule_of_record(SimulationRecord.from_metadata(rec.metadata))
                    got = {}
                    try:
                        cal = calibrate(rec, sched)
                        res = evtk.reconstruct_recording(rec)
                        got["calibrated"] = (res.cells, res.ideal)
                        got["ceiling"] = ceiling(sim, res, cal)
                        got["level table"] = level_table(sim, res, cal)
                        for key in ("model", "table"):  # the route with one linearisation forced
                            r = reconstruct(rec, sched.replace(region=cal.region, origin_px=cal.origin_px,
                                                               cell_map=cal.cell_map(), blur_px=cal.blur_px),
                                            linearization=key)
                            got[key] = (r.cells, r.ideal)
                    except Exception as exc:  # noqa: BLE001 - a benchmark reports what failed and goes on
                        errors.setdefault("calibrated", str(exc)[:60])
                    for key in ("not deblurred", "exp(n theta)", "oracle"):
                        try:
                            if key == "not deblurred":
                                r = evtk.reconstruct_recording(rec, deblur=False)
                            elif key == "oracle":
                                r = evtk.reconstruct_recording(rec, oracle=True)
                            else:
                                placed = calibrate(rec, sched)
                                r = reconstruct(rec, placed.place(as_plan(os.path.join(tmp, "p", "schedule.json"))),
                                                linearization="exp(n theta)")
                            got[key] = (r.cells, r.ideal)
                        except Exception as exc:  # noqa: BLE001
                            errors.setdefault(key, str(exc)[:60])
                for key, (cells, ideal) in got.items():
                    e = _scaled_error(cells, ideal)
                    acc[key].append((e["correlation"], e["nrmse"]))
            row = {"physics": name, "tuned": tuned, "errors": errors}
            for key, vals in acc.items():
                row[key] = None if len(vals) < draws else {
                    "correlation": float(np.mean([v[0] for v in vals])),
                    "nrmse_scaled": float(np.mean([v[1] for v in vals]))}
            rows.append(row)
            print(_line(row), flush=True)
    return rows


def _line(r):
    def cell(key):
        v = r[key]
        if v is None:
            return "error: " + r["errors"].get(key, r["errors"].get("calibrated", "?"))
        return f"{v['correlation']:.3f} / {v['nrmse_scaled']:.2f}"
    return f"| {r['physics']} | {'yes' if r['tuned'] else 'no'} | " + " | ".join(cell(k) for k in ROUTES) + " |"


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--draws", type=int, default=2)
    ap.add_argument("--physics", action="append", help="only the physics whose name holds this text")
    ap.add_argument("--json", dest="json_out")
    args = ap.parse_args()
    print("| physics | tuned on | calibrated: r / NRMSE | model | table | calibrated, not deblurred | exp(n theta) | "
          "level table, not deblurred | oracle | ceiling (true light, same map and deblur) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    rows = run(args.draws, args.physics)
    if args.json_out:
        with open(args.json_out, "w") as fh:
            json.dump({"draws": args.draws, "rows": rows}, fh, indent=1)


if __name__ == "__main__":
    main()
