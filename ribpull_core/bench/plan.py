"""What `ribpull bench` runs: methods (MethodSpec), inputs (Case), the case builders and the plans
quick | docs | full | sweep, plus the skeleton and speed sections' extra runs.

Building a plan writes the synthetic phantoms it needs (`phantom.write_phantom`) unless asked not to
(`write=False`); `ensure_case_files` writes a phantom case that is not on disk yet. Lengths in mm.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .baselines import TAUBIN_ITERATIONS
from .common import (
    GROUP_ACC_MASKS,
    GROUP_ACC_POINTS,
    GROUP_ACC_STERNUM,
    GROUP_MASK,
    GROUP_POINTS,
    GROUP_REAL,
    GROUP_SWEEP,
    GROUP_USER,
    REAL_LABEL_MAP,
    SKELETON_BENCHMARK,
    spacing_label,
)

QUICK_POINTS = 20_000
QUICK_NOISE_MM = 0.3
QUICK_NEURALPULL_ITERATIONS = 200  # default (reference 8x256) network, short schedule (~0.2 s/it on 2 cores)
QUICK_DIGS_ITERATIONS = 60  # default (reference SIREN) network, the smoke preset's length (~1 s/it on 2 cores)
BASELINE_RESOLUTION = 256  # marching-cubes resolution of the Neural-Pull / DiGS baselines (the papers')
SPEED_PAPER_ITERATIONS = 100  # paper preset iterations timed when the plan has no paper run on the case
MASK_SPACING_MM = 1.0  # voxel size of the voxelised phantom masks (quick | docs | full)
MASK_CASE_POINTS = 1_000  # size of the (unused) points.ply written next to a phantom mask
FULL_SEEDS = (0, 1, 2)
SWEEP_SEEDS = (0,)
#: (n_points, noise_mm) of the main phantom point-cloud case (every method, every seed)
MAIN_POINT_CASE = (20_000, 0.3)
#: the docs / full sweep around it: noise 0 / 1 mm at 20k points, 5k / 100k points at 0.3 mm
SWEEP_POINT_CASES = ((20_000, 0.0), (20_000, 1.0), (5_000, 0.3), (100_000, 0.3))
#: the docs run (`--plan docs`, what docs/benchmarks.md shows): the expensive neural methods on the
#: first DOCS_EXPENSIVE_SEEDS seeds only, and SparseOcc's `paper` preset cut to DOCS_PAPER_ITERATIONS
#: of its 20k (its full schedule is ~2 h per case on the 2-core CPU)
DOCS_EXPENSIVE_SEEDS = 2
DOCS_PAPER_ITERATIONS = 2_000

#: `--plan sweep` (issue 9's accuracy sweep), every case on the synthetic phantom, scored against the
#: true surface: point counts x noise levels (mm) ...
ACCURACY_POINT_COUNTS = (5_000, 10_000, 20_000, 60_000, 200_000)
ACCURACY_NOISES_MM = (0.0, 0.3, 1.0)
#: ... plus uniform outliers (this fraction of n_points, added) at these (n_points, noise_mm) ...
ACCURACY_OUTLIER_FRACTION = 0.02
ACCURACY_OUTLIER_CASES = ((60_000, 0.3), (20_000, 0.3))
#: ... outliers drawn uniformly in the points' bounding box grown by this fraction of its size per side
OUTLIER_BOX_MARGIN = 0.05
#: ... partial-volume-correct label maps at these voxel sizes (mm; a number = isotropic) ...
ACCURACY_LABEL_SPACINGS_MM = (1.5, (0.75, 0.75, 2.5))
#: ... and the sternum phantom (sternum + costal cartilages): this point cloud and label map
STERNUM_POINT_CASE = (60_000, 0.3)
STERNUM_SPACING_MM = 1.5

PLANS = ("quick", "docs", "full", "sweep")
POINT_SUFFIXES = (".ply", ".xyz", ".txt", ".csv", ".npy", ".npz", ".pcd")
MASK_SUFFIXES = (".nii", ".nii.gz")
#: method kinds that run outside run_pipeline (their rows share the classical task runner)
CLASSICAL_KINDS = ("poisson", "mask_mc", "mc_taubin")


@dataclass(frozen=True)
class MethodSpec:
    """One benchmarked method. kind: "pipeline" (run_pipeline with preset / method / iterations /
    resolution), "poisson" (screened Poisson on the points), "mask_mc" (marching cubes on the label
    mask) or "mc_taubin" (the same followed by TAUBIN_ITERATIONS Taubin passes); the skeleton and
    speed sections add "contraction_truth", "voxel_thinning" and "speed". inputs: the input kinds
    ("points", "mask") it applies to."""

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
    sampling (None otherwise). phantom: a synthetic phantom built here (its Phantom can be rebuilt
    from seed + sternum, so rib separation is scored); variant: the case's name without the seed;
    sternum: the phantom has a sternum and costal cartilages; spacing_mm: voxel size (x, y, z) of a
    phantom label map; partial_volume: that map is partial-volume correct; outlier_fraction: uniform
    outliers added to a phantom point cloud (fraction of n_points); labels: the NIfTI label values a
    label-map case is read with (None: the loader's default, the rib labels; the sternum phantom's
    map keeps its sternum and cartilage labels too, like its point cloud)."""

    name: str
    group: str
    input_path: str
    input_kind: str
    seed: int = 0
    noise_mm: float | None = None
    n_points: int | None = None
    truth_mesh: str | None = None
    centerlines: str | None = None
    phantom: bool = False
    variant: str | None = None
    sternum: bool = False
    spacing_mm: tuple[float, float, float] | None = None
    partial_volume: bool = False
    outlier_fraction: float = 0.0
    labels: tuple[int, ...] | None = None


