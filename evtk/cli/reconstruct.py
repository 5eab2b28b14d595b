"""``evtk reconstruct`` and ``evtk batch reconstruct``: recordings to responses."""

from __future__ import annotations

import sys

import click

from ._base import (
    _MAX_INT,
    POINT,
    REGION,
    OutputPath,
    _count,
    _dumps,
    _progress,
    _reconstruct_options,
    _reconstruct_settings,
    _reconstructed,
    _scheduler_option,
    main,
)


@main.command("reconstruct")
@click.argument("recording", type=click.Path(dir_okay=False, exists=True))
@click.option("-o", "--output", required=True, type=OutputPath(dir_okay=False), help="Output: .npz, .h5 or .hdf5.")
@_reconstruct_options
@click.option("--png", "png_path", type=OutputPath(dir_okay=False),
              help="Also draw contact sheets: measured beside ideal, and both binarised.")
@click.option("--schedule", "schedule_path", type=click.Path(dir_okay=False, exists=True),
              help="A bench run's schedule.json (evtk patterns): windows matched to its captures, a pixel model "
                   "fitted to its level captures. A simulated recording needs none (its record holds the same).")
@click.option("--calibration", "calibration_path", type=click.Path(dir_okay=False, exists=True),
              help="Where the response lies, from evtk calibrate (default: the run's own dot captures, else the "
                   "bench geometry).")
@click.option("--region", type=REGION, help="Sensor pixels X0,X1,Y0,Y1 the response lies on (instead of a calibration).")
@click.option("--origin-px", type=POINT, help="Sensor pixel X,Y of the response's cell (0, 0), with --region.")
@click.option("--oracle", is_flag=True,
              help="Simulated recordings: invert the simulation record's own pixel model and placement (what a "
                   "perfect calibration gives; a bench has no such answer). Said in the output.")
@click.option("--keep-pixels", is_flag=True,
              help="Fixed windows (--window triggers or period:US): also store every window's ON/OFF counts and "
                   "per-pixel values (windows x region pixels). By default the output holds the responses and "
                   "binary responses only, counted a batch of windows at a time (evtk enob on that file measures the "
                   "responses, not each pixel). Scheduled routes always keep them.")
@click.option("--json", "as_json", is_flag=True, help="Print the summary as one JSON object.")
def reconstruct_cmd(recording, output, png_path, schedule_path, calibration_path, region, origin_px, oracle,
                    keep_pixels, as_json, **settings):
    """Turn a recording into the convolution responses the device computed.

    By default every recording, simulated or from the bench, goes the
    calibrated route: trigger windows matched to the schedule (lost or extra
    edges reported), a pixel model fitted to the run's own level captures,
    the response placed by a calibration. --oracle uses the simulator's
    own model instead; --window triggers or period:US reconstructs fixed
    windows without a schedule.
    """
    from ..io.reconstruction import save_reconstruction  # (light: numpy; HDF5 loads for .h5 outputs only)

    options = _reconstruct_settings(**settings, region=region)
    calibration = None
    if calibration_path:
        from ..calibrate import load_calibration

        if region is not None or origin_px is not None:
            raise click.UsageError("--calibration replaces --region and --origin-px")
        calibration = load_calibration(calibration_path)
    if origin_px is not None and region is None:
        raise click.UsageError("--origin-px goes with --region")
    if oracle and (schedule_path or calibration_path or region is not None):
        raise click.UsageError("--oracle reads the simulation record: leave out --schedule, --calibration and --region")
    if schedule_path and settings["window_spec"] != "schedule":
        raise click.UsageError("--schedule takes the windows from the trigger edges matched to it: leave out --window")
    result, about = _reconstructed(recording, oracle=oracle, schedule=schedule_path, calibration=calibration,
                                   origin_px=origin_px, keep_pixels=keep_pixels, **options.kwargs())
    n_events, sensor = about["events"], about["sensor_size"]
    save_reconstruction(output, result, sensor, {"source": str(recording)})
    pages = []
    if png_path:  # matplotlib only when a figure is asked for (about 1.5 s of a fresh process)
        from ..plots import contact_sheet

        pages = contact_sheet(png_path, result)
    summary = dict(result.summary, output=str(output), events_in_recording=n_events,
                   events_dropped=n_events - result.summary["events_used"], contact_sheet=pages)
    if as_json:
        click.echo(_dumps(summary))
    else:
        err = summary.get("error")
        line = (f"wrote {_count(summary['responses'], 'response')} of {'x'.join(map(str, options.size))} from "
                f"{_count(summary['windows'], 'window')} "
                f"({summary['events_used']:,} of {n_events:,} events used) to {output}")
        if err:
            fmt = lambda v, spec: "n/a" if v is None else format(v, spec)  # noqa: E731
            what = ("the digital correlation of the schedule's patterns (best scale)" if "scale_to_ideal" in summary
                    else "the digital correlation of the schedule's patterns")
            line += (f"\nagainst {what}: correlation {fmt(err['correlation'], '.4f')}, RMS error "
                     f"{fmt(err['nrmse'], '.1%')} of the ideal's RMS, {fmt(err['nrmse_range'], '.1%')} of its range")
        match = summary.get("match")
        if match and (match["missing"] or match["extra"]):
            line += (f"\ntrigger windows: {match['matched']} of {match['captures']} captures matched; missing "
                     f"{match['missing'][:10]}{' ...' if len(match['missing']) > 10 else ''}, {match['extra']} extra"
                     + (f"; pairs left out {summary['pairs_left_out']}" if summary.get("pairs_left_out") else ""))
        if summary.get("route"):
            line += f"\nroute: {summary['route']}" + (f"; response placed by {summary['placement']}"
                                                       if summary.get("placement") else "")
        if summary.get("pixel_model_note"):
            line += f"\nnote: {summary['pixel_model_note']}"
        if abs(summary.get("windows_after_edges_us") or 0) >= 2:  # a µs or so is the fit's own spread
            line += (f"\nwindows: {summary['windows_after_edges_us']} us after the trigger edges, where the fitted "
                     "pixel model puts the light's change")
        if summary.get("timing_skipped"):
            line += f"\nnote: event times were not used: {summary['timing_skipped']}"
        for warning in summary.get("warnings") or []:  # what would otherwise pass unseen (empty windows, ...)
            line += f"\nwarning: {warning}"
        click.echo(line)


