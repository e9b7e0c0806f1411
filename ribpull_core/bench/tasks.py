"""What a bench child process does for each method kind (TASK_RUNNERS): a neural method through
`pipeline.run_pipeline`; a classical baseline (screened Poisson, mask marching cubes, mc_taubin)
with the pipeline's clean-up and skeleton; the skeleton section's truth runs; the speed section's
fit-only timing. Every runner returns its row's columns (times in s, memory in MB, lengths in mm).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

from .baselines import (
    POISSON_DEPTH,
    TAUBIN_ITERATIONS,
    flood_fill_normals,
    mask_marching_cubes,
    poisson_mesh,
    voxel_thinning_skeleton,
)
from .common import PIPELINE_METRIC_SAMPLES, STAGES, case_labels
from .plan import MASK_SPACING_MM
from .score import score_and_render


def iteration_cost(marks: list[tuple[float, int]], fit_s: float, iterations_run: int) -> dict:
    """ms_per_iteration from (perf_counter s, iteration) progress marks (slope between the first and
    the last mark, so set-up and the first iteration are excluded), else fit_s / iterations_run; and
    fit_overhead_s = fit_s - ms_per_iteration x iterations_run (set-up, query sampling, level)."""
    if len(marks) >= 2 and marks[-1][1] > marks[0][1]:
        ms = 1000.0 * (marks[-1][0] - marks[0][0]) / (marks[-1][1] - marks[0][1])
    else:
        ms = 1000.0 * fit_s / max(1, iterations_run)
    return {"ms_per_iteration": round(ms, 2), "fit_overhead_s": round(max(0.0, fit_s - ms * iterations_run / 1000.0), 3)}


def progress_recorder(sampler=None) -> tuple:
    """(on_progress, marks): a pipeline progress callback that appends (perf_counter s, iteration) of
    every fit-stage report to marks and, with a sampler (run.RssSampler), charges memory to each
    reported stage."""
    marks: list[tuple[float, int]] = []

    def on_progress(p):
        if sampler is not None and p.stage != sampler.stage:
            sampler.set(p.stage)
        if p.stage == "fit" and p.iteration is not None:
            marks.append((time.perf_counter(), int(p.iteration)))

    return on_progress, marks


def skeleton_of(mesh, cloud):
    """The pipeline's skeleton of a mesh (20k samples, curves named by the input's labels if any)."""
    from ..pipeline import _Reporter, _skeleton_of

    return _skeleton_of(mesh, cloud, _Reporter(None, None))


def run_pipeline_task(task: dict, sampler, timer) -> dict:
    """A neural method through run_pipeline, then scored; returns the row's columns."""
    import trimesh

    from ..pipeline import PipelineOptions, run_pipeline
    from ..skeleton import Skeleton

    case, spec, rundir = task["case"], task["spec"], Path(task["rundir"])
    on_progress, marks = progress_recorder(sampler)
    options = PipelineOptions(preset=spec["preset"], method=spec["method"], iterations=spec["iterations"],
                              resolution=spec["resolution"], seed=int(case["seed"]), preview=False,
                              device=task["device"], metrics_samples=PIPELINE_METRIC_SAMPLES,
                              labels=case_labels(case))
    result = run_pipeline(Path(case["input_path"]), rundir / "artifacts", options, progress=on_progress)
    m = result.metrics
    row = {f"time_{k}_s": v for k, v in m["timings_s"].items() if k in STAGES}
    row.update(time_total_s=m["timings_s"]["total"], fit_method=m["method"], iterations_run=m["iterations_run"],
               iterations_planned=m["iterations_planned"], torch_threads=m.get("torch_threads"), device=m.get("device"),
               **iteration_cost(marks, m["timings_s"]["fit"], m["iterations_run"]))
    w = m["weights"]
    row.update(n_parameters=w["n_parameters"], weights_bytes_fp32=w["weights_bytes_fp32"],
               weights_bytes_fp16=w["weights_bytes_fp16"], input_bytes=w["input_bytes"],
               weights_to_input_fp32=w["ratio_fp32"], mesh_bytes=result.artifacts["mesh.ply"].stat().st_size)
    mesh = trimesh.load(result.artifacts["mesh.ply"], force="mesh")
    skel = Skeleton.from_json(json.loads(result.artifacts["skeleton.json"].read_text())) if "skeleton.json" in result.artifacts else None
    row.update(score_and_render(task, timer, mesh, skel, 1.0 / m["frame"]["half_extent_mm"]))
    return row


