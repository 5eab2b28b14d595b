"""Trigger channel ids (EVT 3.0's, Triggers.channel) through evtk's HDF5 and Parquet layouts and `evtk convert`."""

import json

import h5py
import numpy as np
import pyarrow.parquet as pq
import pytest
from click.testing import CliRunner
from conftest import random_events

import evtk
from evtk.cli import main
from evtk.errors import FormatError


def _recording(n_triggers=64, seed=7):
    """Events over 2 s and triggers on every channel 0-15, in time order."""
    ev = random_events(5_000, seed=seed, sensor_size=(640, 480), t0=1_000, span_us=2_000_000)
    rng = np.random.default_rng(seed)
    t = np.sort(rng.choice(np.arange(1_000, 2_001_000), n_triggers, replace=False))
    channel = np.arange(n_triggers) % 16
    rng.shuffle(channel)
    return ev, evtk.Triggers(t, rng.choice([1, 2], n_triggers), channel)


@pytest.mark.parametrize("ext", [".h5", ".parquet"])
def test_channels_0_to_15_round_trip(tmp_path, ext):
    ev, tr = _recording()
    path = tmp_path / f"r{ext}"
    evtk.write_events(path, ev, tr)
    with evtk.open(path) as rec:
        got = rec.triggers()
        assert got == tr and got.channels == list(range(16))
        assert rec.triggers().of_channel(9) == tr.of_channel(9)


@pytest.mark.parametrize("ext", [".h5", ".parquet"])
def test_convert_from_evt3_keeps_the_channels(tmp_path, ext):
    ev, tr = _recording(seed=11)
    src = tmp_path / "src.raw"
    evtk.write_events(src, ev, tr)
    with evtk.open(src) as rec:
        assert rec.triggers() == tr  # the source holds them
    dst = tmp_path / f"dst{ext}"
    res = CliRunner().invoke(main, ["convert", str(src), str(dst)])
    assert res.exit_code == 0, res.output
    assert "warning" not in res.output
    with evtk.open(dst) as rec:
        assert rec.triggers() == tr


def test_files_without_the_column_read_channel_0_and_with_it_their_channels(tmp_path):
    """HDF5 and Parquet files as evtk wrote them before channels were kept (/triggers/t and kind only, a JSON
    of t and kind only) read channel 0; the same files with the column added by hand read its channels."""
    ev, _ = _recording()
    h5 = tmp_path / "old.h5"
    evtk.write_events(h5, ev)
    with h5py.File(h5, "a") as f:
        g = f.create_group("triggers")
        g.create_dataset("t", data=np.array([5, 9, 30], np.int64))
        g.create_dataset("kind", data=np.array([1, 2, 1], np.uint8))
    pqt = tmp_path / "old.parquet"
    evtk.write_events(pqt, ev)
    table = pq.read_table(pqt)
    meta = dict(table.schema.metadata)
    meta[b"evtk.triggers"] = json.dumps({"t": [5, 9, 30], "kind": [1, 2, 1]}).encode()
    pq.write_table(table.replace_schema_metadata(meta), pqt)
    for path in (h5, pqt):
        with evtk.open(path) as rec:
            got = rec.triggers()
            assert got == evtk.Triggers([5, 9, 30], [1, 2, 1], [0, 0, 0]), path
            assert got.channel.dtype == np.uint8
    with h5py.File(h5, "a") as f:
        f["triggers"].create_dataset("channel", data=np.array([4, 0, 15], np.uint8))
    meta[b"evtk.triggers"] = json.dumps({"t": [5, 9, 30], "kind": [1, 2, 1], "channel": [4, 0, 15]}).encode()
    pq.write_table(table.replace_schema_metadata(meta), pqt)
    for path in (h5, pqt):
        with evtk.open(path) as rec:
            assert rec.triggers() == evtk.Triggers([5, 9, 30], [1, 2, 1], [4, 0, 15]), path


def test_the_column_is_written_only_when_a_channel_is_not_0(tmp_path):
    """Files of channel 0 only stay as evtk wrote them before (older readers see nothing new)."""
    ev, _ = _recording()
    for channel, keys in (([0, 0], ["kind", "t"]), ([0, 7], ["channel", "kind", "t"])):
        tr = evtk.Triggers([5, 9], [1, 2], channel)
        evtk.write_events(tmp_path / "a.h5", ev, tr)
        with h5py.File(tmp_path / "a.h5") as f:
            assert sorted(f["triggers"]) == keys
        evtk.write_events(tmp_path / "a.parquet", ev, tr)
        d = json.loads(pq.read_schema(tmp_path / "a.parquet").metadata[b"evtk.triggers"])
        assert sorted(d) == keys


def test_a_damaged_channel_column_is_a_format_error(tmp_path):
    ev, tr = _recording()
    path = tmp_path / "bad.h5"
    evtk.write_events(path, ev, tr)
    with h5py.File(path, "a") as f:
        del f["triggers/channel"]
        f["triggers"].create_dataset("channel", data=np.arange(3, dtype=np.uint8))
    with evtk.open(path) as rec, pytest.raises(FormatError, match="/triggers/channel"):
        rec.triggers()
    with h5py.File(path, "a") as f:
        del f["triggers/channel"]
        f["triggers"].create_dataset("channel", data=np.full(len(tr), 300, np.int16))
    with evtk.open(path) as rec, pytest.raises(FormatError, match="channel"):
        rec.triggers()


def test_convert_to_aedat4_warns_once_naming_the_channels(tmp_path):
    ev, tr = _recording(n_triggers=12, seed=3)
    tr = evtk.Triggers(tr.t, tr.kind, np.array([0, 3, 3, 0, 12, 3, 0, 0, 12, 3, 0, 0]))
    src = tmp_path / "src.raw"
    evtk.write_events(src, ev, tr)
    dst = tmp_path / "dst.aedat4"
    res = CliRunner().invoke(main, ["convert", str(src), str(dst)])
    assert res.exit_code == 0, res.output
    warnings = [line for line in res.output.splitlines() if "warning" in line]
    assert len(warnings) == 1 and "channel(s) 3, 12 " in warnings[0], res.output
    with evtk.open(dst) as rec:  # the edges are all there, on channel 0
        assert rec.triggers() == evtk.Triggers(tr.t, tr.kind)
    # channel 0 only: nothing to warn about
    evtk.write_events(src, ev, evtk.Triggers(tr.t, tr.kind))
    res = CliRunner().invoke(main, ["convert", str(src), str(tmp_path / "b.aedat4")])
    assert res.exit_code == 0 and "warning" not in res.output, res.output
