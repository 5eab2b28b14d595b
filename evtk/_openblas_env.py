"""OpenBLAS's idle threads asked to sleep at once, before numpy loads (imported first by :mod:`evtk`).

OpenBLAS (numpy's and scipy's BLAS) starts a thread a core when it loads, and each busy-waits for work about 0.1 s
before it sleeps, at start and again after every call. evtk's own BLAS work is small matrices on one thread
(:mod:`evtk._blas`), so that spinning only takes cores from its decoding threads: 1.2-1.9 s of CPU time in every
fresh process of a 16-core machine, about 0.1 s on two (issue 32, tenth round). With ``OPENBLAS_THREAD_TIMEOUT`` at
OpenBLAS's least (2**4 cycles) the idle threads sleep at once and are woken for work as before; results and thread
counts do not change. Set only where the user has not set it and numpy has not loaded (OpenBLAS reads it once, as
it loads); child processes inherit it.
"""

import os
import sys

if "numpy" not in sys.modules:
    os.environ.setdefault("OPENBLAS_THREAD_TIMEOUT", "4")
