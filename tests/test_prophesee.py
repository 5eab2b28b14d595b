"""Prophesee RAW (EVT 2.0, 3.0), DAT and Event Stream files (issue 20), against faery and expelliarmus."""


import numpy as np
import pytest
from click.testing import CliRunner
from conftest import event_stream_atis_file, no_hang, random_events

import evtk
import evtk.io.prophesee.recording  # noqa: F401  (the block size the tests shrink)
from evtk.cli import main
from evtk.io import prophesee

faery = pytest.importorskip("faery")
expelliarmus = pytest.importorskip("expelliarmus")


def _faery_write(path, ev, version):
    arr = np.zeros(len(ev), faery.EVENTS_DTYPE)
    arr["t"], arr["x"], arr["y"], arr["on"] = ev.t, ev.x, ev.y, ev.p.astype(bool)
    stream = faery.events_stream_from_array(arr, tuple(ev.sensor_size))
    stream.to_file(str(path), **({"version": version} if version else {}))


@pytest.fixture(params=[("evt2", ".raw"), ("evt3", ".raw"), ("dat2", ".dat"), (None, ".es")],
                ids=["evt2", "evt3", "dat", "es"])
def written(request, tmp_path):
    version, ext = request.param
    ev = random_events(30_000, seed=4, sensor_size=(1280, 720), t0=5_000, span_us=3_000_000)
    path = tmp_path / f"rec{ext}"
    _faery_write(path, ev, version)
    return path, ev, "es" if ext == ".es" else "dat" if version == "dat2" else version


def test_read_equals_the_events_written_and_the_public_readers(written):
    path, ev, enc = written
    fa = np.concatenate(list(faery.events_stream_from_file(str(path))))
    if enc == "es":  # Event Stream keeps no t0: faery writes the stamps from the first event on
        got = evtk.read_events(path)
        assert np.array_equal(got.t, ev.t - ev.t[0]) and np.array_equal(got.t, fa["t"])
        assert np.array_equal(got.x, fa["x"]) and np.array_equal(got.y, fa["y"]) and np.array_equal(got.y, ev.y)
        assert np.array_equal(got.p.astype(bool), fa["on"])
        return
    with evtk.open(path) as rec:
        got = rec.events()
        t0 = rec.metadata["header_t0_us"]
        assert rec.sensor_size == (1280, 720) and rec.info()["events"] == len(ev)
    ex = expelliarmus.Wizard(encoding=enc).read(str(path))
    # the stamps as stored; faery writes its own '% t0' header line and adds it back, Prophesee's tools do not
    assert np.array_equal(got.t + t0, ev.t) and np.array_equal(got.t + t0, fa["t"])
    if enc == "evt3":  # expelliarmus adds 4096 us after the first change of the time high (a known disagreement)
        assert np.all((ex["t"] - got.t) % 4096 == 0) and np.any(ex["t"] != got.t)
    else:
        assert np.array_equal(got.t, ex["t"])
    for c in "xy":
        assert np.array_equal(getattr(got, c), ex[c]) and np.array_equal(getattr(got, c), fa[c])
    assert np.array_equal(got.p, ex["p"]) and np.array_equal(got.p.astype(bool), fa["on"])


def test_windows_and_chunks_are_exact_over_many_blocks(written, monkeypatch):
    path, ev, _ = written
    monkeypatch.setattr(prophesee.recording, "BLOCK_WORDS", 2048)  # some fifty blocks
    with evtk.open(path) as rec:
        whole = rec.events()
        assert len(rec._index()) > 10
        for lo, hi in [(0, 1), (100_000, 250_000), (1_234_567, 1_240_000), (2_999_000, 10**9)]:
            assert rec.events(lo, hi) == whole.between(lo, hi)
        chunks = list(rec.iter_events(chunk_events=777))
        assert all(len(c) == 777 for c in chunks[:-1])
        assert evtk.Events.concatenate(chunks) == whole


def _evt2(words, sensor=(640, 480)):
    head = f"% evt 2.0\n% format EVT2;width={sensor[0]};height={sensor[1]}\n".encode()
    return head + np.asarray(words, "<u4").tobytes()


def _cd(t_low, x, y, on=1):
    return (on << 28) | (t_low << 22) | (x << 11) | y


