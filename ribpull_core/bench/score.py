"""Scoring a run against the truth: surface metrics of its mesh (mm and paper units) against the
true phantom surface (else the input), its skeleton against the true centerlines, and rib separation
(how many of the phantom's separable ribs came out as their own mesh component).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .common import FSCORE_TAU_MM, SEPARATION_GAP_MM, case_labels, merge_row


def load_reference(case: dict):
    """(reference, name) for scoring: the true mesh for phantom cases, else the input points (for
    label maps the centres of the boundary voxel faces, the surface the segmentation draws)."""
    import trimesh

    from ..io import load_point_cloud
    from ..pointcloud import mask_boundary_cloud

    if case.get("truth_mesh"):
        return trimesh.load(case["truth_mesh"], force="mesh"), "true surface"
    cloud = load_point_cloud(Path(case["input_path"]), labels=case_labels(case))
    if case["input_kind"] == "mask":
        return mask_boundary_cloud(cloud, max_points=10**9), "label-map boundary (voxel face centres)"
    return cloud, "input points"


def score_surface(case: dict, mesh, paper_units_per_mm: float, n_samples: int, seed: int) -> dict:
    """surface_metrics of a mesh (mm) against the case's reference, n_samples per side; columns of
    results.csv (lengths in mm and paper units, mesh components / watertightness / faces)."""
    from ..metrics import mesh_summary, surface_metrics

    reference, name = load_reference(case)
    s = surface_metrics(mesh, reference, n_samples=n_samples, tau_mm=FSCORE_TAU_MM,
                        paper_units_per_mm=paper_units_per_mm, seed=seed)
    ms = mesh_summary(mesh)
    keep = ("cd_l1_mm", "cd_l2_mm2", "hausdorff_mm", "cd_l1_paper", "cd_l2_paper", "hausdorff_paper",
            "cd_l1_sampled_mm", "hausdorff_sampled_mm", "normal_consistency", "fscore", "precision", "recall",
            "tau_mm", "paper_units_per_mm")
    return {**{k: s[k] for k in keep}, "reference": name, "metric_samples": n_samples,
            "mesh_components": ms["components"], "mesh_watertight": ms["watertight"], "mesh_faces": ms["n_faces"]}


def score_separation(case: dict, mesh) -> dict:
    """n_separable (the phantom's ribs at least SEPARATION_GAP_MM from every other rib:
    phantom.separable_ribs) and n_isolated (those that are their own component of `mesh` (mm):
    phantom.isolated_ribs) for a phantom case; {} for other cases. The phantom is rebuilt from the
    case's seed and sternum flag. A failure here leaves a note instead of failing the run."""
    if not case.get("phantom"):
        return {}
    try:
        from ..phantom import isolated_ribs, make_phantom, separable_ribs
        from .plan import phantom_config

        phantom = make_phantom(phantom_config(case["seed"], bool(case.get("sternum"))))
        names = list(separable_ribs(phantom, min_gap_mm=SEPARATION_GAP_MM))
        isolated = isolated_ribs(mesh, phantom, names=names)
        return {"n_separable": len(names), "n_isolated": int(sum(bool(isolated.get(n)) for n in names))}
    except Exception as exc:  # noqa: BLE001  (separation is an extra column; the surface scores stand)
        return {"note": f"separation not scored ({type(exc).__name__}: {exc})"[:300]}


def load_centerlines(path: str) -> dict[str, np.ndarray]:
    """True centerlines {name: (n, 3) mm} from a centerlines.json written by write_phantom."""
    d = json.loads(Path(path).read_text())
    return {k: np.asarray(v["points"], dtype=np.float64) for k, v in d["ribs"].items()}


def score_skeleton(case: dict, skeleton) -> dict:
    """skeleton_metrics against the case's true centerlines as skel_* columns (empty without truth)."""
    from ..skeleton import skeleton_metrics

    if skeleton is None or not case.get("centerlines"):
        return {}
    m = skeleton_metrics(skeleton, load_centerlines(case["centerlines"]))
    keys = ("mean_dist_mm", "p95_dist_mm", "max_dist_mm", "coverage", "n_paths", "n_branch_nodes", "n_cycles",
            "label_accuracy", "n_curves")
    return {f"skel_{k}": m.get(k) for k in keys}


def render_run(path: Path, mesh, skeleton, title: str) -> None:
    """render_preview of a mesh (mm) and its skeleton curves."""
    from ..render import render_preview

    polylines = [skeleton.curve_points(c) for c in skeleton.curves] if skeleton is not None else None
    render_preview(path, mesh, polylines, title=title)


def score_and_render(task: dict, timer, mesh, skeleton, paper_units_per_mm: float | None) -> dict:
    """The scoring columns of a run: surface metrics and rib separation of `mesh` (when
    paper_units_per_mm is given) and skeleton metrics against the case's truth, timed as stage
    "score" (timer: run.StageTimer); renders the run if the task asks."""
    case, spec = task["case"], task["spec"]
    row: dict = {}
    with timer("score"):
        if paper_units_per_mm is not None:
            row.update(score_surface(case, mesh, paper_units_per_mm, task["metric_samples"], int(case["seed"])))
            merge_row(row, score_separation(case, mesh))
        row.update(score_skeleton(case, skeleton))
    row["time_score_s"] = round(timer.times["score"], 3)
    if task.get("render"):
        render_run(Path(task["rundir"]) / "render.png", mesh, skeleton, f"{spec['label']} — {case['name']}")
    return row
