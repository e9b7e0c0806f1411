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


@contextlib.contextmanager
def default_preset_changed(change):
    """Within the block, SparseOcc's `default` preset is change(default_config()) (change: a
    SparseOccConfig -> SparseOccConfig function; None leaves it as it is)."""
    import ribpull_core.methods.sparseocc as so

    original = so.SparseOcc.presets["default"]
    if change is not None:
        so.SparseOcc.presets["default"] = lambda: change(original())
    try:
        yield
    finally:
        so.SparseOcc.presets["default"] = original


def fit_default(points_path: Path, outdir: Path, change=None, labels=None):
    """run_pipeline (default preset, no skeleton or preview) on `points_path` with `change` applied
    to its SparseOcc config (labels: a label map's values to keep, None: its ribs); returns (mesh in
    mm, seconds of the whole call)."""
    import trimesh

    from ribpull_core.pipeline import PipelineOptions, run_pipeline

    with default_preset_changed(change):
        t = time.perf_counter()
        run_pipeline(points_path, outdir, PipelineOptions(preset="default", skeleton=False, preview=False,
                                                          labels=list(labels) if labels else None))
        return trimesh.load(outdir / "mesh.ply", force="mesh"), time.perf_counter() - t


def poisson_baseline(points_mm):
    """Screened Poisson on flood-fill-oriented normals (the bench's baseline); (mesh mm, seconds)."""
    from ribpull_core.bench.baselines import flood_fill_normals, poisson_mesh

    t = time.perf_counter()
    mesh = poisson_mesh(points_mm, flood_fill_normals(points_mm))
    return mesh, time.perf_counter() - t


def score_cell(mesh, truth_mesh, samples: int) -> tuple[float, str]:
    """(CD-L1 mm, "CD-L1 / HD / parts" cell) of a mesh against the true surface, `samples` per side."""
    from ribpull_core.mesh import count_components
    from ribpull_core.metrics import surface_metrics

    s = surface_metrics(mesh, truth_mesh, n_samples=samples, tau_mm=1.0, seed=0)
    return s["cd_l1_mm"], f"{s['cd_l1_mm']:.3f} / {s['hausdorff_mm']:.2f} / {count_components(mesh)}"


def case_arguments(doc: str, default_cases: tuple[str, ...]):
    """The A/B scripts' command line: --cases POINTS:NOISE_MM ..., --samples, --seed."""
    import argparse

    ap = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", nargs="+", default=list(default_cases), help="POINTS:NOISE_MM pairs")
    ap.add_argument("--samples", type=int, default=1_000_000, help="samples per side against the truth")
    ap.add_argument("--seed", type=int, default=0)
    return ap.parse_args()


def phantom_cases(args, workdir: Path):
    """(phantom, cases): the phantom of args.seed (its `.mesh` is the true surface, mm) and an
    iterator of (n_points, noise_mm, cloud, points_path) for each of args.cases, the phantom sampled
    with that many points and that much Gaussian noise (mm), written under workdir."""
    from ribpull_core.io import write_point_cloud
    from ribpull_core.phantom import PhantomConfig, make_phantom, sample_surface

    phantom = make_phantom(PhantomConfig(seed=args.seed))

    def cases():
        for spec in args.cases:
            n, noise = int(spec.split(":")[0]), float(spec.split(":")[1])
            cloud = sample_surface(phantom, n, noise, seed=args.seed + 1)
            yield n, noise, cloud, write_point_cloud(Path(workdir) / f"points_{n}_{noise}.ply", cloud)

    return phantom, cases()


def bench_case(spec: str, workdir: Path, seed: int = 0):
    """A `ribpull bench` phantom case (bench.plan.Case, files written under workdir) from a spec:
    "POINTS:NOISE_MM", "sternum:POINTS:NOISE_MM", "mask:1.5" (partial-volume label map, 1.5 mm
    voxels), "mask:aniso" (0.75 x 0.75 x 2.5 mm) or "sternum:mask:1.5"."""
    from ribpull_core.bench.plan import phantom_case

    sternum = spec.startswith("sternum:")
    parts = spec.split(":")[1:] if sternum else spec.split(":")
    if parts[0] == "mask":
        spacing = (0.75, 0.75, 2.5) if parts[1] == "aniso" else float(parts[1])
        return phantom_case(workdir, seed, 0, 0.0, mask=True, spacing_mm=spacing, partial_volume=True, sternum=sternum)
    return phantom_case(workdir, seed, int(parts[0]), float(parts[1]), sternum=sternum)


def baseline_for(case):
    """(name, mesh mm, seconds) of a case's bench baseline: marching cubes + 20 Taubin iterations
    for label maps, screened Poisson on flood-fill normals for point clouds."""
    from ribpull_core.bench.baselines import mask_marching_cubes
    from ribpull_core.io import load_point_cloud

    cloud = load_point_cloud(Path(case.input_path), labels=list(case.labels) if case.labels else None)
    if case.input_kind == "mask":
        t = time.perf_counter()
        mesh = mask_marching_cubes(cloud, taubin_iterations=20)
        return "marching cubes + 20 Taubin", mesh, time.perf_counter() - t
    return ("screened Poisson", *poisson_baseline(cloud.points))


def score_case(case, mesh, samples: int) -> dict:
    """The bench's scores of a mesh (mm) on a phantom case: cd_l1_mm, hausdorff_mm,
    mesh_components, n_isolated / n_separable (ribs that are their own component)."""
    import dataclasses

    from ribpull_core.bench.score import score_separation, score_surface

    row = dataclasses.asdict(case)
    return {**score_surface(row, mesh, 1.0, samples, 0), **score_separation(row, mesh)}
