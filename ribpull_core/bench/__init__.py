"""`ribpull bench`: methods x cases benchmark -> results.csv, results.md (the paper's table format),
skeleton.csv, speed.csv, sweep.csv and PNG plots.

    ribpull bench --quick -o bench_out/          # <= 15 min on a 2-core CPU; prints the tables
    ribpull bench --plan sweep -o bench_sweep    # the accuracy sweep (~35-40 min on 2 cores)
    ribpull bench -o bench_full/                 # every method on every case (hours; run by hand)
    ribpull bench --cases my_inputs/ -o out/     # adds your files (and `ribpull phantom` folders)

Every (method, case) pair runs in a fresh child process (multiprocessing "spawn"), so its peak
resident memory (VmHWM, MB) is its own; a sampler thread in the child also records the largest
resident size seen during each stage. Neural methods go through `pipeline.run_pipeline`, the same
call as `ribpull fit`; the classical baselines (screened Poisson on the points, marching cubes on a
voxel mask, plain or Taubin-smoothed) get the same mesh clean-up, skeleton and scoring. Surfaces are
scored with `metrics.surface_metrics` (mm; paper units = the normalised [-1, 1] frame of the input,
CD-L1 and HD x100, CD-L2 x1e4) against the TRUE surface for phantom cases, else against the input
points: samples on one surface measured exactly to the other (`triangle_distance`); results.csv
also keeps the sample-to-sample figures (cd_l1_sampled_mm, hausdorff_sampled_mm) that this
project's tables reported before 2026-12-06. Skeletons are scored with `skeleton_metrics` against the phantom's true centerlines.

Modules: plan (methods, cases, plans), run (child processes, timers, memory), tasks (what a child
does per method kind), baselines (the classical methods), score (against the truth), report (CSV,
markdown), sweep (the accuracy sweep's report), plots, command (options, run_bench, main).
"""

from __future__ import annotations

from .baselines import (
    POISSON_DEPTH,
    TAUBIN_ITERATIONS,
    flood_fill_normals,
    mask_marching_cubes,
    poisson_mesh,
    volume_marching_cubes,
)
from .command import add_arguments, machine_meta, main, run_bench, sparseocc_row
from .common import (
    ACCURACY_GROUPS,
    COLUMNS,
    FSCORE_TAU_MM,
    GROUP_ACC_MASKS,
    GROUP_ACC_POINTS,
    GROUP_ACC_STERNUM,
    GROUP_MASK,
    GROUP_ORDER,
    GROUP_POINTS,
    GROUP_REAL,
    GROUP_SWEEP,
    GROUP_USER,
    GROUPS_BY_CASE,
    METRIC_SAMPLES,
    REAL_LABEL_MAP,
    STAGES,
)
from .plan import (
    ACCURACY_LABEL_SPACINGS_MM,
    ACCURACY_NOISES_MM,
    ACCURACY_OUTLIER_CASES,
    ACCURACY_OUTLIER_FRACTION,
    ACCURACY_POINT_COUNTS,
    DOCS_EXPENSIVE_SEEDS,
    DOCS_PAPER_ITERATIONS,
    FULL_SEEDS,
    MAIN_POINT_CASE,
    MASK_SPACING_MM,
    PLANS,
    QUICK_POINTS,
    STERNUM_POINT_CASE,
    STERNUM_SPACING_MM,
    SWEEP_POINT_CASES,
    SWEEP_SEEDS,
    Case,
    MethodSpec,
    add_outliers,
    build_plan,
    ensure_case_files,
    phantom_case,
    preset_schedule,
    skeleton_plan,
    speed_plan,
    sweep_cases,
    sweep_methods,
)
from .plots import montage, plot_accuracy_vs_time, plot_cdl1_vs_points, plot_metric_bars
from .report import (
    accuracy_table,
    decimals_for,
    fmt_mean,
    fmt_pm,
    mean_std,
    read_csv,
    rewrite_outputs,
    speed_rows,
    write_csv,
    write_markdown,
    write_outputs,
)
from .run import RssSampler, StageTimer, peak_rss_mb, run_plan, run_task
from .sweep import speed_ratio, sweep_section, sweep_summary, sweep_table

__all__ = [
    "ACCURACY_GROUPS",
    "ACCURACY_LABEL_SPACINGS_MM",
    "ACCURACY_NOISES_MM",
    "ACCURACY_OUTLIER_CASES",
    "ACCURACY_OUTLIER_FRACTION",
    "ACCURACY_POINT_COUNTS",
    "COLUMNS",
    "DOCS_EXPENSIVE_SEEDS",
    "DOCS_PAPER_ITERATIONS",
    "FSCORE_TAU_MM",
    "FULL_SEEDS",
    "GROUPS_BY_CASE",
    "GROUP_ACC_MASKS",
    "GROUP_ACC_POINTS",
    "GROUP_ACC_STERNUM",
    "GROUP_MASK",
    "GROUP_ORDER",
    "GROUP_POINTS",
    "GROUP_REAL",
    "GROUP_SWEEP",
    "GROUP_USER",
    "MAIN_POINT_CASE",
    "MASK_SPACING_MM",
    "METRIC_SAMPLES",
    "PLANS",
    "POISSON_DEPTH",
    "QUICK_POINTS",
    "REAL_LABEL_MAP",
    "STAGES",
    "STERNUM_POINT_CASE",
    "STERNUM_SPACING_MM",
    "SWEEP_POINT_CASES",
    "SWEEP_SEEDS",
    "TAUBIN_ITERATIONS",
    "Case",
    "MethodSpec",
    "RssSampler",
    "StageTimer",
    "accuracy_table",
    "add_arguments",
    "add_outliers",
    "build_plan",
    "decimals_for",
    "ensure_case_files",
    "flood_fill_normals",
    "fmt_mean",
    "fmt_pm",
    "machine_meta",
    "main",
    "mask_marching_cubes",
    "mean_std",
    "montage",
    "peak_rss_mb",
    "phantom_case",
    "plot_accuracy_vs_time",
    "plot_cdl1_vs_points",
    "plot_metric_bars",
    "poisson_mesh",
    "preset_schedule",
    "read_csv",
    "rewrite_outputs",
    "run_bench",
    "run_plan",
    "run_task",
    "skeleton_plan",
    "sparseocc_row",
    "speed_plan",
    "speed_ratio",
    "speed_rows",
    "sweep_cases",
    "sweep_methods",
    "sweep_section",
    "sweep_summary",
    "sweep_table",
    "volume_marching_cubes",
    "write_csv",
    "write_markdown",
    "write_outputs",
]
