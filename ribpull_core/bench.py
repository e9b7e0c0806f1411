"""`ribpull bench`: methods x cases benchmark -> results.csv, results.md (the paper's table format),
skeleton.csv, speed.csv and PNG plots.

    ribpull bench --quick -o bench_out/          # <= 15 min on a 2-core CPU; prints the tables
    ribpull bench -o bench_full/                 # every method on every case (hours; run by hand)
    ribpull bench --cases my_inputs/ -o out/     # adds your files (and `ribpull phantom` folders)

Every (method, case) pair runs in a fresh child process (multiprocessing "spawn"), so its peak
resident memory (VmHWM, MB) is its own; a sampler thread in the child also records the largest
resident size seen during each stage. Neural methods go through `pipeline.run_pipeline`, the same
call as `ribpull fit`; the classical baselines (screened Poisson on the points, marching cubes on a
voxel mask) get the same mesh clean-up, skeleton and scoring. Surfaces are scored with
`metrics.surface_metrics` (mm; paper units = the normalised [-1, 1] frame of the input, CD-L1 and
HD x100, CD-L2 x1e4) against the TRUE surface for phantom cases, else against the input points.
Skeletons are scored with `skeleton_metrics` against the phantom's true centerlines.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import multiprocessing as mp
import os
import platform
import resource
import shutil
import sys
import threading
import time
import traceback
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

REPO_ROOT = Path(__file__).resolve().parents[1]
#: the real TotalSegmentator label map shipped next to the repository (../shared/data/...)
REAL_LABEL_MAP = REPO_ROOT.parent / "shared" / "data" / "totalseg_example_seg.nii.gz"
#: the skeleton benchmark whose voxel-thinning baseline (`voxel_skeleton`) is reused here
SKELETON_BENCHMARK = REPO_ROOT / "benchmarks" / "skeleton_phantom.py"

METRIC_SAMPLES = 1_000_000  # samples per side for the surface metrics (sub-mm resolution; methods.md)
PIPELINE_METRIC_SAMPLES = 10_000  # the pipeline's own vs-input metrics (unused here: we score apart)
FSCORE_TAU_MM = 1.0
QUICK_POINTS = 20_000
QUICK_NOISE_MM = 0.3
QUICK_NEURALPULL_ITERATIONS = 200  # default (reference 8x256) network, short schedule (~0.2 s/it on 2 cores)
QUICK_DIGS_ITERATIONS = 60  # default (reference SIREN) network, the smoke preset's length (~1 s/it on 2 cores)
BASELINE_RESOLUTION = 256  # marching-cubes resolution of the Neural-Pull / DiGS baselines (the papers')
SPEED_PAPER_ITERATIONS = 100  # paper preset iterations timed when the plan has no paper run on the case
POISSON_DEPTH = 8  # octree depth of screened Poisson (2^8 cells over ~1.1x the longest side: ~1.2 mm;
#                    depth 9 measured no better on the 20k-point phantom and ~1.7x slower)
MASK_SPACING_MM = 1.0  # voxel size of the voxelised phantom masks
FULL_SEEDS = (0, 1, 2)
#: (n_points, noise_mm) of the main phantom point-cloud case (every method, every seed)
MAIN_POINT_CASE = (20_000, 0.3)
#: the sweep around it: noise 0 / 1 mm at 20k points, 5k / 100k points at 0.3 mm
SWEEP_POINT_CASES = ((20_000, 0.0), (20_000, 1.0), (5_000, 0.3), (100_000, 0.3))
#: the docs run (`--plan docs`, what docs/benchmarks.md shows): the expensive neural methods on the
#: first DOCS_EXPENSIVE_SEEDS seeds only, and SparseOcc's `paper` preset cut to DOCS_PAPER_ITERATIONS
#: of its 20k (its full schedule is ~2 h per case on the 2-core CPU)
DOCS_EXPENSIVE_SEEDS = 2
DOCS_PAPER_ITERATIONS = 2_000
PLANS = ("quick", "docs", "full")
POINT_SUFFIXES = (".ply", ".xyz", ".txt", ".csv", ".npy", ".npz", ".pcd")
MASK_SUFFIXES = (".nii", ".nii.gz")

GROUP_POINTS = "phantom point clouds"
GROUP_SWEEP = "phantom sweeps (noise, point count)"
GROUP_MASK = "phantom voxel masks"
GROUP_REAL = "real label map"
GROUP_USER = "user files"
GROUP_ORDER = (GROUP_POINTS, GROUP_SWEEP, GROUP_MASK, GROUP_REAL, GROUP_USER)
#: groups whose table has one line per (method, case) instead of pooling the cases
GROUPS_BY_CASE = (GROUP_SWEEP,)

#: per-stage columns (seconds and peak resident MB); which stages a row has depends on the method
STAGES = ("load", "normals", "fit", "mesh", "sdf", "skeleton", "metrics", "export", "score")

#: results.csv columns, in order (rows may carry extra keys; they are appended sorted)
COLUMNS = (
    "method", "kind", "preset", "fit_method", "case", "group", "input_kind", "seed", "noise_mm", "n_points",
    "status", "note", "reference", "metric_samples", "paper_units_per_mm",
    "cd_l1_mm", "cd_l2_mm2", "hausdorff_mm", "cd_l1_paper", "cd_l2_paper", "hausdorff_paper",
    "normal_consistency", "fscore", "precision", "recall", "tau_mm",
    "mesh_components", "mesh_watertight", "mesh_faces",
    "skel_mean_dist_mm", "skel_p95_dist_mm", "skel_max_dist_mm", "skel_coverage", "skel_n_paths",
    "skel_n_branch_nodes", "skel_n_cycles", "skel_label_accuracy", "skel_n_curves",
    "iterations_planned", "iterations_run", "ms_per_iteration", "fit_overhead_s", "time_total_s",
    *(f"time_{s}_s" for s in STAGES), "wall_s",
    "peak_rss_mb", *(f"rss_{s}_mb" for s in STAGES),
    "n_parameters", "weights_bytes_fp32", "weights_bytes_fp16", "input_bytes", "weights_to_input_fp32",
    "mesh_bytes", "torch_threads", "device",
)

#: the paper's Table 1 (mean +- std over 20 RibSeg cases, paper units), from shared/notes/methods.md
PAPER_TABLE1 = {
    "SparseOcc": ("1.55 ± 0.24", "1.04 ± 0.16", "12.6 ± 4.39"),
    "Neural-Pull": ("5.81 ± 0.38", "3.90 ± 0.26", "8.25 ± 3.22"),
    "DiGS": ("8.04 ± 10.1", "5.36 ± 6.71", "36.8 ± 23.0"),
}


# ---------------------------------------------------------------------------------- plan


@dataclass(frozen=True)
class MethodSpec:
    """One benchmarked method. kind: "pipeline" (run_pipeline with preset / method / iterations /
    resolution), "poisson" (screened Poisson on the points) or "mask_mc" (marching cubes on the
    label mask). inputs: the input kinds ("points", "mask") it applies to."""

    label: str
    kind: str
    preset: str | None = None
    method: str | None = None
    iterations: int | None = None
    resolution: int | None = None
    inputs: tuple[str, ...] = ("points", "mask")


@dataclass(frozen=True)
class Case:
    """One input. input_kind: "points" or "mask" (NIfTI label map). seed: the phantom's seed and the
    fit seed. truth_mesh / centerlines: paths of the true surface (mm) and true centerlines (JSON of
    `phantom.centerlines_json`), None for inputs without ground truth. noise_mm / n_points: phantom
    sampling (None otherwise)."""

    name: str
    group: str
    input_path: str
    input_kind: str
    seed: int = 0
    noise_mm: float | None = None
    n_points: int | None = None
    truth_mesh: str | None = None
    centerlines: str | None = None


def quick_methods() -> list[MethodSpec]:
    """--quick: SparseOcc default, the baselines' reference networks for a smoke-length schedule,
    screened Poisson, marching cubes on masks."""
    return [
        MethodSpec("sparseocc default", "pipeline", preset="default"),
        MethodSpec(f"neuralpull {QUICK_NEURALPULL_ITERATIONS} it", "pipeline", preset="default", method="neuralpull",
                   iterations=QUICK_NEURALPULL_ITERATIONS, resolution=BASELINE_RESOLUTION),
        MethodSpec(f"digs {QUICK_DIGS_ITERATIONS} it", "pipeline", preset="default", method="digs",
                   iterations=QUICK_DIGS_ITERATIONS, resolution=BASELINE_RESOLUTION),
        MethodSpec("screened poisson", "poisson", inputs=("points",)),
        MethodSpec("mask marching cubes", "mask_mc", inputs=("mask",)),
    ]


def docs_methods() -> tuple[list[MethodSpec], list[MethodSpec]]:
    """--plan docs: (cheap, expensive). Cheap: SparseOcc default, screened Poisson, mask marching
    cubes, run on every case. Expensive: SparseOcc `paper` cut to DOCS_PAPER_ITERATIONS, Neural-Pull
    and DiGS at their `default` presets, run on the main case of the first DOCS_EXPENSIVE_SEEDS seeds."""
    cheap = [MethodSpec("sparseocc default", "pipeline", preset="default"),
             MethodSpec("screened poisson", "poisson", inputs=("points",)),
             MethodSpec("mask marching cubes", "mask_mc", inputs=("mask",))]
    expensive = [
        MethodSpec(f"sparseocc paper {DOCS_PAPER_ITERATIONS // 1000}k it", "pipeline", preset="paper",
                   iterations=DOCS_PAPER_ITERATIONS, inputs=("points",)),
        MethodSpec("neuralpull default", "pipeline", preset="default", method="neuralpull",
                   resolution=BASELINE_RESOLUTION, inputs=("points",)),
        MethodSpec("digs default", "pipeline", preset="default", method="digs", resolution=BASELINE_RESOLUTION,
                   inputs=("points",)),
    ]
    return cheap, expensive


def full_methods() -> list[MethodSpec]:
    """The full run (hours: meant for a GPU or a night): every method at its `default` preset and
    SparseOcc's `paper` preset at its full 20k-iteration schedule (~2 h per case on a 2-core CPU)."""
    return [
        MethodSpec("sparseocc default", "pipeline", preset="default"),
        MethodSpec("sparseocc paper", "pipeline", preset="paper", inputs=("points",)),
        MethodSpec("neuralpull default", "pipeline", preset="default", method="neuralpull",
                   resolution=BASELINE_RESOLUTION),
        MethodSpec("digs default", "pipeline", preset="default", method="digs", resolution=BASELINE_RESOLUTION),
        MethodSpec("screened poisson", "poisson", inputs=("points",)),
        MethodSpec("mask marching cubes", "mask_mc", inputs=("mask",)),
    ]


