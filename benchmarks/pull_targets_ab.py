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

import tempfile
from pathlib import Path

import abkit

DEFAULT_CASES = ("5000:0.3", "20000:0.3", "60000:0.0", "60000:0.3", "60000:1.0")


def main() -> None:
    args = abkit.case_arguments(__doc__, DEFAULT_CASES).parse_args()
    print(abkit.TABLE_HEADER)
    with tempfile.TemporaryDirectory() as tmp:
        for spec in args.cases:
            case = abkit.bench_case(spec, Path(tmp))
            runs = [abkit.baseline_for(case)]
            for targets in ("nearest", "quadric"):
                mesh, seconds = abkit.fit_default(Path(case.input_path), Path(tmp) / f"{case.name}-{targets}",
                                            abkit.config_change("queries", targets=targets), labels=case.labels)
                runs.append((f"targets={targets}", mesh, seconds))
            abkit.print_runs(spec, case, runs, args.samples)


if __name__ == "__main__":
    main()
