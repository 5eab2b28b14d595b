"""Every figure evtk draws, checked for what can be checked without eyes.

Each test draws one figure from inputs it builds itself, keeps the Figure that
:func:`evtk.plots.save_png` writes, and checks it after drawing: every text on
the canvas, no font below 7 pt, no title, axis label or legend over another, every colour bar labelled with a quantity and
its unit, signed continuous images on a diverging map centred on zero,
continuous images in one row of panels on one scale, every legend entry naming
a drawn artist with data, no legend over data or an image, no empty axes.
"""

from __future__ import annotations

import re
from types import SimpleNamespace

import numpy as np
import pytest

import evtk.calibrate as calibrate
import evtk.plots as plots
from evtk.metrics.sinad import SinadReport

matplotlib = pytest.importorskip("matplotlib")
from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: E402
from matplotlib.collections import Collection  # noqa: E402
from matplotlib.container import Container  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402

MIN_FONT_PT = 7.0  # smallest readable font on a figure (points)
DIVERGING = {"RdBu_r", "RdBu", "coolwarm", "bwr", "seismic", "PuOr", "PuOr_r", "BrBG", "PiYG", "PRGn"}


@pytest.fixture
def figures(monkeypatch):
    """The figures the plotting functions save, in order (checked after they are written)."""
    kept = []
    original = plots.save_png

    def keep(fig, path, dpi=100):
        original(fig, path, dpi=dpi)
        kept.append(fig)

    monkeypatch.setattr(plots, "save_png", keep)  # (evtk.calibrate takes it from evtk.plots when it draws)
    return kept


def _is_colorbar(ax):
    return getattr(ax, "_colorbar", None) is not None


def _texts(fig):
    """Every visible, non-empty text a reader sees (titles, labels, drawn tick labels, legends, annotations)."""
    out = list(fig.texts)
    if fig._suptitle is not None:
        out.append(fig._suptitle)
    for leg in list(fig.legends) + [ax.get_legend() for ax in fig.axes if ax.get_legend() is not None]:
        out += list(leg.get_texts()) + [leg.get_title()]
    for ax in fig.axes:
        out += [ax.title, ax._left_title, ax._right_title, ax.xaxis.label, ax.yaxis.label, *ax.texts]
        for axis in (ax.xaxis, ax.yaxis):
            lo, hi = sorted(axis.get_view_interval())
            for tick in axis.get_major_ticks():
                if lo - 1e-9 * abs(hi - lo) <= tick.get_loc() <= hi + 1e-9 * abs(hi - lo):
                    out += [tick.label1, tick.label2]
    return [t for t in out if t.get_visible() and t.get_text().strip()]


def _shows(artist):
    """Whether a legend's artist is drawn with data a reader can see."""
    if isinstance(artist, Container):
        return any(_shows(a) for a in artist.get_children() if a is not None)
    if not artist.get_visible():
        return False
    if isinstance(artist, Line2D):
        x, y = (np.asarray(v, dtype=float) for v in artist.get_data())
        n = int(np.sum(np.isfinite(x) & np.isfinite(y)))
        marker = artist.get_marker() not in (None, "None", "none", "", " ")
        line = artist.get_linestyle() not in ("None", "none", "", " ") and artist.get_linewidth() > 0
        return (marker and n >= 1) or (line and n >= 2)
    if isinstance(artist, Collection):
        return len(artist.get_paths()) > 0 or len(artist.get_offsets()) > 0
    return True


def _data_points(ax):
    """Display coordinates of the data drawn in ``ax`` (line vertices, points along each segment, markers)."""
    pts = []
    for line in ax.lines:
        if not line.get_visible():
            continue
        xy = line.get_transform().transform(np.column_stack(line.get_data()).astype(float))
        xy = xy[np.all(np.isfinite(xy), axis=1)]
        pts.append(xy)
        if len(xy) > 1 and line.get_linestyle() not in ("None", "none", "", " "):
            t = np.linspace(0.0, 1.0, 25)[:, None, None]
            pts.append((xy[:-1][None] * (1 - t) + xy[1:][None] * t).reshape(-1, 2))
    for coll in ax.collections:
        for path in coll.get_paths():
            v = coll.get_transform().transform(path.vertices)
            pts.append(v[np.all(np.isfinite(v), axis=1)])
    return np.concatenate(pts) if pts else np.zeros((0, 2))


