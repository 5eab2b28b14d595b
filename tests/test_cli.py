import gc
import json
import subprocess
import sys

import numpy as np
import pytest
from click.testing import CliRunner
from conftest import random_events

import evtk
from evtk.cli import main


def run(*args):
    result = CliRunner().invoke(main, [str(a) for a in args])
    return result


def test_version():
    r = run("--version")
    assert r.exit_code == 0 and evtk.__version__ in r.output


def test_info_json_on_fixture(fixtures_dir):
    r = run("info", "--json", fixtures_dir / "dvxplorer_lz4.aedat4")
    assert r.exit_code == 0, r.output
    info = json.loads(r.output)
    assert info["format"] == "aedat4" and info["compression"] == "lz4"
    assert info["events"] == 4000 and info["triggers"] == 20
    assert info["sensor_size"] == [320, 240]
    with evtk.open(fixtures_dir / "dvxplorer_lz4.aedat4") as rec:
        ev = rec.events()
    assert info["t_start_us"] == ev.t.min() and info["t_end_us"] == ev.t.max()
    names = {s["name"]: s for s in info["streams"]}
    assert set(names) == {"events", "triggers", "imu", "frames"}
    assert names["imu"]["count"] == 1 and names["frames"]["type"] == "FRME"
    assert all({"name", "type", "count"} <= set(s) for s in info["streams"])


def test_info_human(fixtures_dir):
    r = run("info", fixtures_dir / "dvxplorer_zstd.aedat4")
    assert r.exit_code == 0
    assert "4,000" in r.output and "320x240" in r.output and "zstd" in r.output


@pytest.mark.parametrize("compression", ["lz4", "zstd", "none"])
def test_convert_keeps_events_and_triggers(tmp_path, fixtures_dir, compression):
    src = fixtures_dir / "dvxplorer_lz4.aedat4"
    out = tmp_path / "out.aedat4"
    r = run("convert", src, out, "--compression", compression)
    assert r.exit_code == 0, r.output
    with evtk.open(src) as a, evtk.open(out) as b:
        assert b.compression == compression
        assert a.events() == b.events() and a.triggers() == b.triggers()


def test_salvage_flag(tmp_path):
    ev = random_events(5000, seed=1)
    good = tmp_path / "g.aedat4"
    evtk.write_events(good, ev, packet_events=1000, packet_us=None)
    bad = tmp_path / "b.aedat4"
    bad.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    r = run("info", bad)
    assert r.exit_code == 1
    r = run("info", "--json", "--salvage", bad)
    assert r.exit_code == 0, r.output
    info = json.loads(r.output)
    assert 0 < info["events"] < 5000 and info["events"] % 1000 == 0
    assert info["damage"]["offset"] > 0


def test_info_check_and_salvage_read_every_event(tmp_path):
    """A packet damaged in the middle, the file's index intact: plain info reports the index (5,000
    events); --check reads the events and fails at the damage; --salvage reports what salvage recovers
    (the packets before it), not the index's count."""
    ev = random_events(5000, seed=1)
    good = tmp_path / "g.aedat4"
    evtk.write_events(good, ev, packet_events=1000, packet_us=None)
    data = bytearray(good.read_bytes())
    at = int(len(data) * 0.6)
    data[at:at + 64] = bytes(64)
    bad = tmp_path / "b.aedat4"
    bad.write_bytes(bytes(data))
    assert json.loads(run("info", "--json", bad).output)["events"] == 5000
    r = run("info", "--check", bad)
    assert r.exit_code == 1 and "cannot be decompressed" in r.output
    r = run("info", "--json", "--salvage", bad)
    assert r.exit_code == 0, r.output
    info = json.loads(r.output)
    with evtk.open(bad, salvage=True) as rec:
        got = rec.events()
    assert 0 < len(got) < 5000 and got == ev[:len(got)]
    assert (info["events"], info["t_start_us"], info["t_end_us"]) == (len(got), int(got.t[0]), int(got.t[-1]))
    assert info["damage"]["offset"] > 0 and info["scanned"]
    assert "streams (as the file indexes them)" in run("info", "--salvage", bad).output
    r = run("info", "--json", "--check", good)
    assert r.exit_code == 0 and json.loads(r.output)["events"] == 5000
    assert json.loads(r.output)["t_end_us"] == int(ev.t[-1])


@pytest.mark.parametrize(
    "args, match",
    [
        (["info", "/no/such/file.aedat4"], "no such file"),
        (["convert", "/no/such/file.aedat4", "x.aedat4"], "no such file"),
    ],
)
def test_errors_are_one_line_without_traceback(args, match):
    r = run(*args)
    assert r.exit_code == 1
    assert match in r.output
    assert "Traceback" not in r.output
    assert len(r.output.strip().splitlines()) == 1


