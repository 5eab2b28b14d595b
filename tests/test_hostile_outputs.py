"""Hostile inputs for what evtk loads and writes: no code from data files, no decoding past the memory budget,
no output written over an input, no partial file left behind, no batch result lost."""

from __future__ import annotations

import gzip
import io
import os
import pickle
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest

from evtk.errors import EvtkError, FormatError

# -- no code from a pickle ---------------------------------------------------------------------


class _WritesMarker:
    """Unpickling this writes a marker file (what a crafted batch could do with any command)."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


class _RunsShell:
    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def _cifar_dict(rng, n=5):
    return {b"batch_label": b"training batch 1 of 5", b"labels": [int(v) for v in rng.integers(0, 10, n)],
            b"data": (rng.random((n, 3072)) * 255).astype(np.uint8), b"filenames": [b"x.png"] * n}


class _Py2Pickler(pickle._Pickler):
    """Writes bytes as Python 2's str opcodes, as CIFAR-10's own batches (cPickle, protocol 2) hold them."""

    dispatch = dict(pickle._Pickler.dispatch)

    def save_bytes(self, obj):
        n = len(obj)
        head = pickle.SHORT_BINSTRING + bytes([n]) if n < 256 else pickle.BINSTRING + struct.pack("<i", n)
        self.write(head + obj)
        self.memoize(obj)

    dispatch[bytes] = save_bytes


@pytest.mark.parametrize("protocol", [0, 2, 4, 5, "python2"])
def test_cifar_python_batch_reads_without_unpickling(tmp_path, protocol):
    from evtk.datasets import read_cifar_batch

    rng = np.random.default_rng(3)
    d = _cifar_dict(rng)
    path = tmp_path / "data_batch_1"
    if protocol == "python2":
        buf = io.BytesIO()
        _Py2Pickler(buf, 2).dump(d)
        path.write_bytes(buf.getvalue())
    else:
        path.write_bytes(pickle.dumps(d, protocol=protocol))
    grey, labels = read_cifar_batch(path)
    rgb = d[b"data"].reshape(-1, 3, 32, 32) / 255.0
    np.testing.assert_allclose(grey, 0.2125 * rgb[:, 0] + 0.7154 * rgb[:, 1] + 0.0721 * rgb[:, 2])
    assert labels.tolist() == d[b"labels"]


@pytest.mark.parametrize("payload", ["data", "labels", "whole", "key"])
@pytest.mark.parametrize("cls", [_WritesMarker, _RunsShell])
@pytest.mark.parametrize("protocol", [0, 2, 5])
def test_crafted_cifar_pickle_runs_no_code(tmp_path, payload, cls, protocol):
    from evtk.datasets import read_cifar_batch

    marker = tmp_path / "pwned"
    evil = cls(marker)
    d = _cifar_dict(np.random.default_rng(0))
    if payload == "whole":
        d = evil
    elif payload == "key":
        d[(evil,)] = 1
    else:
        d[payload.encode()] = evil
    path = tmp_path / "data_batch_1"
    path.write_bytes(pickle.dumps(d, protocol=protocol))
    with pytest.raises(FormatError, match="does not load|does not read"):
        read_cifar_batch(path)
    assert not marker.exists()


def test_crafted_cifar_batch_through_classify_runs_no_code(tmp_path):
    from click.testing import CliRunner

    from evtk.cli import main

    marker = tmp_path / "pwned"
    data_dir = tmp_path / "data"
    (data_dir / "lfw" / "A").mkdir(parents=True)
    from PIL import Image

    for j in range(3):
        Image.fromarray((np.random.default_rng(j).random((40, 40, 3)) * 255).astype(np.uint8)).save(
            data_dir / "lfw" / "A" / f"A_{j}.jpg")
    (data_dir / "cifar-10-batches-py").mkdir()
    (data_dir / "cifar-10-batches-py" / "data_batch_1").write_bytes(pickle.dumps(_WritesMarker(marker)))
    r = CliRunner().invoke(main, ["classify", "--data-dir", str(data_dir), "--samples", "2", "--runs", "1",
                                  "--backend", "digital", "--steps", "1", "--out", str(tmp_path / "o")])
    assert r.exit_code == 1 and "evtk: error:" in r.output and "does not load" in r.output
    assert not marker.exists()


def test_pickle_walker_refuses_shared_and_cyclic_bombs(tmp_path):
    from evtk._loaders import read_plain_pickle

    # 60 levels of a list holding the previous one twice: 2**60 elements if expanded naively
    a = []
    for _ in range(60):
        a = [a, a]
    path = tmp_path / "shared"
    path.write_bytes(pickle.dumps(a, protocol=2))
    out = read_plain_pickle(path)
    assert out[0] is out[1]
    c = []
    c.append(c)
    path.write_bytes(pickle.dumps(c, protocol=2))
    with pytest.raises(FormatError, match="contains itself"):
        read_plain_pickle(path)
    path.write_bytes(b"\x80\x02]q\x00")  # no STOP
    with pytest.raises(FormatError):
        read_plain_pickle(path)


def test_cifar_binary_version(tmp_path):
    from evtk.datasets import face_not_face, read_cifar_batch

    rng = np.random.default_rng(5)
    labels = rng.integers(0, 10, 7).astype(np.uint8)
    imgs = (rng.random((7, 3072)) * 255).astype(np.uint8)
    path = tmp_path / "cifar-10-batches-bin" / "data_batch_1.bin"
    path.parent.mkdir()
    path.write_bytes(np.hstack([labels[:, None], imgs]).tobytes())
    grey, got = read_cifar_batch(path)
    assert got.tolist() == labels.tolist() and grey.shape == (7, 32, 32)
    rgb = imgs.reshape(-1, 3, 32, 32) / 255.0
    np.testing.assert_allclose(grey, 0.2125 * rgb[:, 0] + 0.7154 * rgb[:, 1] + 0.0721 * rgb[:, 2])
    bad = tmp_path / "short.bin"
    bad.write_bytes(path.read_bytes()[:-1])
    with pytest.raises(FormatError, match="whole number"):
        read_cifar_batch(bad)
    from PIL import Image

    for j in range(3):
        (tmp_path / "lfw" / "P").mkdir(parents=True, exist_ok=True)
        Image.fromarray((rng.random((40, 40, 3)) * 255).astype(np.uint8)).save(tmp_path / "lfw" / "P" / f"{j}.jpg")
    d = face_not_face(data_dir=str(tmp_path), n_per_class=3, test_fraction=0.5)
    assert "CIFAR-10 (3 images)" in d.source


# -- decoding bounded by the budget --------------------------------------------------------------

def _idx(shape, body):
    return bytes([0, 0, 0x08, len(shape)]) + b"".join(int(d).to_bytes(4, "big") for d in shape) + body


def test_gzip_idx_declared_size_checked_before_inflating(tmp_path, monkeypatch):
    from evtk.datasets import read_idx

    monkeypatch.setenv("EVTK_MEMORY_LIMIT_MB", "1")
    path = tmp_path / "big.idx.gz"
    with gzip.open(path, "wb") as fh:  # 8 MB of zeros in a few KB, and a header that declares them
        fh.write(_idx((8, 1000, 1000), bytes(8_000_000)))
    assert path.stat().st_size < 100_000
    with pytest.raises(EvtkError, match="MiB"):
        read_idx(path)


def test_idx_trailing_and_short_data_refused(tmp_path):
    from evtk.datasets import read_idx

    path = tmp_path / "trail.idx.gz"
    with gzip.open(path, "wb") as fh:  # the header declares 4 bytes; 50 MB follow
        fh.write(_idx((2, 2), bytes(50_000_000)))
    with pytest.raises(FormatError, match="follow"):
        read_idx(path)
    (tmp_path / "t.idx").write_bytes(_idx((2, 2), b"\x01\x02\x03\x04\x05"))
    with pytest.raises(FormatError, match="follow"):
        read_idx(tmp_path / "t.idx")
    (tmp_path / "s.idx").write_bytes(_idx((2, 2), b"\x01\x02"))
    with pytest.raises(FormatError, match="truncated"):
        read_idx(tmp_path / "s.idx")


def _png_header_only(width, height):
    """A PNG whose header declares width x height grey pixels, with a few bytes of picture data."""
    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(bytes(1000))) + chunk(b"IEND", b""))


def test_image_dimensions_checked_before_decoding(tmp_path, monkeypatch):
    from evtk._loaders import read_image
    from evtk.simulate import load_patterns

    path = tmp_path / "bomb.png"
    path.write_bytes(_png_header_only(12000, 12000))
    monkeypatch.setenv("EVTK_MEMORY_LIMIT_MB", "64")
    with pytest.raises(EvtkError, match="12000x12000 pixels"):
        read_image(path)
    with pytest.raises(EvtkError, match="12000x12000 pixels"):
        load_patterns(str(path), "features")
    ok = tmp_path / "ok.png"
    from PIL import Image

    Image.fromarray(np.array([[0, 255], [255, 0]], np.uint8)).save(ok)
    assert load_patterns(str(ok), "features").tolist() == [[0, 1], [1, 0]]


def test_npy_declared_size_checked(tmp_path, monkeypatch):
    from evtk._loaders import read_npy

    good = tmp_path / "a.npy"
    np.save(good, np.arange(6).reshape(2, 3))
    assert read_npy(good).tolist() == [[0, 1, 2], [3, 4, 5]]
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": "<i8", "fortran_order": False, "shape": (99999, 99999)})
    (tmp_path / "big.npy").write_bytes(buf.getvalue() + bytes(48))  # 80 GB declared, 48 bytes held
    with pytest.raises(FormatError, match="declares"):
        read_npy(tmp_path / "big.npy")
    np.save(tmp_path / "obj.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(FormatError, match="pickle"):
        read_npy(tmp_path / "obj.npy")


# -- no output over an input ----------------------------------------------------------------------

_INPUT_BYTES = b"precious input bytes, not to be replaced\n"


def _files(tmp_path):
    """Inputs holding bytes that must survive (no command gets far enough to read them)."""
    names = {"REC": "rec.aedat4", "REC2": "rec2.h5", "SCHED": "schedule.json", "CAL": "cal.toml",
             "BENCH": "bench.toml", "NPY": "k.npy", "JOB": "job.toml"}
    paths = {}
    for key, name in names.items():
        p = tmp_path / name
        p.write_bytes(_INPUT_BYTES + name.encode())
        paths[key] = str(p)
    paths["NEW"] = str(tmp_path / "new-output.h5")
    paths["NEWPNG"] = str(tmp_path / "new.png")
    paths["LINK"] = str(tmp_path / "link.png")
    os.symlink(paths["REC"], paths["LINK"])  # another name of the recording
    paths["DOTREC"] = os.path.join(str(tmp_path), ".", "rec.aedat4")
    return paths


# every command and option that writes, given an input (or another output) of the same command as its target
_OVERWRITES = [
    ["calibrate", "REC", "-o", "REC"],
    ["calibrate", "REC", "-o", "NEW", "--png", "REC"],
    ["calibrate", "REC", "--schedule", "SCHED", "-o", "SCHED"],
    ["calibrate", "REC", "--schedule", "SCHED", "-o", "NEW", "--png", "SCHED"],
    ["calibrate", "REC", "-o", "NEW", "--png", "LINK"],
    ["calibrate", "REC", "-o", "NEWPNG", "--png", "NEWPNG"],
    ["reconstruct", "REC", "-o", "REC"],
    ["reconstruct", "REC", "-o", "DOTREC"],
    ["reconstruct", "REC", "-o", "NEW", "--png", "REC"],
    ["reconstruct", "REC", "-o", "NEW", "--schedule", "SCHED", "--png", "SCHED"],
    ["reconstruct", "REC", "-o", "NEW", "--calibration", "CAL", "--png", "CAL"],
    ["reconstruct", "REC", "-o", "SCHED", "--schedule", "SCHED"],
    ["reconstruct", "REC", "-o", "CAL", "--calibration", "CAL"],
    ["reconstruct", "REC", "-o", "NEW", "--png", "NEW"],
    ["enob", "REC", "--plot", "REC"],
    ["enob", "REC", "--plot", "LINK"],
    ["flips", "REC", "--plot", "REC"],
    ["flips", "REC", "REC2", "--plot", "REC2"],
    ["convert", "REC", "REC"],
    ["convert", "REC", "LINK"],
    ["simulate", "-o", "BENCH", "--bench", "BENCH"],
    ["simulate", "-o", "NEW", "--bench", "BENCH", "--save-bench", "BENCH"],
    ["simulate", "-o", "NEW", "--save-bench", "NEW"],
    ["simulate", "-o", "NPY", "--kernel", "NPY"],
    ["simulate", "-o", "JOB", "--job", "JOB"],
    ["recover", "--target-kernel-bits", "010111010", "--features", "NPY", "--plot", "NPY"],
]


@pytest.mark.parametrize("args", _OVERWRITES, ids=[" ".join(a) for a in _OVERWRITES])
def test_no_output_replaces_an_input(tmp_path, args):
    from click.testing import CliRunner

    from evtk.cli import main

    paths = _files(tmp_path)
    before = {k: Path(p).read_bytes() for k, p in paths.items() if os.path.isfile(p)}
    r = CliRunner().invoke(main, [paths.get(a, a) for a in args])
    assert r.exit_code == 1, r.output
    assert r.output.startswith("evtk: error: the output") and "replace" in r.output, r.output
    after = {k: Path(p).read_bytes() for k, p in paths.items() if os.path.isfile(p)}
    assert after == before
    assert not os.path.exists(paths["NEW"]) and not os.path.exists(paths["NEWPNG"])
    assert not [f for f in os.listdir(tmp_path) if f.endswith(".evtk-partial")]


def test_a_file_a_command_writes_under_a_computed_name_replaces_no_input(tmp_path):
    """`evtk patterns` writes schedule.json into its folder: the job file there is not replaced."""
    from click.testing import CliRunner

    from evtk.cli import main

    out = tmp_path / "frames"
    out.mkdir()
    job = out / "schedule.json"
    job.write_text('{"kernels": ["010111010"]}')
    before = job.read_bytes()
    r = CliRunner().invoke(main, ["patterns", str(job), "-o", str(out)])
    assert r.exit_code == 1 and "is the input" in r.output, r.output
    assert job.read_bytes() == before
    assert not [f for f in os.listdir(out) if f.endswith(".evtk-partial")]


def test_guard_refuses_a_second_write_of_one_output(tmp_path):
    from evtk._atomic import AtomicFile, guard_outputs

    a = tmp_path / "a.bin"
    with guard_outputs([str(a)], []):
        with AtomicFile(a) as f:
            f.write(b"first")
        with pytest.raises(EvtkError, match="just written"):
            with AtomicFile(tmp_path / "." / "a.bin") as f:
                f.write(b"second")
    assert a.read_bytes() == b"first"
    with AtomicFile(a) as f:  # outside the command, a file is replaced as ever
        f.write(b"third")
    assert a.read_bytes() == b"third"


# -- no partial file left behind --------------------------------------------------------------------

_WRITER = r"""
import sys, time
import numpy as np
import evtk
from evtk.io import open_writer

