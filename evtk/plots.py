"""Matplotlib PNGs of the noise reports: ENOB per scene, flips against power, error against time.

Every figure is drawn off-screen (Agg) and written atomically.
"""

from __future__ import annotations

from collections import defaultdict

import numpy as np

from .errors import EvtkError
from .io._atomic import AtomicFile
from .reconstruct import binarize, downsample

__all__ = ["contact_sheet", "wilson_interval", "plot_enob", "plot_flips", "plot_tradeoff", "plot_recovery", "plot_success",
           "plot_robustness"]


def pyplot():
    """matplotlib.pyplot on the off-screen backend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_png(fig, path, dpi=100):
    """Write ``fig`` as a PNG at ``path`` (atomically) and close it; room is kept for a figure title."""

    plt = pyplot()
    try:
        top = 1.0
        if fig._suptitle is not None:  # tight_layout leaves no room for it
            top = 1.0 - 0.5 / fig.get_figheight()
        fig.tight_layout(rect=(0.0, 0.0, 1.0, top))
        with AtomicFile(path) as out:
            fig.savefig(out.file, format="png", dpi=dpi)
    finally:
        plt.close(fig)


def contact_sheet(path, result, rows_per_page=8) -> list:
    """PNG pages of every response: measured and ideal on the cell grid, and both binarised.

    One row per response, ``rows_per_page`` rows a page; the first page is
    ``path``, the next ``<stem>-p2.png`` and so on (returned in order).
    Columns: the measured response and the ideal one (when known) with
    colour bars in response units, then the measured binary response and the
    ideal's, binarised by the same rule (``result.summary["binarize"]``) at the
    same size, so each flipped pixel shows. Row labels name kernel, features
    and repeat. Written atomically.
    """
    import os

    n = len(result.cells)
    if n == 0:
        raise EvtkError("no responses to draw")
    rows_per_page = max(1, int(rows_per_page))
    method = result.summary.get("binarize", "sign")
    try:
        method = float(method)
    except (TypeError, ValueError):
        pass
    ideal_binary = None
    if result.ideal is not None:
        ideal_binary = binarize(downsample(result.ideal, result.binary.shape[1:]), method)
    stem, ext = os.path.splitext(os.fspath(path))
    paths = []
    plt = pyplot()
    for page, start in enumerate(range(0, n, rows_per_page)):
        rows = range(start, min(n, start + rows_per_page))
        cols = [("measured", result.cells, True)]
        if result.ideal is not None:
            cols.append(("ideal", result.ideal, True))
        cols.append((f"measured, binary ({method})", result.binary, False))
        if ideal_binary is not None:
            cols.append(("ideal, binary", ideal_binary, False))
        fig, axes = plt.subplots(len(rows), len(cols), figsize=(2.9 * len(cols), 2.4 * len(rows) + 0.6),
                                 squeeze=False)
        for r, i in enumerate(rows):
            for c, (title, arr, bar) in enumerate(cols):
                ax = axes[r][c]
                im = ax.imshow(arr[i], cmap="gray", interpolation="nearest",
                               vmin=None if bar else -1, vmax=None if bar else 1)
                ax.set_xticks([])
                ax.set_yticks([])
                if r == 0:
                    ax.set_title(title, fontsize=9)
                if bar:
                    fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04).ax.tick_params(labelsize=7)
            if result.pairs is not None:
                k, f, rep = (int(v) for v in result.pairs[i])
                axes[r][0].set_ylabel(f"kernel {k}, features {f}\nrepeat {rep}", fontsize=8)
            else:
                axes[r][0].set_ylabel(f"window {i}", fontsize=8)
        pages = -(-n // rows_per_page)
        err = result.summary.get("error") or {}
        corr = err.get("correlation")
        fig.suptitle(f"responses {rows[0] + 1}-{rows[-1] + 1} of {n}"
                     + (f" (page {page + 1} of {pages})" if pages > 1 else "")
                     + ("" if corr is None else f"; correlation with the ideal {corr:.3f}"), fontsize=10)
        out = os.fspath(path) if page == 0 else f"{stem}-p{page + 1}{ext}"
        save_png(fig, out, dpi=80)
        paths.append(out)
    return paths


def plot_enob(scenes, path):
    """ENOB (eq. 8) of each scene with its interval; noise-free scenes drawn as a marker at the top."""
    if not scenes:
        raise EvtkError("no scenes to plot")
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(max(4.0, 0.5 * len(scenes) + 2), 3.2))
    labels, finite = [], []
    for i, s in enumerate(scenes):
        name = f"K{s['kernel_id']} F{s['features_id']}" if s["kernel_id"] >= 0 else "all windows"
        labels.append(f"{name}\nn={s['repeats']}")
        r = s["sinad"]
        if r is None or r.noise_free:
            continue
        finite.append(r.enob_bits)
        lo, hi = r.ci_enob if r.ci_enob is not None else (r.enob_bits, r.enob_bits)
        hi = hi if np.isfinite(hi) else r.enob_bits
        ax.errorbar(i, r.enob_bits, yerr=[[r.enob_bits - lo], [hi - r.enob_bits]], fmt="o", color="C0", capsize=3)
    top = max(finite) + 1 if finite else 1.0
    for i, s in enumerate(scenes):
        if s["sinad"] is not None and s["sinad"].noise_free:
            ax.plot(i, top, "^", color="C2")
    ax.set_xticks(range(len(scenes)))
    ax.set_xticklabels(labels, rotation=90 if len(scenes) > 8 else 0, fontsize=8)
    ax.set_xlabel("scene (kernel, features; n repeats)")
    ax.set_ylabel("ENOB (bits)")
    kinds = {s["sinad"].interval for s in scenes if s["sinad"] is not None and s["sinad"].interval}
    ax.set_title("effective bits per scene (eq. 8)" + (f", 95 % {kinds.pop()} interval" if len(kinds) == 1 else ""),
                 fontsize=10)
    save_png(fig, path)


def plot_flips(rows, path, x_key="power_mw", x_label="laser power (mW)"):
    """Flip rate against ``x_key`` (laser power), one line per kernel and their mean (the paper's Fig. 3, right)."""
    if not rows:
        raise EvtkError("no flip rates to plot")
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(5.0, 3.5))
    by_kernel = defaultdict(list)
    for r in rows:
        by_kernel[r["kernel_id"]].append((r[x_key], r["pairwise_pct"]))
    for _k, pts in sorted(by_kernel.items()):
        pts.sort()
        ax.plot([p[0] for p in pts], [p[1] for p in pts], color="0.7", lw=0.8)
    xs = sorted({r[x_key] for r in rows})
    mean = [np.mean([r["pairwise_pct"] for r in rows if r[x_key] == x]) for x in xs]
    ax.plot(xs, mean, "o-", color="C3", label=f"mean of {len(by_kernel)} kernels")
    if len(xs) > 1 and min(xs) > 0 and max(xs) / min(xs) > 20:
        ax.set_xscale("log")
    _tick_at(ax, xs)
    ax.set_xlabel(x_label)
    ax.set_ylabel("pixels flipped between repeats (%)")
    ax.set_title("binary pixels that flip between repeats (Fig. 3, right)", fontsize=10)
    ax.legend(fontsize=8)
    save_png(fig, path)


