"""``evtk info`` and ``evtk convert``: what a file holds, and the same events in another format."""

from __future__ import annotations

import click

from .. import io as evio  # (light: its readers and writers load on first use)
from ._base import _MAX_INT, OutputPath, _dumps, main


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
    from ..io.reconstruction import describe_reconstruction, human_description, is_reconstruction

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
@click.argument("target", type=OutputPath(dir_okay=False))
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
@click.option("--format", "fmt", type=click.Choice(["aedat4", "hdf5", "parquet", "evt2", "evt21", "evt3", "dat", "es",
                                                          "csv"]),
              help="TARGET's format where its extension does not say (.raw is EVT 3.0 unless --format evt2 or evt21).")
@click.option("--time-from-zero", is_flag=True,
              help="Subtract the earliest event or trigger time from every time (kept as the metadata key "
                   "time_offset_us): EVT 3.0 and DAT count time from 0 and cannot start at Unix microseconds.")
def convert(source, target, compression, salvage, sort, chunk_events, events_only, fmt, time_from_zero):
    """Convert SOURCE to TARGET (format from TARGET's extension), streaming.

    Any format evtk reads to AEDAT4, HDF5, Parquet, Prophesee RAW (EVT 2.0,
    2.1 or 3.0), DAT, Event Stream or CSV. AEDAT4 to AEDAT4 copies frames, IMU
    and other streams and keeps the camera's name; other targets get one
    warning naming what they cannot hold.
    """
    from ..io import convert as run

    done = run(source, target, compression, salvage=salvage, sort=sort, chunk_events=chunk_events,
               events_only=events_only, fmt=fmt, time_from_zero=time_from_zero)
    if done["left_out"]:
        what = ", ".join(f"{name} ({k:,}{'' if name in ('trigger edges', 'metadata keys') else ' packets'})"
                         for name, k in done["left_out"].items())
        click.echo(f"evtk: warning: left out {what}: {target} cannot hold them (--events-only: no warning)", err=True)
    if done["channels_lost"]:
        lost = ", ".join(map(str, done["channels_lost"]))
        click.echo(f"evtk: warning: {target} holds no trigger channels: the triggers of channel(s) {lost} "
                   "are written without theirs (they read back as channel 0)", err=True)
    if time_from_zero:
        click.echo(f"evtk: times shifted by -{done['time_offset_us']:,} us (metadata time_offset_us)", err=True)
    copied = "".join(f", {k:,} {name} packets" for name, k in done["copied"].items())
    click.echo(f"wrote {done['events']:,} events and {done['triggers']:,} triggers{copied} to {target}", err=True)
