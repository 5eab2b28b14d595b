"""evtk._arrays.distinct against numpy.unique, and what it spares a fresh process."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

import evtk
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
    code = ("import sys\nimport numpy as np\nfrom evtk.events import Triggers\n"
            "tr = Triggers(np.arange(6), np.ones(6, np.uint8), np.array([2, 0, 2, 1, 0, 2]))\n"
            "assert tr.channels == [0, 1, 2]\nprint('numpy.ma' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env={"PYTHONPATH": str(Path(evtk.__file__).parents[1]), "PATH": "/usr/bin:/bin"})
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "False"


@given(hnp.arrays(np.float64, st.integers(1, 40), elements=st.floats(allow_nan=True, allow_infinity=True)))
def test_median_is_numpys(a):
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # numpy's inf - inf
        want = float(np.median(a))
    got = median(a)
    assert (np.isnan(got) and np.isnan(want)) or got == want
