"""A fresh process that reads one format imports only what that format needs: no compiler (numba, llvmlite),
no scipy, no plotting, and no other format's library (h5py, pyarrow). Importing numba alone took 0.5-1 s of a
read of a 2 MB file whose decode takes milliseconds (issue 32); the AEDAT4 case is also in
``test_aedat4_bad_input.py``."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import random_events
from test_aedat_legacy import write_aedat2_davis

import evtk
from evtk._native import enabled as native_enabled

HEAVY = ("numba", "llvmlite", "scipy", "matplotlib", "h5py", "pyarrow", "dask", "distributed", "pandas")


def _nmnist(path, n=200):
    """An N-MNIST binary: x, y, then the polarity in bit 7 and a 23-bit time stamp over three bytes."""
    rng = np.random.default_rng(4)
    t = np.sort(rng.integers(0, 300_000, n))
    rec = np.empty((n, 5), np.uint8)
    rec[:, 0], rec[:, 1] = rng.integers(0, 34, n), rng.integers(0, 34, n)
    rec[:, 2] = (rng.integers(0, 2, n) << 7) | (t >> 16)
    rec[:, 3], rec[:, 4] = (t >> 8) & 0xFF, t & 0xFF
    path.write_bytes(rec.tobytes())


def _fixture(tmp_path: Path, fmt: str) -> Path:
    ev = random_events(50_000, seed=9, sensor_size=(320, 240))
    if fmt == "aedat2":
        path = tmp_path / "f.aedat"
        write_aedat2_davis(path, ev, 240)
    elif fmt == "nmnist":
        path = tmp_path / "f.bin"
        _nmnist(path)
    else:
        ext = {"aedat4": "aedat4", "evt2": "raw", "evt3": "raw", "dat": "dat", "es": "es", "hdf5": "h5",
               "parquet": "parquet", "csv": "csv"}[fmt]
        path = tmp_path / f"f.{ext}"
        evtk.write_events(path, ev, fmt=fmt)
    return path


def _loaded_by(code: str) -> list[str]:
    env = dict(os.environ, PYTHONPATH=str(Path(evtk.__file__).parents[1]))  # this checkout's evtk
    code += f"\nprint('LOADED', sorted(m for m in {HEAVY!r} if m in sys.modules))\n"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env).stdout
    return eval(out.split("LOADED", 1)[1].strip())  # a list of names printed by the child


# what each format's own reader needs (its library); nothing else may load
ALLOWED = {"hdf5": {"h5py"}, "parquet": {"pyarrow"}}
FORMATS = ["aedat4", "evt2", "evt3", "dat", "es", "aedat2", "nmnist", "csv", "hdf5", "parquet"]


@pytest.mark.parametrize("fmt", FORMATS)
def test_a_fresh_read_loads_only_what_the_format_needs(tmp_path, fmt):
    """Read every event, the streams and a window: EVT 2.0, EVT 3.0, DAT and Event Stream loaded numba (and with it scipy) for
    their decoders, HDF5 and Parquet for their order check."""
    path = _fixture(tmp_path, fmt)
    loaded = _loaded_by("import sys, evtk\n"
                        f"with evtk.open({str(path)!r}) as rec:\n"
                        "    n = len(rec.events())\n"
                        "    n += len(rec.events(0, 50_000)) + sum(s.count or 0 for s in rec.streams)\n"
                        "assert n > 0\n")
    assert set(loaded) <= ALLOWED.get(fmt, set()), loaded


@pytest.mark.parametrize("fmt", ["evt2", "evt3", "dat", "es", "hdf5"])
def test_info_and_convert_to_hdf5_load_no_compiler(tmp_path, fmt):
    """`evtk info --check` and `evtk convert F out.h5` went through numba's order check (io/_checks.py)."""
    path = _fixture(tmp_path, fmt)
    out = tmp_path / "out_converted.h5"
    loaded = _loaded_by("import sys\n"
                        "from evtk.cli import main\n"
                        f"for args in (['info', '--check', {str(path)!r}], ['convert', {str(path)!r}, {str(out)!r}]):\n"
                        "    try:\n"
                        "        main(args)\n"
                        "    except SystemExit as exc:\n"
                        "        assert not exc.code, exc.code\n")
    assert set(loaded) <= {"h5py"}, loaded
    assert len(evtk.read_events(out)) == 50_000


# what a fresh process's start pays for beyond Python, numpy and evtk's own modules: 0.5-2.5 ms each here, against
# peers whose whole read of a small file takes a few (issue 32)
START_UP = ("lz4", "zstandard", "xxhash", "hdf5plugin", "click", "xml.etree.ElementTree", "json", "threading",
            "numpy.typing", "dataclasses", "xml.parsers.expat", "pyexpat", "bisect", "_bisect")