def test_triggers_and_wrapping_time(tmp_path):
    words = [(8 << 28) | 0xFFFFFFF, _cd(5, 1, 2), (10 << 28) | (6 << 22) | 1,  # rising edge
             (8 << 28) | 0, _cd(3, 3, 4, 0), (10 << 28) | (9 << 22) | (3 << 8)]  # the counter wrapped; falling
    path = tmp_path / "w.raw"
    path.write_bytes(_evt2(words))
    with evtk.open(path) as rec:
        ev, tr = rec.events(), rec.triggers()
    top = (0xFFFFFFF << 6)
    assert ev.t.tolist() == [top | 5, (1 << 34) | 3] and ev.x.tolist() == [1, 3] and ev.p.tolist() == [1, 0]
    assert tr.t.tolist() == [top | 6, (1 << 34) | 9] and tr.kind.tolist() == [1, 2]


def test_damage_is_an_error_and_salvage_keeps_the_intact_prefix(tmp_path):
    words = [(8 << 28) | 1] + [_cd(k % 64, k, k) for k in range(100)]
    path = tmp_path / "d.raw"
    data = _evt2(words)
    path.write_bytes(data[:-2])  # cut inside the last word
    with pytest.raises(evtk.FormatError, match="ends inside an event"):
        evtk.open(path)
    with evtk.open(path, salvage=True) as rec:
        assert len(rec.events()) == 99 and rec.damage is not None
    bad = list(words)
    bad[50] = _cd(0, 700, 1)  # off a 640-pixel-wide sensor
    path.write_bytes(_evt2(bad))
    with pytest.raises(evtk.FormatError, match="outside the 640x480 sensor"):
        evtk.read_events(path)
    with evtk.open(path, salvage=True) as rec:
        assert rec.events().x.tolist() == list(range(49))
    bad[50] = 5 << 28  # a type EVT 2.0 does not have
    path.write_bytes(_evt2(bad))
    with pytest.raises(evtk.FormatError, match="unknown type 5"):
        evtk.read_events(path)


def test_cli_info_and_convert(written, tmp_path):
    path, ev, enc = written
    r = CliRunner().invoke(main, ["info", "--json", str(path)])
    fmt = "event_stream" if enc == "es" else "prophesee"
    assert r.exit_code == 0 and f'"format": "{fmt}"' in r.output and f'"events": {len(ev)}' in r.output
    out = tmp_path / "c.h5"
    r = CliRunner().invoke(main, ["convert", str(path), str(out)])
    assert r.exit_code == 0, r.output
    assert evtk.read_events(out) == evtk.read_events(path)


def test_header_without_size_needs_one(tmp_path):
    path = tmp_path / "n.raw"
    path.write_bytes(b"% evt 2.0\n" + np.asarray([_cd(1, 1, 1)], "<u4").tobytes())
    with pytest.raises(evtk.FormatError, match="no sensor size"):
        evtk.open(path)
    with evtk.open(path, sensor_size=(640, 480)) as rec:
        assert len(rec.events()) == 1


def _evt3(words, sensor=(640, 480)):
    head = f"% evt 3.0\n% format EVT3;width={sensor[0]};height={sensor[1]}\n".encode()
    return head + np.asarray(words, "<u2").tobytes()


def test_evt3_vectors_triggers_and_wrapping_time(tmp_path):
    words = [(8 << 12) | 0xFFF, (6 << 12) | 0x010,  # t = 0xFFF010
             (0 << 12) | 7,  # y = 7
             (3 << 12) | (1 << 11) | 100,  # vector base x 100, ON
             (4 << 12) | 0b100000000101,  # x = 100, 102, 111
             (5 << 12) | 0b10000001,  # x = 112, 119
             (2 << 12) | 5,  # x = 5, OFF
             (10 << 12) | (2 << 8) | 1,  # trigger, channel 2, rising
             (8 << 12) | 0x000, (6 << 12) | 0x003,  # the 24-bit time wrapped: t = 2^24 + 3
             (2 << 12) | (1 << 11) | 9, (7 << 12), (14 << 12), (15 << 12)]  # ON at x 9; fillers
    path = tmp_path / "v.raw"
    path.write_bytes(_evt3(words))
    with evtk.open(path) as rec:
        ev, tr = rec.events(), rec.triggers()
    t1 = 0xFFF010
    assert ev.x.tolist() == [100, 102, 111, 112, 119, 5, 9]
    assert ev.y.tolist() == [7] * 7 and ev.p.tolist() == [1, 1, 1, 1, 1, 0, 1]
    assert ev.t.tolist() == [t1] * 6 + [(1 << 24) | 3]
    assert tr.t.tolist() == [t1] and tr.kind.tolist() == [1] and tr.channel.tolist() == [2]
    path.write_bytes(_evt3(words[:4] + [(4 << 12) | (1 << 11)] ))  # x = 100 + 11 on a 640-wide sensor: fine
    assert evtk.read_events(path).x.tolist() == [111]
    path.write_bytes(_evt3([(0 << 12) | 7, (2 << 12) | 700]))
    with pytest.raises(evtk.FormatError, match="outside the 640x480"):
        evtk.read_events(path)
    path.write_bytes(_evt3([(0 << 12) | 7, (9 << 12)]))
    with pytest.raises(evtk.FormatError, match="unknown type 9"):
        evtk.read_events(path)