def phantom_case(workdir: Path, seed: int, n_points: int, noise_mm: float, mask: bool = False,
                 group: str | None = None) -> Case:
    """Write a synthetic ribcage (phantom.write_phantom) under workdir and return its case: the point
    cloud (n_points samples, noise_mm Gaussian noise) or, with mask, the label map voxelised at
    MASK_SPACING_MM (noise-free; n_points is then only the size of the unused points.ply). group:
    the table it is reported in (default: GROUP_MASK for masks, else GROUP_POINTS)."""
    from .phantom import PhantomConfig, write_phantom

    name = f"phantom-s{seed}-mask{MASK_SPACING_MM:g}mm" if mask else f"phantom-s{seed}-n{n_points}-noise{noise_mm:g}"
    files = write_phantom(Path(workdir) / name, PhantomConfig(seed=seed, n_points=n_points, noise_mm=noise_mm),
                          nifti=mask, spacing_mm=MASK_SPACING_MM)
    return Case(name=name, group=group or (GROUP_MASK if mask else GROUP_POINTS),
                input_path=str(files["mask"] if mask else files["points"]), input_kind="mask" if mask else "points",
                seed=seed, noise_mm=None if mask else noise_mm, n_points=None if mask else n_points,
                truth_mesh=str(files["truth_mesh"]), centerlines=str(files["centerlines"]))


def input_kind_of(path: Path) -> str | None:
    """"mask" for NIfTI, "points" for point formats, None for anything else."""
    name = path.name.lower()
    if name.endswith(MASK_SUFFIXES):
        return "mask"
    return "points" if name.endswith(POINT_SUFFIXES) else None


def user_cases(cases_dir: Path, seeds: tuple[int, ...]) -> list[Case]:
    """Cases from --cases DIR: every supported file (scored against its own points), and every folder
    written by `ribpull phantom` (points.ply / mask.nii.gz + truth_mesh.ply [+ centerlines.json],
    scored against its true surface and centerlines). One case per seed (the fit seed)."""
    cases_dir = Path(cases_dir)
    if not cases_dir.is_dir():
        from .errors import RibPullInputError

        raise RibPullInputError("bad_parameter", f"--cases {cases_dir} is not a directory")
    out = []
    for path in sorted(cases_dir.rglob("*")):
        kind = input_kind_of(path)
        if not path.is_file() or kind is None or path.name in ("truth_mesh.ply",):
            continue
        truth = path.parent / "truth_mesh.ply"
        cl = path.parent / "centerlines.json"
        phantom_layout = truth.exists() and path.name in ("points.ply", "mask.nii.gz")
        for seed in seeds:
            out.append(Case(name=f"user:{path.relative_to(cases_dir)}", group=GROUP_USER, input_path=str(path),
                            input_kind=kind, seed=seed, truth_mesh=str(truth) if phantom_layout else None,
                            centerlines=str(cl) if phantom_layout and cl.exists() else None))
    return out


def applicable(spec: MethodSpec, case: Case) -> bool:
    """Whether a method runs on a case's input kind."""
    return case.input_kind in spec.inputs


