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


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
