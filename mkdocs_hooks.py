"""MkDocs hooks for evtk's site (named in ``mkdocs.yml``).

mkdocs-click prints an option's ``default`` attribute as it is. Since click 8.2
an option given no default holds click's ``UNSET`` sentinel there, and a flag's
default (False) is only resolved when the command runs, so the reference showed
``Sentinel.UNSET`` for 92 options. This hook puts the value the command really
uses in those cells: the flag's resolved default, or "none" (or "required").
"""

from __future__ import annotations

import re
from typing import Any

import click

_HEADING = re.compile(r'<h([2-6]) id="[^"]*">([^<]+)<a class="headerlink"')
_OPTION = re.compile(r"<td>(<code>-.*)</td>")
_NAME = re.compile(r"<code>([^<]*)</code>")
_UNSET = "<td><code>Sentinel.UNSET</code></td>"


def _resolved_default(command: click.Command, ctx: click.Context, opt_text: str) -> str:
    """The default ``command`` uses for the option whose name cell is ``opt_text`` (``<code>-o</code>, ...``)."""
    names = {n.strip() for code in _NAME.findall(opt_text) for n in re.split(r"[,/]", code) if n.strip()}
    for param in [*command.params, command.get_help_option(ctx)]:
        if isinstance(param, click.Option) and names & set(param.opts + param.secondary_opts):
            value = param.get_default(ctx, call=False)
            if value is None or type(value).__name__ == "Sentinel":
                return "_required_" if param.required else "none"
            return f"<code>{value}</code>"
    raise ValueError(f"the command reference names {opt_text!r}, an option {command.name!r} does not have")


def on_page_content(html: str, page: Any, **kwargs: Any) -> str:
    """Replace the ``Sentinel.UNSET`` default cells of the command reference with the defaults in force.

    Parameters
    ----------
    html : str
        The page's HTML as MkDocs rendered it.
    page : mkdocs.structure.pages.Page
        The page; only ``cli.md`` is changed.
    **kwargs
        MkDocs' other hook arguments (unused).

    Returns
    -------
    str
        The page's HTML with every default cell naming the value the command uses.
    """
    if page.file.src_uri != "cli.md" or _UNSET not in html:
        return html
    from evtk.cli import main

    stack: list[tuple[int, click.Command, click.Context]] = []
    option = ""
    out = []
    for line in html.splitlines(keepends=True):
        heading = _HEADING.search(line)
        if heading:
            level, name = int(heading.group(1)), heading.group(2).strip()
            while stack and stack[-1][0] >= level:
                stack.pop()
            if not stack:
                stack.append((level, main, click.Context(main, info_name="evtk")))
            else:
                parent, pctx = stack[-1][1], stack[-1][2]
                child = parent.commands[name] if isinstance(parent, click.Group) else None
                if child is not None:
                    stack.append((level, child, click.Context(child, parent=pctx, info_name=name)))
        found = _OPTION.search(line)
        if found:
            option = found.group(1)
        if _UNSET in line and stack:
            cell = _resolved_default(stack[-1][1], stack[-1][2], option)
            line = line.replace(_UNSET, f"<td>{cell}</td>")
        out.append(line)
    return "".join(out)
