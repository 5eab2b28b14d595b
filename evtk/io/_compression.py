"""Packet-body compression of AEDAT4 files (LZ4 frames and Zstandard frames).

Both libraries release the GIL while they work, so the reader and writer run
them on a small thread pool.
"""

from __future__ import annotations

import functools
import os
import threading
from typing import TYPE_CHECKING

import lz4.frame

from .._threads import workers

if TYPE_CHECKING:
    from concurrent.futures import ThreadPoolExecutor

# zstandard, xxhash and concurrent.futures load where first needed: an LZ4 file small enough to decode on one
# thread needs none of them

NONE, LZ4, LZ4_HIGH, ZSTD, ZSTD_HIGH = range(5)

#: Names used in the AEDAT4 header XML, indexed by the IOHeader code.
CODE_NAMES = ("NONE", "LZ4", "LZ4_HIGH", "ZSTD", "ZSTD_HIGH")
#: Names accepted by evtk's API and CLI.
BY_NAME = {"none": NONE, "lz4": LZ4, "lz4_high": LZ4_HIGH, "zstd": ZSTD, "zstd_high": ZSTD_HIGH}

_LZ4_MAGIC = b"\x04\x22\x4d\x18"
_ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"
# Largest FlatBuffer a packet can hold; nothing decompresses past it.
MAX_PACKET_BYTES = 2**31 - 1

_local = threading.local()
_pool = None
_pool_size = 0
_pool_lock = threading.Lock()


#: The environment variable that turns checksum verification off (``0``); ``evtk --no-verify-checksums`` sets it.
VERIFY_ENV = "EVTK_VERIFY_CHECKSUMS"


def verify_by_default() -> bool:
    """Whether readers check the checksums a file carries when not told: yes, unless ``$EVTK_VERIFY_CHECKSUMS``
    says ``0``, ``false``, ``no`` or ``off``.

    Returns
    -------
    bool
        True to verify.
    """
    return os.environ.get(VERIFY_ENV, "").strip().lower() not in ("0", "false", "no", "off")


def pool() -> ThreadPoolExecutor:
    """The decode and compression threads, :func:`evtk._threads.workers` of them (made again when that changes).

    Returns
    -------
    concurrent.futures.ThreadPoolExecutor
        The shared pool.
    """
    global _pool, _pool_size
    n = workers()
    with _pool_lock:
        if _pool is None or _pool_size != n:
            if _pool is not None:
                _pool.shutdown(wait=False)  # what it runs finishes; new work goes to the new pool
            from concurrent.futures import ThreadPoolExecutor

            _pool, _pool_size = ThreadPoolExecutor(max_workers=n, thread_name_prefix="evtk-io"), n
        return _pool


def sniff(body) -> str | None:
    """Name the compressed format a body starts with, if any."""
    head = bytes(body[:4])
    if head == _LZ4_MAGIC:
        return "LZ4"
    if head == _ZSTD_MAGIC:
        return "ZSTD"
    return None


class CodecError(Exception):
    """A body could not be decompressed (converted to FormatError by callers)."""


#: What any packet body may decompress to, whatever its compressed size (frames of black pixels, tiny packets).
BODY_FLOOR_BYTES = 8 << 20
#: How many times its compressed size a larger body may grow. Event packets compress 2-6x; LZ4 cannot pass 255x
#: and a frame of one grey level reaches ZSTD's thousands only when it is also small, which the floor covers.
BODY_RATIO = 32
#: Bytes decompressed at a time from a frame that does not state its size.
STEP_BYTES = 4 << 20


def output_limit(compressed_bytes: int) -> int:
    """Most bytes a packet body may decompress to before it is called damaged.

    ``BODY_FLOOR_BYTES + BODY_RATIO * compressed_bytes`` (at most 2 GiB): bounded by the file's own bytes,
    never by what a frame header, a vector length or the data table claims, so memory stays within a fixed
    budget plus a small multiple of the file whatever a hostile file declares.
    """
    return min(MAX_PACKET_BYTES, BODY_FLOOR_BYTES + BODY_RATIO * max(0, int(compressed_bytes)))


