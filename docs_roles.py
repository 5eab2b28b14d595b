"""A griffe extension for evtk's API pages (named in ``mkdocs.yml``): Sphinx roles become cross-references.

evtk's docstrings refer to other objects as ``:func:`name```, ``:class:`~evtk.x.Y``` and so on, which reads well in
``help()`` and in an editor. mkdocstrings renders Markdown, where those roles would show as raw text. Before the
pages are rendered, this extension rewrites each role into an optional autorefs link, resolving a relative name as
Python would look it up from the docstring's place (its class, its module, the ``evtk`` package, then a unique
object of that name anywhere in ``evtk``). A name that resolves to no ``evtk`` object (``numpy.ndarray``) stays
code; a link to an object no page renders stays plain code too (the reference is optional), so nothing breaks
the strict build.
"""

from __future__ import annotations

import html
import re
from typing import Any

import griffe

_ROLE = re.compile(r":(?:py:)?(func|meth|class|data|attr|mod|obj|exc|const)?:`([^`]+)`")


def _objects(root: Any) -> dict[str, Any]:
    """Every object under ``root`` by its path (aliases left out: their targets are listed)."""
    out: dict[str, Any] = {}
    stack = [root]
    while stack:
        obj = stack.pop()
        if obj.is_alias:
            continue
        out[obj.path] = obj
        stack.extend(obj.members.values())
    return out


class RolesToRefs(griffe.Extension):
    """Rewrite Sphinx roles in every docstring of a package into optional autorefs links."""

    def on_package(self, *, pkg: Any, **kwargs: Any) -> None:  # noqa: D102 - the class says it
        objects = _objects(pkg)
        by_name: dict[str, list[str]] = {}
        for path in objects:
            by_name.setdefault(path.rsplit(".", 1)[-1], []).append(path)
        for obj in objects.values():
            if obj.docstring is not None and ":`" in obj.docstring.value:
                obj.docstring.value = _ROLE.sub(
                    lambda m, here=obj: self._link(m, here, objects, by_name, pkg.path), obj.docstring.value)

    @staticmethod
    def _link(match: re.Match, obj: Any, objects: dict[str, Any], by_name: dict[str, list[str]], top: str) -> str:
        role, text = match.group(1) or "obj", match.group(2).strip()
        explicit = re.fullmatch(r"(.*?)\s*<(.+)>", text)  # :func:`title <target>`
        title, target = (explicit.group(1), explicit.group(2)) if explicit else (None, text)
        short = target.startswith("~")
        target = target.lstrip("~.").removesuffix("()")
        if title is None:
            title = target.rsplit(".", 1)[-1] if short else target
            if role in ("func", "meth"):
                title += "()"
        scopes = []
        node = obj
        while node is not None:
            scopes.append(node.path)
            node = node.parent
        candidates = [f"{s}.{target}" for s in scopes] + [target, f"{top}.{target}"]
        found = next((c for c in candidates if c in objects), None)
        if found is None:
            unique = by_name.get(target.rsplit(".", 1)[-1], [])
            found = next((p for p in unique if p.endswith("." + target)), None) if len(unique) == 1 else None
        code = f"<code>{html.escape(title)}</code>"
        if found is None:
            return code
        return f'<autoref identifier="{found}" optional>{code}</autoref>'
