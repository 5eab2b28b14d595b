"""The ``evtk`` group, its error handling, and the option types and helpers every command shares."""

from __future__ import annotations

import sys

import click
import numpy as np

from .. import io as evio  # (light: its readers and writers load on first use)
from .._version import __version__
from ..errors import EvtkError, one_line

#: Largest whole number an option takes: microseconds and counts stay far inside int64 arithmetic.
_MAX_INT = 2**62


class OutputPath(click.Path):
    """A path a command writes (a file, or a folder it writes into): checked against every input of the
    command before it runs, and every file the command commits inside it (see :class:`_Command`)."""


def _paths_of(ctx):
    """The (label, path) pairs of a command's outputs (:class:`OutputPath` parameters) and inputs (every other
    path parameter: the recording, the schedule, the calibration, the bench, ...)."""
    outputs, inputs = [], []
    for param in ctx.command.params:
        if not isinstance(param.type, click.Path):
            continue
        value = ctx.params.get(param.name)
        values = value if isinstance(value, (tuple, list)) else [value]
        label = max(param.opts, key=len) if isinstance(param, click.Option) else param.human_readable_name
        pairs = [(label, v) for v in values if v]
        (outputs if isinstance(param.type, OutputPath) else inputs).extend(pairs)
    return outputs, inputs


def _long_spelling(command: click.Command, ctx: click.Context, args: list[str]) -> list[str]:
    """``args`` with each short option that stands alone (``-o``) spelled as its option's long name
    (``--output``).

    click matches every option as a long one first, and a miss builds its "did you mean" list with difflib
    (loading it and comparing the option with every long name: 2.5-3 ms of a fresh ``evtk reconstruct ... -o
    x.npz``) before it tries the short name. The values of options that take them, and everything after
    ``--``, are left as they are; a command with an option whose value is optional is left to click whole.
    """
    long_of: dict[str, str] = {}
    values: dict[str, int] = {}  # each option name: the tokens its value takes
    for param in command.get_params(ctx):
        if not isinstance(param, click.Option):
            continue
        if getattr(param, "_flag_needs_value", False):  # a value that may be left out: click alone decides
            return args
        names = [*param.opts, *param.secondary_opts]
        takes = 0 if param.is_flag or param.count else max(1, param.nargs)
        values.update(dict.fromkeys(names, takes))
        longs = [n for n in names if n.startswith("--")]
        if longs:
            long_of.update({n: longs[0] for n in param.opts if len(n) == 2 and n[0] == "-" and n != "--"})
    if not long_of:
        return args
    out = list(args)
    i = 0
    while i < len(out):
        arg = out[i]
        if arg == "--":
            break
        if arg in long_of:
            out[i] = long_of[arg]
        # a value-taking option given without "=value" takes the next tokens as they are
        i += 1 + (values.get(arg, 0) if "=" not in arg else 0)
    return out


class _Command(click.Command):
    """A command whose outputs are checked against its inputs (:func:`evtk._atomic.guard_outputs`): an output
    that is an input, or two outputs that are one file, is refused before anything runs, and every file written
    while it runs may replace neither an input nor another of its outputs. Its short options are parsed as their
    long names (:func:`_long_spelling`)."""

    def parse_args(self, ctx, args):
        return super().parse_args(ctx, _long_spelling(self, ctx, args))

    def invoke(self, ctx):
        from .._atomic import guard_outputs

        outputs, inputs = _paths_of(ctx)
        with guard_outputs(outputs, inputs):
            return super().invoke(ctx)


