"""Packet-body compression of AEDAT4 files (LZ4 frames and Zstandard frames).

Both libraries release the GIL while they work, so the reader and writer run
them on a small thread pool. The reader's threads each reuse one :class:`Scratch` for every packet they
read: the compressed body is read into it and an LZ4 body decompressed into it, so a read allocates
nothing per packet (new 100-200 KiB buffers for every packet are allocator work and page faults, which
do not run in parallel, and python-lz4 copies each body once more with the GIL held).
"""

from __future__ import annotations

import _thread  # threading itself costs a fresh read 0.6 ms; its local and Lock are these
import functools
import os
import struct
import sys
from typing import Any

import numpy as np

from .._threads import Pool, switched_off, workers

# lz4.frame, zstandard and xxhash load where first needed: an LZ4 file small enough to decode
# on one thread needs none of them (its frames go through the LZ4 library bound by ctypes, :func:`decompress_into`)

NONE, LZ4, LZ4_HIGH, ZSTD, ZSTD_HIGH = range(5)

#: Names used in the AEDAT4 header XML, indexed by the IOHeader code.
CODE_NAMES = ("NONE", "LZ4", "LZ4_HIGH", "ZSTD", "ZSTD_HIGH")
#: Names accepted by evtk's API and CLI.
BY_NAME = {"none": NONE, "lz4": LZ4, "lz4_high": LZ4_HIGH, "zstd": ZSTD, "zstd_high": ZSTD_HIGH}

_LZ4_MAGIC = b"\x04\x22\x4d\x18"
_ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"
# Largest FlatBuffer a packet can hold; nothing decompresses past it.
MAX_PACKET_BYTES = 2**31 - 1

_local = _thread._local()  # threading.local
_pool = None
_pool_size = 0
_pool_lock = _thread.allocate_lock()  # threading.Lock


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
    return not switched_off(VERIFY_ENV)


def pool() -> Pool:
    """The decode and compression threads, :func:`evtk._threads.workers` of them (made again when that changes).

    Returns
    -------
    evtk._threads.Pool
        The shared pool.
    """
    global _pool, _pool_size
    n = workers()
    with _pool_lock:
        if _pool is None or _pool_size != n:
            if _pool is not None:
                _pool.shutdown()  # what it runs finishes; new work goes to the new pool
            _pool, _pool_size = Pool(n, "evtk-io"), n
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


def output_limits(compressed_bytes: np.ndarray) -> np.ndarray:
    """:func:`output_limit` of many bodies at once (a data table's packets: a Python call each was 0.3 µs a
    packet of every open).

    Parameters
    ----------
    compressed_bytes : numpy.ndarray
        The bodies' sizes in bytes (any integers).

    Returns
    -------
    numpy.ndarray
        int64, each :func:`output_limit` of its size.
    """
    sizes = np.clip(np.asarray(compressed_bytes, np.int64), 0, MAX_PACKET_BYTES)  # past it the limit is the cap
    return np.minimum(MAX_PACKET_BYTES, BODY_FLOOR_BYTES + BODY_RATIO * sizes)


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
        import lz4.frame

        body, size = _lz4_checked(body, limit, verify)
        try:
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


def _lz4_checked(body, limit: int, verify: bool):
    """``(body, content size)`` of an LZ4 body about to be decompressed: its magic checked, its checksums left
    out when ``verify`` is off, its stated content size (0: none) within ``limit``; else :class:`CodecError`."""
    if bytes(body[:4]) != _LZ4_MAGIC:
        raise CodecError(_mismatch("LZ4", body))
    if not verify and len(body) > 6 and body[4] & _LZ4_CHECKSUMS:  # opted out: the checksums go unread
        body = lz4_without_checksums(body)
    size = _lz4_content_size(body)
    if size > limit:
        raise CodecError(f"LZ4 frame announces {size} bytes, more than the {limit} allowed")
    return body, size


def _at_least(buf: np.ndarray, n: int) -> np.ndarray:
    """``buf``, or a new uint8 buffer of at least ``n`` bytes (twice its length if more) where it is shorter."""
    return buf if len(buf) >= n else np.empty(max(n, 2 * len(buf)), np.uint8)


