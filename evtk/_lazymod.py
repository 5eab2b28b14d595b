"""A package's public names imported from their modules on first use (PEP 562), so that importing the package
loads none of its heavier modules (numba, scipy) until one of their names is asked for."""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Mapping
from typing import Any


def lazy_names(package: str, where: Mapping[str, str]) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """The module ``__getattr__`` and ``__dir__`` of a package whose names load with their modules.

    Parameters
    ----------
    package : str
        The package's ``__name__``.
    where : Mapping of str to str
        Each public name's module, relative to the package (``{"Plan": "core"}``).

    Returns
    -------
    tuple of two callables
        ``__getattr__`` (imports the name's module, keeps the name in the package, returns it; an
        ``AttributeError`` for names not in ``where``) and ``__dir__``.
    """

    def __getattr__(name: str) -> Any:
        if name not in where:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(f".{where[name]}", package), name)
        setattr(sys.modules[package], name, value)
        return value

    def __dir__() -> list[str]:
        return sorted(set(vars(sys.modules[package])) | set(where))

    return __getattr__, __dir__