def decompress(code: int, body, limit: int, verify: bool = True):
    """Decompress one packet body, refusing to produce more than ``limit`` bytes.

    Parameters
    ----------
    code : int
        The compression code (:data:`NONE`, :data:`LZ4`, :data:`LZ4_HIGH`, :data:`ZSTD`, :data:`ZSTD_HIGH`).
    body : bytes-like
        The packet body as stored in the file.
    limit : int
        Most bytes the body may decompress to (:func:`output_limit`).
    verify : bool
        Check every checksum the frame carries: an LZ4 frame's xxHash32 block and content checksums (faery
        writes both), a Zstandard frame's content checksum. lz4 and zstandard check them in C while they
        decompress, in the decode threads. ``False`` leaves LZ4 checksums out before decompressing
        (:func:`lz4_without_checksums`; Zstandard frames are checked either way); the frames' structure is
        checked and a damaged block still fails to decode, but damage a block survives goes unnoticed.

    Returns
    -------
    bytes-like
        The decompressed body (``body`` itself for :data:`NONE`).

    Raises
    ------
    CodecError
        When the frame is damaged, fails a checksum, is of another kind than ``code`` or holds more than
        ``limit`` bytes.
    """
    limit = min(int(limit), MAX_PACKET_BYTES)
    if code == NONE:
        return body
    if code in (LZ4, LZ4_HIGH):
        if bytes(body[:4]) != _LZ4_MAGIC:
            raise CodecError(_mismatch("LZ4", body))
        if not verify and len(body) > 6 and body[4] & _LZ4_CHECKSUMS:  # opted out: the checksums go unread
            body = lz4_without_checksums(body)
        try:
            size = _lz4_content_size(body)
            if size > limit:
                raise CodecError(f"LZ4 frame announces {size} bytes, more than the {limit} allowed")
            if size > 0:
                out = lz4.frame.decompress(body)
            else:  # no size in the frame header (DV, dv-processing): a step at a time, never past the limit
                d = lz4.frame.LZ4FrameDecompressor()
                parts = [d.decompress(body, max_length=STEP_BYTES)]
                total = len(parts[0])
                while not d.eof and not d.needs_input:
                    if total > limit:
                        break
                    part = d.decompress(b"", max_length=STEP_BYTES)
                    parts.append(part)
                    total += len(part)
                if total > limit:
                    raise CodecError(f"LZ4 frame decompresses to more than {limit} bytes")
                if not d.eof:
                    raise CodecError("LZ4 frame ends before its end mark (truncated)")
                out = parts[0] if len(parts) == 1 else b"".join(parts)
        except CodecError:
            raise
        except Exception as exc:  # lz4 raises RuntimeError for damaged frames
            raise CodecError(_lz4_error(exc)) from None
        if len(out) > limit:
            raise CodecError(f"LZ4 frame decompresses to more than {limit} bytes")
        if size > 0 and len(out) != size:
            raise CodecError(f"LZ4 frame announces {size} bytes but holds {len(out)}")
        return out
    if code in (ZSTD, ZSTD_HIGH):
        if bytes(body[:4]) != _ZSTD_MAGIC:
            raise CodecError(_mismatch("ZSTD", body))
        import zstandard

        dctx = getattr(_local, "dctx", None)
        if dctx is None:
            dctx = _local.dctx = zstandard.ZstdDecompressor()
        try:
            size = zstandard.frame_content_size(body)
            if size > limit:
                raise CodecError(f"ZSTD frame announces {size} bytes, more than the {limit} allowed")
            if size >= 0:
                return dctx.decompress(body)
            # no size in the frame header (dv-processing streams its frames):
            # read in bounded steps so a damaged frame cannot demand a huge buffer
            reader = dctx.stream_reader(body, read_across_frames=False)
            parts, total = [], 0
            while True:
                part = reader.read(STEP_BYTES)
                if not part:
                    break
                total += len(part)
                if total > limit:
                    raise CodecError(f"ZSTD frame decompresses to more than {limit} bytes")
                parts.append(part)
            return b"".join(parts)
        except CodecError:
            raise
        except zstandard.ZstdError as exc:
            if "checksum" in str(exc):
                raise CodecError("ZSTD frame fails its content checksum (damaged data)") from None
            raise CodecError(f"damaged ZSTD frame ({exc})") from None
    raise CodecError(f"unknown compression code {code}")