def build_plan(mode: str, workdir: Path, seeds: tuple[int, ...], n_points: int | None = None,
               cases_dir: Path | None = None, label_map: Path | None = REAL_LABEL_MAP,
               method_filter: list[str] | None = None, notes: list[str] | None = None) -> tuple[list, list[Case]]:
    """(plan, cases): plan is the ordered list of (MethodSpec, Case) to run; mode is one of PLANS.

    quick: one phantom point cloud (first seed, n_points or QUICK_POINTS, QUICK_NOISE_MM) with every
    point method, the mask with marching cubes, the real label map with SparseOcc default and
    marching cubes. docs: per seed the main phantom case (MAIN_POINT_CASE) with the cheap methods,
    plus the expensive ones on the first DOCS_EXPENSIVE_SEEDS seeds; for the first seed the
    SWEEP_POINT_CASES and the mask with the cheap methods; the real label map. full: per seed the main
    case, the sweeps and the mask with every applicable method; the real label map per seed. User
    cases (--cases) get SparseOcc default and the classical methods (full: every method). Skips go
    to notes."""
    if mode not in PLANS:
        raise ValueError(f"unknown plan {mode!r}; choose one of {PLANS}")
    notes = notes if notes is not None else []
    workdir = Path(workdir)
    if mode == "docs":
        cheap, expensive = docs_methods()
    else:
        cheap = quick_methods() if mode == "quick" else full_methods()
        expensive = []
    if method_filter:
        def wanted(m: MethodSpec) -> bool:
            return any(m.label.startswith(f) or m.kind == f for f in method_filter)

        cheap, expensive = [m for m in cheap if wanted(m)], [m for m in expensive if wanted(m)]
    methods = cheap + expensive
    light = [m for m in methods if m.label == "sparseocc default" or m.kind != "pipeline"]
    cases: list[Case] = []
    plan: list[tuple[MethodSpec, Case]] = []

    def add(case: Case, specs: list[MethodSpec]) -> None:
        cases.append(case)
        plan.extend((m, case) for m in specs if applicable(m, case))

    main_n, main_noise = MAIN_POINT_CASE
    if mode == "quick":
        add(phantom_case(workdir, seeds[0], n_points or QUICK_POINTS, QUICK_NOISE_MM), methods)
        add(phantom_case(workdir, seeds[0], 1_000, 0.0, mask=True), [m for m in methods if m.kind == "mask_mc"])
    else:
        for i, seed in enumerate(seeds):
            main_specs = methods if mode == "full" or i < DOCS_EXPENSIVE_SEEDS else cheap
            add(phantom_case(workdir, seed, n_points or main_n, main_noise), main_specs)
            if mode == "full" or i == 0:
                for n, noise in SWEEP_POINT_CASES:
                    add(phantom_case(workdir, seed, n, noise, group=GROUP_SWEEP), cheap if mode == "docs" else methods)
                add(phantom_case(workdir, seed, 1_000, 0.0, mask=True), cheap if mode == "docs" else methods)
    extra_specs = methods if mode == "full" else light
    if label_map is not None:
        if Path(label_map).exists():
            for seed in (seeds if mode == "full" else seeds[:1]):
                add(Case(name=Path(label_map).name, group=GROUP_REAL, input_path=str(label_map), input_kind="mask",
                         seed=seed), extra_specs)
        else:
            notes.append(f"real label map {label_map} not found: its rows are skipped")
    if cases_dir is not None:
        for c in user_cases(Path(cases_dir), seeds if mode == "full" else seeds[:1]):
            add(c, extra_specs)
    if not methods:
        notes.append(f"no method matches --methods {method_filter}")
    return plan, cases


# ------------------------------------------------------------------------------ child side


class RssSampler:
    """Largest resident set size (MB) of this process per stage, sampled every interval_s by a thread.
    `set(stage)` switches the stage being charged. Linux (/proc/self/statm); elsewhere only the
    process peak (ru_maxrss) is known and the per-stage values stay empty."""

    def __init__(self, interval_s: float = 0.02):
        self.interval_s, self.stage, self.peaks = interval_s, "start", {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self._page = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096

    def rss_mb(self) -> float | None:
        """Current resident set size in MB (None when /proc is unavailable)."""
        try:
            with open("/proc/self/statm") as fh:
                return int(fh.read().split()[1]) * self._page / 2**20
        except (OSError, ValueError, IndexError):
            return None

    def _sample(self) -> None:
        v = self.rss_mb()
        if v is not None:
            self.peaks[self.stage] = max(self.peaks.get(self.stage, 0.0), v)

    def _loop(self) -> None:
        while not self._stop.wait(self.interval_s):
            self._sample()

    def start(self) -> RssSampler:
        self._sample()
        self._thread.start()
        return self

    def set(self, stage: str) -> None:
        """Charge what follows to `stage` (samples now for the stage that ends and the one that starts)."""
        self._sample()
        self.stage = stage
        self._sample()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=1.0)
        self._sample()

    def columns(self) -> dict:
        """rss_<stage>_mb for the known stages (MB, rounded) and peak_rss_mb (this process's peak)."""
        out = {f"rss_{s}_mb": round(v, 1) for s, v in self.peaks.items() if s in STAGES}
        out["peak_rss_mb"] = round(peak_rss_mb(), 1)
        return out


def peak_rss_mb() -> float:
    """This process's peak resident set size in MB: VmHWM of /proc/self/status on Linux, else
    ru_maxrss (KB on Linux, bytes on macOS). Not ru_maxrss on Linux: it survives fork + exec, so a
    spawned child would report its parent's peak whenever that is larger than its own."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024
    except (OSError, ValueError, IndexError):
        pass
    r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return r / 2**20 if sys.platform == "darwin" else r / 1024


class StageTimer:
    """`with timer("fit"):` adds the block's wall seconds to time_fit_s and charges its memory to it."""

    def __init__(self, sampler: RssSampler):
        self.sampler, self.times = sampler, {}

    def __call__(self, stage: str):
        timer = self

        class _Block:
            def __enter__(self):
                timer.sampler.set(stage)
                self.t = time.perf_counter()

            def __exit__(self, *exc):
                timer.times[stage] = timer.times.get(stage, 0.0) + time.perf_counter() - self.t
                return False

        return _Block()

    def columns(self, exclude=("score",)) -> dict:
        """time_<stage>_s (rounded) and time_total_s (the method's own stages: scoring excluded)."""
        out = {f"time_{s}_s": round(v, 3) for s, v in self.times.items()}
        out["time_total_s"] = round(sum(v for s, v in self.times.items() if s not in exclude), 3)
        return out


def iteration_cost(marks: list[tuple[float, int]], fit_s: float, iterations_run: int) -> dict:
    """ms_per_iteration from (perf_counter s, iteration) progress marks (slope between the first and
    the last mark, so set-up and the first iteration are excluded), else fit_s / iterations_run; and
    fit_overhead_s = fit_s - ms_per_iteration x iterations_run (set-up, query sampling, level)."""
    if len(marks) >= 2 and marks[-1][1] > marks[0][1]:
        ms = 1000.0 * (marks[-1][0] - marks[0][0]) / (marks[-1][1] - marks[0][1])
    else:
        ms = 1000.0 * fit_s / max(1, iterations_run)
    return {"ms_per_iteration": round(ms, 2), "fit_overhead_s": round(max(0.0, fit_s - ms * iterations_run / 1000.0), 3)}


def load_reference(case: dict):
    """(reference, name) for scoring: the true mesh for phantom cases, else the input points (for
    label maps the centres of the boundary voxel faces, the surface the segmentation draws)."""
    import trimesh

    from .io import load_point_cloud
    from .pointcloud import mask_boundary_cloud

    if case.get("truth_mesh"):
        return trimesh.load(case["truth_mesh"], force="mesh"), "true surface"
    cloud = load_point_cloud(Path(case["input_path"]))
    if case["input_kind"] == "mask":
        return mask_boundary_cloud(cloud, max_points=10**9), "label-map boundary (voxel face centres)"
    return cloud, "input points"


