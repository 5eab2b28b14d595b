"""A writer killed mid-write leaves the previous file intact and a salvageable partial file."""

import os
import signal
import subprocess
import sys
import textwrap

import numpy as np
import pytest

import evtk

from conftest import random_events

WRITER = textwrap.dedent(
    """
    import sys, numpy as np, evtk
    from evtk.io.aedat4 import Aedat4Writer
    rng = np.random.default_rng(0)
    with Aedat4Writer(sys.argv[1], (320, 240), compression="lz4") as w:
        t = 0
        while True:  # write forever; the test kills us
            n = 20000
            ts = t + np.sort(rng.integers(0, 10000, n))
            w.write_events(evtk.Events(ts, rng.integers(0, 320, n), rng.integers(0, 240, n), rng.integers(0, 2, n), (320, 240)))
            t += 10000
            print(t, flush=True)
    """
)


def test_killed_writer_keeps_previous_file(tmp_path):
    path = tmp_path / "rec.aedat4"
    previous = random_events(1000, seed=5)
    evtk.write_events(path, previous)
    before = path.read_bytes()
    for delay_lines in (1, 5):
        proc = subprocess.Popen([sys.executable, "-c", WRITER, str(path)], stdout=subprocess.PIPE, text=True)
        try:
            for _ in range(delay_lines):
                assert proc.stdout.readline()
        finally:
            proc.send_signal(signal.SIGKILL)
            proc.wait()
        assert path.read_bytes() == before
        partials = [p for p in tmp_path.iterdir() if p.name.endswith(".evtk-partial")]
        assert len(partials) == 1
        with evtk.open(partials[0], salvage=True) as rec:
            got = rec.events()
            assert len(got) >= 20000 * delay_lines and len(got) % 1 == 0
            assert got.is_sorted
        os.unlink(partials[0])


ANY_WRITER = textwrap.dedent(
    """
    import sys, numpy as np, evtk
    from evtk.io import open_writer
    rng = np.random.default_rng(0)
    with open_writer(sys.argv[1], (320, 240), "lz4") as w:
        t = 0
        print("open", flush=True)
        while True:  # write forever; the test kills us at a random moment
            n = 20000
            ts = t + np.sort(rng.integers(0, 10000, n))
            w.write_events(evtk.Events(ts, rng.integers(0, 320, n), rng.integers(0, 240, n),
                                       rng.integers(0, 2, n), (320, 240)))
            t += 10000
    """
)


def _expected_prefix(n_chunks):
    import numpy as np

    rng = np.random.default_rng(0)
    parts, t = [], 0
    for _ in range(n_chunks):
        n = 20000
        ts = t + np.sort(rng.integers(0, 10000, n))
        parts.append(evtk.Events(ts, rng.integers(0, 320, n), rng.integers(0, 240, n), rng.integers(0, 2, n),
                                 (320, 240)))
        t += 10000
    return evtk.Events.concatenate(parts, sensor_size=(320, 240))


@pytest.mark.parametrize("ext", [".aedat4", ".h5", ".parquet"])
def test_writer_killed_at_random_moments(tmp_path, ext):
    """SIGKILL at random times, from start-up to deep in the write: the previous file stays byte for byte, no
    half file appears under the final name, and `evtk info --salvage` on the partial file either recovers a
    prefix of what was written or says in one line that nothing is recoverable.

    AEDAT4 partial files are recovered (every complete packet); HDF5 and Parquet keep their metadata (the
    HDF5 object headers, the Parquet footer) in memory until they close, so theirs are not (measured: every
    kill here).
    """
    import random
    import time

    from click.testing import CliRunner

    from evtk.cli import main

    path = tmp_path / f"rec{ext}"
    evtk.write_events(path, random_events(1000, seed=5))
    before = path.read_bytes()
    rnd = random.Random(ext)
    for delay in [0.0] + [rnd.uniform(0.0, 0.6) for _ in range(4)]:
        proc = subprocess.Popen([sys.executable, "-c", ANY_WRITER, str(path)], stdout=subprocess.PIPE, text=True)
        try:
            if delay:
                proc.stdout.readline()  # the writer is open
                time.sleep(delay)
        finally:
            proc.send_signal(signal.SIGKILL)
            proc.wait()
        assert path.read_bytes() == before
        partials = [p for p in tmp_path.iterdir() if p.name.endswith(".evtk-partial")]
        assert len(partials) <= 1
        for p in partials:
            r = CliRunner().invoke(main, ["info", "--salvage", "--json", str(p)])
            if ext == ".aedat4" and delay > 0:  # the header is on disk once the writer is open: salvage reads it
                assert r.exit_code == 0, r.output
            if r.exit_code == 0:
                with evtk.open(p, salvage=True) as rec:
                    got = rec.events()
                expected = _expected_prefix(-(-len(got) // 20000))
                assert np.array_equal(got.t, expected.t[:len(got)]) and np.array_equal(got.x, expected.x[:len(got)])
                assert np.array_equal(got.p, expected.p[:len(got)])
            else:
                assert r.exit_code == 1 and len(r.output.strip().splitlines()) == 1 and "Traceback" not in r.output
            os.unlink(p)