_LZ4_CHECKSUMS = 0x14  # FLG bits: block checksums (0x10), content checksum (0x04)


def lz4_without_checksums(body):
    """The LZ4 frame ``body`` with its block and content checksums left out and its header checksum redone.

    Returns ``body`` unchanged when its block structure does not parse, so
    that the decompressor reports the damage.
    """
    flg = body[4]
    desc_len = 2 + (8 if flg & 0x08 else 0) + (4 if flg & 0x01 else 0)
    pos = 4 + desc_len + 1
    block_sum = 4 if flg & 0x10 else 0
    desc = bytes([flg & ~_LZ4_CHECKSUMS]) + bytes(body[5:4 + desc_len])
    parts = [_LZ4_MAGIC, desc, _lz4_header_checksum(desc)]
    n = len(body)
    while True:
        if pos + 4 > n:
            return body
        size = int.from_bytes(body[pos:pos + 4], "little")
        if size == 0:
            break
        end = pos + 4 + (size & 0x7FFFFFFF)
        if end + block_sum > n:
            return body
        parts.append(body[pos:end])
        pos = end + block_sum
    parts.append(b"\0\0\0\0")
    return b"".join(parts)


@functools.lru_cache(maxsize=64)
def _lz4_header_checksum(desc: bytes) -> bytes:
    """The frame descriptor's check byte: the second byte of its xxHash32 (seed 0)."""
    import xxhash

    return bytes([(xxhash.xxh32_intdigest(desc) >> 8) & 0xFF])


def _lz4_error(exc: Exception) -> str:
    """What lz4's error ``exc`` says about a frame, its failed checksums named plainly."""
    msg = str(exc)
    for code, what in (("contentChecksum", "content"), ("blockChecksum", "block"), ("headerChecksum", "header")):
        if code in msg:
            return f"LZ4 frame fails its xxHash32 {what} checksum (damaged data)"
    return f"damaged LZ4 frame ({msg})"


def _lz4_content_size(body) -> int:
    """The content size an LZ4 frame's descriptor states (0: none), read from its bytes; lz4's own frame-info
    call builds a dictionary for every packet. A damaged descriptor is left to the decompressor to refuse."""
    if len(body) >= 15 and body[4] & 0x08:
        return int.from_bytes(body[6:14], "little")
    return 0


def _mismatch(declared: str, body) -> str:
    found = sniff(body)
    if found:
        return f"the header declares {declared} compression but the body is a {found} frame"
    return f"the header declares {declared} compression but the body is not a {declared} frame"


def compress(code: int, data) -> bytes:
    """Compress one packet body: LZ4 frames of 64 KiB linked blocks (level 0,
    or 9 for LZ4_HIGH) or one Zstandard frame (level 1, or 9 for ZSTD_HIGH)."""
    if code == NONE:
        return bytes(data)
    if code in (LZ4, LZ4_HIGH):
        return lz4.frame.compress(
            data,
            compression_level=0 if code == LZ4 else 9,
            block_size=lz4.frame.BLOCKSIZE_MAX64KB,
            block_linked=True,
            content_checksum=False,
            store_size=True,
        )
    if code in (ZSTD, ZSTD_HIGH):
        key = f"cctx{code}"
        cctx = getattr(_local, key, None)
        if cctx is None:
            import zstandard

            cctx = zstandard.ZstdCompressor(level=1 if code == ZSTD else 9, write_content_size=True)
            setattr(_local, key, cctx)
        return cctx.compress(data)
    raise ValueError(f"unknown compression code {code}")