class Scratch:
    """Buffers one thread reuses from packet to packet: the body as read from the file (:meth:`room`) and the
    body decompressed (:func:`decompress_into`). Each grows to the largest packet met and is never shrunk;
    what it holds is valid until the next packet, so a body decoded from it must be used (copied out) first.
    Not to be shared between threads.
    """

    __slots__ = ("_raw", "_out", "_out_at", "_lz4", "_zstd", "_stage", "header_hint")

    def __init__(self) -> None:
        self._raw = np.empty(0, np.uint8)
        self._out = np.empty(0, np.uint8)
        self._out_at = 0  # the output buffer's address, for the LZ4 library
        self._lz4: _Lz4Context | None = None  # this thread's LZ4 decompression context, made on first use
        self._zstd: _ZstdContext | None = None  # this thread's libzstd context, for the compiled batches (zstd_addresses)
        self._stage = np.empty(0, np.uint8)
        #: a packet header's length in bytes, as the last packet had it (the AEDAT4 reader's batches)
        self.header_hint = 0

    def stage(self, n: int) -> np.ndarray:
        """A third buffer of at least ``n`` bytes, where several packets' bodies are laid out side by side
        (the AEDAT4 reader's batches); its contents are left from before.

        Parameters
        ----------
        n : int
            Bytes needed.

        Returns
        -------
        numpy.ndarray
            uint8, writable, at least ``n`` long.
        """
        self._stage = _at_least(self._stage, n)
        return self._stage

    def read_room(self, n: int) -> np.ndarray:
        """The whole buffer :meth:`room` reads into, grown to at least ``n`` bytes as :meth:`stage` grows (for a
        caller that reads several packets into it at once: the AEDAT4 reader's compiled range).

        Parameters
        ----------
        n : int
            The most bytes one read will put into it.

        Returns
        -------
        numpy.ndarray
            The whole buffer (uint8, writable; what it held is left).
        """
        self._raw = _at_least(self._raw, n)
        return self._raw

    def room(self, n: int) -> np.ndarray:
        """A buffer of exactly ``n`` bytes to read a packet into (its contents are left from before).

        Parameters
        ----------
        n : int
            Bytes needed.

        Returns
        -------
        numpy.ndarray
            uint8, writable, ``n`` long.
        """
        return self.read_room(n)[:n]

    def _output(self, n: int, keep: int, most: int) -> np.ndarray:
        """The output buffer, at least ``n`` bytes, its first ``keep`` bytes kept when it has to grow (to twice
        its size, at most ``most`` >= ``n`` bytes, so that packets growing a little at a time do not each
        allocate)."""
        if len(self._out) < n:
            grown = np.empty(min(most, max(n, 2 * len(self._out))), np.uint8)
            grown[:keep] = self._out[:keep]
            self._out, self._out_at = grown, grown.ctypes.data
        return self._out


def decompress_into(code: int, body, limit: int, verify: bool, scratch: Scratch) -> np.ndarray:
    """:func:`decompress`, into ``scratch`` instead of a new buffer where the codec allows.

    LZ4 bodies are decompressed by the LZ4 frame library that python-lz4 is built with, straight into the
    scratch's output buffer (the GIL released while it works, as python-lz4 does), but for bodies under
    :data:`INTO_MIN_BYTES` whose frame states its content size once ``lz4.frame`` is loaded (python-lz4's
    one call is then cheaper by 1-2 us; loading it costs a fresh process 1 ms). Where that library's
    functions cannot be reached, and for Zstandard bodies, this is :func:`decompress`. The checks, the
    limit and the errors are :func:`decompress`'s, and so are the bytes.

    Parameters
    ----------
    code : int
        The compression code.
    body : bytes-like
        The packet body as stored in the file (it may lie in ``scratch``'s read buffer).
    limit : int
        Most bytes the body may decompress to (:func:`output_limit`).
    verify : bool
        Check the checksums the frame carries (see :func:`decompress`).
    scratch : Scratch
        This thread's buffers.

    Returns
    -------
    numpy.ndarray
        The decompressed body, uint8: a view of ``body`` for :data:`NONE`, of the scratch's output buffer
        for LZ4 decompressed into it (valid until the scratch's next use), else a view of a new buffer.

    Raises
    ------
    CodecError
        As :func:`decompress`.
    """
    limit = min(int(limit), MAX_PACKET_BYTES)
    if code in (LZ4, LZ4_HIGH) and (len(body) >= INTO_MIN_BYTES or "lz4.frame" not in sys.modules
                                    or not _lz4_content_size(body)):
        lib = _lz4f()
        if lib:
            return _lz4_into(lib, body, limit, verify, scratch)
    return np.frombuffer(decompress(code, body, limit, verify), np.uint8)