def problems(fig):
    """What a reviewer would object to in ``fig``, as sentences (empty: none found)."""
    out = []
    canvas_agg = FigureCanvasAgg(fig)  # the figure was closed after saving: draw it afresh
    canvas_agg.draw()
    renderer = canvas_agg.get_renderer()
    canvas = fig.bbox
    inside = lambda bb: (bb.x0 >= canvas.x0 - 1 and bb.y0 >= canvas.y0 - 1  # noqa: E731
                         and bb.x1 <= canvas.x1 + 1 and bb.y1 <= canvas.y1 + 1)
    for t in _texts(fig):
        if not inside(t.get_window_extent(renderer)):
            out.append(f"text {t.get_text()!r} runs off the canvas")
        if t.get_fontsize() < MIN_FONT_PT:
            out.append(f"text {t.get_text()!r} is {t.get_fontsize():g} pt")
    labels = [t for ax in fig.axes for t in (ax.title, ax.xaxis.label, ax.yaxis.label)
              if t.get_visible() and t.get_text().strip()]
    labels += [fig._suptitle] if fig._suptitle is not None else []
    boxes = [(t.get_text(), t.get_window_extent(renderer)) for t in labels]
    boxes += [("a legend", leg.get_window_extent(renderer)) for leg in fig.legends]
    for i, (a, box_a) in enumerate(boxes):
        for b, box_b in boxes[i + 1:]:
            if box_a.overlaps(box_b):
                out.append(f"{a!r} overlaps {b!r}")
    for ax in fig.axes:
        if not inside(ax.get_tightbbox(renderer)):
            out.append(f"axes {ax.get_title() or ax.get_ylabel()!r} runs off the canvas")
        if _is_colorbar(ax):
            label = ax.get_ylabel() or ax.get_xlabel()
            if not re.search(r"\S.*\(.+\)", label):
                out.append(f"a colour bar has no quantity and unit: {label!r}")
            continue
        if ax.get_visible() and not (ax.images or ax.lines or ax.collections or ax.patches or ax.containers):
            out.append(f"axes {ax.get_title()!r} is empty")
        for im in ax.get_images():
            a = np.asarray(im.get_array(), dtype=float)
            a = a[np.isfinite(a)]
            if np.unique(a).size > 2 and a.min() < -0.1 * np.abs(a).max():
                lo, hi = im.get_clim()
                if im.get_cmap().name not in DIVERGING or not np.isclose(lo, -hi):
                    out.append(f"signed image in {ax.get_title()!r} on {im.get_cmap().name} from {lo:g} to {hi:g}")
    # continuous images side by side (one row of panels) share one colour scale, unless colour bars of different
    # quantities say they differ
    bar_of = {id(ax._colorbar.mappable): ax.get_ylabel() or ax.get_xlabel() for ax in fig.axes if _is_colorbar(ax)}
    rows = {}
    for ax in fig.axes:
        for im in ax.get_images():
            if np.unique(np.asarray(im.get_array(), dtype=float)).size > 2:
                row = rows.setdefault(round(ax.get_position().y0, 3), {"clims": set(), "quantities": set()})
                row["clims"].add(tuple(np.round(im.get_clim(), 9)))
                if id(im) in bar_of:
                    row["quantities"].add(bar_of[id(im)])
    for y, row in rows.items():
        if len(row["clims"]) > max(1, len(row["quantities"])):
            out.append(f"the images of the row at y={y} have different colour scales {sorted(row['clims'])}")
    # legends: every entry a drawn artist with data; none over data or an image
    named = {}
    for ax in fig.axes:
        for h, lab in zip(*ax.get_legend_handles_labels()):
            named.setdefault(lab, []).append(h)
    legends = list(fig.legends) + [ax.get_legend() for ax in fig.axes if ax.get_legend() is not None]
    for leg in legends:
        for text in leg.get_texts():
            lab = text.get_text()
            if not any(_shows(a) for a in named.get(lab, [])):
                out.append(f"legend entry {lab!r} names no drawn artist with data")
        box = leg.get_window_extent(renderer)
        for ax in fig.axes:
            if _is_colorbar(ax):
                continue
            pts = _data_points(ax)
            over = ((pts[:, 0] >= box.x0) & (pts[:, 0] <= box.x1) & (pts[:, 1] >= box.y0) & (pts[:, 1] <= box.y1))
            if over.any():
                out.append(f"legend over the data of {ax.get_title()!r}")
            for im in ax.get_images():
                if box.overlaps(im.get_window_extent(renderer)):
                    out.append(f"legend over the image in {ax.get_title()!r}")
    return out


