"""Opening an AEDAT4 file: the IOHeader, the data table or a walk over the packets, checked."""

from __future__ import annotations

import _thread  # the lock of _fail: threading is a module more for a fresh read to load
import os
import struct

import numpy as np

from ...errors import EvtkError, FormatError
from .. import _compression as cz
from .. import _fbpy
from ..base import Damage, StreamInfo, sensor_dims
from .common import _HEADER_START, MAGIC, _status

_DAMAGE_LOCK = _thread.allocate_lock()


def _among(values: np.ndarray, ids) -> np.ndarray:
    """Whether each of ``values`` is one of the few ``ids`` (a header's streams): ``np.isin``'s answer, one
    comparison per id (``np.isin``'s first call costs a fresh process's open 0.2-0.5 ms).

    Returns
    -------
    numpy.ndarray
        bool, shaped as ``values``.
    """
    out = np.zeros(values.shape, bool)
    for i in ids:
        out |= values == i
    return out


class _Stop(Exception):
    def __init__(self, offset, reason):
        self.offset = offset
        self.reason = reason


class _CountMismatch(Exception):
    """A packet holds another number of elements than the data table says."""


class _PacketIndex:
    """Per-packet columns: body offset and size, stream, element count, time range."""

    def __init__(self, offset, size, stream, count, t0, t1, from_table):
        self.offset = np.asarray(offset, np.int64)
        self.size = np.asarray(size, np.int64)
        self.stream = np.asarray(stream, np.int64)
        self.count = np.asarray(count, np.int64)  # -1: unknown until decoded
        self.t0 = np.asarray(t0, np.int64)
        self.t1 = np.asarray(t1, np.int64)
        self.from_table = from_table

    def __len__(self):
        return len(self.offset)

    def take(self, mask):
        return _PacketIndex(
            self.offset[mask], self.size[mask], self.stream[mask], self.count[mask], self.t0[mask], self.t1[mask],
            self.from_table,
        )


class _Node:
    """An element of the header XML: its tag, attributes, child elements and the text before the first child."""

    __slots__ = ("tag", "attrib", "children", "text")

    def __init__(self, tag: str, attrib: dict[str, str]) -> None:
        self.tag, self.attrib, self.text = tag, attrib, ""
        self.children: list[_Node] = []

    def get(self, key: str) -> str | None:
        return self.attrib.get(key)

    def findall(self, tag: str) -> list[_Node]:
        return [c for c in self.children if c.tag == tag]


def _xml_tree(text: str) -> _Node:
    """The element tree of ``text`` (expat's parse, as xml.etree's; :class:`_XmlError` when malformed).

    Headers in the plain form DV and evtk write go through :func:`_plain_xml_tree` (``str`` methods only);
    any other, or any it finds malformed, through expat, loaded then (0.5-1.5 ms of a fresh read otherwise).
    """
    tree = _plain_xml_tree(text)
    if tree is not None:
        return tree
    import pyexpat as expat  # what xml.parsers.expat re-exports, without the xml package

    root = _Node("", {})
    stack = [root]

    def start(tag, attrib):
        node = _Node(tag, attrib)
        stack[-1].children.append(node)
        stack.append(node)

    def data(chunk):
        if not stack[-1].children:  # the text before the first child, as xml.etree's ``text``
            stack[-1].text += chunk

    parser = expat.ParserCreate()
    parser.buffer_text = True
    parser.StartElementHandler, parser.EndElementHandler, parser.CharacterDataHandler = start, \
        lambda tag: stack.pop(), data
    try:
        parser.Parse(text, True)
    except expat.ExpatError as exc:
        raise _XmlError(parser.ErrorByteIndex, str(exc)) from None
    return root.children[0]


class _XmlError(Exception):
    """Malformed header XML: expat's message and the byte of the XML (UTF-8) where it found the fault."""

    def __init__(self, at: int, reason: str) -> None:
        super().__init__(reason)
        self.at, self.reason = max(0, at), reason


# ASCII control characters: XML allows none but tab, line feed and carriage return (which expat folds: expat's)
_CONTROL = bytes(c for c in range(32) if c not in (9, 10)) + b"\r"
_ENTITIES = {"lt": "<", "gt": ">", "amp": "&", "quot": '"', "apos": "'"}
_SPACE = " \t\n"


def _name_ok(name: str) -> bool:
    """An XML name in ASCII: a letter, ``_`` or ``:``, then letters, digits, ``_``, ``:``, ``-`` or ``.``."""
    return bool(name) and (name[0].isalpha() or name[0] in "_:") and \
        name.replace("_", "a").replace(":", "a").replace("-", "a").replace(".", "a").isalnum()


