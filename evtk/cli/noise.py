"""``evtk enob``, ``evtk flips`` and ``evtk tradeoff``: the noise reports."""

from __future__ import annotations

import click
import numpy as np

from .. import io as evio  # (light: its readers and writers load on first use)
from ..errors import EvtkError, check_positive
from ._base import (
    _MAX_INT,
    OutputPath,
    _dumps,
    _inf_if_free,
    _progress,
    _scene_rows,
    _scheduler_option,
    _table,
    _theta_option,
    _with_window_options,
    main,
    number_list,
)


@main.command(short_help="SINAD and effective bits (eq. 8) of every repeated scene.")
@click.argument("recording", type=click.Path(dir_okay=False, exists=True))
@_with_window_options
@click.option("--interval", type=click.Choice(["jackknife", "bootstrap", "none"]), default="jackknife",
              show_default=True, help="The 95 % interval over repeats (the bootstrap undercovers with few repeats).")
@click.option("--per-pixel", is_flag=True, help="Also report each pixel's SINAD (JSON only).")
@_theta_option
@click.option("--plot", "plot_path", type=OutputPath(dir_okay=False), help="ENOB per scene as a PNG.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def enob(recording, window_spec, skip_us, length_us, interval, per_pixel, theta, plot_path, as_json):
    """SINAD and effective bits (eq. 8) of every scene captured more than once.

    Without a schedule every window is a repeat of one scene; they are
    measured a batch at a time, so memory stays bounded however many.
    Their values are net counts ON - OFF, or exp(n theta) - 1 with --theta
    (as reconstruct gives them).
    """
    from ..io.reconstruction import is_reconstruction

    if theta is not None:  # NaN, infinity or <= 0 refused as reconstruct refuses them (ReconstructOptions)
        check_positive(theta=theta)
    if is_reconstruction(recording):  # the responses of an earlier `evtk reconstruct`
        if theta is not None:
            raise EvtkError(f"--theta linearises a recording's counts; {recording} holds responses already")
        from ..reconstruct.files import load_reconstruction
        from ..sweeps import scene_noise

        scenes = scene_noise(load_reconstruction(recording), interval=None if interval == "none" else interval,
                             per_pixel=per_pixel)
        for s in scenes:
            s["route"] = f"the responses stored in {recording}" + (f" ({s['route']})" if s.get("route") else "")
    else:
        scenes = _recording_noise(recording, window_spec, skip_us, length_us, interval, per_pixel, theta)
    _report_scenes(recording, scenes, plot_path, as_json)


def _recording_noise(recording, window_spec, skip_us, length_us, interval, per_pixel, theta=None):
    from ..sweeps import recording_noise

    with evio.open(recording) as rec:
        update, finish = _progress(rec.info()["events"], f"measuring {recording}")
        try:
            scenes = recording_noise(rec, window_spec, skip_us, length_us,
                                     interval=None if interval == "none" else interval, per_pixel=per_pixel,
                                     progress=update, **({} if theta is None else {"theta": theta}))
        finally:
            finish()
    return scenes


def _report_scenes(recording, scenes, plot_path, as_json):
    if plot_path:
        from ..plots import plot_enob

        plot_enob(scenes, plot_path)
    rows = _scene_rows(scenes)
    routes = list(dict.fromkeys(s["route"] for s in scenes if s.get("route")))
    if as_json:
        click.echo(_dumps({"file": str(recording), "route": "; ".join(routes) or None, "scenes": rows}))
        return
    for route in routes:  # a recording and its own reconstruction can be measured by different routes: say which
        click.echo(f"route: {route}")
    ci = lambda r, i: None if r["sinad"] is None or r["sinad"]["ci_enob"] is None else r["sinad"]["ci_enob"][i]  # noqa: E731
    sin = lambda key: lambda r: None if r["sinad"] is None else r["sinad"][key]  # noqa: E731
    click.echo(_table(rows, [
        ("kernel", "kernel_id", "d"), ("features", "features_id", "d"), ("repeats", "repeats", "d"),
        ("SINAD dB", lambda r: _inf_if_free(r, "sinad_db"), ".2f"), ("ENOB", lambda r: _inf_if_free(r, "enob_bits"), ".2f"),
        ("ENOB 95% lo", lambda r: ci(r, 0), ".2f"), ("hi", lambda r: ci(r, 1), ".2f"),
        ("noise std", sin("noise_std"), ".4g"), ("flips %", lambda r: r["flips"]["pairwise_pct"], ".2f"),
    ]))
    if plot_path:
        click.echo(f"plot: {plot_path}")


@main.command()
@click.argument("recordings", nargs=-1, type=click.Path(dir_okay=False, exists=True))
@_with_window_options
@click.option("--power-mw", "powers", type=number_list("--power-mw"), default="0.05,0.2,1,5,20", show_default=True,
              help="Without recordings: laser powers to sweep on the simulated bench.")
@click.option("--kernels", "n_kernels", type=click.IntRange(min=1, max=_MAX_INT), default=11, show_default=True,
              help="Without recordings: random signed 3x3 kernels to show.")
@click.option("--repeats", type=click.IntRange(min=2, max=_MAX_INT), default=10, show_default=True,
              help="Without recordings: captures of each kernel per power.")
@click.option("--window-us", type=click.IntRange(min=1, max=_MAX_INT), default=1000, show_default=True,
              help="Without recordings: capture window.")
@click.option("--seed", type=click.IntRange(min=0, max=_MAX_INT), default=0, show_default=True)
@click.option("--plot", "plot_path", type=OutputPath(dir_okay=False), help="Flip rate against power as a PNG.")
@_scheduler_option
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def flips(recordings, window_spec, skip_us, length_us, powers, n_kernels, repeats, window_us, seed, plot_path,
          scheduler_spec, as_json):
    """Pixels whose binarised response flips between repeats, per kernel and light power.

    With RECORDINGS: each is reconstructed (16x16, binarised as reconstruct does) and its scenes
    compared over their repeats. Without: the paper's Fig. 3 (right) on the
    simulated bench: random kernels on the default features, swept over
    laser power.
    """
    from ..simulate import SimulationRecord, default_features
    from ..sweeps import flip_sweep, random_kernels, recording_noise

    if recordings:
        rows = []
        for i, path in enumerate(recordings):
            with evio.open(path) as rec:
                sim = SimulationRecord.from_metadata(rec.metadata)
                power = None if sim is None else sim.bench.power_mw
                scenes = recording_noise(rec, window_spec, skip_us, length_us, interval=None)
            for s in scenes:
                rows.append({"file": str(path), "file_index": i, "power_mw": power, "kernel_id": s["kernel_id"],
                             "features_id": s["features_id"], "repeats": s["repeats"],
                             "pairwise_pct": s["flips"].pairwise_pct, "majority_pct": s["flips"].majority_pct})
        x_key = "power_mw" if all(r["power_mw"] is not None for r in rows) else "file_index"
    else:
        power_list = powers
        kernels = random_kernels(n_kernels, seed=seed)
        features = np.where(default_features() > 0, 1, -1)
        from ..cluster import scheduler

        update, finish = _progress(len(power_list), "sweeping power")
        try:
            with scheduler(scheduler_spec) as client:
                rows = flip_sweep(power_list, kernels, features, repeats=repeats, window_us=window_us, seed=seed,
                                  progress=update, client=client)
        finally:
            finish()
        x_key = "power_mw"
    if plot_path:
        from ..plots import plot_flips

        plot_flips(rows, plot_path, x_key=x_key, x_label="laser power (mW)" if x_key == "power_mw" else "recording")
    if as_json:
        click.echo(_dumps({"rows": rows}))
        return
    by_x = {}
    for r in rows:
        by_x.setdefault(r[x_key], []).append(r)
    summary = [{"x": x, "kernels": len(v), "pairwise": float(np.mean([r["pairwise_pct"] for r in v])),
                "majority": float(np.mean([r["majority_pct"] for r in v])),
                "worst": float(np.max([r["pairwise_pct"] for r in v]))} for x, v in by_x.items()]
    click.echo(_table(summary, [("power mW" if x_key == "power_mw" else "recording", "x", "g"),
                                ("kernels", "kernels", "d"), ("flips % (pairs)", "pairwise", ".2f"),
                                ("vs majority %", "majority", ".2f"), ("worst kernel %", "worst", ".2f")]))
    if plot_path:
        click.echo(f"plot: {plot_path}")


@main.command()
@click.option("--window-us", "windows", type=number_list("--window-us", integer=True), default="200,300,500,1000,2000",
              show_default=True,
              help="Capture windows to sweep (us, at least eq. 7's minimum).")
@click.option("--power-mw", "powers", type=number_list("--power-mw"), help="Laser powers to sweep (default: the bench's).")
@click.option("--settle-us", "settles", type=number_list("--settle-us", integer=True),
              help="Dark times after each pattern to sweep (default: recommended).")
@click.option("--decimation", "decimations", type=number_list("--decimation", integer=True),
              help="Decimations to sweep (keep every d-th pixel; default 1).")
@click.option("--kernels", "n_kernels", type=click.IntRange(min=1, max=_MAX_INT), default=2, show_default=True,
              help="Random signed 3x3 kernels on the default features.")
@click.option("--repeats", type=click.IntRange(min=2, max=_MAX_INT), default=10, show_default=True)
@click.option("--seed", type=click.IntRange(min=0, max=_MAX_INT), default=0, show_default=True)
@click.option("--fast", is_flag=True, help="Time the reconstruction from counts instead of from a written recording.")
@click.option("--plot", "plot_path", type=OutputPath(dir_okay=False), help="Work-precision plot as a PNG.")
@_scheduler_option
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def tradeoff(windows, powers, settles, decimations, n_kernels, repeats, seed, fast, plot_path, scheduler_spec,
             as_json):
    """Error, ENOB and flips against time per capture on the simulated bench (Pareto front marked *)."""
    from ..simulate import default_features
    from ..sweeps import random_kernels
    from ..sweeps import tradeoff as run_tradeoff

    w = windows
    p = powers if powers else None
    z = settles if settles else None
    d = decimations if decimations else None
    n_settings = len(w) * (len(p) if p else 1) * (len(z) if z else 1) * (len(d) if d else 1)
    from ..cluster import scheduler

    update, finish = _progress(n_settings, "sweeping")
    try:
        with scheduler(scheduler_spec) as client:
            rows = run_tradeoff(w, random_kernels(n_kernels, seed=seed), np.where(default_features() > 0, 1, -1),
                                powers_mw=p, settles_us=z, decimations=d, repeats=repeats, seed=seed,
                                time_events=not fast, progress=update, client=client)
    finally:
        finish()
    if plot_path:
        from ..plots import plot_tradeoff

        plot_tradeoff(rows, plot_path)
    if as_json:
        click.echo(_dumps({"rows": rows}))
        return
    click.echo(_table(rows, [
        ("Pareto", lambda r: "*" if r["pareto"] else "", "s"), ("power mW", "power_mw", "g"), ("window us", "window_us", "d"),
        ("settle us", "settle_us", "d"), ("decimation", "decimation", "d"), ("device us/capture", "device_us_per_capture", ".0f"),
        ("compute us/capture", "compute_us_per_capture", ".0f"), ("corr", "correlation", ".3f"),
        ("RMSE/RMS", "nrmse", ".3f"), ("ENOB", lambda r: float("inf") if r["noise_free"] else r["enob_bits"], ".2f"),
        ("flips %", "flip_pct", ".2f"),
    ]))
    if plot_path:
        click.echo(f"plot: {plot_path}")
