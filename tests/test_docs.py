"""The documentation's Python snippets run as written, in order, page by page (README's too)."""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PAGES = ["README.md", "docs/getting-started.md", "docs/walkthrough-simulated.md", "docs/walkthrough-bench.md",
         "docs/guide.md"]


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


def test_every_page_and_format_spec_is_in_the_site_navigation():
    nav = (ROOT / "mkdocs.yml").read_text()
    pages = sorted(str(p.relative_to(ROOT / "docs")) for p in (ROOT / "docs").rglob("*.md"))
    missing = [p for p in pages if p not in nav]
    assert not missing, f"pages left out of mkdocs.yml's nav: {missing}"