def _tick_at(ax, xs):
    """Ticks at the measured values only (no crowded log-axis labels), rotated when there are many."""
    from matplotlib.ticker import NullFormatter, NullLocator

    ax.xaxis.set_minor_locator(NullLocator())
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.set_xticks(list(xs))
    ax.set_xticklabels([f"{x:g}" for x in xs], rotation=45 if len(xs) > 5 else 0, fontsize=8)


def plot_tradeoff(rows, path):
    """Work-precision plot: NRMSE against device time per capture, the Pareto front joined."""
    pts = [r for r in rows if r["nrmse"] is not None]
    if not pts:
        raise EvtkError("no settings with a defined error to plot")
    plt = pyplot()
    fig, (ax, ax_c) = plt.subplots(1, 2, figsize=(10.0, 4.0), gridspec_kw={"width_ratios": [3, 2]})
    x = np.array([r["device_us_per_capture"] for r in pts])
    y = np.array([r["nrmse"] for r in pts])
    front = np.array([r["pareto"] for r in pts])
    powers = sorted({r["power_mw"] for r in pts})
    markers = "osD^v<>p*h"
    for j, pw in enumerate(powers):
        sel = np.array([r["power_mw"] == pw for r in pts])
        spread = np.array([r.get("nrmse_std") or 0.0 for r in pts])[sel]
        ax.errorbar(x[sel], y[sel], yerr=spread, color=f"C{j % 10}", marker=markers[j % len(markers)], ls="none",
                    capsize=2, label=f"{pw:g} mW", zorder=3)
        ax_c.errorbar([r["compute_us_per_capture"] for r, s in zip(pts, sel) if s], y[sel], yerr=spread,
                      color=f"C{j % 10}", marker=markers[j % len(markers)], ls="none", capsize=2)
    order = np.argsort(x[front])
    ax.plot(x[front][order], y[front][order], "-", color="0.2", lw=1.2, label="Pareto front", zorder=2)
    for r in pts:
        label = f"{r['window_us']}/{r['settle_us']}" + (f"/d{r['decimation']}" if r.get("decimation", 1) > 1 else "")
        ax.annotate(label, (r["device_us_per_capture"], r["nrmse"]),
                    fontsize=6, xytext=(3, 3), textcoords="offset points")
    if x.max() / max(x.min(), 1e-9) > 20:
        ax.set_xscale("log")
    ax.set_xlabel("device time per capture (µs; labels: window/settle µs)")
    ax.set_ylabel("RMS error / RMS of ideal")
    ax.set_title("error against device time per capture (bars: sd over responses)", fontsize=9)
    ax.legend(fontsize=8, title="laser power", title_fontsize=8)
    pipeline = {r.get("pipeline", "events") for r in pts}
    ax_c.set_xlabel("compute time per capture (µs)")
    ax_c.set_ylabel("RMS error / RMS of ideal")
    ax_c.set_title(f"error against compute time ({', '.join(sorted(pipeline))} pipeline)", fontsize=9)
    save_png(fig, path)


