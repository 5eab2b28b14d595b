"""evtk's compiled kernels (``evtk._ckernels``) called raw, past their wrappers, with hostile arguments.

    python -m tests.fuzz.kernels --calls 100000 --seed 1

The C file promises that no argument can make a kernel read or write outside its buffers: each checks every
length, index and state itself. This calls each kernel with arguments a wrapper would never pass (columns of
other lengths, picks and window bounds outside the events, bins past the output, table sizes, LZ4 frames with
flipped bits and lying sizes, decoder states at the ends of int64, widths of any sign) and random words and
bytes. A call must return or raise ``ValueError`` / ``TypeError`` / ``OverflowError``; anything else is raised. Run under
AddressSanitizer and UBSan (``tests/fuzz/sanitized.sh``), any access outside a buffer or undefined arithmetic
stops the process with its place in ``_ckernels.c``.
"""

from __future__ import annotations

import argparse
import collections
import random
import struct
import sys

import numpy as np

REFUSED = (ValueError, TypeError, OverflowError)


def _extreme(rng: random.Random) -> int:
    """An int64 from the ends and the middle of its range, or a small one."""
    return rng.choice([0, 1, -1, 2, 7, 11, 100, 2047, 4096, 65535, 65536, 1 << 28, 1 << 31, 1 << 32, -(1 << 31),
                       1 << 39, 1 << 40, 1 << 62, -(1 << 63), (1 << 63) - 1, rng.randrange(-1000, 1000)])


