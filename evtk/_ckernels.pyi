from typing import Any

def count_windows(x: Any, y: Any, p: Any, picks: Any, use_picks: bool, first: int, at: Any, ky: Any, kx: Any,
                  on_step: int, limit: int, per_window: int, dump: int, net: bool, out: Any, width: int, /) -> None: ...

def decode_lz4_batch(raw: Any, heads: Any, sids: Any, sizes: Any, counts: Any, verify: bool, decompress: int,
                     is_error: int, reset: int, ctx: int, stage: Any, floor_bytes: int, ratio: int, most: int, t: Any,
                     x: Any, y: Any, p: Any, width: int, height: int, /) -> bool: ...