SPARSEOCC_DEFAULT = MethodSpec("sparseocc default", "pipeline", preset="default")
POISSON = MethodSpec("screened poisson", "poisson", inputs=("points",))
MASK_MC = MethodSpec("mask marching cubes", "mask_mc", inputs=("mask",))
MC_TAUBIN = MethodSpec(f"mc_taubin ({TAUBIN_ITERATIONS} it)", "mc_taubin", inputs=("mask",))


def _neural_baseline(method: str, iterations: int | None = None, points_only: bool = False) -> MethodSpec:
    """Neural-Pull / DiGS at the `default` preset with the papers' marching-cubes resolution; labelled
    "<method> <iterations> it" when the schedule is cut, else "<method> default"."""
    label = f"{method} {iterations} it" if iterations else f"{method} default"
    return MethodSpec(label, "pipeline", preset="default", method=method, iterations=iterations,
                      resolution=BASELINE_RESOLUTION, inputs=("points",) if points_only else ("points", "mask"))


def quick_methods() -> list[MethodSpec]:
    """--quick: SparseOcc default, the baselines' reference networks for a smoke-length schedule,
    screened Poisson, marching cubes on masks."""
    return [SPARSEOCC_DEFAULT, _neural_baseline("neuralpull", QUICK_NEURALPULL_ITERATIONS),
            _neural_baseline("digs", QUICK_DIGS_ITERATIONS), POISSON, MASK_MC]


def docs_methods() -> tuple[list[MethodSpec], list[MethodSpec]]:
    """--plan docs: (cheap, expensive). Cheap: SparseOcc default, screened Poisson, mask marching
    cubes, run on every case. Expensive: SparseOcc `paper` cut to DOCS_PAPER_ITERATIONS, Neural-Pull
    and DiGS at their `default` presets, run on the main case of the first DOCS_EXPENSIVE_SEEDS seeds."""
    paper = MethodSpec(f"sparseocc paper {DOCS_PAPER_ITERATIONS // 1000}k it", "pipeline", preset="paper",
                       iterations=DOCS_PAPER_ITERATIONS, inputs=("points",))
    return ([SPARSEOCC_DEFAULT, POISSON, MASK_MC],
            [paper, _neural_baseline("neuralpull", points_only=True), _neural_baseline("digs", points_only=True)])


