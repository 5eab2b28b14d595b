"""``evtk simulate`` and ``evtk demo``: the simulated device."""

from __future__ import annotations

import click
import numpy as np

from ..errors import EvtkError
from ._base import _MAX_INT, OutputPath, _dumps, _fmt, _progress, main


@main.command()
@click.option("--kernel", "kernel_path", type=click.Path(dir_okay=False, exists=True),
              help="Kernel(s): .npy (h, w) or (n, h, w), or an image.")
@click.option("--kernel-bits", help="Kernel as a bit string filling a square row by row, e.g. 101010101.")
@click.option("--features", "features_path", type=click.Path(dir_okay=False, exists=True),
              help="Features: .npy (h, w) or (n, h, w), or an image (binarised). Default: a 16x16 "
                   "binarised picture bundled with scikit-image.")
@click.option("--signed", is_flag=True, help="Read 0 as -1 in kernels and features (four passes per pair).")
@click.option("--repeat", type=click.IntRange(min=1, max=_MAX_INT), default=1, show_default=True,
              help="Times each pair is shown.")
@click.option("--flat-field", type=click.IntRange(min=0, max=_MAX_INT), default=2, show_default=True,
              help="Flat-field captures (all mirrors on) shown first, for per-pixel threshold calibration.")
@click.option("--levels", type=click.IntRange(min=0, max=_MAX_INT), default=6, show_default=True,
              help="Level captures (a staircase of light) after the flat fields: reconstruction fits the pixel model "
                   "to them instead of assuming one. 0: none.")
@click.option("--calibration", type=click.IntRange(min=0, max=_MAX_INT), default=0, show_default=True,
              help="Dot-grid captures, for evtk calibrate (where the response lies on the sensor).")
@click.option("--power-mw", type=float, help="Laser power (default: the bench's).")
@click.option("--window-us", type=click.IntRange(min=1, max=_MAX_INT), default=1000, show_default=True,
              help="How long each pattern is shown.")
@click.option("--settle-us", type=click.IntRange(min=1, max=_MAX_INT), help="Darkness after each pattern (default: recommended).")
@click.option("--bench", "bench_path", type=click.Path(dir_okay=False), help="Bench description (.toml or .json).")
@click.option("--seed", type=click.IntRange(min=0, max=_MAX_INT), default=0, show_default=True)
@click.option("--compression", type=click.Choice(["lz4", "zstd", "none", "lz4_high", "zstd_high", "gzip"]),
              default="lz4", show_default=True)
@click.option("-o", "--output", required=True, type=OutputPath(dir_okay=False),
              help="Recording to write: .aedat4, .h5/.hdf5 or .parquet.")