#: Smallest LZ4 body :func:`decompress_into` decompresses into the scratch whatever its frame: below it, for a
#: frame that states its size, python-lz4's new buffer and copy cost less than the ctypes call (1-2 µs, once
#: ``lz4.frame`` is loaded), and the buffer is too small for glibc to map it on its own. A frame without its
#: size (DV's) costs python-lz4 as much as the ctypes call, through its streaming decompressor.
INTO_MIN_BYTES = 8 << 10


_LZ4F_VERSION = 100  # LZ4F_VERSION of lz4frame.h: the context layout every lz4 1.x agrees on
_lz4f_lib = None  # the bound LZ4 frame functions; False where they cannot be reached
_LZ4F_HINT_MAX = 1 << 62  # above it a return value may be an error code
_ctypes: Any = None  # the ctypes module, once the LZ4 library is bound


def _lz4f():
    """The LZ4 frame library python-lz4 carries (its extension module exports ``LZ4F_*``, or links the
    system's liblz4, which the lookup then finds), bound through ctypes; False when it cannot be reached."""
    global _lz4f_lib, _ctypes
    if _lz4f_lib is None:
        try:
            import ctypes

            lib = ctypes.CDLL(_lz4_frame_file())
            size_t, ptr, size_p = ctypes.c_size_t, ctypes.c_void_p, ctypes.POINTER(ctypes.c_size_t)
            lib.LZ4F_createDecompressionContext.argtypes = [ctypes.POINTER(ptr), ctypes.c_uint]
            lib.LZ4F_createDecompressionContext.restype = size_t
            lib.LZ4F_freeDecompressionContext.argtypes = [ptr]
            lib.LZ4F_freeDecompressionContext.restype = size_t
            lib.LZ4F_resetDecompressionContext.argtypes = [ptr]
            lib.LZ4F_resetDecompressionContext.restype = None
            lib.LZ4F_decompress.argtypes = [ptr, ptr, size_p, ptr, size_p, ptr]
            lib.LZ4F_decompress.restype = size_t
            lib.LZ4F_isError.argtypes = [size_t]
            lib.LZ4F_isError.restype = ctypes.c_uint
            lib.LZ4F_getErrorName.argtypes = [size_t]
            lib.LZ4F_getErrorName.restype = ctypes.c_char_p
            _lz4f_lib, _ctypes = lib, ctypes
        except (ImportError, OSError, AttributeError, TypeError):  # another build of python-lz4: decompress() serves
            _lz4f_lib = False
    return _lz4f_lib


def _lz4_frame_file() -> str:
    """The file of python-lz4's frame extension (``lz4.frame._frame``), found without importing ``lz4.frame``:
    its Python part (with ``_compression`` and the file classes) is 1 ms of a fresh process that only decodes."""
    loaded = getattr(sys.modules.get("lz4.frame._frame"), "__file__", None)
    if loaded:
        return loaded
    from importlib.machinery import PathFinder

    package = PathFinder.find_spec("lz4")
    if package is None or not package.submodule_search_locations:
        raise ImportError("lz4 is not installed")
    frame = PathFinder.find_spec("_frame", [os.path.join(d, "frame") for d in package.submodule_search_locations])
    if frame is None or not frame.origin:
        raise ImportError("lz4.frame._frame not found")
    return frame.origin


class _Lz4Context:
    """One LZ4 frame decompression context and the two size cells its calls pass, freed with the object."""

    def __init__(self, lib) -> None:
        import ctypes

        self.lib = lib
        self.ctx: Any = ctypes.c_void_p()
        err = lib.LZ4F_createDecompressionContext(ctypes.byref(self.ctx), _LZ4F_VERSION)
        if lib.LZ4F_isError(err):
            raise CodecError(f"LZ4 cannot make a decompression context ({lib.LZ4F_getErrorName(err).decode()})")
        self.dst_n, self.src_n = ctypes.c_size_t(), ctypes.c_size_t()
        self.dst_p, self.src_p = ctypes.byref(self.dst_n), ctypes.byref(self.src_n)

    def __del__(self) -> None:
        if getattr(self, "ctx", None):
            self.lib.LZ4F_freeDecompressionContext(self.ctx)
            self.ctx = None


def _context(lib, scratch: Scratch) -> _Lz4Context:
    """``scratch``'s LZ4 decompression context (made on first use)."""
    d = scratch._lz4
    if d is None or d.lib is not lib:
        d = scratch._lz4 = _Lz4Context(lib)
    return d


