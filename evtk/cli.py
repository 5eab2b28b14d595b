"""The ``evtk`` command: one sub-command per library entry point."""

from __future__ import annotations

import json
import sys

import click
import numpy as np

from . import io as evio
from ._version import __version__
from .errors import EvtkError


class _Group(click.Group):
    """Turns evtk errors and OS errors into one line on stderr and exit code 1."""

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except (EvtkError, OSError, MemoryError) as exc:
            if ctx.meta.get("evtk.debug"):
                raise
            msg = str(exc) if isinstance(exc, EvtkError) else f"{type(exc).__name__}: {exc}"
            click.echo(f"evtk: error: {msg}", err=True)
            ctx.exit(1)


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="evtk")
@click.option("--debug", is_flag=True, help="Show the full traceback on errors.")
@click.pass_context
def main(ctx, debug):
    """evtk: event recordings of the opto-electronic convolution accelerator."""
    ctx.meta["evtk.debug"] = debug


def _human_info(info: dict) -> str:
    lines = [
        f"file         {info['path']}",
        f"format       {info['format']} ({info.get('compression', '-')})",
        f"sensor       {info['sensor_size'][0]}x{info['sensor_size'][1]}" if info["sensor_size"] else "sensor       -",
        f"events       {info['events']:,}",
        f"triggers     {info['triggers']:,}",
    ]
    if info["t_start_us"] is not None:
        span = (info["t_end_us"] - info["t_start_us"]) / 1e6
        lines.append(f"time         {info['t_start_us']} .. {info['t_end_us']} us ({span:.6f} s)")
    lines.append("streams")
    for s in info["streams"]:
        count = "?" if s["count"] is None else f"{s['count']:,}"
        lines.append(f"  {s['id']:>3}  {s['name']:<16} {s['type']:<5} {count:>14} elements in {s['packets']:,} packets")
    for w in info.get("warnings", []):
        lines.append(f"warning: {w}")
    if info.get("damage"):
        d = info["damage"]
        lines.append(f"salvaged: stopped at byte {d['offset']}: {d['reason']}")
    return "\n".join(lines)


@main.command()
@click.argument("file", type=click.Path(dir_okay=False))
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
@click.option("--salvage", is_flag=True, help="Report what is intact before damage instead of failing.")
def info(file, as_json, salvage):
    """Describe a recording: format, sensor, counts, time span, streams."""
    with evio.open(file, salvage=salvage) as rec:
        summary = rec.info()
    if as_json:
        click.echo(json.dumps(summary))
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
@click.option("--chunk-events", type=click.IntRange(min=1), default=4_000_000, show_default=True,
              help="Events held in memory at a time while streaming.")
def convert(source, target, compression, salvage, sort, chunk_events):
    """Convert SOURCE to TARGET (format from TARGET's extension), streaming."""
    with evio.open(source, salvage=salvage) as rec:
        has_triggers = any(s.type == "TRIG" for s in rec.streams)
        triggers = rec.triggers() if has_triggers else None
        n = 0
        if sort:  # in memory: a stable sort by time
            events = rec.events()
            order = np.argsort(events.t, kind="stable")
            events = events.__class__(events.t[order], events.x[order], events.y[order], events.p[order], events.sensor_size)
            evio.write_events(target, events, triggers, compression=compression, metadata=rec.metadata or None)
            n = len(events)
        else:
            with evio.open_writer(target, rec.sensor_size, compression, rec.metadata or None, triggers) as writer:
                for chunk in rec.iter_events(chunk_events=chunk_events):
                    writer.write_events(chunk)
                    n += len(chunk)
    n_trig = 0 if triggers is None else len(triggers)
    click.echo(f"wrote {n:,} events and {n_trig:,} triggers to {target}", err=True)


def _progress(total, label):
    """A click progress bar on a terminal, nothing otherwise; returns (callback, finish)."""
    if not sys.stderr.isatty() or total < 2:
        return None, lambda: None
    bar = click.progressbar(length=total, label=label, file=sys.stderr)
    bar.__enter__()
    return bar.update, lambda: bar.__exit__(None, None, None)


def _default_features(side=16):
    """The embedded default input: scikit-image's camera picture, 16x16, binarised at its mean."""
    from skimage import data, transform

    img = transform.resize(data.camera().astype(np.float64), (side, side), anti_aliasing=True)
    return (img > img.mean()).astype(np.int8)


@main.command()
@click.option("--kernel", "kernel_path", type=click.Path(dir_okay=False, exists=True),
              help="Kernel(s): .npy (h, w) or (n, h, w), or an image.")
@click.option("--kernel-bits", help="Kernel as a bit string filling a square row by row, e.g. 101010101.")
@click.option("--features", "features_path", type=click.Path(dir_okay=False, exists=True),
              help="Features: .npy (h, w) or (n, h, w), or an image (binarised). Default: a 16x16 "
                   "binarised picture bundled with scikit-image.")
@click.option("--signed", is_flag=True, help="Read 0 as -1 in kernels and features (four passes per pair).")
@click.option("--repeat", type=click.IntRange(min=1), default=1, show_default=True, help="Times each pair is shown.")
@click.option("--flat-field", type=click.IntRange(min=0), default=2, show_default=True,
              help="Flat-field captures (all mirrors on) shown first, for per-pixel threshold calibration.")
@click.option("--power-mw", type=float, help="Laser power (default: the bench's).")
@click.option("--window-us", type=click.IntRange(min=1), default=1000, show_default=True,
              help="How long each pattern is shown.")