@click.option("--save-bench", type=OutputPath(dir_okay=False), help="Also write the bench used (.toml or .json).")
@click.option("--job", "job_path", type=click.Path(dir_okay=False, exists=True),
              help="A job file (.toml/.json, as `evtk patterns` takes) instead of the pattern and timing options.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
@click.pass_context
def simulate(ctx, kernel_path, kernel_bits, features_path, signed, repeat, flat_field, levels, calibration, power_mw,
             window_us, settle_us, bench_path, seed, compression, output, save_bench, job_path, as_json):
    """Simulate the device and write the event recording it would produce."""
    from ..optics import Bench, load_bench
    from ..sensor import SensorModel
    from ..simulate import Simulation, default_features, load_patterns

    if job_path:
        given = [f"--{name.replace('_', '-')}" for name in ("kernel_path", "kernel_bits", "features_path", "signed",
                                                             "repeat", "flat_field", "levels", "calibration",
                                                             "window_us", "settle_us",
                                                             "bench_path", "seed")
                 if ctx.get_parameter_source(name) == click.core.ParameterSource.COMMANDLINE]
        if given:
            raise click.UsageError(f"--job sets the patterns and timing; leave out {', '.join(given)}")
        from ..patterns import load_job

        job = load_job(job_path)
        if power_mw is not None:
            job["bench"] = job["bench"].replace(power_mw=power_mw)
        kernel, features, bench, sensor = job.pop("kernels"), job.pop("features"), job.pop("bench"), job.pop("sensor")
        try:
            sim = Simulation(kernel, features, bench, sensor, **job)
        except EvtkError as exc:
            raise EvtkError(f"{job_path}: {exc}") from None
        return _write_simulation(sim, bench, sensor, compression, output, save_bench, as_json)
    if kernel_path and kernel_bits:
        raise EvtkError("give --kernel or --kernel-bits, not both")
    if kernel_bits is not None and not (kernel_bits and set(kernel_bits) <= {"0", "1"}):
        raise EvtkError(f"--kernel-bits must be a string of 0s and 1s, not {kernel_bits!r}")
    kernel = load_patterns(kernel_path or kernel_bits or "010111010", "kernel")
    features = load_patterns(features_path, "features") if features_path else default_features()
    if signed:
        kernel = np.where(np.asarray(kernel) > 0, 1, -1)
        features = np.where(np.asarray(features) > 0, 1, -1)
    bench, sensor = (Bench(), {}) if bench_path is None else load_bench(bench_path)
    if power_mw is not None:
        bench = bench.replace(power_mw=power_mw)
    sensor = SensorModel.from_dict(sensor)
    sim = Simulation(kernel, features, bench, sensor, window_us=window_us, settle_us=settle_us, repeat=repeat,
                     seed=seed, flat_field=flat_field, levels=levels, calibration=calibration)
    _write_simulation(sim, bench, sensor, compression, output, save_bench, as_json)


def _write_simulation(sim, bench, sensor, compression, output, save_bench, as_json):
    from ..optics import save_bench as _save_bench

    update, finish = _progress(len(sim.schedule), "simulating")
    try:
        summary = sim.write(output, compression=compression, progress=update)
    finally:
        finish()
    if save_bench:
        _save_bench(save_bench, bench, sensor)
    summary.update({
        "sigma": bench.sigma, "varsigma": bench.varsigma, "kernel_mirrors": bench.kernel_mirrors,
        "stride_eff": bench.stride_eff, "min_window_us": bench.min_window_us,
        "kernel_shape": list(sim.kernels.shape[1:]), "features_shape": list(sim.features.shape[1:]),
        "response_region": list(sim.region),
        "fresnel_number": bench.fresnel_number, "shadow_model_note": bench.shadow_model_note(),
    })
    if as_json:
        click.echo(_dumps(summary))
    else:
        span = (summary["t_end_us"] - summary["t_start_us"]) / 1e6
        click.echo(f"wrote {summary['events']:,} events and {summary['triggers']:,} triggers "
                   f"({summary['captures']:,} captures, {span:.3f} s) to {output}\n"
                   f"sigma {bench.sigma:.4g} (eq. 3), varsigma {bench.varsigma:.4g} (eq. 4; shown as "
                   f"{bench.kernel_mirrors} mirrors), effective stride {bench.stride_eff:.4g} (eq. 6), "
                   f"e_min {bench.min_window_us:g} us (eq. 7), settle {summary['settle_us']} us")
        if bench.shadow_model_note():
            click.echo(f"note: {bench.shadow_model_note()}", err=True)


@main.command()
@click.option("--out", "out_dir", default="evtk-demo", show_default=True, type=OutputPath(file_okay=False),
              help="Directory for the recording, the reconstruction and the plots.")
@click.option("--repeat", type=click.IntRange(min=2, max=_MAX_INT), default=10, show_default=True)
@click.option("--seed", type=click.IntRange(min=0, max=_MAX_INT), default=0, show_default=True)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def demo(out_dir, repeat, seed, as_json):
    """The main job on the embedded defaults: simulate, record, reconstruct, report.

    A 3x3 kernel (a plus sign, as ``evtk simulate``) on a 16x16 binary
    feature map made from scikit-image's camera picture, shown on the
    paper's bench; the event stream goes to an
    AEDAT4 file, is reconstructed, and compared with the digital correlation.
    """
    from ..demo import run_demo

    summary = run_demo(out_dir, repeat, seed, status=lambda text: click.echo(f"evtk demo: {text}", err=True),
                       progress_factory=_progress)
    s, fl, err = summary["sinad"], summary["flips"], summary["error"]
    written, rec_path, out_h5 = summary, summary["recording"], summary["reconstruction"]
    sheet, enob_png = ", ".join(summary["contact_sheet"]), summary["enob_plot"]
    if as_json:
        click.echo(_dumps(summary))
        return
    if s is None:
        enob_txt = "n/a (no signal)"
    elif s["noise_free"]:
        enob_txt = "inf (noise-free)"
    else:
        ci = "" if s["ci_enob"] is None else f" (95 % {_fmt(s['ci_enob'][0], '.2f')}..{_fmt(s['ci_enob'][1], '.2f')})"
        enob_txt = f"{s['enob_bits']:.2f} bits{ci}, SINAD {s['sinad_db']:.1f} dB"
    click.echo("\n".join([
        f"simulated {written['captures']} captures ({repeat} repeats of a 3x3 kernel on 16x16 binary features, "
        f"2 flat fields, 6 level captures): {written['events']:,} events",
        f"route: {summary['route']}",
        f"against the digital correlation: correlation {_fmt(err['correlation'], '.3f')}, RMS error "
        f"{_fmt(err['nrmse'], '.1%')} of the ideal's RMS ({_fmt(err['nrmse_range'], '.1%')} of its range)",
        f"effective bits (eq. 8): {enob_txt}",
        f"binary pixels (16x16, binarised by {summary['binarize']}) flipped between repeats: "
        f"{fl['pairwise_pct']:.2f} % (pairs), {fl['majority_pct']:.2f} % against the majority",
        f"files: {rec_path}, {out_h5}, {sheet}, {enob_png}",
        f"done in {summary['seconds']:.1f} s",
    ]))


@main.command(short_help="DMD frames and the capture schedule of a job, for the bench.")
@click.argument("job_path", metavar="JOB", type=click.Path(dir_okay=False, exists=True))
@click.option("-o", "--out", "out_dir", required=True, type=OutputPath(file_okay=False),
              help="Folder for the frames (kernel/, features/, dark) and schedule.json.")
@click.option("--format", "image_format", type=click.Choice(["png", "bmp"]), default="png", show_default=True,
              help="1-bit images at the DMD's resolution.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def patterns(job_path, out_dir, image_format, as_json):
    """Write the frame each DMD shows for every capture of JOB, and the schedule that says which trigger edge
    starts which frame pair. `evtk simulate --job JOB` simulates the same run."""
    from ..patterns import job_simulation, write_patterns

    summary = write_patterns(job_simulation(job_path), out_dir, image_format)
    if as_json:
        click.echo(_dumps(summary))
        return
    click.echo(f"wrote {summary['kernel_frames']} kernel and {summary['features_frames']} features frames "
               f"({summary['dmd'][0]}x{summary['dmd'][1]} mirrors, 1 bit, {summary['format']}) for "
               f"{summary['captures']} captures; schedule: {summary['schedule']}")


@main.command(short_help="Where the response lies on the sensor, from the recording's calibration dots.")
@click.argument("recording", type=click.Path(dir_okay=False, exists=True))
@click.option("--schedule", "schedule_path", type=click.Path(dir_okay=False, exists=True),
              help="The schedule.json evtk patterns wrote for the run (its job needs calibration = N; levels = N "
                   "also fits the pixel model). A simulated recording's own record stands in for it.")
@click.option("-o", "--output", required=True, type=OutputPath(dir_okay=False),
              help="Calibration to write (.toml or .json), for evtk reconstruct --calibration.")
@click.option("--png", "png_path", type=OutputPath(dir_okay=False), help="Also draw the dots, the fit and residuals.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def calibrate(recording, schedule_path, output, png_path, as_json):
    """Fit the map from response cells to sensor pixels (projective, RANSAC) from the dot-grid captures,
    and the pixel model from the level captures when the run has them."""
    from .. import io as evio
    from ..calibrate import calibrate as run
    from ..calibrate import plot_calibration, save_calibration
    from ..reconstruct import schedule_of_record
    from ..simulate import SimulationRecord

    with evio.open(recording) as rec:
        if schedule_path is None:
            record = SimulationRecord.from_metadata(rec.metadata)
            if record is None:
                raise click.UsageError("a bench recording needs --schedule (the schedule.json of its run)")
            schedule_path = schedule_of_record(record)
        cal = run(rec, schedule_path)
    save_calibration(output, cal)
    if png_path:
        plot_calibration(png_path, cal)
    if as_json:
        click.echo(_dumps(dict(cal.to_dict(), output=str(output))))
        return
    click.echo(f"{cal.dots_found} of {cal.dots_expected} dots found, {cal.inliers} fit one map: residual RMS "
               f"{cal.residual_rms_px:.3f} px (max {cal.residual_max_px:.3f}); response origin "
               f"({cal.origin_px[0]:.2f}, {cal.origin_px[1]:.2f}) px, {cal.step_px:.4f} px per cell, region "
               f"{cal.region}; written to {output}")
    if cal.background_rate_hz is not None:
        click.echo(f"background activity outside the response: {cal.background_rate_hz:.3g} events per pixel "
                   "and second")
    m = cal.pixel_model
    if m:
        click.echo(f"pixel model from {len(m['levels'])} level steps: threshold {m['theta_on']:.3f}, time constant "
                   f"{m['tau_min_us']:.0f} us bright to {m['tau_dark_us']:.0f} us dark, dark level "
                   f"{m['blank_units']:.4f} units of light, counts fitted to {m['rms_counts']:.2f} RMS"
                   + (f"; refractory period {m['refractory_us']:.1f} us" if m.get("refractory_resolved") else
                      f"; refractory period at most {m['refractory_bound_us']:.0f} us"
                      if m.get("refractory_bound_us") is not None else ""))
        if abs(m.get("light_delay_us", 0.0)) >= 2:  # a µs or so is the fit's own spread
            click.echo(f"the light follows the trigger edges by {m['light_delay_us']:.1f} us; reconstruction windows "
                       "follow it")
    if cal.blur_px > 0:
        click.echo(f"camera defocus: {cal.blur_px:.2f} px (Gaussian sigma, beyond the bench's footprint)")
    if cal.orientation not in (None, "upright"):
        click.echo(f"the camera sees the screen {cal.orientation} (from the dot grid's marker); the map holds it")
    for warning in cal.warnings:  # what the calibration assumed or left out
        click.echo(f"warning: {warning}")