w = open_writer(sys.argv[1], (64, 48))
n = 50_000
t = np.arange(n, dtype=np.int64)
w.write_events(evtk.Events(t, t % 64, t % 48, t % 2, (64, 48)))
print("ready", flush=True)
time.sleep(120)
"""


def _start_writer(tmp_path, name):
    import subprocess
    import sys

    script = tmp_path / "writer.py"
    script.write_text(_WRITER)
    env = dict(os.environ, PYTHONPATH=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    proc = subprocess.Popen([sys.executable, str(script), str(tmp_path / name)], stdout=subprocess.PIPE, env=env,
                            cwd=str(tmp_path))
    assert proc.stdout.readline().strip() == b"ready"
    return proc


def _partials(folder):
    return [f for f in os.listdir(folder) if f.endswith(".evtk-partial")]


@pytest.mark.parametrize("name", ["out.aedat4", "out.h5", "out.parquet"])
@pytest.mark.parametrize("sig", ["SIGTERM", "SIGINT"])
def test_interrupted_writer_leaves_no_partial_file(tmp_path, name, sig):
    import signal

    proc = _start_writer(tmp_path, name)
    try:
        assert len(_partials(tmp_path)) == 1  # it is mid-write
        proc.send_signal(getattr(signal, sig))
        rc = proc.wait(timeout=60)
    finally:
        proc.kill()
        proc.stdout.close()
    if sig == "SIGTERM":
        assert rc == -signal.SIGTERM  # it still dies of the signal
    else:
        assert rc != 0
    assert _partials(tmp_path) == [] and not (tmp_path / name).exists()


def test_killed_simulate_leaves_no_partial_file(tmp_path):
    import signal
    import subprocess
    import sys
    import time

    # 3000 repeats: long enough to be killed while writing, within the memory budget (100,000 is now refused)
    env = dict(os.environ, PYTHONPATH=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    proc = subprocess.Popen([sys.executable, "-m", "evtk.cli", "simulate", "--repeat", "3000", "-o", "run.aedat4"],
                            cwd=str(tmp_path), env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 120
        while not _partials(tmp_path) and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.05)
        assert _partials(tmp_path), "simulate never started writing"
        proc.send_signal(signal.SIGTERM)
        rc = proc.wait(timeout=60)
    finally:
        proc.kill()
    assert rc == -signal.SIGTERM
    assert _partials(tmp_path) == [] and not (tmp_path / "run.aedat4").exists()


def test_stale_partial_of_a_dead_process_removed_by_the_next_write(tmp_path):
    import signal

    proc = _start_writer(tmp_path, "out.h5")
    proc.send_signal(signal.SIGKILL)  # no chance to clean up
    proc.wait(timeout=60)
    proc.stdout.close()
    stale = _partials(tmp_path)
    assert len(stale) == 1
    live = _start_writer(tmp_path, "out.h5")  # another writer of the same target, still running
    try:
        theirs = [f for f in _partials(tmp_path) if f not in stale]
        import evtk

        t = np.arange(10, dtype=np.int64)
        evtk.write_events(tmp_path / "out.h5", evtk.Events(t, t, t, t % 2, (64, 48)))
        assert _partials(tmp_path) == theirs  # the dead one's went, the live one's stays
    finally:
        live.kill()
        live.wait()
        live.stdout.close()
    with evtk.open(tmp_path / "out.h5") as rec:
        assert len(rec.events()) == 10


# -- batches: every format, one output per input, no result lost to a concurrent batch -------------------

def _small(path, seed, sensor=(346, 260)):
    """A recording of 3,000 events over 0.3 s in the format of ``path``'s extension."""
    import sys

    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    from conftest import random_events

    ev = random_events(3000, seed=seed, sensor_size=sensor, span_us=300_000)
    ext = os.path.splitext(str(path))[1]
    if ext in (".raw", ".dat", ".es"):
        faery = pytest.importorskip("faery")
        arr = np.zeros(len(ev), faery.EVENTS_DTYPE)
        arr["t"], arr["x"], arr["y"], arr["on"] = ev.t, ev.x, ev.y, ev.p.astype(bool)
        version = {".raw": {"version": "evt3"}, ".dat": {"version": "dat2"}, ".es": {}}[ext]
        faery.events_stream_from_array(arr, tuple(ev.sensor_size)).to_file(str(path), **version)
    elif ext == ".aedat":  # AEDAT 2.0 as jAER writes DAVIS346 events: big-endian, y from the bottom
        head = b"#!AER-DAT2.0\r\n# AEChip: eu.seebetter.ini.chips.davis.DAVIS346B\r\n"
        rec = np.empty(2 * len(ev), ">u4")
        rec[0::2] = ((259 - ev.y.astype(np.uint32)) << 22) | (ev.x.astype(np.uint32) << 12) | \
            (ev.p.astype(np.uint32) << 11)
        rec[1::2] = ev.t.astype(np.uint32)
        path.write_bytes(head + rec.tobytes())
    else:
        import evtk

        evtk.write_events(path, ev)