def _result(n=10, size=12, signed=False, seed=1):
    """A reconstruction's fields as contact_sheet reads them: measured near a known ideal."""
    rng = np.random.default_rng(seed)
    base = rng.normal(size=(size, size)).cumsum(axis=0).cumsum(axis=1)
    base = base - base.mean() if signed else base - base.min()
    ideal = np.repeat(base[None], n, axis=0)
    cells = ideal * 1.4 + rng.normal(scale=0.5, size=ideal.shape)
    binary = np.where(cells >= (0 if signed else cells.mean()), 1, -1).astype(np.int8)
    pairs = np.array([[0, 0, r] for r in range(n)])
    return SimpleNamespace(cells=cells, ideal=ideal, binary=binary, pairs=pairs,
                           summary={"binarize": "sign" if signed else "mean", "linear": True,
                                    "error": {"correlation": 0.9}})


@pytest.mark.parametrize("signed", [False, True])
def test_contact_sheet_pages_are_balanced_labelled_and_share_a_scale_per_row(tmp_path, figures, signed):
    pages = plots.contact_sheet(tmp_path / "sheet.png", _result(signed=signed), rows_per_page=8)
    assert len(pages) == len(figures) == 2
    rows = [len({round(ax.get_position().y0, 3) for ax in fig.axes if not _is_colorbar(ax)}) for fig in figures]
    assert rows == [5, 5]  # ten responses on two pages: five each, not eight and two
    for fig in figures:
        assert problems(fig) == []
        assert "share one colour scale" in fig._suptitle.get_text()
    bars = [ax.get_ylabel() for ax in figures[0].axes if _is_colorbar(ax)]
    assert "light (kernel elements)" in bars


def test_contact_sheet_without_ideal_names_its_quantity(tmp_path, figures):
    res = _result(n=3)
    res.ideal = None
    res.summary = {"binarize": "mean", "linear": False}
    plots.contact_sheet(tmp_path / "sheet.png", res)
    assert problems(figures[0]) == []
    assert any("net events" in ax.get_ylabel() for ax in figures[0].axes if _is_colorbar(ax))


def test_contact_sheet_of_counts_gives_counts_and_light_a_bar_each(tmp_path, figures):
    res = _result(n=2)
    res.summary["linear"] = False
    res.cells = res.cells * 9.0  # net events: not the ideal's units
    plots.contact_sheet(tmp_path / "sheet.png", res)
    fig = figures[0]
    assert problems(fig) == []
    assert {ax.get_ylabel() for ax in fig.axes if _is_colorbar(ax)} >= {"light (kernel elements)",
                                                                          "net events (ON - OFF, count per cell)"}
    assert "own colour scale" in fig._suptitle.get_text()


def _report(enob, noise_free=False, interval="bootstrap"):
    return SinadReport(sinad_db=6.02 * enob + 1.76, enob_bits=enob, noise_free=noise_free, signal_rms=1.0,
                       noise_std=0.1, repeats=10, pixels=256, ci_db=None,
                       ci_enob=None if noise_free else (enob - 0.2, np.inf), interval=interval)


@pytest.mark.parametrize("count", [1, 3, 12])
def test_enob_title_fits_and_the_noise_free_marker_is_named(tmp_path, figures, count):
    scenes = [{"kernel_id": k, "features_id": 0, "repeats": 10, "sinad": _report(2.0 + 0.1 * k)}
              for k in range(count)]
    scenes.append({"kernel_id": 99, "features_id": 7, "repeats": 10, "sinad": _report(np.inf, noise_free=True)})
    plots.plot_enob(scenes, tmp_path / "enob.png")
    fig = figures[0]
    assert problems(fig) == []
    labels = [t.get_text() for leg in fig.legends for t in leg.get_texts()]
    assert any("noise-free" in lab for lab in labels)
    assert any("unbounded above" in lab for lab in labels)  # the intervals' infinite upper ends are drawn as such


def test_flips_against_power_and_against_recordings(tmp_path, figures):
    rows = [{"kernel_id": k, "power_mw": p, "pairwise_pct": 40.0 / (1 + p) + k} for k in range(4)
            for p in (0.05, 0.2, 1, 5, 20)]
    plots.plot_flips(rows, tmp_path / "flips.png")
    files = [{"kernel_id": 0, "file_index": i, "file": f"/data/run-{i}.aedat4", "pairwise_pct": 3.0 + i}
             for i in range(3)]
    plots.plot_flips(files, tmp_path / "files.png", x_key="file_index", x_label="recording")
    for fig in figures:
        assert problems(fig) == []
    ticks = [t.get_text() for t in figures[1].axes[0].get_xticklabels()]
    assert ticks == ["run-0.aedat4", "run-1.aedat4", "run-2.aedat4"]


