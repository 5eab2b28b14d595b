"""Fanning out on Dask: same results as serial, batches with manifests, lost workers, dead schedulers."""

import json
import os

import numpy as np
import pytest
from click.testing import CliRunner

import evtk
from evtk import EvtkError
from evtk.cli import main
from evtk.cluster import run_tasks, scheduler

distributed = pytest.importorskip("distributed")


@pytest.fixture(scope="module")
def client():
    with scheduler("local:2") as c:
        yield c


def _by_value(fn):
    """Ship ``fn`` to the workers by value (they cannot import this test module)."""
    fn.__module__ = "__main__"
    fn.__qualname__ = fn.__name__
    return fn


def test_scheduler_specs():
    with scheduler("serial") as c:
        assert c is None
    for bad in ("cluster", "local:0", "local:x", "udp://x"):
        with pytest.raises(EvtkError, match="scheduler|local:N"):
            with scheduler(bad):
                pass


def test_a_dead_scheduler_address_fails_fast(monkeypatch):
    """A refused address is answered by one socket probe with a bounded time-out, before any Dask client (and
    its own time-out) is made; an address that accepts but never answers gives the client the same bound."""
    import socket

    from evtk import cluster

    probes, clients = [], []
    real_connect = socket.create_connection

    def probe(address, timeout=None, *args, **kwargs):
        probes.append((address, timeout))
        return real_connect(address, timeout, *args, **kwargs)

    def silent_client(address, timeout=None, **kwargs):
        clients.append((address, timeout))
        raise TimeoutError("no handshake")

    monkeypatch.setattr(socket, "create_connection", probe)
    monkeypatch.setattr(distributed, "Client", silent_client)
    with pytest.raises(EvtkError, match="no Dask scheduler at tcp://127.0.0.1:9"):
        with scheduler("tcp://127.0.0.1:9"):
            pass
    assert probes == [(("127.0.0.1", 9), cluster.CONNECT_TIMEOUT_S)] and clients == []
    assert 0 < cluster.CONNECT_TIMEOUT_S <= 10
    with socket.socket() as listener:  # accepts connections (the probe succeeds) but never speaks Dask
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        address = f"tcp://127.0.0.1:{listener.getsockname()[1]}"
        with pytest.raises(EvtkError, match=f"no Dask scheduler answered at {address} within "
                                            f"{cluster.CONNECT_TIMEOUT_S} s"):
            with scheduler(address):
                pass
    assert clients == [(address, f"{cluster.CONNECT_TIMEOUT_S}s")]
    monkeypatch.undo()
    r = CliRunner().invoke(main, ["flips", "--scheduler", "tcp://127.0.0.1:9", "--power-mw", "1"])
    assert r.exit_code == 1 and len(r.output.strip().splitlines()) == 1 and "no Dask scheduler" in r.output