def plot_recovery(path, features, target_response, solution_response, result, true_kernel=None):
    """The paper's Fig. 4 for one recovery: features, target kernel and response, solution, loss per candidate."""
    plt = pyplot()
    panels = [("input features", features, "gray")]
    if true_kernel is not None:
        panels.append(("target kernel", true_kernel, "gray"))
    panels += [("target response", target_response, "viridis"),
               (f"solution kernel ({result.status or '?'})", result.kernel, "gray"),
               ("solution response", solution_response, "viridis")]
    with_curve = result.losses is not None
    fig = plt.figure(figsize=(2.3 * len(panels), 4.6 if with_curve else 2.6))
    grid = fig.add_gridspec(2 if with_curve else 1, len(panels))
    for i, (title, img, cmap) in enumerate(panels):
        ax = fig.add_subplot(grid[0, i])
        ax.imshow(np.asarray(img, dtype=float), cmap=cmap, interpolation="nearest")
        ax.set_title(title, fontsize=8)
        ax.set_xticks([])
        ax.set_yticks([])
    if with_curve:
        ax = fig.add_subplot(grid[1, :])
        ax.plot(result.losses, lw=0.6, color="0.3")
        best = int(np.argmin(result.losses))
        ax.plot(best, result.losses[best], "o", color="C3", label="solution")
        ax.set_yscale("log" if np.all(result.losses > 0) else "linear")
        ax.set_xlabel("candidate kernel (bits as a number)")
        ax.set_ylabel("loss")
        ax.legend(fontsize=8)
    save_png(fig, path)


def plot_success(rows, path):
    """Share of kernels recovered (exactly or up to a shift) against laser power."""
    if not rows:
        raise EvtkError("no success rates to plot")
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(5.0, 3.5))
    by = defaultdict(list)
    for r in rows:
        by[(r["size"], r["method"], r.get("weights"))].append((r["power_mw"], r["recovered_pct"], r["exact_pct"],
                                                               int(r["trials"])))
    trials = set()
    for (size, method, weights), pts in sorted(by.items(), key=str):
        pts.sort()
        ns = [n for _, _, _, n in pts]
        trials.update(ns)
        share = np.array([p[1] for p in pts]) / 100.0
        lo, hi = wilson_interval(share, np.array(ns))
        ax.errorbar([p[0] for p in pts], 100 * share, yerr=[100 * (share - lo), 100 * (hi - share)], fmt="o-",
                    capsize=3, label=f"{size}x{size} {method} ({weights or 'mse'})")
    ax.set_xscale("log")
    _tick_at(ax, sorted({r["power_mw"] for r in rows}))
    ax.set_ylim(-3, 103)
    ax.set_xlabel("laser power (mW)")
    ax.set_ylabel("recovered, exact or shifted (%)")
    n_text = ", ".join(str(n) for n in sorted(trials))
    ax.set_title(f"kernels recovered (n = {n_text} trials a point; 95 % Wilson intervals)", fontsize=9)
    ax.legend(fontsize=8)
    save_png(fig, path)


def wilson_interval(share, n, z=1.959963984540054):
    """Wilson score interval of binomial shares ``share`` out of ``n`` trials (95 % by default)."""
    share = np.asarray(share, dtype=float)
    n = np.maximum(np.asarray(n, dtype=float), 1.0)
    centre = (share + z * z / (2 * n)) / (1 + z * z / n)
    half = z * np.sqrt(share * (1 - share) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return np.clip(centre - half, 0.0, 1.0), np.clip(centre + half, 0.0, 1.0)


def plot_robustness(result, path):
    """Fig. 3 (left): accuracy and flipped pixels against the Poisson noise scale."""
    rows = result["rows"]
    if not rows:
        raise EvtkError("no noise levels to plot")
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(5.0, 3.5))
    xs = [r["scale"] for r in rows]
    ax.plot(xs, [100 * r["accuracy"] for r in rows], "o-", color="C0", label="test accuracy")
    ax.axhline(100 * result["r"], color="C0", ls=":", lw=0.8)
    ax.set_ylabel("test accuracy (%)")
    ax2 = ax.twinx()
    ax2.plot(xs, [r["flip_pct"] for r in rows], "s--", color="C3", label="flipped pixels")
    ax2.set_ylabel("flipped pixels (%)")
    if min(xs) >= 0 and max(xs) > 0 and len([x for x in xs if x > 0]) > 1:
        ax.set_xscale("symlog", linthresh=min(x for x in xs if x > 0))
    ax.set_xlabel("Poisson noise scale (response units per photon)")
    ax.set_title("accuracy and flipped pixels against noise (Fig. 3, left)", fontsize=10)
    handles = ax.get_legend_handles_labels()[0] + ax2.get_legend_handles_labels()[0]
    ax.legend(handles, [h.get_label() for h in handles], fontsize=8, loc="center left", framealpha=0.9)
    save_png(fig, path)
