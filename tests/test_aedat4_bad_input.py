"""Damaged AEDAT4 files: a FormatError naming file, offset and reason, or with
salvage=True every intact packet before the damage."""

import struct
import sys

import numpy as np
import pytest
from conftest import random_events

import evtk
from evtk.io import aedat4

PACKET = 1000


@pytest.fixture
def good(tmp_path):
    """An LZ4 file of 10 event packets (and one trigger packet) plus its layout."""
    ev = random_events(10 * PACKET, seed=21, span_us=100_000)
    tr = evtk.Triggers([ev.t[-1]], [1])  # after the last event: the final packet
    path = tmp_path / "good.aedat4"
    evtk.write_events(path, ev, tr, packet_events=PACKET, packet_us=None)
    with evtk.open(path) as rec:
        index = rec._index
        layout = dict(
            offsets=index.offset.copy(), sizes=index.size.copy(), streams=index.stream.copy(),
            data_start=rec._data_start, dtp=rec._data_table_pos,
        )
    return path, ev, layout


def damaged(tmp_path, good, edit, name="bad.aedat4"):
    path, _, layout = good
    data = bytearray(path.read_bytes())
    data = edit(data, layout)
    out = tmp_path / name
    out.write_bytes(bytes(data))
    return out


def expect_error(path, match, offset=None):
    with pytest.raises(evtk.FormatError, match=match) as info:
        with evtk.open(path) as rec:
            rec.events()
            rec.triggers()
    err = info.value
    assert err.path == str(path)
    if offset is not None:
        assert err.offset == offset
    assert str(path) in str(err)
    return err


def test_empty_file(tmp_path):
    p = tmp_path / "empty.aedat4"
    p.write_bytes(b"")
    expect_error(p, "empty", offset=0)


def test_not_aedat(tmp_path):
    p = tmp_path / "junk.aedat4"
    p.write_bytes(b"hello world, not events" * 10)
    expect_error(p, "unrecognised", offset=0)


def test_older_aedat_version_is_named(tmp_path):
    p = tmp_path / "old.aedat"
    p.write_bytes(b"#!AER-DAT5.0\r\n#Format: RAW\r\n")
    expect_error(p, "version 5.0", offset=0)
    p.write_bytes(b"#!AER-DAT3.1\r\n#Format: RAW\r\n")  # read by the legacy reader, whose header must end
    expect_error(p, "END-HEADER")


def test_garbage_after_magic(tmp_path):
    p = tmp_path / "garbage.aedat4"
    p.write_bytes(aedat4.MAGIC + np.random.default_rng(0).bytes(500))
    expect_error(p, "header", offset=14)


@pytest.mark.parametrize("cut", [14, 16, 18, 40, 200])
def test_truncated_inside_header(tmp_path, good, cut):
    p = damaged(tmp_path, good, lambda d, L: d[:cut])
    expect_error(p, "header")