def test_bad_file_and_bad_target(tmp_path, fixtures_dir):
    junk = tmp_path / "junk.aedat4"
    junk.write_bytes(b"\x00" * 100)
    r = run("info", junk)
    assert r.exit_code == 1 and "unrecognised" in r.output and "Traceback" not in r.output
    r = run("convert", fixtures_dir / "dvxplorer_lz4.aedat4", tmp_path / "out.xyz")
    assert r.exit_code == 1 and "extension" in r.output
    r = run("convert", fixtures_dir / "dvxplorer_lz4.aedat4", tmp_path / "o.aedat4", "--compression", "rar")
    assert r.exit_code == 2  # click's usage error


def test_installed_entry_point(fixtures_dir):
    out = subprocess.run(
        [sys.executable, "-m", "evtk.cli", "info", "--json", str(fixtures_dir / "dvxplorer_lz4.aedat4")],
        capture_output=True, text=True, check=True,
    )
    assert json.loads(out.stdout)["events"] == 4000
    bad = subprocess.run([sys.executable, "-m", "evtk.cli", "info", "/nope"], capture_output=True, text=True)
    assert bad.returncode == 1 and bad.stderr.startswith("evtk: error:") and "Traceback" not in bad.stderr


@pytest.mark.parametrize("ext, fmt", [(".h5", "hdf5"), (".parquet", "parquet"), (".aedat4", "aedat4")])
def test_info_on_every_format(tmp_path, fixtures_dir, ext, fmt):
    out = tmp_path / ("x" + ext)
    assert run("convert", fixtures_dir / "dvxplorer_zstd.aedat4", out).exit_code == 0
    r = run("info", "--json", out)
    assert r.exit_code == 0, r.output
    info = json.loads(r.output)
    assert info["format"] == fmt and info["events"] == 4000 and info["triggers"] == 20
    assert info["sensor_size"] == [320, 240]
    assert run("info", out).exit_code == 0


def test_convert_streams_in_bounded_chunks(tmp_path, monkeypatch):
    """convert never asks the reader for more than --chunk-events at a time."""
    ev = random_events(50_000, seed=2)
    src = tmp_path / "s.aedat4"
    evtk.write_events(src, ev, packet_events=1000)
    seen = []
    from evtk.io import aedat4

    original = aedat4.Recording.iter_events

    def spy(self, chunk_events=1_000_000, **kw):
        for chunk in original(self, chunk_events=chunk_events, **kw):
            seen.append(len(chunk))
            yield chunk

    monkeypatch.setattr(aedat4.Recording, "iter_events", spy)
    for ext in (".h5", ".parquet", ".aedat4"):
        seen.clear()
        out = tmp_path / ("o" + ext)
        r = run("convert", src, out, "--chunk-events", 7000)
        assert r.exit_code == 0, r.output
        assert max(seen) <= 7000 and sum(seen) == len(ev)
        assert evtk.read_events(out) == ev


def test_convert_unsorted_needs_sort_flag_for_hdf5(tmp_path):
    ev = random_events(3000, seed=3, sort=False)
    src = tmp_path / "u.aedat4"
    evtk.write_events(src, ev)
    r = run("convert", src, tmp_path / "u.h5")
    assert r.exit_code == 1 and "time order" in r.output
    assert not (tmp_path / "u.h5").exists()
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".evtk-partial")]
    r = run("convert", "--sort", src, tmp_path / "u.h5")
    assert r.exit_code == 0
    got = evtk.read_events(tmp_path / "u.h5")
    assert got.is_sorted and len(got) == len(ev)


@pytest.mark.parametrize("args", [
    ["info", "{missing}"], ["info", "{junk}"], ["info", "--salvage", "{junk}"], ["info", "{dir}"],
    ["convert", "{missing}", "{out}.aedat4"], ["convert", "{junk}", "{out}.aedat4"],
    ["simulate", "--kernel-bits", "12", "-o", "{out}.aedat4"], ["simulate", "--window-us", "0", "-o", "{out}.h5"],
    ["simulate", "--features", "{missing}", "-o", "{out}.h5"], ["simulate", "--features", "{junk}", "-o", "{out}.h5"],
    ["simulate", "-o", "{out}.txt"], ["simulate", "--bench", "{junk}", "-o", "{out}.h5"],
    ["reconstruct", "{missing}", "-o", "{out}.npz"], ["reconstruct", "{junk}", "-o", "{out}.npz"],
    ["reconstruct", "{junk}", "-o", "{out}.npz", "--size", "4by4"], ["reconstruct"],
    ["demo", "--out", "{junk}"], ["demo", "--repeat", "1"],
    ["enob", "{missing}"], ["enob", "{junk}"], ["enob", "{junk}", "--bootstrap", "-1"],
    ["flips", "{junk}"], ["flips", "--power-mw", "x"], ["flips", "--repeats", "1"],
    ["tradeoff", "--window-us", "0"], ["tradeoff", "--kernels", "0"], ["tradeoff", "--settle-us", "1.5"],
    ["recover", "--target-kernel-bits", "12"], ["recover", "--size", "9", "--target-kernel-bits", "1"],
    ["recover", "--target", "{junk}"], ["recover", "--features", "{junk}", "--target-kernel-bits", "111000111"],
    ["classify", "--task", "nosuch"], ["classify", "--runs", "0"], ["classify", "--data-dir", "{missing}"],
    ["robustness", "--scales", "-1"], ["robustness", "--optimizer", "sgd"],
    ["nosuchcommand"], ["info", "--nosuchflag", "x"],
])
def test_every_command_fails_in_one_line(tmp_path, args):
    """Missing, unreadable or wrong-format files and nonsense parameters: one line, non-zero exit, no traceback."""
    junk = tmp_path / "junk.aedat4"
    junk.write_bytes(b"\x00garbage" * 50)
    fill = {"{missing}": str(tmp_path / "nope" / "missing.aedat4"), "{junk}": str(junk),
            "{dir}": str(tmp_path), "{out}": str(tmp_path / "out")}
    argv = [fill.get(a, a.replace("{out}", str(tmp_path / "out"))) for a in args]
    r = run(*argv)
    assert r.exit_code in (1, 2), (argv, r.exit_code, r.output)
    assert "Traceback" not in r.output
    lines = r.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("evtk: error: "), (argv, r.output)
    assert not (tmp_path / "out.aedat4").exists() and not (tmp_path / "out.h5").exists()