class _LazyCommands(dict):
    """A group's commands, each module imported when one of its commands is first asked for by name, so that a
    fresh ``evtk reconstruct`` loads evtk.cli.reconstruct alone (click cleans every command's and option's help
    text when the module defining it loads: 3-5 ms for all of them); listing them, or asking for their number,
    imports every module first.

    Parameters
    ----------
    modules : dict
        Command name to the module (absolute name) that registers it.
    """

    def __init__(self, modules: dict[str, str]) -> None:
        super().__init__()
        self.modules = dict(modules)

    def _load(self, name: object) -> None:
        module = self.modules.get(name) if isinstance(name, str) else None
        if module is not None and not dict.__contains__(self, name):
            import importlib

            importlib.import_module(module)

    def _load_all(self) -> None:
        for name in list(self.modules):
            self._load(name)

    def get(self, name, default=None):
        self._load(name)
        return super().get(name, default)

    def __getitem__(self, name):
        self._load(name)
        return super().__getitem__(name)

    def __contains__(self, name: object) -> bool:
        self._load(name)
        return super().__contains__(name)

    def __iter__(self):
        self._load_all()
        return super().__iter__()

    def __len__(self) -> int:
        self._load_all()
        return super().__len__()

    def keys(self):
        self._load_all()
        return super().keys()

    def values(self):
        self._load_all()
        return super().values()

    def items(self):
        self._load_all()
        return super().items()


class _Group(click.Group):
    """Turns evtk errors and OS errors into one line on stderr and exit code 1; usage errors into one line and 2."""

    command_class = _Command
    group_class = type  # subgroups (evtk batch) are _Groups, their commands _Commands

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
@click.option("--verify-checksums/--no-verify-checksums", default=None,
              help="Check the checksums AEDAT4 packet bodies carry (LZ4 xxHash32 block and content checksums, "
                   "Zstandard content checksums): on by default; --no-verify-checksums reads damaged files "
                   "unchecked (EVTK_VERIFY_CHECKSUMS=0 does the same).")
@click.option("--memory-limit-mb", type=click.FloatRange(min=1, max=2**40),
              help="Largest allocation a command may plan (estimated first; default 8192).")
@click.option("--trigger-channel", type=click.IntRange(min=0, max=255),
              help="The trigger input whose edges make windows, when a camera records several (Prophesee).")
@click.option("--sensor-size", type=click.STRING, metavar="WxH",
              help="The sensor's size for files that do not give it (Prophesee without geometry, DAT, text, "
                   "N-MNIST, HDF5 and Parquet without one).")
@click.option("--layout", type=click.Choice(["dvs128", "davis"]),
              help="AEDAT 2.0: the address layout, where the header names no camera (found from the addresses "
                   "otherwise).")
@click.option("--threads", type=click.IntRange(min=1, max=4096),
              help="Threads for decoding, compression and parallel loops (default: every core the process may "
                   "run on; EVTK_THREADS does the same).")
@click.pass_context
def main(ctx, debug, trust_external, verify_checksums, memory_limit_mb, trigger_channel, sensor_size,
         layout, threads):
    """evtk: event recordings of the opto-electronic convolution accelerator."""
    import os

    from ..events import TRIGGER_CHANNEL_ENV
    from ..limits import LIMIT_ENV

    ctx.meta["evtk.debug"] = debug
    # through the environment, so that batch workers inherit them; put back when the command ends (it may
    # run inside another program, a test runner or a notebook)
    changes = {}
    if trust_external:
        changes["EVTK_TRUST_EXTERNAL"] = "1"
    if verify_checksums is not None:
        changes["EVTK_VERIFY_CHECKSUMS"] = "1" if verify_checksums else "0"
    if memory_limit_mb is not None:
        changes[LIMIT_ENV] = repr(float(memory_limit_mb))
    if trigger_channel is not None:
        changes[TRIGGER_CHANNEL_ENV] = str(trigger_channel)
    if sensor_size is not None:
        changes["EVTK_SENSOR_SIZE"] = sensor_size.strip()
    if layout is not None:
        changes["EVTK_LAYOUT"] = layout
    if threads is not None:
        from .._threads import ENV as THREADS_ENV

        changes[THREADS_ENV] = str(threads)
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
    import json  # here: a command without --json does not load it (1-1.5 ms of a fresh process)

    return json.dumps(_finite(obj), allow_nan=False)