def test_batch_folder_takes_every_format_evtk_reads_and_names_what_it_leaves_out(tmp_path):
    from click.testing import CliRunner

    from evtk.cli import main

    src = tmp_path / "in"
    src.mkdir()
    names = ["a.aedat4", "b.h5", "c.parquet", "d.raw", "e.dat", "f.es", "g.aedat"]
    for k, name in enumerate(names):
        _small(src / name, k)
    _small(src / "h.aedat4", 9)
    os.rename(src / "h.aedat4", src / "h-recording")  # no extension: found by its first bytes
    (src / "notes.txt").write_text("what was recorded\n")
    (src / "scope.dat").write_bytes(b"\x00\x01 an oscilloscope trace, not a Prophesee file")
    out = tmp_path / "out"
    r = CliRunner().invoke(main, ["batch", "reconstruct", str(src), "-o", str(out), "--window", "period:50000",
                                  "--size", "4x4", "--scheduler", "serial"])
    assert r.exit_code == 0, r.output
    manifest = __import__("json").loads((out / "batch.json").read_text())
    got = {os.path.basename(e["input"]): e["status"] for e in manifest["inputs"]}
    assert got == {n: "ok" for n in names + ["h-recording"]}
    assert [os.path.basename(e["file"]) for e in manifest["left_out"]] == ["notes.txt", "scope.dat"]
    assert "notes.txt" in r.output and "scope.dat" in r.output and "left out" in r.output


