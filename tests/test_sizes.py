"""Sensor sizes as the vendors' tools find them (issue 33): Prophesee system IDs, DAT files sized from their events,
the jAER chip from the addresses' bits, and the overrides every reading command takes (--sensor-size, --layout)."""

import numpy as np
import pytest
from click.testing import CliRunner
from conftest import random_events

import evtk
from evtk.cli import main
from evtk.errors import EvtkError, FormatError
from evtk.io.prophesee.sensors import SYSTEM_IDS


def _old_header_raw(path, ev, system_id):
    """An EVT 2.0 file with a header as Metavision 1.x wrote it: a system ID and no geometry."""
    evtk.write_events(path, ev, fmt="evt2")
    data = path.read_bytes()
    body = data[data.index(b"% end\n") + len(b"% end\n"):]
    path.write_bytes(f"% Date 2020-09-14 09:03:25\n% integrator_name Prophesee\n% system_ID {system_id}\n"
                     "% evt 2.0\n".encode() + body)


@pytest.mark.parametrize("system_id,size", [(21, (640, 480)), (48, (1280, 720)), ("0x40", (320, 320))])
def test_a_header_with_only_a_system_id_is_sized_as_prophesee_s_reader_does(system_id, size, tmp_path):
    ev = random_events(500, seed=1, sensor_size=size)
    path = tmp_path / "old.raw"
    _old_header_raw(path, ev, system_id)
    with evtk.open(path) as rec:
        assert rec.sensor_size == size and rec.events() == ev
        assert "system ID" in rec.metadata["sensor_size_from"]


def test_an_unknown_system_id_is_refused_naming_the_option(tmp_path):
    ev = random_events(50, seed=2, sensor_size=(640, 480))
    path = tmp_path / "old.raw"
    _old_header_raw(path, ev, 7)
    assert 7 not in SYSTEM_IDS
    with pytest.raises(FormatError, match="--sensor-size"):
        evtk.open(path)
    res = CliRunner().invoke(main, ["--sensor-size", "640x480", "info", str(path), "--json"])
    assert res.exit_code == 0, res.output and '"sensor_size": [640, 480]' in res.output


def test_a_dat_file_without_a_size_is_sized_from_its_events_with_a_warning(tmp_path):
    ev = random_events(400, seed=3, sensor_size=(120, 100))
    path = tmp_path / "ncars.dat"
    evtk.write_events(path, ev)
    data = path.read_bytes()
    cut = data.index(b"% Height")
    rest = data[data.index(b"% Width"):]
    path.write_bytes(data[:cut] + rest[rest.index(b"\n") + 1:])  # neither Height nor Width
    with evtk.open(path) as rec:
        assert rec.sensor_size == (int(ev.x.max()) + 1, int(ev.y.max()) + 1)
        assert rec.events() == evtk.Events(ev.t, ev.x, ev.y, ev.p, rec.sensor_size)
        assert any("smallest" in w for w in rec.warnings)
    with evtk.open(path, sensor_size=(120, 100)) as rec:
        assert rec.sensor_size == (120, 100) and not rec.warnings


def _aedat2(path, addr, t, header="#!AER-DAT2.0\r\n# This is a raw AE data file\r\n"):
    rec = np.empty((len(addr), 2), ">u4")
    rec[:, 0], rec[:, 1] = addr, t
    path.write_bytes(header.encode() + rec.tobytes())


def test_a_jaer_file_naming_no_camera_is_read_by_its_address_bits(tmp_path):
    """DVS128 addresses (x in bits 1-7 mirrored, y in 8-14, OFF in bit 0) in a file that names no AEChip: read as
    a 128x128 DVS128, as jAER's DVS128 extractor would, not as an 8x1 DAVIS."""
    rng = np.random.default_rng(4)
    n = 3000
    x, y, off = rng.integers(0, 128, n), rng.integers(0, 128, n), rng.integers(0, 2, n)
    addr = ((127 - x) << 1) | (y << 8) | off
    t = np.sort(rng.integers(0, 1_000_000, n))
    path = tmp_path / "box.aedat"
    _aedat2(path, addr, t)
    with evtk.open(path) as rec:
        got = rec.events()
        assert rec.sensor_size == (128, 128) and rec.metadata["chip"] == "dvs128"
        assert any("DVS128" in w for w in rec.warnings)
    assert np.array_equal(got.x, x) and np.array_equal(got.y, 127 - y) and np.array_equal(got.p, 1 - off)


def test_a_layout_that_gives_a_degenerate_sensor_is_an_error_not_a_warning(tmp_path):
    rng = np.random.default_rng(5)
    n = 500
    addr = ((127 - rng.integers(0, 128, n)) << 1) | (rng.integers(0, 128, n) << 8)
    path = tmp_path / "box.aedat"
    _aedat2(path, addr, np.arange(n) * 10)
    with pytest.raises(FormatError, match="--layout"):
        evtk.open(path, layout="davis")
    res = CliRunner().invoke(main, ["--layout", "davis", "info", str(path)])
    assert res.exit_code == 1 and "no camera has such a sensor" in res.output
    res = CliRunner().invoke(main, ["--layout", "dvs128", "info", str(path)])
    assert res.exit_code == 0 and "128x128" in res.output


def test_bad_overrides_are_clear_errors(tmp_path):
    path = tmp_path / "a.aedat"
    _aedat2(path, np.array([2, 4]), np.array([1, 2]))
    with pytest.raises(EvtkError, match="layout"):
        evtk.open(path, layout="atis")
    res = CliRunner().invoke(main, ["--sensor-size", "big", "info", str(path)])
    assert res.exit_code == 1 and "WIDTHxHEIGHT" in res.output
