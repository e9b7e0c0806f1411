"""Writing what a bench run measured: results.csv (and skeleton.csv, speed.csv, sweep.csv), the
markdown tables of results.md (the paper's table format: lengths in mm and paper units), and
`rewrite_outputs`, which rebuilds results.md and the plots from the CSVs.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

from .common import COLUMNS, FSCORE_TAU_MM, GROUP_ORDER, GROUPS_BY_CASE, finite, num
from .plan import preset_schedule

#: the paper's Table 1 (mean +- std over 20 RibSeg cases, paper units), from shared/notes/methods.md
PAPER_TABLE1 = {
    "SparseOcc": ("1.55 ± 0.24", "1.04 ± 0.16", "12.6 ± 4.39"),
    "Neural-Pull": ("5.81 ± 0.38", "3.90 ± 0.26", "8.25 ± 3.22"),
    "DiGS": ("8.04 ± 10.1", "5.36 ± 6.71", "36.8 ± 23.0"),
}

# ------------------------------------------------------------------------------------ CSV


def read_csv(path: Path) -> list[dict]:
    """Rows of a CSV written by write_csv, numbers parsed back (int, float, bool), empty cells None."""
    def parse(v: str):
        if v == "":
            return None
        if v in ("True", "False"):
            return v == "True"
        for kind in (int, float):
            try:
                return kind(v)
            except ValueError:
                pass
        return v

    with open(path, newline="") as fh:
        return [{k: parse(v) for k, v in r.items()} for r in csv.DictReader(fh)]


def write_csv(path: Path, rows: list[dict], columns=COLUMNS) -> Path:
    """rows -> CSV with `columns` first, then any other keys (sorted); missing values are empty."""
    extra = sorted({k for r in rows for k in r} - set(columns))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=[*columns, *extra], extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow({k: ("" if v is None else v) for k, v in r.items()})
    return path


# ------------------------------------------------------------------------------ formatting


def decimals_for(x: float) -> int:
    """Decimals that show ~3 significant digits of x (1 to 4): 1.55 -> 2, 12.6 -> 1, 0.712 -> 3."""
    if not finite(x) or x == 0:
        return 3
    return int(min(4, max(1, 2 - math.floor(math.log10(abs(x))))))


def mean_std(values) -> tuple[float, float, int]:
    """(mean, sample std (n-1; 0 when n = 1), n) of the finite values; (nan, nan, 0) if none."""
    v = np.array([float(x) for x in values if finite(x)])
    if len(v) == 0:
        return float("nan"), float("nan"), 0
    return float(v.mean()), float(v.std(ddof=1)) if len(v) > 1 else 0.0, len(v)


def fmt_pm(values) -> str:
    """"mean ± std" of the finite values (decimals from the mean), "—" when there are none."""
    m, s, n = mean_std(values)
    if n == 0:
        return "—"
    d = decimals_for(m)
    return f"{m:.{d}f} ± {s:.{d}f}"


def fmt_mean(values, digits: int | None = None) -> str:
    """Mean of the finite values, "—" when none."""
    m, _, n = mean_std(values)
    if n == 0:
        return "—"
    return f"{m:.{digits if digits is not None else decimals_for(m)}f}"


def md_table(headers: list[str], body: list[list], align: str | None = None) -> list[str]:
    """Markdown lines of a table: header, rule (align: one character per column, "l" left, anything
    else right; default: first column left, the rest right) and one line per body row."""
    align = align or "l" + "r" * (len(headers) - 1)
    assert len(align) == len(headers), (align, headers)
    rule = "|" + "".join("---|" if a == "l" else "---:|" for a in align)
    return ["| " + " | ".join(headers) + " |", rule, *("| " + " | ".join(str(c) for c in r) + " |" for r in body)]


# ---------------------------------------------------------------------------------- tables


#: (header, column, formatter) of the accuracy table
ACCURACY_COLUMNS = (
    ("CD-L1 (mm)", "cd_l1_mm", fmt_pm), ("CD-L2 (mm²)", "cd_l2_mm2", fmt_pm), ("HD (mm)", "hausdorff_mm", fmt_pm),
    ("CD-L1 [paper]", "cd_l1_paper", fmt_pm), ("CD-L2 [paper]", "cd_l2_paper", fmt_pm),
    ("HD [paper]", "hausdorff_paper", fmt_pm), ("NC", "normal_consistency", fmt_pm),
    (f"F@{FSCORE_TAU_MM:g}mm", "fscore", fmt_pm), ("time (s)", "time_total_s", fmt_pm),
    ("peak RSS (MB)", "peak_rss_mb", lambda v: fmt_mean(v, 0)), ("weights / input", "weights_to_input_fp32", fmt_mean),
)


def accuracy_table(rows: list[dict], group: str, by_case: bool = False) -> list[str]:
    """Markdown lines: one line per method of `group` (by_case: per case, then method), mean ± std
    over its successful rows (cases x seeds), lengths in mm and in paper units, NC, F-score, time,
    peak memory; failures counted."""
    sel = [r for r in rows if r.get("group") == group]

    def key(r: dict) -> str:
        return f"{r['case']}: {r['method']}" if by_case else r["method"]

    keys = sorted(dict.fromkeys(map(key, sel))) if by_case else list(dict.fromkeys(map(key, sel)))
    ref = next((r.get("reference") for r in sel if r.get("reference")), "—")
    body = []
    for k in keys:
        ok = [r for r in sel if key(r) == k and r.get("status") == "ok"]
        bad = [r for r in sel if key(r) == k and r.get("status") != "ok"]
        n = f"{len(ok)}" + (f" ({len(bad)} failed)" if bad else "")
        body.append([k, n, *(fmt([r.get(c) for r in ok]) for _, c, fmt in ACCURACY_COLUMNS)])
    return [f"### Surface accuracy: {group} (reference: {ref})", "",
            *md_table(["Case: method" if by_case else "Method", "n", *(h for h, _, _ in ACCURACY_COLUMNS)], body)]


def skeleton_table(rows: list[dict], case_name: str | None) -> list[str]:
    """Markdown lines of the skeleton section: every row of case_name with skeleton metrics."""
    body = []
    for r in (r for r in rows if r.get("case") == case_name and finite(r.get("skel_mean_dist_mm"))):
        src = r["method"] if r.get("kind") in ("contraction_truth", "voxel_thinning") else f"contraction on reconstruction: {r['method']}"
        lab = "—" if not finite(r.get("skel_label_accuracy")) else f"{float(r['skel_label_accuracy']):.2f}"
        body.append([src, f"{num(r['skel_mean_dist_mm']):.3f}", f"{num(r.get('skel_p95_dist_mm')):.3f}",
                     f"{num(r.get('skel_max_dist_mm')):.2f}", f"{num(r.get('skel_coverage')):.3f}", r.get("skel_n_paths"),
                     r.get("skel_n_branch_nodes"), r.get("skel_n_cycles"), lab, f"{num(r.get('time_skeleton_s')):.1f}"])
    return md_table(["Skeleton", "mean (mm)", "p95 (mm)", "max (mm)", "coverage@2mm", "paths", "branch nodes",
                     "cycles", "labels", "skeleton time (s)"], body)


def speed_entry(r: dict, preset: str, fit_s, pipeline_total_s, fit_s_kind: str) -> dict:
    """One measured line of the speed table from a (pipeline or speed-section) row."""
    return {"preset": preset, "method": r["method"], "case": r["case"], "iterations": r.get("iterations_run"),
            "schedule": r.get("iterations_planned"), "ms_per_iteration": r.get("ms_per_iteration"),
            "fit_overhead_s": r.get("fit_overhead_s"), "fit_s": fit_s, "pipeline_total_s": pipeline_total_s,
            "fit_s_kind": fit_s_kind}


def speed_rows(default_row: dict | None, timed: list[dict], paper_row: dict | None = None) -> list[dict]:
    """Rows of the speed table (paper vs default on the same case, same machine, same run), with the
    ratios: per-iteration cost and fit time (paper extrapolated to its full schedule / default
    measured). paper_row: a (shortened) paper-preset run of the plan on that case, preferred to the
    speed section's own short timing."""
    out = []
    d = default_row or next((r for r in timed if r.get("preset") == "default" and r.get("status") == "ok"), None)
    if d is not None and d.get("status") == "ok":
        out.append(speed_entry(d, "default", d.get("time_fit_s"), d.get("time_total_s"), "measured"))
    p = paper_row or next((r for r in timed if r.get("preset") == "paper"), None)
    if paper_row is not None and paper_row.get("status") == "ok" and finite(paper_row.get("ms_per_iteration")):
        schedule = preset_schedule("paper")
        p = {**paper_row, "iterations_planned": schedule,
             "extrapolated_fit_s": round(num(paper_row.get("fit_overhead_s")) + schedule * float(paper_row["ms_per_iteration"]) / 1000, 1)}
    if p is not None and p.get("status") == "ok":
        out.append(speed_entry(p, "paper", p.get("extrapolated_fit_s"), None,
                               f"extrapolated from {p.get('iterations_run')} iterations"))
    if len(out) == 2 and all(finite(r["ms_per_iteration"]) and finite(r["fit_s"]) for r in out):
        out.append({"preset": "ratio paper / default", "ms_per_iteration": out[1]["ms_per_iteration"] / out[0]["ms_per_iteration"],
                    "fit_s": out[1]["fit_s"] / out[0]["fit_s"], "fit_s_kind": "extrapolated / measured"})
    return out


