"""The ``evtk`` command: one sub-command per library entry point."""

from __future__ import annotations

import json
import sys

import click
import numpy as np

from . import io as evio  # (light: its readers and writers load on first use)
from ._version import __version__
from .errors import EvtkError, one_line

#: Largest whole number an option takes: microseconds and counts stay far inside int64 arithmetic.
_MAX_INT = 2**62


class _Group(click.Group):
    """Turns evtk errors and OS errors into one line on stderr and exit code 1; usage errors into one line and 2."""

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True, **extra):
        if not standalone_mode:
            return super().main(args, prog_name, complete_var, standalone_mode, **extra)
        try:
            rv = super().main(args, prog_name, complete_var, standalone_mode=False, **extra)
        except click.UsageError as exc:
            where = exc.ctx.command_path if exc.ctx is not None else "evtk"
            click.echo(f"evtk: error: {exc.format_message()} (see '{where} --help')", err=True)
            sys.exit(exc.exit_code)
        except click.ClickException as exc:
            click.echo(f"evtk: error: {exc.format_message()}", err=True)
            sys.exit(exc.exit_code)
        except click.Abort:
            click.echo("evtk: aborted", err=True)
            sys.exit(1)
        except KeyboardInterrupt:
            click.echo("evtk: interrupted", err=True)
            sys.exit(130)
        sys.exit(rv if isinstance(rv, int) else 0)

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except (EvtkError, OSError, MemoryError) as exc:
            if ctx.meta.get("evtk.debug"):
                raise
            msg = str(exc) if isinstance(exc, EvtkError) else f"{type(exc).__name__}: {exc}"
            click.echo(f"evtk: error: {one_line(msg)}", err=True)
            ctx.exit(1)


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="evtk")
@click.option("--debug", is_flag=True, help="Show the full traceback on errors.")
@click.option("--trust-external", is_flag=True,
              help="Let HDF5 files read other files (external links, external storage, virtual datasets).")
@click.option("--verify-checksums", is_flag=True,
              help="Check the xxHash checksums of AEDAT4 LZ4 bodies that carry them (slower; structure is always checked).")
@click.option("--memory-limit-mb", type=click.FloatRange(min=1, max=2**40),
              help="Largest allocation a command may plan (estimated first; default 8192).")
@click.pass_context
def main(ctx, debug, trust_external, verify_checksums, memory_limit_mb):
    """evtk: event recordings of the opto-electronic convolution accelerator."""
    import os

    from .limits import LIMIT_ENV

    ctx.meta["evtk.debug"] = debug
    # through the environment, so that batch workers inherit them; put back when the command ends (it may
    # run inside another program, a test runner or a notebook)
    changes = {}
    if trust_external:
        changes["EVTK_TRUST_EXTERNAL"] = "1"
    if verify_checksums:
        changes["EVTK_VERIFY_CHECKSUMS"] = "1"
    if memory_limit_mb is not None:
        changes[LIMIT_ENV] = repr(float(memory_limit_mb))
    saved = {k: os.environ.get(k) for k in changes}
    os.environ.update(changes)

    def restore():
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v

    ctx.call_on_close(restore)


def _finite(obj):
    """``obj`` with every NaN or infinite float replaced by None (JSON has no such numbers)."""
    if isinstance(obj, float):
        return obj if np.isfinite(obj) else None
    if isinstance(obj, np.floating):
        return float(obj) if np.isfinite(obj) else None
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    return obj


def _dumps(obj) -> str:
    """What ``--json`` prints: strict JSON (no bare NaN or Infinity; they become null)."""
    return json.dumps(_finite(obj), allow_nan=False)


def _human_info(info: dict) -> str:
    lines = [
        f"file         {info['path']}",
        f"format       {info['format']} ({info.get('compression') or info.get('encoding') or info.get('aedat_version') or '-'})",
        f"sensor       {info['sensor_size'][0]}x{info['sensor_size'][1]}" if info["sensor_size"] else "sensor       -",
        f"events       {info['events']:,}",
        f"triggers     {info['triggers']:,}",
    ]
    if info["t_start_us"] is not None:
        span = (info["t_end_us"] - info["t_start_us"]) / 1e6
        lines.append(f"time         {info['t_start_us']} .. {info['t_end_us']} us ({span:.6f} s)")
    lines.append("streams (as the file indexes them)" if info.get("scanned") else "streams")
    for s in info["streams"]:
        count = "?" if s["count"] is None else f"{s['count']:,}"
        lines.append(f"  {s['id']:>3}  {s['name']:<16} {s['type']:<5} {count:>14} elements in {s['packets']:,} packets")
    for w in info.get("warnings", []):
        lines.append(f"warning: {w}")
    if info.get("damage"):
        d = info["damage"]
        where = f" at byte {d['offset']}" if d["offset"] is not None else ""
        lines.append(f"salvaged: stopped{where}: {d['reason']}")
    return "\n".join(lines)


@main.command()
@click.argument("file", type=click.Path(dir_okay=False))
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
@click.option("--salvage", is_flag=True,
              help="Report what is intact before damage instead of failing (reads every event once).")
@click.option("--check", is_flag=True, help="Read every event once and fail at the first damage.")
def info(file, as_json, salvage, check):
    """Describe a recording: format, sensor, counts, time span, streams.

    Without --salvage or --check the counts and times are what the file's
    headers and indexes say; with either, what its events read back as.
    A reconstruction file (from ``evtk reconstruct``) is described as one.
    """
    from .io.reconstruction import describe_reconstruction, human_description, is_reconstruction

    if is_reconstruction(file):
        d = describe_reconstruction(file)
        click.echo(_dumps(d) if as_json else human_description(d))
        return
    with evio.open(file, salvage=salvage) as rec:
        summary = rec.info()
        if salvage or check:
            summary.update(rec.scan())
    if as_json:
        click.echo(_dumps(summary))
    else:
        click.echo(_human_info(summary))


