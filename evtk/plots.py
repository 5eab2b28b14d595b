"""Matplotlib PNGs of the noise reports: ENOB per scene, flips against power, error against time.

Every figure is drawn off-screen (Agg) with matplotlib's constrained layout (titles, colour bars and
legends get their room; legends sit outside the axes, never over the data) and written atomically.
"""

from __future__ import annotations

import os
import textwrap
from collections import defaultdict
from typing import TYPE_CHECKING, Any

import numpy as np

from ._atomic import AtomicFile
from .errors import EvtkError
from .reconstruct import Reconstruction, binarize, downsample

if TYPE_CHECKING:
    import numpy.typing as npt
    from matplotlib.figure import Figure

    from .recover import Recovery

#: A file path as the plots take it.
PathLike = str | os.PathLike[str]

__all__ = ["contact_sheet", "wilson_interval", "plot_enob", "plot_flips", "plot_tradeoff", "plot_recovery", "plot_success",
           "plot_robustness"]

#: Colour map of signed data (centred on zero: white is 0).
DIVERGING_CMAP = "RdBu_r"
#: Smallest font (points) on any figure.
MIN_FONT_PT = 7.0


def pyplot() -> Any:
    """matplotlib.pyplot on the off-screen backend.

    Returns
    -------
    module
        ``matplotlib.pyplot`` with the Agg backend selected.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_png(fig: Figure, path: PathLike, dpi: int = 100) -> None:
    """Write ``fig`` as a PNG at ``path`` (atomically) and close it.

    A figure made without a layout engine gets matplotlib's constrained layout, which keeps titles, colour
    bars and outside legends on the canvas.

    Parameters
    ----------
    fig : matplotlib.figure.Figure
        The figure; closed afterwards, written or not.
    path : str or os.PathLike
        Where the PNG goes.
    dpi : int
        Pixels per inch.
    """
    plt = pyplot()
    try:
        if fig.get_layout_engine() is None:
            fig.set_layout_engine("constrained")
        with AtomicFile(path) as out:
            fig.savefig(out.file, format="png", dpi=dpi)
    finally:
        plt.close(fig)


def wrap_title(text: str, width_in: float, fontsize: float) -> str:
    """``text`` broken into lines that fit ``width_in`` inches at ``fontsize`` points.

    Parameters
    ----------
    text : str
        The title.
    width_in : float
        Width it may take (inches).
    fontsize : float
        Its font size (points).

    Returns
    -------
    str
        The title with newlines (an average glyph taken as 0.55 of the font size wide).
    """
    chars = max(12, int(width_in * 72.0 / (0.55 * fontsize)))
    return "\n".join(textwrap.fill(part, chars) for part in text.split("\n"))


def _legend_below(fig, handles, labels=None, ncols=None):
    """One figure legend under the axes (outside them: never over the data)."""
    if labels is None:
        labels = [h.get_label() for h in handles]
    fig.legend(handles, labels, loc="outside lower center", ncols=ncols or min(len(handles), 3), fontsize=8,
               frameon=False)


def response_quantity(result: Reconstruction) -> str:
    """What a reconstruction's response values are, with their unit, for a colour bar.

    Parameters
    ----------
    result : evtk.reconstruct.Reconstruction
        The reconstruction (its ``summary["linear"]`` and whether the ideal is known).

    Returns
    -------
    str
        ``"net events (count per cell)"`` for an unlinearised reconstruction, ``"light (kernel elements)"`` for
        a linear one against a known ideal (the ideal's units), else the relative light change.
    """
    if not result.summary.get("linear", True):
        return "net events (ON - OFF, count per cell)"
    if result.ideal is not None:
        return "light (kernel elements)"
    return "light change (relative to the dark level)"


def _is_signed(arr, tol=0.1):
    """Whether ``arr`` holds signed data: values below zero by more than ``tol`` of its largest magnitude."""
    arr = np.asarray(arr, dtype=float)
    finite = arr[np.isfinite(arr)]
    if finite.size == 0:
        return False
    return bool(finite.min() < -tol * max(np.abs(finite).max(), 1e-300))


def _scale(arrays, signed):
    """(vmin, vmax, cmap) shared by ``arrays``: symmetric about zero on the diverging map when ``signed``."""
    finite = [a[np.isfinite(a)] for a in (np.asarray(x, dtype=float) for x in arrays)]
    finite = [a for a in finite if a.size]
    lo = min((a.min() for a in finite), default=0.0)
    hi = max((a.max() for a in finite), default=1.0)
    if signed:
        m = max(abs(lo), abs(hi)) or 1.0
        return -m, m, DIVERGING_CMAP
    if hi <= lo:
        hi = lo + 1.0
    return lo, hi, "gray"


def contact_sheet(path: PathLike, result: Reconstruction, rows_per_page: int = 8) -> list:
    """PNG pages of every response: measured and ideal on the cell grid, and both binarised.

    One row per response, at most ``rows_per_page`` rows a page and the rows
    spread evenly over the pages (no nearly empty last page); the first page
    is ``path``, the next ``<stem>-p2.png`` and so on. Columns: the measured
    response and the ideal one (when known), which share one colour scale
    per row (symmetric about zero on a diverging map when the responses are
    signed) with a colour bar labelled with the quantity and its unit
    (:func:`response_quantity`; unlinearised counts and the ideal's light
    get a scale and bar each); then the measured binary response and the
    ideal's, binarised by the same rule (``result.summary["binarize"]``) at
    the same size, so each flipped pixel shows. Row labels name kernel,
    features and repeat. Written atomically.

    Parameters
    ----------
    path : str or os.PathLike
        The first page's PNG.
    result : evtk.reconstruct.Reconstruction
        The reconstruction to draw.
    rows_per_page : int
        Most responses on one page.

    Returns
    -------
    list of str
        The pages written, in order.

    Raises
    ------
    EvtkError
        When the reconstruction holds no responses.
    """
    n = len(result.cells)
    if n == 0:
        raise EvtkError("no responses to draw")
    rows_per_page = max(1, int(rows_per_page))
    pages = -(-n // rows_per_page)
    per_page = -(-n // pages)  # the same number of rows on every page, give or take one
    method = result.summary.get("binarize", "sign")
    try:
        method = float(method)
    except (TypeError, ValueError):
        pass
    ideal_binary = None
    if result.ideal is not None:
        ideal_binary = binarize(downsample(result.ideal, result.binary.shape[1:]), method)
    signed = _is_signed(result.ideal if result.ideal is not None else result.cells)
    quantity = response_quantity(result)
    ideal_quantity = "light (kernel elements)"  # the digital correlation of the binary patterns
    one_scale = quantity == ideal_quantity
    stem, ext = os.path.splitext(os.fspath(path))
    paths = []
    plt = pyplot()
    from matplotlib.colors import ListedColormap

    two_tone = ListedColormap(["black", "white"])
    err = result.summary.get("error") or {}
    corr = err.get("correlation")
    for page in range(pages):
        rows = range(page * per_page, min(n, (page + 1) * per_page))
        # (title, arrays, quantity: panels of one quantity share a colour scale and bar; None: binary)
        cols: list[tuple[str, np.ndarray, str | None]] = [("measured", result.cells, quantity)]
        if result.ideal is not None:
            cols.append(("ideal", result.ideal, ideal_quantity))
        cols.append((f"measured, binary ({method})", result.binary, None))
        if ideal_binary is not None:
            cols.append(("ideal, binary", ideal_binary, None))
        width_in = 2.5 * len(cols) + 1.6
        fig, axes = plt.subplots(len(rows), len(cols), figsize=(width_in, 2.2 * len(rows) + 1.1), squeeze=False,
                                 layout="constrained")
        # fixed-aspect panels leave constrained layout a few points short at the left edge: pad it
        fig.get_layout_engine().set(w_pad=0.15)
        binary_im = None
        for r, i in enumerate(rows):
            groups: dict = {}
            for c, col in enumerate(cols):
                if col[2] is not None:
                    groups.setdefault(col[2], []).append(c)
            for what, members in groups.items():
                vmin, vmax, cmap = _scale([cols[c][1][i] for c in members], signed)
                for c in members:
                    im = axes[r][c].imshow(cols[c][1][i], cmap=cmap, vmin=vmin, vmax=vmax, interpolation="nearest")
                cb = fig.colorbar(im, ax=[axes[r][c] for c in members], shrink=0.9)
                cb.set_label(what, fontsize=8)
                cb.ax.tick_params(labelsize=7)
            for c, (title, arr, what) in enumerate(cols):
                ax = axes[r][c]
                if what is None:
                    binary_im = ax.imshow(arr[i], cmap=two_tone, vmin=-1, vmax=1, interpolation="nearest")
                ax.set_xticks([])
                ax.set_yticks([])
                if r == 0:
                    ax.set_title(title, fontsize=9)
            if result.pairs is not None:
                k, f, rep = (int(v) for v in result.pairs[i])
                axes[r][0].set_ylabel(f"kernel {k}, features {f}\nrepeat {rep}", fontsize=8)
            else:
                axes[r][0].set_ylabel(f"window {i}", fontsize=8)
        # the binary key beside the first row only (a bar spanning rows upsets constrained layout's margins)
        cb = fig.colorbar(binary_im, ax=[axes[0][c] for c, col in enumerate(cols) if col[2] is None], shrink=0.9)
        cb.set_ticks([-0.5, 0.5], labels=["-1", "+1"])
        cb.set_label("binary response (-1 or +1)", fontsize=8)
        cb.ax.tick_params(labelsize=7)
        title = (f"responses {rows[0] + 1}-{rows[-1] + 1} of {n}" + (f" (page {page + 1} of {pages})" if pages > 1
                                                                     else "")
                 + ("" if corr is None else f"; correlation with the ideal {corr:.3f}")
                 + ("\nmeasured and ideal share one colour scale per row" if result.ideal is not None and one_scale
                    else "\nmeasured (counts) and ideal (light) each on their own colour scale"
                    if result.ideal is not None else "\neach response on its own colour scale"))
        fig.suptitle(wrap_title(title, width_in, 10), fontsize=10)
        out = os.fspath(path) if page == 0 else f"{stem}-p{page + 1}{ext}"
        save_png(fig, out, dpi=100)  # 7 pt labels stay legible
        paths.append(out)
    return paths


def plot_enob(scenes: list[dict], path: PathLike) -> None:
    """ENOB (eq. 8) of each scene with its interval; noise-free scenes drawn as a marker at the top.

    Parameters
    ----------
    scenes : list of dict
        :func:`evtk.sweeps.recording_noise`'s scenes (``kernel_id``, ``features_id``, ``repeats``, ``sinad``).
    path : str or os.PathLike
        The PNG.

    Raises
    ------
    EvtkError
        When there are no scenes.
    """
    if not scenes:
        raise EvtkError("no scenes to plot")
    plt = pyplot()
    width_in = max(5.5, 0.5 * len(scenes) + 2)
    fig, ax = plt.subplots(figsize=(width_in, 3.8), layout="constrained")
    kinds = {s["sinad"].interval for s in scenes if s["sinad"] is not None and s["sinad"].interval}
    kind = kinds.pop() if len(kinds) == 1 else None
    labels, finite, handles = [], [], {}
    for i, s in enumerate(scenes):
        name = f"K{s['kernel_id']} F{s['features_id']}" if s["kernel_id"] >= 0 else "all windows"
        labels.append(f"{name}\nn={s['repeats']}")
        r = s["sinad"]
        if r is None or r.noise_free:
            continue
        lo, hi = r.ci_enob if r.ci_enob is not None else (r.enob_bits, r.enob_bits)
        lo = lo if np.isfinite(lo) else r.enob_bits
        finite += [r.enob_bits] + ([hi] if np.isfinite(hi) else [])
        handles["enob"] = ax.errorbar(i, r.enob_bits, yerr=[[r.enob_bits - lo],
                                                            [hi - r.enob_bits if np.isfinite(hi) else 0.0]],
                                      fmt="o", color="C0", capsize=3,
                                      label="ENOB" + (f" and its 95 % {kind} interval" if kind else ""))
    top = max(finite) + 1 if finite else 1.0
    for i, s in enumerate(scenes):
        r = s["sinad"]
        if r is None:
            continue
        if r.noise_free:
            handles["free"], = ax.plot(i, top, "*", ms=10, color="C2",
                                       label="noise-free: ENOB unbounded (drawn at the top)")
        elif r.ci_enob is not None and not np.isfinite(r.ci_enob[1]):  # the interval has no upper end
            handles["open"], = ax.plot([i, i], [r.enob_bits, top], "--", lw=0.8, color="C0", marker="^",
                                       markevery=[1], label="interval unbounded above")
    ax.set_xticks(range(len(scenes)))
    ax.set_xticklabels(labels, rotation=90 if len(scenes) > 8 else 0, fontsize=8)
    ax.set_xlim(-0.6, len(scenes) - 0.4)
    ax.set_xlabel("scene (kernel, features; n repeats)")
    ax.set_ylabel("ENOB (bits)")
    ax.set_title(wrap_title("effective bits per scene (eq. 8)" + (f", 95 % {kind} interval" if kind else ""),
                            width_in - 0.6, 10), fontsize=10)
    if handles:
        _legend_below(fig, list(handles.values()), ncols=1)
    save_png(fig, path)


def plot_flips(rows: list[dict], path: PathLike, x_key: str = "power_mw", x_label: str = "laser power (mW)") -> None:
    """Flip rate against ``x_key`` (laser power), one line per kernel and their mean (the paper's Fig. 3, right).

    Parameters
    ----------
    rows : list of dict
        ``kernel_id``, ``pairwise_pct`` and ``x_key`` per kernel and point (``file`` too when ``x_key`` is
        ``"file_index"``: the ticks then name the files).
    path : str or os.PathLike
        The PNG.
    x_key : str
        The abscissa's key in ``rows``.
    x_label : str
        The abscissa's axis label.

    Raises
    ------
    EvtkError
        When there are no rows.
    """
    if not rows:
        raise EvtkError("no flip rates to plot")
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(5.5, 4.0), layout="constrained")
    by_kernel = defaultdict(list)
    for r in rows:
        by_kernel[r["kernel_id"]].append((r[x_key], r["pairwise_pct"]))
    handles = []
    join = "-" if x_key != "file_index" else ""  # recordings are categories: points, not a line through them
    for j, (_k, pts) in enumerate(sorted(by_kernel.items())):
        pts.sort()
        line, = ax.plot([p[0] for p in pts], [p[1] for p in pts], "." + join, color="0.65", lw=0.8, ms=4,
                        label="each kernel" if j == 0 else "_nolegend_")
        if j == 0:
            handles.append(line)
    xs = sorted({r[x_key] for r in rows})
    mean = [np.mean([r["pairwise_pct"] for r in rows if r[x_key] == x]) for x in xs]
    handles += ax.plot(xs, mean, "o" + join, color="C3", label=f"mean of {len(by_kernel)} kernels")
    if len(xs) > 1 and min(xs) > 0 and max(xs) / min(xs) > 20:
        ax.set_xscale("log")
    names = None
    if x_key == "file_index":
        files = {r[x_key]: os.path.basename(str(r.get("file", r[x_key]))) for r in rows}
        names = [files[x] for x in xs]
    _tick_at(ax, xs, names)
    ax.set_xlabel(x_label)
    ax.set_ylabel("pixels flipped between repeats (%)")
    ax.set_title("binary pixels that flip between repeats (Fig. 3, right)", fontsize=10)
    _legend_below(fig, handles)
    save_png(fig, path)


def _tick_at(ax, xs, names=None):
    """Ticks at the measured values only (no crowded log-axis labels), rotated when there are many."""
    from matplotlib.ticker import NullFormatter, NullLocator

    ax.xaxis.set_minor_locator(NullLocator())
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.set_xticks(list(xs))
    labels = names if names is not None else [f"{x:g}" for x in xs]
    ax.set_xticklabels(labels, rotation=45 if len(xs) > 5 or names is not None else 0, fontsize=8,
                       ha="right" if len(xs) > 5 or names is not None else "center")


def plot_tradeoff(rows: list[dict], path: PathLike) -> None:
    """Work-precision plot: NRMSE against device time per capture, the Pareto front joined.

    Both panels share the error axis; the right one puts the same settings against compute time.

    Parameters
    ----------
    rows : list of dict
        :func:`evtk.sweeps.tradeoff`'s rows.
    path : str or os.PathLike
        The PNG.

    Raises
    ------
    EvtkError
        When no setting has a defined error.
    """
    pts = [r for r in rows if r["nrmse"] is not None]
    if not pts:
        raise EvtkError("no settings with a defined error to plot")
    plt = pyplot()
    fig, (ax, ax_c) = plt.subplots(1, 2, figsize=(10.0, 4.6), gridspec_kw={"width_ratios": [3, 2]}, sharey=True,
                                   layout="constrained")
    x = np.array([r["device_us_per_capture"] for r in pts])
    y = np.array([r["nrmse"] for r in pts])
    front = np.array([r["pareto"] for r in pts])
    powers = sorted({r["power_mw"] for r in pts})
    markers = "osD^v<>p*h"
    handles = []
    for j, pw in enumerate(powers):
        sel = np.array([r["power_mw"] == pw for r in pts])
        spread = np.array([r.get("nrmse_std") or 0.0 for r in pts])[sel]
        handles.append(ax.errorbar(x[sel], y[sel], yerr=spread, color=f"C{j % 10}", marker=markers[j % len(markers)],
                                   ls="none", capsize=2, label=f"laser {pw:g} mW", zorder=3))
        ax_c.errorbar([r["compute_us_per_capture"] for r, s in zip(pts, sel) if s], y[sel], yerr=spread,
                      color=f"C{j % 10}", marker=markers[j % len(markers)], ls="none", capsize=2)
    order = np.argsort(x[front])
    # a ring round each point on the front: a front of one point still shows
    handles += ax.plot(x[front][order], y[front][order], "-", color="0.2", lw=1.2, marker="o", ms=11, mfc="none",
                       label="Pareto front", zorder=2)
    if x.max() / max(x.min(), 1e-9) > 20:
        ax.set_xscale("log")
    ax.margins(x=0.12, y=0.08)
    # each point is labelled with the settings that vary; the ones all share go in the axis label
    settings = [("window_us", "window", "{} µs"), ("settle_us", "settle", "{} µs"), ("decimation", "decimation", "{}")]
    varying = [s for s in settings if len({r.get(s[0], 1) for r in pts}) > 1] or settings[:1]
    fixed = [f"{name} " + unit.format(pts[0].get(key, 1)) for key, name, unit in settings if (key, name, unit)
             not in varying and not (key == "decimation" and pts[0].get(key, 1) == 1)]
    mid = np.median(x)
    for r in pts:
        label = "/".join(str(r.get(key, 1)) for key, _, _ in varying)
        right = r["device_us_per_capture"] > mid
        ax.annotate(label, (r["device_us_per_capture"], r["nrmse"]), fontsize=7, xytext=(-5 if right else 5, 4),
                    textcoords="offset points", ha="right" if right else "left")
    ax.set_xlabel(wrap_title("device time per capture (µs); labels: " + "/".join(
        name + (" (µs)" if unit.endswith("µs") else "") for _, name, unit in varying)
        + ("; " + ", ".join(fixed) if fixed else ""), 5.5, 10))
    ax.set_ylabel("RMS error / RMS of ideal")
    ax.set_title("error against device time per capture (bars: sd over responses)", fontsize=9)
    pipeline = {r.get("pipeline", "events") for r in pts}
    ax_c.set_xlabel("compute time per capture (µs)")
    ax_c.set_title(f"error against compute time ({', '.join(sorted(pipeline))} pipeline)", fontsize=9)
    ax_c.margins(x=0.12)
    _legend_below(fig, handles, ncols=min(len(handles), 6))
    save_png(fig, path)


def plot_recovery(path: PathLike, features: npt.ArrayLike, target_response: npt.ArrayLike,
                  solution_response: npt.ArrayLike, result: Recovery, true_kernel: npt.ArrayLike | None = None) -> None:
    """The paper's Fig. 4 for one recovery: features, target and solution kernels and responses, loss per candidate.

    The two responses share one colour scale (one colour bar, in the target's units).

    Parameters
    ----------
    path : str or os.PathLike
        The PNG.
    features : array_like
        The binary features.
    target_response : array_like
        The captured response (2-D, cells).
    solution_response : array_like
        The solution kernel's response, same shape.
    result : evtk.recover.Recovery
        The recovery (its kernel, status and, for brute force, every candidate's loss).
    true_kernel : array_like, optional
        The kernel that made the target, when known.
    """
    plt = pyplot()
    binary = [("input features", features)]
    if true_kernel is not None:
        binary.append(("target kernel", true_kernel))
    binary.append(("solution kernel" + (f" ({result.status})" if result.status else ""), result.kernel))
    responses = [("target response", np.asarray(target_response, dtype=float)),
                 ("solution response", np.asarray(solution_response, dtype=float))]
    n_panels = len(binary) + len(responses)
    losses = result.losses
    with_curve = losses is not None
    width_in = 2.4 * n_panels + 1.2
    fig = plt.figure(figsize=(width_in, 5.2 if with_curve else 3.0), layout="constrained")
    grid = fig.add_gridspec(2 if with_curve else 1, n_panels)
    for i, (title, img) in enumerate(binary):
        ax = fig.add_subplot(grid[0, i])
        ax.imshow(np.asarray(img, dtype=float), cmap="gray", vmin=0, vmax=1, interpolation="nearest")
        ax.set_title(title, fontsize=8)
        ax.set_xticks([])
        ax.set_yticks([])
    signed = _is_signed(responses[0][1])
    vmin, vmax, cmap = _scale([img for _, img in responses], signed)
    shared = []
    for j, (title, img) in enumerate(responses):
        ax = fig.add_subplot(grid[0, len(binary) + j])
        im = ax.imshow(img, cmap="viridis" if not signed else cmap, vmin=vmin, vmax=vmax, interpolation="nearest")
        ax.set_title(title, fontsize=8)
        ax.set_xticks([])
        ax.set_yticks([])
        shared.append(ax)
    cb = fig.colorbar(im, ax=shared, shrink=0.9)
    cb.set_label("response (light, kernel elements)", fontsize=8)
    cb.ax.tick_params(labelsize=7)
    fig.suptitle(wrap_title("kernel recovery (Fig. 4): features and kernels black 0, white 1; "
                            "the responses share one colour scale", width_in, 9), fontsize=9)
    if losses is not None:
        ax = fig.add_subplot(grid[1, :])
        ax.plot(losses, lw=0.6, color="0.3")
        best = int(np.argmin(losses))
        ax.plot(best, losses[best], "o", color="C3")
        ax.set_yscale("log" if np.all(losses > 0) else "linear")
        ax.set_xlabel("candidate kernel (bits as a number)")
        ax.set_ylabel("loss (weighted mean square)")
        ax.set_title(f"loss of every candidate; red dot: the solution (candidate {best})", fontsize=8)
    save_png(fig, path)


def plot_success(rows: list[dict], path: PathLike) -> None:
    """Share of kernels recovered (exactly or up to a shift) against laser power.

    Parameters
    ----------
    rows : list of dict
        :func:`evtk.recover.success_rate`'s rows (``size``, ``method``, ``weights``, ``power_mw``,
        ``recovered_pct``, ``exact_pct``, ``trials``).
    path : str or os.PathLike
        The PNG.

    Raises
    ------
    EvtkError
        When there are no rows.
    """
    if not rows:
        raise EvtkError("no success rates to plot")
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(5.5, 4.0), layout="constrained")
    by = defaultdict(list)
    for r in rows:
        by[(r["size"], r["method"], r.get("weights"))].append((r["power_mw"], r["recovered_pct"], r["exact_pct"],
                                                               int(r["trials"])))
    trials = set()
    handles = []
    for (size, method, weights), pts in sorted(by.items(), key=str):
        pts.sort()
        ns = [n for _, _, _, n in pts]
        trials.update(ns)
        share = np.array([p[1] for p in pts]) / 100.0
        lo, hi = wilson_interval(share, np.array(ns))
        handles.append(ax.errorbar([p[0] for p in pts], 100 * share, yerr=[100 * (share - lo), 100 * (hi - share)],
                                   fmt="o-", capsize=3, label=f"{size}x{size} {method} ({weights or 'mse'})"))
    if min(r["power_mw"] for r in rows) > 0:
        ax.set_xscale("log")
    _tick_at(ax, sorted({r["power_mw"] for r in rows}))
    ax.set_ylim(-3, 103)
    ax.set_xlabel("laser power (mW)")
    ax.set_ylabel("recovered, exact or shifted (%)")
    n_text = ", ".join(str(n) for n in sorted(trials))
    ax.set_title(wrap_title(f"kernels recovered (n = {n_text} trials a point; 95 % Wilson intervals)", 5.0, 9),
                 fontsize=9)
    _legend_below(fig, handles)
    save_png(fig, path)


def wilson_interval(share: npt.ArrayLike, n: npt.ArrayLike,
                    z: float = 1.959963984540054) -> tuple[np.ndarray, np.ndarray]:
    """Wilson score interval of binomial shares ``share`` out of ``n`` trials (95 % by default).

    Parameters
    ----------
    share : array_like
        Observed shares (0 to 1).
    n : array_like
        Trials behind each share.
    z : float
        Normal quantile of the interval's level.

    Returns
    -------
    low : numpy.ndarray
        Lower bounds, float64 within 0 and 1, of the broadcast shape.
    high : numpy.ndarray
        Upper bounds, likewise.
    """
    p = np.asarray(share, dtype=float)
    trials = np.maximum(np.asarray(n, dtype=float), 1.0)
    centre = (p + z * z / (2 * trials)) / (1 + z * z / trials)
    half = z * np.sqrt(p * (1 - p) / trials + z * z / (4 * trials * trials)) / (1 + z * z / trials)
    return np.clip(centre - half, 0.0, 1.0), np.clip(centre + half, 0.0, 1.0)


def plot_robustness(result: dict[str, Any], path: PathLike) -> None:
    """Fig. 3 (left): accuracy and flipped pixels against the Poisson noise scale.

    Parameters
    ----------
    result : dict
        :func:`evtk.bcnn.poisson_robustness`'s result (``rows`` with ``scale``, ``accuracy``, ``flip_pct``;
        ``r``, the accuracy eq. 12 keeps).
    path : str or os.PathLike
        The PNG.

    Raises
    ------
    EvtkError
        When there are no rows.
    """
    rows = result["rows"]
    if not rows:
        raise EvtkError("no noise levels to plot")
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(5.5, 4.2), layout="constrained")
    xs = [r["scale"] for r in rows]
    handles = ax.plot(xs, [100 * r["accuracy"] for r in rows], "o-", color="C0", label="test accuracy")
    handles.append(ax.axhline(100 * result["r"], color="C0", ls=":", lw=1.0,
                              label=f"r = {100 * result['r']:.1f} %: accuracy kept (eq. 12)"))
    ax.set_ylabel("test accuracy (%)", color="C0")
    ax2 = ax.twinx()
    handles += ax2.plot(xs, [r["flip_pct"] for r in rows], "s--", color="C3", label="flipped pixels")
    ax2.set_ylabel("flipped pixels (%)", color="C3")
    if min(xs) >= 0 and max(xs) > 0 and len([x for x in xs if x > 0]) > 1:
        ax.set_xscale("symlog", linthresh=min(x for x in xs if x > 0))
    _tick_at(ax, sorted(set(xs)))
    ax.set_xlabel("Poisson noise scale (response units per photon)")
    ax.set_title("accuracy and flipped pixels against noise (Fig. 3, left)", fontsize=10)
    _legend_below(fig, handles, ncols=2)
    save_png(fig, path)
