from typing import Any

def count_windows(x: Any, y: Any, p: Any, picks: Any, use_picks: bool, first: int, at: Any, ky: Any, kx: Any,
                  on_step: int, limit: int, per_window: int, dump: int, net: bool, out: Any, width: int, /) -> None: ...
