"""PNG figures of a bench run (matplotlib, Agg canvas, no display): metric bars per method,
accuracy against time, CD-L1 against point count (the accuracy sweep), and a montage of renders.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from .common import FSCORE_TAU_MM, GROUP_ACC_POINTS, GROUP_ORDER, finite
from .report import mean_std


def _figure(w: float, h: float):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(w, h), dpi=100)
    FigureCanvasAgg(fig)
    return fig


def _colours(keys: list) -> dict:
    from matplotlib import colormaps

    cmap = colormaps["tab10"]
    return {m: cmap(i % 10) for i, m in enumerate(keys)}


def _save_log_plot(fig, ax, path: Path, drawn: bool, xlabel: str, ylabel: str, title: str,
                   log_y: bool = False, legend_size: int = 8) -> Path:
    """Finish a log-x plot (log-y too when log_y; a "no rows" note when nothing was drawn) and save it."""
    if drawn:
        ax.set_xscale("log")
        if log_y:
            ax.set_yscale("log")
        ax.legend(fontsize=legend_size, loc="best")
    else:
        _no_rows(ax)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3, which="both")
    fig.savefig(path, facecolor="white")
    return Path(path)


def _no_rows(ax) -> None:
    ax.text(0.5, 0.5, "no successful rows", transform=ax.transAxes, ha="center")


def plot_metric_bars(path: Path, rows: list[dict], group: str | None = None) -> Path:
    """PNG bar chart, one bar per method (mean, std error bar) of CD-L1 (mm), Hausdorff (mm) and
    F-score for one case group (default: the first group with successful rows)."""
    ok = [r for r in rows if r.get("status") == "ok" and finite(r.get("cd_l1_mm"))]
    group = group or next((g for g in GROUP_ORDER if any(r.get("group") == g for r in ok)),
                          ok[0]["group"] if ok else None)
    sel = [r for r in ok if r.get("group") == group]
    methods = list(dict.fromkeys(r["method"] for r in sel))
    fig = _figure(13, 4.5)
    fig.suptitle(f"Surface accuracy per method: {group or 'no results'}")
    colours = _colours(methods)
    for k, (col, name) in enumerate((("cd_l1_mm", "CD-L1 (mm)"), ("hausdorff_mm", "Hausdorff (mm)"),
                                     ("fscore", f"F-score @ {FSCORE_TAU_MM:g} mm"))):
        ax = fig.add_subplot(1, 3, k + 1)
        stats = [mean_std(r.get(col) for r in sel if r["method"] == m) for m in methods]
        x = np.arange(len(methods))
        ax.bar(x, [s[0] for s in stats], yerr=[s[1] for s in stats], color=[colours[m] for m in methods], capsize=3)
        ax.set_xticks(x, methods, rotation=30, ha="right", fontsize=8)
        ax.set_title(name)
        ax.grid(axis="y", alpha=0.3)
        if not methods:
            _no_rows(ax)
    fig.subplots_adjust(bottom=0.3, wspace=0.3)
    fig.savefig(path, facecolor="white")
    return Path(path)


def plot_accuracy_vs_time(path: Path, rows: list[dict]) -> Path:
    """PNG scatter: CD-L1 (mm) against the method's wall time (s), both log scale, one colour per
    method, one marker per case group."""
    ok = [r for r in rows if r.get("status") == "ok" and finite(r.get("cd_l1_mm")) and finite(r.get("time_total_s"))]
    methods = list(dict.fromkeys(r["method"] for r in ok))
    colours = _colours(methods)
    markers = dict(zip(GROUP_ORDER, "osDP^X*"))
    fig = _figure(8, 5.5)
    ax = fig.add_subplot(1, 1, 1)
    for r in ok:
        ax.scatter(max(float(r["time_total_s"]), 1e-3), max(float(r["cd_l1_mm"]), 1e-4), color=colours[r["method"]],
                   marker=markers.get(r.get("group"), "v"), s=40, edgecolors="black", linewidths=0.4)
    for m in methods:
        ax.scatter([], [], color=colours[m], label=m)
    for g in dict.fromkeys(r.get("group") for r in ok):
        ax.scatter([], [], color="grey", marker=markers.get(g, "v"), label=g)
    return _save_log_plot(fig, ax, path, bool(ok), "wall time of the method (s)",
                          "CD-L1 (mm) vs the true surface (phantoms) or the input (others)",
                          "Accuracy vs time (colour: method, marker: case group)", log_y=True, legend_size=7)


def plot_cdl1_vs_points(path: Path, rows: list[dict]) -> Path:
    """PNG of the accuracy sweep: CD-L1 (mm, vs the true surface) against the number of input points
    (log x), SparseOcc default (solid) and screened Poisson (dashed), one colour per noise level (mm);
    the sweep's outlier-free point clouds of the ordinary phantom, mean over seeds."""
    from .sweep import is_default

    ok = [r for r in rows if r.get("group") == GROUP_ACC_POINTS and r.get("status") == "ok"
          and not r.get("outlier_fraction") and finite(r.get("cd_l1_mm")) and finite(r.get("n_points"))]
    noises = sorted({float(r.get("noise_mm") or 0.0) for r in ok})
    colours = _colours(noises)
    fig = _figure(8, 5.5)
    ax = fig.add_subplot(1, 1, 1)
    drawn = False
    for wanted, style in ((is_default, "-"), (lambda r: r.get("kind") == "poisson", "--")):
        for noise in noises:
            sel = [r for r in ok if wanted(r) and float(r.get("noise_mm") or 0.0) == noise]
            xs = sorted({int(r["n_points"]) for r in sel})
            ys = [mean_std(r["cd_l1_mm"] for r in sel if int(r["n_points"]) == x)[0] for x in xs]
            if xs:
                drawn = True
                ax.plot(xs, ys, style, marker="o", color=colours[noise], label=f"{sel[0]['method']}, noise {noise:g} mm")
    return _save_log_plot(fig, ax, path, drawn, "input points", "CD-L1 (mm) to the true surface",
                          "CD-L1 vs point count (solid: SparseOcc default, dashed: screened Poisson)")


def montage(path: Path, images: list[Path], columns: int = 2) -> Path | None:
    """One PNG tiling the given images (renders carry their own titles); None when there are none."""
    from matplotlib.image import imread

    images = [Path(p) for p in images if Path(p).exists()]
    if not images:
        return None
    rows_n = math.ceil(len(images) / columns)
    fig = _figure(6 * columns, 3.2 * rows_n)
    for i, p in enumerate(images):
        ax = fig.add_subplot(rows_n, columns, i + 1)
        ax.imshow(imread(p))
        ax.set_axis_off()  # each render carries its own title
    fig.subplots_adjust(left=0, right=1, bottom=0, top=0.95, wspace=0.02, hspace=0.1)
    fig.savefig(path, facecolor="white")
    return Path(path)