def test_batch_inputs_of_one_name_get_outputs_of_their_own(tmp_path):
    from evtk.batch import batch_reconstruct

    a, b = tmp_path / "a" / "x", tmp_path / "b" / "x"  # the same folder name too
    a.mkdir(parents=True)
    b.mkdir(parents=True)
    for k, p in enumerate([a / "rec.h5", b / "rec.h5", a / "rec.aedat4"]):
        _small(p, k)
    out = tmp_path / "out"
    m = batch_reconstruct([a / "rec.h5", b / "rec.h5", a / "rec.aedat4"], out,
                          {"window": ("period", 50_000), "size": (4, 4)})
    outs = [e["output"] for e in m["inputs"]]
    assert [e["status"] for e in m["inputs"]] == ["ok"] * 3 and len(set(outs)) == 3
    from evtk.reconstruct import load_reconstruction

    for e in m["inputs"]:
        assert len(load_reconstruction(e["output"]).cells) >= 5  # 0.3 s in 50 ms windows


@pytest.mark.parametrize("force", [False, True])
def test_concurrent_batch_result_is_reported_not_lost(tmp_path, monkeypatch, force):
    """Batch B reconstructs b/one.h5 while batch A writes a/one.h5's result under the same name: B reports it
    and A's result stays (before, both said ok and A's result was replaced)."""
    import json

    import evtk.workflow
    from evtk import batch as evbatch
    from evtk.batch import batch_reconstruct

    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    _small(tmp_path / "a" / "one.h5", 1)
    _small(tmp_path / "b" / "one.h5", 2)
    out = tmp_path / "out"
    opts = {"window": ("period", 50_000), "size": (4, 4)}
    if force:
        batch_reconstruct([tmp_path / "a" / "one.h5"], out, opts)
    real = evtk.workflow.reconstruct_recording
    state = {}

    def meanwhile(rec, **kw):  # while B computes, A runs to the end
        result = real(rec, **kw)
        if rec.path.endswith(os.path.join("b", "one.h5")) and "a" not in state:
            monkeypatch.setattr(evbatch, "reconstruct_recording", real)
            state["a"] = batch_reconstruct([tmp_path / "a" / "one.h5"], out, opts, force=True)
            state["a_bytes"] = (out / "one.h5").read_bytes()
        return result

    monkeypatch.setattr(evbatch, "reconstruct_recording", meanwhile)
    m = batch_reconstruct([tmp_path / "b" / "one.h5"], out, opts, force=force)
    assert state["a"]["inputs"][0]["status"] == "ok"
    assert m["inputs"][0]["status"] == "error" and "another process" in m["inputs"][0]["error"]
    assert (out / "one.h5").read_bytes() == state["a_bytes"]
    manifest = json.loads((out / "batch.json").read_text())
    assert sorted(e["status"] for e in manifest["inputs"]) == ["error", "ok"]
    assert not [f for f in os.listdir(out) if f.endswith(".evtk-partial")]


def test_contact_sheet_page_replaces_no_other_output(tmp_path):
    """A contact sheet's second page is named after the first (`<stem>-p2`): it may not replace `-o`."""
    from click.testing import CliRunner

    from evtk.cli import main

    rec = tmp_path / "rec.aedat4"
    r = CliRunner().invoke(main, ["simulate", "--repeat", "10", "-o", str(rec)])
    assert r.exit_code == 0, r.output
    out = tmp_path / "sheet-p2.npz"
    r = CliRunner().invoke(main, ["reconstruct", str(rec), "-o", str(out), "--png", str(tmp_path / "sheet.npz"),
                                  "--oracle"])
    assert r.exit_code == 1 and "just written" in r.output, r.output
    from evtk.reconstruct import load_reconstruction

    assert len(load_reconstruction(out).cells) >= 10  # still the reconstruction, not a picture of it
