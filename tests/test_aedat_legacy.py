"""AEDAT 2.0 (jAER) and 3.1 (cAER) polarity events (issue 20), against iniVation's legacy reader (dv)."""

import struct

import numpy as np
import pytest
from click.testing import CliRunner
from conftest import no_hang, random_events

import evtk

dv = pytest.importorskip("dv")


def write_aedat31(path, ev, packet=1000, other=True):
    """AEDAT 3.1 as cAER writes it: header, polarity packets (and a frame packet to be left out)."""
    out = bytearray(b"#!AER-DAT3.1\r\n#Format: RAW\r\n#Source 1: DAVIS346\r\n#!END-HEADER\r\n")
    # a packet never spans a change of the overflow counter (cAER starts a new one)
    cuts = sorted(set(range(0, len(ev), packet)) | set(np.flatnonzero(np.diff(ev.t >> 31)) + 1))
    for a, b in zip(cuts, cuts[1:] + [len(ev)]):
        packet = b - a
        t = ev.t[a:a + packet]
        n = len(t)
        overflow = int(t[0]) >> 31
        d = (ev.x[a:a + packet].astype(np.uint32) << 17) | (ev.y[a:a + packet].astype(np.uint32) << 2) | \
            (ev.p[a:a + packet].astype(np.uint32) << 1) | 1
        body = np.empty(2 * n, "<u4")
        body[0::2], body[1::2] = d, (t & 0x7FFFFFFF).astype(np.uint32)
        out += struct.pack("<hhiiiiii", 1, 1, 8, 4, overflow, n, n, n) + body.tobytes()
        if other and a == 0:  # a frame packet of one 4-byte "event": listed, left out
            out += struct.pack("<hhiiiiii", 2, 1, 4, 0, 0, 1, 1, 1) + bytes(4)
    path.write_bytes(bytes(out))


def write_aedat2_davis(path, ev, height, aps_every=0):
    """AEDAT 2.0 as jAER writes DAVIS events: big-endian address and time stamp; y from the bottom row."""
    out = bytearray(b"#!AER-DAT2.0\r\n# This is a raw AE data file - do not edit\r\n"
                    b"# AEChip: eu.seebetter.ini.chips.davis.DAVIS346B\r\n")
    yraw = (height - 1 - ev.y.astype(np.uint32))
    addr = (yraw << 22) | (ev.x.astype(np.uint32) << 12) | (ev.p.astype(np.uint32) << 11)
    rec = np.empty(2 * len(ev), ">u4")
    rec[0::2], rec[1::2] = addr, (ev.t & 0xFFFFFFFF).astype(np.uint32)
    if aps_every:  # APS samples (bit 31) in between: left out
        aps = np.empty(2, ">u4")
        aps[0], aps[1] = (1 << 31) | 5, rec[1]
        rec = np.concatenate([aps, rec]).astype(">u4")
    path.write_bytes(bytes(out) + rec.tobytes())


def _dv_read(path):
    with dv.LegacyAedatFile(str(path)) as f:
        rows = [(e.timestamp, e.x, e.y, e.polarity) for e in f]
    return np.array(rows, np.int64).reshape(-1, 4)


def test_aedat31_equals_dv_and_the_events_written(tmp_path):
    ev = random_events(20_000, seed=7, sensor_size=(346, 260), span_us=2_000_000)
    path = tmp_path / "r.aedat"
    write_aedat31(path, ev)
    with evtk.open(path) as rec:
        got = rec.events()
        assert rec.sensor_size == (346, 260) and rec.info()["left_out"] == {"frame": 1}
    assert got == ev
    ref = _dv_read(path)
    assert np.array_equal(ref[:, 0], got.t) and np.array_equal(ref[:, 1], got.x)
    assert np.array_equal(ref[:, 2], got.y) and np.array_equal(ref[:, 3], got.p)


def test_aedat31_time_beyond_31_bits_uses_the_overflow_counter(tmp_path):
    ev = random_events(3000, seed=8, sensor_size=(346, 260), t0=(1 << 31) - 500_000, span_us=1_000_000)
    path = tmp_path / "o.aedat"
    write_aedat31(path, ev, packet=100, other=False)
    assert evtk.read_events(path) == ev


