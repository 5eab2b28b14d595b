"""``import evtk`` asks OpenBLAS's idle threads to sleep at once instead of busy-waiting (issue 32, tenth round:
1.2-1.9 s of CPU time in every fresh process of a 16-core machine went to their spinning), before numpy loads, and
only where the user has not set it and numpy has not loaded (then the setting could no longer take effect)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest


def _timeout_seen(code: str, value: str | None) -> str:
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_THREAD_TIMEOUT"}
    if value is not None:
        env["OPENBLAS_THREAD_TIMEOUT"] = value
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    return done.stdout.strip()


SHOW = "import os; print(os.environ.get('OPENBLAS_THREAD_TIMEOUT'))"


def test_import_evtk_sets_the_timeout_before_numpy_loads():
    code = ("import sys, evtk; assert 'numpy' not in sys.modules; import numpy; " + SHOW)
    assert _timeout_seen(code, None) == "4"


@pytest.mark.parametrize("value", ["12", "30"])
def test_a_users_timeout_is_kept(value):
    assert _timeout_seen("import evtk; " + SHOW, value) == value


def test_nothing_is_set_once_numpy_has_loaded():
    assert _timeout_seen("import numpy, evtk; " + SHOW, None) == "None"


def test_the_command_line_sets_it_for_its_own_process_and_children():
    code = ("import sys, subprocess; from evtk.cli import main; "
            "print(subprocess.run([sys.executable, '-c', \"" + SHOW + "\"], capture_output=True, text=True).stdout)")
    assert _timeout_seen(code, None) == "4"
