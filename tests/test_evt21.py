"""Prophesee EVT 2.1 (issue 33): 64-bit vectorised words, read (both word layouts) and written.

The hand-built streams below assemble each word from the format's published bit layout with explicit shifts
(upper 32 bits: type 63..60, six low time bits 59..54, base x 53..43, y 42..32; lower 32 bits: the validity
mask of pixels base x + 0 .. 31), independently of evtk's reader and writer; evlib, a public reader of EVT 2.1,
checks the files evtk writes.
"""

import numpy as np
import pytest
from click.testing import CliRunner
from conftest import random_events

import evtk
from evtk.cli import main
from evtk.io import prophesee

CD_OFF, CD_ON, TIME_HIGH, EXT_TRIGGER, OTHERS = 0x0, 0x1, 0x8, 0xA, 0xE


def _upper(kind, t_low=0, x=0, y=0):
    """The 32 bits holding a word's type: the type, the time's six low bits, base x and y."""
    return (kind << 28) | (t_low << 22) | (x << 11) | y


def _cd(on, t_low, x_base, y, mask):
    return (_upper(CD_ON if on else CD_OFF, t_low, x_base, y), mask)


def _time_high(high):
    return ((TIME_HIGH << 28) | high, 0)


def _trigger(t_low, channel, rising):
    return ((EXT_TRIGGER << 28) | (t_low << 22) | (channel << 8) | int(rising), 0)


def _file(words, legacy=False, sensor=(640, 480), header=None):
    """An EVT 2.1 RAW file: a header, then each (upper, mask) pair as one little-endian 64-bit word (the mask
    in its low half), or with ``legacy`` as two little-endian 32-bit halves, the upper one first."""
    if header is None:
        header = f"% evt 2.1\n% format EVT21;height={sensor[1]};width={sensor[0]}"
        header += ";endianness=legacy\n" if legacy else "\n"
        header += "% end\n"
    out = bytearray(header.encode())
    for upper, mask in words:
        if legacy:
            out += upper.to_bytes(4, "little") + mask.to_bytes(4, "little")
        else:
            out += ((upper << 32) | mask).to_bytes(8, "little")
    return bytes(out)


HAND = [_time_high(3), _cd(1, 5, 32, 7, 0b101), _cd(0, 6, 0, 3, 1 << 31), _trigger(7, 19, True),
        (OTHERS << 28, 0xDEADBEEF), _time_high(0xFFFFFFF), _cd(1, 63, 608, 479, 0x80000001),
        _time_high(0), _cd(0, 1, 64, 0, 0xFFFFFFFF), _trigger(2, 0, False)]  # the 28-bit counter wrapped


def _hand_expected():
    top = 0xFFFFFFF << 6
    t = [3 * 64 + 5] * 2 + [3 * 64 + 6] + [top | 63] * 2 + [(1 << 34) | 1] * 32
    x = [32, 34, 31, 608, 639] + list(range(64, 96))
    y = [7, 7, 3, 479, 479] + [0] * 32
    p = [1, 1, 0, 1, 1] + [0] * 32
    return t, x, y, p


@pytest.mark.parametrize("legacy", [False, True])
def test_hand_built_words_decode_as_the_layout_says(legacy, tmp_path):
    path = tmp_path / "h.raw"
    path.write_bytes(_file(HAND, legacy))
    t, x, y, p = _hand_expected()
    with evtk.open(path) as rec:
        ev, tr = rec.events(), rec.triggers()
        assert rec.metadata["encoding"] == "evt21"
        assert rec.metadata["evt21_layout"] == ("legacy" if legacy else "64-bit")
        assert rec.sensor_size == (640, 480)
    assert ev.t.tolist() == t and ev.x.tolist() == x and ev.y.tolist() == y and ev.p.tolist() == p
    assert tr.t.tolist() == [3 * 64 + 7, (1 << 34) | 2]
    assert tr.kind.tolist() == [1, 2] and tr.channel.tolist() == [19, 0]
    r = CliRunner().invoke(main, ["info", "--json", str(path)])
    assert r.exit_code == 0 and '"encoding": "evt21"' in r.output and f'"events": {len(t)}' in r.output


