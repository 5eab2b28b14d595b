"""One BLAS thread for evtk's small linear algebra, without finding the BLAS libraries again on every call."""

from __future__ import annotations

import threading

from threadpoolctl import ThreadpoolController

_lock = threading.Lock()
_controller = None


def one_blas_thread():
    """A context manager limiting BLAS to one thread (:mod:`threadpoolctl`).

    The reconstruction's matrices are small, and OpenBLAS's threads spin for
    a while after each call, taking a core from the next read's
    decompression (measured: 25 ms more on the next 3.8 M-event read).
    Finding the loaded libraries costs about 1 ms, so it is done once, on
    first use (after numpy and scipy.linalg have loaded theirs).
    """
    global _controller
    with _lock:
        if _controller is None:
            _controller = ThreadpoolController()
    return _controller.limit(limits=1, user_api="blas")
