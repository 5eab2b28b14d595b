"""Recovering a Parquet file whose footer was never written.

A Parquet writer keeps the file metadata (schema, row-group directory,
key-value metadata) in memory and writes it as the footer when it closes, so
a writer killed mid-write leaves ``PAR1`` followed by complete column chunks
and then a torn one, with no footer.  Every page still starts with its own
header (Thrift compact protocol), so the chunks can be found by walking the
page headers from the start of the file.  This module does that walk, groups
the pages into evtk's columns (``t`` int64, ``x``, ``y`` uint16, ``p``
uint8, in that order), and writes a new footer for the complete row groups.
:class:`evtk.io._overlay.SplicedFile` presents the intact prefix plus that
footer to pyarrow as one read-only file, so pyarrow decodes the pages.

What the lost footer held besides the directory (sensor size, evtk metadata,
triggers in its key-value metadata) cannot be recovered.
"""

from __future__ import annotations

import os
import struct

__all__ = ["find_row_groups", "encode_footer", "rebuild_footer", "ThriftError", "read_struct"]

MAGIC = b"PAR1"

# Thrift compact protocol element types
_STOP, _TRUE, _FALSE, _I8, _I16, _I32, _I64, _DOUBLE, _BINARY, _LIST, _SET, _MAP, _STRUCT = range(13)
_MAX_DEPTH = 24

# parquet.thrift enums (the ones used here)
_DATA_PAGE, _INDEX_PAGE, _DICTIONARY_PAGE, _DATA_PAGE_V2 = 0, 1, 2, 3
_INT32, _INT64 = 1, 2
REQUIRED, OPTIONAL = 0, 1
_UINT_8, _UINT_16 = 11, 12
# codec enum value -> pyarrow codec name; tried in this order on the first page
_CODECS = [(7, "lz4_raw"), (6, "zstd"), (1, "snappy"), (2, "gzip"), (4, "brotli"), (5, "lz4")]
# evtk's columns: name, physical type, converted type
COLUMNS = [("t", _INT64, None), ("x", _INT32, _UINT_16), ("y", _INT32, _UINT_16), ("p", _INT32, _UINT_8)]


class ThriftError(ValueError):
    """Bytes that do not decode as the Thrift compact protocol."""


# -- decoding -----------------------------------------------------------------
class _Reader:
    def __init__(self, data: bytes, pos: int = 0):
        self.data = data
        self.pos = pos

    def byte(self) -> int:
        if self.pos >= len(self.data):
            raise ThriftError("ends inside a value")
        b = self.data[self.pos]
        self.pos += 1
        return b

    def varint(self) -> int:
        out = shift = 0
        while True:
            b = self.byte()
            out |= (b & 0x7F) << shift
            if not b & 0x80:
                return out
            shift += 7
            if shift > 63:
                raise ThriftError("varint longer than 64 bits")

    def zigzag(self) -> int:
        v = self.varint()
        return (v >> 1) ^ -(v & 1)

    def take(self, n: int) -> bytes:
        if n < 0 or self.pos + n > len(self.data):
            raise ThriftError("a length runs past the end")
        out = self.data[self.pos : self.pos + n]
        self.pos += n
        return out

    def value(self, kind: int, depth: int):
        if depth > _MAX_DEPTH:
            raise ThriftError("nested too deeply")
        if kind in (_TRUE, _FALSE):  # only inside lists: one byte
            return self.byte() == 1
        if kind == _I8:
            v = self.byte()
            return v - 256 if v > 127 else v
        if kind in (_I16, _I32, _I64):
            return self.zigzag()
        if kind == _DOUBLE:
            return struct.unpack("<d", self.take(8))[0]
        if kind == _BINARY:
            return self.take(self.varint())
        if kind in (_LIST, _SET):
            head = self.byte()
            size, elem = head >> 4, head & 0x0F
            if size == 15:
                size = self.varint()
            if size > len(self.data) - self.pos:  # every element takes at least a byte
                raise ThriftError("a list longer than its bytes")
            return [self.value(elem, depth + 1) for _ in range(size)]
        if kind == _MAP:
            size = self.varint()
            if size == 0:
                return {}
            if 2 * size > len(self.data) - self.pos:
                raise ThriftError("a map longer than its bytes")
            types = self.byte()
            return {self._key(self.value(types >> 4, depth + 1)): self.value(types & 0x0F, depth + 1) for _ in range(size)}
        if kind == _STRUCT:
            return self.struct(depth + 1)
        raise ThriftError(f"unknown element type {kind}")

    @staticmethod
    def _key(k):
        return tuple(k) if isinstance(k, list) else (tuple(sorted(k.items())) if isinstance(k, dict) else k)

    def struct(self, depth: int = 0) -> dict:
        out: dict = {}
        last = 0
        while True:
            head = self.byte()
            kind = head & 0x0F
            if kind == _STOP:
                return out
            delta = head >> 4
            fid = last + delta if delta else self.zigzag()
            if kind == _TRUE:
                out[fid] = True
            elif kind == _FALSE:
                out[fid] = False
            else:
                out[fid] = self.value(kind, depth)
            last = fid


