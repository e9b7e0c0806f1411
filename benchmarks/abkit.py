"""Shared pieces of the A/B scripts in benchmarks/: a run of the `default` preset with one change
to its SparseOcc config, and the phantom case each script scores against its TRUE surface."""

from __future__ import annotations

import contextlib
import dataclasses
import time
from pathlib import Path


def config_change(part: str, **values):
    """A SparseOccConfig change for `fit_default`: config.<part> (e.g. "queries") with `values` replaced."""
    return lambda c: dataclasses.replace(c, **{part: dataclasses.replace(getattr(c, part), **values)})


@dataclasses.dataclass(frozen=True)
class RefineChange:
    """A change for `fit_default` to the `default` run preset's RefineConfig (its fields replaced
    by `values`), e.g. RefineChange({"dense_fit_iterations": 800})."""

    values: dict


@dataclasses.dataclass(frozen=True)
class LabelMapChange:
    """A change for `fit_default` to the `default` run preset's LabelMapConfig (its fields replaced
    by `values`), e.g. LabelMapChange({"boundary_sigma_mm": 0.6})."""

    values: dict


@dataclasses.dataclass(frozen=True)
class Changes:
    """Several changes for `fit_default` at once (each a RefineChange, LabelMapChange or SparseOcc
    config function)."""

    parts: tuple


@contextlib.contextmanager
def default_preset_changed(change):
    """Within the block, the `default` preset is changed: a RefineChange replaces fields of its
    RefineConfig, a LabelMapChange of its LabelMapConfig, Changes applies several; any other
    change is a SparseOccConfig -> SparseOccConfig function applied to SparseOcc's `default`
    config; None leaves it as it is."""
    import ribpull_core.methods.sparseocc as so
    from ribpull_core import methods

    original, run = so.SparseOcc.presets["default"], methods.RUN_PRESETS["default"]
    for part in (change.parts if isinstance(change, Changes) else (change,)):
        preset = methods.RUN_PRESETS["default"]
        if isinstance(part, RefineChange):
            methods.RUN_PRESETS["default"] = dataclasses.replace(preset, refine=dataclasses.replace(preset.refine, **part.values))
        elif isinstance(part, LabelMapChange):
            methods.RUN_PRESETS["default"] = dataclasses.replace(preset, label_map=dataclasses.replace(preset.label_map, **part.values))
        elif part is not None:
            method_preset = so.SparseOcc.presets["default"]
            so.SparseOcc.presets["default"] = lambda p=part, m=method_preset: p(m())
    try:
        yield
    finally:
        so.SparseOcc.presets["default"], methods.RUN_PRESETS["default"] = original, run


def fit_default(points_path: Path, outdir: Path, change=None, labels=None):
    """run_pipeline (default preset, no skeleton or preview) on `points_path` with `change` applied
    (`default_preset_changed`) (labels: a label map's values to keep, None: its ribs); returns (mesh in
    mm, seconds of the whole call)."""
    import trimesh

    from ribpull_core.pipeline import PipelineOptions, run_pipeline

    with default_preset_changed(change):
        t = time.perf_counter()
        run_pipeline(points_path, outdir, PipelineOptions(preset="default", skeleton=False, preview=False,
                                                          labels=list(labels) if labels else None))
        return trimesh.load(outdir / "mesh.ply", force="mesh"), time.perf_counter() - t


def case_arguments(doc: str, default_cases: tuple[str, ...]):
    """The A/B scripts' command line: --cases (bench_case specs, e.g. POINTS:NOISE_MM), --samples."""
    import argparse

    ap = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", nargs="+", default=list(default_cases), help="see abkit.bench_case")
    ap.add_argument("--samples", type=int, default=1_000_000, help="samples per side against the truth")
    return ap


def bench_case(spec: str, workdir: Path, seed: int = 0):
    """A `ribpull bench` phantom case (bench.plan.Case, files written under workdir) from a spec:
    "POINTS:NOISE_MM", "POINTS:NOISE_MM:OUTLIER_FRACTION", "sternum:POINTS:NOISE_MM", "mask:1.5" (partial-volume label map, 1.5 mm
    voxels), "mask:aniso" (0.75 x 0.75 x 2.5 mm) or "sternum:mask:1.5"."""
    from ribpull_core.bench.plan import phantom_case

    sternum = spec.startswith("sternum:")
    parts = spec.split(":")[1:] if sternum else spec.split(":")
    if parts[0] == "mask":
        spacing = (0.75, 0.75, 2.5) if parts[1] == "aniso" else float(parts[1])
        return phantom_case(workdir, seed, 0, 0.0, mask=True, spacing_mm=spacing, partial_volume=True, sternum=sternum)
    outliers = float(parts[2]) if len(parts) > 2 else 0.0
    return phantom_case(workdir, seed, int(parts[0]), float(parts[1]), sternum=sternum, outlier_fraction=outliers)


