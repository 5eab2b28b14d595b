"""A writer killed mid-write leaves the previous file intact and a salvageable partial file."""

import os
import signal
import subprocess
import sys
import textwrap

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