def read_struct(data: bytes, pos: int = 0):
    """One Thrift compact struct from ``data[pos:]``: ({field id: value}, end position)."""
    r = _Reader(data, pos)
    return r.struct(), r.pos


# -- encoding -----------------------------------------------------------------
def _varint(v: int) -> bytes:
    out = bytearray()
    while True:
        b = v & 0x7F
        v >>= 7
        if v:
            out.append(b | 0x80)
        else:
            out.append(b)
            return bytes(out)


def _zigzag(v: int) -> bytes:
    return _varint((v << 1) ^ (v >> 63))


class _Writer:
    """Just what a Parquet footer needs: i32/i64/binary fields, structs and lists of them."""

    def __init__(self):
        self.out = bytearray()
        self._last = [0]

    def _field(self, fid: int, kind: int):
        delta = fid - self._last[-1]
        if 0 < delta <= 15:
            self.out.append((delta << 4) | kind)
        else:
            self.out.append(kind)
            self.out += _zigzag(fid)
        self._last[-1] = fid

    def i32(self, fid, v):
        self._field(fid, _I32)
        self.out += _zigzag(int(v))

    def i64(self, fid, v):
        self._field(fid, _I64)
        self.out += _zigzag(int(v))

    def binary(self, fid, v):
        v = v.encode() if isinstance(v, str) else bytes(v)
        self._field(fid, _BINARY)
        self.out += _varint(len(v)) + v

    def _list_head(self, fid, kind, n):
        self._field(fid, _LIST)
        self.out.append((n << 4) | kind if n < 15 else 0xF0 | kind)
        if n >= 15:
            self.out += _varint(n)

    def i32_list(self, fid, values):
        self._list_head(fid, _I32, len(values))
        for v in values:
            self.out += _zigzag(int(v))

    def binary_list(self, fid, values):
        self._list_head(fid, _BINARY, len(values))
        for v in values:
            v = v.encode() if isinstance(v, str) else bytes(v)
            self.out += _varint(len(v)) + v

    def struct_list(self, fid, items, fill):
        """A list of structs, each written by ``fill(writer, item)``."""
        self._list_head(fid, _STRUCT, len(items))
        for item in items:
            self._begin()
            fill(self, item)
            self._end()

    def struct(self, fid, fill):
        self._field(fid, _STRUCT)
        self._begin()
        fill(self)
        self._end()

    def _begin(self):
        self._last.append(0)

    def _end(self):
        self.out.append(_STOP)
        self._last.pop()

    def finish(self) -> bytes:
        self.out.append(_STOP)
        return bytes(self.out)


# -- walking the pages ----------------------------------------------------------
class _Page:
    __slots__ = ("offset", "end", "kind", "values", "compressed", "uncompressed", "encodings", "low", "high")

    def __init__(self, offset, end, kind, values, compressed, uncompressed, encodings, low=None, high=None):
        self.offset, self.end, self.kind, self.values = offset, end, kind, values
        self.compressed, self.uncompressed, self.encodings = compressed, uncompressed, encodings
        self.low, self.high = low, high  # the page's min and max statistics (plain-encoded), when it has them

    @property
    def stored_uncompressed(self):
        """Header plus uncompressed body: what a footer's uncompressed sizes add up."""
        return self.uncompressed + (self.end - self.compressed - self.offset)