def test_aedat2_davis_equals_dv_with_y_from_the_top(tmp_path):
    ev = random_events(20_000, seed=9, sensor_size=(346, 260), span_us=2_000_000)
    path = tmp_path / "r2.aedat"
    write_aedat2_davis(path, ev, 260, aps_every=1)
    with evtk.open(path) as rec:
        got = rec.events()
        assert rec.sensor_size == (346, 260) and rec.metadata["chip"] == "davis346"
        assert rec.info()["left_out"] == {"aps/imu samples": 1}
    assert got == ev
    ref = _dv_read(path)  # dv keeps jAER's rows, counted from the bottom
    assert np.array_equal(ref[:, 0], got.t) and np.array_equal(ref[:, 1], got.x)
    assert np.array_equal(259 - ref[:, 2], got.y) and np.array_equal(ref[:, 3], got.p)


def test_aedat2_windows_streaming_wraps_and_damage(tmp_path, monkeypatch):
    from evtk.io import aedat_legacy

    monkeypatch.setattr(aedat_legacy, "BLOCK_RECORDS", 1000)
    ev = random_events(10_000, seed=10, sensor_size=(346, 260), t0=(1 << 32) - 400_000, span_us=1_000_000)
    path = tmp_path / "w.aedat"
    write_aedat2_davis(path, ev, 260)
    with evtk.open(path) as rec:
        whole = rec.events()
        assert whole == ev  # the 32-bit stamps wrapped inside the file and were unwrapped
        for lo, hi in [(0, 1), (int(ev.t[1234]), int(ev.t[5678])), (int(ev.t[-1]), 2**62)]:
            assert rec.events(lo, hi) == ev.between(lo, hi)
        assert evtk.Events.concatenate(list(rec.iter_events(chunk_events=999))) == ev
    data = path.read_bytes()
    path.write_bytes(data[:-3])
    with pytest.raises(evtk.FormatError, match="ends inside a record"):
        evtk.open(path)
    with evtk.open(path, salvage=True) as rec:
        assert rec.events() == ev[:-1]


def test_unknown_version_and_damaged_packet_are_one_error(tmp_path):
    path = tmp_path / "v.aedat"
    path.write_bytes(b"#!AER-DAT9.1\r\n")
    with pytest.raises(evtk.FormatError, match="version 9.1 is not read"):
        evtk.open(path)
    ev = random_events(500, seed=1, sensor_size=(346, 260))
    write_aedat31(path, ev, packet=100, other=False)
    data = bytearray(path.read_bytes())
    head = data.index(b"#!END-HEADER\r\n") + 14
    struct.pack_into("<i", data, head + 28 + 800 + 16, 10**9)  # the second packet's capacity
    path.write_bytes(bytes(data))
    with pytest.raises(evtk.FormatError, match="claims"):
        evtk.open(path)
    with evtk.open(path, salvage=True) as rec:
        assert rec.events() == ev[:100]


def _stamp_at(path, k):
    """Byte offset of record ``k``'s time stamp in an AEDAT 2.0 file written without APS samples."""
    data = path.read_bytes()
    return data.index(b"DAVIS346B\r\n") + 11 + 8 * k + 4


def test_aedat2_step_back_is_an_error_not_a_wrap(tmp_path):
    """A stamp that goes back 1 ms (or from 3e9 to 2e9 us) is no 32-bit wrap: the old reader took every step
    back for one and added 4295 s to every later event, and `info --check` passed."""
    from evtk.cli import main

    ev = random_events(2000, seed=11, sensor_size=(346, 260), t0=1_000_000, span_us=1_000_000)
    for base, back in [(0, 1000), (3_000_000_000, 1_000_000_000)]:
        shifted = evtk.Events(ev.t + base, ev.x, ev.y, ev.p, ev.sensor_size)
        path = tmp_path / f"b{base}.aedat"
        write_aedat2_davis(path, shifted, 260)
        at = _stamp_at(path, 1500)
        data = bytearray(path.read_bytes())
        struct.pack_into(">I", data, at, int(shifted.t[1499]) - back)
        path.write_bytes(bytes(data))
        with pytest.raises(evtk.FormatError, match=f"at byte {at}: the time stamp steps back"):
            evtk.read_events(path)
        with evtk.open(path, salvage=True) as rec:
            assert rec.events() == shifted[:1500]
            assert rec.damage.offset == at
        result = CliRunner().invoke(main, ["info", "--check", str(path)])
        assert result.exit_code != 0 and "steps back" in result.output


def test_aedat2_wrap_from_top_to_bottom_half_is_unwrapped(tmp_path):
    """A wrap is a step from near 2**32 to near 0: the later events get 2**32 us added, in every read."""
    ev = random_events(3000, seed=12, sensor_size=(346, 260), t0=(1 << 32) - 1_000, span_us=3_000)
    assert ev.t[0] < 1 << 32 < ev.t[-1]
    path = tmp_path / "w.aedat"
    write_aedat2_davis(path, ev, 260)
    with evtk.open(path) as rec:
        assert rec.events() == ev
        lo, hi = int(ev.t[100]), int(ev.t[2900])
        assert rec.events(lo, hi) == ev.between(lo, hi)


