"""Matplotlib PNGs of the noise reports: ENOB per scene, flips against power, error against time.

Every figure is drawn off-screen (Agg) and written atomically.
"""

from __future__ import annotations

from collections import defaultdict

import numpy as np

from .errors import EvtkError

__all__ = ["plot_enob", "plot_flips", "plot_tradeoff", "plot_recovery", "plot_success", "plot_robustness"]


def pyplot():
    """matplotlib.pyplot on the off-screen backend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_png(fig, path, dpi=100):
    """Write ``fig`` as a PNG at ``path`` (atomically) and close it."""
    from .io._atomic import AtomicFile

    plt = pyplot()
    try:
        fig.tight_layout()
        with AtomicFile(path) as out:
            fig.savefig(out.file, format="png", dpi=dpi)
    finally:
        plt.close(fig)


def plot_enob(scenes, path):
    """ENOB (eq. 8) of each scene with its bootstrap interval; noise-free scenes drawn as a marker at the top."""
    if not scenes:
        raise EvtkError("no scenes to plot")
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(max(4.0, 0.5 * len(scenes) + 2), 3.2))
    labels, finite = [], []
    for i, s in enumerate(scenes):
        labels.append(f"K{s['kernel_id']}F{s['features_id']}" if s["kernel_id"] >= 0 else "all")
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
    ax.set_xticklabels(labels, rotation=90 if len(scenes) > 8 else 0)
    ax.set_ylabel("ENOB (bits)")
    ax.set_title("effective bits per scene (eq. 8)")
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
    ax.set_xlabel(x_label)
    ax.set_ylabel("pixels flipped between repeats (%)")
    ax.legend()
    save_png(fig, path)


def plot_tradeoff(rows, path):
    """Work-precision plot: NRMSE against device time per capture, the Pareto front joined."""
    pts = [r for r in rows if r["nrmse"] is not None]
    if not pts:
        raise EvtkError("no settings with a defined error to plot")
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(5.5, 3.8))
    x = np.array([r["device_us_per_capture"] for r in pts])
    y = np.array([r["nrmse"] for r in pts])
    front = np.array([r["pareto"] for r in pts])
    ax.scatter(x[~front], y[~front], color="0.6", label="setting")
    order = np.argsort(x[front])
    ax.plot(x[front][order], y[front][order], "o-", color="C3", label="Pareto front")
    for r in pts:
        label = f"{r['window_us']}/{r['settle_us']}" + (f"/d{r['decimation']}" if r.get("decimation", 1) > 1 else "")
        ax.annotate(label, (r["device_us_per_capture"], r["nrmse"]),
                    fontsize=6, xytext=(3, 3), textcoords="offset points")
    if x.max() / max(x.min(), 1e-9) > 20:
        ax.set_xscale("log")
    ax.set_xlabel("device time per capture (us; labels: window/settle)")
    ax.set_ylabel("RMS error / RMS of ideal")
    ax.legend()
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
        by[(r["size"], r["method"], r.get("weights"))].append((r["power_mw"], r["recovered_pct"], r["exact_pct"]))
    for (size, method, weights), pts in sorted(by.items(), key=str):
        pts.sort()
        ax.plot([p[0] for p in pts], [p[1] for p in pts], "o-", label=f"{size}x{size} {method} ({weights or 'mse'})")
    ax.set_xscale("log")
    ax.set_ylim(-3, 103)
    ax.set_xlabel("laser power (mW)")
    ax.set_ylabel("recovered, exact or shifted (%)")
    ax.legend(fontsize=8)
    save_png(fig, path)


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
    fig.legend(loc="lower left", fontsize=8)
    save_png(fig, path)
