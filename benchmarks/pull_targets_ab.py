"""A/B of SparseOcc's eq. 1 pull targets in one run: nearest input point vs local quadric patch,
beside screened Poisson on flood-fill normals, on phantom point clouds scored against the TRUE
surface (CD-L1 / HD in mm, >= 1M samples per side; mesh components).

    .venv/bin/python benchmarks/pull_targets_ab.py                       # 5k, 20k, 60k x 0.3 mm; 60k x 0 / 1 mm
    .venv/bin/python benchmarks/pull_targets_ab.py --cases 60000:0.3 --samples 300000

Both fits are the `default` preset (no skeleton, no preview) through run_pipeline; only
queries.targets differs. Times are the whole run_pipeline call and the Poisson call (s).
"""

from __future__ import annotations

import tempfile
from pathlib import Path

from abkit import case_arguments, config_change, fit_default, phantom_cases, poisson_baseline, score_cell

DEFAULT_CASES = ("5000:0.3", "20000:0.3", "60000:0.0", "60000:0.3", "60000:1.0")


def main() -> None:
    args = case_arguments(__doc__, DEFAULT_CASES)
    print("| points | noise mm | nearest CD-L1 / HD / parts / s | quadric CD-L1 / HD / parts / s "
          "| Poisson CD-L1 / HD / parts / s | quadric / Poisson |")
    print("|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        phantom, cases = phantom_cases(args, Path(tmp))
        for n, noise, cloud, path in cases:
            cells, cd = [], {}
            for name in ("nearest", "quadric", "poisson"):
                if name == "poisson":
                    mesh, seconds = poisson_baseline(cloud.points)
                else:
                    mesh, seconds = fit_default(path, Path(tmp) / f"out_{n}_{noise}_{name}", config_change("queries", targets=name))
                cd[name], cell = score_cell(mesh, phantom.mesh, args.samples)
                cells.append(f"{cell} / {seconds:.0f}")
            print(f"| {n} | {noise:g} | " + " | ".join(cells) + f" | {cd['quadric'] / cd['poisson']:.2f} |", flush=True)


if __name__ == "__main__":
    main()