def full_methods() -> list[MethodSpec]:
    """The full run (hours: meant for a GPU or a night): every method at its `default` preset and
    SparseOcc's `paper` preset at its full 20k-iteration schedule (~2 h per case on a 2-core CPU)."""
    return [SPARSEOCC_DEFAULT, MethodSpec("sparseocc paper", "pipeline", preset="paper", inputs=("points",)),
            _neural_baseline("neuralpull"), _neural_baseline("digs"), POISSON, MASK_MC]


def sweep_methods() -> list[MethodSpec]:
    """--plan sweep: SparseOcc default everywhere, screened Poisson (flood-fill normals) on the point
    clouds, mc_taubin and plain mask marching cubes on the label maps."""
    return [SPARSEOCC_DEFAULT, POISSON, MC_TAUBIN, MASK_MC]


def baseline_kind(input_kind: str) -> str:
    """The kind of the baseline the sweep compares SparseOcc default with: "poisson" for point clouds,
    "mc_taubin" for label maps."""
    return "poisson" if input_kind == "points" else "mc_taubin"


# ---------------------------------------------------------------------------------- cases


def phantom_config(seed: int, sternum: bool = False, n_points: int = MASK_CASE_POINTS, noise_mm: float = 0.0):
    """phantom.PhantomConfig of a bench case (`sternum` is passed only when set)."""
    from ..phantom import PhantomConfig

    return PhantomConfig(seed=int(seed), n_points=int(n_points), noise_mm=float(noise_mm),
                         **({"sternum": True} if sternum else {}))


def phantom_case(workdir: Path, seed: int, n_points: int, noise_mm: float, mask: bool = False,
                 group: str | None = None, *, spacing_mm: float | tuple[float, float, float] = MASK_SPACING_MM,
                 partial_volume: bool = False, sternum: bool = False, outlier_fraction: float = 0.0,
                 write: bool = True) -> Case:
    """A synthetic ribcage case under workdir/<name>/ (phantom.write_phantom; written now unless
    write=False, see ensure_case_files): the point cloud (n_points samples, noise_mm Gaussian noise,
    plus outlier_fraction x n_points uniform outliers) or, with mask, the label map voxelised at
    spacing_mm (a number or (x, y, z) mm; partial_volume: partial-volume correct; n_points and
    noise_mm are then ignored). sternum: the phantom with sternum and costal cartilages. group: the
    table it is reported in (default: GROUP_MASK for masks, else GROUP_POINTS)."""
    spacing = tuple(float(v) for v in np.broadcast_to(np.asarray(spacing_mm, dtype=np.float64), (3,)))
    if mask:
        variant = f"mask{spacing_label(spacing)}mm" + ("-pv" if partial_volume else "")
    else:
        variant = f"n{n_points}-noise{noise_mm:g}" + (f"-out{100 * outlier_fraction:g}pct" if outlier_fraction else "")
    variant = ("sternum-" if sternum else "") + variant
    name = f"phantom-s{seed}-{variant}"
    folder = Path(workdir) / name
    case = Case(name=name, group=group or (GROUP_MASK if mask else GROUP_POINTS),
                input_path=str(folder / ("mask.nii.gz" if mask else "points.ply")),
                input_kind="mask" if mask else "points", seed=seed, noise_mm=None if mask else float(noise_mm),
                n_points=None if mask else int(n_points), truth_mesh=str(folder / "truth_mesh.ply"),
                centerlines=str(folder / "centerlines.json"), phantom=True, variant=variant, sternum=sternum,
                spacing_mm=spacing if mask else None, partial_volume=bool(partial_volume and mask),
                outlier_fraction=0.0 if mask else float(outlier_fraction),
                labels=sternum_phantom_labels() if mask and sternum else None)
    if write:
        write_case(case)
    return case


