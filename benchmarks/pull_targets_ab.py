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
from pathlib import Path

from abkit import fit_default, poisson_baseline, score_cell

DEFAULT_CASES = ("5000:0.3", "20000:0.3", "60000:0.0", "60000:0.3", "60000:1.0")


def with_targets(targets: str):
    """A SparseOccConfig change: queries.targets = targets."""
    return lambda c: dataclasses.replace(c, queries=dataclasses.replace(c.queries, targets=targets))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", nargs="+", default=list(DEFAULT_CASES), help="POINTS:NOISE_MM pairs")
    ap.add_argument("--samples", type=int, default=1_000_000, help="samples per side against the truth")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    from ribpull_core.io import write_point_cloud
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
                    mesh, seconds = poisson_baseline(cloud.points)
                else:
                    mesh, seconds = fit_default(path, Path(tmp) / f"out_{n}_{noise}_{name}", with_targets(name))
                cd[name], cell = score_cell(mesh, phantom.mesh, args.samples)
                cells.append(f"{cell} / {seconds:.0f}")
            print(f"| {n} | {noise:g} | " + " | ".join(cells) + f" | {cd['quadric'] / cd['poisson']:.2f} |", flush=True)


if __name__ == "__main__":
    main()