def score_surface(case: dict, mesh, paper_units_per_mm: float, n_samples: int, seed: int) -> dict:
    """surface_metrics of a mesh (mm) against the case's reference; columns of results.csv."""
    from .metrics import mesh_summary, surface_metrics

    reference, name = load_reference(case)
    s = surface_metrics(mesh, reference, n_samples=n_samples, tau_mm=FSCORE_TAU_MM,
                        paper_units_per_mm=paper_units_per_mm, seed=seed)
    ms = mesh_summary(mesh)
    keep = ("cd_l1_mm", "cd_l2_mm2", "hausdorff_mm", "cd_l1_paper", "cd_l2_paper", "hausdorff_paper",
            "normal_consistency", "fscore", "precision", "recall", "tau_mm", "paper_units_per_mm")
    return {**{k: s[k] for k in keep}, "reference": name, "metric_samples": n_samples,
            "mesh_components": ms["components"], "mesh_watertight": ms["watertight"], "mesh_faces": ms["n_faces"]}


def load_centerlines(path: str) -> dict[str, np.ndarray]:
    """True centerlines {name: (n, 3) mm} from a centerlines.json written by write_phantom."""
    d = json.loads(Path(path).read_text())
    return {k: np.asarray(v["points"], dtype=np.float64) for k, v in d["ribs"].items()}


def score_skeleton(case: dict, skeleton) -> dict:
    """skeleton_metrics against the case's true centerlines as skel_* columns (empty without truth)."""
    from .skeleton import skeleton_metrics

    if skeleton is None or not case.get("centerlines"):
        return {}
    m = skeleton_metrics(skeleton, load_centerlines(case["centerlines"]))
    keys = ("mean_dist_mm", "p95_dist_mm", "max_dist_mm", "coverage", "n_paths", "n_branch_nodes", "n_cycles",
            "label_accuracy", "n_curves")
    return {f"skel_{k}": m.get(k) for k in keys}


def skeleton_of(mesh, cloud):
    """The pipeline's skeleton of a mesh (20k samples, curves named by the input's labels if any)."""
    from .pipeline import _Reporter, _skeleton_of

    return _skeleton_of(mesh, cloud, _Reporter(None, None))


def render_run(path: Path, mesh, skeleton, title: str) -> None:
    """render_preview of a mesh (mm) and its skeleton curves."""
    from .render import render_preview

    polylines = [skeleton.curve_points(c) for c in skeleton.curves] if skeleton is not None else None
    render_preview(path, mesh, polylines, title=title)


def score_and_render(task: dict, timer: StageTimer, mesh, skeleton, paper_units_per_mm: float | None) -> dict:
    """The scoring columns of a run: surface metrics of `mesh` (when paper_units_per_mm is given) and
    skeleton metrics against the case's truth, timed as stage "score"; renders the run if asked."""
    case, spec = task["case"], task["spec"]
    row: dict = {}
    with timer("score"):
        if paper_units_per_mm is not None:
            row.update(score_surface(case, mesh, paper_units_per_mm, task["metric_samples"], int(case["seed"])))
        row.update(score_skeleton(case, skeleton))
    row["time_score_s"] = round(timer.times["score"], 3)
    if task.get("render"):
        render_run(Path(task["rundir"]) / "render.png", mesh, skeleton, f"{spec['label']} — {case['name']}")
    return row


def run_pipeline_task(task: dict, sampler: RssSampler, timer: StageTimer) -> dict:
    """A neural method through run_pipeline, then scored; returns the row's columns."""
    import trimesh

    from .pipeline import PipelineOptions, run_pipeline
    from .skeleton import Skeleton

    case, spec, rundir = task["case"], task["spec"], Path(task["rundir"])
    marks: list[tuple[float, int]] = []

    def on_progress(p):
        if p.stage != sampler.stage:
            sampler.set(p.stage)
        if p.stage == "fit" and p.iteration is not None:
            marks.append((time.perf_counter(), int(p.iteration)))

    options = PipelineOptions(preset=spec["preset"], method=spec["method"], iterations=spec["iterations"],
                              resolution=spec["resolution"], seed=int(case["seed"]), preview=False,
                              device=task["device"], metrics_samples=PIPELINE_METRIC_SAMPLES)
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


def flood_fill_normals(points_mm: np.ndarray) -> np.ndarray:
    """(N, 3) unit normals of unoriented points: PCA over 16 neighbours, oriented towards the
    flood-filled empty space (the orientation RibPull's default preset derives from the data)."""
    from .frame import UnitFrame
    from .methods.sparseocc import oriented_normals, outside_mask

    pu = UnitFrame.fit(points_mm).to_unit(points_mm)
    outside, _, spacing, origin = outside_mask(pu)
    return oriented_normals(pu, outside, spacing, origin)


def poisson_mesh(points_mm: np.ndarray, normals: np.ndarray, depth: int = POISSON_DEPTH):
    """Screened Poisson surface (pymeshlab) of oriented points; mm in, trimesh in mm out."""
    import pymeshlab
    import trimesh

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=np.ascontiguousarray(points_mm, dtype=np.float64),
                               v_normals_matrix=np.ascontiguousarray(normals, dtype=np.float64)))
    ms.generate_surface_reconstruction_screened_poisson(depth=int(depth), preclean=True)
    out = ms.current_mesh()
    return trimesh.Trimesh(out.vertex_matrix(), out.face_matrix(), process=True)


def mask_marching_cubes(cloud):
    """Marching cubes at 0.5 on the binary mask of a label map's selected voxels (the cloud's voxel
    centres put back on their grid through the inverse affine, padded by one voxel); vertices mapped
    to mm through the affine, faces oriented outwards. Returns a trimesh in mm."""
    import trimesh
    from skimage.measure import marching_cubes

    from .pointcloud import mask_voxel_indices

    ijk = mask_voxel_indices(cloud)  # ValueError unless the cloud comes from a NIfTI label map
    a = np.asarray(cloud.nifti_affine, dtype=np.float64)
    mask = np.zeros(np.asarray(cloud.nifti_shape) + 2, dtype=np.float32)
    mask[ijk[:, 0] + 1, ijk[:, 1] + 1, ijk[:, 2] + 1] = 1.0
    verts, faces, _, _ = marching_cubes(mask, level=0.5)
    mesh = trimesh.Trimesh(trimesh.transform_points(verts - 1.0, a), faces, process=True)
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def run_classical_task(task: dict, sampler: RssSampler, timer: StageTimer) -> dict:
    """Screened Poisson on the points or marching cubes on the mask: the pipeline's clean-up (Poisson),
    skeleton and scoring; returns the row's columns."""
    from .frame import UnitFrame
    from .io import load_point_cloud
    from .mesh import remove_unsupported_components
    from .pipeline import support_distance_mm

    case, spec, rundir = task["case"], task["spec"], Path(task["rundir"])
    row: dict = {"fit_method": spec["kind"]}
    with timer("load"):
        cloud = load_point_cloud(Path(case["input_path"]))
    if spec["kind"] == "poisson":
        with timer("normals"):
            normals = flood_fill_normals(cloud.points)
        with timer("fit"):
            mesh = poisson_mesh(cloud.points, normals)
        with timer("mesh"):
            mesh, cleanup = remove_unsupported_components(mesh, cloud.points, support_distance_mm(cloud.points))
            mesh.export(rundir / "mesh.ply")
        row["note"] = (f"depth {POISSON_DEPTH}, flood-fill-oriented PCA normals (input normals ignored); "
                       f"removed {cleanup['removed_unsupported']} unsupported + {cleanup['removed_cavities']} cavity components")
    else:
        with timer("mesh"):
            mesh = mask_marching_cubes(cloud)
            mesh.export(rundir / "mesh.ply")
        row["note"] = "marching cubes at 0.5 on the binary mask of the selected labels"
    with timer("skeleton"):
        skel = skeleton_of(mesh, cloud)
    row.update(timer.columns())
    row.update(input_bytes=cloud.source_bytes, mesh_bytes=(rundir / "mesh.ply").stat().st_size, device="cpu")
    row.update(score_and_render(task, timer, mesh, skel, UnitFrame.fit(cloud.points).paper_units_per_mm))
    return row