def test_aedat2_time_past_int64_stops_the_read_at_its_stamp(tmp_path, monkeypatch):
    """2**31 wraps (32 GiB of records at the least) take the time past 2**63 - 1 µs: the read stops at the stamp
    whose wrap does, naming its byte, and salvage keeps the events before it (numpy wrapped to negative times).
    The reader starts one wrap short of the limit."""
    from evtk.io import aedat_legacy

    most = (2**63 - 1) >> 32
    monkeypatch.setattr(aedat_legacy.LegacyAedatRecording, "_TIME_START", (most, -1))
    ev = random_events(3000, seed=12, sensor_size=(346, 260), t0=(1 << 32) - 1_000, span_us=3_000)
    k = int(np.argmax(ev.t >= 1 << 32))
    assert 0 < k < len(ev)
    path = tmp_path / "w.aedat"
    write_aedat2_davis(path, ev, 260)
    at = _stamp_at(path, k)
    with pytest.raises(evtk.FormatError, match=rf"at byte {at}: the time passes 2\*\*63 - 1 us"):
        evtk.read_events(path)
    with evtk.open(path, salvage=True) as rec:
        got = rec.events()
        assert got.t.tolist() == [(most << 32) + int(t) for t in ev.t[:k]] and got.x.tolist() == ev.x[:k].tolist()
        assert rec.damage.offset == at
    with evtk.open(path, salvage=True) as rec:  # the windowed path: its index, then a window
        lo, hi = (most << 32) + int(ev.t[100]), (most << 32) + int(ev.t[k - 100])
        assert rec.events(lo, hi) == got.between(lo, hi)


def test_aedat31_negative_overflow_counter_is_refused(tmp_path):
    ev = random_events(500, seed=13, sensor_size=(346, 260))
    path = tmp_path / "n.aedat"
    write_aedat31(path, ev, packet=100, other=False)
    data = bytearray(path.read_bytes())
    at = data.index(b"#!END-HEADER\r\n") + 14 + 28 + 800 + 12  # the second packet's overflow counter
    struct.pack_into("<i", data, at, -1)
    path.write_bytes(bytes(data))
    with pytest.raises(evtk.FormatError, match=f"at byte {at}: .*negative time-stamp overflow"):
        evtk.read_events(path)
    with evtk.open(path, salvage=True) as rec:
        got = rec.events()
    assert got == ev[:100] and got.t.min() >= 0


