"""A/B of SparseOcc's eq. 1 pull targets in one run: nearest input point vs local quadric patch,
beside screened Poisson on flood-fill normals, on phantom point clouds scored against the TRUE
surface (CD-L1 / HD in mm, >= 1M samples per side; mesh components).

    .venv/bin/python benchmarks/pull_targets_ab.py                       # 5k, 20k, 60k x 0.3 mm; 60k x 0 / 1 mm
    .venv/bin/python benchmarks/pull_targets_ab.py --cases 60000:0.3 --samples 300000

Both fits are the `default` preset (no skeleton, no preview) through run_pipeline; only
queries.targets differs. Times are the whole run_pipeline call and the Poisson call (s).
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from pathlib import Path

DEFAULT_CASES = ("5000:0.3", "20000:0.3", "60000:0.0", "60000:0.3", "60000:1.0")


def fit_with_targets(points_path: Path, outdir: Path, targets: str):
    """run_pipeline on `points_path` with the default preset's queries.targets set to `targets`;
    returns (mesh in mm, seconds)."""
    import trimesh

    import ribpull_core.methods.sparseocc as so
    from ribpull_core.pipeline import PipelineOptions, run_pipeline

    original = so.SparseOcc.presets["default"]

    def preset():
        c = original()
        return dataclasses.replace(c, queries=dataclasses.replace(c.queries, targets=targets))

    so.SparseOcc.presets["default"] = preset
    try:
        t = time.perf_counter()
        run_pipeline(points_path, outdir, PipelineOptions(preset="default", skeleton=False, preview=False))
        return trimesh.load(outdir / "mesh.ply", force="mesh"), time.perf_counter() - t
    finally:
        so.SparseOcc.presets["default"] = original


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", nargs="+", default=list(DEFAULT_CASES), help="POINTS:NOISE_MM pairs")
    ap.add_argument("--samples", type=int, default=1_000_000, help="samples per side against the truth")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    from ribpull_core.bench.baselines import flood_fill_normals, poisson_mesh
    from ribpull_core.io import write_point_cloud
    from ribpull_core.mesh import count_components
    from ribpull_core.metrics import surface_metrics
    from ribpull_core.phantom import PhantomConfig, make_phantom, sample_surface

    phantom = make_phantom(PhantomConfig(seed=args.seed))
    print("| points | noise mm | nearest CD-L1 / HD / parts / s | quadric CD-L1 / HD / parts / s "
          "| Poisson CD-L1 / HD / parts / s | quadric / Poisson |")
    print("|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for spec in args.cases:
            n, noise = int(spec.split(":")[0]), float(spec.split(":")[1])
            cloud = sample_surface(phantom, n, noise, seed=args.seed + 1)
            path = write_point_cloud(Path(tmp) / f"points_{n}_{noise}.ply", cloud)
            cells, cd = [], {}
            for name in ("nearest", "quadric", "poisson"):
                if name == "poisson":
                    t = time.perf_counter()
                    mesh = poisson_mesh(cloud.points, flood_fill_normals(cloud.points))
                    seconds = time.perf_counter() - t
                else:
                    mesh, seconds = fit_with_targets(path, Path(tmp) / f"out_{n}_{noise}_{name}", name)
                s = surface_metrics(mesh, phantom.mesh, n_samples=args.samples, tau_mm=1.0, seed=0)
                cd[name] = s["cd_l1_mm"]
                cells.append(f"{s['cd_l1_mm']:.3f} / {s['hausdorff_mm']:.2f} / {count_components(mesh)} / {seconds:.0f}")
            print(f"| {n} | {noise:g} | " + " | ".join(cells) + f" | {cd['quadric'] / cd['poisson']:.2f} |", flush=True)


if __name__ == "__main__":
    main()
