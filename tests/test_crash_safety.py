"""A writer killed mid-write leaves the previous file intact and a salvageable partial file."""

import os
import signal
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from conftest import random_events

import evtk

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


def _written(n):
    """The first ``n`` events WRITER writes (the same generator, the same draws in the same order)."""
    rng = np.random.default_rng(0)
    parts, t, total = [], 0, 0
    while total < n:
        m = 20000
        ts = t + np.sort(rng.integers(0, 10000, m))
        parts.append(evtk.Events(ts, rng.integers(0, 320, m), rng.integers(0, 240, m), rng.integers(0, 2, m),
                                 (320, 240)))
        t += 10000
        total += m
    return evtk.Events.concatenate(parts)[:n]


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
            proc.stdout.close()
        assert path.read_bytes() == before
        partials = [p for p in tmp_path.iterdir() if p.name.endswith(".evtk-partial")]
        assert len(partials) == 1
        with evtk.open(partials[0], salvage=True) as rec:
            got = rec.events()
            assert len(got) >= 20000 * delay_lines
            # what the partial file gives back is exactly the start of what was written: no event lost,
            # altered or invented before the point where the kill cut the file
            want = _written(len(got))
            for col in ("t", "x", "y", "p"):
                np.testing.assert_array_equal(getattr(got, col), getattr(want, col))
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
            print("wrote", flush=True)
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
    half file appears under the final name, and `evtk info --salvage` on the partial file recovers a prefix of
    what was written: every complete AEDAT4 packet, the HDF5 events of the writer's last flush, the Parquet row
    groups before the torn one (through a rebuilt footer).
    """
    import random
    import time

    from click.testing import CliRunner

    from evtk.cli import main

    path = tmp_path / f"rec{ext}"
    evtk.write_events(path, random_events(1000, seed=5))
    before = path.read_bytes()
    rnd = random.Random(ext)
    recovered = []
    # the last kill comes after the writer has said it finished 8 writes (160,000 events), whatever the clock
    # says: on a loaded machine importing evtk alone can take longer than any fixed delay
    for delay in [0.0] + [rnd.uniform(0.0, 0.6) for _ in range(4)] + ["after 8 writes"]:
        proc = subprocess.Popen([sys.executable, "-c", ANY_WRITER, str(path)], stdout=subprocess.PIPE, text=True)
        try:
            if delay == "after 8 writes":
                lines = [proc.stdout.readline() for _ in range(9)]  # "open", then one line per write
                assert lines[0].strip() == "open" and all(x.strip() == "wrote" for x in lines[1:]), lines
            elif delay:
                proc.stdout.readline()  # the writer is open
                time.sleep(delay)
        finally:
            proc.send_signal(signal.SIGKILL)
            proc.wait()
            proc.stdout.close()
        assert path.read_bytes() == before
        partials = [p for p in tmp_path.iterdir() if p.name.endswith(".evtk-partial")]
        assert len(partials) <= 1
        if delay:
            assert len(partials) == 1
        for p in partials:
            r = CliRunner().invoke(main, ["info", "--salvage", "--json", str(p)])
            if delay:  # what the writer put on disk on opening is enough for salvage to read the file
                assert r.exit_code == 0, r.output
            if r.exit_code == 0:
                with evtk.open(p, salvage=True) as rec:
                    got = rec.events()
                    damaged = rec.damage is not None
                if ext != ".aedat4" or damaged:  # the partial file is recognised as such, and refused without salvage
                    assert damaged
                    with pytest.raises(evtk.FormatError):
                        evtk.open(p).events()
                else:  # an AEDAT4 file cut between packets is a valid file (the data table is optional)
                    assert evtk.read_events(p) == got
                expected = _expected_prefix(-(-len(got) // 20000))
                assert np.array_equal(got.t, expected.t[:len(got)]) and np.array_equal(got.x, expected.x[:len(got)])
                assert np.array_equal(got.y, expected.y[:len(got)]) and np.array_equal(got.p, expected.p[:len(got)])
                recovered.append((delay, len(got)))
            else:
                assert r.exit_code == 1 and len(r.output.strip().splitlines()) == 1 and "Traceback" not in r.output
            os.unlink(p)
    # 8 finished writes of 20,000 events: salvage must find complete ones (an HDF5 chunk of 65,536 is flushed
    # once stored, AEDAT4 packets and Parquet row groups as they are written)
    assert recovered and recovered[-1][0] == "after 8 writes" and recovered[-1][1] >= 20000, recovered


# -- what salvage does with the partial files ---------------------------------------------------------------


def _footer_fields(data):
    """The Parquet footer of a complete file, decoded (field numbers of parquet.thrift)."""
    import struct

    from evtk.io._parquet_footer import read_struct

    n = struct.unpack("<I", data[-8:-4])[0]
    return read_struct(data[-8 - n : -8])[0]


@pytest.mark.parametrize("compression", ["lz4", "zstd", "gzip", "none"])
def test_rebuilt_parquet_footer_matches_pyarrows(tmp_path, compression):
    """The footer rebuilt from the page headers alone describes every column chunk as pyarrow's own footer
    does (type, encodings, codec, value count, sizes, page offsets, t statistics)."""
    from evtk.io._parquet_footer import read_struct, rebuild_footer

    path = tmp_path / "a.parquet"
    ev = random_events(30000, seed=2)
    evtk.write_events(path, ev, row_group_events=4000, compression=compression)
    data = path.read_bytes()
    real = _footer_fields(data)
    end, footer, rows, groups = rebuild_footer(path)
    mine = read_struct(footer[:-8])[0]
    assert (rows, groups) == (real[3], len(real[4])) and rows == 30000 and groups > 1
    footer_len = int.from_bytes(data[-8:-4], "little") + 8
    assert end == len(data) - footer_len  # the row groups end where pyarrow's footer begins
    assert [c[4] for c in mine[2]] == [c[4] for c in real[2]]  # column names, in order
    for rg_mine, rg_real in zip(mine[4], real[4]):
        assert rg_mine[3] == rg_real[3]  # rows
        for c_mine, c_real in zip(rg_mine[1], rg_real[1]):
            m, r = c_mine[3], c_real[3]
            for field in (1, 2, 3, 4, 5, 6, 7, 9, 11):
                assert m.get(field) == r.get(field), (field, m.get(field), r.get(field))
        t_mine, t_real = rg_mine[1][0][3][12], rg_real[1][0][3][12]
        assert (t_mine[5], t_mine[6]) == (t_real[5], t_real[6])  # max and min of t


@pytest.mark.parametrize("nullable", [True, False])
def test_parquet_without_footer_salvages_complete_row_groups(tmp_path, nullable):
    """Cut anywhere: salvage returns exactly the row groups that end before the cut (their offsets from the
    real footer are the oracle), and strict reading refuses the file in one line that says what happened."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    ev = random_events(20000, seed=4)
    path = tmp_path / "a.parquet"
    if nullable:
        evtk.write_events(path, ev, row_group_events=2500)
    else:  # a foreign writer's required columns (no definition levels in the pages), zstd
        schema = pa.schema([pa.field("t", pa.int64(), False), pa.field("x", pa.uint16(), False),
                            pa.field("y", pa.uint16(), False), pa.field("p", pa.uint8(), False)])
        table = pa.Table.from_arrays([pa.array(ev.t), pa.array(ev.x), pa.array(ev.y), pa.array(ev.p)], schema=schema)
        pq.write_table(table, path, row_group_size=2500, compression="zstd")
    data = path.read_bytes()
    md = pq.ParquetFile(path).metadata
    ends, rows = [], [0]
    for g in range(md.num_row_groups):
        col = md.row_group(g).column(md.num_columns - 1)
        start = col.dictionary_page_offset if col.has_dictionary_page else col.data_page_offset
        ends.append(start + col.total_compressed_size)
        rows.append(rows[-1] + md.row_group(g).num_rows)
    assert len(ends) > 4
    cut_path = tmp_path / "cut.parquet"
    rng = np.random.default_rng(1)
    for cut in sorted(set(rng.integers(4, len(data) - 8, 25).tolist()) | {ends[0], ends[0] - 1, ends[3] + 1}):
        cut_path.write_bytes(data[:cut])
        complete = sum(e <= cut for e in ends)
        with evtk.open(cut_path, salvage=True, sensor_size=ev.sensor_size) as rec:
            got = rec.events()
            assert rec.damage is not None and "footer" in rec.damage.reason
        assert got == ev[: rows[complete]], (cut, complete, len(got))
        with pytest.raises(evtk.FormatError, match="without a Parquet footer") as err:
            evtk.open(cut_path)
        assert "\n" not in str(err.value)