def _unescape(seg: str) -> str | None:
    """``seg`` with XML's five named entities replaced; None for any other reference (expat's case)."""
    if "&" not in seg:
        return seg
    parts = seg.split("&")
    out = [parts[0]]
    for part in parts[1:]:
        name, semi, rest = part.partition(";")
        if not semi or name not in _ENTITIES:
            return None
        out.append(_ENTITIES[name] + rest)
    return "".join(out)


def _plain_xml_tree(text: str) -> _Node | None:
    """The tree of ``text`` in the plain XML subset headers use, with ``str`` methods only (no expat to load).

    The subset: ASCII; elements with attributes in either quotes; text; the five named entities; whitespace
    around the root. No declaration, comment, processing instruction, CDATA, DOCTYPE, other reference or
    carriage return. Returns None for anything outside it or malformed, for expat to parse or refuse (its
    message then names the place): a tree is returned only where expat gives the same one.
    """
    if not text.isascii():
        return None
    raw = text.encode("ascii")
    if raw.translate(None, _CONTROL) != raw or "<!" in text or "<?" in text or "]]>" in text:
        return None
    pos = len(text) - len(text.lstrip(_SPACE))
    top = _Node("", {})
    stack = [top]
    find = text.find
    while True:
        lt = find("<", pos)
        if lt < 0:
            if len(stack) > 1 or not top.children or text[pos:].strip(_SPACE):
                return None  # an element left open, no element, or text after the root
            return top.children[0]
        if lt > pos:  # character data
            seg = text[pos:lt]
            node = stack[-1]
            if node is top:
                if seg.strip(_SPACE):
                    return None  # text outside the root
            elif not node.children:
                plain = _unescape(seg)
                if plain is None:
                    return None
                node.text += plain
            elif "&" in seg and _unescape(seg) is None:
                return None
        gt = find(">", lt)
        if gt < 0:
            return None
        if text[lt + 1:lt + 2] == "/":  # end tag: '</name' and optional whitespace
            name = text[lt + 2:gt].rstrip(_SPACE)
            if len(stack) < 2 or name != stack[-1].tag:
                return None
            stack.pop()
            pos = gt + 1
            continue
        if len(stack) == 1 and top.children:
            return None  # a second root
        inner = text[lt + 1:gt]
        empty = inner.endswith("/")
        if empty:
            inner = inner[:-1]
        # the name runs to the first whitespace; then ' key="value"' pairs, each after whitespace
        cut = len(inner)
        for c in _SPACE:
            k = inner.find(c)
            if 0 <= k < cut:
                cut = k
        name = inner[:cut]
        if not _name_ok(name):
            return None
        attrib: dict[str, str] = {}
        rest = inner[cut:]
        while True:
            stripped = rest.lstrip(_SPACE)
            if not stripped:
                break
            if len(stripped) == len(rest):
                return None  # no whitespace before an attribute
            key, eq, rest = stripped.partition("=")
            key = key.rstrip(_SPACE)
            rest = rest.lstrip(_SPACE)
            if not eq or not _name_ok(key) or key in attrib or not rest or rest[0] not in "\"'":
                return None
            close = rest.find(rest[0], 1)
            if close < 0:
                return None  # the value runs on (past a '>' it may hold): expat decides
            value = None if "<" in rest[1:close] else _unescape(rest[1:close])
            if value is None:
                return None
            attrib[key] = value.replace("\t", " ").replace("\n", " ")
            rest = rest[close + 1:]
        node = _Node(name, attrib)
        stack[-1].children.append(node)
        if not empty:
            stack.append(node)
        pos = gt + 1


def _parse_xml(text: str, path, offset: int = _HEADER_START) -> dict:
    """Streams described by the header XML (at byte ``offset`` of the file): ``{id: (attrs, info_attrs)}``."""
    try:
        root = _xml_tree(text)
    except _XmlError as exc:
        raise FormatError(path, offset + exc.at, f"the header's XML is malformed ({exc.reason})") from None

    def attrs(node):
        out = {}
        for a in node.findall("attr"):
            key, typ, val = a.get("key"), a.get("type"), a.text or ""
            if key is None:
                continue
            try:
                if typ in ("int", "long", "short", "byte"):
                    out[key] = int(val)
                elif typ in ("float", "double"):
                    out[key] = float(val)
                elif typ == "bool":
                    out[key] = val.strip().lower() == "true"
                else:
                    out[key] = val
            except ValueError:
                raise FormatError(path, _HEADER_START, f"header attribute {key!r} is not a valid {typ}: {val!r}") from None
        return out

    streams = {}
    outinfo, todo = None, [root]
    while todo:  # the first in document order, as xml.etree's iter (without recursion: nesting is the file's)
        node = todo.pop()
        if node.tag == "node" and node.get("name") == "outInfo":
            outinfo = node
            break
        todo.extend(reversed(node.children))
    if outinfo is None:
        raise FormatError(path, _HEADER_START, "the header's XML has no 'outInfo' node describing the streams")
    for node in outinfo.findall("node"):
        try:
            sid = int(node.get("name") or "")
        except (TypeError, ValueError):
            continue
        info = next((c for c in node.findall("node") if c.get("name") == "info"), None)
        streams[sid] = (attrs(node), attrs(info) if info is not None else {})
    return streams