def test_event_stream_overflow_reset_bytes_and_a_cut_event(tmp_path):
    head = b"Event Stream" + bytes([2, 0, 0, 1]) + (640).to_bytes(2, "little") + (480).to_bytes(2, "little")
    body = bytes([0xFF, 0xFE, 0xFF, 0x0B]) + (7).to_bytes(2, "little") + (470).to_bytes(2, "little")
    path = tmp_path / "o.es"
    path.write_bytes(head + body)
    ev = evtk.read_events(path)
    assert ev.t.tolist() == [127 + 127 + 5] and ev.x.tolist() == [7] and ev.y.tolist() == [9] and ev.p.tolist() == [1]
    path.write_bytes(head + body + bytes([0x02, 1, 0]))  # a second event cut after its x
    with pytest.raises(evtk.FormatError, match="ends inside an event"):
        evtk.open(path).events()
    with evtk.open(path, salvage=True) as rec:
        assert len(rec.events()) == 1 and rec.damage is not None
    path.write_bytes(head[:15] + bytes([4]) + head[16:] + body)
    with pytest.raises(evtk.FormatError, match="colour"):
        evtk.open(path)


def _atis_bytes(*records):
    """An ATIS Event Stream 2.0 body packed by hand from the format's table: (gap_us, polarity, is_tc, x, y) each,
    a gap of 63 us or more as overflow bytes (0xFD-0xFF: 63 us times the low two bits) before the event's byte 0;
    None is a reset byte (0xFC)."""
    out = bytearray()
    for r in records:
        if r is None:
            out.append(0xFC)
            continue
        gap, pol, tc, x, y = r
        while gap >= 63:
            step = min(gap // 63, 3)
            out.append(0xFC | step)
            gap -= 63 * step
        out += bytes([(gap << 2) | (pol << 1) | tc]) + x.to_bytes(2, "little") + y.to_bytes(2, "little")
    return bytes(out)


def test_event_stream_atis_bytes_as_the_format_describes_them(tmp_path):
    """ATIS bytes packed by hand: overflow and reset bytes, change-detection events (ON and OFF, y counted from the
    bottom row in the file) read as events, threshold crossings counted and left out; a cut event and an event off
    the sensor are errors at their bytes, salvage keeping what comes before."""
    head = b"Event Stream" + bytes([2, 0, 0, 2]) + (304).to_bytes(2, "little") + (240).to_bytes(2, "little")
    body = _atis_bytes((200, 1, 0, 7, 9), None, (5, 0, 1, 300, 239), (63, 0, 0, 303, 0), None, (62, 1, 1, 0, 0),
                       (1, 0, 0, 1, 1))
    path = tmp_path / "a.es"
    path.write_bytes(head + body)
    with evtk.open(path) as rec:
        ev = rec.events()
        assert rec.metadata["header"][1] == "type atis" and rec.sensor_size == (304, 240)
        assert rec.info()["left_out"] == {"threshold crossings": 2}
    assert ev.t.tolist() == [200, 268, 331] and ev.x.tolist() == [7, 303, 1]
    assert ev.y.tolist() == [230, 239, 238] and ev.p.tolist() == [1, 0, 0]
    path.write_bytes(head + body + _atis_bytes((3, 1, 0, 2, 2))[:3])
    with pytest.raises(evtk.FormatError, match=f"at byte {len(head) + len(body) + 3}: the file ends inside an event"):
        evtk.read_events(path)
    with evtk.open(path, salvage=True) as rec:
        assert rec.events() == ev and rec.damage is not None
    path.write_bytes(head + body + _atis_bytes((3, 0, 1, 304, 2)) + body)  # a threshold crossing off the sensor
    with pytest.raises(evtk.FormatError, match="outside the 304x240"):
        evtk.read_events(path)
    with evtk.open(path, salvage=True) as rec:
        assert rec.events() == ev


def test_event_stream_atis_equals_event_stream_s_change_detection_events(tmp_path, monkeypatch):
    """ATIS streams written and read by event_stream, the format's own library: evtk's events are its events that
    are no exposure measurement (y from the top, ON the polarity), in full reads, windows and chunks, across blocks
    that cut events and gaps long enough for overflow bytes; the exposure measurements are counted."""
    event_stream = pytest.importorskip("event_stream")
    monkeypatch.setattr(prophesee.recording, "BLOCK_WORDS", 4099)
    rng = np.random.default_rng(17)
    n = 30_000
    written = np.zeros(n, event_stream.atis_dtype)
    written["t"] = np.cumsum(rng.choice([0, 1, 30, 62, 63, 64, 200, 5000], n))
    written["x"], written["y"] = rng.integers(0, 346, n), rng.integers(0, 260, n)
    written["exposure"], written["polarity"] = rng.random(n) < 0.4, rng.random(n) < 0.5
    path = tmp_path / "atis.es"
    event_stream_atis_file(path, written, 346, 260)
    decoder = event_stream.Decoder(str(path))
    theirs = np.concatenate(list(decoder))
    assert decoder.type == "atis" and np.array_equal(theirs, written)
    cd = theirs[~theirs["exposure"]]
    with evtk.open(path) as rec:
        ev = rec.events()
        assert rec.info()["left_out"] == {"threshold crossings": int(theirs["exposure"].sum())}
        assert len(rec._blocks) > 5
        lo, hi = int(cd["t"][1000]), int(cd["t"][15000])
        assert rec.events(lo, hi) == ev.between(lo, hi)
        assert evtk.Events.concatenate(list(rec.iter_events(chunk_events=997)), sensor_size=(346, 260)) == ev
    assert np.array_equal(ev.t, cd["t"].astype(np.int64)) and np.array_equal(ev.x, cd["x"])
    assert np.array_equal(ev.y, 259 - cd["y"]) and np.array_equal(ev.p, cd["polarity"])
    assert np.dtype(bool).str == "|b1"  # event_stream wrote in a child process: this one's numpy is unharmed


def test_event_stream_whole_read_peaks_near_its_columns(tmp_path):
    """A whole Event Stream read decodes straight into the columns it returns: each block decoded into its own
    buffers and copied over took 1.37x the columns at its peak (400,000 events), now within 1.2x."""
    import tracemalloc

    path = tmp_path / "m.es"
    evtk.write_events(path, random_events(400_000, seed=3, sensor_size=(640, 480)))
    tracemalloc.start()
    try:
        ev = evtk.read_events(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert len(ev) == 400_000
    assert peak <= 1.2 * sum(c.nbytes for c in (ev.t, ev.x, ev.y, ev.p)), peak


def test_event_stream_whole_read_across_blocks_with_damage_equals_the_block_route(tmp_path, monkeypatch):
    """The whole read (columns filled block by block) and the windowed one (the index, then blocks) agree on
    events that cross blocks, on the index they leave, and at an event off the sensor in a later block."""
    monkeypatch.setattr(prophesee.recording, "BLOCK_WORDS", 4099)  # events cut by every block's end
    path = tmp_path / "b.es"
    evtk.write_events(path, random_events(5_000, seed=5, sensor_size=(640, 480)))
    with evtk.open(path) as whole, evtk.open(path) as windowed:
        ev = whole.events()
        assert windowed.events(0, 1 << 62) == ev
        assert len(whole._blocks) > 5 and repr(whole._blocks) == repr(windowed._blocks)
    data = bytearray(path.read_bytes())
    starts, i = [], 20
    while i < len(data):  # event starts: bytes read where an event may begin that are not 0xFE/0xFF
        if data[i] >= 0xFE:
            i += 1
        else:
            starts.append(i)
            i += 5
    at = starts[3000]
    data[at + 1:at + 3] = (700).to_bytes(2, "little")  # x = 700 on a 640-wide sensor
    path.write_bytes(bytes(data))
    with pytest.raises(evtk.FormatError, match=f"at byte {at + 4}.*outside the 640x480"):
        evtk.read_events(path)
    with evtk.open(path, salvage=True) as rec:
        got = rec.events()
        assert got == ev[:3000] and rec.damage is not None and rec.damage.offset == at + 4
    with evtk.open(path, salvage=True) as rec:
        assert rec.events(0, 1 << 62) == ev[:3000]


def test_evt3_vectors_with_more_events_than_words(tmp_path, monkeypatch):
    """Full 12-pixel vectors give 12 events a word: the straight-through decoder resumes where room runs out."""
    monkeypatch.setattr(prophesee.recording, "BLOCK_WORDS", 256)
    words = [(8 << 12) | 1]
    for k in range(1000):
        words += [(6 << 12) | (k % 4096), (0 << 12) | (k % 480), (3 << 12) | (1 << 11) | 0, (4 << 12) | 0xFFF]
    path = tmp_path / "full.raw"
    path.write_bytes(_evt3(words))
    with evtk.open(path) as rec:
        ev = rec.events()
        assert len(ev) == 12_000 and ev.x[:13].tolist() == list(range(12)) + [0]
        assert rec.events(4096 + 100, 4096 + 200) == ev.between(4096 + 100, 4096 + 200)
    with evtk.open(path) as rec:  # the windowed path first: its index, then the same events
        assert rec.events(4096 + 100, 4096 + 200) == ev.between(4096 + 100, 4096 + 200)
        assert rec.info()["events"] == 12_000


def test_first_data_word_starting_with_a_percent_sign_is_data(tmp_path):
    """Older headers end without '% end': a word whose first (low) byte is '%' (0x25) must not be taken for text."""
    words = [(8 << 28) | 1, _cd(0, 1, 0x25), _cd(1, 2, 3)]
    assert np.asarray(words[1:2], "<u4").tobytes()[:1] == b"%"
    path = tmp_path / "pct.raw"
    path.write_bytes(b"% evt 2.0\n% format EVT2;width=640;height=480\n" + np.asarray(words[1:], "<u4").tobytes())
    ev = evtk.read_events(path)
    assert ev.x.tolist() == [1, 2] and ev.y.tolist() == [0x25, 3]
    path.write_bytes(b"% evt 2.0\n% geometry 640x480\n% end\n" + np.asarray(words, "<u4").tobytes())
    assert evtk.read_events(path).t.tolist() == [64, 65]


def test_dat_whose_events_spell_a_header_line_is_read_as_dat(tmp_path):
    """The old sniffer searched the first 4096 bytes, events included, for '% evt 2.0' and took a valid DAT
    file for EVT 2.0 (and refused it); only header lines count, and a DAT header ends at its type byte."""
    header = b"% Data file containing Event2D events.\n% Version 2\n% Width 16384\n% Height 16384\n"
    body = np.array([1000], "<u4").tobytes() + b"% evt 2.0\n\x00\x10" + np.array([2 << 30, 0], "<u4").tobytes()
    path = tmp_path / "spell.dat"
    path.write_bytes(header + bytes([0x0C, 8]) + body)
    assert b"% evt 2.0" in path.read_bytes()[len(header):]
    assert evtk.io.detect_format(path) == "prophesee"
    with evtk.open(path) as rec:
        assert rec.encoding == "dat"
        got = rec.events()
    ref = expelliarmus.Wizard(encoding="dat").read(str(path))
    assert len(got) == 3 and np.array_equal(got.t, ref["t"]) and np.array_equal(got.x, ref["x"])
    assert np.array_equal(got.y, ref["y"]) and np.array_equal(got.p, ref["p"] != 0)  # a 4-bit polarity: ON if set


def test_long_percent_headers_are_refused_in_linear_time(tmp_path):
    """A 16 MiB '%' header: refused past 1 MiB, in one pass (the guard stops a hang; it is no speed assertion)."""
    path = tmp_path / "long.raw"
    for line in (b"% evt 2.0\n", b"%\n", b"%" + b" " * 100_000 + b"\n"):
        path.write_bytes(b"% format EVT2;width=640;height=480\n" + line * ((16 << 20) // len(line)))
        with no_hang(10), pytest.raises(evtk.FormatError, match="header runs past 1 MiB"):
            evtk.open(path)
    path.write_bytes(b"% geometry 640x480\n" + b"% x\n" * 200_000 + b"% evt 2.0\n% end\n"
                     + np.array([_cd(3, 1, 2)], "<u4").tobytes())
    with no_hang(10):
        assert evtk.read_events(path).x.tolist() == [1]


def test_trigger_channels_are_kept_and_windows_use_one(tmp_path, monkeypatch):
    """A camera with two trigger inputs: the old reader merged them, so `--window triggers` made windows from
    the edges of both signals (the second one 642 us late). Each trigger keeps its channel; windows need one."""
    from evtk.events import TRIGGER_CHANNEL_ENV
    from evtk.reconstruct import windows_from_triggers

    monkeypatch.delenv(TRIGGER_CHANNEL_ENV, raising=False)
    words = []
    for k in range(4):  # channel 0: a 1000 us window every 10 ms; channel 3: the same edges 642 us later
        for t_us, edge in [(k * 10_000, 1), (k * 10_000 + 1000, 0)]:
            for ch, late in [(0, 0), (3, 642)]:
                t = t_us + late
                words += [(8 << 28) | (t >> 6), (10 << 28) | ((t & 63) << 22) | (ch << 8) | edge]
    words += [(8 << 28) | (40_000 >> 6), _cd(0, 1, 2)]
    path = tmp_path / "two.raw"
    path.write_bytes(_evt2(words))
    with evtk.open(path) as rec:
        tr = rec.triggers()
    assert tr.channels == [0, 3] and len(tr) == 16
    assert tr.of_channel(3).t.tolist() == [k * 10_000 + d + 642 for k in range(4) for d in (0, 1000)]
    with pytest.raises(evtk.EvtkError, match=r"2 channels \(0, 3\)"):
        windows_from_triggers(tr)
    win = windows_from_triggers(tr, channel=0)
    assert win.t_start_us.tolist() == [0, 10_000, 20_000, 30_000] and win.t_end_us.tolist() == [1000, 11_000, 21_000, 31_000]
    monkeypatch.setenv(TRIGGER_CHANNEL_ENV, "3")  # what `evtk --trigger-channel 3` sets
    assert windows_from_triggers(tr).t_start_us.tolist() == [642, 10_642, 20_642, 30_642]
    with pytest.raises(evtk.EvtkError, match="no trigger comes from channel 5; the channels are 0, 3"):
        windows_from_triggers(tr, channel=5)
    monkeypatch.delenv(TRIGGER_CHANNEL_ENV)
    assert windows_from_triggers(tr.of_channel(0)).t_start_us.tolist() == [0, 10_000, 20_000, 30_000]


def test_a_word_of_unknown_type_stops_the_index_not_only_a_full_read(tmp_path, monkeypatch):
    """`evtk info` (no --check) counted a Prophesee file's events up to a word of unknown type and exited 0, and the
    blocks after it were indexed from the state where the count stopped (a window there read from a wrong state).
    Now the index stops at that word: an error naming its byte offset, or with salvage the intact prefix."""
    monkeypatch.setattr(prophesee.recording, "BLOCK_WORDS", 64)
    words = [(8 << 28) | 1] + [_cd(k % 64, k % 640, k % 480) for k in range(400)]
    words[100] = 5 << 28  # a type EVT 2.0 does not have, in the second block
    path = tmp_path / "u.raw"
    path.write_bytes(_evt2(words))
    at = len(_evt2([])) + 4 * 100
    with pytest.raises(evtk.FormatError, match=rf"byte {at}.*unknown type 5"):
        with evtk.open(path) as rec:
            rec.info()
    with pytest.raises(evtk.FormatError, match="unknown type 5"):
        with evtk.open(path) as rec:
            rec.events(0, 1 << 40)
    res = CliRunner().invoke(main, ["info", str(path)])
    assert res.exit_code == 1 and "unknown type 5" in res.output, res.output
    with evtk.open(path, salvage=True) as rec:
        assert rec.info()["events"] == 99 and rec.damage is not None
        assert len(rec.events()) == 99 and len(rec.events(0, 1 << 40)) == 99