def test_interrupted_hdf5_writer_leaves_its_last_flush(tmp_path):
    """A writer that never closes (copy its partial file while it is open) leaves whole chunks on disk,
    flushed after each write: salvage reads them, strict reading refuses the file."""
    import shutil

    from evtk.io.hdf5 import Hdf5Writer

    ev = random_events(50000, seed=6)
    w = Hdf5Writer(tmp_path / "rec.h5", ev.sensor_size, chunk_events=4096)
    copies = []
    try:
        for a in range(0, 30000, 7000):
            part = ev[a : a + 7000]
            t, x = part.t.copy(), part.x.copy()
            w.write_events(evtk.Events(t, x, part.y, part.p, ev.sensor_size))
            t[:] = -1  # the caller reuses its arrays: what was written must not change
            x[:] = 0
            copy = tmp_path / f"copy{a}.h5"
            shutil.copy(w._atomic.tmp_path, copy)
            copies.append((copy, a + 7000))
    finally:
        w.abort()
    for copy, written in copies:
        with pytest.raises(evtk.FormatError, match="never closed"):
            evtk.open(copy)
        with evtk.open(copy, salvage=True) as rec:
            got = rec.events()
            assert "never closed" in rec.damage.reason
        assert len(got) == written // 4096 * 4096  # whole chunks only
        assert got == ev[: len(got)]
    # a writer that closes normally leaves no trace of the marker
    evtk.write_events(tmp_path / "done.h5", ev, chunk_events=4096)
    assert evtk.read_events(tmp_path / "done.h5") == ev