def sternum_phantom_labels() -> tuple[int, ...]:
    """Every label value of the sternum phantom's map: the 24 TotalSegmentator rib labels, the
    sternum and the costal cartilages."""
    from ..io import TOTALSEG_RIB_LABELS
    from ..phantom import CARTILAGE_LABEL, STERNUM_LABEL

    return (*TOTALSEG_RIB_LABELS, STERNUM_LABEL, CARTILAGE_LABEL)


def write_case(case: Case) -> dict[str, Path]:
    """Write a phantom case's files (write_phantom into the folder of case.input_path, then the
    outliers if any). Returns write_phantom's {name: path}."""
    from ..phantom import write_phantom

    folder = Path(case.input_path).parent
    if case.input_kind == "mask":
        spacing = case.spacing_mm[0] if len(set(case.spacing_mm)) == 1 else tuple(case.spacing_mm)
        files = write_phantom(folder, phantom_config(case.seed, case.sternum), nifti=True, spacing_mm=spacing,
                              **({"partial_volume": True} if case.partial_volume else {}))
        key = "mask"
    else:
        files = write_phantom(folder, phantom_config(case.seed, case.sternum, case.n_points, case.noise_mm))
        key = "points"
        if case.outlier_fraction:
            add_outliers(files["points"], case.outlier_fraction, seed=case.seed)
    assert Path(files[key]) == Path(case.input_path) and Path(files["truth_mesh"]) == Path(case.truth_mesh)
    return files


def add_outliers(path: Path, fraction: float, seed: int = 0, margin: float = OUTLIER_BOX_MARGIN) -> int:
    """Append round(fraction x N) points drawn uniformly in the bounding box of the N points of the
    point file at `path` grown by `margin` x its size on every side (mm), with random unit normals and
    the label of the nearest original point; rewrites the file. Returns the number added."""
    from scipy.spatial import cKDTree

    from ..io import load_point_cloud, write_point_cloud
    from ..pointcloud import PointCloud

    cloud = load_point_cloud(Path(path))
    n = round(fraction * len(cloud))
    rng = np.random.default_rng(10_007 + int(seed))
    lo, hi = cloud.points.min(axis=0), cloud.points.max(axis=0)
    lo, hi = lo - margin * (hi - lo), hi + margin * (hi - lo)
    extra = rng.uniform(lo, hi, size=(n, 3))
    normals = labels = None
    if cloud.normals is not None:
        nrm = rng.normal(size=(n, 3))
        normals = np.vstack([cloud.normals, nrm / np.linalg.norm(nrm, axis=1, keepdims=True)])
    if cloud.labels is not None:
        labels = np.concatenate([cloud.labels, cloud.labels[cKDTree(cloud.points).query(extra)[1]]])
    write_point_cloud(path, PointCloud(np.vstack([cloud.points, extra]), normals, labels,
                                       label_names=cloud.label_names))
    return n


def ensure_case_files(case: Case) -> None:
    """Write a phantom case built with write=False if its input is not on disk yet."""
    if case.phantom and not Path(case.input_path).exists():
        write_case(case)


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
        from ..errors import RibPullInputError

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


# ---------------------------------------------------------------------------------- plans


def sweep_cases(workdir: Path, seed: int, write: bool = True) -> list[Case]:
    """The accuracy sweep's cases for one seed, in report order: ACCURACY_POINT_COUNTS x
    ACCURACY_NOISES_MM, the ACCURACY_OUTLIER_CASES with outliers, the partial-volume label maps at
    ACCURACY_LABEL_SPACINGS_MM, then the sternum phantom's point cloud and label map."""
    def case(n=MASK_CASE_POINTS, noise=0.0, group=GROUP_ACC_POINTS, **kw) -> Case:
        return phantom_case(workdir, seed, n, noise, group=group, write=write, **kw)

    out = [case(n, noise) for noise in ACCURACY_NOISES_MM for n in ACCURACY_POINT_COUNTS]
    out += [case(n, noise, outlier_fraction=ACCURACY_OUTLIER_FRACTION) for n, noise in ACCURACY_OUTLIER_CASES]
    out += [case(mask=True, spacing_mm=s, partial_volume=True, group=GROUP_ACC_MASKS) for s in ACCURACY_LABEL_SPACINGS_MM]
    out += [case(*STERNUM_POINT_CASE, group=GROUP_ACC_STERNUM, sternum=True),
            case(mask=True, spacing_mm=STERNUM_SPACING_MM, partial_volume=True, group=GROUP_ACC_STERNUM, sternum=True)]
    return out


