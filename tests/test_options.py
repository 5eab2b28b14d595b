"""One source for options (issue 30): the command-line options of ``evtk reconstruct`` and ``evtk batch reconstruct``
are checked against :class:`evtk.reconstruct.ReconstructOptions`, field by field, default by default."""

import dataclasses
import inspect

import click
import pytest

from evtk.cli import main
from evtk.cli._base import _reconstruct_settings
from evtk.reconstruct import ReconstructOptions

COMMANDS = [("reconstruct",), ("batch", "reconstruct")]
#: fields no reconstruct option sets: region comes from --region (or --calibration)
NOT_OPTIONS = {"region"}


def _command(path):
    cmd = main
    for name in path:
        cmd = cmd.commands[name]
    return cmd


@pytest.mark.parametrize("path", COMMANDS, ids=" ".join)
def test_the_commands_defaults_are_the_dataclass_defaults(path):
    cmd = _command(path)
    ctx = click.Context(cmd)
    names = set(inspect.signature(_reconstruct_settings).parameters) - {"region"}
    defaults = {}
    for p in cmd.params:
        if p.name in names:
            value = p.get_default(ctx, call=True)
            unset = value is None or type(value).__name__ == "Sentinel"  # click 8.2+: no default given
            defaults[p.name] = None if unset else p.type_cast_value(ctx, value)
    assert set(defaults) == names, f"{' '.join(path)} lacks {sorted(names - set(defaults))}"
    assert _reconstruct_settings(**defaults) == ReconstructOptions()


def test_every_dataclass_field_is_set_by_an_option_or_named_as_not():
    fields = {f.name for f in dataclasses.fields(ReconstructOptions)}
    set_by = set(inspect.signature(_reconstruct_settings).parameters)
    renamed = {"window_spec": "window", "linearize": "linear"}
    covered = {renamed.get(n, n) for n in set_by}
    assert fields - covered <= NOT_OPTIONS, f"fields no option sets: {sorted(fields - covered - NOT_OPTIONS)}"
    assert covered - {"region"} <= fields


def test_enob_window_options_are_the_dataclass_defaults_and_the_library_defaults():
    """`evtk enob`'s windows are cut as reconstruct's (the same fields of ReconstructOptions), and its interval and
    per-pixel flag default as evtk.sweeps.recording_noise does: one source for each default."""
    from evtk.sweeps import recording_noise

    cmd = _command(("enob",))
    ctx = click.Context(cmd)
    got = {p.name: p.get_default(ctx, call=True) for p in cmd.params}
    fields = {f.name: f.default for f in dataclasses.fields(ReconstructOptions)}
    assert got["window_spec"] == fields["window"]
    assert got["skip_us"] == fields["skip_us"]
    assert (None if type(got["length_us"]).__name__ == "Sentinel" else got["length_us"]) == fields["length_us"]
    lib = inspect.signature(recording_noise).parameters
    assert got["interval"] == lib["interval"].default
    assert bool(got["per_pixel"]) == lib["per_pixel"].default