class _FileIndex:
    """The reading side's file access, header and packet index, shared as a mixin by :class:`Recording`.

    Expects ``path``, ``salvage``, ``damage``, ``warnings`` and ``_fd`` on the instance.
    """

    path: str
    salvage: bool
    _size: int

    def _pread(self, n, offset):
        if self._fd < 0:
            raise EvtkError(f"{self.path}: the recording is closed")
        data = os.pread(self._fd, n, offset)
        return data

    def _fail(self, offset, reason):
        """Raise in strict mode; in salvage mode record the damage and stop."""
        if not self.salvage:
            raise FormatError(self.path, offset, reason)
        with _DAMAGE_LOCK:  # decoding threads may meet damage at once: the earliest is kept
            if self.damage is None or offset < self.damage.offset:
                self.damage = Damage(int(offset), reason)
        raise _Stop(offset, reason)

    # -- header ---------------------------------------------------------------
    def _read_header(self):
        head = self._pread(_HEADER_START + 4, 0)
        if head[: len(MAGIC)] != MAGIC:
            if head.startswith(b"#!AER-DAT"):
                version = head[9:12].decode("ascii", "replace")
                raise FormatError(self.path, 0, f"AEDAT version {version} is not supported; evtk reads AEDAT 4.0")
            raise FormatError(self.path, 0, "not an AEDAT4 file (the magic line '#!AER-DAT4.0' is missing)")
        if len(head) < _HEADER_START + 4:
            raise FormatError(self.path, _HEADER_START, "file ends inside the header (no header length)")
        (hlen,) = struct.unpack_from("<I", head, _HEADER_START)
        self._data_start = _HEADER_START + 4 + hlen
        if self._data_start > self._size:
            raise FormatError(
                self.path, _HEADER_START,
                f"the header claims {hlen} bytes but the file has only {self._size - _HEADER_START - 4} after it",
            )
        # IOHeader is stored like a plain (not size-prefixed) buffer after its length
        buf = struct.pack("<I", hlen) + self._pread(hlen, _HEADER_START + 4)
        root = _fbpy.fb_root(buf, b"IOHE")
        if root < 0:
            raise FormatError(self.path, _HEADER_START + 4, "the IOHeader FlatBuffer is damaged (" + _status(root) + ")")
        # each field's whole value must lie inside the header (a field at the table's end read past it once)
        f_comp = _fbpy.fb_field(buf, root, 0, 4)
        f_dtp = _fbpy.fb_field(buf, root, 1, 8)
        f_xml = _fbpy.fb_field(buf, root, 2, 4)
        if f_comp < 0 or f_dtp < 0 or f_xml < 0:
            raise FormatError(self.path, _HEADER_START + 4, "the IOHeader FlatBuffer has offsets outside the header")
        code = _fbpy.i32(buf, f_comp) if f_comp else 0
        if not 0 <= code < len(cz.CODE_NAMES):
            raise FormatError(self.path, _HEADER_START + f_comp, f"unknown compression code {code} in the header")
        self._code = int(code)
        self._data_table_pos = int(_fbpy.i64(buf, f_dtp)) if f_dtp else -1
        if f_xml == 0:
            raise FormatError(self.path, _HEADER_START + 4, "the header has no stream description (infoNode)")
        s = _fbpy.fb_deref(buf, f_xml)
        if s < 0:
            raise FormatError(self.path, _HEADER_START + f_xml, "the header's infoNode string lies outside the header")
        slen = _fbpy.u32(buf, s)
        if s + 4 + slen > len(buf):
            raise FormatError(self.path, _HEADER_START + s, "the header's infoNode string runs past the header")
        self.header_xml = buf[s + 4 : s + 4 + slen].decode("utf-8", "replace").rstrip("\x00")
        described = _parse_xml(self.header_xml, self.path, _HEADER_START + s + 4)
        self._streams: dict[int, StreamInfo] = {}
        for sid, (attrs, info) in sorted(described.items()):
            typ = str(attrs.get("typeIdentifier", "")).strip()
            name = str(attrs.get("originalOutputName", f"stream{sid}"))
            size = None
            if "sizeX" in info and "sizeY" in info:
                size = sensor_dims(info["sizeX"], info["sizeY"], self.path, f"the header of stream {sid}")
            elif typ == "EVTS":
                raise FormatError(self.path, _HEADER_START, f"event stream {sid} ({name}) has no sizeX/sizeY in its header")
            merged = dict(attrs)
            merged.update(info)
            self._streams[sid] = StreamInfo(sid, name, typ, sensor_size=size, attributes=merged)
        if not self._streams:
            raise FormatError(self.path, _HEADER_START, "the header describes no streams")

    # -- index ------------------------------------------------------------------
    def _build_index(self) -> _PacketIndex:
        dtp = self._data_table_pos
        if dtp >= 0:
            if dtp < self._data_start or dtp > self._size:
                if not self.salvage:
                    raise FormatError(
                        self.path, _HEADER_START,
                        f"the data table is said to start at byte {dtp}, outside the file of {self._size} bytes "
                        "(truncated file?)",
                    )
                self.damage = Damage(self._size, "file truncated: the data table lies past the end")
            else:
                table = self._read_data_table(dtp)
                if table is not None:
                    return table
        end = dtp if self._data_start <= dtp <= self._size else self._size
        return self._walk(end)

    def _read_data_table(self, dtp):
        body = self._pread(self._size - dtp, dtp)
        if not body:
            self.warnings.append("the data table is empty; packets were indexed by walking the file")
            return None
        try:
            # into a scratch buffer: as the packets are, without python-lz4's module where the packets need none
            raw = cz.decompress_into(self._code, body, cz.output_limit(len(body)), self.verify_checksums, cz.Scratch())
        except cz.CodecError as exc:
            self.warnings.append(f"the data table is unreadable ({exc}); packets were indexed by walking the file")
            return None
        cols, st = _fbpy.decode_data_table(raw, b"FTAB")
        if st != _fbpy.ST_OK:
            self.warnings.append(
                f"the data table is damaged ({_status(st)}); packets were indexed by walking the file"
            )
            return None
        offset, stream, size, count, t0, t1 = cols
        n = len(offset)
        ok = (
            (offset - 8 >= self._data_start)
            & (size >= 0)
            & (offset + size <= dtp)
            & _among(stream, self._streams)
            & (count >= 0)
        )
        if n and not ok.all():
            self.warnings.append("the data table points outside the packets; packets were indexed by walking the file")
            return None
        # an element count the packet's size cannot hold would make the reader
        # allocate for it: such a table is not trusted
        # (an event packet's body grows at most BODY_RATIO times when decompressed: the fixed allowance
        # the decompressor grants frames of pixels is no licence for event counts)
        evts = _among(stream, [sid for sid, st in self._streams.items() if st.type == "EVTS"])
        per_element = np.where(evts, _fbpy.EVENT_STRUCT, 1)
        room = np.where(evts, cz.BODY_RATIO * size + 4096, cz.output_limits(size))
        plausible = count <= room // per_element
        if n and not plausible.all():
            self.warnings.append("the data table claims more elements than its packets can hold; "
                                 "packets were indexed by walking the file")
            return None
        order = np.argsort(offset, kind="stable")
        starts, ends = offset[order] - 8, (offset + size)[order]
        if n and np.any(starts[1:] < ends[:-1]):
            self.warnings.append("the data table lists overlapping packets; packets were indexed by walking the file")
            return None
        # writers list every packet, one after the other from the header to the table: a table that leaves
        # bytes out (a vector cut short by damage, an entry moved) would drop those packets' events unseen
        if (starts[0] != self._data_start or ends[-1] != dtp or np.any(starts[1:] != ends[:-1])) if n \
                else dtp > self._data_start:
            self.warnings.append("the data table leaves out bytes between the packets; "
                                 "packets were indexed by walking the file")
            return None
        idx = _PacketIndex(offset[order], size[order], stream[order], count[order], t0[order], t1[order], True)
        return idx

    def _walk(self, end) -> _PacketIndex:
        offs, sizes, sids = [], [], []
        pos = self._data_start
        while pos < end:
            if pos + 8 > end:
                self._note(pos, f"file ends inside a packet header ({end - pos} of 8 bytes)")
                break
            sid, size = struct.unpack("<ii", self._pread(8, pos))
            if sid not in self._streams:
                self._note(pos, f"packet names stream {sid}, which the header does not describe")
                break
            if size < 0 or pos + 8 + size > end:
                self._note(pos, f"packet of stream {sid} claims {size} bytes but only {end - pos - 8} remain")
                break
            offs.append(pos + 8)
            sizes.append(size)
            sids.append(sid)
            pos += 8 + size
        n = len(offs)
        unknown = np.full(n, -1, np.int64)
        return _PacketIndex(offs, sizes, sids, unknown, np.full(n, np.iinfo(np.int64).min),
                            np.full(n, np.iinfo(np.int64).max), False)

    def _note(self, offset, reason):
        if not self.salvage:
            raise FormatError(self.path, offset, reason)
        if self.damage is None or offset < self.damage.offset:
            self.damage = Damage(int(offset), reason)