def test_truncated_hdf5_salvages_the_prefix(tmp_path):
    """A truncated copy (shorter than its superblock's end-of-file address) opens with salvage, the missing end
    reading as zeros, and gives back a prefix of the events; strict reading names the truncation."""
    from evtk.io.hdf5 import Hdf5Writer

    ev = random_events(200000, seed=7)
    path = tmp_path / "a.h5"
    with Hdf5Writer(path, ev.sensor_size, chunk_events=8192) as w:
        for a in range(0, len(ev), 16384):  # columns interleaved through the file, as a long recording is
            w.write_events(ev[a : a + 16384])
    data = path.read_bytes()
    cut_path = tmp_path / "cut.h5"
    recovered = []
    for frac in (0.3, 0.6, 0.9, 0.999):
        cut_path.write_bytes(data[: int(len(data) * frac)])
        with pytest.raises(evtk.FormatError, match="truncated"):
            evtk.open(cut_path)
        with evtk.open(cut_path, salvage=True) as rec:
            got = rec.events()
            assert rec.damage is not None and "truncated" in rec.damage.reason
        assert got == ev[: len(got)]
        recovered.append(len(got))
    assert recovered == sorted(recovered) and recovered[0] > 0 and recovered[-1] >= len(ev) * 0.9, recovered


def test_salvaged_recording_left_open_exits_cleanly(tmp_path):
    """h5py reading through a Python file object must be closed before the interpreter shuts down: a
    recording its user never closes is closed at exit (without that, the process dies of SIGSEGV)."""
    ev = random_events(50000, seed=8)
    path = tmp_path / "a.h5"
    evtk.write_events(path, ev, chunk_events=4096)
    data = path.read_bytes()
    (tmp_path / "cut.h5").write_bytes(data[: int(len(data) * 0.9)])
    code = f"import evtk; r = evtk.open({str(tmp_path / 'cut.h5')!r}, salvage=True); print(len(r.events()))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert int(out.stdout) > 0