# an AEDAT4 file evtk writes has LZ4 packets, decoded through the LZ4 library bound by ctypes: python-lz4's frame
# module (with the stdlib's _compression) and threading (the pool's lock is _thread's) load for none of them
# module; the Prophesee decoders' numpy and numba routes (their module, numba's lazy decorator and _bisect, a shared
# library to load, 0.2-0.7 ms, which Event Stream's numpy route searches with) load only where the compiled kernels
# are off; _queue (0.4 ms) with the first thread pool, which a small read on one thread never starts
START_UP += ("_queue", "evtk.io.prophesee._fallbacks", "evtk._lazyjit",
             # evtk's own modules a read does not need: the Arrow table code (the header checks every reader uses
             # live with the errors), the version (the writers and the command line load it), the trigger kinds
             "evtk._table", "evtk._version", "evtk._trigger_kind")
START_UP_NEEDED: dict[str, set[str]] = ({} if native_enabled() else
                                        {fmt: {"_bisect", "evtk.io.prophesee._fallbacks", "evtk._lazyjit"}
                                         for fmt in ("evt3", "es", "evt2", "dat")})


@pytest.mark.parametrize("fmt", ["aedat4", "evt3", "es", "evt2", "dat"])
def test_a_fresh_read_events_loads_no_module_it_does_not_use(tmp_path, fmt):
    """``import evtk; evtk.read_events(F)`` in a fresh process: no compiler or other format's library, and none of the
    modules a file of this format does not use. Every format's read loaded lz4 (the checksum setting lives beside
    the codecs) and json, numpy.typing, threading and dataclasses (module-level imports); AEDAT4's xml.etree, and
    for its LZ4 packets and data table lz4.frame and threading, for its header the xml package (expat's parser is
    pyexpat, which the plain headers DV and evtk write no longer need); Event Stream's decoder the bisect module
    (its functions are _bisect's)."""
    path = _fixture(tmp_path, fmt)
    names = HEAVY + START_UP
    code = (f"import sys, evtk\nassert len(evtk.read_events({str(path)!r})) == 50_000\n"
            f"print('LOADED', sorted(m for m in {names!r} if m in sys.modules))\n")
    env = dict(os.environ, PYTHONPATH=str(Path(evtk.__file__).parents[1]))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env).stdout
    loaded = set(eval(out.split("LOADED", 1)[1].strip()))  # a list of names printed by the child
    assert loaded <= START_UP_NEEDED.get(fmt, set()), sorted(loaded - START_UP_NEEDED.get(fmt, set()))


@pytest.mark.parametrize("module", ["evtk", "evtk.io", "evtk.events"])
def test_the_lazily_loaded_names_are_listed_and_load(module):
    """The names loaded on first use (module ``__getattr__``) are in ``dir()`` and resolve, as ``from evtk import X``
    does; ``dir(evtk)`` lacked Events, Triggers, Recording and the others."""
    import importlib

    mod = importlib.import_module(module)
    assert set(mod.__all__) <= set(dir(mod)), sorted(set(mod.__all__) - set(dir(mod)))
    for name in mod.__all__:
        assert getattr(mod, name) is not None


@pytest.mark.parametrize("fmt", ["aedat4", "es", "evt3", "csv"])
def test_a_readers_modules_load_with_the_collector_paused_and_it_runs_again_after(tmp_path, fmt, monkeypatch):
    """``evtk.open`` imports the reader of a file's format through ``evtk.io._load``, with the garbage collector
    paused (its collections were about 3 ms of a fresh read of a small file); the collector runs again after, also
    when the import fails, and stays off where the caller had switched it off."""
    import gc
    import importlib

    from evtk import io

    path = _fixture(tmp_path, fmt)
    seen = []
    real = importlib.import_module

    def spy(name, package=None):
        seen.append((name, gc.isenabled()))
        return real(name, package)

    monkeypatch.setattr(importlib, "import_module", spy)
    assert gc.isenabled()
    with evtk.open(path) as rec:
        assert len(rec.events()) == 50_000
    module = {"aedat4": "aedat4", "es": "prophesee", "evt3": "prophesee", "csv": "decoded"}[fmt]
    assert (f"evtk.io.{module}", False) in seen and all(not running for _, running in seen), seen
    assert gc.isenabled()
    with pytest.raises(ModuleNotFoundError):
        io._load("no_such_reader", "Recording")
    assert gc.isenabled()
    gc.disable()
    try:
        assert io._load(module, "__name__") == f"evtk.io.{module}"
        assert not gc.isenabled()
    finally:
        gc.enable()


