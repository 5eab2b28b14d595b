"""The documentation's Python snippets run as written, in order, page by page (README's too)."""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PAGES = ["README.md", "docs/getting-started.md", "docs/guide.md", "docs/formats/foreign.md"]
#: pages whose shell commands and Python snippets run together, in page order, each on the files the page made
WALKTHROUGHS = ["docs/walkthrough-simulated.md", "docs/walkthrough-bench.md"]


def _blocks(page):
    return re.findall(r"```python\n(.*?)```", (ROOT / page).read_text(), re.S)


@pytest.mark.parametrize("page", PAGES)
def test_snippets_run_as_written(page, tmp_path, monkeypatch):
    """Each page's snippets share one namespace and a fresh working directory. The guide's first snippet reads
    the reader's own files (``recording.aedat4``, a DSEC file, a Prophesee RAW file), which are made here by
    evtk's simulator, h5py (DSEC's layout) and faery (EVT 2.0)."""
    import evtk
    from evtk.simulate import Simulation

    blocks = _blocks(page)
    assert blocks, f"{page} has no Python snippets"
    monkeypatch.chdir(tmp_path)
    Simulation([[1, 0], [0, 1]], [[1, 0, 1], [0, 1, 0], [1, 0, 1]], repeat=2).write("recording.aedat4")
    ev = evtk.read_events("recording.aedat4")
    if page == "docs/guide.md":
        from test_hdf5_parquet import make_dsec

        make_dsec(tmp_path / "dsec_events.h5", evtk.Events(ev.t, ev.x, ev.y, ev.p, (640, 480)), 0)
        faery = pytest.importorskip("faery")
        from test_prophesee import _faery_write

        assert faery
        _faery_write(tmp_path / "camera.raw", ev, "evt2")
    namespace = {"__name__": "__docs__"}
    for i, code in enumerate(blocks):
        exec(compile(code, f"{page} (snippet {i + 1})", "exec"), namespace)


def _page_blocks(page):
    """The page's ``bash`` and ``python`` blocks in page order, as (language, code); a block right after an
    ``<!-- not run: ... -->`` comment, and shell lines that install packages, are left out."""
    text = (ROOT / page).read_text()
    out = []
    for m in re.finditer(r"(<!-- not run[^>]*-->\s*)?```(bash|python)\n(.*?)```", text, re.S):
        if m.group(1):
            continue
        code = m.group(3)
        if m.group(2) == "bash":
            code = "\n".join(line for line in code.splitlines() if "pip install" not in line)
        out.append((m.group(2), code))
    return out


@pytest.mark.parametrize("page", WALKTHROUGHS)
def test_walkthrough_runs_in_page_order(page, tmp_path, monkeypatch):
    """A walkthrough's shell commands (with ``evtk`` as installed beside this Python) and Python snippets run one
    after another in one fresh directory, as a reader following the page would: each step reads only the files
    the page's earlier steps wrote. A step that fails names the page and the block."""
    import os
    import subprocess
    import sys

    blocks = _page_blocks(page)
    assert any(lang == "bash" for lang, _ in blocks), f"{page} has no shell commands"
    monkeypatch.chdir(tmp_path)
    env = dict(os.environ, PATH=os.path.dirname(sys.executable) + os.pathsep + os.environ.get("PATH", ""),
               MPLBACKEND="Agg")
    namespace = {"__name__": "__docs__"}
    for i, (lang, code) in enumerate(blocks):
        where = f"{page} (block {i + 1}, {lang})"
        if lang == "python":
            exec(compile(code, where, "exec"), namespace)
            continue
        done = subprocess.run(["bash", "-euo", "pipefail", "-c", code], cwd=tmp_path, env=env,
                              capture_output=True, text=True, timeout=600)
        assert done.returncode == 0, f"{where} failed ({done.returncode}):\n{code}\n{done.stdout[-2000:]}\n{done.stderr[-2000:]}"
        for line in done.stderr.splitlines():
            assert "Traceback" not in line, f"{where} printed a traceback:\n{done.stderr[-2000:]}"


def test_every_page_and_format_spec_is_in_the_site_navigation():
    nav = (ROOT / "mkdocs.yml").read_text()
    pages = sorted(str(p.relative_to(ROOT / "docs")) for p in (ROOT / "docs").rglob("*.md"))
    missing = [p for p in pages if p not in nav]
    assert not missing, f"pages left out of mkdocs.yml's nav: {missing}"


def test_every_environment_variable_is_documented_in_one_place():
    """Each ``EVTK_*`` variable the package reads (a string literal in its source) has a row in the command-line
    overview's table of environment variables."""
    found = set()
    for path in (ROOT / "evtk").rglob("*.py"):
        found |= set(re.findall(r"[\"'](EVTK_[A-Z_]+)[\"']", path.read_text()))
    found -= {"EVTK_FORMAT"}   # the HDF5 layout's name constant, not an environment variable
    page = (ROOT / "docs/cli-overview.md").read_text()
    table = page[page.index("## Environment variables"):]
    missing = sorted(v for v in found if f"`{v}`" not in table)
    assert found and not missing, f"environment variables read but not documented: {missing}"
