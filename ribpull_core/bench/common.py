"""Constants and small value helpers shared by the bench modules (no science here).

Lengths are in mm, times in seconds, memory in MB (2**20 bytes).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

REPO_ROOT = Path(__file__).resolve().parents[2]
#: the real TotalSegmentator label map shipped next to the repository (../shared/data/...)
REAL_LABEL_MAP = REPO_ROOT.parent / "shared" / "data" / "totalseg_example_seg.nii.gz"
#: the skeleton benchmark whose voxel-thinning baseline (`voxel_skeleton`) is reused here
SKELETON_BENCHMARK = REPO_ROOT / "benchmarks" / "skeleton_phantom.py"

METRIC_SAMPLES = 1_000_000  # samples per side for the surface metrics (sub-mm resolution; methods.md)
PIPELINE_METRIC_SAMPLES = 10_000  # the pipeline's own vs-input metrics (unused here: we score apart)
FSCORE_TAU_MM = 1.0
#: smallest gap (mm) between two ribs for them to count as separable (phantom.separable_ribs)
SEPARATION_GAP_MM = 1.5

GROUP_POINTS = "phantom point clouds"
GROUP_SWEEP = "phantom sweeps (noise, point count)"
GROUP_MASK = "phantom voxel masks"
GROUP_ACC_POINTS = "accuracy sweep: phantom point clouds"
GROUP_ACC_MASKS = "accuracy sweep: partial-volume label maps"
GROUP_ACC_STERNUM = "accuracy sweep: sternum phantom"
GROUP_REAL = "real label map"
GROUP_USER = "user files"
#: the groups of `--plan sweep` (they get the sweep section of results.md)
ACCURACY_GROUPS = (GROUP_ACC_POINTS, GROUP_ACC_MASKS, GROUP_ACC_STERNUM)
GROUP_ORDER = (GROUP_POINTS, GROUP_SWEEP, GROUP_MASK, *ACCURACY_GROUPS, GROUP_REAL, GROUP_USER)
#: groups whose table has one line per (method, case) instead of pooling the cases
GROUPS_BY_CASE = (GROUP_SWEEP, *ACCURACY_GROUPS)

#: per-stage columns (seconds and peak resident MB); which stages a row has depends on the method
STAGES = ("load", "normals", "fit", "mesh", "sdf", "skeleton", "metrics", "export", "score")

#: results.csv columns, in order (rows may carry extra keys; they are appended sorted)
COLUMNS = (
    "method", "kind", "preset", "fit_method", "case", "variant", "group", "input_kind", "seed", "noise_mm",
    "n_points", "outlier_fraction", "spacing_mm", "partial_volume", "sternum",
    "status", "note", "reference", "metric_samples", "paper_units_per_mm",
    "cd_l1_mm", "cd_l2_mm2", "hausdorff_mm", "cd_l1_paper", "cd_l2_paper", "hausdorff_paper",
    "cd_l1_sampled_mm", "hausdorff_sampled_mm", "normal_consistency", "fscore", "precision", "recall",
    "tau_mm",
    "mesh_components", "mesh_watertight", "mesh_faces", "n_separable", "n_isolated",
    "skel_mean_dist_mm", "skel_p95_dist_mm", "skel_max_dist_mm", "skel_coverage", "skel_n_paths",
    "skel_n_branch_nodes", "skel_n_cycles", "skel_label_accuracy", "skel_n_curves",
    "iterations_planned", "iterations_run", "ms_per_iteration", "fit_overhead_s", "time_total_s",
    *(f"time_{s}_s" for s in STAGES), "wall_s",
    "peak_rss_mb", *(f"rss_{s}_mb" for s in STAGES),
    "n_parameters", "weights_bytes_fp32", "weights_bytes_fp16", "input_bytes", "weights_to_input_fp32",
    "mesh_bytes", "torch_threads", "device",
)


def finite(x) -> bool:
    """True for a value that parses as a finite float (None, "", NaN, text: False)."""
    try:
        return x is not None and x != "" and math.isfinite(float(x))
    except (TypeError, ValueError):
        return False


def num(x) -> float:
    """float(x), NaN when x is not a finite number."""
    return float(x) if finite(x) else float("nan")


def slug(text: str) -> str:
    """File-name-safe version of a label."""
    return "".join(ch if ch.isalnum() or ch in "-." else "_" for ch in text).strip("_")


def json_default(o):
    """json.dumps fallback for numpy scalars and paths."""
    if isinstance(o, (np.floating, np.integer, np.bool_)):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o)}")


def merge_row(row: dict, extra: dict) -> dict:
    """row.update(extra), except that a "note" in both is joined (space-separated) instead of replaced."""
    note = " ".join(x for x in (row.get("note"), extra.get("note")) if x)
    row.update(extra)
    if note:
        row["note"] = note
    return row


def spacing_label(spacing_mm) -> str:
    """"1.5" for an isotropic voxel size (a number or three equal ones), else "0.75x0.75x2.5"."""
    s = [float(v) for v in np.broadcast_to(np.asarray(spacing_mm, dtype=np.float64), (3,))]
    return f"{s[0]:g}" if s[0] == s[1] == s[2] else "x".join(f"{v:g}" for v in s)


def case_labels(case: dict) -> list[int] | None:
    """The NIfTI label values a case (plan.Case as a dict) is read with (None: the loader's default,
    the rib labels)."""
    return [int(v) for v in case["labels"]] if case.get("labels") else None