def load_skeleton_benchmark():
    """benchmarks/skeleton_phantom.py as a module (for its `voxel_skeleton` baseline)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("ribpull_benchmarks_skeleton_phantom", SKELETON_BENCHMARK)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def run_skeleton_task(task: dict, sampler: RssSampler, timer: StageTimer) -> dict:
    """Skeleton section: the project's contraction on the TRUE surface ("contraction_truth") or voxel
    thinning of the true solid at MASK_SPACING_MM ("voxel_thinning"), scored against the true
    centerlines. Voxelising the phantom is timed apart (time_load_s)."""
    import trimesh

    from .io import load_point_cloud
    from .phantom import PhantomConfig, make_phantom, voxelize

    case, spec = task["case"], task["spec"]
    if spec["kind"] == "contraction_truth":
        with timer("load"):
            mesh = trimesh.load(case["truth_mesh"], force="mesh")
            cloud = load_point_cloud(Path(case["input_path"]))
        with timer("skeleton"):
            skel = skeleton_of(mesh, cloud)
    else:
        with timer("load"):
            vol, affine = voxelize(make_phantom(PhantomConfig(seed=int(case["seed"]))), MASK_SPACING_MM)
            thinning = load_skeleton_benchmark()
            mesh = None
        with timer("skeleton"):
            skel = thinning.voxel_skeleton(vol, affine)
    return {**timer.columns(), **score_and_render(task, timer, mesh, skel, None)}


def run_speed_task(task: dict, sampler: RssSampler, timer: StageTimer) -> dict:
    """Fit only (pipeline.fit_field) of spec's preset for spec's iterations; per-iteration cost and the
    extrapolated fit time of the preset's full schedule (overhead + schedule x ms/iteration)."""
    from .io import load_point_cloud
    from .methods import build_fit_config
    from .pipeline import _Reporter, configure_torch_threads, fit_field, select_device

    case, spec = task["case"], task["spec"]
    threads = configure_torch_threads()
    marks: list[tuple[float, int]] = []

    def on_progress(p):
        if p.iteration is not None:
            marks.append((time.perf_counter(), int(p.iteration)))

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
    "contraction_truth": run_skeleton_task, "voxel_thinning": run_skeleton_task, "speed": run_speed_task,
}


def base_row(task: dict) -> dict:
    """The identifying columns of a task's row."""
    case, spec = task["case"], task["spec"]
    return {"method": spec["label"], "kind": spec["kind"], "preset": spec.get("preset"), "case": case["name"],
            "group": case["group"], "input_kind": case["input_kind"], "seed": case["seed"],
            "noise_mm": case.get("noise_mm"), "n_points": case.get("n_points"), "status": "failed", "note": ""}


def child_main(task: dict, result_path: str) -> None:
    """Entry point of the spawned child: run the task, write its row (JSON) to result_path."""
    sampler = RssSampler().start()
    timer = StageTimer(sampler)
    row = base_row(task)
    try:
        extra = TASK_RUNNERS[task["spec"]["kind"]](task, sampler, timer)
        note = " ".join(x for x in (row.get("note"), extra.pop("note", "")) if x)
        row.update(extra, status="ok", note=note)
    except Exception as exc:  # noqa: BLE001  (the row records the failure; the benchmark goes on)
        row["note"] = f"{type(exc).__name__}: {getattr(exc, 'message', None) or exc}"[:400]
        Path(task["rundir"], "error.txt").write_text(traceback.format_exc())
    finally:
        sampler.stop()
    row.update(sampler.columns())
    Path(result_path).write_text(json.dumps(row, default=_json_default))


def _json_default(o):
    if isinstance(o, (np.floating, np.integer, np.bool_)):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o)}")


# ----------------------------------------------------------------------------- parent side


def slug(text: str) -> str:
    """File-name-safe version of a label."""
    return "".join(ch if ch.isalnum() or ch in "-." else "_" for ch in text).strip("_")


def make_task(spec: MethodSpec, case: Case, outdir: Path, metric_samples: int, device: str, render: bool) -> dict:
    """JSON-able description of one run for the child (its own folder under outdir/runs/)."""
    rundir = Path(outdir) / "runs" / f"{slug(case.name)}-seed{case.seed}__{slug(spec.label)}"
    return {"spec": asdict(spec), "case": asdict(case), "rundir": str(rundir), "metric_samples": int(metric_samples),
            "device": device, "render": bool(render)}


def run_task(task: dict, timeout_s: float | None = None) -> dict:
    """Run one task in a fresh spawned child and return its row; a child that dies or runs past
    timeout_s gives a failed row. wall_s: the child's whole life (start-up and imports included)."""
    rundir = Path(task["rundir"])
    if rundir.exists():
        shutil.rmtree(rundir)
    rundir.mkdir(parents=True)
    result = rundir / "row.json"
    proc = mp.get_context("spawn").Process(target=child_main, args=(task, str(result)), daemon=False)
    t0 = time.perf_counter()
    proc.start()
    proc.join(timeout_s)
    if proc.is_alive():
        proc.terminate()
        proc.join()
    wall = round(time.perf_counter() - t0, 2)
    if result.exists():
        row = json.loads(result.read_text())
    else:
        row = base_row(task)
        if timeout_s and wall >= timeout_s:
            why = f"stopped after running past --task-timeout {timeout_s:g} s"
        elif proc.exitcode == -9:
            why = "killed by SIGKILL: out of memory?"
        else:
            why = f"exit code {proc.exitcode}; see the log above"
        row["note"] = f"child process died ({why})"
    row["wall_s"] = wall
    return row


def run_plan(outdir: Path, plan: list, metric_samples: int, device: str = "auto", timeout_s: float | None = None,
             log=print) -> list[dict]:
    """Run every (MethodSpec, Case) of the plan in order; renders each method on its first case with
    ground truth (copied to outdir/renders/). Returns the rows."""
    rows, rendered = [], set()
    for i, (spec, case) in enumerate(plan, 1):
        render = case.truth_mesh is not None and spec.label not in rendered
        if render:
            rendered.add(spec.label)
        task = make_task(spec, case, outdir, metric_samples, device, render)
        log(f"[{i}/{len(plan)}] {spec.label} on {case.name} (seed {case.seed}) ...")
        row = run_task(task, timeout_s)
        rows.append(row)
        copy_render(task, outdir)
        log(f"    {row_summary(row)}")
    return rows


def copy_render(task: dict, outdir: Path) -> Path | None:
    """Copy a run's render.png to outdir/renders/<method>__<case>.png (None when there is none)."""
    src = Path(task["rundir"]) / "render.png"
    if not src.exists():
        return None
    dst = Path(outdir) / "renders" / f"{slug(task['spec']['label'])}__{slug(task['case']['name'])}.png"
    dst.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(src, dst)
    return dst