def test_the_layout_is_the_header_s_a_legacy_file_read_as_64_bit_is_refused(tmp_path):
    """The same bytes under the other layout: the upper halves land in the mask, and the first word's type is
    a time-high's low bits (here 0, a CD word whose y is off the sensor) -- a clean error, never events."""
    path = tmp_path / "x.raw"
    path.write_bytes(_file(HAND, legacy=True).replace(b";endianness=legacy", b""))
    with pytest.raises(evtk.FormatError):
        evtk.read_events(path)


def test_sensor_from_the_system_id_and_evt_line_alone(tmp_path):
    path = tmp_path / "s.raw"
    path.write_bytes(_file([_time_high(1), _cd(1, 0, 288, 319, 1 << 31)],
                           header="% evt 2.1\n% system_ID 64\n"))  # 0x40: EVK3 GenX320, 320x320
    with evtk.open(path) as rec:
        assert rec.sensor_size == (320, 320) and "system ID" in rec.size_source
        assert rec.events().x.tolist() == [319]
    assert evtk.io.detect_format(path) == "prophesee"


def test_damage_names_the_byte_offset_and_salvage_keeps_the_prefix(tmp_path):
    words = [_time_high(1)] + [_cd(1, k % 64, 32 * (k % 20), k % 480, 0b11) for k in range(100)]
    data = _file(words)
    start = len(data) - 8 * len(words)
    path = tmp_path / "d.raw"
    path.write_bytes(data[:-3])  # cut inside the last word
    with pytest.raises(evtk.FormatError, match=rf"byte {len(data) - 8}\b.*ends inside an event"):
        evtk.open(path)
    with evtk.open(path, salvage=True) as rec:
        assert len(rec.events()) == 2 * 99 and rec.damage.offset == len(data) - 8
    bad = list(words)
    bad[51] = _cd(1, 0, 640 - 16, 0, 1 << 16)  # x = 640: off the sensor
    path.write_bytes(_file(bad))
    with pytest.raises(evtk.FormatError, match=rf"byte {start + 8 * 51}\b.*outside the 640x480 sensor"):
        evtk.read_events(path)
    with evtk.open(path, salvage=True) as rec:
        assert len(rec.events()) == 2 * 50
    for legacy in (False, True):
        bad[51] = (5 << 28, 0)  # a type EVT 2.1 does not have
        path.write_bytes(_file(bad, legacy))
        with pytest.raises(evtk.FormatError, match="unknown type 5"):
            evtk.read_events(path)
    r = CliRunner().invoke(main, ["info", "--check", str(path)])
    assert r.exit_code != 0 and "Traceback" not in r.output and "unknown type 5" in r.output