class _Caller:
    """One seeded stream of hostile calls; :meth:`call` counts each outcome."""

    def __init__(self, seed: int) -> None:
        from evtk import _ckernels
        from evtk.io import _compression

        self.k = _ckernels
        self.rng = random.Random(seed)
        self.nrng = np.random.default_rng(seed)
        self.scratch = _compression.Scratch()
        self.lz4f = _compression.lz4f_addresses(self.scratch)
        # the system libzstd's functions for the range's Zstandard packets, where there is one
        self.zstd = _compression.zstd_addresses(self.scratch) if getattr(_ckernels, "RANGE_CODECS", 1) >= 2 else None
        self.outcomes: collections.Counter = collections.Counter()

    def array(self, dtype, size: int) -> np.ndarray:
        """``size`` random values of ``dtype`` (every bit pattern)."""
        raw = self.nrng.integers(0, 256, size * np.dtype(dtype).itemsize, dtype=np.uint8)
        return raw.view(dtype)

    def call(self, name: str, *args, label: str | None = None) -> None:
        try:
            getattr(self.k, name)(*args)
            self.outcomes[label or name, "returned"] += 1
        except REFUSED:
            self.outcomes[label or name, "refused"] += 1

    def state(self, size: int, ranges: list[tuple[int, int]]) -> np.ndarray:
        """A decoder's state: each value within its ``[lo, hi)``, with one or all values extreme now and then, or
        of the wrong size."""
        rng = self.rng
        state = np.array([rng.randrange(lo, hi) for lo, hi in ranges], np.int64)
        if rng.random() < 0.2:
            state[rng.randrange(size)] = _extreme(rng)
        if rng.random() < 0.05:
            state[:] = [_extreme(rng) for _ in range(size)]
        if rng.random() < 0.05:
            state = state[: rng.randrange(size)]
        return state

    def count_windows(self) -> None:
        """Arguments that fit one another (so that the counting runs), then now and then one of them not."""
        rng, nrng = self.rng, self.nrng
        n = rng.choice([0, 1, 5, 100, 1000])
        width = 2 if rng.random() < 0.5 else 4
        x, y, p = self.array(np.uint16, n), self.array(np.uint16, n), self.array(np.uint8, n)
        use_picks = rng.random() < 0.5
        picks = nrng.integers(0, max(n, 1), rng.choice([0, 3, 50, 500])).astype(np.int64) if n else \
            np.zeros(0, np.int64)
        first = rng.randrange(0, n + 1)
        most = len(picks) if use_picks else n - first
        at = np.sort(nrng.integers(0, most + 1, rng.choice([0, 1, 2, 5, 30]))).astype(np.int64)
        ky = nrng.integers(-5, 40, 65536).astype(np.int64)
        kx = nrng.integers(-5, 40, 65536).astype(np.int64)
        per_window, on_step = rng.choice([1, 5, 40, 80]), rng.choice([0, 3, 40])
        limit = rng.randrange(0, per_window + 1)
        out = np.zeros(max(len(at) - 1, 0) * per_window + 1, np.int16 if width == 2 else np.int32)
        args = [x, y, p, picks, use_picks, first, at, ky, kx, on_step, limit, per_window, len(out) - 1,
                rng.random() < 0.5, out, width]
        if rng.random() < 0.4:  # one argument that does not fit
            k = rng.choice([0, 1, 2, 3, 5, 6, 7, 9, 10, 11, 12, 14, 15])
            if k in (0, 1, 2):
                args[k] = args[k][:-1] if len(args[k]) else self.array(args[k].dtype, 1)
            elif k == 3:
                args[3] = nrng.integers(-3, n + 3, len(picks) + 1).astype(np.int64)
            elif k == 6:
                args[6] = np.sort(nrng.integers(-2, most + 5, len(at) + 1)).astype(np.int64)
            elif k == 7:
                args[7] = ky[: rng.choice([0, 100, 65535])]
            elif k == 15:
                args[15] = rng.choice([0, 1, 3, 8, -2])
            elif k == 14:
                args[14] = out[: rng.randrange(len(out) + 1)]
            else:
                args[k] = _extreme(rng)
        if rng.random() < 0.5:  # the windows to clear: among them, past them, reversed, or extreme
            n_w = max(len(at) - 1, 0)
            args += [rng.choice([0, 1, n_w, -1, _extreme(rng)]), rng.choice([0, n_w, n_w + 1, 2, _extreme(rng)])]
        self.call("count_windows", *args)

    def decode_lz4_batch(self) -> None:
        import lz4.frame

        if not self.lz4f:
            return
        rng = self.rng
        body = self.array(np.uint8, rng.choice([0, 8, 100, 4000])).tobytes()
        frame = bytearray(lz4.frame.compress(body, content_checksum=rng.random() < 0.3,
                                             store_size=rng.random() < 0.7))
        for _ in range(rng.choice([0, 0, 1, 3])):
            frame[rng.randrange(len(frame))] ^= 1 << rng.randrange(8)
        size = len(frame) if rng.random() < 0.8 else rng.choice([-1, 0, len(frame) + 1, 1 << 30])
        head = np.array([rng.choice([1, 2, -1]), size], np.int32)
        raw = np.frombuffer(head.tobytes() + bytes(frame) + bytes(rng.choice([0, 3])), np.uint8)
        heads = np.array([rng.choice([0, 0, 0, 1, -1, len(raw), _extreme(rng)])], np.int64)
        sids, sizes = np.array([head[0]], np.int64), np.array([head[1]], np.int64)
        counts = np.array([rng.choice([0, 1, 10, _extreme(rng)])], np.int64)
        m = rng.choice([0, 1, 3, 10])
        stage = np.zeros(rng.choice([0, 16, 4096, 1 << 16]), np.uint8)
        limits = [_extreme(rng) if rng.random() < 0.2 else v for v in (1024, 4, 1 << 20)]
        self.call("decode_lz4_batch", raw, heads, sids, sizes, counts, rng.random() < 0.5, *self.lz4f, stage,
                  *limits, np.zeros(m, np.int64), np.zeros(m, np.uint16), np.zeros(m, np.uint16),
                  np.zeros(m, np.uint8), rng.choice([0, 1, 640, -1, _extreme(rng)]),
                  rng.choice([0, 1, 480, -1, _extreme(rng)]))

    def decode_lz4_range(self) -> None:
        """A file of a few packets (LZ4 or Zstandard frames whole, damaged or lying about their size; Zstandard
        bodies of two frames), read through rows whose offsets, sizes, counts and starts are right or hostile, from
        a descriptor open or not, into buffers of any size."""
        import os
        import tempfile

        import lz4.frame
        import zstandard

        if not self.lz4f:
            return
        rng = self.rng
        zstd = self.zstd is not None and rng.random() < 0.5
        heads, bodies, n_ev = [], bytearray(), []
        for _ in range(rng.choice([0, 1, 2, 4])):
            n = rng.choice([0, 1, 10, 200])
            recs = self.array(np.uint8, 16 * n).reshape(n, 16).copy()
            if rng.random() < 0.8:  # coordinates on the sensor, most of the time
                recs[:, 8:12].view(np.uint16)[:] %= np.array([640, 480], np.uint16)
            # an EVTS FlatBuffer (root offset, identifier, vtable, table, the vector ending the buffer), or noise
            body = (struct.pack("<I4sHHH2xiII", 16, b"EVTS", 6, 8, 4, 8, 4, n) + recs.tobytes()
                    if rng.random() < 0.85 else self.array(np.uint8, 28 + 16 * n).tobytes())
            if zstd:
                frame = bytearray(zstandard.ZstdCompressor(write_content_size=rng.random() < 0.7,
                                                           write_checksum=rng.random() < 0.5).compress(body))
                if rng.random() < 0.1:
                    frame += zstandard.ZstdCompressor().compress(body[:rng.randrange(len(body) + 1)])
            else:
                frame = bytearray(lz4.frame.compress(body, store_size=rng.random() < 0.7))
            for _ in range(rng.choice([0, 0, 0, 1, 3])):
                frame[rng.randrange(len(frame))] ^= 1 << rng.randrange(8)
            heads.append(len(bodies) + 8)
            bodies += np.array([0, len(frame)], np.int32).tobytes() + bytes(frame)
            n_ev.append(n)
        rows = len(heads)
        with tempfile.TemporaryDirectory() as tmp:
            path = os.path.join(tmp, "packets.bin")
            with open(path, "wb") as f:
                f.write(bytes(bodies))
            fd = os.open(path, os.O_RDONLY)
            try:
                offs = np.array(heads, np.int64)
                sizes = np.array([int.from_bytes(bodies[h - 4:h], "little", signed=True) for h in heads], np.int64)
                counts = np.array(n_ev, np.int64)
                starts = np.zeros(rows + 1, np.int64)
                np.cumsum(counts, out=starts[1:])
                hostile = rng.random() < 0.5  # else only the file's bytes are damaged: the batches are decoded
                for table in (offs, sizes, counts, starts):
                    if hostile and len(table) and rng.random() < 0.15:
                        table[rng.randrange(len(table))] = _extreme(rng)
                sids = np.zeros(rows, np.int64)
                if hostile and rows and rng.random() < 0.1:
                    sids = sids[:-1]
                m = int(starts[-1]) if not hostile or (rng.random() < 0.8 and 0 <= starts[-1] < 10_000) else \
                    rng.choice([0, 5, 300])
                cols = [np.zeros(m if not hostile or rng.random() < 0.9 else m + 1, np.int64), np.zeros(m, np.uint16),
                        np.zeros(m, np.uint16), np.zeros(m, np.uint8)]
                k0, k1 = (0, rows) if not hostile or rng.random() < 0.7 else (rng.choice([0, 1, -1, 5]),
                                                                              rng.choice([0, rows, 7]))
                batch_events = rng.choice([1, 10, 1 << 16] + ([0, -1, _extreme(rng)] if hostile else []))
                slack = rng.choice([0, 1 << 16] + ([-1, _extreme(rng)] if hostile else []))
                raw = np.zeros(rng.choice([0, 8, 100, len(bodies), 1 << 16]), np.uint8)
                stage = np.zeros(rng.choice([0, 16, 4096, 1 << 18, 1 << 20]), np.uint8)
                limits = [_extreme(rng) if hostile and rng.random() < 0.2 else v for v in (1024, 4, 1 << 20)]
                sensor = (640, 480) if not hostile else (rng.choice([640, 1, 0, -1, _extreme(rng)]),
                                                         rng.choice([480, 1, 0, -1, _extreme(rng)]))
                fd_used = fd if not hostile or rng.random() < 0.8 else rng.choice([-1, 9999])
                if zstd:  # libzstd's functions in the LZ4 ones' places, then the codec and ZSTD_getFrameContentSize
                    dec, err, frame_bytes, ctx, content_size = self.zstd
                    codec = [1 if not hostile or rng.random() < 0.9 else rng.choice([2, -1]), content_size]
                    if hostile and rng.random() < 0.1:
                        codec[1] = 0
                    self.call("decode_lz4_range", fd_used, offs, sids, sizes, counts, starts, k0, k1, batch_events,
                              slack, raw, rng.random() < 0.5, dec, err, frame_bytes, ctx, stage, *limits, *cols,
                              *sensor, *codec, label="decode_lz4_range/zstd")
                else:
                    self.call("decode_lz4_range", fd_used, offs, sids, sizes, counts, starts, k0, k1, batch_events,
                              slack, raw, rng.random() < 0.5, *self.lz4f, stage, *limits, *cols, *sensor)
            finally:
                os.close(fd)

    def prophesee_run(self) -> None:
        rng, nrng = self.rng, self.nrng
        # each kernel's state: time high, time low, epoch, y, vector base x, polarity (EVT 3.0); time high, epoch
        # (EVT 2.0); last stamp, epoch (DAT)
        name, dtype, ranges = rng.choice([
            ("evt3_run", np.uint16, [(0, 4096), (0, 4096), (0, 8), (0, 2048), (0, 3000), (0, 2)]),
            ("evt2_run", np.uint32, [(0, 1 << 28), (0, 8)]), ("dat_run", np.uint32, [(-1, 1 << 32), (0, 8)])])
        words = self.array(dtype, rng.choice([0, 1, 3, 100, 5000]))
        if rng.random() < 0.5:  # words of the encoding's types, so that the decoding goes on
            kinds = [0, 2, 3, 4, 5, 6, 8, 10, 7, 14] if dtype == np.uint16 else [0, 1, 8, 10, 14, 15]
            shift, low = (12, 0xFFF) if dtype == np.uint16 else (28, 0xFFFFFFF)
            words = ((nrng.choice(kinds, len(words)).astype(dtype) << dtype(shift)) | (words & dtype(low))
                     ).astype(dtype)
        state = self.state(len(ranges), ranges)
        m = rng.choice([0, 1, 10, len(words), 12 * len(words) + 12])
        cols = [np.zeros(m if rng.random() < 0.95 else m + 1, np.int64), np.zeros(m, np.uint16),
                np.zeros(m, np.uint16), np.zeros(m, np.uint8)]
        mt = rng.choice([0, 2, len(words)])
        triggers = [np.zeros(mt, np.int64), np.zeros(mt, np.uint8),
                    np.zeros(mt if rng.random() < 0.95 else mt + 1, np.uint8)]
        sensor = [rng.choice([640, 2048, 16384, 65536]) if rng.random() < 0.8 else
                  rng.choice([0, 1, -1, _extreme(rng)]) for _ in range(2)]
        args = [words, state, *sensor, rng.random() < 0.7, *cols]
        self.call(name, *(args if name == "dat_run" else args + triggers))

    def event_stream_run(self) -> None:
        """Event Stream bytes, DVS or ATIS, from a state in range or not, into columns long enough or not."""
        rng = self.rng
        data = self.array(np.uint8, rng.choice([0, 1, 4, 5, 100, 5000]))
        state = self.state(6, [(0, 1 << 40), (0, 5), (0, 65536), (0, 65536), (0, 4), (0, 100)])
        m = len(data) // 5 + 1 if rng.random() < 0.8 else rng.choice([0, 1, len(data) // 5])
        cols = [np.zeros(m if rng.random() < 0.95 else m + 1, np.int64), np.zeros(m, np.uint16),
                np.zeros(m, np.uint16), np.zeros(m, np.uint8)]
        sensor = [rng.choice([640, 2048, 65536]) if rng.random() < 0.8 else rng.choice([0, 1, -1, _extreme(rng)])
                  for _ in range(2)]
        self.call("es_run", data, state, *sensor, rng.random() < 0.7, rng.random() < 0.5, *cols)

    def net_sums(self) -> None:
        """Frames of net counts and their sums' buffers that fit one another, then now and then one that does not."""
        rng, nrng = self.rng, self.nrng
        dtype = np.int16 if rng.random() < 0.6 else np.int32
        k, h, w = rng.choice([0, 1, 2, 3, 9]), rng.choice([1, 2, 6, 15]), rng.choice([1, 7, 8, 16, 21])
        info = np.iinfo(dtype)
        net = nrng.integers(info.min, info.max, (k, h, w), endpoint=True).astype(dtype) if rng.random() < 0.3 \
            else nrng.integers(-40, 40, (k, h, w)).astype(dtype)
        fy, fx = rng.choice([(0, 0), (1, 1), (h, w), (1, w), (3, 2), (2, 7)])
        s1, s2 = np.zeros(h * w, np.int64), np.zeros(h * w, np.int64)
        blocks = np.zeros(k * (h // fy) * (w // fx) if fy and fx else 0, np.int64)
        ya, yb = 0, h
        args = [net, net.itemsize, k, h, w, ya, yb, fy, fx, s1, s2, blocks]
        if rng.random() < 0.4:  # one argument that does not fit
            i = rng.choice([1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11])
            if i in (9, 10, 11):
                args[i] = args[i][:rng.randrange(len(args[i]) + 1)]
            elif i == 1:
                args[1] = rng.choice([0, 1, 3, 8, -2])
            else:
                args[i] = _extreme(self.rng)
        self.call("net_sums", *args)

    def misfit(self, args: list, among: int) -> None:
        """Now and then, one of the first ``among`` arguments made not to fit: an array cut short (or, empty,
        replaced by three int64s), a number from the ends of int64."""
        rng = self.rng
        if rng.random() < 0.4:
            i = rng.choice(range(among))
            if isinstance(args[i], np.ndarray):
                args[i] = args[i][:rng.randrange(len(args[i]) + 1)] if len(args[i]) else self.array(np.int64, 3)
            else:
                args[i] = _extreme(rng)

    def accumulate_chunk(self) -> None:
        """A chunk and windows that fit one another (times anywhere in int64, windows of any length, regions
        reaching past the coordinates), then now and then an argument that does not fit."""
        rng, nrng = self.rng, self.nrng
        n, n_w = rng.choice([0, 1, 5, 200]), rng.choice([0, 1, 3, 17])
        t0 = _extreme(rng)
        t = np.sort(nrng.integers(-(1 << 63), (1 << 63) - 1, n, endpoint=True)) if rng.random() < 0.3 else \
            np.sort(t0 + nrng.integers(0, 1000, n).astype(np.int64) if abs(t0) < 1 << 62 else np.full(n, t0))
        t = t.astype(np.int64)
        x, y = self.array(np.uint16, n), self.array(np.uint16, n)
        if rng.random() < 0.7:
            x, y = x % 40, y % 30
        p = self.array(np.uint8, n)
        near = [_extreme(rng) if rng.random() < 0.3 else t0 + rng.randrange(-50, 1000) for _ in range(n_w)]
        starts = np.sort(np.array([min(max(v, -(1 << 63)), (1 << 63) - 1) for v in near], np.int64))
        ends = np.array([int(s) + rng.choice([0, 1, 100, 5000]) if abs(int(s)) < 1 << 62 else s for s in starts],
                        np.int64)
        x0, y0 = rng.choice([0, 3, 39]), rng.choice([0, 2, 29])
        x1, y1 = x0 + rng.choice([1, 4, 40]), y0 + rng.choice([1, 5, 30])
        frame = (x1 - x0) * (y1 - y0)
        timed = rng.random() < 0.6
        counts = self.array(np.int32, 2 * n_w * frame)
        total, started = np.zeros(n_w, np.int64), (self.array(np.uint8, n_w) & 1).astype(np.bool_)
        first = self.array(np.int32, n_w * frame if timed else 0)
        last = self.array(np.int32, first.size)
        args = [t, x, y, p, starts, ends, x0, x1, y0, y1, counts, total, started, first, last, 0, n_w]
        self.misfit(args, len(args))
        self.call("accumulate_chunk", *args)

    def timing_solve(self) -> None:
        """Counts and times anywhere in int64, thresholds and bands of any float (NaN, inf, 0, negative), then now
        and then an argument that does not fit."""
        rng = self.rng
        rows, n_px = rng.choice([0, 1, 4]), rng.choice([1, 3, 17])
        n_on = self.array(np.int64, rows * n_px) if rng.random() < 0.3 else \
            self.nrng.integers(0, 40, rows * n_px).astype(np.int64)
        first = self.array(np.int64, rows * n_px) if rng.random() < 0.3 else \
            self.nrng.integers(-1, 500, rows * n_px).astype(np.int64)
        last = first + self.nrng.integers(-3, 9000, first.size) if rng.random() < 0.7 else \
            self.array(np.int64, first.size)
        bands = rng.choice([1, 2, 27])
        floats = [0.0, -1.0, 1e-300, 1e300, float("inf"), float("nan"), 0.2, 1.0, 100.0, 1e5]
        theta = np.array([rng.choice(floats) for _ in range(n_px)])
        lo = np.sort(self.nrng.uniform(0.0, 6.0, bands)) if rng.random() < 0.8 else self.array(np.float64, bands)
        hi = lo + 0.3
        out = np.empty(rows * n_px)
        args = [n_on, first, last, theta, lo, hi, out, n_px, 0, rows] + [rng.choice(floats) for _ in range(6)]
        self.misfit(args, 10)
        self.call("timing_solve", *args)

    def scans(self) -> None:
        for name, dtype in (("evt3_scan", np.uint16), ("evt2_scan", np.uint32), ("dat_scan", np.uint32)):
            self.call(name, self.array(dtype, self.rng.choice([0, 1, 2, 3, 999])))


def _compression_zstd():
    """The system libzstd evtk binds for the range's Zstandard packets (False where there is none)."""
    from evtk.io import _compression

    return _compression._zstd()


def run(seed: int, calls: int) -> collections.Counter:
    """``calls`` hostile calls (the kernels in turn) from ``seed``; the count of each (kernel, outcome).

    Raises whatever a kernel raises other than ``ValueError``, ``TypeError`` or ``OverflowError``.
    """
    caller = _Caller(seed)
    steps = (caller.count_windows, caller.decode_lz4_batch, caller.prophesee_run, caller.prophesee_run,
             caller.event_stream_run, caller.scans, caller.decode_lz4_range, caller.net_sums, caller.accumulate_chunk,
             caller.timing_solve)
    for i in range(calls):
        steps[i % len(steps)]()
    return caller.outcomes


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--calls", type=int, default=20000)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    outcomes = run(args.seed, args.calls)
    for (name, outcome), n in sorted(outcomes.items()):
        print(f"{name:<22}{outcome:<10}{n:>8}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