def _lz4_steps(lib, d: _Lz4Context, src_at: int, n: int, read: int, out_at: int, written: int,
               cap: int) -> tuple[int, int, bool]:
    """``LZ4F_decompress`` calls on the frame at ``src_at`` (``n`` bytes, ``read`` of them consumed) into
    ``out_at`` (``cap`` bytes, ``written`` of them filled) until the frame ends or a call makes no progress
    (out of room or out of input); returns ``(written, read, ended)``. A damaged frame raises
    :class:`CodecError` (the context reset)."""
    while True:
        d.dst_n.value, d.src_n.value = cap - written, n - read
        hint = lib.LZ4F_decompress(d.ctx, out_at + written, d.dst_p, src_at + read, d.src_p, None)
        if hint > _LZ4F_HINT_MAX and lib.LZ4F_isError(hint):  # errors are -code as a size_t; hints are small
            lib.LZ4F_resetDecompressionContext(d.ctx)
            name = lib.LZ4F_getErrorName(hint).decode("ascii", "replace")
            raise CodecError(_lz4_error(RuntimeError(f"LZ4F_decompress failed with code: {name}")))
        step_out, step_in = d.dst_n.value, d.src_n.value
        written += step_out
        read += step_in
        if hint == 0:  # the end mark (and content checksum) read: the frame is whole
            return written, read, True
        if not (step_out or step_in):
            return written, read, False


_lz4f_functions: tuple[int, ...] | None = None


def _addresses(lib, names: tuple[str, ...]) -> tuple[int, ...]:
    """The addresses of a ctypes library's functions ``names``, as ints (0 where one has none), for the compiled
    kernels, which call them through pointers."""
    import ctypes

    return tuple(ctypes.cast(getattr(lib, name), ctypes.c_void_p).value or 0 for name in names)


def lz4f_addresses(scratch: Scratch) -> tuple[int, int, int, int] | None:
    """The addresses of the LZ4 frame library's ``LZ4F_decompress``, ``LZ4F_isError`` and
    ``LZ4F_resetDecompressionContext`` (the library :func:`lz4_into_at` calls) and of ``scratch``'s decompression
    context, for evtk's compiled batches (:func:`evtk._native.decode_lz4_batch`); None where the library cannot be
    reached.

    Parameters
    ----------
    scratch : Scratch
        This thread's buffers (their LZ4 context, made on first use).

    Returns
    -------
    tuple of int or None
        ``(decompress, is_error, reset, context)``.
    """
    global _lz4f_functions
    lib = _lz4f_lib or _lz4f()
    if not lib:
        return None
    if _lz4f_functions is None:
        _lz4f_functions = _addresses(lib, ("LZ4F_decompress", "LZ4F_isError", "LZ4F_resetDecompressionContext"))
    ctx = _context(lib, scratch).ctx.value
    if not ctx or not all(_lz4f_functions):
        return None
    return (*_lz4f_functions, ctx)


#: The names the Zstandard library is looked for under (Linux, macOS, Windows), in order. zstandard, which evtk's
#: Python route decompresses with, carries its own copy but exports none of its functions: the compiled batches use
#: the system's library where there is one (:func:`zstd_addresses`), and the Python route everywhere else.
ZSTD_LIBRARIES = ("libzstd.so.1", "libzstd.1.dylib", "libzstd.dylib", "libzstd.dll", "zstd.dll")

#: The oldest libzstd whose frame functions the compiled batches call (1.3.0: ``ZSTD_findFrameCompressedSize`` and
#: ``ZSTD_getFrameContentSize``), as ``ZSTD_versionNumber`` gives it.
ZSTD_LEAST_VERSION = 10300

_zstd_lib: Any = None  # the bound Zstandard library; False where none can be used
_zstd_functions: tuple[int, ...] | None = None