def _options(opts):
    """A decorator applying a shared list of click options in order."""
    def deco(f):
        for opt in reversed(opts):
            f = opt(f)
        return f
    return deco


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


class _Parsed(click.ParamType):
    """A click type from a parse function that raises EvtkError: bad values are usage errors (exit status 2)."""

    def __init__(self, metavar, parse, **options):
        self.name = metavar
        self._parse = parse
        self._options = options

    def convert(self, value, param, ctx):
        if not isinstance(value, str):
            return value  # a default already parsed
        try:
            return self._parse(value, **self._options)
        except EvtkError as exc:
            self.fail(str(exc), param, ctx)


def _parse_binarize(text):
    if not isinstance(text, str):
        return text
    if text in ("auto", "sign", "mean", "otsu"):
        return text
    try:
        return float(text)
    except ValueError:
        raise EvtkError(f"--binarize must be auto, sign, mean, otsu or a number, not {text!r}") from None


def _parse_window(spec):
    if not isinstance(spec, str):
        return spec
    if spec.startswith("period:"):
        try:
            return ("period", int(spec.split(":", 1)[1]))
        except ValueError:
            raise EvtkError(f"--window period:US needs a whole number of us, not {spec!r}") from None
    if spec in ("schedule", "triggers"):
        return spec
    raise EvtkError(f"--window must be schedule, triggers or period:US, not {spec!r}")


def _parse_size(text):
    if not isinstance(text, str):
        return text
    try:
        rows, cols = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise EvtkError(f"--size must look like 16x16, not {text!r}") from None
    return rows, cols


def _parse_ints(text, n, name):
    try:
        vals = [float(v) for v in text.split(",")]
    except ValueError:
        vals = []
    if len(vals) != n or not all(np.isfinite(vals)):
        raise EvtkError(f"{name} must be {n} comma-separated numbers, not {text!r}")
    return vals


def _parse_region(text):
    x0, x1, y0, y1 = (int(v) for v in _parse_ints(text, 4, "--region"))
    if not (0 <= x0 < x1 and 0 <= y0 < y1):
        raise EvtkError(f"--region X0,X1,Y0,Y1 must satisfy 0 <= X0 < X1 and 0 <= Y0 < Y1, not {text!r}")
    return (x0, x1, y0, y1)


WINDOW = _Parsed("window", _parse_window)
REGION = _Parsed("X0,X1,Y0,Y1", _parse_region)
POINT = _Parsed("X,Y", lambda text: tuple(_parse_ints(text, 2, "--origin-px")))
SIZE = _Parsed("ROWSxCOLS", _parse_size)
BINARIZE = _Parsed("binarize", _parse_binarize)


def number_list(name, integer=False, allow_zero=False):
    """A click type for a comma-separated list of positive numbers (whole ones with ``integer``)."""
    return _Parsed("LIST", lambda text: _number_list(text, name, integer, allow_zero))


#: ``--theta``, shared by reconstruct, batch reconstruct and enob (ReconstructOptions refuses NaN and infinity).
_theta_option = click.option(
    "--theta", type=click.FloatRange(min=0, min_open=True),
    help="A fixed contrast threshold (log units) linearising by exp(n theta): fixed windows, or a simulated run in "
         "place of its pixel model. Default: the plan's pixel model where there is one, else net counts.")