def _long_header(path, n_bytes, line=b"# dvsSizeX 240\r\n"):
    path.write_bytes(b"#!AER-DAT2.0\r\n# AEChip: eu.seebetter.ini.chips.davis.DAVIS240C\r\n"
                     + line * (n_bytes // len(line)) + struct.pack(">II", 5 << 12, 7))


def test_long_headers_parse_or_are_refused_in_linear_time(tmp_path):
    """A header of many 'dvsSizeX' lines and no 'dvsSizeY' took the old reader's regular expression
    quadratic time: 22-40 s for 257 KB, minutes for 1 MiB and more. The guard stops a hang; it is no
    speed assertion."""
    path = tmp_path / "h.aedat"
    _long_header(path, 3 << 20)  # under the 4 MiB limit: read
    with no_hang(10):
        with evtk.open(path) as rec:
            assert rec.sensor_size == (240, 180) and len(rec.events()) == 1
    _long_header(path, 16 << 20)
    with no_hang(10), pytest.raises(evtk.FormatError, match="header runs past 4 MiB"):
        evtk.open(path)
    _long_header(path, 16 << 20, b"#\n")  # 8 M one-character lines
    with no_hang(10), pytest.raises(evtk.FormatError, match="header runs past 4 MiB"):
        evtk.open(path)



@pytest.mark.parametrize("n_bytes", [30, 65_530, 65_536, 65_545, 262_150, 1_048_600])
def test_text_header_ends_where_the_text_lines_end(tmp_path, n_bytes):
    """The header's end, across the reader's growing reads: text lines starting with '#', then a record whose
    first byte is '#' but which holds binary (data, not header)."""
    from evtk.io.base import text_header

    line = b"# a header line of text\r\n"
    head = line * (n_bytes // len(line)) + b"#" * (n_bytes % len(line) + 1) + b"\n"
    path = tmp_path / "t.bin"
    path.write_bytes(head + b"#\x00\x01\x02\x03\x04\x05\x06" + b"# trailing text\n")
    lines, end = text_header(path, b"#", 4 << 20)
    assert end == len(head) and len(lines) == head.count(b"\n") and lines[0] == line.strip().decode()


_DVS128_HEAD = b"# This is a raw AE data file - do not edit\r\n# AEChip: ch.unizh.ini.jaer.chip.retina.DVS128\r\n"


def _jaer_records(version, addresses, stamps):
    """AEDAT 1.0 or 2.0 as jAER's file output writes it: the version line, the header, then each record packed as
    jAER packs it (big-endian: a 16-bit address and a 32-bit stamp for 1.0, two 32-bit words for 2.0)."""
    fmt = ">HI" if version == "1.0" else ">II"
    body = b"".join(struct.pack(fmt, int(a), int(t)) for a, t in zip(addresses, stamps))
    return f"#!AER-DAT{version}\r\n".encode() + _DVS128_HEAD + body


def _dvs128_records(n, seed, t0=0):
    """Random DVS128 addresses (x bits 1-7, y bits 8-14, polarity bit 0) and rising 32-bit stamps from t0 (mod
    2**32: past 2**32 they wrap, as the camera's counter does)."""
    rng = np.random.default_rng(seed)
    addresses = rng.integers(0, 1 << 15, n)
    t = t0 + np.cumsum(rng.integers(0, 400, n))
    return addresses, t % (1 << 32), t


@pytest.mark.parametrize("t0", [0, (1 << 32) - 300_000])
def test_aedat1_reads_as_the_same_records_in_aedat2(tmp_path, t0):
    """jAER's first format (16-bit addresses) against AEDAT 2.0 holding the same addresses and stamps, which
    tonic's reader and the real DVS128 recordings check: the same events; the stamps the records' own, unwrapped
    past 2**32; x, y and polarity the address bits, in evtk's orientation (x and y mirrored, OFF in bit 0)."""
    addresses, stamps, t = _dvs128_records(4000, seed=21, t0=t0)
    v1, v2 = tmp_path / "old.dat", tmp_path / "new.aedat"
    v1.write_bytes(_jaer_records("1.0", addresses, stamps))
    v2.write_bytes(_jaer_records("2.0", addresses, stamps))
    with evtk.open(v1) as rec:
        assert rec.metadata["aedat_version"] == "1.0" and rec.metadata["chip"] == "dvs128"
        assert rec.sensor_size == (128, 128) and not rec.warnings
        ev = rec.events()
        lo, hi = int(t[500]), int(t[3500])
        assert rec.events(lo, hi) == ev.between(lo, hi)
        assert evtk.Events.concatenate(list(rec.iter_events(chunk_events=333)), sensor_size=(128, 128)) == ev
    assert ev == evtk.read_events(v2)
    assert np.array_equal(ev.t, t)
    assert np.array_equal(ev.x, 127 - ((addresses >> 1) & 0x7F))
    assert np.array_equal(ev.y, 127 - ((addresses >> 8) & 0x7F))  # jAER counts y from the bottom row
    assert np.array_equal(ev.p, 1 - (addresses & 1))


def test_aedat1_damage_is_named_at_its_record(tmp_path):
    """A cut inside a 6-byte record, and a stamp that steps back: the byte offset of the record (of its stamp),
    and salvage reads the events before it; a DAVIS layout for 16-bit addresses is refused."""
    addresses, stamps, _ = _dvs128_records(900, seed=22)
    data = _jaer_records("1.0", addresses, stamps)
    head = len(data) - 6 * 900
    path = tmp_path / "cut.dat"
    path.write_bytes(data[:-2])
    with pytest.raises(evtk.FormatError, match=f"at byte {head + 6 * 899}: the file ends inside a record "
                                               r"\(4 of 6 bytes\)"):
        evtk.open(path)
    with evtk.open(path, salvage=True) as rec:
        assert rec.events() == evtk.read_events(_write(tmp_path / "whole.dat", data))[:899]
    back = bytearray(data)
    struct.pack_into(">I", back, head + 6 * 600 + 2, int(stamps[599]) - 1000)
    path.write_bytes(bytes(back))
    with pytest.raises(evtk.FormatError, match=f"at byte {head + 6 * 600 + 2}: the time stamp steps back"):
        evtk.read_events(path)
    with evtk.open(path, salvage=True) as rec:
        assert len(rec.events()) == 600 and rec.damage.offset == head + 6 * 600 + 2
    with pytest.raises(evtk.EvtkError, match="no DAVIS layout"):
        evtk.open(path, layout="davis")


def _write(path, data):
    path.write_bytes(data)
    return path
