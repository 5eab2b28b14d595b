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
#: fields no reconstruct option sets: theta comes from the recording or --calibration, region from --region
NOT_OPTIONS = {"theta", "region"}


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
