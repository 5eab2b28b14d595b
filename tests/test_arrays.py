"""evtk._arrays.distinct against numpy.unique, and what it spares a fresh process."""

from __future__ import annotations

import numpy as np
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
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # numpy's inf - inf
        want = float(np.median(a))
    got = median(a)
    assert (np.isnan(got) and np.isnan(want)) or got == want