def build_plan(mode: str, workdir: Path, seeds: tuple[int, ...], n_points: int | None = None,
               cases_dir: Path | None = None, label_map: Path | None = REAL_LABEL_MAP,
               method_filter: list[str] | None = None, notes: list[str] | None = None,
               write: bool = True) -> tuple[list, list[Case]]:
    """(plan, cases): plan is the ordered list of (MethodSpec, Case) to run; mode is one of PLANS.

    quick: one phantom point cloud (first seed, n_points or QUICK_POINTS, QUICK_NOISE_MM) with every
    point method, the mask with marching cubes, the real label map with SparseOcc default and
    marching cubes. docs: per seed the main phantom case (MAIN_POINT_CASE) with the cheap methods,
    plus the expensive ones on the first DOCS_EXPENSIVE_SEEDS seeds; for the first seed the
    SWEEP_POINT_CASES and the mask with the cheap methods; the real label map. full: per seed the main
    case, the sweeps and the mask with every applicable method; the real label map per seed. sweep:
    per seed the sweep_cases with sweep_methods (no real label map). User cases (--cases) get
    SparseOcc default and the classical methods (full: every method). Skips go to notes. write=False
    builds the phantom cases without writing them (run_plan writes them when they run)."""
    if mode not in PLANS:
        raise ValueError(f"unknown plan {mode!r}; choose one of {PLANS}")
    notes = notes if notes is not None else []
    workdir = Path(workdir)
    expensive: list[MethodSpec] = []
    if mode == "docs":
        cheap, expensive = docs_methods()
    else:
        cheap = {"quick": quick_methods, "full": full_methods, "sweep": sweep_methods}[mode]()
    if method_filter:
        def wanted(m: MethodSpec) -> bool:
            return any(m.label.startswith(f) or m.kind == f for f in method_filter)

        cheap, expensive = [m for m in cheap if wanted(m)], [m for m in expensive if wanted(m)]
    methods = cheap + expensive
    light = [m for m in methods if m.label == SPARSEOCC_DEFAULT.label or m.kind != "pipeline"]
    cases: list[Case] = []
    plan: list[tuple[MethodSpec, Case]] = []

    def add(case: Case, specs: list[MethodSpec]) -> None:
        cases.append(case)
        plan.extend((m, case) for m in specs if applicable(m, case))

    def phantom(seed: int, n: int, noise: float, **kw) -> Case:
        return phantom_case(workdir, seed, n, noise, write=write, **kw)

    main_n, main_noise = MAIN_POINT_CASE
    if mode == "quick":
        add(phantom(seeds[0], n_points or QUICK_POINTS, QUICK_NOISE_MM), methods)
        add(phantom(seeds[0], MASK_CASE_POINTS, 0.0, mask=True), [m for m in methods if m.kind == "mask_mc"])
    elif mode == "sweep":
        for seed in seeds:
            for c in sweep_cases(workdir, seed, write):
                add(c, methods)
        label_map = None  # the sweep is synthetic only
    else:
        for i, seed in enumerate(seeds):
            main_specs = methods if mode == "full" or i < DOCS_EXPENSIVE_SEEDS else cheap
            add(phantom(seed, n_points or main_n, main_noise), main_specs)
            if mode == "full" or i == 0:
                for n, noise in SWEEP_POINT_CASES:
                    add(phantom(seed, n, noise, group=GROUP_SWEEP), cheap if mode == "docs" else methods)
                add(phantom(seed, MASK_CASE_POINTS, 0.0, mask=True), cheap if mode == "docs" else methods)
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
    from ..methods import build_fit_config

    return int(build_fit_config(preset, method).method_config.iterations)

