"""The package's layers (issue 30, item 2): no private name crosses from one part of evtk into another.

A part is a top-level module (``evtk/bcnn.py``) or subpackage (``evtk/io/``). Inside a part, private names are
shared freely; across parts only public names are imported. ``evtk``'s own private top-level modules
(``evtk/_atomic.py``, ``evtk/_threads.py``, ...) are the library's shared internals and may be imported anywhere in it.
"""

from __future__ import annotations

import ast
from pathlib import Path

import evtk

ROOT = Path(evtk.__file__).resolve().parent


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _imports(path: Path):
    """(target module, imported name) for every ``from ... import`` in ``path``, relative ones resolved."""
    mod = _module_name(path).split(".")
    package = mod if path.name == "__init__.py" else mod[:-1]
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            for alias in node.names:
                yield target, alias.name


def _part(dotted: str) -> str:
    parts = dotted.split(".")
    return parts[1] if len(parts) > 1 else ""


def private_crossings() -> list[str]:
    found = []
    for path in sorted(ROOT.rglob("*.py")):
        here = _module_name(path)
        for target, name in _imports(path):
            if not target.startswith("evtk") or _part(target) == _part(here):
                continue
            shared = _part(target).startswith("_") and target.count(".") == 1  # evtk/_x.py
            private_module = any(p.startswith("_") for p in target.split(".")[2:])
            if (name.startswith("_") and not name.startswith("__")) or private_module or (
                _part(target).startswith("_") and not shared
            ):
                found.append(f"{here} imports {name} from {target}")
    return found


def test_the_scan_sees_relative_and_absolute_imports():
    bench = ROOT / "optics" / "bench.py"
    targets = {t for t, _ in _imports(bench)}
    assert "evtk._atomic" in targets and "evtk.errors" in targets


def test_no_private_name_crosses_parts():
    assert private_crossings() == []


def _targets(part: str) -> dict[str, set[str]]:
    """Each evtk module that the modules of ``part`` (``io``, ``reconstruct``) import, with the importers;
    ``import evtk.x`` statements and imports inside functions included."""
    found: dict[str, set[str]] = {}
    base = ROOT / part
    for path in sorted(base.rglob("*.py")) if base.is_dir() else [ROOT / f"{part}.py"]:
        here = _module_name(path)
        targets = [t for t, _ in _imports(path)]
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                targets += [a.name for a in node.names]
        for t in targets:
            if t.startswith("evtk") and _part(t) != part:
                found.setdefault(t, set()).add(here)
    return found


def test_the_target_scan_sees_imports_inside_functions():
    """The scan sees what io imports inside a function (the HDF5 reader's lazy ``evtk.limits``)."""
    assert "evtk.limits" in _targets("io")


def test_reconstruct_imports_nothing_from_the_simulator():
    """What a run is comes from evtk.plan; the reconstruction never reads the simulator's code (issue 30, item 1)."""
    wrong = {t: sorted(m) for t, m in _targets("reconstruct").items() if _part(t) == "simulate"}
    assert wrong == {}


def test_io_is_the_ground_floor():
    """io imports nothing from evtk's other parts but the errors, the memory budget, the event containers
    (``evtk.events``, which io reads into) and evtk's shared internals (``evtk/_*.py``): never the reconstruction
    or anything above it (issue 30, item 2)."""
    allowed = ("errors", "limits", "events")
    wrong = {t: sorted(m) for t, m in _targets("io").items()
             if not (_part(t) in allowed or (_part(t).startswith("_") and t.count(".") == 1))}
    assert wrong == {}


def _part_graph() -> dict[str, set[str]]:
    """Which of evtk's public parts each public part imports (at the top or inside a function)."""
    parts = sorted({p.stem if p.suffix == ".py" else p.name for p in ROOT.iterdir()
                    if (p.suffix == ".py" or (p.is_dir() and (p / "__init__.py").exists())) and not p.name.startswith("_")})
    return {part: {_part(t) for t in _targets(part)} - {part} - {p for p in parts if p.startswith("_")} for part in parts}


def test_no_import_runs_back_up():
    """The parts import one another without a cycle (issue 30, item 2): each can be read, tested and replaced
    without the ones above it. (The event container and the file formats imported each other until the Arrow
    table code moved below both, to ``evtk/_table.py``.)"""
    graph = _part_graph()
    assert graph["events"] and "io" not in graph["events"] and "events" in graph["io"]

    def reaches(start: str, goal: str) -> bool:
        seen, todo = set(), [start]
        while todo:
            for nxt in graph.get(todo.pop(), ()):
                if nxt == goal:
                    return True
                if nxt not in seen:
                    seen.add(nxt)
                    todo.append(nxt)
        return False

    cycles = sorted(f"{a} -> {b} -> ... -> {a}" for a in graph for b in graph[a] if reaches(b, a))
    assert cycles == []
