"""The ``evtk`` commands parse a short option that stands alone as its long name (``-o`` as ``--output``), so that
click's near-name suggestion (difflib) is not loaded for it; what a command receives must not change."""

from __future__ import annotations

import click
import pytest

from evtk.cli._base import _Command, _long_spelling


def _options(fn):
    fn = click.argument("inputs", nargs=-1)(fn)
    fn = click.option("-o", "--output", default=None)(fn)
    fn = click.option("--title", default=None)(fn)
    fn = click.option("--pair", nargs=2, type=int, default=None)(fn)
    fn = click.option("--flag/--no-flag", default=False)(fn)
    fn = click.option("-v", "--verbose", count=True)(fn)
    return fn


@_options
def _body(**kwargs):
    return kwargs


ARGS = [
    ["a", "-o", "x.npz"],
    ["-o", "x.npz", "a", "b"],
    ["--title", "-o", "a"],  # "-o" is the title here: left as it is
    ["--title=-o", "-o", "y"],
    ["-o=x", "a"],  # click's short form: the value is "=x"
    ["-ox.npz", "a"],
    ["a", "--", "-o", "x"],  # after "--": an input named "-o"
    ["--pair", "1", "2", "-o", "z"],
    ["-v", "-v", "--flag", "-o", "-v"],  # "-v" is the output's value
    ["-vv", "a", "-o", "q"],
    ["--output", "-o", "b"],
    [],
]


def _parse(cls, args):
    cmd = cls("t", callback=_body, params=list(reversed(getattr(_body, "__click_params__", []))))
    try:
        with cmd.make_context("t", list(args)) as ctx:
            return ctx.params
    except click.UsageError as exc:
        return type(exc).__name__


@pytest.mark.parametrize("args", ARGS)
def test_the_long_spelling_parses_as_click_does(args):
    assert _parse(_Command, args) == _parse(click.Command, args)


def test_only_standalone_short_options_outside_values_are_spelled_long():
    cmd = _Command("t", callback=_body, params=list(reversed(_body.__click_params__)))
    ctx = click.Context(cmd)
    assert _long_spelling(cmd, ctx, ["a", "-o", "x", "--title", "-o", "--", "-o"]) == [
        "a", "--output", "x", "--title", "-o", "--", "-o"]
    assert _long_spelling(cmd, ctx, ["-ox", "-o=y", "-vv"]) == ["-ox", "-o=y", "-vv"]


def test_a_command_with_an_optional_value_is_left_to_click():
    @click.option("-o", "--output", is_flag=False, flag_value="default.npz", default=None)
    def body(**kwargs):
        return kwargs

    cmd = _Command("t", callback=body, params=list(body.__click_params__))
    ctx = click.Context(cmd)
    assert _long_spelling(cmd, ctx, ["-o", "x"]) == ["-o", "x"]
