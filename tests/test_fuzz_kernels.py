"""A seeded slice of tests/fuzz/kernels.py: evtk's compiled kernels called raw with hostile arguments.

Each call must return or refuse (ValueError, TypeError, OverflowError); a crash ends the test process. Under
AddressSanitizer and UBSan (``bash tests/fuzz/sanitized.sh``) the same calls also stop at any access outside a
buffer or any undefined arithmetic, which a plain build may not show.
"""

from __future__ import annotations

import pytest
from fuzz import kernels

from evtk import _native

KERNELS = ("count_windows", "decode_lz4_batch", "decode_lz4_range", "evt3_run", "evt2_run", "dat_run", "es_run", "evt3_scan",
           "evt2_scan", "dat_scan", "net_sums", "accumulate_chunk", "timing_solve")


@pytest.mark.parametrize("seed", [5, 6])
def test_every_raw_kernel_runs_or_refuses_hostile_arguments(seed):
    if not _native.BUILT or _native._kernel_evt3_run is None:
        pytest.skip("evtk's compiled kernels were not built (no C compiler at install)")
    outcomes = kernels.run(seed, 3000)
    zstd = _native.RANGE_ZSTD and bool(kernels._compression_zstd())
    for name in KERNELS + (("decode_lz4_range/zstd",) if zstd else ()):
        # both outcomes met: the arguments reach the kernels' work, and their refusals (the scans refuse nothing)
        assert outcomes[name, "returned"] > 20, (name, dict(outcomes))
        if not name.endswith("_scan"):
            assert outcomes[name, "refused"] > 20, (name, dict(outcomes))