def test_version_and_help_load_no_reader_or_compiler():
    """`evtk --version` and `--help` start without numba, h5py, pyarrow or Dask: they load on first use."""
    code = ("import sys\n"
            "from evtk.cli import main\n"
            "for args in (['--version'], ['--help'], ['info', '--help']):\n"
            "    try:\n"
            "        main(args)\n"
            "    except SystemExit:\n"
            "        pass\n"
            "heavy = sorted(m for m in ('numba', 'h5py', 'pyarrow', 'distributed', 'scipy', 'skimage', 'matplotlib')\n"
            "               if m in sys.modules)\n"
            "print('HEAVY', heavy)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert "HEAVY []" in out, out


def test_info_on_an_aedat4_file_with_a_data_table_loads_no_compiler(tmp_path):
    """Describing a file reads its header and data table in plain Python and numpy (no numba to load)."""
    path = tmp_path / "i.aedat4"
    evtk.write_events(path, evtk.Events(np.arange(4000), np.zeros(4000, np.uint16), np.zeros(4000, np.uint16),
                                        np.ones(4000, np.uint8), (320, 240)))
    code = ("import sys\n"
            "from evtk.cli import main\n"
            "try:\n"
            f"    main(['info', '--json', {str(path)!r}])\n"
            "except SystemExit:\n"
            "    pass\n"
            "print('NUMBA', 'numba' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert '"events": 4000' in out and "NUMBA False" in out, out


def test_the_installed_command_freezes_the_collector_after_its_command_and_main_does_not(fixtures_dir, tmp_path):
    """`evtk` (the console entry point, and ``python -m evtk.cli``) freezes the objects alive after its command out
    of the garbage collector, so the interpreter's exit skips collecting them; ``main``, which other programs call
    and go on after, leaves the collector as it was. The exit status and the output are the command's."""
    from importlib.metadata import entry_points

    [script] = [e for e in entry_points(group="console_scripts") if e.name == "evtk"]
    assert script.value == "evtk.cli:console"
    probe = ("import atexit, gc, sys\n"
             "atexit.register(lambda: print('FROZEN', gc.get_freeze_count() > 0))\n"
             "from evtk.cli import console\n"
             "console(sys.argv[1:])\n")
    good = subprocess.run([sys.executable, "-c", probe, "info", "--json", str(fixtures_dir / "dvxplorer_lz4.aedat4")],
                          capture_output=True, text=True)
    assert good.returncode == 0 and '"events": 4000' in good.stdout and "FROZEN True" in good.stdout, good
    bad = subprocess.run([sys.executable, "-c", probe, "info", str(tmp_path / "missing.aedat4")],
                         capture_output=True, text=True)
    assert bad.returncode == 1 and "evtk: error: " in bad.stderr and "FROZEN True" in bad.stdout, bad
    module = subprocess.run([sys.executable, "-c", "import atexit, gc, runpy, sys\n"
                             "atexit.register(lambda: print('FROZEN', gc.get_freeze_count() > 0))\n"
                             "sys.argv = ['evtk', '--version']\n"
                             "runpy.run_module('evtk.cli', run_name='__main__')\n"], capture_output=True, text=True)
    assert module.returncode == 0 and evtk.__version__ in module.stdout and "FROZEN True" in module.stdout, module
    before = gc.get_freeze_count()
    assert run("info", fixtures_dir / "dvxplorer_lz4.aedat4").exit_code == 0
    assert gc.get_freeze_count() == before
