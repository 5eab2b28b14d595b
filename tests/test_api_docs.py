"""Every public callable of the library is typed and documented (issue 30, item 4).

"Public" is every function and class a non-private module of :mod:`evtk` offers (its ``__all__``, or its names
without a leading underscore that it defines itself), and every public method of those classes. The command-line
package is left out: its commands are documented by their ``--help``, which ``docs/cli.md`` renders and
``tests/test_options.py`` checks. Each callable must pass numpydoc's validator on the checks below and carry type
hints on every parameter and on its return.

``PENDING`` named the callables not yet brought up to this; it could only shrink (a test failed when one of them
passed, so the list was never stale), and it is now empty: it stays so (a callable that fails is fixed, not listed).
"""

from __future__ import annotations

import importlib
import inspect
import pkgutil

import pytest

import evtk

numpydoc_validate = pytest.importorskip("numpydoc.validate").validate

#: numpydoc's codes we enforce: a docstring exists, its summary is one line, every parameter is documented (and
#: none that does not exist), parameters have descriptions, and a callable that returns something has Returns.
CHECKS = {"GL08", "SS01", "PR01", "PR02", "PR07", "RT01", "RT03"}


def _public_modules() -> list[str]:
    names = []
    for info in pkgutil.walk_packages(evtk.__path__, "evtk."):
        parts = info.name.split(".")[1:]
        if parts[0] == "cli" or any(p.startswith("_") for p in parts):
            continue
        names.append(info.name)
    return names


def public_callables() -> list[str]:
    """Dotted names of the public functions, classes and methods, each once (where it is defined)."""
    seen: dict[str, None] = {}
    for name in _public_modules():
        module = importlib.import_module(name)
        exported = getattr(module, "__all__", None) or [n for n in vars(module) if not n.startswith("_")]
        for attr in exported:
            obj = getattr(module, attr, None)
            if not (inspect.isfunction(obj) or inspect.isclass(obj)):
                continue
            if not getattr(obj, "__module__", "").startswith("evtk."):
                continue
            if any(p.startswith("_") for p in obj.__module__.split(".")[1:]) and not getattr(module, "__all__", None):
                continue
            qual = f"{obj.__module__}.{obj.__qualname__}"
            seen[qual] = None
            if inspect.isclass(obj):
                for meth, value in vars(obj).items():
                    if not meth.startswith("_") and (inspect.isfunction(value) or isinstance(value, (classmethod, staticmethod))):
                        seen[f"{qual}.{meth}"] = None
    return list(seen)


def _resolve(dotted: str) -> object:
    parts = dotted.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj: object = importlib.import_module(".".join(parts[:i]))
        except ImportError:
            continue
        for attr in parts[i:]:
            obj = inspect.getattr_static(obj, attr) if inspect.isclass(obj) else getattr(obj, attr)
        return obj.__func__ if isinstance(obj, (classmethod, staticmethod)) else obj
    raise LookupError(dotted)


def problems(dotted: str) -> list[str]:
    """What keeps ``dotted`` from being typed and documented: numpydoc codes, and unannotated names."""
    found = [f"{code}: {msg}" for code, msg in numpydoc_validate(dotted)["errors"] if code in CHECKS]
    obj = _resolve(dotted)
    func = obj.__init__ if inspect.isclass(obj) else obj  # type: ignore[misc]
    if inspect.isclass(obj) and func is object.__init__:
        return found
    try:
        sig = inspect.signature(func)
    except (TypeError, ValueError):
        return found
    params = list(sig.parameters.values())
    if params and params[0].name in ("self", "cls"):
        params = params[1:]
    missing = [p.name for p in params if p.annotation is inspect.Parameter.empty]
    if missing:
        found.append(f"no type hint on {', '.join(missing)}")
    if not inspect.isclass(obj) and sig.return_annotation is inspect.Signature.empty:
        found.append("no return type hint")
    return found


#: Not yet typed and documented: empty since every public callable passes (issue 30); it may only shrink, so it
#: stays empty.
PENDING: set[str] = set()

ALL = public_callables()


def test_the_list_of_public_callables_is_sane():
    assert len(ALL) > 300, "the walk over evtk's modules found too few callables"
    assert "evtk.events.Events" in ALL and any(d.endswith(".read_events") for d in ALL)


@pytest.mark.parametrize("dotted", [d for d in ALL if d not in PENDING])
def test_public_callable_is_typed_and_documented(dotted):
    assert problems(dotted) == []


def test_pending_only_shrinks():
    passing = sorted(d for d in PENDING if d in ALL and not problems(d))
    assert not passing, f"these now pass; take them off PENDING: {passing}"
    gone = sorted(PENDING - set(ALL))
    assert not gone, f"these are no longer public callables; take them off PENDING: {gone}"
    assert not PENDING, f"PENDING was emptied and only shrinks: type and document these instead: {sorted(PENDING)}"