def _zstd() -> Any:
    """The system's Zstandard library bound through ctypes (:data:`ZSTD_LIBRARIES`, at least
    :data:`ZSTD_LEAST_VERSION`); False where there is none."""
    global _zstd_lib
    if _zstd_lib is None:
        _zstd_lib = False
        try:
            import ctypes
        except ImportError:
            return _zstd_lib
        for name in ZSTD_LIBRARIES:
            try:
                lib = ctypes.CDLL(name)
                lib.ZSTD_versionNumber.restype = ctypes.c_uint
                lib.ZSTD_versionNumber.argtypes = []
                if lib.ZSTD_versionNumber() < ZSTD_LEAST_VERSION:
                    continue
                lib.ZSTD_createDCtx.restype = ctypes.c_void_p
                lib.ZSTD_createDCtx.argtypes = []
                lib.ZSTD_freeDCtx.restype = ctypes.c_size_t
                lib.ZSTD_freeDCtx.argtypes = [ctypes.c_void_p]
                for fn in ("ZSTD_decompressDCtx", "ZSTD_isError", "ZSTD_findFrameCompressedSize",
                           "ZSTD_getFrameContentSize"):
                    getattr(lib, fn)  # (each must be there)
            except (OSError, AttributeError):
                continue
            _zstd_lib = lib
            break
    return _zstd_lib


class _ZstdContext:
    """One libzstd decompression context, freed with the object."""

    def __init__(self, lib) -> None:
        self.lib = lib
        self.ctx = lib.ZSTD_createDCtx() or 0

    def __del__(self) -> None:
        if getattr(self, "ctx", 0):
            self.lib.ZSTD_freeDCtx(self.ctx)
            self.ctx = 0


def zstd_addresses(scratch: Scratch) -> tuple[int, int, int, int, int] | None:
    """The addresses of the system Zstandard library's ``ZSTD_decompressDCtx``, ``ZSTD_isError`` and
    ``ZSTD_findFrameCompressedSize``, of ``scratch``'s decompression context and of ``ZSTD_getFrameContentSize``,
    for evtk's compiled batches of Zstandard packets (:func:`evtk._native.decode_lz4_range` with codec 1); None
    where no such library can be used (:data:`ZSTD_LIBRARIES`): then the Python route decodes them.

    Parameters
    ----------
    scratch : Scratch
        This thread's buffers (their Zstandard context, made on first use).

    Returns
    -------
    tuple of int or None
        ``(decompress, is_error, frame_bytes, context, content_size)``.
    """
    global _zstd_functions
    lib = _zstd_lib or _zstd()
    if not lib:
        return None
    if _zstd_functions is None:
        _zstd_functions = _addresses(lib, ("ZSTD_decompressDCtx", "ZSTD_isError", "ZSTD_findFrameCompressedSize",
                                           "ZSTD_getFrameContentSize"))
    d = scratch._zstd
    if d is None or d.lib is not lib:
        d = scratch._zstd = _ZstdContext(lib)
    if not d.ctx or not all(_zstd_functions):
        return None
    dec, err, frame_bytes, content_size = _zstd_functions
    return dec, err, frame_bytes, d.ctx, content_size


def lz4_into_at(body, src_at: int, limit: int, verify: bool, scratch: Scratch, out_at: int, cap: int) -> int:
    """Decompress the LZ4 frame ``body`` (at address ``src_at``) to the address ``out_at``, at most ``cap``
    bytes, with the frame library python-lz4 carries (the GIL released while it works).

    The quick path of the AEDAT4 reader's batches: it reports only success. Whatever else happens (no
    library, damage, a failed checksum, a frame larger than ``cap`` or ``limit``, a stated size not met) it
    returns -1 and the caller decompresses the body again through :func:`decompress_into`, which names
    the fault.

    Parameters
    ----------
    body : bytes-like
        The LZ4 frame.
    src_at : int
        Its address (``body`` must stay alive).
    limit : int
        Most bytes the body may decompress to (:func:`output_limit`).
    verify : bool
        Check the checksums the frame carries (see :func:`decompress`).
    scratch : Scratch
        This thread's buffers (their LZ4 context).
    out_at : int
        Where the output goes: the address of writable memory of at least ``cap`` bytes.
    cap : int
        Room there.

    Returns
    -------
    int
        Bytes written, or -1.
    """
    n = len(body)
    lib = _lz4f_lib or _lz4f()
    if not lib or n < 6:  # (a frame too short for its descriptor: decompress_into names it)
        return -1
    magic, flg = _LZ4_START.unpack_from(body, 0)  # the frame's start read at once, not a numpy slice a field
    if magic != _LZ4_MAGIC:
        return -1
    if not verify and n > 6 and flg & _LZ4_CHECKSUMS:
        return -1  # the frame rebuilt without its checksums: decompress_into's route
    size = _lz4_content_size(body)
    limit = min(int(limit), MAX_PACKET_BYTES)
    if size > limit or size > cap:
        return -1
    d = _context(lib, scratch)
    room = min(cap, limit)
    # the whole frame and the room for it in one call, which a frame of one packet's body needs; else steps
    d.dst_n.value, d.src_n.value = room, n
    hint = lib.LZ4F_decompress(d.ctx, out_at, d.dst_p, src_at, d.src_p, None)
    if hint == 0:
        written, ended = d.dst_n.value, True
    elif hint > _LZ4F_HINT_MAX and lib.LZ4F_isError(hint):
        lib.LZ4F_resetDecompressionContext(d.ctx)
        return -1
    else:
        try:
            written, _, ended = _lz4_steps(lib, d, src_at, n, d.src_n.value, out_at, d.dst_n.value, room)
        except CodecError:
            return -1
    if not ended or (size > 0 and written != size):
        lib.LZ4F_resetDecompressionContext(d.ctx)
        return -1
    return written


