"""A/B of SparseOcc's eq. 1 pull targets in one run: nearest input point vs local quadric patch,
beside the bench's baseline (screened Poisson on flood-fill normals), on the bench's phantom cases
scored like `ribpull bench` against the TRUE surface (CD-L1 / HD in mm, `--samples` per side; mesh
components).

    .venv/bin/python benchmarks/pull_targets_ab.py                       # 5k, 20k, 60k x 0.3 mm; 60k x 0 / 1 mm
    .venv/bin/python benchmarks/pull_targets_ab.py --cases 60000:0.3 --samples 300000

Both fits are the `default` preset (no skeleton, no preview) through run_pipeline; only
queries.targets differs. Times are the whole run_pipeline call and the baseline's call (s).
"""

from __future__ import annotations

import abkit

DEFAULT_CASES = ("5000:0.3", "20000:0.3", "60000:0.0", "60000:0.3", "60000:1.0")


def main() -> None:
    args = abkit.case_arguments(__doc__, DEFAULT_CASES).parse_args()
    abkit.compare_variants(args, [(f"targets={t}", abkit.config_change("queries", targets=t)) for t in ("nearest", "quadric")])


if __name__ == "__main__":
    main()
