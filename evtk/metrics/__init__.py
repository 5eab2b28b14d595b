"""How good the device's numbers are: SINAD and ENOB (eq. 8), flip rates, and the Poisson factors (eqs. 9-11).

* :func:`sinad` measures the signal-to-noise-and-distortion ratio of repeated
  captures of one scene (eq. 8) and :func:`enob_bits` turns it into effective
  bits; jackknife confidence intervals over repeats have close to nominal
  coverage, and :class:`SinadAccumulator` measures more repeats than fit in
  memory.
* :func:`flip_rates` counts binarised pixels that change between repeated
  captures, pairwise and against the majority vote (the paper's Fig. 3).
* :func:`poisson_log_pmf` (eq. 9) and :func:`log_cumulative_factor` (the
  factor ``C`` of eq. 10, and ``C_low`` of eq. 11 through
  :func:`lowest_cumulative_factor`) work in log space, so photon counts from
  1e-12 to 1e12 neither underflow nor overflow.

Every statistic is float64. Degenerate input is either a defined answer
(zero noise is ``SINAD = +inf`` with ``noise_free=True``) or an
:class:`evtk.EvtkError`, never NaN.
"""

from __future__ import annotations

from .flips import FlipReport, flip_rates, flip_rates_bytes
from .poisson import (
    capture_terms,
    cumulative_factor,
    log_cumulative_factor,
    lowest_cumulative_factor,
    poisson_log_pmf,
    poisson_pmf,
)
from .sinad import MAX_BOOTSTRAP_GROUPS, SinadAccumulator, SinadReport, _bootstrap_db, enob_bits, sinad  # noqa: F401  (the tests check the bootstrap)

__all__ = [
    "SinadReport", "sinad", "SinadAccumulator", "enob_bits", "FlipReport", "flip_rates", "flip_rates_bytes",
    "poisson_log_pmf",
    "poisson_pmf", "log_cumulative_factor", "cumulative_factor", "lowest_cumulative_factor", "capture_terms",
]
