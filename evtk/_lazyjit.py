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

    On that call every deferred kernel the defining module holds, and those of
    the modules whose kernels it imported, is compiled and put in the modules'
    namespaces in place of its :class:`Deferred`, so that kernels calling each
    other, within a module or across modules, see numba's dispatchers.

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
            _compile_module(self.py_func.__globals__, self)
        return self.compiled(*args)


def _compile_module(namespace: dict, caller: Deferred | None = None) -> None:
    """Compile every :class:`Deferred` a module holds and replace it there by numba's dispatcher.

    ``namespace`` is the module's dict (the kernels' ``__globals__``); ``caller``, the kernel being called, is
    compiled too when its module no longer holds it (a test's spy put in its place).

    A :class:`Deferred` the module imported from another one (``from ._rng import normal``) brings that module
    along, and so on (cycles allowed): every module reached gets dispatchers for all its kernels and in place
    of every :class:`Deferred` it holds, so that numba, which reads a kernel's callees from its module's
    namespace when it compiles, sees no :class:`Deferred` anywhere (and keeps options such as
    ``inline="always"``, which it reads from the callee's dispatcher). numba's ``njit`` only wraps here; the
    compiling itself happens on each kernel's first call. ``compiled`` is set last, once every namespace is
    done, so that a thread that finds it set and skips the lock never meets a :class:`Deferred`.
    """
    import numba

    with _lock:
        # the namespaces reachable through the Deferreds they hold (a kernel's globals are its module's dict)
        todo, spaces = [namespace], {}
        while todo:
            space = todo.pop()
            if id(space) in spaces:
                continue
            held = [(attr, obj) for attr, obj in space.items() if isinstance(obj, Deferred)]
            spaces[id(space)] = (space, held)
            todo.extend(obj.py_func.__globals__ for _, obj in held if obj.compiled is None)
        made: dict[int, tuple[Deferred, Any]] = {}
        for _, held in spaces.values():
            for _, obj in held:
                if obj.compiled is None and id(obj) not in made:
                    made[id(obj)] = (obj, numba.njit(**obj.options)(obj.py_func))
        if caller is not None and caller.compiled is None and id(caller) not in made:
            made[id(caller)] = (caller, numba.njit(**caller.options)(caller.py_func))
        for space, held in spaces.values():
            for attr, obj in held:
                space[attr] = obj.compiled if obj.compiled is not None else made[id(obj)][1]
        for obj, dispatcher in made.values():
            obj.compiled = dispatcher


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