@main.command()
@click.argument("source", type=click.Path(dir_okay=False))
@click.argument("target", type=click.Path(dir_okay=False))
@click.option(
    "--compression",
    type=click.Choice(["lz4", "zstd", "none", "lz4_high", "zstd_high"]),
    default="lz4",
    show_default=True,
    help="Packet compression of the written file.",
)
@click.option("--salvage", is_flag=True, help="Convert what is intact before damage.")
@click.option("--sort", is_flag=True, help="Sort events by time (in memory) when the source is out of order.")
@click.option("--chunk-events", type=click.IntRange(min=1, max=_MAX_INT), default=4_000_000, show_default=True,
              help="Events held in memory at a time while streaming.")
@click.option("--events-only", is_flag=True,
              help="Write events and triggers only (no frames, IMU or other streams, and no warning about them).")
def convert(source, target, compression, salvage, sort, chunk_events, events_only):
    """Convert SOURCE to TARGET (format from TARGET's extension), streaming.

    AEDAT4 to AEDAT4 copies frames, IMU and other streams and keeps the
    camera's name; other targets get one warning naming what they cannot hold.
    """
    from .io._convert import convert as run

    done = run(source, target, compression, salvage=salvage, sort=sort, chunk_events=chunk_events,
               events_only=events_only)
    if done["left_out"]:
        what = ", ".join(f"{name} ({k:,} packets)" for name, k in done["left_out"].items())
        click.echo(f"evtk: warning: left out {what}: {target} cannot hold them (--events-only: no warning)", err=True)
    copied = "".join(f", {k:,} {name} packets" for name, k in done["copied"].items())
    click.echo(f"wrote {done['events']:,} events and {done['triggers']:,} triggers{copied} to {target}", err=True)


def _count(n, noun):
    """``1 response``, ``3 responses``."""
    return f"{n:,} {noun}" + ("" if n == 1 else "s")


def _progress(total, label):
    """A click progress bar on a terminal, nothing otherwise; returns (callback, finish)."""
    if not sys.stderr.isatty() or total < 2:
        return None, lambda: None
    bar = click.progressbar(length=total, label=label, file=sys.stderr)
    bar.__enter__()
    return bar.update, lambda: bar.__exit__(None, None, None)


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
@click.option("--power-mw", type=float, help="Laser power (default: the bench's).")
@click.option("--window-us", type=click.IntRange(min=1, max=_MAX_INT), default=1000, show_default=True,
              help="How long each pattern is shown.")
@click.option("--settle-us", type=click.IntRange(min=1, max=_MAX_INT), help="Darkness after each pattern (default: recommended).")
@click.option("--bench", "bench_path", type=click.Path(dir_okay=False), help="Bench description (.toml or .json).")
@click.option("--seed", type=click.IntRange(min=0, max=_MAX_INT), default=0, show_default=True)
@click.option("--compression", type=click.Choice(["lz4", "zstd", "none", "lz4_high", "zstd_high", "gzip"]),
              default="lz4", show_default=True)
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False),
              help="Recording to write: .aedat4, .h5/.hdf5 or .parquet.")
@click.option("--save-bench", type=click.Path(dir_okay=False), help="Also write the bench used (.toml or .json).")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def simulate(kernel_path, kernel_bits, features_path, signed, repeat, flat_field, power_mw, window_us, settle_us,
             bench_path, seed, compression, output, save_bench, as_json):
    """Simulate the device and write the event recording it would produce."""
    from .optics import Bench, load_bench
    from .optics import save_bench as _save_bench
    from .sensor import SensorModel
    from .simulate import Simulation, default_features, load_patterns

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
                     seed=seed, flat_field=flat_field)
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


def _parse_binarize(text):
    if text in ("auto", "sign", "mean", "otsu"):
        return text
    try:
        return float(text)
    except ValueError:
        raise EvtkError(f"--binarize must be auto, sign, mean, otsu or a number, not {text!r}") from None


def _parse_window(spec):
    if spec.startswith("period:"):
        try:
            return ("period", int(spec.split(":", 1)[1]))
        except ValueError:
            raise EvtkError(f"--window period:US needs a whole number of us, not {spec!r}") from None
    if spec in ("schedule", "triggers"):
        return spec
    raise EvtkError(f"--window must be schedule, triggers or period:US, not {spec!r}")


def _parse_size(text):
    try:
        rows, cols = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise EvtkError(f"--size must look like 16x16, not {text!r}") from None
    return rows, cols


@main.command("reconstruct")
@click.argument("recording", type=click.Path(dir_okay=False, exists=True))
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False), help="Output: .npz, .h5 or .hdf5.")
@click.option("--window", "window_spec", default="schedule", show_default=True,
              help="schedule, triggers or period:US.")
@click.option("--skip-us", type=click.IntRange(min=0, max=_MAX_INT), default=0, show_default=True,
              help="Leave out the start of every window (pixel settling).")
@click.option("--length-us", type=click.IntRange(min=1, max=_MAX_INT), help="Keep at most this much of every window.")
@click.option("--size", default="16x16", show_default=True, help="Size of each response, ROWSxCOLS.")
@click.option("--binarize", "binarize_method", default="auto", show_default=True,
              help="auto (sign for signed responses, else each response's mean), sign, mean, otsu or a threshold.")
@click.option("--linearize/--counts", default=True, show_default=True,
              help="Linearise counts to light, or keep net counts (ON - OFF).")
@click.option("--crop", type=click.Choice(["valid", "full"]), default="valid", show_default=True)
@click.option("--flat-field/--no-flat-field", default=True, show_default=True,
              help="Calibrate each pixel's threshold on the recording's flat-field captures, if any.")
@click.option("--deblur/--no-deblur", default=None,
              help="Undo the known optical footprint blur (default: when the pixels are calibrated).")
@click.option("--timing/--no-timing", default=None,
              help="Read light below one threshold from each window's first and last ON-event times "
                   "(default: wherever the recording's pixel model allows).")
