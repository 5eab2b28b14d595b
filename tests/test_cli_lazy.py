"""The ``evtk`` command loads the module of the command it runs, not every command's (issue 32: a fresh process's
start-up), and its table of which module registers which command stays complete."""

from __future__ import annotations

from conftest import modules_after

from evtk.cli import COMMAND_MODULES, main


def test_every_command_is_in_the_table_under_its_module():
    commands = dict(main.commands.items())  # lists them: every module loads
    assert sorted(commands) == sorted(COMMAND_MODULES)
    for name, cmd in commands.items():
        assert cmd.callback is not None and cmd.callback.__module__ == f"evtk.cli.{COMMAND_MODULES[name]}", name


def test_a_command_loads_its_own_module_only():
    loaded = modules_after("from evtk.cli import main\n"
                           "try:\n    main(['reconstruct', '--help'])\nexcept SystemExit as exc:\n    assert not exc.code\n")
    assert [m for m in loaded if m.startswith("evtk.cli.")] == ["evtk.cli._base", "evtk.cli.reconstruct"]


def test_the_help_lists_every_command_and_an_unknown_one_is_refused():
    from click.testing import CliRunner

    res = CliRunner().invoke(main, ["--help"])
    assert res.exit_code == 0 and all(f"  {name} " in res.output for name in COMMAND_MODULES)
    res = CliRunner().invoke(main, ["reconstrct"])
    assert res.exit_code != 0 and "No such command" in res.output


def test_enob_on_fixed_windows_loads_no_reconstruction_options_optics_or_compiler(tmp_path):
    """`evtk enob --window period:US` measures net counts: its check of --theta is the shared one
    (:func:`evtk.errors.check_positive`), not a ReconstructOptions built for it, and it loads none of the
    optics, the sensor model, the simulator, numba or scipy (issue 32: a fresh enob's start)."""
    from conftest import random_events

    from evtk.io import write_events

    path = tmp_path / "r.aedat4"
    write_events(path, random_events(20_000, seed=3, span_us=100_000))
    loaded = modules_after("from evtk.cli import main\n"
                           f"try:\n    main(['enob', {str(path)!r}, '--window', 'period:10000', '--theta', '0.2'])\n"
                           "except SystemExit as exc:\n    assert not exc.code, exc.code\n")
    assert "evtk.sweeps" in loaded and "evtk.metrics.sinad" in loaded  # (it measured)
    for name in ("evtk.reconstruct.options", "evtk.optics", "evtk.sensor", "evtk.simulate", "numba", "scipy"):
        assert name not in loaded, name