def _lz4_into(lib, body, limit: int, verify: bool, scratch: Scratch) -> np.ndarray:
    """Decompress the LZ4 frame ``body`` into ``scratch``'s output buffer (see :func:`decompress_into`)."""
    body, size = _lz4_checked(body, limit, verify)
    try:  # the body's address: a view of the scratch's read buffer (writable) costs a fifth of numpy's route
        src_at = _ctypes.addressof(_ctypes.c_char.from_buffer(body))
        n = memoryview(body).nbytes
    except TypeError:  # read-only (bytes: the frame rebuilt without its checksums)
        src = np.frombuffer(body, np.uint8)
        src_at, n = src.ctypes.data, len(src)
    # the output buffer: the stated size exactly, else growing up to one byte past the limit (to see it passed)
    if size > 0:
        out, cap = scratch._output(size, 0, limit + 1), size
    else:
        out = scratch._output(min(limit + 1, max(2 * n, 1 << 16)), 0, limit + 1)
        cap = min(len(out), limit + 1)
    d = _context(lib, scratch)
    written, read, out_at = 0, 0, scratch._out_at
    while True:
        written, read, ended = _lz4_steps(lib, d, src_at, n, read, out_at, written, cap)
        if ended:
            break
        # no progress: out of room (more room may let output held inside lz4 out) or out of input
        if written == cap and (size == 0 or read < n):
            if size > 0:
                lib.LZ4F_resetDecompressionContext(d.ctx)
                raise CodecError(f"LZ4 frame announces {size} bytes but holds more")
            if cap > limit:
                lib.LZ4F_resetDecompressionContext(d.ctx)
                raise CodecError(f"LZ4 frame decompresses to more than {limit} bytes")
            out = scratch._output(min(limit + 1, 2 * cap), written, limit + 1)
            cap, out_at = min(len(out), limit + 1), scratch._out_at
            continue
        lib.LZ4F_resetDecompressionContext(d.ctx)
        raise CodecError("LZ4 frame ends before its end mark (truncated)")
    if written > limit:
        raise CodecError(f"LZ4 frame decompresses to more than {limit} bytes")
    if size > 0 and written != size:
        raise CodecError(f"LZ4 frame announces {size} bytes but holds {written}")
    return out[:written]


_LZ4_CHECKSUMS = 0x14  # FLG bits: block checksums (0x10), content checksum (0x04)
_LZ4_START = struct.Struct("<4sB")  # a frame's magic number and FLG byte
_LZ4_SIZE = struct.Struct("<Q")  # the content size a frame's descriptor may state (at byte 6)


def lz4_without_checksums(body):
    """The LZ4 frame ``body`` with its block and content checksums left out and its header checksum redone.

    Returns ``body`` unchanged when its block structure does not parse, so
    that the decompressor reports the damage.
    """
    flg = int(body[4])  # (a numpy uint8 would refuse the negative mask below)
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
    if "Frame incomplete" in msg:  # lz4.frame.decompress on a frame that stops short
        return "LZ4 frame ends before its end mark (truncated)"
    for code, what in (("contentChecksum", "content"), ("blockChecksum", "block"), ("headerChecksum", "header")):
        if code in msg:
            return f"LZ4 frame fails its xxHash32 {what} checksum (damaged data)"
    return f"damaged LZ4 frame ({msg})"


def _lz4_content_size(body) -> int:
    """The content size an LZ4 frame's descriptor states (0: none), read from its bytes; lz4's own frame-info
    call builds a dictionary for every packet. A damaged descriptor is left to the decompressor to refuse."""
    return _LZ4_SIZE.unpack_from(body, 6)[0] if len(body) >= 15 and body[4] & 0x08 else 0


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
        import lz4.frame

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