@click.option("--png", "png_path", type=click.Path(dir_okay=False),
              help="Also draw a contact sheet: captured beside ideal and binary.")
@click.option("--json", "as_json", is_flag=True, help="Print the summary as one JSON object.")
def reconstruct_cmd(recording, output, window_spec, skip_us, length_us, size, binarize_method, linearize, crop,
                    flat_field, deblur, timing, png_path, as_json):
    """Turn a recording into the convolution responses the device computed."""
    from .io._atomic import refuse_overwriting_inputs
    from .reconstruct import contact_sheet, save_reconstruction

    refuse_overwriting_inputs(output, [recording])
    if png_path:
        refuse_overwriting_inputs(png_path, [recording, output])
    window = _parse_window(window_spec)
    binarize_method = _parse_binarize(binarize_method)
    result, about = _reconstructed(recording, window=window, skip_us=skip_us, length_us=length_us,
                                   size=_parse_size(size), binarize_method=binarize_method, linear=linearize,
                                   crop=crop, flat_field=flat_field, deblur=deblur, timing=timing)
    n_events, sensor = about["events"], about["sensor_size"]
    save_reconstruction(output, result, sensor, {"source": str(recording)})
    if png_path:
        contact_sheet(png_path, result)
    summary = dict(result.summary, output=str(output), events_in_recording=n_events,
                   events_dropped=n_events - result.summary["events_used"])
    if as_json:
        click.echo(_dumps(summary))
    else:
        err = summary.get("error")
        line = (f"wrote {_count(summary['responses'], 'response')} of {size} from "
                f"{_count(summary['windows'], 'window')} "
                f"({summary['events_used']:,} of {n_events:,} events used) to {output}")
        if err:
            fmt = lambda v, spec: "n/a" if v is None else format(v, spec)  # noqa: E731
            line += (f"\nagainst ground truth: correlation {fmt(err['correlation'], '.4f')}, RMS error "
                     f"{fmt(err['nrmse'], '.1%')} of the ideal's RMS, {fmt(err['nrmse_range'], '.1%')} of its range")
        click.echo(line)


def _number_list(text, name, integer=False, allow_zero=False):
    try:
        vals = [float(v) for v in str(text).split(",") if v.strip()]
    except ValueError:
        raise EvtkError(f"{name} must be a comma-separated list of numbers, not {text!r}") from None
    if not vals or not all(np.isfinite(v) and (v > 0 or (allow_zero and v == 0)) for v in vals):
        raise EvtkError(f"{name} must list {'numbers >= 0' if allow_zero else 'positive numbers'}, not {text!r}")
    if integer:
        if any(v != int(v) for v in vals):
            raise EvtkError(f"{name} must list whole numbers, not {text!r}")
        vals = [int(v) for v in vals]
    return vals


def _fmt(v, spec):
    if v is None:
        return "-"
    if isinstance(v, float) and not np.isfinite(v):
        return "inf" if v > 0 else "-inf"
    return format(v, spec)


def _table(rows, columns):
    """Plain aligned text table: columns are (header, key or callable, format spec)."""
    cells = [[h for h, _, _ in columns]]
    for r in rows:
        cells.append([_fmt(get(r) if callable(get) else r.get(get), spec) for _, get, spec in columns])
    widths = [max(len(row[i]) for row in cells) for i in range(len(columns))]
    lines = ["  ".join(c.rjust(w) for c, w in zip(row, widths)) for row in cells]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def _scene_rows(scenes, source=None, power=None):
    rows = []
    for s in scenes:
        r = s["sinad"]
        row = {"kernel_id": s["kernel_id"], "features_id": s["features_id"], "repeats": s["repeats"],
               "flips": s["flips"].to_dict()}
        if source is not None:
            row["file"] = source
        if power is not None:
            row["power_mw"] = power
        row["sinad"] = None if r is None else r.to_dict()
        if "error" in s:
            row["error"] = s["error"]
        rows.append(row)
    return rows


def _reconstructed(path, **options):
    """``reconstruct`` on one recording with a progress bar; returns (result, {events, sensor_size, power_mw})."""
    from .reconstruct import reconstruct

    with evio.open(path) as rec:
        n_events = rec.info()["events"]
        update, finish = _progress(n_events, f"reconstructing {path}")
        try:
            result = reconstruct(rec, progress=update, **options)
        finally:
            finish()
        sim = (rec.metadata or {}).get("simulation")
        about = {"events": n_events, "sensor_size": rec.sensor_size,
                 "power_mw": None if sim is None else float(sim["bench"]["power_mw"])}
    return result, about


_scheduler_option = click.option(
    "--scheduler", "scheduler_spec", default=None,
    help="Where independent tasks run: serial, local[:N] (a local Dask cluster) or tcp://HOST:PORT; "
         "default local with Dask installed, else serial.")

_window_options = [
    click.option("--window", "window_spec", default="schedule", show_default=True,
                 help="schedule, triggers or period:US (without a schedule every window is a repeat of one scene)."),
    click.option("--skip-us", type=click.IntRange(min=0, max=_MAX_INT), default=0, show_default=True),
    click.option("--length-us", type=click.IntRange(min=1, max=_MAX_INT)),
]


def _options(opts):
    """A decorator applying a shared list of click options in order."""
    def deco(f):
        for opt in reversed(opts):
            f = opt(f)
        return f
    return deco


_with_window_options = _options(_window_options)


@main.command(short_help="SINAD and effective bits (eq. 8) of every repeated scene.")
@click.argument("recording", type=click.Path(dir_okay=False, exists=True))
@_with_window_options
@click.option("--interval", type=click.Choice(["jackknife", "bootstrap", "none"]), default="jackknife",
              show_default=True, help="The 95 % interval over repeats (the bootstrap undercovers with few repeats).")