def test_local_workers_share_out_threads_without_touching_this_process(client):
    """Each of the 2 workers decodes (and runs numba's parallel loops) on its share of the threads; this
    process's environment stays as it was (numba refuses to compile once its thread count changes under it)."""
    from evtk.io._compression import workers

    def probe(_):
        import os as _os

        from evtk.io._compression import workers as w

        return _os.environ.get("EVTK_IO_THREADS"), w()

    got = run_tasks(_by_value(probe), range(4), client)
    assert got == [(str(max(1, workers() // 2)), max(1, workers() // 2))] * 4
    before = {k: os.environ.get(k) for k in ("EVTK_IO_THREADS", "NUMBA_NUM_THREADS")}
    with scheduler("local:1") as c1:
        assert run_tasks(_by_value(probe), [0], c1) == [(str(workers()), workers())]
    assert {k: os.environ.get(k) for k in before} == before


def test_local_workers_allocator_settings_and_this_process_environment_left_as_it_was():
    """The workers start with one malloc arena and glibc's own trim threshold (Dask's nanny would set
    MALLOC_TRIM_THRESHOLD_); the nanny applies its pre-spawn environment to this process's os.environ,
    which evtk puts back when the cluster closes. In a fresh interpreter, whose environment has none of them."""
    import subprocess
    import sys

    code = """
import json, os
from evtk.cluster import scheduler
before = dict(os.environ)
with scheduler("local:1") as c:
    workers = list(c.run(lambda: {k: os.environ.get(k) for k in
                                  ("MALLOC_ARENA_MAX", "MALLOC_TRIM_THRESHOLD_", "OMP_NUM_THREADS")}).values())
print(json.dumps({"workers": workers, "same": dict(os.environ) == before,
                  "leaked": sorted(set(os.environ) - set(before))}))
"""
    env = {k: v for k, v in os.environ.items()
           if k not in ("MALLOC_ARENA_MAX", "MALLOC_TRIM_THRESHOLD_", "OMP_NUM_THREADS", "MKL_NUM_THREADS",
                        "OPENBLAS_NUM_THREADS")}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    got = json.loads(r.stdout.strip().splitlines()[-1])
    assert got["workers"] == [{"MALLOC_ARENA_MAX": "1", "MALLOC_TRIM_THRESHOLD_": None, "OMP_NUM_THREADS": "1"}]
    assert got["same"] and got["leaked"] == []


def test_run_tasks_keeps_order_and_survives_a_killed_worker(client, tmp_path):
    square = _by_value(lambda v: v * v)
    assert run_tasks(square, range(20), client) == [v * v for v in range(20)]

    def kill_once(args):
        import os as _os

        marker, value = args
        if value == 3 and not _os.path.exists(marker):
            open(marker, "w").close()
            _os._exit(1)  # the worker dies mid-task, once
        return value * 10

    marker = str(tmp_path / "killed-once")
    got = run_tasks(_by_value(kill_once), [(marker, v) for v in range(6)], client)
    assert got == [0, 10, 20, 30, 40, 50] and os.path.exists(marker)


def test_sweeps_equal_serial_runs(client):
    from evtk.simulate import default_features
    from evtk.sweeps import flip_sweep, random_kernels

    f = np.where(default_features() > 0, 1, -1)
    k = random_kernels(2, seed=1)
    # the same numbers, to the rounding of the deblur's linear algebra (BLAS threads differ between processes)
    assert flip_sweep([0.2, 5.0], k, f, repeats=3, seed=2, client=client) == [
        pytest.approx(row, rel=1e-12) for row in flip_sweep([0.2, 5.0], k, f, repeats=3, seed=2)]
    from evtk.recover import success_rate

    a = success_rate([20.0], size=4, trials=6, seed=3, client=client)
    b = success_rate([20.0], size=4, trials=6, seed=3)
    for ra, rb in zip(a, b):
        for key in ("exact_pct", "shift_pct", "recovered_pct", "proven_pct"):
            assert ra[key] == rb[key]
    from evtk.bcnn import BCNN, DigitalBackend, poisson_robustness
    from evtk.datasets import face_not_face
    from evtk.optimize import train_layerwise

    d = face_not_face()
    m = BCNN.random(seed=0)
    train_layerwise(m, DigitalBackend(), d.x_train, d.y_train, steps=50, seed=0)
    assert (poisson_robustness(m, d.x_test, d.y_test, [0, 0.5, 2], client=client)
            == poisson_robustness(m, d.x_test, d.y_test, [0, 0.5, 2]))


def _recordings(folder, n=3):
    from evtk.simulate import Simulation

    folder.mkdir()
    rng = np.random.default_rng(0)
    for i in range(n):
        Simulation(rng.choice([-1, 1], (3, 3)), rng.choice([-1, 1], (8, 8)), repeat=2, seed=i).write(
            folder / f"run{i}.aedat4")
    (folder / "broken.aedat4").write_bytes(b"#!AER-DAT4.0\r\n garbage")
    return folder


def test_batch_on_a_cluster_equals_serial_and_resumes(tmp_path):
    import h5py

    src = _recordings(tmp_path / "in")
    outs = {}
    for spec in ("serial", "local:2"):
        out = tmp_path / spec.replace(":", "")
        r = CliRunner().invoke(main, ["batch", "reconstruct", str(src), "-o", str(out), "--scheduler", spec,
                                      "--json"])
        assert r.exit_code == 1, r.output  # the broken file fails, the rest completes
        m = json.loads(r.output)
        assert m["counts"] == {"ok": 3, "skipped": 0, "error": 1}
        bad = [e for e in m["inputs"] if e["status"] == "error"]
        assert len(bad) == 1 and "broken" in bad[0]["input"] and bad[0]["error"]
        assert json.loads((out / "batch.json").read_text()) == m
        outs[spec] = out
    for i in range(3):
        with h5py.File(outs["serial"] / f"run{i}.h5") as a, h5py.File(outs["local:2"] / f"run{i}.h5") as b:
            np.testing.assert_array_equal(a["reconstruction/binary"][...], b["reconstruction/binary"][...])
            for name in ("reconstruction/responses", "reconstruction/cells"):  # to the linear algebra's rounding
                np.testing.assert_allclose(a[name][...], b[name][...], rtol=1e-12, atol=1e-12)
        with evtk.open(src / f"run{i}.aedat4") as rec:
            from evtk.workflow import reconstruct_recording

            lib = reconstruct_recording(rec)  # the route evtk reconstruct takes
        with h5py.File(outs["serial"] / f"run{i}.h5") as a:
            np.testing.assert_allclose(a["reconstruction/responses"][...], lib.responses)
    # again: the finished inputs are skipped, the broken one is tried again
    stamp = (outs["serial"] / "run0.h5").stat().st_mtime_ns
    r = CliRunner().invoke(main, ["batch", "reconstruct", str(src), "-o", str(outs["serial"]), "--scheduler",
                                  "serial", "--json"])
    m = json.loads(r.output)
    assert m["counts"] == {"ok": 0, "skipped": 3, "error": 1}
    assert (outs["serial"] / "run0.h5").stat().st_mtime_ns == stamp
    assert all(e["events"] for e in m["inputs"] if e["status"] == "skipped")
    assert not [p for p in outs["serial"].iterdir() if p.name.endswith(".evtk-partial")]
    r = CliRunner().invoke(main, ["batch", "reconstruct", str(tmp_path / "nothing-*.aedat4"), "-o",
                                  str(tmp_path / "x"), "--scheduler", "serial"])
    # an empty glob is reported as such, in the manifest too
    assert r.exit_code == 1 and "matches no file" in r.output


def test_time_split_reconstruction_equals_the_whole(client, tmp_path):
    """Groups of whole windows counted in separate tasks, stitched: exactly the single-process result."""
    from evtk.batch import reconstruct_split
    from evtk.reconstruct import reconstruct
    from evtk.simulate import Simulation

    rng = np.random.default_rng(5)
    path = tmp_path / "long.aedat4"
    Simulation(rng.choice([-1, 1], (3, 3)), rng.choice([-1, 1], (16, 16)), repeat=6, seed=2).write(path)
    with evtk.open(path) as rec:
        whole = reconstruct(rec, size=(8, 8))
        by_period = reconstruct(rec, window=("period", 7000), crop="full")
    for parts, c in ((3, None), (5, client), (1000, None)):
        split = reconstruct_split(str(path), parts, c, size=(8, 8))
        np.testing.assert_array_equal(split.counts.on, whole.counts.on)
        np.testing.assert_array_equal(split.counts.off, whole.counts.off)
        # counts exactly; what the deblur's linear algebra gives, to its rounding (BLAS threads differ by process)
        np.testing.assert_allclose(split.cells, whole.cells, rtol=1e-12, atol=1e-12)
        np.testing.assert_array_equal(split.binary, whole.binary)
        rounded = ("error", "deblur_regularisation")
        assert {k: v for k, v in split.summary.items() if k not in rounded} == {
            k: v for k, v in whole.summary.items() if k not in rounded}
        assert split.summary["error"] == pytest.approx(whole.summary["error"], rel=1e-12)
        assert split.summary["deblur_regularisation"] == pytest.approx(whole.summary["deblur_regularisation"], rel=1e-12)
    split = reconstruct_split(str(path), 4, client, window=("period", 7000), crop="full")
    np.testing.assert_array_equal(split.cells, by_period.cells)
    # through the batch command: a recording over --split-events goes in parts, with the same output
    import h5py

    for extra, out in (([], "a"), (["--split-events", "100000"], "b")):
        r = CliRunner().invoke(main, ["batch", "reconstruct", str(path), "-o", str(tmp_path / out), "--scheduler",
                                      "local:2", "--json", "--oracle", *extra])
        assert r.exit_code == 0, r.output
    m = json.loads((tmp_path / "b" / "batch.json").read_text())
    assert m["inputs"][0]["parts"] > 1 and m["inputs"][0]["status"] == "ok"
    with h5py.File(tmp_path / "a" / "long.h5") as fa, h5py.File(tmp_path / "b" / "long.h5") as fb:
        np.testing.assert_array_equal(fa["reconstruction/on"][...], fb["reconstruction/on"][...])
        for name in ("reconstruction/responses", "reconstruction/cells"):
            np.testing.assert_allclose(fa[name][...], fb[name][...], rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("ext", [".aedat4", ".h5", ".parquet"])
def test_to_dask_reads_lazily_by_time(tmp_path, ext):
    pytest.importorskip("dask.dataframe")
    from conftest import random_events

    ev = random_events(50_000, seed=3, span_us=2_000_000)
    path = tmp_path / f"r{ext}"
    evtk.write_events(path, ev)
    df = evtk.to_dask(path, partitions=7)
    assert df.npartitions == 7 and list(df.columns) == ["t", "x", "y", "p"]
    got = df.compute(scheduler="synchronous")
    np.testing.assert_array_equal(got["t"].to_numpy(), ev.t)
    np.testing.assert_array_equal(got["x"].to_numpy(), ev.x)
    np.testing.assert_array_equal(got["p"].to_numpy(), ev.p)
    assert int(df[df.p == 1].t.count().compute(scheduler="synchronous")) == int(ev.p.sum())
    assert evtk.to_dask(path).npartitions == 1  # 50 000 events: one default partition


def test_local_workers_start_warm():
    """Issue 32 item 4: a worker of evtk's local cluster has loaded what a batch task loads before the first
    task (the reader, the reconstruction, numba and its cached kernels of the schedule route), so no task
    pays for it; the warm-up runs when the worker starts (the cluster's start, reported apart)."""
    import subprocess
    import sys

    code = """
import json, sys
from evtk.cluster import scheduler
with scheduler("local:1") as c:
    got = list(c.run(lambda: sorted(m for m in ("numba", "evtk.reconstruct.accumulate", "evtk.io.aedat4.reader",
                                                "evtk.batch") if m in sys.modules)).values())
print(json.dumps(got))
"""
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=180)
    assert r.returncode == 0, r.stderr[-2000:]
    assert json.loads(r.stdout.strip().splitlines()[-1]) == [
        ["evtk.batch", "evtk.io.aedat4.reader", "evtk.reconstruct.accumulate", "numba"]]
