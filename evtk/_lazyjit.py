"""numba's ``njit``, compiled on first call: a module whose kernels use this decorator imports numba only when one
of them is first called, so that reading a format whose decoders are numpy loads no compiler."""

from __future__ import annotations

import _thread  # threading itself costs a fresh process 0.6 ms; its RLock is this one
import functools
import sys
from collections.abc import Callable
from typing import Any

_lock = _thread.RLock()


class Deferred:
    """A function to be compiled by ``numba.njit(**options)`` when first called.

    On that call every deferred kernel the defining module holds is compiled and
    put in the module's namespace in place of its :class:`Deferred`, so that
    kernels calling each other see numba's dispatchers.

    Parameters
    ----------
    func : callable
        The Python function.
    options : dict
        ``numba.njit``'s options (``cache``, ``nogil``, ...).
    """

    def __init__(self, func: Callable, options: dict):
        self.py_func = func
        self.options = options
        self.compiled: Any = None
        functools.update_wrapper(self, func)

    def __call__(self, *args: Any) -> Any:
        if self.compiled is None:
            _compile_module(self.py_func.__module__)
        return self.compiled(*args)


def _compile_module(name: str) -> None:
    """Compile every :class:`Deferred` the module ``name`` holds and replace it there by numba's dispatcher."""
    import numba

    with _lock:
        module = sys.modules[name]
        for attr, obj in list(vars(module).items()):
            if isinstance(obj, Deferred):
                if obj.compiled is None:
                    obj.compiled = numba.njit(**obj.options)(obj.py_func)
                setattr(module, attr, obj.compiled)


def njit(**options: Any) -> Callable[[Callable], Deferred]:
    """``numba.njit(**options)``, deferred to the first call (see :class:`Deferred`).

    Parameters
    ----------
    **options
        numba's ``njit`` options.

    Returns
    -------
    callable
        The decorator.
    """

    def wrap(func: Callable) -> Deferred:
        return Deferred(func, options)

    return wrap


def numba_ready() -> bool:
    """Whether numba is already imported in this process, so that a kernel's first call costs no compiler start.

    A fresh process pays about 0.6 s for numba's import and its target's registries on the first kernel call
    (docs/performance.md, "The calibrated route in a fresh process"); a numpy path that does the same work in
    less than that is the faster choice until something else has paid it.

    Returns
    -------
    bool
        True when ``numba`` is in ``sys.modules``.
    """
    return "numba" in sys.modules