def row_summary(row: dict) -> str:
    """One line: status, time, CD-L1, F-score, peak memory."""
    if row.get("status") != "ok":
        return f"{row.get('status')}: {row.get('note', '')}"
    parts = ["ok", f"{_num(row.get('time_total_s')):.1f} s"]
    if _finite(row.get("cd_l1_mm")):
        parts.append(f"CD-L1 {row['cd_l1_mm']:.3f} mm ({row['reference']}), F@{FSCORE_TAU_MM:g}mm {row['fscore']:.3f}")
    if _finite(row.get("skel_mean_dist_mm")):
        parts.append(f"skeleton mean {row['skel_mean_dist_mm']:.2f} mm")
    if _finite(row.get("ms_per_iteration")):
        parts.append(f"{row['ms_per_iteration']:.1f} ms/it")
    parts.append(f"peak {_num(row.get('peak_rss_mb')):.0f} MB")
    return ", ".join(parts)


def skeleton_plan(case: Case) -> list[tuple[MethodSpec, Case]]:
    """The skeleton section's extra runs on a phantom case: contraction on the true surface and voxel
    thinning of the true solid (the reconstructions' skeletons come from the method rows)."""
    runs = [(MethodSpec("contraction on true surface", "contraction_truth"), case)]
    if SKELETON_BENCHMARK.exists():
        runs.append((MethodSpec(f"voxel thinning {MASK_SPACING_MM:g} mm", "voxel_thinning"), case))
    return runs


def speed_plan(case: Case, default_row: dict | None, paper_row: dict | None = None,
               iterations: int = SPEED_PAPER_ITERATIONS) -> list[tuple[MethodSpec, Case]]:
    """Speed section runs: the paper preset for `iterations` iterations (fit only) unless the plan
    already ran it on this case (paper_row), and the default preset's full schedule (fit only) unless
    a successful default row on this case can be reused."""
    runs = []
    if paper_row is None:
        runs.append((MethodSpec(f"sparseocc paper ({iterations} it timed)", "speed", preset="paper",
                                method="sparseocc", iterations=iterations), case))
    if default_row is None:
        runs.append((MethodSpec("sparseocc default (fit only)", "speed", preset="default", method="sparseocc"), case))
    return runs


def preset_schedule(preset: str, method: str = "sparseocc") -> int:
    """Iterations of a preset's full schedule."""
    from .methods import build_fit_config

    return int(build_fit_config(preset, method).method_config.iterations)


def speed_rows(default_row: dict | None, timed: list[dict], paper_row: dict | None = None) -> list[dict]:
    """Rows of the speed table (paper vs default on the same case, same machine, same run), with the
    ratios: per-iteration cost and fit time (paper extrapolated to its full schedule / default
    measured). paper_row: a (shortened) paper-preset run of the plan on that case, preferred to the
    speed section's own short timing."""
    out = []
    d = default_row or next((r for r in timed if r.get("preset") == "default" and r.get("status") == "ok"), None)
    if d is not None and d.get("status") == "ok":
        out.append({"preset": "default", "method": d["method"], "case": d["case"], "iterations": d.get("iterations_run"),
                    "schedule": d.get("iterations_planned"), "ms_per_iteration": d.get("ms_per_iteration"),
                    "fit_overhead_s": d.get("fit_overhead_s"), "fit_s": d.get("time_fit_s"),
                    "pipeline_total_s": d.get("time_total_s"), "fit_s_kind": "measured"})
    p = paper_row or next((r for r in timed if r.get("preset") == "paper"), None)
    if paper_row is not None and paper_row.get("status") == "ok" and _finite(paper_row.get("ms_per_iteration")):
        schedule = preset_schedule("paper")
        p = {**paper_row, "iterations_planned": schedule,
             "extrapolated_fit_s": round(_num(paper_row.get("fit_overhead_s")) + schedule * float(paper_row["ms_per_iteration"]) / 1000, 1)}
    if p is not None and p.get("status") == "ok":
        out.append({"preset": "paper", "method": p["method"], "case": p["case"], "iterations": p.get("iterations_run"),
                    "schedule": p.get("iterations_planned"), "ms_per_iteration": p.get("ms_per_iteration"),
                    "fit_overhead_s": p.get("fit_overhead_s"), "fit_s": p.get("extrapolated_fit_s"),
                    "pipeline_total_s": None, "fit_s_kind": f"extrapolated from {p.get('iterations_run')} iterations"})
    if len(out) == 2 and all(_finite(r["ms_per_iteration"]) and _finite(r["fit_s"]) for r in out):
        out.append({"preset": "ratio paper / default", "ms_per_iteration": out[1]["ms_per_iteration"] / out[0]["ms_per_iteration"],
                    "fit_s": out[1]["fit_s"] / out[0]["fit_s"], "fit_s_kind": "extrapolated / measured"})
    return out


# ---------------------------------------------------------------------------------- writers


def _finite(x) -> bool:
    try:
        return x is not None and x != "" and math.isfinite(float(x))
    except (TypeError, ValueError):
        return False


def _num(x) -> float:
    return float(x) if _finite(x) else float("nan")


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


def rewrite_outputs(outdir: Path, meta: dict | None = None, notes: list[str] | None = None) -> dict:
    """Rebuild results.md and the plots of outdir from its results.csv (+ skeleton.csv, speed.csv when
    present), e.g. after rows of several runs were put into one results.csv. Returns write_outputs'."""
    outdir = Path(outdir)
    if not (outdir / "results.csv").exists():
        from .errors import RibPullInputError

        raise RibPullInputError("bad_parameter", f"{outdir / 'results.csv'} does not exist: nothing to rewrite")
    rows = read_csv(outdir / "results.csv")
    skel = read_csv(outdir / "skeleton.csv") if (outdir / "skeleton.csv").exists() else None
    speed = read_csv(outdir / "speed.csv") if (outdir / "speed.csv").exists() else None
    return write_outputs(outdir, rows, skel, speed, meta, notes)


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


def decimals_for(x: float) -> int:
    """Decimals that show ~3 significant digits of x (1 to 4): 1.55 -> 2, 12.6 -> 1, 0.712 -> 3."""
    if not _finite(x) or x == 0:
        return 3
    return int(min(4, max(1, 2 - math.floor(math.log10(abs(x))))))


def mean_std(values) -> tuple[float, float, int]:
    """(mean, sample std (n-1; 0 when n = 1), n) of the finite values; (nan, nan, 0) if none."""
    v = np.array([float(x) for x in values if _finite(x)])
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
    lines = [f"### Surface accuracy: {group} (reference: {ref})", "",
             f"| {'Case: method' if by_case else 'Method'} | n | " + " | ".join(h for h, _, _ in ACCURACY_COLUMNS) + " |",
             "|---|---:|" + "---:|" * len(ACCURACY_COLUMNS)]
    for k in keys:
        ok = [r for r in sel if key(r) == k and r.get("status") == "ok"]
        bad = [r for r in sel if key(r) == k and r.get("status") != "ok"]
        n = f"{len(ok)}" + (f" ({len(bad)} failed)" if bad else "")
        cells = [fmt([r.get(c) for r in ok]) for _, c, fmt in ACCURACY_COLUMNS]
        lines.append(f"| {k} | {n} | " + " | ".join(cells) + " |")
    return lines


