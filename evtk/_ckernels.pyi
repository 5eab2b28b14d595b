from typing import Any

def count_windows(x: Any, y: Any, p: Any, picks: Any, use_picks: bool, first: int, at: Any, ky: Any, kx: Any,
                  on_step: int, limit: int, per_window: int, dump: int, net: bool, out: Any, width: int,
                  zero_from: int = 0, zero_to: int = 0, /) -> None: ...

def decode_lz4_batch(raw: Any, heads: Any, sids: Any, sizes: Any, counts: Any, verify: bool, decompress: int,
                     is_error: int, reset: int, ctx: int, stage: Any, floor_bytes: int, ratio: int, most: int, t: Any,
                     x: Any, y: Any, p: Any, width: int, height: int, /) -> bool: ...

def decode_lz4_range(fd: int, offs: Any, sids: Any, sizes: Any, counts: Any, starts: Any, k0: int, k1: int,
                     batch_events: int, slack: int, raw: Any, verify: bool, decompress: int, is_error: int, reset: int,
                     ctx: int, stage: Any, floor_bytes: int, ratio: int, most: int, t: Any, x: Any, y: Any, p: Any,
                     width: int, height: int, codec: int = 0, content_size: int = 0, /) -> tuple[int, int, int, int]: ...

RANGE_CODECS: int
COUNT_CLEARS: int

def evt3_run(words: Any, state: Any, width: int, height: int, decode: bool, t: Any, x: Any, y: Any, p: Any, tt: Any,
             tk: Any, tch: Any, /) -> tuple[int, int, int, int, int, int]: ...

def evt3_scan(words: Any, /) -> tuple[int, int, int, tuple[int, int, int, int, int, int, int]]: ...

def evt2_run(words: Any, state: Any, width: int, height: int, decode: bool, t: Any, x: Any, y: Any, p: Any, tt: Any,
             tk: Any, tch: Any, /) -> tuple[int, int, int, int, int, int]: ...

def dat_run(words: Any, state: Any, width: int, height: int, decode: bool, t: Any, x: Any, y: Any, p: Any,
            /) -> tuple[int, int, int, int, int, int]: ...

def evt2_scan(words: Any, /) -> tuple[int, int, int, tuple[int, int, int]]: ...

def dat_scan(words: Any, /) -> tuple[int, int, int, tuple[int, int, int]]: ...

def es_run(data: Any, state: Any, width: int, height: int, decode: bool, atis: bool, t: Any, x: Any, y: Any, p: Any,
           /) -> tuple[int, int, int, int, int, int]: ...

def net_sums(net: Any, width: int, k: int, h: int, w: int, ya: int, yb: int, fy: int, fx: int, s1: Any, s2: Any,
             blocks: Any, /) -> int: ...

def accumulate_chunk(t: Any, x: Any, y: Any, p: Any, starts: Any, ends: Any, x0: int, x1: int, y0: int, y1: int,
                     counts: Any, total: Any, started: Any, first: Any, last: Any, wa: int, wz: int, /) -> int: ...

def timing_solve(n_on: Any, first: Any, last: Any, theta: Any, band_lo: Any, band_hi: Any, out: Any, n_px: int,
                 ya: int, yb: int, theta_nominal: float, offset_us: float, log_blank: float, tau_min_us: float,
                 tau_electrons: float, refr_us: float, /) -> None: ...
