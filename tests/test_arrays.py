"""evtk._arrays.distinct against numpy.unique, and what it spares a fresh process."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import modules_after
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from evtk._arrays import distinct, median


@given(hnp.arrays(st.sampled_from([np.int64, np.uint16, np.int8, np.float64]), hnp.array_shapes(min_dims=0, max_dims=3,
                                                                                                min_side=0, max_side=9),
                  elements={"allow_nan": False}))
def test_distinct_is_numpys_unique(a):
    got, want = distinct(a), np.unique(a)
    assert got.dtype == want.dtype and np.array_equal(got, want)


def test_channels_load_no_masked_arrays():
    """Triggers.channels (every bench reconstruction asks it) went through numpy.unique, whose first call loads
    numpy.ma: 7 ms and more of a fresh process."""
    loaded = modules_after("import numpy as np\nfrom evtk.events import Triggers\n"
                           "tr = Triggers(np.arange(6), np.ones(6, np.uint8), np.array([2, 0, 2, 1, 0, 2]))\n"
                           "assert tr.channels == [0, 1, 2]\n")
    assert "numpy.ma" not in loaded


@given(hnp.arrays(np.float64, st.integers(1, 40), elements=st.floats(allow_nan=True, allow_infinity=True)))
def test_median_is_numpys(a):
    """evtk's median is numpy's, bit for bit, except where numpy's mean of the two middle values overflows to inf
    (both finite, beyond half the largest float64): there the exact midpoint, rounded once, and no warning."""
    import warnings
    from fractions import Fraction

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # numpy's inf - inf, and its overflow
        want = float(np.median(a))
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        got = median(a)
    if np.isinf(want) and np.isfinite(a).all():
        s = np.sort(a)
        lo, hi = (Fraction(float(v)) for v in s[len(a) // 2 - 1:len(a) // 2 + 1])
        assert got == float((lo + hi) / 2), (got, want)
        return
    assert (np.isnan(got) and np.isnan(want)) or got == want


@pytest.mark.parametrize("pair", [(1e308, 1e308), (-1.7e308, -1.6e308), (1.7976931348623157e308,) * 2,
                                  (9e307, 1.7976931348623157e308)])
def test_median_of_values_near_the_largest_float_is_their_midpoint(pair):
    """Two middle values whose sum leaves float64 gave inf (numpy's median does) with an overflow warning."""
    import warnings
    from fractions import Fraction

    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        got = median(np.array([np.inf, *pair, -np.inf]))  # the pair in the middle
    assert got == float((Fraction(pair[0]) + Fraction(pair[1])) / 2)
