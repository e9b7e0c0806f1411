"""Why the default trails screened Poisson under 1 mm noise: changes to the default tried in one
run, beside screened Poisson on flood-fill normals, on phantom point clouds scored against the TRUE
surface (CD-L1 / HD in mm, `--samples` per side; mesh components). None of them is the default.

    .venv/bin/python benchmarks/noise_ab.py                      # 60k and 200k points x 1 mm noise
    .venv/bin/python benchmarks/noise_ab.py --cases 20000:1.0 --samples 300000

Rows: the `default` preset (no skeleton, no preview) through run_pipeline; the same with one
SparseOcc setting changed (the near-surface hinges twice as far off the points; the finest grid
cell two sampling gaps instead of one; eq. 1's quadric targets over 40 neighbours instead of 20);
the default's mesh after 3 Taubin passes (trimesh, lambda = nu = 0.5); Poisson. The refinement is
skipped on all of these inputs (the points lie ~0.8 mm RMS off their patches: "too noisy").
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
from pathlib import Path

from abkit import fit_default, poisson_baseline, score_cell

DEFAULT_CASES = ("60000:1.0", "200000:1.0")


def _change(part: str, **values):
    """A SparseOccConfig change: config.<part> with `values` replaced."""
    return lambda c: dataclasses.replace(c, **{part: dataclasses.replace(getattr(c, part), **values)})


VARIANTS = {
    "near-surface offset x2": _change("sign", near_surface_offset=1.0),
    "finest cell 2 gaps": _change("field", grid_finest_cell=2.0),
    "quadric targets k40": _change("queries", target_knn=40),
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", nargs="+", default=list(DEFAULT_CASES), help="POINTS:NOISE_MM pairs")
    ap.add_argument("--samples", type=int, default=1_000_000, help="samples per side against the truth")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    import trimesh

    from ribpull_core.io import write_point_cloud
    from ribpull_core.phantom import PhantomConfig, make_phantom, sample_surface

    phantom = make_phantom(PhantomConfig(seed=args.seed))
    print("| points | noise mm | run | CD-L1 / HD / parts | s | CD-L1 / Poisson |")
    print("|---|---|---|---|---:|---:|")
    with tempfile.TemporaryDirectory() as tmp:
        for spec in args.cases:
            n, noise = int(spec.split(":")[0]), float(spec.split(":")[1])
            cloud = sample_surface(phantom, n, noise, seed=args.seed + 1)
            path = write_point_cloud(Path(tmp) / f"points_{n}_{noise}.ply", cloud)
            runs = []
            mesh, seconds = poisson_baseline(cloud.points)
            runs.append(("screened Poisson", mesh, seconds))
            mesh, seconds = fit_default(path, Path(tmp) / f"out_{n}_default")
            runs.append(("default", mesh, seconds))
            smoothed = mesh.copy()
            trimesh.smoothing.filter_taubin(smoothed, iterations=3)
            runs.append(("default + 3 Taubin passes", smoothed, seconds))
            for i, (name, change) in enumerate(VARIANTS.items()):
                mesh, seconds = fit_default(path, Path(tmp) / f"out_{n}_{i}", change)
                runs.append((name, mesh, seconds))
            poisson_cd = None
            for name, mesh, seconds in runs:
                cd, cell = score_cell(mesh, phantom.mesh, args.samples)
                poisson_cd = poisson_cd or cd
                print(f"| {n} | {noise:g} | {name} | {cell} | {seconds:.0f} | {cd / poisson_cd:.2f} |", flush=True)


if __name__ == "__main__":
    main()