_reconstruct_options = _options([
    click.option("--window", "window_spec", type=WINDOW, default="schedule", show_default=True,
                 help="schedule, triggers or period:US (without a schedule every window is a repeat of one scene)."),
    click.option("--skip-us", type=click.IntRange(min=0, max=_MAX_INT), default=0, show_default=True,
                 help="Leave out the start of every window (pixel settling)."),
    click.option("--length-us", type=click.IntRange(min=1, max=_MAX_INT), help="Keep at most this much of every window."),
    click.option("--size", type=SIZE, default="16x16", show_default=True, help="Size of each response, ROWSxCOLS."),
    click.option("--binarize", "binarize_method", type=BINARIZE, default="auto", show_default=True,
                 help="auto (sign for signed responses, else each response's mean), sign, mean, otsu or a threshold."),
    click.option("--linearize/--counts", default=True, show_default=True,
                 help="Linearise counts to light, or keep net counts (ON - OFF). Fixed windows (--window triggers "
                      "or period:US) have no pixel model to linearise by and stay net counts, unless --theta."),
    _theta_option,
    click.option("--crop", type=click.Choice(["valid", "full"]), default="valid", show_default=True),
    click.option("--flat-field/--no-flat-field", default=True, show_default=True,
                 help="Calibrate each pixel's threshold on the recording's flat-field captures, if any."),
    click.option("--deblur/--no-deblur", default=None,
                 help="Undo the known optical footprint blur (default: when the pixels are calibrated)."),
    click.option("--timing/--no-timing", default=None,
                 help="Read light below one threshold from each window's first and last ON-event times "
                      "(default: wherever the recording's pixel model allows)."),
])


def _reconstruct_settings(window_spec, skip_us, length_us, size, binarize_method, linearize, crop, flat_field,
                          deblur, timing, theta=None, region=None):
    """The options of :data:`_reconstruct_options` as one :class:`evtk.reconstruct.ReconstructOptions`."""
    from ..reconstruct import ReconstructOptions

    return ReconstructOptions(window=window_spec, skip_us=skip_us, length_us=length_us,
                              size=size, binarize_method=binarize_method,
                              linear=linearize, crop=crop, flat_field=flat_field, deblur=deblur, timing=timing,
                              theta=theta, region=region)


def _number_list(text, name="the list", integer=False, allow_zero=False):
    if isinstance(text, list):
        return text
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


def _reconstructed(path, oracle=False, schedule=None, calibration=None, origin_px=None, **options):
    """:func:`evtk.workflow.reconstruct_recording` on one recording with a progress bar; returns
    (result, {events, sensor_size, power_mw})."""
    from ..reconstruct.route import has_record
    from ..workflow import reconstruct_recording

    with evio.open(path) as rec:
        n_events = rec.info()["events"]
        update, finish = _progress(n_events, f"reconstructing {path}")
        try:
            result = reconstruct_recording(rec, oracle=oracle, schedule=schedule, calibration=calibration,
                                           origin_px=origin_px, progress=update, **options)
        finally:
            finish()
        power_mw = None
        if has_record(rec.metadata):  # (the record's module, with the optics, loads for a simulated run only)
            from ..plan import SimulationRecord

            sim = SimulationRecord.from_metadata(rec.metadata)
            power_mw = None if sim is None else sim.bench.power_mw
        about = {"events": n_events, "sensor_size": rec.sensor_size, "power_mw": power_mw}
    return result, about


_scheduler_option = click.option(
    "--scheduler", "scheduler_spec", default=None,
    help="Where independent tasks run: serial, local[:N] (a local Dask cluster) or tcp://HOST:PORT; "
         "default local with Dask installed, else serial.")


_window_options = [
    click.option("--window", "window_spec", type=WINDOW, default="schedule", show_default=True,
                 help="schedule, triggers or period:US (without a schedule every window is a repeat of one scene)."),
    click.option("--skip-us", type=click.IntRange(min=0, max=_MAX_INT), default=0, show_default=True),
    click.option("--length-us", type=click.IntRange(min=1, max=_MAX_INT)),
]


_with_window_options = _options(_window_options)


def _inf_if_free(row, key):
    s = row["sinad"]
    if s is None:
        return None
    return float("inf") if s["noise_free"] else s[key]


def _load_array(path, what):
    import os

    ext = os.path.splitext(path)[1].lower()
    if ext != ".npy":
        raise EvtkError(f"{what} must be a .npy file, not {path!r}")
    from .._loaders import read_npy

    return read_npy(path, what)


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