def skeleton_table(rows: list[dict], case_name: str | None) -> list[str]:
    """Markdown lines of the skeleton section: every row of case_name with skeleton metrics."""
    sel = [r for r in rows if r.get("case") == case_name and _finite(r.get("skel_mean_dist_mm"))]
    lines = ["| Skeleton | mean (mm) | p95 (mm) | max (mm) | coverage@2mm | paths | branch nodes | cycles | labels | skeleton time (s) |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in sel:
        src = r["method"] if r.get("kind") in ("contraction_truth", "voxel_thinning") else f"contraction on reconstruction: {r['method']}"
        lab = "—" if not _finite(r.get("skel_label_accuracy")) else f"{float(r['skel_label_accuracy']):.2f}"
        lines.append(f"| {src} | {_num(r['skel_mean_dist_mm']):.3f} | {_num(r.get('skel_p95_dist_mm')):.3f} | "
                     f"{_num(r.get('skel_max_dist_mm')):.2f} | {_num(r.get('skel_coverage')):.3f} | {r.get('skel_n_paths')} | "
                     f"{r.get('skel_n_branch_nodes')} | {r.get('skel_n_cycles')} | {lab} | {_num(r.get('time_skeleton_s')):.1f} |")
    return lines


def speed_table(speed: list[dict]) -> list[str]:
    """Markdown lines of the speed section."""
    lines = ["| Preset | iterations timed | schedule | ms / iteration | fit overhead (s) | fit time (s) | how |",
             "|---|---:|---:|---:|---:|---:|---|"]
    for r in speed:
        if r["preset"].startswith("ratio"):
            lines.append(f"| **{r['preset']}** | | | **{r['ms_per_iteration']:.2f}×** | | **{r['fit_s']:.1f}×** | {r['fit_s_kind']} |")
            continue
        lines.append(f"| {r['preset']} ({r['method']}) | {r.get('iterations')} | {r.get('schedule')} | "
                     f"{_num(r.get('ms_per_iteration')):.1f} | {_num(r.get('fit_overhead_s')):.1f} | {_num(r.get('fit_s')):.1f} | {r['fit_s_kind']} |")
    return lines


def write_markdown(path: Path, rows: list[dict], skeleton_rows: list[dict] | None = None,
                   speed: list[dict] | None = None, meta: dict | None = None, notes: list[str] | None = None,
                   figures: list[str] | None = None) -> str:
    """results.md: run details, one accuracy table per case group (paper format, mm and paper units),
    the paper's Table 1 for context, the skeleton and speed sections, notes, figures. Returns the text."""
    meta = meta or {}
    out = ["# RibPull benchmark", ""]
    for k, v in meta.items():
        out.append(f"- **{k}**: {v}")
    out += ["", ("Paper units: lengths in the input's normalised frame (longest bounding-box side = 2, as in the "
            "paper), CD-L1 and HD ×100, CD-L2 ×10⁴. mean ± std over cases × seeds (sample std; 0 for one row). "
            "NC: normal consistency; F: F-score at the given distance. time: the method's own wall time "
            "(scoring excluded); peak RSS: the child process's own peak (VmHWM)."), ""]
    for g in [*GROUP_ORDER, *sorted({r.get("group") for r in rows} - set(GROUP_ORDER) - {None})]:
        if any(r.get("group") == g for r in rows):
            out += accuracy_table(rows, g, by_case=g in GROUPS_BY_CASE) + [""]
    out += ["### For context: the paper's Table 1 (20 real RibSeg cases, paper units; not this run)", "",
            "| Method | CD-L1 | CD-L2 | HD |", "|---|---:|---:|---:|"]
    out += [f"| {m} | {a} | {b} | {c} |" for m, (a, b, c) in PAPER_TABLE1.items()] + [""]
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
        out += [f"- {r['method']} on {r['case']} (seed {r['seed']}): {r.get('status')}: {r.get('note', '')}" for r in failed]
        out.append("")
    if figures:
        out += ["## Figures", ""] + [f"![{Path(f).stem}]({f})" for f in figures] + [""]
    text = "\n".join(out)
    Path(path).write_text(text)
    return text


# ---------------------------------------------------------------------------------- plots


def _figure(w: float, h: float):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(w, h), dpi=100)
    FigureCanvasAgg(fig)
    return fig


def plot_metric_bars(path: Path, rows: list[dict], group: str | None = None) -> Path:
    """PNG bar chart, one bar per method (mean, std error bar) of CD-L1 (mm), Hausdorff (mm) and
    F-score for one case group (default: the first group with successful rows)."""
    ok = [r for r in rows if r.get("status") == "ok" and _finite(r.get("cd_l1_mm"))]
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
            ax.text(0.5, 0.5, "no successful rows", transform=ax.transAxes, ha="center")
    fig.subplots_adjust(bottom=0.3, wspace=0.3)
    fig.savefig(path, facecolor="white")
    return Path(path)


def plot_accuracy_vs_time(path: Path, rows: list[dict]) -> Path:
    """PNG scatter: CD-L1 (mm) against the method's wall time (s), both log scale, one colour per
    method, one marker per case group."""
    ok = [r for r in rows if r.get("status") == "ok" and _finite(r.get("cd_l1_mm")) and _finite(r.get("time_total_s"))]
    methods = list(dict.fromkeys(r["method"] for r in ok))
    colours = _colours(methods)
    markers = dict(zip(GROUP_ORDER, "osD^"))
    fig = _figure(8, 5.5)
    ax = fig.add_subplot(1, 1, 1)
    for r in ok:
        ax.scatter(max(float(r["time_total_s"]), 1e-3), max(float(r["cd_l1_mm"]), 1e-4), color=colours[r["method"]],
                   marker=markers.get(r.get("group"), "v"), s=40, edgecolors="black", linewidths=0.4)
    for m in methods:
        ax.scatter([], [], color=colours[m], label=m)
    for g in dict.fromkeys(r.get("group") for r in ok):
        ax.scatter([], [], color="grey", marker=markers.get(g, "v"), label=g)
    if ok:
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.legend(fontsize=7, loc="best")
    else:
        ax.text(0.5, 0.5, "no successful rows", transform=ax.transAxes, ha="center")
    ax.set_xlabel("wall time of the method (s)")
    ax.set_ylabel("CD-L1 (mm) vs the true surface (phantoms) or the input (others)")
    ax.set_title("Accuracy vs time (colour: method, marker: case group)")
    ax.grid(alpha=0.3, which="both")
    fig.savefig(path, facecolor="white")
    return Path(path)


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


def _colours(methods: list[str]) -> dict[str, tuple]:
    from matplotlib import colormaps

    cmap = colormaps["tab10"]
    return {m: cmap(i % 10) for i, m in enumerate(methods)}


def write_outputs(outdir: Path, rows: list[dict], skeleton_rows=None, speed=None, meta=None, notes=None) -> dict:
    """results.csv, skeleton.csv, speed.csv, the plots, renders.png and results.md in outdir.
    Returns {"markdown": text, name: path}."""
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    paths = {"results.csv": write_csv(outdir / "results.csv", rows)}
    if skeleton_rows is not None:
        paths["skeleton.csv"] = write_csv(outdir / "skeleton.csv", skeleton_rows)
    if speed is not None:
        paths["speed.csv"] = write_csv(outdir / "speed.csv", speed, columns=())
    paths["metrics_by_method.png"] = plot_metric_bars(outdir / "metrics_by_method.png", rows)
    paths["accuracy_vs_time.png"] = plot_accuracy_vs_time(outdir / "accuracy_vs_time.png", rows)
    renders = montage(outdir / "renders.png", sorted((outdir / "renders").glob("*.png")))
    if renders is not None:
        paths["renders.png"] = renders
    figures = [n for n in ("metrics_by_method.png", "accuracy_vs_time.png", "renders.png") if n in paths]
    text = write_markdown(outdir / "results.md", rows, skeleton_rows, speed, meta, notes, figures)
    paths["results.md"] = outdir / "results.md"
    return {"markdown": text, **paths}