def _pages(f, size: int):
    """The complete pages from byte 4 on, stopping at the first that does not parse or is cut short."""
    pos = len(MAGIC)
    window = 1 << 12
    while pos < size:
        f.seek(pos)
        data = f.read(min(window, size - pos))
        try:
            head, used = read_struct(data)
        except ThriftError:
            if len(data) == size - pos or window >= 1 << 20:
                return
            window *= 4  # a header longer than the window (large statistics): read more
            continue
        window = 1 << 12
        page = _page(head, pos, used, size)
        if page is None:
            return
        yield page
        pos = page.end


def _page(head, pos, header_len, size):
    kind = head.get(1)
    uncompressed, compressed = head.get(2), head.get(3)
    if not all(isinstance(v, int) for v in (kind, uncompressed, compressed)) or compressed < 0 or uncompressed < 0:
        return None
    end = pos + header_len + compressed
    if end > size:
        return None
    low = high = None
    if kind == _DICTIONARY_PAGE:
        sub = head.get(7)
        values, encodings = (sub.get(1), [sub.get(2)]) if isinstance(sub, dict) else (None, [])
    elif kind == _DATA_PAGE:
        sub = head.get(5)
        values, encodings = (sub.get(1), [sub.get(2), sub.get(3), sub.get(4)]) if isinstance(sub, dict) else (None, [])
        stats = sub.get(5) if isinstance(sub, dict) else None
        if isinstance(stats, dict) and isinstance(stats.get(6), bytes) and isinstance(stats.get(5), bytes):
            low, high = stats[6], stats[5]
    elif kind == _DATA_PAGE_V2:
        sub = head.get(8)
        values, encodings = (sub.get(1), [sub.get(4), 3]) if isinstance(sub, dict) else (None, [])
    else:
        return None
    if not isinstance(values, int) or values < 0 or not all(isinstance(e, int) for e in encodings if e is not None):
        return None
    return _Page(pos, end, kind, values, compressed, uncompressed, [e for e in encodings if e is not None], low, high)


def _chunks(pages):
    """Split the pages into column chunks, each starting at a dictionary page."""
    chunks, current = [], []
    for page in pages:
        if page.kind == _DICTIONARY_PAGE and current:
            chunks.append(current)
            current = []
        current.append(page)
    if current:
        chunks.append(current)
    return chunks


def _values(chunk):
    return sum(p.values for p in chunk if p.kind != _DICTIONARY_PAGE)


def _codec(f, pages):
    """The codec that turns the first page it can into exactly its uncompressed size; 0 (none) when every page
    is stored at its uncompressed size and no codec applies; None when a page matches no codec."""
    import pyarrow as pa

    for page in pages:
        if not page.uncompressed:
            continue
        f.seek(page.end - page.compressed)
        body = f.read(page.compressed)
        for number, name in _CODECS:
            if not pa.Codec.is_available(name):
                continue
            try:
                out = pa.decompress(body, decompressed_size=page.uncompressed, codec=name)
            except Exception:  # noqa: BLE001 - any failure means: not this codec
                continue
            if len(out) == page.uncompressed:
                return number
        if page.compressed != page.uncompressed:
            return None
    return 0