@pytest.mark.parametrize("fmt", ["es", "evt3"])
def test_evtk_info_loads_no_writer_or_archive_modules(tmp_path, fmt):
    """``evtk info F`` in a fresh process: every command loaded evtk's output guard with hashlib, socket and
    tempfile (13 ms) for a partial-file tag only a write uses, and ``info`` zipfile (with shutil, bz2 and lzma,
    8 ms) to tell a reconstruction NPZ from a recording."""
    path = _fixture(tmp_path, fmt)
    names = ("hashlib", "socket", "tempfile", "zipfile", "shutil", "lzma", "bz2")
    code = ("import sys\nfrom evtk.cli import main\n"
            f"try:\n    main(['info', {str(path)!r}])\nexcept SystemExit as exc:\n    assert not exc.code, exc.code\n"
            f"print('LOADED', sorted(m for m in {names!r} if m in sys.modules))\n")
    env = dict(os.environ, PYTHONPATH=str(Path(evtk.__file__).parents[1]))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env).stdout
    assert eval(out.split("LOADED", 1)[1].strip()) == []  # a list of names printed by the child


@pytest.fixture(scope="module")
def calibrated_job(tmp_path_factory):
    """A small simulated bench run: a calibration run (dots and levels), ``evtk calibrate`` on it, and a job run,
    both as the camera's AEDAT4 copy (no simulation record)."""
    from click.testing import CliRunner

    from evtk.cli import main
    from evtk.patterns import job_simulation

    tmp = tmp_path_factory.mktemp("calibrated")
    base = 'kernels = ["010111010"]\nrepeat = 1\nflat_field = 2\nwindow_us = 1000\nseed = 4\n'
    (tmp / "cal.toml").write_text(base + "calibration = 2\nlevels = 6\n")
    (tmp / "job.toml").write_text(base + "levels = 0\n")
    for name in ("cal", "job"):
        res = CliRunner().invoke(main, ["patterns", str(tmp / f"{name}.toml"), "-o", str(tmp / name)])
        assert res.exit_code == 0, res.output
        job_simulation(tmp / f"{name}.toml").write(tmp / f"{name}_sim.h5")
        with evtk.open(tmp / f"{name}_sim.h5") as rec:
            evtk.write_events(tmp / f"{name}_cam.aedat4", rec.events(), rec.triggers())
    res = CliRunner().invoke(main, ["calibrate", str(tmp / "cal_cam.aedat4"), "--schedule",
                                    str(tmp / "cal" / "schedule.json"), "-o", str(tmp / "c.toml")])
    assert res.exit_code == 0, res.output
    return tmp


# what a calibrated reconstruction of a 16x16 response loads nothing of: numba and its llvmlite (the count, the
# count table, the timing solve run in numpy while numba is not loaded), scipy (the deblur runs dense in numpy up to
# 512 cells), scikit-image, matplotlib, numpy.random (no noise is drawn), and numpy.typing (annotations only; its
# import parses numpy's docstrings, 1 ms of the start).
NOT_FOR_RECONSTRUCT = ("numba", "llvmlite", "scipy", "skimage", "matplotlib", "numpy.random", "numpy.typing")


def test_a_fresh_calibrated_reconstruction_loads_no_compiler_or_scipy(calibrated_job):
    """``evtk reconstruct F --schedule S --calibration C`` in a fresh process: loading the calibration imported
    evtk.calibrate with scipy.ndimage, scipy.optimize and scikit-image (0.65 s), and the ideal response's small
    correlation scipy.signal (0.85 s), of a run whose read takes 0.14 s; then numba's start (0.6 s) and scipy's
    sparse and linear algebra (0.15 s) for the route's kernels and deblur (issue 32)."""
    tmp = calibrated_job
    code = ("import sys\nfrom evtk.cli import main\n"
            f"args = ['reconstruct', {str(tmp / 'job_cam.aedat4')!r}, '--schedule', "
            f"{str(tmp / 'job' / 'schedule.json')!r}, '--calibration', {str(tmp / 'c.toml')!r}, "
            f"'-o', {str(tmp / 'r.npz')!r}]\n"
            "try:\n    main(args)\nexcept SystemExit as exc:\n    assert not exc.code, exc.code\n"
            f"print('LOADED', sorted(m for m in {NOT_FOR_RECONSTRUCT!r} if m in sys.modules))\n")
    env = dict(os.environ, PYTHONPATH=str(Path(evtk.__file__).parents[1]))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env).stdout
    assert eval(out.split("LOADED", 1)[1].strip()) == []  # a list of names printed by the child
    assert evtk.load_reconstruction(tmp / "r.npz").responses.shape[1:] == (16, 16)  # the default --size