@pytest.mark.parametrize("legacy", [False, True])
def test_a_time_past_int64_stops_the_read_at_its_word(tmp_path, monkeypatch, legacy):
    """2**29 wraps of the 34-bit time (4 GiB of words) take the time past 2**63 - 1 µs: the read stops at the time
    high that does, naming its byte, and salvage keeps the events before it (numba's loop wrapped to negative
    times). The reader starts one wrap short of the limit."""
    from evtk.io.prophesee import recording

    most = (2**63 - 1) >> 34
    initial = recording.PropheseeRecording._initial_state

    def near_the_end(self):
        state = initial(self)
        state[1] = most  # the epoch
        return state

    monkeypatch.setattr(recording.PropheseeRecording, "_initial_state", near_the_end)
    words = [_time_high(0xFFFFFF0)] + [_cd(1, k % 64, 32 * (k % 20), k % 480, 0b11) for k in range(60)]
    words += [_time_high(5)] + [_cd(0, k % 64, 0, k % 480, 1) for k in range(10)]
    data = _file(words, legacy)
    start = len(data) - 8 * len(words)
    path = tmp_path / "w.raw"
    path.write_bytes(data)
    with pytest.raises(evtk.FormatError, match=rf"byte {start + 8 * 61}\b.*passes 2\*\*63 - 1 us"):
        evtk.read_events(path)
    with evtk.open(path, salvage=True) as rec:
        ev = rec.events()
        assert len(ev) == 120 and rec.damage.offset == start + 8 * 61
        assert ev.t.tolist() == [(most << 34) | (0xFFFFFF0 << 6) | (k // 2 % 64) for k in range(120)]


def test_full_vectors_resume_and_stay_within_the_memory_budget(tmp_path, monkeypatch):
    """32 events a word: the decoder resumes where the output is full; a budget too small for the events is a
    clean error before the memory is taken."""
    monkeypatch.setattr(prophesee.recording, "BLOCK_WORDS", 256)
    words = [_time_high(1)] + [_cd(k % 2, k % 64, 32 * (k % 20), k % 480, 0xFFFFFFFF) for k in range(3000)]
    path = tmp_path / "f.raw"
    path.write_bytes(_file(words))
    with evtk.open(path) as rec:
        ev = rec.events()
        assert len(ev) == 32 * 3000 and ev.x[:33].tolist() == list(range(32)) + [32]
        assert rec.events(64 + 10, 64 + 20) == ev.between(64 + 10, 64 + 20)
        assert evtk.Events.concatenate(list(rec.iter_events(1000))) == ev
    monkeypatch.setenv("EVTK_MEMORY_LIMIT_MB", "1")
    with pytest.raises(evtk.EvtkError, match="memory"):
        evtk.read_events(path)


def _events(n=30_000, seed=3, size=(640, 480)):
    ev = random_events(n, seed=seed, sensor_size=size, t0=1_000, span_us=5_000_000)
    # runs of events at one time and row, in and across 32-pixel groups, some x falling or repeated
    t, x, y, p = ev.t.copy(), ev.x.copy(), ev.y.copy(), ev.p.copy()
    t[100:200], y[100:200], p[100:200] = t[100], 9, 1
    x[100:200] = np.r_[np.arange(0, 80), np.arange(79, 59, -1)]
    x[300:310], t[300:310], y[300:310], p[300:310] = 5, t[300], 1, 0
    return evtk.Events(t, x, y, p, size)


def _triggers(n=60, channels=32, seed=5):
    rng = np.random.default_rng(seed)
    return evtk.Triggers(np.sort(rng.integers(1_000, 5_001_000, n)), rng.choice([1, 2], n), rng.integers(0, channels, n))


def test_written_files_read_back_exactly_with_triggers_windows_and_chunks(tmp_path, monkeypatch):
    ev, tr = _events(), _triggers()
    path = tmp_path / "w.raw"
    evtk.write_events(path, ev, tr, fmt="evt21")
    assert path.read_bytes().startswith(b"% date")
    monkeypatch.setattr(prophesee.recording, "BLOCK_WORDS", 1024)  # many blocks
    with evtk.open(path) as rec:
        assert rec.metadata["encoding"] == "evt21" and rec.sensor_size == ev.sensor_size
        assert rec.events() == ev
        got = rec.triggers()
        assert got.t.tolist() == tr.t.tolist() and got.kind.tolist() == tr.kind.tolist()
        assert got.channel.tolist() == tr.channel.tolist()
        for lo, hi in [(0, 1), (100_000, 250_000), (1_234_567, 1_240_000), (4_999_000, 10**9)]:
            assert rec.events(lo, hi) == ev.between(lo, hi)
        assert evtk.Events.concatenate(list(rec.iter_events(777))) == ev
    data = path.read_bytes()
    words = np.frombuffer(data[data.index(b"% end\n") + 6:], "<u8")
    assert ((words >> 60) <= 1).sum() <= len(ev) - 77  # x 0..79 at one time and row: 3 words, not 80


def test_chunked_writer_equals_one_write_and_long_gaps_keep_the_time(tmp_path):
    t = np.array([5, 70, 70, 2**33, 2**34 + 7, 2**35 + 2**34 + 1], np.int64)
    ev = evtk.Events(t, [1, 2, 3, 4, 33, 34], [0, 1, 1, 2, 3, 3], [1, 0, 0, 1, 1, 1], (64, 8))
    one, two = tmp_path / "one.raw", tmp_path / "two.raw"
    evtk.write_events(one, ev, fmt="evt21")
    with evtk.io.open_writer(two, ev.sensor_size, fmt="evt21") as w:
        w.write_events(ev[:2])
        w.write_events(ev[2:5])
        w.write_events(ev[5:])
    assert evtk.read_events(one) == ev == evtk.read_events(two)


def test_triggers_before_between_and_after_the_events_across_a_wrap(tmp_path):
    ev = evtk.Events([5, 9], [1, 40], [0, 1], [1, 0], (64, 8))
    tr = evtk.Triggers([1, 9, 100, 2**35], [1, 2, 1, 2], [3, 4, 5, 31])
    path = tmp_path / "t.raw"
    evtk.write_events(path, ev, tr, fmt="evt21")
    with evtk.open(path) as rec:
        got = rec.triggers()
        assert rec.events() == ev and got.t.tolist() == tr.t.tolist() and got.channel.tolist() == [3, 4, 5, 31]
        assert got.kind.tolist() == [1, 2, 1, 2]


def test_what_evt21_cannot_hold_is_refused_by_name(tmp_path):
    ev = _events(n=1000)
    with pytest.raises(evtk.EvtkError, match="EVT 2.1 holds trigger channels 0-31"):
        evtk.write_events(tmp_path / "c.raw", ev, evtk.Triggers([2_000], [1], [32]), fmt="evt21")
    with pytest.raises(evtk.EvtkError, match="EVT 2.1 holds coordinates below 2048"):
        evtk.write_events(tmp_path / "b.raw", evtk.Events([1], [1], [1], [1], (4096, 8)), fmt="evt21")
    with pytest.raises(evtk.EvtkError, match="EVT 2.1 stores time from 0"):
        evtk.write_events(tmp_path / "n.raw", evtk.Events([-1], [1], [1], [1], (8, 8)), fmt="evt21")
    assert not list(tmp_path.iterdir())


def test_cli_converts_to_and_from_evt21_with_trigger_channels(tmp_path):
    ev, tr = _events(n=5_000), _triggers(channels=32)
    src = tmp_path / "s.h5"
    evtk.write_events(src, ev, tr)
    out = tmp_path / "o.raw"
    r = CliRunner().invoke(main, ["convert", "--format", "evt21", str(src), str(out)])
    assert r.exit_code == 0, r.output
    back = tmp_path / "b.h5"
    r = CliRunner().invoke(main, ["convert", str(out), str(back)])
    assert r.exit_code == 0, r.output
    with evtk.open(back) as rec:
        assert rec.events() == ev and rec.triggers().channel.tolist() == tr.channel.tolist()


def test_evlib_reads_evtk_s_evt21_files_exactly(tmp_path):
    evlib = pytest.importorskip("evlib", reason="evlib (a public EVT 2.1 reader) is not installed")
    ev = _events(seed=11)
    path = tmp_path / "e.raw"
    evtk.write_events(path, ev, _triggers(), fmt="evt21")
    df = evlib.load_events(str(path)).collect()
    assert np.array_equal(df["x"].to_numpy(), ev.x) and np.array_equal(df["y"].to_numpy(), ev.y)
    assert np.array_equal(df["t"].dt.total_microseconds().to_numpy(), ev.t)
    assert np.array_equal(df["polarity"].to_numpy() > 0, ev.p.astype(bool))


def test_evlib_and_evtk_agree_on_the_hand_built_stream(tmp_path):
    evlib = pytest.importorskip("evlib", reason="evlib (a public EVT 2.1 reader) is not installed")
    path = tmp_path / "h.raw"
    path.write_bytes(_file(HAND[:5]))  # before the counter's wrap, which evlib does not unwrap
    t, x, y, p = (c[:3] for c in _hand_expected())
    df = evlib.load_events(str(path)).collect()
    assert df["x"].to_list() == x == evtk.read_events(path).x.tolist()
    assert df["y"].to_list() == y and df["t"].dt.total_microseconds().to_list() == t
    assert (df["polarity"].to_numpy() > 0).astype(int).tolist() == p