def classical_mesh(cloud, kind: str, timer=None) -> tuple:
    """(mesh mm, note) of a classical baseline on a loaded cloud (io.PointCloud, mm): "poisson" is
    screened Poisson on flood-fill-oriented normals with the pipeline's clean-up of unsupported
    pieces; "mask_mc" / "mc_taubin" is marching cubes on the cloud's mask, plain or with
    TAUBIN_ITERATIONS Taubin passes. timer (run.StageTimer, optional) times normals / fit / mesh."""
    import contextlib

    from ..mesh import remove_unsupported_components
    from ..pipeline import support_distance_mm

    stage = timer or (lambda name: contextlib.nullcontext())
    if kind == "poisson":
        with stage("normals"):
            normals = flood_fill_normals(cloud.points)
        with stage("fit"):
            mesh = poisson_mesh(cloud.points, normals)
        with stage("mesh"):
            mesh, cleanup = remove_unsupported_components(mesh, cloud.points, support_distance_mm(cloud.points))
        return mesh, (f"depth {POISSON_DEPTH}, flood-fill-oriented PCA normals (input normals ignored); "
                      f"removed {cleanup['removed_unsupported']} unsupported + {cleanup['removed_cavities']} cavity components")
    taubin = TAUBIN_ITERATIONS if kind == "mc_taubin" else 0
    with stage("mesh"):
        mesh = mask_marching_cubes(cloud, taubin_iterations=taubin)
    return mesh, "marching cubes at 0.5 on the binary mask of the selected labels" + (
        f", then {taubin} Taubin passes (trimesh filter_taubin, lambda = nu = 0.5)" if taubin else "")


def run_classical_task(task: dict, sampler, timer) -> dict:
    """A classical baseline (classical_mesh: screened Poisson on the points, or marching cubes on
    the mask, plain or Taubin-smoothed for "mc_taubin"); then the pipeline's skeleton and the
    scoring. Returns the row's columns."""
    from ..frame import UnitFrame
    from ..io import load_point_cloud

    case, spec, rundir = task["case"], task["spec"], Path(task["rundir"])
    row: dict = {"fit_method": spec["kind"]}
    with timer("load"):
        cloud = load_point_cloud(Path(case["input_path"]), labels=case_labels(case))
    mesh, row["note"] = classical_mesh(cloud, spec["kind"], timer)
    with timer("export"):
        mesh.export(rundir / "mesh.ply")
    with timer("skeleton"):
        skel = skeleton_of(mesh, cloud)
    row.update(timer.columns())
    row.update(input_bytes=cloud.source_bytes, mesh_bytes=(rundir / "mesh.ply").stat().st_size, device="cpu")
    row.update(score_and_render(task, timer, mesh, skel, UnitFrame.fit(cloud.points).paper_units_per_mm))
    return row


def run_skeleton_task(task: dict, sampler, timer) -> dict:
    """Skeleton section: the project's contraction on the TRUE surface ("contraction_truth") or voxel
    thinning of the true solid at MASK_SPACING_MM ("voxel_thinning"), scored against the true
    centerlines. Voxelising the phantom is timed apart (time_load_s)."""
    import trimesh

    from ..io import load_point_cloud
    from ..phantom import make_phantom, voxelize
    from .plan import phantom_config

    case, spec = task["case"], task["spec"]
    mesh = None
    if spec["kind"] == "contraction_truth":
        with timer("load"):
            mesh = trimesh.load(case["truth_mesh"], force="mesh")
            cloud = load_point_cloud(Path(case["input_path"]))
        with timer("skeleton"):
            skel = skeleton_of(mesh, cloud)
    else:
        with timer("load"):
            vol, affine = voxelize(make_phantom(phantom_config(case["seed"], bool(case.get("sternum")))),
                                   MASK_SPACING_MM)
        with timer("skeleton"):
            skel = voxel_thinning_skeleton(vol, affine)
    return {**timer.columns(), **score_and_render(task, timer, mesh, skel, None)}


def run_speed_task(task: dict, sampler, timer) -> dict:
    """Fit only (pipeline.fit_field) of spec's preset for spec's iterations; per-iteration cost and the
    extrapolated fit time of the preset's full schedule (overhead + schedule x ms/iteration)."""
    from ..io import load_point_cloud
    from ..methods import build_fit_config
    from ..pipeline import _Reporter, configure_torch_threads, fit_field, select_device

    case, spec = task["case"], task["spec"]
    threads = configure_torch_threads()
    on_progress, marks = progress_recorder()
    with timer("load"):
        cloud = load_point_cloud(Path(case["input_path"]))
    cfg = build_fit_config(spec["preset"], spec["method"], spec["iterations"], seed=int(case["seed"]))
    schedule = build_fit_config(spec["preset"], spec["method"]).method_config.iterations
    with timer("fit"):
        field_, _ = fit_field(cloud, cfg, select_device(task["device"]), _Reporter(on_progress, None))
    cost = iteration_cost(marks, timer.times["fit"], field_.iterations_run)
    return {**timer.columns(), **cost, "iterations_run": field_.iterations_run, "iterations_planned": schedule,
            "batch_size": getattr(cfg.method_config, "batch_size", None), "torch_threads": threads,
            "extrapolated_fit_s": round(cost["fit_overhead_s"] + schedule * cost["ms_per_iteration"] / 1000.0, 1)}


TASK_RUNNERS = {
    "pipeline": run_pipeline_task, "poisson": run_classical_task, "mask_mc": run_classical_task,
    "mc_taubin": run_classical_task, "contraction_truth": run_skeleton_task, "voxel_thinning": run_skeleton_task,
    "speed": run_speed_task,
}