def test_truncated_inside_packet_strict_and_salvage(tmp_path, good):
    _, ev, layout = good
    k = 6  # cut in the middle of the 7th packet's body
    cut = int(layout["offsets"][k] + layout["sizes"][k] // 2)
    p = damaged(tmp_path, good, lambda d, L: d[:cut])
    expect_error(p, "truncated|outside the file")
    with evtk.open(p, salvage=True) as rec:
        got = rec.events()
        assert got == ev[: k * PACKET]
        assert rec.damage.offset == int(layout["offsets"][k] - 8)
        assert "remain" in rec.damage.reason


def test_packet_size_larger_than_file(tmp_path, good):
    _, ev, layout = good
    k = 3

    def edit(d, L):
        struct.pack_into("<i", d, int(L["offsets"][k] - 4), 2**31 - 1)
        return d

    p = damaged(tmp_path, good, edit)
    err = expect_error(p, "packet header says", offset=int(layout["offsets"][k] - 8))
    with evtk.open(p, salvage=True) as rec:
        assert rec.events() == ev[: k * PACKET]
        assert rec.damage.offset == err.offset


def test_packet_size_larger_than_file_without_data_table(tmp_path, good):
    _, ev, layout = good
    k = 2

    def edit(d, L):
        d = d[: L["dtp"]]
        struct.pack_into("<q", d, aedat4._DTP_FIELD, -1)
        struct.pack_into("<i", d, int(L["offsets"][k] - 4), 2**31 - 1)
        return d

    p = damaged(tmp_path, good, edit)
    expect_error(p, "claims 2147483647 bytes", offset=int(layout["offsets"][k] - 8))
    with evtk.open(p, salvage=True) as rec:
        assert rec.events() == ev[: k * PACKET]


def test_unknown_stream_id(tmp_path, good):
    _, ev, layout = good

    def edit(d, L):
        d = d[: L["dtp"]]
        struct.pack_into("<q", d, aedat4._DTP_FIELD, -1)
        struct.pack_into("<i", d, int(L["offsets"][5] - 8), 77)
        return d

    p = damaged(tmp_path, good, edit)
    expect_error(p, "stream 77", offset=int(layout["offsets"][5] - 8))


def test_corrupt_compressed_body(tmp_path, good):
    _, ev, layout = good
    k = 4

    def edit(d, L):
        o = int(L["offsets"][k])
        d[o + 4 : o + 40] = b"\xff" * 36  # keep the LZ4 magic, break the frame
        return d

    p = damaged(tmp_path, good, edit)
    expect_error(p, "LZ4", offset=int(layout["offsets"][k]))
    with evtk.open(p, salvage=True) as rec:
        assert rec.events() == ev[: k * PACKET]
        assert rec.damage.offset == int(layout["offsets"][k])


@pytest.mark.parametrize("code, match", [(3, "declares ZSTD compression but the body is a LZ4"),
                                         (0, "no compression but the body is a LZ4")])
def test_header_names_wrong_compression(tmp_path, good, code, match):
    def edit(d, L):
        struct.pack_into("<i", d, 14 + 32, code)
        return d

    p = damaged(tmp_path, good, edit)
    expect_error(p, match)


def test_unknown_compression_code(tmp_path, good):
    p = damaged(tmp_path, good, lambda d, L: d[:46] + struct.pack("<i", 9) + d[50:])
    expect_error(p, "unknown compression code 9")


def test_out_of_range_coordinates(tmp_path, good):
    _, ev, layout = good

    def edit(d, L):
        i = d.index(b'key="sizeX" type="int">320<')
        d[i + 23 : i + 26] = b"100"  # claim a 100-pixel wide sensor
        return d

    p = damaged(tmp_path, good, edit)
    err = expect_error(p, "outside the 100x240 sensor", offset=int(layout["offsets"][0]))
    assert err.offset == int(layout["offsets"][0])
    with evtk.open(p, salvage=True) as rec:
        assert len(rec.events()) == 0 and rec.damage is not None


def test_malformed_xml(tmp_path, good):
    def edit(d, L):
        i = d.index(b"<dv version")
        d[i : i + 3] = b"<<<"
        return d

    p = damaged(tmp_path, good, edit)
    expect_error(p, "XML is malformed")


@pytest.mark.parametrize("claimed, warning", [(5, "counts are wrong"), (2**62, "more elements than its packets can hold")])
def test_data_table_lies_about_counts(tmp_path, good, claimed, warning):
    """A wrong element count in the data table is noticed (never allocated for) and the file still reads."""
    path, ev, layout = good
    with evtk.open(path) as rec:
        dtp = rec._data_table_pos
    data = bytearray(path.read_bytes())
    import lz4.frame

    from evtk.io import _fbpy

    table = bytearray(lz4.frame.decompress(bytes(data[dtp:])))
    b = np.frombuffer(bytes(table), np.uint8)
    root = _fbpy.fb_root(b, b"FTAB")
    start, n = _fbpy.fb_vector(b, root, 0, 4)
    entry = _fbpy.fb_deref(b, start)
    f_count = _fbpy.fb_field(b, entry, 2, 8)
    struct.pack_into("<q", table, f_count, claimed)
    data = data[:dtp] + lz4.frame.compress(bytes(table))
    p = tmp_path / "lying.aedat4"
    p.write_bytes(bytes(data))
    with evtk.open(p) as rec:
        assert rec.events() == ev
        assert any(warning in w for w in rec.warnings)


def test_data_table_position_garbage_falls_back_to_walking(tmp_path, good):
    _, ev, layout = good

    def edit(d, L):
        struct.pack_into("<q", d, aedat4._DTP_FIELD, int(L["offsets"][3]))  # points into a packet
        return d

    p = damaged(tmp_path, good, edit)
    # walking stops at the claimed table position, which is inside packet 3
    expect_error(p, "claims .* bytes but only 0 remain", offset=int(layout["offsets"][3] - 8))
    with evtk.open(p, salvage=True) as rec:
        assert rec.events() == ev[: 3 * PACKET]


def test_huge_but_valid_header_is_read(tmp_path):
    ev = random_events(10, seed=3)
    p = tmp_path / "bigmeta.aedat4"
    evtk.write_events(p, ev, metadata={"blob": "x" * 5_000_000})
    with evtk.open(p) as rec:
        assert rec.events() == ev and len(rec.metadata["blob"]) == 5_000_000


def test_header_length_larger_than_file(tmp_path):
    p = tmp_path / "hlen.aedat4"
    p.write_bytes(aedat4.MAGIC + struct.pack("<I", 2**32 - 1) + b"\0" * 100)
    expect_error(p, "header claims", offset=14)


def test_missing_file_and_directory(tmp_path):
    with pytest.raises(evtk.EvtkError, match="no such file"):
        evtk.open(tmp_path / "nope.aedat4")
    with pytest.raises(evtk.EvtkError, match="directory"):
        evtk.open(tmp_path)


@pytest.mark.parametrize("seed", range(40))
def test_random_bit_flips_never_crash(tmp_path, good, seed):
    """Any flipped byte gives a correct read, a FormatError, or with salvage a prefix."""
    path, ev, layout = good
    rng = np.random.default_rng(seed)

    def edit(d, L):
        for _ in range(rng.integers(1, 4)):
            i = int(rng.integers(0, len(d)))
            d[i] ^= 1 << int(rng.integers(0, 8))
        return d

    p = damaged(tmp_path, good, edit)
    try:
        with evtk.open(p) as rec:
            rec.info()
            got = rec.events()
            rec.triggers()
            assert len(got) == len(ev)
    except evtk.FormatError as err:
        assert err.path == str(p)
    try:
        with evtk.open(p, salvage=True) as rec:
            got = rec.events()
            assert len(got) <= len(ev)
    except evtk.FormatError:
        pass  # damage in the header itself cannot be salvaged


def _outcome(path):
    """Read strictly and with salvage; any exception other than FormatError fails the test."""
    try:
        with evtk.open(path) as rec:
            rec.info()
            n = len(rec.events())
            rec.triggers()
        strict = n
    except evtk.FormatError as err:
        assert err.path == str(path) and err.reason
        strict = None
    try:
        with evtk.open(path, salvage=True) as rec:
            salvaged = len(rec.events())
            rec.triggers()
            rec.info()
    except evtk.FormatError:
        salvaged = None
    return strict, salvaged


@pytest.mark.parametrize("name", ["dvxplorer_lz4.aedat4", "dvxplorer_zstd.aedat4"])
def test_truncating_a_dv_recording_anywhere(tmp_path, fixtures_dir, name):
    """Cut a dv-processing recording at every packet boundary (and next to it):
    salvage returns exactly the events of the packets that are complete."""
    src = fixtures_dir / name
    data = src.read_bytes()
    with evtk.open(src) as rec:
        full = rec.events()
        idx = rec._index
        ev_rows = np.flatnonzero(idx.stream == 0)
        ends = {int(idx.offset[i] + idx.size[i]): int(np.sum(idx.count[ev_rows][ev_rows <= i])) for i in ev_rows}
        cuts = sorted({c + d for c in [int(o) - 8 for o in idx.offset] + list(ends) for d in (-1, 0, 1)} | {15, 17, 100})
    for cut in cuts:
        p = tmp_path / "cut.aedat4"
        p.write_bytes(data[:cut])
        strict, salvaged = _outcome(p)
        assert strict is None  # the data table lies past the end: always an error
        if cut in ends:
            assert salvaged == ends[cut]
        if salvaged:
            with evtk.open(p, salvage=True) as rec:
                assert rec.events() == full[:salvaged]


@pytest.mark.parametrize("seed", range(60))
def test_bit_flips_in_a_dv_recording(tmp_path, fixtures_dir, seed):
    src = fixtures_dir / ("dvxplorer_lz4.aedat4" if seed % 2 else "dvxplorer_zstd.aedat4")
    data = bytearray(src.read_bytes())
    rng = np.random.default_rng(1000 + seed)
    for _ in range(int(rng.integers(1, 6))):
        i = int(rng.integers(0, len(data)))
        data[i] ^= 1 << int(rng.integers(0, 8))
    p = tmp_path / "flip.aedat4"
    p.write_bytes(bytes(data))
    strict, salvaged = _outcome(p)
    if strict is not None:
        assert strict <= 4000  # an undetectable flip (a time stamp, a shorter vector) reads on


@pytest.mark.parametrize("shift", range(8))
def test_event_decoder_reads_the_vector_at_any_alignment(shift):
    """The numpy decoder views the event vector as records wherever the body lies in memory (a damaged file
    can leave it unaligned): every event exact, and the first out-of-sensor event found by its index, with the
    events before it written."""
    from evtk.io import _fb, _fbpy

    rng = np.random.default_rng(shift)
    n = 1000
    t = np.sort(rng.integers(-(2**62), 2**62, n))
    x = rng.integers(0, 320, n).astype(np.uint16)
    y = rng.integers(0, 240, n).astype(np.uint16)
    p = rng.integers(0, 2, n).astype(np.uint8)
    out = np.zeros(40 + 16 * n, np.uint8)
    _fb.encode_event_packets(t, x, y, p, np.array([0, n]), 0, out)
    body = out[8:]  # past the packet header (stream id, size)
    for bad, value, field in ((None, 0, 8), (517, 320, 8), (3, 0xFFFF, 10), (999, 240, 10)):
        b = body.copy()
        if bad is not None:  # x = 320 or y = 240 lies outside the sensor; y = -1 reads as 65535
            root = _fbpy.fb_root(b, b"EVTS")
            start, _ = _fbpy.fb_vector(b, root, 0, 16)
            b[start + 16 * bad + field:start + 16 * bad + field + 2] = np.frombuffer(np.uint16(value).tobytes(), np.uint8)
        holder = np.zeros(len(b) + 16, np.uint8)
        off = (shift - holder.ctypes.data % 8) % 8
        shifted = holder[off:off + len(b)]
        shifted[:] = b
        assert shifted.ctypes.data % 8 == shift
        cols = (np.zeros(n + 5, np.int64), np.zeros(n + 5, np.uint16), np.zeros(n + 5, np.uint16),
                np.zeros(n + 5, np.uint8))
        got = _fbpy.decode_events(shifted, b"EVTS", *cols, 5, n, 320, 240)
        assert got == ((n, _fbpy.ST_OK) if bad is None else (bad, _fbpy.ST_COORD))
        k = got[0]
        for c, ref in zip(cols, (t, x, y, p)):
            assert np.array_equal(c[5:5 + k], ref[:k]) and not c[:5].any()
    # the polarity is a bool: any byte but 0 reads as ON
    root = _fbpy.fb_root(body, b"EVTS")
    start, _ = _fbpy.fb_vector(body, root, 0, 16)
    body[start + 16 * 10 + 12] = 200
    cols = (np.zeros(n, np.int64), np.zeros(n, np.uint16), np.zeros(n, np.uint16), np.zeros(n, np.uint8))
    assert _fbpy.decode_events(body, b"EVTS", *cols, 0, n, 320, 240) == (n, _fbpy.ST_OK)
    assert cols[3][10] == 1 and np.array_equal(np.delete(cols[3], 10), np.delete(p, 10))


def test_writing_loads_no_compiler(tmp_path):
    """The FlatBuffers encoders were numba functions: writing an AEDAT4 file (events, triggers, the data table) in a
    fresh process imported numba and loaded their cached machine code, 1-1.5 s of `evtk convert F out.aedat4`.
    They are numpy now; the file reads back exactly."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    ev = random_events(30_000, seed=3, sensor_size=(346, 260))
    src = tmp_path / "src.npz"
    np.savez(src, t=ev.t, x=ev.x, y=ev.y, p=ev.p)
    out = tmp_path / "w.aedat4"
    code = ("import sys, numpy as np, evtk\n"
            f"a = np.load({str(src)!r})\n"
            "ev = evtk.Events(a['t'], a['x'], a['y'], a['p'], (346, 260))\n"
            "tr = evtk.Triggers(np.arange(0, 20_000, 7), np.ones(2858, np.uint8))\n"
            f"evtk.write_events({str(out)!r}, ev, tr, packet_events=1000)\n"
            "print('LOADED', sorted(m for m in ('numba', 'llvmlite') if m in sys.modules))\n")
    env = dict(os.environ, PYTHONPATH=str(Path(evtk.__file__).parents[1]))
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    assert res.stdout.split("LOADED", 1)[1].strip() == "[]"
    with evtk.open(out) as rec:
        back = rec.events()
        assert len(rec.triggers()) == 2858
    for a, b in zip((back.t, back.x, back.y, back.p), (ev.t, ev.x, ev.y, ev.p)):
        assert np.array_equal(a, b)


def test_reading_loads_no_compiler(tmp_path, good):
    """A fresh process spent about a second of a 20 M-event read importing numba and loading its cached
    decoders: reading an AEDAT4 file (events, windows, chunks, triggers, and a file without a data table,
    counted packet by packet) must import no numba at all."""
    import subprocess
    import sys

    path, ev, layout = good
    bare = tmp_path / "no_table.aedat4"
    data = bytearray(path.read_bytes())
    struct.pack_into("<q", data, aedat4._DTP_FIELD, -1)
    bare.write_bytes(bytes(data[:layout["dtp"]]))
    code = (
        "import sys, evtk\n"
        f"for f in ({str(path)!r}, {str(bare)!r}):\n"
        "    with evtk.open(f) as rec:\n"
        "        n = len(rec.events()) + len(rec.events(0, 50_000)) + len(rec.triggers())\n"
        "        n += sum(len(c) for c in rec.iter_events(777)) + sum(s.count or 0 for s in rec.streams)\n"
        "    print(n, 'numba' in sys.modules)\n"
    )
    import os
    from pathlib import Path

    env = dict(os.environ, PYTHONPATH=str(Path(evtk.__file__).parents[1]))  # this checkout's evtk
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env)
    lines = res.stdout.split()
    assert lines[1::2] == ["False", "False"], res.stdout
    assert int(lines[0]) == int(lines[2]) > 2 * len(ev)


def test_window_reads_find_an_out_of_order_stamp_inside_a_packet(tmp_path):
    """A packet whose middle event is stamped before the packet's first (DV's data table gives each packet's
    first and last stamp): `events(t0, t1)` and `iter_events` used to choose packets by those and miss the
    event that `events().between(t0, t1)` has. Windows must equal reading everything and filtering."""
    from evtk.io import _fb

    ev = random_events(20 * PACKET, seed=22, span_us=200_000)
    t = ev.t.copy()
    t[15 * PACKET + PACKET // 2] = 5  # in the middle of packet 15, long before its first stamp
    ev = evtk.Events(t, ev.x, ev.y, ev.p, ev.sensor_size)
    path = tmp_path / "ooo.aedat4"
    evtk.write_events(path, ev, compression="none", packet_events=PACKET, packet_us=None)
    with evtk.open(path) as rec:
        idx, dtp = rec._index, rec._data_table_pos
        cols = [idx.offset, idx.stream, idx.size, idx.count, idx.t0.copy(), idx.t1.copy()]
    cols[4][:] = ev.t[::PACKET]  # the table as DV writes it: first and last stamp of each packet
    cols[5][:] = ev.t[PACKET - 1::PACKET]
    buf = np.empty(_fb.data_table_size(len(cols[0])), np.uint8)
    size = _fb.encode_data_table(*cols, buf)
    data = bytearray(path.read_bytes())
    data[dtp:dtp + size] = buf[:size].tobytes()
    path.write_bytes(bytes(data))
    for lo, hi in [(0, 100), (0, int(ev.t[3 * PACKET])), (int(ev.t[14 * PACKET]), int(ev.t[17 * PACKET])), (3, 6)]:
        with evtk.open(path) as rec:
            want = rec.events().between(lo, hi)
            assert 5 in want.t or lo > 5
            assert rec.events(lo, hi) == want
            assert evtk.Events.concatenate(list(rec.iter_events(777, lo, hi)), sensor_size=ev.sensor_size) == want


def test_data_table_output_limits_are_each_packets_own():
    """The open checks a data table's element counts against every packet's decompression limit at once (a Python
    call a packet was a third of a 1,400-packet file's open): the same limits, for hostile sizes too."""
    from evtk.io import _compression as cz

    sizes = np.array([-2**62, -1, 0, 1, 100, 1 << 20, (1 << 26) - 1, 1 << 26, cz.MAX_PACKET_BYTES,
                      cz.MAX_PACKET_BYTES + 1, 2**40, 2**62], np.int64)
    got = cz.output_limits(sizes)
    assert got.dtype == np.int64
    assert got.tolist() == [cz.output_limit(int(z)) for z in sizes]


def test_malformed_xml_names_the_byte_of_the_fault(tmp_path, good):
    """A header whose XML closes its root with another tag: the error names the file's byte where expat found the
    mismatched end tag's name (it named the header's start, byte 14, for every XML fault)."""
    def edit(d, L):
        i = d.rindex(b"</dv>")
        d[i:i + 5] = b"</dx>"
        return d

    p = damaged(tmp_path, good, edit)
    at = p.read_bytes().rindex(b"</dx>") + 2  # the end tag's name
    expect_error(p, "XML is malformed.*mismatched tag", offset=at)


def _expat_tree(text):
    """The header XML's tree through expat itself (the reference for the plain parser)."""
    import pyexpat

    from evtk.io.aedat4 import index

    root = index._Node("", {})
    stack = [root]

    def start(tag, attrib):
        node = index._Node(tag, attrib)
        stack[-1].children.append(node)
        stack.append(node)

    def data(chunk):
        if not stack[-1].children:
            stack[-1].text += chunk

    parser = pyexpat.ParserCreate()
    parser.buffer_text = True
    parser.StartElementHandler, parser.EndElementHandler, parser.CharacterDataHandler = \
        start, lambda tag: stack.pop(), data
    parser.Parse(text, True)
    return root.children[0]


def _dump(node):
    return node.tag, node.attrib, node.text, [_dump(c) for c in node.children]


_HEADER = ('<dv version="2.0">\n    <node name="outInfo" path="/outInfo/">\n        <node name="0" path="/outInfo/0/">\n'
           '            <attr key="typeIdentifier" type="string">EVTS</attr>\n'
           "            <attr key='compression' type=\"string\">LZ4 &amp; &lt;x&gt;</attr>\n"
           '            <node name="info" path="/outInfo/0/info/">\n'
           '                <attr key="sizeX" type="int">346</attr><attr key="sizeY" type="int">260</attr>\n'
           '                <empty a="1"/>\n            </node>\n        </node>\n    </node>\n</dv>\n')
_PIECES = ["<", ">", "</", "/>", "/", "=", '"', "'", " ", "\n", "\t", "\r", "&", "amp;", "lt;", "&#65;", "&x;", "a",
           "dv", "node", "1", "-", ".", ":", "_", "<!-- c -->", "<![CDATA[x]]>", "]]>", '<?xml version="1.0"?>',
           "<!DOCTYPE dv>", "\x00", "\x01", "\u00e9", "\ufffd", "<a>", "</a>", '<a x="1">', "<dv>", "</dv>", "<a/>",
           '<b y="2"/>', 'x="1"', " y='2'", "\"'"]


def _plain_agrees_with_expat(text):
    from evtk.io.aedat4 import index

    plain = index._plain_xml_tree(text)
    try:
        want = _dump(_expat_tree(text))
    except Exception as exc:  # noqa: BLE001 - expat's ExpatError (or a ValueError for NUL bytes)
        assert plain is None, (text, exc)  # malformed: the plain parser leaves it to expat, which refuses it
        return
    assert plain is None or _dump(plain) == want, text


def test_the_plain_header_parser_gives_expat_s_tree_on_the_real_headers():
    """The str-scanning parser (no expat to load) takes every real AEDAT4 header and evtk's, giving expat's tree."""
    from pathlib import Path

    from evtk.io.aedat4 import index

    real = sorted((Path(__file__).resolve().parents[2] / "shared" / "real-files").glob("*.aedat4")) + \
        sorted((Path(__file__).resolve().parents[3] / "shared" / "real-files").glob("*.aedat4"))
    texts = [_HEADER]
    for path in real:
        with evtk.open(path) as rec:
            texts.append(rec.header_xml)
    for text in texts:
        plain = index._plain_xml_tree(text)
        assert plain is not None and _dump(plain) == _dump(_expat_tree(text))


@pytest.mark.parametrize("text", [
    "<a/><a/>", '<a x="1" x="2"/>', '<a x="1"y="2"/>', "<a></b>", "<a>t</a> x", "x<a/>", "<a>&foo;</a>", "<a>&#65;</a>",
    '<a x="<"/>', '<a x="&amp;&lt;"/>', "<a>]]></a>", "<a>\r\n</a>", "<a/ >", "< a/>", "</ a>", "<a></ a>",
    "<1a/>", "<a 1x='2'/>", "<a x='1\"/>", "<a x=1/>", "<a\x01/>", "", "  ", "<a>", "<a>\u00e9</a>",
    '<a x="t\tn\n"> <b/>c</a>', "<a:b c-d.e='f'/>", "<a><b></a></b>", '<?xml version="1.0"?><a/>'])
def test_the_plain_header_parser_on_hostile_headers(text):
    """Each fault expat refuses (a second root, a repeated attribute, no space between attributes, crossed tags,
    unknown references, a '<' in a value, ']]>' in text) gets no tree from the plain parser; what it accepts
    (named entities, whitespace in values, names with ':', '-' and '.') is expat's tree."""
    _plain_agrees_with_expat(text)


@pytest.mark.parametrize("seed", range(4))
def test_the_plain_header_parser_never_accepts_what_expat_refuses(seed):
    """Headers edited at random (pieces of XML inserted, bytes dropped or replaced) and strings of XML pieces: the
    plain parser returns a tree only where expat gives the same one, and nothing where expat refuses the text."""
    from hypothesis import given, settings
    from hypothesis import strategies as st

    edits = st.lists(st.tuples(st.integers(0, len(_HEADER)), st.integers(0, 3), st.sampled_from(_PIECES)),
                     min_size=1, max_size=3)

    @settings(max_examples=400, deadline=None, derandomize=True, database=None)
    @given(edits, st.lists(st.sampled_from(_PIECES), max_size=25))
    def check(changes, pieces):
        text = _HEADER
        for at, drop, piece in changes:
            at = (at + seed * 97) % (len(text) + 1)
            text = text[:at] + piece + text[at + drop:]
        _plain_agrees_with_expat(text)
        _plain_agrees_with_expat("".join(pieces))

    check()


def _edit_data_table(path, edit):
    """``path``'s bytes with its (LZ4) data table decompressed, changed by ``edit(table, b, start, n)`` (``start``,
    ``n``: the entry vector's first slot and length) and compressed again."""
    import lz4.frame

    from evtk.io import _fbpy

    with evtk.open(path) as rec:
        dtp = rec._data_table_pos
    data = path.read_bytes()
    table = bytearray(lz4.frame.decompress(data[dtp:]))
    b = np.frombuffer(bytes(table), np.uint8)
    start, n = _fbpy.fb_vector(b, _fbpy.fb_root(b, b"FTAB"), 0, 4)
    edit(table, b, start, n)
    return data[:dtp] + lz4.frame.compress(bytes(table))


@pytest.mark.parametrize("keep", [0, 1, 10])
def test_data_table_that_leaves_out_packets_is_not_trusted(tmp_path, good, keep):
    """A data table whose entry vector was cut short (damage to its length, found fuzzing copies of real
    recordings) listed only some packets, and the reader trusted it: their events vanished without a warning
    (0 events from a whole recording). The packets must tile the file from the header to the table; a table
    that leaves bytes out is set aside and the packets walked."""
    path, ev, layout = good

    def cut_vector(table, b, start, n):
        assert keep < n
        struct.pack_into("<I", table, start - 4, keep)

    p = tmp_path / "short_table.aedat4"
    p.write_bytes(_edit_data_table(path, cut_vector))
    with evtk.open(p) as rec:
        assert rec.events() == ev
        assert rec.events(int(ev.t[5000]), int(ev.t[6000])) == ev[5000:6000]
        assert any("leaves out" in w for w in rec.warnings)
    assert evtk.read_events(p) == ev


def test_salvaged_stream_summary_after_the_table_counts_prove_wrong(tmp_path, good):
    """Salvage on a file whose data table miscounts a packet and whose sixth packet is damaged: the events read
    (five packets) made the counts be taken again from the packets, which stopped at the damage, and
    ``streams`` then failed with numpy's IndexError (a mask of five packets on ten)."""
    path, ev, layout = good
    from evtk.io import _fbpy

    def miscount(table, b, start, n):
        entry = _fbpy.fb_deref(b, start)
        struct.pack_into("<q", table, _fbpy.fb_field(b, entry, 2, 8), PACKET - 1)

    data = bytearray(_edit_data_table(path, miscount))
    data[int(layout["offsets"][5])] ^= 0xFF  # the LZ4 magic of packet 5
    p = tmp_path / "miscount_damaged.aedat4"
    p.write_bytes(bytes(data))
    with evtk.open(p, salvage=True) as rec:
        assert rec.events() == ev[: 5 * PACKET]
        assert rec.damage is not None and rec.damage.offset == int(layout["offsets"][5])
        events = next(s for s in rec.streams if s.type == "EVTS")
        assert events.count == 5 * PACKET
        assert events.t_start_us == int(ev.t[: 5 * PACKET].min()) and events.t_end_us == int(ev.t[5 * PACKET - 1])


@pytest.mark.parametrize("stretch, per_header", [(1 << 18, 1 << 14), (64, 1 << 14), (1 << 18, 0)])
def test_data_table_that_gives_an_event_packet_to_another_stream_is_damage_not_a_short_read(tmp_path, good, monkeypatch,
                                                                                         stretch, per_header):
    """One bit of a data table's stream id (0 to 1, found fuzzing copies of the real DAVIS recordings) gave an
    event packet to the trigger stream: reading events never opened it, so its 1,000 events vanished without a
    word (dv-processing, which trusts the table too, reads as few). The table's ids are now checked against the
    headers of the packets it gives to other streams: a FormatError at the packet, or with salvage the events
    before it."""
    path, ev, layout = good
    from evtk.io import _fbpy

    # the other streams' headers read a stretch at a time, in stretches of a few headers, or one by one
    reader = sys.modules["evtk.io.aedat4.reader"]
    monkeypatch.setattr(reader, "HEADER_STRETCH_BYTES", stretch)
    monkeypatch.setattr(reader, "HEADER_READ_BYTES", per_header)
    trigger_id = int(layout["streams"][-1])
    assert trigger_id != int(layout["streams"][0])

    def relabel(table, b, start, n):
        entry = _fbpy.fb_deref(b, start + 4 * 6)  # packet 6: events
        struct.pack_into("<i", table, _fbpy.fb_field(b, entry, 1, 8), trigger_id)

    p = tmp_path / "relabelled.aedat4"
    p.write_bytes(_edit_data_table(path, relabel))
    at = int(layout["offsets"][6]) - 8
    for window in ((None, None), (int(ev.t[100]), int(ev.t[200]))):  # a window far from the packet too
        with evtk.open(p) as rec, pytest.raises(evtk.FormatError, match="the data table says stream") as info:
            rec.events(*window)
        assert info.value.offset == at and str(p) in str(info.value)
    with evtk.open(p, salvage=True) as rec:
        assert rec.events() == ev[: 6 * PACKET]
        assert rec.damage is not None and rec.damage.offset == at
        a, b = int(ev.t[100]), int(ev.t[200])
        kept = ev[: 6 * PACKET]
        assert rec.events(a, b) == kept[(kept.t >= a) & (kept.t < b)]