def test_tradeoff_with_a_front_of_one_point(tmp_path, figures):
    rows = [{"nrmse": e, "nrmse_std": 0.04, "device_us_per_capture": d, "compute_us_per_capture": c,
             "pareto": front, "power_mw": 20.0, "window_us": w, "settle_us": 13340, "decimation": 1,
             "pipeline": "counts"}
            for e, d, c, front, w in [(0.49, 13540, 5087, True, 200), (0.53, 14340, 10390, False, 1000)]]
    plots.plot_tradeoff(rows, tmp_path / "tradeoff.png")
    fig = figures[0]
    assert problems(fig) == []
    ax, ax_c = (a for a in fig.axes if not _is_colorbar(a))
    assert ax.get_ylim() == ax_c.get_ylim()  # one error scale for both panels


def test_recovery_responses_share_a_labelled_scale(tmp_path, figures):
    rng = np.random.default_rng(0)
    features = (rng.random((16, 16)) > 0.5).astype(float)
    kernel = np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]])
    target = rng.random((18, 18)) * 7
    losses = rng.random(512) + 0.01
    result = SimpleNamespace(kernel=kernel, status="exact", losses=losses)
    plots.plot_recovery(tmp_path / "rec.png", features, target, target * 0.8, result, kernel)
    result.losses = None
    plots.plot_recovery(tmp_path / "rec2.png", features, target - 3.5, target * 0.8 - 3.5, result)
    for fig in figures:
        assert problems(fig) == []


def test_success_and_robustness(tmp_path, figures):
    rows = [{"size": 3, "method": "brute", "weights": w, "power_mw": p, "recovered_pct": r, "exact_pct": r,
             "trials": 4} for w in ("relative", None) for p, r in ((0.05, 0.0), (1, 100.0), (20, 100.0))]
    plots.plot_success(rows, tmp_path / "success.png")
    rob = {"r": 0.867, "rows": [{"scale": s, "accuracy": a, "flip_pct": f}
                                for s, a, f in ((0, 0.92, 0.0), (0.1, 0.93, 2.6), (1, 0.85, 28.5), (3, 0.67, 43.2))]}
    plots.plot_robustness(rob, tmp_path / "robust.png")
    for fig in figures:
        assert problems(fig) == []
    labels = [t.get_text() for leg in figures[1].legends for t in leg.get_texts()]
    assert any("eq. 12" in lab for lab in labels)  # the dotted line is named


@pytest.mark.parametrize("with_model", [False, True])
def test_calibration_report(tmp_path, figures, with_model):
    rng = np.random.default_rng(2)
    cells = np.array([(c, r) for r in range(2, 14, 4) for c in range(2, 14, 4)], dtype=float)
    matrix = [[1.0, 0.0, 150.0], [0.0, 1.0, 110.0], [0.0, 0.0, 1.0]]
    image = rng.poisson(0.05, size=(260, 346)).astype(float)
    found = cells + [150.0, 110.0] + rng.normal(scale=0.05, size=cells.shape)
    for x, y in found:
        image[int(round(y)) - 1:int(round(y)) + 2, int(round(x)) - 1:int(round(x)) + 2] += 30
    model = None
    if with_model:
        model = {"theta_on": 0.2, "theta_off": 0.2, "blank_units": 0.02, "tau_min_us": 100.0, "tau_dark_us": 2000.0,
                 "levels": [1.0, 3.0, 4.0, 6.0, 7.0, 9.0], "level_counts": [17.3, 21.5, 22.6, 24.2, 24.7, 25.6],
                 "window_us": 1000, "settle_us": 13340}
    cal = calibrate.Calibration(matrix=matrix, origin_px=[150.0, 110.0], step_px=1.0, region=[149, 165, 109, 125],
                                residual_rms_px=0.05, residual_max_px=0.08, dots_expected=16, dots_found=16,
                                inliers=16, sensor_size=[346, 260], response_shape=[16, 16], pixel_model=model)
    cal._evidence = (image, found, cells)
    calibrate.plot_calibration(tmp_path / "cal.png", cal)
    assert problems(figures[0]) == []
    bar = figures[0].axes[-1] if _is_colorbar(figures[0].axes[-1]) else next(a for a in figures[0].axes
                                                                             if _is_colorbar(a))
    assert "ON events" in bar.get_ylabel()
