"""THE pipeline: input file -> fitted field -> mesh, SDF, skeleton, metrics, weights on disk.

`run_pipeline` is the one function the CLI (`ribpull fit`), the Celery worker and the benchmark call.
It reports progress through a callback and stops cleanly (raising `JobCanceled`) when its
cancellation check returns True. Bad input raises `RibPullInputError`; nothing is written to
`outdir` until a stage has finished (files are written to a temporary directory and moved in).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from .dicom.export import DICOM_ARTIFACTS
from .dicom.nifti_source import STUDY_CT_ARTIFACT

#: artifact file names the pipeline can produce (the service serves exactly these)
ARTIFACT_NAMES = (
    "mesh.ply", "mesh.stl", "mesh.obj", "mesh.glb",
    "sdf.nii.gz",
    "model.safetensors", "model.json",
    "metrics.json",
    "skeleton.json", "skeleton.glb", "skeleton.obj", "scene.glb",
    "preview.png",
) + DICOM_ARTIFACTS + (STUDY_CT_ARTIFACT,)  # DICOM ones: DICOM SEG inputs, and NIfTI ones with dicom_outputs


@dataclass
class PipelineOptions:
    """User-facing knobs (CLI flags and the service's `params` map onto these).

    preset: named FitConfig preset ("default", "paper", "smoke", ...); method: override the preset's
    method ("sparseocc", "neuralpull", "digs"); iterations / resolution: override the schedule and the
    finest marching-cubes resolution; labels: NIfTI label values to keep; skeleton: also extract the
    medial axis; device: "auto", "cpu" or "cuda"; reference: a mesh or point file to measure against
    instead of the input; metrics_samples: samples per side for the surface metrics; dicom_outputs:
    a NIfTI label map also gets the DICOM outputs (seg.dcm, measurements_sr.dcm, mesh_stl.dcm, in LPS)
    on a generated CT study (study_ct.zip); a DICOM SEG input gets them anyway; a point cloud is refused.
    """

    preset: str = "default"
    method: str | None = None
    iterations: int | None = None
    resolution: int | None = None
    labels: list[int] | None = None
    skeleton: bool = True
    preview: bool = True
    device: str = "auto"
    seed: int = 0
    reference: Path | None = None
    metrics_samples: int | None = None
    max_points: int = 2_000_000
    max_file_bytes: int = 512 * 1024 * 1024
    units: str = "mm"
    dicom_outputs: bool = False


@dataclass
class PipelineProgress:
    """stage: load|fit|mesh|sdf|skeleton|metrics|export|done; fraction: overall progress in [0, 1]."""

    stage: str
    fraction: float
    iteration: int | None = None
    iterations: int | None = None
    loss: float | None = None
    message: str = ""


@dataclass
class PipelineResult:
    outdir: Path
    artifacts: dict[str, Path] = field(default_factory=dict)
    metrics: dict = field(default_factory=dict)


ProgressCallback = Callable[[PipelineProgress], None]
CancelCheck = Callable[[], bool]


# --- implementation ----------------------------------------------------------------------------

import json
import os
import shutil
import tempfile
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import replace

import numpy as np

from .errors import JobCanceled, RibPullInputError
from .frame import UnitFrame
from .workshare import WorkShare

#: where each stage's progress lives in the overall [0, 1] fraction
STAGE_SPANS = {
    "load": (0.0, 0.02), "fit": (0.02, 0.72), "mesh": (0.72, 0.82), "sdf": (0.82, 0.88),
    "skeleton": (0.88, 0.95), "metrics": (0.95, 0.98), "export": (0.98, 1.0),
}


def select_device(name: str = "auto"):
    """torch.device for "auto" (CUDA when present, else CPU), "cpu" or "cuda[:i]"."""
    import torch

    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise RibPullInputError("bad_parameter", f"device {name!r} requested but no CUDA device is available; use 'cpu' or 'auto'")
    if name != "cpu" and not name.startswith("cuda"):
        raise RibPullInputError("bad_parameter", f"unknown device {name!r}; use 'auto', 'cpu' or 'cuda'")
    return torch.device(name)


def configure_torch_threads(n: int | None = None) -> int:
    """Set torch's intra-op threads (env RIBPULL_TORCH_THREADS, else all cores) and as many for the
    compiled hash-grid kernels (numba, at most its launch-time pool); returns the count.

    Both pools follow one count because two processes on two cores that each run 2 torch and 2
    numba threads were measured ~16x slower per training step (0.65 s against 0.04 s) than one
    thread each."""
    import numba
    import torch

    n = max(1, n or int(os.environ.get("RIBPULL_TORCH_THREADS", "0") or 0) or (os.cpu_count() or 1))
    torch.set_num_threads(n)
    numba.set_num_threads(min(n, numba.config.NUMBA_NUM_THREADS))
    return torch.get_num_threads()


class _Reporter:
    """Maps stage-local progress onto the overall fraction and forwards it; checks cancellation.

    Safe to call from the SDF's thread beside the calling one (`run_pipeline` runs the SDF beside
    the skeleton): calls are serialised, the fraction never goes back, and `abandon()` makes every
    later check() raise, so the other thread stops at its next check when one has failed."""

    def __init__(self, progress: ProgressCallback | None, should_cancel: CancelCheck | None):
        self.progress, self.user_cancel = progress, should_cancel
        self._lock = threading.Lock()
        self._fraction = 0.0
        self._abandoned = False

    def should_cancel(self) -> bool:
        if self._abandoned:
            return True
        with self._lock:
            return self.user_cancel is not None and bool(self.user_cancel())

    def abandon(self) -> None:
        self._abandoned = True

    def check(self) -> None:
        if self.should_cancel():
            raise JobCanceled("canceled")

    def __call__(self, stage: str, local: float, **kw) -> None:
        lo, hi = STAGE_SPANS[stage]
        if self.progress is None:
            return
        with self._lock:
            self._fraction = max(self._fraction, lo + (hi - lo) * min(max(local, 0.0), 1.0))
            self.progress(PipelineProgress(stage=stage, fraction=self._fraction, **kw))


def _label_map_samples(voxels, config, seed: int):
    """What the fit takes from a label map (a PointCloud of its voxel centres, mm) under a
    LabelMapConfig: its boundary points (`mask_boundary_cloud`), with the occupancy of the voxel
    centres near the boundary (`mask_band_samples`, band_voxels > 0) and the solid's coarse signed
    distance (`mask_signed_distance`, solid_distance_cell_mm > 0). The band samples are made in a
    thread beside the boundary points (both read the map alone; their single-threaded numpy
    overlaps: 0.75 x 0.75 x 2.5 mm map ~0.6 + 0.6 s)."""
    from .pointcloud import mask_band_samples, mask_boundary_cloud, mask_signed_distance

    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="ribpull-band") as pool:
        band_job = pool.submit(mask_band_samples, voxels, width_voxels=config.band_voxels, seed=seed) \
            if config.band_voxels > 0 else None
        cloud = mask_boundary_cloud(voxels, seed=seed, subvoxel_sigma_mm=config.boundary_sigma_mm,
                                    between_labels=config.between_labels)
        if band_job is not None:  # voxel centres near the boundary: occupancy the map states
            band = band_job.result()
            cloud = replace(cloud, occupancy_points=band.occupancy_points, occupancy_inside=band.occupancy_inside,
                            occupancy_distance_mm=band.occupancy_distance_mm)
    if config.solid_distance_cell_mm > 0:  # the map's solid, a warm start for the field
        cloud = mask_signed_distance(voxels, cloud, config.solid_distance_cell_mm)
    return cloud


def _reference_for_metrics(options: PipelineOptions, cloud):
    """The reference surface for the metrics: a user-given mesh/points file, else the input points."""
    if options.reference is None:
        return cloud, "input points"
    ref = Path(options.reference)
    if ref.suffix.lower() in (".stl", ".obj", ".glb", ".off") or (ref.suffix.lower() == ".ply" and _ply_has_faces(ref)):
        import trimesh

        mesh = trimesh.load(ref, force="mesh")
        if len(mesh.faces) == 0:
            raise RibPullInputError("parse_error", f"reference {ref.name} has no faces")
        return mesh, f"mesh {ref.name}"
    from .io import load_point_cloud

    return load_point_cloud(ref), f"points {ref.name}"


def _ply_has_faces(path: Path) -> bool:
    with open(path, "rb") as fh:
        head = fh.read(4096)
    for line in head.split(b"\n"):
        if line.startswith(b"element face"):
            return int(line.split()[-1]) > 0
        if line.startswith(b"end_header"):
            break
    return False


def fit_field(cloud, fit_config, device, report: _Reporter):
    """Fit the configured method to a PointCloud; returns (FittedField, UnitFrame). Stage "fit"."""
    from .methods import get_method_class

    frame = UnitFrame.fit(cloud.points)
    method_cfg = replace(fit_config.method_config, seed=fit_config.seed) if hasattr(fit_config.method_config, "seed") else fit_config.method_config
    method = get_method_class(fit_config.method)(method_cfg, unit_mm=frame.half_extent_mm)

    def on_fit(p):
        report("fit", p.iteration / max(1, p.iterations), iteration=p.iteration, iterations=p.iterations, loss=p.loss,
               message=p.message)

    known = None
    if cloud.occupancy_points is not None:
        from .methods.base import KnownOccupancy

        solid, unit_to_index = None, None
        if cloud.solid_distance_mm is not None:  # in the unit frame: distances / half extent, and
            # index = A^-1 (x_unit * half_extent + centre) for the volume's affine A (index -> mm)
            solid = np.asarray(cloud.solid_distance_mm, np.float32) / np.float32(frame.half_extent_mm)
            unit_to_mm = np.diag([frame.half_extent_mm] * 3 + [1.0])
            unit_to_mm[:3, 3] = frame.center_mm
            unit_to_index = (np.linalg.inv(np.asarray(cloud.solid_distance_affine, dtype=np.float64)) @ unit_to_mm)[:3]
        known = KnownOccupancy(frame.to_unit(cloud.occupancy_points).astype(np.float32), cloud.occupancy_inside,
                               np.asarray(cloud.occupancy_distance_mm) / frame.half_extent_mm, solid, unit_to_index)
    field = method.fit(frame.to_unit(cloud.points).astype(np.float32), device, progress=on_fit,
                       should_cancel=report.should_cancel, known=known, labels=cloud.labels)
    return field, frame


def run_pipeline(
    input_path: Path,
    outdir: Path,
    options: PipelineOptions | None = None,
    progress: ProgressCallback | None = None,
    should_cancel: CancelCheck | None = None,
) -> PipelineResult:
    """Input file -> artifacts in `outdir` (see ARTIFACT_NAMES) and a metrics dict (lengths in mm).

    Raises RibPullInputError for bad input or options and JobCanceled when should_cancel() is True.
    All files are written to a temporary sibling directory and moved into `outdir` at the end, so a
    failed or canceled run leaves `outdir` as it was.
    """
    from .io import load_point_cloud
    from .methods import build_fit_config
    from .refine import point_weights_of, refinement_patches

    options = options or PipelineOptions()
    report = _Reporter(progress, should_cancel)
    timings: dict[str, float] = {}
    t_all = time.perf_counter()

    def timed(stage):
        class _T:
            def __enter__(self_):
                report.check()
                report(stage, 0.0, message=f"{stage} started")
                self_.t = time.perf_counter()

            def __exit__(self_, *exc):
                # a stage entered twice (export: before and after the SDF) adds up
                timings[stage] = round(timings.get(stage, 0.0) + time.perf_counter() - self_.t, 3)
                return False

        return _T()

    fit_config = build_fit_config(options.preset, options.method, options.iterations, options.resolution, options.seed)
    if options.metrics_samples is not None:
        if options.metrics_samples < 1000:
            raise RibPullInputError("bad_parameter", "metrics_samples must be at least 1000")
        fit_config.metrics.n_samples = int(options.metrics_samples)
    device = select_device(options.device)
    threads = configure_torch_threads()

    outdir = Path(outdir)
    outdir.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".ribpull-", dir=outdir.parent))
    try:
        with timed("load"):
            cloud = load_point_cloud(Path(input_path), labels=options.labels, max_points=options.max_points,
                                     max_file_bytes=options.max_file_bytes, units=options.units)
            generated_study = None
            if options.dicom_outputs and cloud.dicom_source is None:  # a DICOM SEG input has its own study
                from .dicom.nifti_source import GeneratedStudy

                generated_study = GeneratedStudy.from_label_cloud(cloud)  # refuses a point cloud
            if cloud.nifti_affine is not None:
                # a label map's voxel centres fill the solid: fit (and score against) its boundary
                cloud = _label_map_samples(cloud, fit_config.label_map, options.seed)
            reference, reference_name = _reference_for_metrics(options, cloud)
        with timed("fit"), ThreadPoolExecutor(max_workers=1, thread_name_prefix="ribpull-patches") as pool:
            refine_plan = _plan_refinement(cloud, fit_config, options)

            def make_patches():  # the input's alone: beside the training, or beside marching cubes below
                return refinement_patches(cloud.points, refine_plan, point_weights_of(cloud, fit_config.refine))

            patch_job = pool.submit(make_patches) if _patches_beside_the_fit(cloud, refine_plan) else None
            field, frame = fit_field(cloud, fit_config, device, report)
            patches = patch_job.result() if patch_job is not None else None
        # One thread beside the main one from here on. It makes what depends on the input alone
        # while the mesh stage leaves a core idle part of its time: the refinement's patches where
        # the training did not (the mesh stage needs them after marching cubes: 1.5 mm label maps
        # ~0.6 s), then the metrics' reference; then the SDF.
        with ThreadPoolExecutor(max_workers=1, thread_name_prefix=ASIDE_THREAD_PREFIX) as aside:
            if patches is None and refine_plan is not None and refine_plan.applies:
                patches = aside.submit(make_patches)
            reference_job = aside.submit(_metrics_reference, reference, fit_config)
            with timed("mesh"):
                mesh = _surface_mesh(cloud, field, frame, fit_config, refine_plan, patches, report)
            # The SDF volume (and the weights) is made in the thread beside the skeleton, the
            # metrics and the files: each leaves a core idle much of its time (kd-tree waits,
            # single-threaded scipy), so together they take about the longer one's time (60k
            # points: 4.8 -> 3.3 s, 1.5 mm label map: 6.5 -> 4.7 s for the SDF, skeleton and
            # preview). timings_s keeps each stage's own wall time, so "sdf" overlaps the stages
            # after it.
            # The surface metrics need neither the SDF nor the skeleton. Their parts
            # (`_SurfaceMetricsWork`) go to whichever thread is free first: the SDF's after its
            # volume, the main one after the skeleton and the files, so that neither core idles
            # at the end while the other measures alone.
            surface_work = _SurfaceMetricsWork(mesh, reference_job, frame, fit_config, timings, report)

            # The SDF's point queries (a map whose voxel centres are not grid nodes: 12M on the
            # anisotropic one, the run's last work) are shared: the main thread, once done with the
            # skeleton and the files, takes chunks of them before the metrics' parts.
            sdf_share = WorkShare()

            def sdf_stage():
                t = time.perf_counter()
                out = _sdf_and_weights(cloud, mesh, field, frame, fit_config, tmp, report, sdf_share)
                timings["sdf"] = round(time.perf_counter() - t, 3)
                if not report.should_cancel():
                    surface_work.run_untaken()
                return out

            report("sdf", 0.0, message="sdf started")
            sdf_job = aside.submit(sdf_stage)
            try:
                skeleton = None
                artifacts = {}
                if options.skeleton:
                    with timed("skeleton"):
                        skeleton = _skeleton_of(mesh, cloud, report)
                        from .skeleton import export_skeleton

                        artifacts.update({k: Path(v) for k, v in export_skeleton(skeleton, tmp, mesh_mm=mesh).items()})
                with timed("export"):
                    from .mesh import export_mesh

                    artifacts.update({Path(v).name: Path(v) for v in export_mesh(mesh, tmp).values()})
                    if options.preview:
                        from .render import render_preview

                        polylines = _polylines(skeleton) if skeleton is not None else None
                        artifacts["preview.png"] = Path(render_preview(tmp / "preview.png", mesh, polylines,
                                                                       title=f"RibPull {fit_config.preset}"))
                report.check()
                # the metrics' parts, each after helping with the SDF's point queries if it is at
                # them: they are the longer thread's work
                surface_work.run_untaken(before_each=sdf_share.help)
                sdf_share.help()
                metrics = _metrics(cloud, surface_work.result(), reference_name, mesh, field, frame, fit_config, skeleton)
            except BaseException:
                report.abandon()  # the SDF thread stops at its next check; the pool then joins it
                raise
            sdf_artifacts, sdf = sdf_job.result()
        artifacts.update(sdf_artifacts)
        with timed("export"):
            if cloud.dicom_source is not None:  # a DICOM input gets DICOM results on its own geometry
                from .dicom.export import write_dicom_outputs

                artifacts.update(write_dicom_outputs(tmp, cloud, mesh, *sdf, metrics))
            elif generated_study is not None:  # a NIfTI input: the same objects on its generated CT, in LPS
                artifacts.update(generated_study.write_outputs(tmp, cloud, mesh, *sdf, metrics))
        metrics["timings_s"] = {**timings, "total": round(time.perf_counter() - t_all, 3)}
        metrics["device"] = str(device)
        metrics["torch_threads"] = threads
        metrics["options"] = {k: (str(v) if isinstance(v, Path) else v) for k, v in options.__dict__.items()}
        (tmp / "metrics.json").write_text(json.dumps(metrics, indent=2, default=_json_default))
        artifacts["metrics.json"] = tmp / "metrics.json"
        report.check()
        outdir.mkdir(parents=True, exist_ok=True)
        final = {}
        for name, path in artifacts.items():
            os.replace(path, outdir / name)
            final[name] = outdir / name
        report("export", 1.0, message="done")
        return PipelineResult(outdir=outdir, artifacts=final, metrics=metrics)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


#: the name prefix of the thread beside the main one after the fit (patches, metrics' reference, SDF)
ASIDE_THREAD_PREFIX = "ribpull-aside"

#: point-neighbour pairs of the refinement's patches above which they are made beside the training
#: (`_patches_beside_the_fit`)
PATCHES_BESIDE_FIT_MIN_PAIRS = 2_500_000


def _patches_beside_the_fit(cloud, plan) -> bool:
    """Whether the refinement's patches (they depend on the input alone) are made in a thread beside
    the training, whose threads leave some of the cores' time: where they are many. `ribpull fit`
    wall, old -> new, this machine: 105k label-map boundary points x 32 neighbours 29.2 / 30.1 ->
    27.4 / 28.3 s, 200k points x 48 40.7 -> 38.9 s; but 60k points x 19 19.4 / 19.1 -> 20.0 / 19.7
    s (the slower training costs more than the patches' 0.3 s), hence the bound."""
    return plan is not None and plan.applies and len(cloud.points) * plan.neighbours >= PATCHES_BESIDE_FIT_MIN_PAIRS


def _plan_refinement(cloud, fit_config, options: PipelineOptions):
    """The input's refine.RefinePlan, or None when the preset does not refine. A label map is refined
    onto its boundary points (placed between the voxel centres), like a point cloud. A plan that applies
    shortens the fit to the refinement's fit_iterations (never lengthens it) unless the options name
    an iteration count or another method (fit_config is changed in place). A point cloud of more than
    refine.dense_points points is planned with dense_max_neighbours and dense_fit_iterations, and is
    meshed at dense_mesh_resolution cells unless the options name a resolution. A label map's
    patches reach refine.label_map_radius_voxels of its largest voxel edge. A field that starts
    from a solid is fitted for warm_fit_iterations: a label map's (the load stage measured it) or,
    for a point cloud whose sampling gap is at most flood_prior_max_gap_mm, the one its flood fill
    encloses where the method trusts it (the method's config is set to start from it,
    `methods.with_flood_prior`; a dense cloud then fits dense_warm_fit_iterations)."""
    from scipy.spatial import cKDTree

    from .methods import with_flood_prior, with_iterations
    from .pointcloud import sampling_gap, voxel_spacing_mm
    from .refine import plan_refinement

    config = fit_config.refine
    if config is None:
        return None
    dense = cloud.nifti_affine is None and len(cloud.points) > config.dense_points
    if dense:
        config = replace(config, max_neighbours=config.dense_max_neighbours)
    elif cloud.nifti_affine is not None and config.label_map_radius_voxels:
        config = replace(config, radius_mm=config.label_map_radius_voxels * float(voxel_spacing_mm(cloud).max()))
    tree = cKDTree(np.asarray(cloud.points, dtype=np.float64))  # the plan's and the sampling gap's
    plan = plan_refinement(cloud.points, config, tree=tree)
    planned = fit_config.method_config.schedule.iterations
    # the shorter schedule was measured for the preset's own method: another method keeps its own
    own = plan.applies and options.iterations is None and options.method is None
    iterations = config.dense_fit_iterations if dense else config.fit_iterations
    if cloud.solid_distance_mm is not None and config.warm_fit_iterations is not None:
        iterations = config.warm_fit_iterations  # a field that starts from the map's solid settles sooner
    # a dense enough point cloud may start from its flood fill's solid (the method judges whether
    # it trusts that flood fill, and then shortens its own schedule)
    if own and cloud.nifti_affine is None and config.flood_prior_cell_mm > 0 \
            and sampling_gap(cloud.points, tree=tree) <= config.flood_prior_max_gap_mm:
        fit_config.method_config = with_flood_prior(fit_config.method_config, config.flood_prior_cell_mm,
                                                    config.dense_warm_fit_iterations if dense else config.warm_fit_iterations)
    if own and iterations is not None and iterations < planned:
        fit_config.method_config = with_iterations(fit_config.method_config, iterations)
    # the finer mesh pays off only where its vertices are moved onto the patches
    if plan.applies and dense and options.resolution is None and config.dense_mesh_resolution:
        fit_config.mesh = replace(fit_config.mesh, resolution=max(fit_config.mesh.resolution, config.dense_mesh_resolution))
    return plan


def _surface_mesh(cloud, field, frame, fit_config, refine_plan, patches, report: _Reporter):
    """The field's mesh in mm: marching cubes, unsupported components removed, then refined onto
    the input under `refine_plan` (a refine.RefinePlan; None: not refined) and `patches`
    (refine.refinement_patches, a Future of them, or None: made there). Stage "mesh"."""
    from .mesh import extract_mesh, remove_unsupported_components

    lo, hi = frame.to_unit(cloud.points).min(0), frame.to_unit(cloud.points).max(0)
    mesh = extract_mesh(field, frame, (lo, hi), fit_config.mesh, progress=lambda f: report("mesh", f),
                        should_cancel=report.should_cancel)
    mesh, cleanup = remove_unsupported_components(mesh, cloud.points, support_distance_mm(cloud.points))
    mesh.metadata["cleanup"] = cleanup
    if refine_plan is not None:
        patches = patches.result() if isinstance(patches, Future) else patches
        mesh, mesh.metadata["refine"] = _refined(mesh, cloud, fit_config.refine, refine_plan, patches)
    return mesh


def _sdf_and_weights(cloud, mesh, field, frame, fit_config, tmp: Path, report: _Reporter, share=None):
    """sdf.nii.gz (the SDF volume on the input's grid, mm) and the weights into `tmp`; returns
    (name -> path, (volume, affine)). Stage "sdf"; checks report.should_cancel between chunks;
    share: a WorkShare through which another thread may help with its point queries."""
    from .dicom import LPS_FROM_RAS
    from .sdf import sdf_grid_for, signed_distance_volume, write_nifti
    from .weights import save_field

    report.check()
    shape, affine = sdf_grid_for(cloud, frame, fit_config.sdf)
    volume = signed_distance_volume(mesh, field, frame, shape, affine, should_cancel=report.should_cancel, share=share)
    # NIfTI's world is RAS; a DICOM input's frame is LPS: the file says so through its affine
    nifti_affine = affine if cloud.dicom_source is None else LPS_FROM_RAS @ affine
    artifacts = {"sdf.nii.gz": Path(write_nifti(tmp / "sdf.nii.gz", volume, nifti_affine))}
    st, js = save_field(field, frame, tmp, extra={"preset": fit_config.preset, "fit_config": fit_config.to_dict()})
    artifacts["model.safetensors"], artifacts["model.json"] = Path(st), Path(js)
    return artifacts, (volume, affine)


def _refined(mesh, cloud, config, plan, patches=None):
    """The mesh with its vertices refined onto the cloud's points under `plan`
    (`refine.refine_vertices`: onto the patches, and then out by the smoothing a label map's
    boundary points carry; or for a too-noisy input the noise-bias flow), and the summary (with
    its seconds). patches: (kd-tree, patches) from refine.refinement_patches, or None (made here)."""
    import time

    import trimesh

    from .refine import point_weights_of, refine_vertices

    t0 = time.perf_counter()
    tree, patches = patches if patches is not None else (None, None)
    weights = point_weights_of(cloud, config) if patches is None and plan.applies else None
    vertices, summary = refine_vertices(mesh.vertices, cloud.points, config, plan, tree=tree, faces=mesh.faces,
                                        smoothing_time_mm2=cloud.boundary_smoothing_mm2, patches=patches,
                                        point_weights=weights)
    out = trimesh.Trimesh(vertices, mesh.faces, process=False)
    out.metadata.update(mesh.metadata)
    return out, {**summary, "seconds": round(time.perf_counter() - t0, 3)}


def support_distance_mm(points_mm: np.ndarray) -> float:
    """How far from the input a reconstructed surface may lie and still count as supported (mm):
    twice the median distance to the 8th neighbour, i.e. a couple of sampling gaps."""
    from .pointcloud import sampling_gap

    return 2.0 * sampling_gap(points_mm)


def _skeleton_of(mesh, cloud, report: _Reporter, n_points: int = 20_000):
    """Skeleton of the reconstruction from points sampled on it. For labelled inputs (NIfTI label
    maps) each sample takes the label of its nearest input point, so curves are named by the input."""
    from .skeleton import skeleton_from_mesh

    def on_progress(fraction, message=""):
        report("skeleton", fraction, message=message)

    kw = {}
    if cloud.labels is not None and len(np.unique(cloud.labels)) > 1:
        from scipy.spatial import cKDTree

        tree = cKDTree(cloud.points)
        kw = {"point_labels_fn": lambda pts: cloud.labels[tree.query(pts, workers=-1)[1]], "label_names": cloud.label_names}
    return skeleton_from_mesh(mesh, n_points=n_points, progress=on_progress, **kw)


def _polylines(skeleton) -> list[np.ndarray]:
    """The skeleton's polylines as (m, 3) mm arrays (skeleton_polylines gives node ids)."""
    from .skeleton.export import skeleton_polylines

    return [skeleton.nodes_mm[ids] for ids in skeleton_polylines(skeleton)]


class _FirstFreeThread:
    """Work that either of two threads may do: the first to get to it runs it (`run_unless_taken`),
    and `result()` returns its result, running it if no thread took it yet, else waiting for it."""

    def __init__(self, fn):
        self._fn, self._lock, self._taken, self._future = fn, threading.Lock(), False, Future()

    def run_unless_taken(self) -> None:
        with self._lock:
            if self._taken:
                return
            self._taken = True
        try:
            self._future.set_result(self._fn())
        except BaseException as e:  # noqa: BLE001 - handed to whoever waits for the result
            self._future.set_exception(e)

    def result(self):
        self.run_unless_taken()
        return self._future.result()


def _metrics_reference(reference, fit_config):
    """metrics.reference_samples of the run's reference under its MetricsConfig."""
    from .metrics import reference_samples

    return reference_samples(reference, n_samples=fit_config.metrics.n_samples, seed=fit_config.seed)


class _SurfaceMetricsWork:
    """metrics.surface_metrics of the mesh (mm) under the run's MetricsConfig, as three parts that
    either of two threads may do: `metrics.completeness_mm` (the reference points' distances to the
    mesh, most of the work) of the first and of the second half of the reference points, against
    one shared triangle search, and `metrics.prediction_samples`. `run_untaken()` runs each part
    that no thread has taken yet, in that order; `result()` does the same, waits for the parts the
    other thread took, and returns metrics.summarise_surface_metrics of them: the same numbers as
    surface_metrics. timings["metrics"]: from the first part's start to the last one's end (s)."""

    def __init__(self, mesh, reference_job: Future, frame, fit_config, timings: dict, report: _Reporter):
        from .metrics import completeness_mm, prediction_samples
        from .triangle_distance import TriangleSearch

        self._reference_job, self._frame, self._config = reference_job, frame, fit_config
        self._timings, self._report = timings, report
        self._lock, self._start = threading.Lock(), None
        search = _FirstFreeThread(lambda: TriangleSearch(mesh.triangles))  # built by the first part to ask

        def completeness(first_half: bool):
            reference = reference_job.result()
            half = len(reference.points) // 2
            rows = slice(0, half) if first_half else slice(half, None)
            return completeness_mm(mesh, reference, rows, search=search.result())

        self._parts = [
            _FirstFreeThread(self._timed(lambda: completeness(True))),
            _FirstFreeThread(self._timed(lambda: completeness(False))),
            _FirstFreeThread(self._timed(lambda: prediction_samples(mesh, reference_job.result(),
                                                                    fit_config.metrics.n_samples, fit_config.seed))),
        ]

    def _timed(self, fn):
        def run():
            with self._lock:
                first, self._start = self._start is None, self._start or time.perf_counter()
            if first:
                self._report("metrics", 0.0, message="metrics started")
            try:
                return fn()
            finally:  # the parts end in any order: the stage lasts until the last one's end
                with self._lock:
                    self._timings["metrics"] = round(time.perf_counter() - self._start, 3)

        return run

    def run_untaken(self, before_each: Callable[[], object] | None = None) -> None:
        """Run the parts no thread has taken yet, in order; before_each() before each of them."""
        for part in self._parts:
            if before_each is not None:
                before_each()
            part.run_unless_taken()

    def result(self) -> dict:
        from .metrics import summarise_surface_metrics

        self.run_untaken()  # first whatever part is left, then wait for those the other thread took
        first, second, prediction = (part.result() for part in self._parts)
        return summarise_surface_metrics(prediction, self._reference_job.result(), np.concatenate([first, second]),
                                         tau_mm=self._config.metrics.fscore_tau_mm,
                                         paper_units_per_mm=self._frame.paper_units_per_mm)


def _metrics(cloud, surface, reference_name, mesh, field, frame, fit_config, skeleton) -> dict:
    """metrics.json's content; `surface`: `_SurfaceMetricsWork.result()`."""
    from .metrics import compression_metrics, mesh_summary

    out = {
        "units": "mm",
        "input": {"n_points": len(cloud), "format": cloud.source_format, "bytes": cloud.source_bytes,
                  "labels": sorted(int(v) for v in np.unique(cloud.labels)) if cloud.labels is not None else None},
        "method": fit_config.method,
        "preset": fit_config.preset,
        "iterations_run": field.iterations_run,
        # the method's own schedule: a warm start may have shortened the configured one
        "iterations_planned": (field.config.get("schedule") or {}).get("iterations",
                                                                        getattr(fit_config.method_config, "iterations", None)),
        "fit_seconds": round(field.fit_seconds, 3),
        "loss_terms": {k: round(v, 6) for k, v in field.loss_terms.items()},
        "surface_level": field.level,
        "reference": reference_name,
        "surface": surface,
        "mesh": {**mesh_summary(mesh), **mesh.metadata.get("cleanup", {}), "refine": mesh.metadata.get("refine"),
                 "field_queries": mesh.metadata.get("field_queries"), "dense_queries": mesh.metadata.get("dense_queries")},
        "weights": compression_metrics(cloud.source_bytes, field.module),
        "frame": frame.to_dict(),
    }
    if skeleton is not None:
        out["skeleton"] = {
            "n_curves": len(skeleton.curves),
            "curves": [{"label": c.label, "length_mm": c.length_mm, "mean_radius_mm": c.mean_radius_mm,
                        "min_radius_mm": c.min_radius_mm} for c in skeleton.curves],
        }
    return out


def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o)}")