def speed_table(speed: list[dict]) -> list[str]:
    """Markdown lines of the speed section."""
    body = []
    for r in speed:
        if r["preset"].startswith("ratio"):
            body.append([f"**{r['preset']}**", "", "", f"**{r['ms_per_iteration']:.2f}×**", "", f"**{r['fit_s']:.1f}×**",
                         r["fit_s_kind"]])
        else:
            body.append([f"{r['preset']} ({r['method']})", r.get("iterations"), r.get("schedule"),
                         f"{num(r.get('ms_per_iteration')):.1f}", f"{num(r.get('fit_overhead_s')):.1f}",
                         f"{num(r.get('fit_s')):.1f}", r["fit_s_kind"]])
    return md_table(["Preset", "iterations timed", "schedule", "ms / iteration", "fit overhead (s)", "fit time (s)",
                     "how"], body, align="lrrrrrl")


# ---------------------------------------------------------------------------------- results.md


def write_markdown(path: Path, rows: list[dict], skeleton_rows: list[dict] | None = None,
                   speed: list[dict] | None = None, meta: dict | None = None, notes: list[str] | None = None,
                   figures: list[str] | None = None, sweep_lines: list[str] | None = None) -> str:
    """results.md: run details, the accuracy sweep's section (sweep_lines, when given), one accuracy
    table per case group (paper format, mm and paper units), the paper's Table 1 for context, the
    skeleton and speed sections, notes, figures. Returns the text."""
    meta = meta or {}
    out = ["# RibPull benchmark", ""]
    for k, v in meta.items():
        out.append(f"- **{k}**: {v}")
    out += ["", ("Paper units: lengths in the input's normalised frame (longest bounding-box side = 2, as in the "
            "paper), CD-L1 and HD ×100, CD-L2 ×10⁴. mean ± std over cases × seeds (sample std; 0 for one row). "
            "NC: normal consistency; F: F-score at the given distance. time: the method's own wall time "
            "(scoring excluded); peak RSS: the child process's own peak (VmHWM)."), ""]
    if sweep_lines:
        out += sweep_lines + [""]
    for g in [*GROUP_ORDER, *sorted({r.get("group") for r in rows} - set(GROUP_ORDER) - {None})]:
        if any(r.get("group") == g for r in rows):
            out += accuracy_table(rows, g, by_case=g in GROUPS_BY_CASE) + [""]
    out += ["### For context: the paper's Table 1 (20 real RibSeg cases, paper units; not this run)", ""]
    out += md_table(["Method", "CD-L1", "CD-L2", "HD"], [[m, *v] for m, v in PAPER_TABLE1.items()]) + [""]
    if skeleton_rows is not None:
        case = skeleton_rows[0]["case"] if skeleton_rows else None
        out += [f"## Skeletons vs the true centerlines ({case})", "",
                ("Distances from the skeleton to the true centerlines (mm); coverage: fraction of the true centerline "
                "within 2 mm of the skeleton; a perfect ribcage has 24 paths, 0 branch nodes, 0 cycles."), ""]
        out += skeleton_table(skeleton_rows + rows, case) + [""]
    if speed is not None:
        out += ["## Speed: `paper` vs `default` preset (same machine, same run)", ""]
        out += speed_table(speed) if speed else ["(not measured)"]
        out += ["", ("The paper preset's full schedule is extrapolated from a shorter run as fit overhead + schedule × "
                "ms/iteration (slope between the first and last progress reports); the default preset's time is "
                "measured (early stopping included)."), ""]
    failed = [r for r in rows + (skeleton_rows or []) if r.get("status") != "ok"]
    if notes or failed:
        out += ["## Notes", ""] + [f"- {n}" for n in notes or []]
        out += [f"- {r['method']} on {r['case']} (seed {r['seed']}): {r.get('status')}: {r.get('note') or ''}" for r in failed]
        out.append("")
    if figures:
        out += ["## Figures", ""] + [f"![{Path(f).stem}]({f})" for f in figures] + [""]
    text = "\n".join(out)
    Path(path).write_text(text)
    return text