@click.option("--settle-us", type=click.IntRange(min=1), help="Darkness after each pattern (default: recommended).")
@click.option("--bench", "bench_path", type=click.Path(dir_okay=False), help="Bench description (.toml or .json).")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True)
@click.option("--compression", type=click.Choice(["lz4", "zstd", "none", "lz4_high", "zstd_high", "gzip"]),
              default="lz4", show_default=True)
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False),
              help="Recording to write: .aedat4, .h5/.hdf5 or .parquet.")
@click.option("--save-bench", type=click.Path(dir_okay=False), help="Also write the bench used (.toml or .json).")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def simulate(kernel_path, kernel_bits, features_path, signed, repeat, flat_field, power_mw, window_us, settle_us,
             bench_path, seed, compression, output, save_bench, as_json):
    """Simulate the device and write the event recording it would produce."""
    from .optics import Bench, load_bench, save_bench as _save_bench
    from .sensor import SensorModel
    from .simulate import Simulation, load_patterns

    if kernel_path and kernel_bits:
        raise EvtkError("give --kernel or --kernel-bits, not both")
    if kernel_bits is not None and not (kernel_bits and set(kernel_bits) <= {"0", "1"}):
        raise EvtkError(f"--kernel-bits must be a string of 0s and 1s, not {kernel_bits!r}")
    kernel = load_patterns(kernel_path or kernel_bits or "010111010", "kernel")
    features = load_patterns(features_path, "features") if features_path else _default_features()
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
        click.echo(json.dumps(summary))
    else:
        span = (summary["t_end_us"] - summary["t_start_us"]) / 1e6
        click.echo(f"wrote {summary['events']:,} events and {summary['triggers']:,} triggers "
                   f"({summary['captures']:,} captures, {span:.3f} s) to {output}\n"
                   f"sigma {bench.sigma:.4g} (eq. 3), varsigma {bench.varsigma:.4g} (eq. 4; shown as "
                   f"{bench.kernel_mirrors} mirrors), effective stride {bench.stride_eff:.4g} (eq. 6), "
                   f"e_min {bench.min_window_us:g} us (eq. 7), settle {summary['settle_us']} us")


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
@click.option("--skip-us", type=click.IntRange(min=0), default=0, show_default=True,
              help="Leave out the start of every window (pixel settling).")
@click.option("--length-us", type=click.IntRange(min=1), help="Keep at most this much of every window.")
@click.option("--size", default="16x16", show_default=True, help="Size of each response, ROWSxCOLS.")
@click.option("--binarize", "binarize_method", default="sign", show_default=True,
              help="sign, mean, otsu or a threshold value.")
@click.option("--linearize/--counts", default=True, show_default=True,
              help="Linearise counts to light, or keep net counts (ON - OFF).")
@click.option("--crop", type=click.Choice(["valid", "full"]), default="valid", show_default=True)
@click.option("--flat-field/--no-flat-field", default=True, show_default=True,
              help="Calibrate each pixel's threshold on the recording's flat-field captures, if any.")
@click.option("--deblur/--no-deblur", default=None,
              help="Undo the known optical footprint blur (default: when the pixels are calibrated).")
@click.option("--png", "png_path", type=click.Path(dir_okay=False),
              help="Also draw a contact sheet: captured beside ideal and binary.")
@click.option("--json", "as_json", is_flag=True, help="Print the summary as one JSON object.")
def reconstruct_cmd(recording, output, window_spec, skip_us, length_us, size, binarize_method, linearize, crop,
                    flat_field, deblur, png_path, as_json):
    """Turn a recording into the convolution responses the device computed."""
    from .reconstruct import contact_sheet, reconstruct, save_reconstruction

    if window_spec.startswith("period:"):
        try:
            window = ("period", int(window_spec.split(":", 1)[1]))
        except ValueError:
            raise EvtkError(f"--window period:US needs a whole number of us, not {window_spec!r}") from None
    elif window_spec in ("schedule", "triggers"):
        window = window_spec
    else:
        raise EvtkError(f"--window must be schedule, triggers or period:US, not {window_spec!r}")
    if binarize_method not in ("sign", "mean", "otsu"):
        try:
            binarize_method = float(binarize_method)
        except ValueError:
            raise EvtkError(f"--binarize must be sign, mean, otsu or a number, not {binarize_method!r}") from None
    with evio.open(recording) as rec:
        n_events = rec.info()["events"]
        update, finish = _progress(n_events, "reconstructing")
        try:
            result = reconstruct(rec, window=window, skip_us=skip_us, length_us=length_us, size=_parse_size(size),
                                 binarize_method=binarize_method, linear=linearize, crop=crop,
                                 flat_field=flat_field, deblur=deblur, progress=update)
        finally:
            finish()
        sensor = rec.sensor_size
    save_reconstruction(output, result, sensor, {"source": str(recording)})
    if png_path:
        contact_sheet(png_path, result)
    summary = dict(result.summary, output=str(output), events_in_recording=n_events,
                   events_dropped=n_events - result.summary["events_used"])
    if as_json:
        click.echo(json.dumps(summary))
    else:
        err = summary.get("error")
        line = (f"wrote {summary['responses']} responses of {size} from {summary['windows']} windows "
                f"({summary['events_used']:,} of {n_events:,} events used) to {output}")
        if err:
            fmt = lambda v, spec: "n/a" if v is None else format(v, spec)  # noqa: E731
            line += (f"\nagainst ground truth: correlation {fmt(err['correlation'], '.4f')}, RMS error "
                     f"{fmt(err['nrmse'], '.1%')} of the ideal's RMS, {fmt(err['nrmse_range'], '.1%')} of its range")
        click.echo(line)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