# ------------------------------------------------------------------------------------ CLI


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The `ribpull bench` options."""
    parser.add_argument("-o", "--output", required=True, help="output directory (results.csv, results.md, PNGs, runs/)")
    parser.add_argument("--quick", action="store_true",
                        help="<= 15 min on 2 cores: one phantom case, short baselines, mask + real map, skeletons, "
                             "speed (same as --plan quick)")
    parser.add_argument("--plan", choices=PLANS, default=None,
                        help="quick (as --quick); docs: what docs/benchmarks.md shows (~65 min on 2 cores); "
                             "full: every method on every case and seed, SparseOcc paper at 20k iterations "
                             "(hours; default)")
    parser.add_argument("--cases", default=None, help="folder of extra inputs (point files, label maps, phantom folders)")
    parser.add_argument("--seeds", type=int, nargs="+", default=None, help=f"seeds (default {list(FULL_SEEDS)}; quick: 0)")
    parser.add_argument("--methods", nargs="+", default=None,
                        help="only methods whose label starts with one of these (or of this kind: pipeline, poisson, mask_mc)")
    parser.add_argument("--points", type=int, default=None, help=f"points of the main phantom case (default {QUICK_POINTS})")
    parser.add_argument("--label-map", default=str(REAL_LABEL_MAP), help="the real label map case ('' to leave out)")
    parser.add_argument("--metric-samples", type=int, default=METRIC_SAMPLES, help="surface samples per side for scoring")
    parser.add_argument("--device", default="auto", help="auto | cpu | cuda (neural methods)")
    parser.add_argument("--task-timeout", type=float, default=None, help="seconds after which one run is stopped")
    parser.add_argument("--no-skeleton-section", action="store_true")
    parser.add_argument("--no-speed-section", action="store_true")
    parser.add_argument("--rewrite", action="store_true",
                        help="run nothing: rebuild results.md and the plots in -o DIR from its CSVs")


def sparseocc_row(rows: list[dict], case: Case, preset: str) -> dict | None:
    """The plan's first successful SparseOcc pipeline row of `preset` on `case` (None if there is none)."""
    return next((r for r in rows if r["case"] == case.name and r.get("kind") == "pipeline" and r.get("preset") == preset
                 and r.get("fit_method") == "sparseocc" and r.get("status") == "ok"), None)


def run_bench(outdir: Path, plan: list, *, metric_samples: int = METRIC_SAMPLES, device: str = "auto",
              skeleton_case: Case | None = None, speed_case: Case | None = None, notes: list[str] | None = None,
              meta: dict | None = None, timeout_s: float | None = None, speed_iterations: int = SPEED_PAPER_ITERATIONS,
              log=print) -> dict:
    """Run a plan and the optional skeleton and speed sections, write every output (write_outputs).
    Returns write_outputs' dict plus "rows", "skeleton_rows", "speed"."""
    outdir = Path(outdir)
    t0 = time.perf_counter()
    rows = run_plan(outdir, plan, metric_samples, device, timeout_s, log)
    skel_rows = None
    if skeleton_case is not None:
        log("skeleton section ...")
        skel_rows = run_plan(outdir, skeleton_plan(skeleton_case), metric_samples, device, timeout_s, log)
    speed = None
    if speed_case is not None:
        log("speed section ...")
        default_row, paper_row = (sparseocc_row(rows, speed_case, p) for p in ("default", "paper"))
        timed = run_plan(outdir, speed_plan(speed_case, default_row, paper_row, speed_iterations), metric_samples,
                         device, timeout_s, log)
        speed = speed_rows(default_row, timed, paper_row)
    meta = {**(meta or {}), "bench wall time": f"{time.perf_counter() - t0:.0f} s"}
    result = write_outputs(outdir, rows, skel_rows, speed, meta, notes)
    return {**result, "rows": rows, "skeleton_rows": skel_rows, "speed": speed}


def machine_meta() -> dict:
    """Where and how the benchmark ran (for results.md)."""
    import torch

    from .pipeline import configure_torch_threads

    return {"machine": f"{platform.machine()} {platform.processor() or ''}, {os.cpu_count()} cores, "
                       f"torch {torch.__version__} with {configure_torch_threads()} threads, "
                       f"CUDA {'yes' if torch.cuda.is_available() else 'no'}, Python {platform.python_version()}",
            "date": time.strftime("%Y-%m-%d %H:%M %Z")}


def main(args: argparse.Namespace) -> int:
    """`ribpull bench`: build the plan, run it, write the outputs, print results.md. 0 if any row succeeded."""
    outdir = Path(args.output)
    if args.rewrite:
        result = rewrite_outputs(outdir, {"rewritten from": str(outdir / "results.csv"),
                                          "date": time.strftime("%Y-%m-%d %H:%M %Z")})
        print(result["markdown"])
        return 0
    outdir.mkdir(parents=True, exist_ok=True)
    mode = "quick" if args.quick else (args.plan or "full")
    if args.quick and args.plan not in (None, "quick"):
        print(f"ribpull bench: --quick and --plan {args.plan} disagree; choose one", file=sys.stderr)
        return 2
    seeds = tuple(args.seeds) if args.seeds else ((0,) if mode == "quick" else FULL_SEEDS)
    notes: list[str] = []
    plan, cases = build_plan(mode, outdir / "cases", seeds, args.points,
                             Path(args.cases) if args.cases else None,
                             Path(args.label_map) if args.label_map else None, args.methods, notes)
    if importlib_missing("pymeshlab"):
        notes.append("screened Poisson skipped: pymeshlab is not installed (pip install 'ribpull[bench]')")
        plan = [(m, c) for m, c in plan if m.kind != "poisson"]
    truth_points = next((c for c in cases if c.group == GROUP_POINTS), None)
    its = {m.label: (m.iterations or "preset schedule") for m, _ in plan if m.kind == "pipeline"}
    meta = {"command": "ribpull " + " ".join(sys.argv[1:]) if Path(sys.argv[0]).name == "ribpull" else f"ribpull bench ({mode})",
            "mode": mode, "seeds": list(seeds), "iterations": ", ".join(f"{k}: {v}" for k, v in its.items()) or "—",
            "surface metric samples per side": f"{args.metric_samples:,}", **machine_meta()}
    if not args.no_speed_section:
        meta["speed section"] = ("paper preset's full schedule extrapolated from its run in the plan, else from "
                                 f"{SPEED_PAPER_ITERATIONS} timed iterations")
    print(f"ribpull bench ({mode}): {len(plan)} runs on {len(cases)} cases -> {outdir}", file=sys.stderr)
    for label, n in its.items():
        print(f"  {label}: {n} iterations", file=sys.stderr)
    for n in notes:
        print(f"  note: {n}", file=sys.stderr)
    result = run_bench(outdir, plan, metric_samples=args.metric_samples, device=args.device,
                       skeleton_case=None if args.no_skeleton_section else truth_points,
                       speed_case=None if args.no_speed_section else truth_points, notes=notes, meta=meta,
                       timeout_s=args.task_timeout, log=lambda s: print(s, file=sys.stderr, flush=True))
    print(result["markdown"])
    print(f"\nwrote {outdir / 'results.csv'}, {outdir / 'results.md'} and the PNGs", file=sys.stderr)
    return 0 if any(r.get("status") == "ok" for r in result["rows"]) else 1


def importlib_missing(name: str) -> bool:
    """True when module `name` cannot be found (without importing it)."""
    import importlib.util

    return importlib.util.find_spec(name) is None
