"""Conformance on the real recordings beside the checkout (``../shared/real-files``, issue 33): every event file
an independent reader decodes reads exactly, with no sensor size passed; 40 time windows, ``iter_events`` and the
triggers (with their channels) too. The files are never copied into the repository (their licences differ)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

REAL = Path(__file__).resolve().parent.parent.parent / "shared" / "real-files"
pytestmark = pytest.mark.skipif(not (REAL / "check_evtk.py").exists(),
                                reason="../shared/real-files is not beside the checkout")


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    for module in ("evt3", "event_stream", "tonic", "expelliarmus", "faery", "dv_processing"):
        pytest.importorskip(module)
    out = tmp_path_factory.mktemp("real") / "results.json"
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parent.parent))
    done = subprocess.run([sys.executable, str(REAL / "check_evtk.py"), str(REAL), "refs.json", str(out)],
                          capture_output=True, text=True, timeout=1200, env=env)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(out.read_text()), json.loads((REAL / "refs.json").read_text())


def test_every_file_a_reference_reader_decodes_reads_exactly(results):
    got, refs = results
    decoded = [name for name, ref in refs.items() if "sha256" in ref]  # a reference decode of DVS events exists
    assert len(decoded) >= 27
    wrong = {name: got[name].get("result") for name in decoded
             if not str(got.get(name, {}).get("result", "")).startswith("exact")}
    assert not wrong, f"not exact: {wrong}"


def test_windows_streaming_and_triggers_agree_with_the_references(results):
    got, refs = results
    for name, ref in refs.items():
        if "sha256" not in ref:
            continue
        r = got[name]
        assert "'n_wrong': 0" in str(r.get("windows")), (name, r.get("windows"))
        if str(r.get("reference_events")) != "0":  # a header-only file has no stream to compare
            assert str(r.get("iter_events_7777_equal")) == "True", name
        trig = r.get("triggers")
        if isinstance(trig, dict) and trig.get("reference"):
            assert trig.get("t_same") and trig.get("edge_same"), (name, trig)
            if trig.get("reference_channels"):
                assert trig.get("evtk_keeps_channel"), (name, trig)


def test_files_no_reader_decodes_are_read_or_refused_by_name(results):
    got, refs = results
    for name, ref in refs.items():
        if "sha256" in ref:
            continue
        r = got[name]
        res = str(r.get("result", ""))
        assert "crash" not in res and "Traceback" not in json.dumps(r), (name, res)
        if name.endswith(".es"):  # Event Stream colour and generic streams: refused, naming the type
            error = str(r.get("evtk_error", ""))
            assert res == "error" and ("colour" in error or "generic" in error), (name, res, error)