@main.group()
def batch():
    """Run a command over many recordings (one task each, resumable, with a manifest)."""


@batch.command("reconstruct")
@click.argument("inputs", nargs=-1, required=True)
@click.option("-o", "--out", "out_dir", required=True, type=OutputPath(file_okay=False),
              help="Folder for the outputs and batch.json.")
@_reconstruct_options
@click.option("--format", "fmt", type=click.Choice(["h5", "npz"]), default="h5", show_default=True)
@click.option("--force", is_flag=True, help="Redo inputs whose output exists.")
@click.option("--oracle", is_flag=True, help="Simulated recordings: the simulation record's own pixel model "
                                              "(see evtk reconstruct --oracle).")
@click.option("--split-events", type=click.IntRange(min=1, max=_MAX_INT), default=50_000_000, show_default=True,
              help="Split recordings with more events than this into tasks by time.")
@_scheduler_option
@click.option("--json", "as_json", is_flag=True, help="Print the manifest as one JSON object.")
def batch_reconstruct_cmd(inputs, out_dir, fmt, force, oracle, split_events, scheduler_spec, as_json, **settings):
    """Reconstruct every recording in INPUTS (files, folders, glob patterns) into OUT.

    Exit status 1 when any input failed; the others are still done, and
    batch.json says what happened to each. A folder's files that are not
    recordings evtk reads are named as left out.
    """
    from ..batch import batch_reconstruct
    from ..cluster import scheduler

    options = dict(_reconstruct_settings(**settings).kwargs(), oracle=oracle)  # the settings of `evtk reconstruct`
    update, finish = _progress(len(inputs), "batch")
    try:
        with scheduler(scheduler_spec) as client:
            manifest = batch_reconstruct(inputs, out_dir, options, fmt=fmt, client=client, progress=update,
                                         force=force, split_events=split_events)
    finally:
        finish()
    c = manifest["counts"]
    if as_json:
        click.echo(_dumps(manifest))
    else:
        click.echo(f"{c['ok']} reconstructed, {c['skipped']} already done, {c['error']} failed "
                   f"({manifest['seconds']:.1f} s); manifest: {out_dir}/batch.json")
        for e in manifest["inputs"]:
            if e["status"] == "error":
                click.echo(f"  failed: {e['input']}: {e['error']}")
        for e in manifest.get("left_out", []):
            click.echo(f"  left out (not a recording evtk reads): {e['file']}: {e['reason']}")
    if c["error"]:
        sys.exit(1)