def baseline_for(case):
    """(name, mesh mm, seconds) of a case's bench baseline, built as `ribpull bench` builds it
    (bench.tasks.classical_mesh): marching cubes + 20 Taubin iterations for label maps, screened
    Poisson on flood-fill normals with the pipeline's clean-up for point clouds."""
    from ribpull_core.bench.plan import baseline_kind
    from ribpull_core.bench.tasks import classical_mesh
    from ribpull_core.io import load_point_cloud

    cloud = load_point_cloud(Path(case.input_path), labels=list(case.labels) if case.labels else None)
    t = time.perf_counter()
    mesh, _ = classical_mesh(cloud, baseline_kind(case.input_kind))
    name = {"poisson": "screened Poisson", "mc_taubin": "marching cubes + 20 Taubin"}[baseline_kind(case.input_kind)]
    return name, mesh, time.perf_counter() - t


def score_case(case, mesh, samples: int) -> dict:
    """The bench's scores of a mesh (mm) on a phantom case: cd_l1_mm, hausdorff_mm,
    mesh_components, n_isolated / n_separable (ribs that are their own component)."""
    from ribpull_core.bench.score import score_separation, score_surface

    row = dataclasses.asdict(case)
    return {**score_surface(row, mesh, 1.0, samples, 0), **score_separation(row, mesh)}


def score_cell(score: dict) -> str:
    """A score_case result as a table cell: "CD-L1 / HD / parts" (mm, mm, mesh components)."""
    return f"{score['cd_l1_mm']:.4f} / {score['hausdorff_mm']:.2f} / {score['mesh_components']}"


TABLE_HEADER = ("| case | run | CD-L1 / HD / parts | isolated / separable | s | CD-L1 / baseline |\n"
                "|---|---|---|---|---:|---:|")


def print_runs(spec: str, case, runs, samples: int) -> None:
    """Score each (name, mesh mm, seconds) of `runs` on `case` (score_case, `samples` per side) and
    print it as a row under TABLE_HEADER; runs[0] is the baseline the last column divides by."""
    scores = [score_case(case, mesh, samples) for _, mesh, _ in runs]
    base = scores[0]["cd_l1_mm"]
    for (name, _, seconds), s in zip(runs, scores):
        sep = f"{s['n_isolated']} / {s['n_separable']}" if "n_isolated" in s else ""
        print(f"| {spec} | {name} | {score_cell(s)} | {sep} | {seconds:.0f} | {s['cd_l1_mm'] / base:.3f} |", flush=True)


def compare_variants(args, variants, extra=None, prepare=None) -> None:
    """The A/B scripts' loop: for each case of args.cases (`bench_case` specs; at each phantom seed
    of args.seeds when the script has that option, else 0) print the bench baseline and one
    `default` run per (name, change) of `variants` (change: a `config_change`, a RefineChange, or
    None for the preset as it is), scored on args.samples per side. prepare(case) may change the
    case's input file first (e.g. roughen a label map); extra(runs) may append derived (name, mesh
    mm, seconds) runs (e.g. a post-processed copy) before the rows are printed."""
    import tempfile

    print(TABLE_HEADER)
    with tempfile.TemporaryDirectory() as tmp:
        for spec in args.cases:
            for seed in getattr(args, "seeds", None) or (0,):
                case = bench_case(spec, Path(tmp), seed)
                if prepare is not None:
                    prepare(case)
                runs = [baseline_for(case)]
                for i, (name, change) in enumerate(variants):
                    mesh, seconds = fit_default(Path(case.input_path), Path(tmp) / f"{case.name}-{i}", change, labels=case.labels)
                    runs.append((name, mesh, seconds))
                if extra is not None:
                    extra(runs)
                print_runs(f"{spec} seed {seed}" if seed else spec, case, runs, args.samples)