def write_outputs(outdir: Path, rows: list[dict], skeleton_rows=None, speed=None, meta=None, notes=None) -> dict:
    """results.csv, skeleton.csv, speed.csv, the plots, renders.png and results.md in outdir; with
    accuracy-sweep rows also sweep.csv, cdl1_vs_points.png and the sweep section of results.md.
    Returns {"markdown": text, name: path}."""
    from .plots import montage, plot_accuracy_vs_time, plot_cdl1_vs_points, plot_metric_bars
    from .sweep import has_sweep, sweep_section, sweep_summary

    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    paths = {"results.csv": write_csv(outdir / "results.csv", rows)}
    if skeleton_rows is not None:
        paths["skeleton.csv"] = write_csv(outdir / "skeleton.csv", skeleton_rows)
    if speed is not None:
        paths["speed.csv"] = write_csv(outdir / "speed.csv", speed, columns=())
    sweep_lines = None
    if has_sweep(rows):
        paths["sweep.csv"] = write_csv(outdir / "sweep.csv", sweep_summary(rows), columns=())
        paths["cdl1_vs_points.png"] = plot_cdl1_vs_points(outdir / "cdl1_vs_points.png", rows)
        sweep_lines = sweep_section(rows)
    paths["metrics_by_method.png"] = plot_metric_bars(outdir / "metrics_by_method.png", rows)
    paths["accuracy_vs_time.png"] = plot_accuracy_vs_time(outdir / "accuracy_vs_time.png", rows)
    renders = montage(outdir / "renders.png", sorted((outdir / "renders").glob("*.png")))
    if renders is not None:
        paths["renders.png"] = renders
    figures = [n for n in ("cdl1_vs_points.png", "metrics_by_method.png", "accuracy_vs_time.png", "renders.png")
               if n in paths]
    text = write_markdown(outdir / "results.md", rows, skeleton_rows, speed, meta, notes, figures, sweep_lines)
    paths["results.md"] = outdir / "results.md"
    return {"markdown": text, **paths}


def rewrite_outputs(outdir: Path, meta: dict | None = None, notes: list[str] | None = None) -> dict:
    """Rebuild results.md and the plots of outdir from its results.csv (+ skeleton.csv, speed.csv when
    present), e.g. after rows of several runs were put into one results.csv. Returns write_outputs'."""
    outdir = Path(outdir)
    if not (outdir / "results.csv").exists():
        from ..errors import RibPullInputError

        raise RibPullInputError("bad_parameter", f"{outdir / 'results.csv'} does not exist: nothing to rewrite")
    rows = read_csv(outdir / "results.csv")
    skel = read_csv(outdir / "skeleton.csv") if (outdir / "skeleton.csv").exists() else None
    speed = read_csv(outdir / "speed.csv") if (outdir / "speed.csv").exists() else None
    return write_outputs(outdir, rows, skel, speed, meta, notes)