def test_the_ideal_response_is_scipys_correlation_to_the_bit():
    """The ideal response sums integer patterns in numpy (scipy.signal costs a process 0.85 s to import): the same
    floats as ``scipy.signal.correlate2d`` / ``convolve2d``, signed and flipped kernels included; real-valued
    patterns still go through scipy."""
    from scipy import signal

    from evtk.optics import Bench, ideal_response

    rng = np.random.default_rng(32)
    flipped = Bench(kernel_flipped=True)
    for _ in range(300):
        k = rng.integers(-4, 5, (rng.integers(1, 8), rng.integers(1, 8))).astype(np.float64)
        f = rng.integers(-3, 4, (rng.integers(1, 24), rng.integers(1, 24))).astype(np.float64)
        assert ideal_response(k, f).tobytes() == signal.correlate2d(f, k, mode="full").tobytes()
        assert ideal_response(k, f, flipped).tobytes() == signal.convolve2d(f, k, mode="full").tobytes()
        real = f + rng.random(f.shape)
        assert ideal_response(k, real).tobytes() == signal.correlate2d(real, k, mode="full").tobytes()


@pytest.mark.parametrize("fmt", ["es", "evt2", "dat"])
def test_a_fresh_read_of_another_prophesee_encoding_loads_no_evt3_decoder(tmp_path, fmt):
    """``evtk.read_events`` of an Event Stream, EVT 2.0 or DAT file in a fresh process: the EVT 3.0 decoder module
    (1.5-5 ms of the start, issue 32) was imported with the Prophesee reader whatever the file's encoding."""
    path = _fixture(tmp_path, fmt)
    code = (f"import sys, evtk\nassert len(evtk.read_events({str(path)!r})) == 50_000\n"
            "print('LOADED', 'evtk.io.prophesee._evt3' in sys.modules)\n")
    env = dict(os.environ, PYTHONPATH=str(Path(evtk.__file__).parents[1]))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env).stdout
    assert out.split("LOADED", 1)[1].strip() == "False"


def _cli_loads(args: list[str], names: tuple[str, ...]) -> list[str]:
    """Which of ``names`` a fresh ``evtk ARGS`` process has loaded when it ends (it must succeed)."""
    code = ("import sys\nfrom evtk.cli import main\n"
            f"try:\n    main({args!r})\nexcept SystemExit as exc:\n    assert not exc.code, exc.code\n"
            f"print('LOADED', sorted(m for m in {names!r} if m in sys.modules))\n")
    env = dict(os.environ, PYTHONPATH=str(Path(evtk.__file__).parents[1]))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env).stdout
    return eval(out.split("LOADED", 1)[1].strip())  # a list of names printed by the child


def test_a_short_option_loads_no_difflib(tmp_path):
    """``evtk reconstruct F ... -o x.npz``: click tried ``-o`` as a long option first, and its miss loaded difflib to
    suggest a near name (2.5-3 ms of a fresh process) before it matched the short one."""
    path = _fixture(tmp_path, "aedat4")
    args = ["reconstruct", str(path), "--window", "period:10000", "-o", str(tmp_path / "x.npz")]
    assert _cli_loads(args, ("difflib",)) == []
    assert (tmp_path / "x.npz").exists()


@pytest.mark.parametrize("command", [["enob", "--window", "period:10000"], ["info"], ["info", "--check"]])
def test_commands_that_write_nothing_load_no_json_or_signal(tmp_path, command):
    """``evtk enob`` and ``evtk info`` without ``--json``: json (the CLI's, the settings' and the reconstruction
    files' module-level imports) and signal (the partial-file guard's) loaded for every command, 1.5-2 ms."""
    path = _fixture(tmp_path, "aedat4")
    assert _cli_loads([command[0], str(path), *command[1:]], ("json", "signal", "difflib")) == []


def test_enob_of_fixed_windows_loads_no_schedule_or_reconstruction_result(tmp_path):
    """``evtk enob F --window period:US`` counts net counts into frames and sums them: the capture schedule's
    module (with the settings it checks against), the scheduled route's entry and its result and summary classes
    loaded with the windows, the block means and the fixed route's module (about 13 ms of imports in a fresh
    process), though a recording without a schedule uses none of them."""
    path = _fixture(tmp_path, "aedat4")
    heavy = ("evtk.plan.schedule", "evtk.settings", "evtk.reconstruct.entry", "evtk.reconstruct.result",
             "evtk.reconstruct.summary")
    assert _cli_loads(["enob", str(path), "--window", "period:10000"], heavy) == []