def find_row_groups(path):
    """The complete row groups of a footerless evtk Parquet file, from its page headers.

    Returns ``(end, groups, codec)``: the byte offset where the intact row
    groups end, a list of ``(rows, column chunks)`` (empty when not even one
    is complete) and the codec number.  Raises :class:`ThriftError` when the
    file does not start with ``PAR1`` or its pages use a codec pyarrow does
    not have.

    Every column chunk must start with a dictionary page (pyarrow's default,
    kept by evtk's writer), which is how the chunks are told apart.
    """
    with open(path, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        if f.read(4) != MAGIC:
            raise ThriftError("the file does not start with PAR1")
        pages = list(_pages(f, size))
        chunks = _chunks(pages)
        groups = []
        ncol = len(COLUMNS)
        for g in range(len(chunks) // ncol):
            cols = chunks[g * ncol : (g + 1) * ncol]
            if any(c[0].kind != _DICTIONARY_PAGE for c in cols):
                break
            rows = _values(cols[0])
            if rows == 0 or any(_values(c) != rows for c in cols):
                break
            groups.append((rows, cols))
        codec = _codec(f, [p for c in groups[0][1] for p in c]) if groups else 0
        if codec is None:
            raise ThriftError("the pages are compressed with no codec pyarrow knows")
    end = groups[-1][1][-1][-1].end if groups else len(MAGIC)
    return end, groups, codec


def encode_footer(groups, codec, repetition=OPTIONAL) -> bytes:
    """The footer (Thrift metadata, its length, the closing magic) for :func:`find_row_groups`' result, its
    columns declared with ``repetition`` (:data:`OPTIONAL`: nullable, as pyarrow writes by default)."""
    ncol = len(COLUMNS)
    rows = sum(r for r, _ in groups)
    w = _Writer()
    w.i32(1, 1)  # format version

    def schema_root(s):
        s.binary(4, "schema")
        s.i32(5, ncol)

    def schema_column(s, col):
        name, physical, converted = col
        s.i32(1, physical)
        s.i32(3, repetition)
        s.binary(4, name)
        if converted is not None:
            s.i32(6, converted)

    def element(s, item):
        if item is None:
            schema_root(s)
        else:
            schema_column(s, item)

    w.struct_list(2, [None] + COLUMNS, element)
    w.i64(3, rows)

    def column_chunk(s, item):
        (name, physical, _), pages = item
        first = pages[0].offset
        data = next((p for p in pages if p.kind != _DICTIONARY_PAGE), pages[0])
        compressed = pages[-1].end - first
        uncompressed = sum(p.stored_uncompressed for p in pages)
        encodings = sorted({e for p in pages for e in p.encodings})

        def meta(m):
            m.i32(1, physical)
            m.i32_list(2, encodings)
            m.binary_list(3, [name])
            m.i32(4, codec)
            m.i64(5, _values(pages))
            m.i64(6, uncompressed)
            m.i64(7, compressed)
            m.i64(9, data.offset)
            if pages[0].kind == _DICTIONARY_PAGE:
                m.i64(11, first)
            lows = [p.low for p in pages if p.kind != _DICTIONARY_PAGE]
            highs = [p.high for p in pages if p.kind != _DICTIONARY_PAGE]
            width = 8 if physical == _INT64 else 4
            if lows and all(v is not None and len(v) == width for v in lows + highs):
                fmt = "<q" if physical == _INT64 else "<i"
                low = min(struct.unpack(fmt, v)[0] for v in lows)
                high = max(struct.unpack(fmt, v)[0] for v in highs)

                def stats(st):  # min and max, plain-encoded (the page headers' own values)
                    st.binary(5, struct.pack(fmt, high))
                    st.binary(6, struct.pack(fmt, low))

                m.struct(12, stats)

        s.i64(2, first)
        s.struct(3, meta)

    def row_group(s, item):
        rows_g, cols = item
        s.struct_list(1, list(zip(COLUMNS, cols)), column_chunk)
        s.i64(2, sum(p.stored_uncompressed for c in cols for p in c))
        s.i64(3, rows_g)

    w.struct_list(4, groups, row_group)
    w.binary(6, "evtk footer recovery")
    # type-defined sort order for every column: without it readers ignore min_value/max_value
    w.struct_list(7, COLUMNS, lambda s, _col: s.struct(1, lambda _order: None))
    meta = w.finish()
    return meta + struct.pack("<I", len(meta)) + MAGIC


def rebuild_footer(path, repetition=OPTIONAL):
    """``(end, footer, rows, row groups)`` for a footerless evtk Parquet file: where its intact row groups end,
    the footer to place there, and what it holds."""
    end, groups, codec = find_row_groups(path)
    return end, encode_footer(groups, codec, repetition), sum(r for r, _ in groups), len(groups)