@click.option("--per-pixel", is_flag=True, help="Also report each pixel's SINAD (JSON only).")
@click.option("--plot", "plot_path", type=click.Path(dir_okay=False), help="ENOB per scene as a PNG.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def enob(recording, window_spec, skip_us, length_us, interval, per_pixel, plot_path, as_json):
    """SINAD and effective bits (eq. 8) of every scene captured more than once.

    Without a schedule every window is a repeat of one scene; they are
    measured a batch at a time, so memory stays bounded however many.
    """
    from .io.reconstruction import is_reconstruction, load_reconstruction
    from .sweeps import scene_noise

    if is_reconstruction(recording):  # the responses of an earlier `evtk reconstruct`
        scenes = scene_noise(load_reconstruction(recording), interval=None if interval == "none" else interval,
                             per_pixel=per_pixel)
    else:
        scenes = _recording_noise(recording, window_spec, skip_us, length_us, interval, per_pixel)
    _report_scenes(recording, scenes, plot_path, as_json)


def _recording_noise(recording, window_spec, skip_us, length_us, interval, per_pixel):
    from .sweeps import recording_noise

    with evio.open(recording) as rec:
        update, finish = _progress(rec.info()["events"], f"measuring {recording}")
        try:
            scenes = recording_noise(rec, _parse_window(window_spec), skip_us, length_us,
                                     interval=None if interval == "none" else interval, per_pixel=per_pixel,
                                     progress=update)
        finally:
            finish()
    return scenes


def _report_scenes(recording, scenes, plot_path, as_json):
    if plot_path:
        from .plots import plot_enob

        plot_enob(scenes, plot_path)
    rows = _scene_rows(scenes)
    if as_json:
        click.echo(_dumps({"file": str(recording), "scenes": rows}))
        return
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


def _inf_if_free(row, key):
    s = row["sinad"]
    if s is None:
        return None
    return float("inf") if s["noise_free"] else s[key]


@main.command()
@click.argument("recordings", nargs=-1, type=click.Path(dir_okay=False, exists=True))
@_with_window_options
@click.option("--power-mw", "powers", default="0.05,0.2,1,5,20", show_default=True,
              help="Without recordings: laser powers to sweep on the simulated bench.")
@click.option("--kernels", "n_kernels", type=click.IntRange(min=1, max=_MAX_INT), default=11, show_default=True,
              help="Without recordings: random signed 3x3 kernels to show.")
@click.option("--repeats", type=click.IntRange(min=2, max=_MAX_INT), default=10, show_default=True,
              help="Without recordings: captures of each kernel per power.")
@click.option("--window-us", type=click.IntRange(min=1, max=_MAX_INT), default=1000, show_default=True,
              help="Without recordings: capture window.")
@click.option("--seed", type=click.IntRange(min=0, max=_MAX_INT), default=0, show_default=True)
@click.option("--plot", "plot_path", type=click.Path(dir_okay=False), help="Flip rate against power as a PNG.")
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
    from .simulate import default_features
    from .sweeps import flip_sweep, random_kernels, recording_noise

    if recordings:
        rows = []
        for i, path in enumerate(recordings):
            with evio.open(path) as rec:
                sim = (rec.metadata or {}).get("simulation")
                power = None if sim is None else float(sim["bench"]["power_mw"])
                scenes = recording_noise(rec, _parse_window(window_spec), skip_us, length_us, interval=None)
            for s in scenes:
                rows.append({"file": str(path), "file_index": i, "power_mw": power, "kernel_id": s["kernel_id"],
                             "features_id": s["features_id"], "repeats": s["repeats"],
                             "pairwise_pct": s["flips"].pairwise_pct, "majority_pct": s["flips"].majority_pct})
        x_key = "power_mw" if all(r["power_mw"] is not None for r in rows) else "file_index"
    else:
        power_list = _number_list(powers, "--power-mw")
        kernels = random_kernels(n_kernels, seed=seed)
        features = np.where(default_features() > 0, 1, -1)
        from .cluster import scheduler

        update, finish = _progress(len(power_list), "sweeping power")
        try:
            with scheduler(scheduler_spec) as client:
                rows = flip_sweep(power_list, kernels, features, repeats=repeats, window_us=window_us, seed=seed,
                                  progress=update, client=client)
        finally:
            finish()
        x_key = "power_mw"
    if plot_path:
        from .plots import plot_flips

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
@click.option("--window-us", "windows", default="200,300,500,1000,2000", show_default=True,
              help="Capture windows to sweep (us, at least eq. 7's minimum).")
@click.option("--power-mw", "powers", help="Laser powers to sweep (default: the bench's).")
@click.option("--settle-us", "settles", help="Dark times after each pattern to sweep (default: recommended).")
@click.option("--decimation", "decimations", help="Decimations to sweep (keep every d-th pixel; default 1).")
@click.option("--kernels", "n_kernels", type=click.IntRange(min=1, max=_MAX_INT), default=2, show_default=True,
              help="Random signed 3x3 kernels on the default features.")
@click.option("--repeats", type=click.IntRange(min=2, max=_MAX_INT), default=10, show_default=True)
@click.option("--seed", type=click.IntRange(min=0, max=_MAX_INT), default=0, show_default=True)
@click.option("--fast", is_flag=True, help="Time the reconstruction from counts instead of from a written recording.")
@click.option("--plot", "plot_path", type=click.Path(dir_okay=False), help="Work-precision plot as a PNG.")
@_scheduler_option
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def tradeoff(windows, powers, settles, decimations, n_kernels, repeats, seed, fast, plot_path, scheduler_spec,
             as_json):
    """Error, ENOB and flips against time per capture on the simulated bench (Pareto front marked *)."""
    from .simulate import default_features
    from .sweeps import random_kernels
    from .sweeps import tradeoff as run_tradeoff

    w = _number_list(windows, "--window-us", integer=True)
    p = _number_list(powers, "--power-mw") if powers else None
    z = _number_list(settles, "--settle-us", integer=True) if settles else None
    d = _number_list(decimations, "--decimation", integer=True) if decimations else None
    n_settings = len(w) * (len(p) if p else 1) * (len(z) if z else 1) * (len(d) if d else 1)
    from .cluster import scheduler

    update, finish = _progress(n_settings, "sweeping")
    try:
        with scheduler(scheduler_spec) as client:
            rows = run_tradeoff(w, random_kernels(n_kernels, seed=seed), np.where(default_features() > 0, 1, -1),
                                powers_mw=p, settles_us=z, decimations=d, repeats=repeats, seed=seed,
                                time_events=not fast, progress=update, client=client)
    finally:
        finish()
    if plot_path:
        from .plots import plot_tradeoff

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


@main.command()
@click.option("--out", "out_dir", default="evtk-demo", show_default=True, type=click.Path(file_okay=False),
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
    import os
    import time

    from .plots import plot_enob
    from .reconstruct import contact_sheet, save_reconstruction
    from .simulate import Simulation, default_features, load_patterns
    from .sweeps import scene_noise

    t0 = time.perf_counter()
    os.makedirs(out_dir, exist_ok=True)
    kernel = load_patterns("010111010", "kernel")
    features = default_features()
    sim = Simulation(kernel, features, repeat=repeat, seed=seed)
    rec_path = os.path.join(out_dir, "demo.aedat4")
    update, finish = _progress(len(sim.schedule), "simulating")
    try:
        written = sim.write(rec_path, progress=update)
    finally:
        finish()
    result, about = _reconstructed(rec_path)  # binarised as reconstruct does by default (auto)
    out_h5 = os.path.join(out_dir, "reconstruction.h5")
    save_reconstruction(out_h5, result, about["sensor_size"], {"source": rec_path})
    sheet = os.path.join(out_dir, "responses.png")
    contact_sheet(sheet, result, max_rows=4)
    scenes = scene_noise(result, seed=seed)
    enob_png = os.path.join(out_dir, "enob.png")
    plot_enob(scenes, enob_png)
    s, fl, err = scenes[0]["sinad"], scenes[0]["flips"], result.summary["error"]
    summary = {
        "recording": rec_path, "reconstruction": out_h5, "contact_sheet": sheet, "enob_plot": enob_png,
        "events": written["events"], "captures": written["captures"], "repeats": repeat,
        "error": err, "sinad": None if s is None else s.to_dict(), "flips": fl.to_dict(),
        "seconds": time.perf_counter() - t0,
    }
    if as_json:
        click.echo(_dumps(summary))
        return
    if s is None:
        enob_txt = "n/a (no signal)"
    elif s.noise_free:
        enob_txt = "inf (noise-free)"
    else:
        ci = "" if s.ci_enob is None else f" (95 % {_fmt(s.ci_enob[0], '.2f')}..{_fmt(s.ci_enob[1], '.2f')})"
        enob_txt = f"{s.enob_bits:.2f} bits{ci}, SINAD {s.sinad_db:.1f} dB"
    click.echo("\n".join([
        f"simulated {written['captures']} captures ({repeat} repeats of a 3x3 kernel on 16x16 binary features, "
        f"2 flat fields): {written['events']:,} events",
        f"against the digital correlation: correlation {_fmt(err['correlation'], '.3f')}, RMS error "
        f"{_fmt(err['nrmse'], '.1%')} of the ideal's RMS ({_fmt(err['nrmse_range'], '.1%')} of its range)",
        f"effective bits (eq. 8): {enob_txt}",
        f"binary pixels (16x16, above/below the mean) flipped between repeats: {fl.pairwise_pct:.2f} % (pairs), "
        f"{fl.majority_pct:.2f} % against the majority",
        f"files: {rec_path}, {out_h5}, {sheet}, {enob_png}",
        f"done in {summary['seconds']:.1f} s",
    ]))


def _load_array(path, what):
    import os

    ext = os.path.splitext(path)[1].lower()
    if ext != ".npy":
        raise EvtkError(f"{what} must be a .npy file, not {path!r}")
    try:
        return np.load(path, allow_pickle=False)
    except (ValueError, OSError) as exc:
        raise EvtkError(f"cannot read {what} {path!r}: {exc}") from None


def _recorded_candidates(path, size, features):
    """Responses of every candidate kernel from a recording holding one capture (at least) per candidate."""
    from .reconstruct import reconstruct
    from .recover import all_kernels, kernel_bits

    with evio.open(path) as rec:
        sim = (rec.metadata or {}).get("simulation")
        if sim is None:
            raise EvtkError(f"{path}: no capture schedule, so the candidates cannot be told apart")
        result = reconstruct(rec, crop="full", deblur=False)
    feats = np.asarray(sim["features"])
    if feats.shape[0] != 1 or not np.array_equal(feats[0], features):
        raise EvtkError(f"{path}: its features are not the ones given")
    index = {kernel_bits(k): i for i, k in enumerate(np.asarray(sim["kernels"]))}
    out = np.zeros((2 ** (size * size),) + result.cells.shape[1:])
    missing = 0
    for j, cand in enumerate(all_kernels(size)):
        i = index.get(kernel_bits(cand))
        rows = [] if i is None else [r for r, (k, _, _) in enumerate(result.pairs.tolist()) if k == i]
        if rows:
            out[j] = result.cells[rows].mean(axis=0)
        elif cand.any():
            missing += 1
    if missing:
        raise EvtkError(f"{path}: {missing} candidate kernels of {size}x{size} were never captured")
    return out


@main.command()
@click.option("--features", "features_path", type=click.Path(dir_okay=False, exists=True),
              help="Binary features (.npy or image). Default: the bundled 16x16 picture (or random per trial).")
@click.option("--target", "target_path", type=click.Path(dir_okay=False, exists=True),
              help="Captured response (.npy) on the full cell grid, as evtk reconstruct --crop full --no-deblur "
                   "saves in 'cells'.")
@click.option("--target-kernel-bits", help="Capture the target on the simulated device with this kernel.")
@click.option("--size", type=click.IntRange(1, 7), default=3, show_default=True, help="Kernel side.")
@click.option("--method", type=click.Choice(["brute", "search"]), help="Default: brute up to 3x3, search above.")
@click.option("--weights", type=click.Choice(["relative", "none"]), default="relative", show_default=True,
              help="Weigh cells by 1/max(|target|, 1) (better at nominal light) or plain MSE (better when dim).")
@click.option("--candidates", "candidates_path", type=click.Path(dir_okay=False, exists=True),
              help="Brute force from a recording with one capture per candidate (default: the simulated device).")
@click.option("--events", is_flag=True, help="Simulate candidates through the event stream, not the count path.")
@click.option("--power-mw", "powers", default="20", show_default=True,
              help="Laser power of the simulated device; with --trials a comma-separated sweep.")
@click.option("--trials", type=click.IntRange(min=1, max=_MAX_INT), help="Success rate over this many random trials per power.")
@click.option("--seed", type=click.IntRange(min=0, max=_MAX_INT), default=0, show_default=True)
@click.option("--plot", "plot_path", type=click.Path(dir_okay=False),
              help="PNG: Fig. 4 for one recovery, success against power for --trials.")
@_scheduler_option
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def recover(features_path, target_path, target_kernel_bits, size, method, weights, candidates_path, events, powers,
            trials, seed, plot_path, scheduler_spec, as_json):
    """Find the binary kernel behind a captured response (paper 4.4), or measure how often that works."""
    from .optics import Bench
    from .recover import (
        all_kernels,
        device_responses,
        kernel_from_bits,
        recover_brute,
        recover_search,
        response_matrix,
        success_rate,
    )
    from .simulate import default_features, load_patterns

    w = None if weights == "none" else weights
    power_list = _number_list(powers, "--power-mw")
    method = method or ("brute" if size <= 3 else "search")
    if trials:
        if target_path or target_kernel_bits or candidates_path:
            raise EvtkError("--trials draws its own kernels and features: drop --target, --target-kernel-bits "
                            "and --candidates")
        from .cluster import scheduler

        update, finish = _progress(len(power_list), "trials")
        try:
            with scheduler(scheduler_spec) as client:
                rows = success_rate(power_list, size=size, trials=trials, method=method, seed=seed, weights=w,
                                    progress=update, client=client)
        finally:
            finish()
        if plot_path:
            from .plots import plot_success

            plot_success(rows, plot_path)
        if as_json:
            click.echo(_dumps({"rows": rows}))
            return
        click.echo(_table(rows, [("power mW", "power_mw", "g"), ("trials", "trials", "d"),
                                 ("exact %", "exact_pct", ".1f"), ("shift %", "shift_pct", ".1f"),
                                 ("recovered %", "recovered_pct", ".1f"), ("median s", "median_s", ".3f"),
                                 ("max s", "max_s", ".3f"), ("proven %", "proven_pct", ".0f")]))
        return
    if bool(target_path) == bool(target_kernel_bits):
        raise EvtkError("give exactly one of --target and --target-kernel-bits")
    features = load_patterns(features_path, "features") if features_path else default_features()
    features = np.asarray(features)
    if features.ndim == 3:
        if features.shape[0] != 1:
            raise EvtkError("recovery takes one features pattern, not a stack")
        features = features[0]
    if not np.isin(features, (0, 1)).all():
        raise EvtkError("features must be binary (0/1) for kernel recovery")
    bench = Bench(power_mw=power_list[0])
    true_kernel = None
    if target_kernel_bits:
        true_kernel = kernel_from_bits(target_kernel_bits, size)
        if not true_kernel.any():
            raise EvtkError("an all-zero target kernel casts no light: nothing to recover")
        target = device_responses(true_kernel[None], features, bench, seed=seed, noise_seed=seed + 1,
                                  method="events" if events else "fast")[0]
    else:
        target = np.asarray(_load_array(target_path, "target"), dtype=np.float64)
        if target.ndim == 3 and target.shape[0] == 1:
            target = target[0]
        full = (features.shape[0] + size - 1, features.shape[1] + size - 1)
        if target.shape != full:
            raise EvtkError(f"target has shape {target.shape}; a {size}x{size} kernel on {features.shape[0]}x"
                            f"{features.shape[1]} features gives a full response of {full[0]}x{full[1]}")
    if method == "brute":
        if candidates_path:
            cands = _recorded_candidates(candidates_path, size, features)
        else:
            cands = device_responses(all_kernels(size), features, bench, seed=seed, noise_seed=seed + 2,
                                     method="events" if events else "fast")
        result = recover_brute(target, cands, true_kernel=true_kernel, weights=w)
        solution = cands[int(np.argmin(result.losses))]
    else:
        a_mat = response_matrix(features, size, bench, blurred=True)
        result = recover_search(target, a_mat, size, true_kernel=true_kernel, weights=w)
        solution = (result.scale * (a_mat @ result.kernel.ravel())).reshape(target.shape)
    if plot_path:
        from .plots import plot_recovery

        plot_recovery(plot_path, features, target, solution, result, true_kernel)
    out = result.to_dict()
    if true_kernel is not None:
        out["target_kernel_bits"] = target_kernel_bits
    if as_json:
        click.echo(_dumps(out))
        return
    lines = [f"solution kernel {out['kernel_bits']} ({method}, loss {result.loss:.4g}"
             + (", proven optimal" if result.proven else ", best found: node budget ran out") + ")"]
    for row in result.kernel:
        lines.append("  " + " ".join("#" if v else "." for v in row))
    if result.status is not None:
        lines.append(f"against the target kernel {target_kernel_bits}: {result.status}")
    if result.near:
        near = ", ".join(f"{b} ({v:.4g})" for b, v in result.near[:5])
        lines.append(f"within 5 % of the best loss: {near}" + (" ..." if len(result.near) > 5 else ""))
    lines.append(f"search time {result.seconds:.3f} s")
    click.echo("\n".join(lines))


def _train(task_data, backend_name, optimizer, steps, temperature, final_temperature, epochs, channels, seed,
           power_mw=None, progress=None, channel_masks=False):
    """One run: a fresh network trained on the data; returns (model, backend, record)."""
    from .bcnn import BCNN, DigitalBackend, OpticalBackend
    from .optics import Bench
    from .optimize import train_layerwise, train_ste

    model = BCNN.random(layers=3, channels=channels, seed=seed, channel_masks=channel_masks)
    if backend_name == "digital":
        backend = DigitalBackend()
    else:
        backend = OpticalBackend(bench=Bench() if power_mw is None else Bench(power_mw=power_mw), seed=seed)
    if optimizer == "ste":
        record = train_ste(model, task_data.x_train, task_data.y_train, epochs=epochs, seed=seed)
    else:
        record = train_layerwise(model, backend, task_data.x_train, task_data.y_train, optimizer=optimizer,
                                 steps=steps, temperature=temperature, final_temperature=final_temperature,
                                 seed=seed, progress=progress)
    return model, backend, record


def _classify_run(args):
    """One training run of ``evtk classify`` (a task: everything it needs is in ``args``)."""
    import time

    (data, backend_name, optimizer, steps, temperature, final_temperature, epochs, channels, channel_masks, run_seed,
     power_mw, r) = args
    t0 = time.perf_counter()
    model, backend, record = _train(data, backend_name, optimizer, steps, temperature, final_temperature, epochs,
                                    channels, run_seed, power_mw, channel_masks=channel_masks)
    return {"run": r, "seed": run_seed, "seconds": time.perf_counter() - t0,
            "train_accuracy": model.accuracy(backend, data.x_train, data.y_train),
            "test_accuracy": model.accuracy(backend, data.x_test, data.y_test),
            "kernels": [k.tolist() for k in model.kernels], "mask": model.masks[-1].tolist(), "record": record}


def _stats(values):
    v = np.asarray(values, dtype=np.float64)
    return {"max": float(v.max()), "min": float(v.min()), "mean": float(v.mean()),
            "std": float(v.std(ddof=1)) if v.size > 1 else 0.0}


_task_options = [
    click.option("--task", type=click.Choice(["fnf", "letters-digits"]), default="fnf", show_default=True),
    click.option("--data-dir", type=click.Path(file_okay=False, exists=True),
                 help="Local LFW + CIFAR-10 (fnf) or EMNIST IDX files (letters-digits); default: bundled/synthetic."),
    click.option("--optimizer", type=click.Choice(["anneal", "walk", "brute", "ste"]), default="anneal",
                 show_default=True),
    click.option("--steps", type=click.IntRange(min=1, max=_MAX_INT), default=600, show_default=True,
                 help="Metropolis steps per layer (anneal, walk)."),
    click.option("--temperature", type=float, default=None,
                 help="Start (anneal) or constant (walk) temperature; default 10 (anneal), 5 (walk)."),
    click.option("--final-temperature", type=float, default=0.01, show_default=True),
    click.option("--epochs", type=click.IntRange(min=1, max=_MAX_INT), default=300, show_default=True, help="STE epochs."),
    click.option("--channels", type=click.IntRange(min=1, max=_MAX_INT), default=1, show_default=True,
                 help="Kernels per layer (the paper: one)."),
    click.option("--channel-masks", is_flag=True,
                 help="Score each channel with its own mask plane (default: one plane scores the channels' mean)."),
    click.option("--samples", "n_per_class", type=click.IntRange(min=2, max=_MAX_INT),
                 help="Samples per class (letters-digits: default 1000; fnf: needs --data-dir, default 1000)."),
    click.option("--seed", type=click.IntRange(min=0, max=_MAX_INT), default=0, show_default=True),
]


_with_task_options = _options(_task_options)


@main.command()
@_with_task_options
@click.option("--backend", "backend_name", type=click.Choice(["digital", "optical"]), default="optical",
              show_default=True, help="Exact binary correlations, or every correlation through the simulated device.")
@click.option("--power-mw", type=float, help="Laser power of the simulated device (optical backend).")
@click.option("--runs", type=click.IntRange(min=1, max=_MAX_INT), default=10, show_default=True)
@click.option("--out", "out_dir", type=click.Path(file_okay=False), default="evtk-classify", show_default=True,
              help="Where the per-run curves (runs.json) go.")
@_scheduler_option
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def classify(task, data_dir, optimizer, steps, temperature, final_temperature, epochs, channels, channel_masks,
             n_per_class, seed, backend_name, power_mw, runs, out_dir, scheduler_spec, as_json):
    """Train the binary CNN several times and report test accuracy (the paper's Tables 2 and 3)."""
    import os
    import time

    from .datasets import load_dataset

    if temperature is None:
        temperature = 5.0 if optimizer == "walk" else 10.0
    data = load_dataset(task, seed=seed, data_dir=data_dir, n_per_class=n_per_class)
    from .cluster import run_tasks, scheduler

    update, finish = _progress(runs, f"{task} {optimizer} on {backend_name}")
    t_all = time.perf_counter()
    tasks = [(data, backend_name, optimizer, steps, temperature, final_temperature, epochs, channels, channel_masks,
              seed + r, power_mw, r) for r in range(runs)]
    try:
        with scheduler(scheduler_spec) as client:
            per_run = run_tasks(_classify_run, tasks, client, update)
    finally:
        finish()
    seconds = time.perf_counter() - t_all
    steps_done = sum(run["record"].get("steps", 0) for run in per_run)
    summary = {
        "task": task, "data": data.summary(), "backend": backend_name, "optimizer": optimizer, "runs": runs,
        "channels": channels, "channel_masks": bool(channel_masks),
        "steps_per_layer": steps if optimizer in ("anneal", "walk") else None,
        "temperature": temperature if optimizer in ("anneal", "walk") else None,
        "test_accuracy": _stats([r["test_accuracy"] for r in per_run]),
        "train_accuracy": _stats([r["train_accuracy"] for r in per_run]),
        "seconds": seconds, "steps_per_s": steps_done / seconds if steps_done else None,
    }
    os.makedirs(out_dir, exist_ok=True)
    from .io._atomic import AtomicFile

    with AtomicFile(os.path.join(out_dir, "runs.json")) as fh:
        fh.write(_dumps({"summary": summary, "runs": per_run}).encode())
    summary["curves"] = os.path.join(out_dir, "runs.json")
    if as_json:
        click.echo(_dumps(summary))
        return
    note = " (SYNTHETIC glyphs, not EMNIST)" if data.synthetic else ""
    click.echo(f"{task}{note}: {data.summary()['train']} train / {data.summary()['test']} test images; "
               f"{optimizer} on the {backend_name} backend, {runs} runs, {seconds:.1f} s")
    rows = [dict(summary["test_accuracy"], what="test accuracy %"), dict(summary["train_accuracy"],
                                                                         what="train accuracy %")]
    pct = lambda key: lambda r: 100 * r[key]  # noqa: E731
    click.echo(_table(rows, [("", "what", "s"), ("max", pct("max"), ".1f"), ("min", pct("min"), ".1f"),
                             ("mean", pct("mean"), ".1f"), ("std", pct("std"), ".1f")]))
    if summary["steps_per_s"]:
        click.echo(f"{summary['steps_per_s']:.0f} optimisation steps/s; curves in {summary['curves']}")


@main.command(short_help="Accuracy and flipped pixels under Poisson noise (Fig. 3 left, eq. 12).")
@_with_task_options
@click.option("--scales", default="0,0.01,0.03,0.1,0.3,1,3", show_default=True,
              help="Poisson noise scales (response units per photon; 0 is noise-free).")
@click.option("--target-accuracy", type=float, help="r of eq. 12 (default: noise-free accuracy minus 0.05).")
@click.option("--plot", "plot_path", type=click.Path(dir_okay=False), help="Accuracy and flips against noise (PNG).")
@_scheduler_option
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def robustness(task, data_dir, optimizer, steps, temperature, final_temperature, epochs, channels, channel_masks,
               n_per_class, seed, scales, target_accuracy, plot_path, scheduler_spec, as_json):
    """Fig. 3 (left) and eq. 12: test accuracy and flipped pixels with scaled Poisson noise in every layer."""
    from .bcnn import poisson_robustness
    from .datasets import load_dataset

    if temperature is None:
        temperature = 5.0 if optimizer == "walk" else 10.0
    data = load_dataset(task, seed=seed, data_dir=data_dir, n_per_class=n_per_class)
    model, backend, _ = _train(data, "digital", optimizer, steps, temperature, final_temperature, epochs, channels,
                               seed, channel_masks=channel_masks)
    from .cluster import scheduler

    with scheduler(scheduler_spec) as client:
        res = poisson_robustness(model, data.x_test, data.y_test, _number_list(scales, "--scales", allow_zero=True),
                                 seed=seed, target_accuracy=target_accuracy, client=client)
    if plot_path:
        from .plots import plot_robustness

        plot_robustness(res, plot_path)
    if as_json:
        click.echo(_dumps(res))
        return
    click.echo(_table(res["rows"], [("noise scale", "scale", "g"), ("test accuracy %", lambda r: 100 * r["accuracy"],
                                                                    ".1f"), ("flipped %", "flip_pct", ".2f")]))
    big_r = "none" if res["R_pct"] is None else f"{res['R_pct']:.2f} %"
    click.echo(f"eq. 12: keeping accuracy >= {100 * res['r']:.1f} % tolerates R = {big_r} flipped pixels")


@main.group()
def batch():
    """Run a command over many recordings (one task each, resumable, with a manifest)."""


@batch.command("reconstruct")
@click.argument("inputs", nargs=-1, required=True)
@click.option("-o", "--out", "out_dir", required=True, type=click.Path(file_okay=False),
              help="Folder for the outputs and batch.json.")
@_with_window_options
@click.option("--size", default="16x16", show_default=True, help="Size of each response, ROWSxCOLS.")
@click.option("--binarize", "binarize_method", default="auto", show_default=True,
              help="auto (sign for signed responses, else each response's mean), sign, mean, otsu or a threshold.")
@click.option("--linearize/--counts", default=True, show_default=True)
@click.option("--crop", type=click.Choice(["valid", "full"]), default="valid", show_default=True)
@click.option("--format", "fmt", type=click.Choice(["h5", "npz"]), default="h5", show_default=True)
@click.option("--force", is_flag=True, help="Redo inputs whose output exists.")
@click.option("--split-events", type=click.IntRange(min=1, max=_MAX_INT), default=50_000_000, show_default=True,
              help="Split recordings with more events than this into tasks by time.")
@_scheduler_option
@click.option("--json", "as_json", is_flag=True, help="Print the manifest as one JSON object.")
def batch_reconstruct_cmd(inputs, out_dir, window_spec, skip_us, length_us, size, binarize_method, linearize, crop,
                          fmt, force, split_events, scheduler_spec, as_json):
    """Reconstruct every recording in INPUTS (files, folders, glob patterns) into OUT.

    Exit status 1 when any input failed; the others are still done, and
    batch.json says what happened to each.
    """
    from .batch import batch_reconstruct
    from .cluster import scheduler

    binarize_method = _parse_binarize(binarize_method)
    options = {"window": _parse_window(window_spec), "skip_us": skip_us, "length_us": length_us,
               "size": _parse_size(size), "binarize_method": binarize_method, "linear": linearize, "crop": crop}
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
    if c["error"]:
        sys.exit(1)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
