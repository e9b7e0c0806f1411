"""The mean-curvature flows' Laplacian (`curvature_bias.flow_step`): the numpy cotangent Laplacian
(`curvature_bias.cotangent_laplacian`, the default) against robust_laplacian's intrinsic-Delaunay
one, beside each case's bench baseline, scored like `ribpull bench` against the phantom's TRUE
surface (CD-L1 / HD in mm, `--samples` per side; mesh components; separable ribs that are their own
component). The flows run on label maps (`restore_smoothing_bias`) and too-noisy point clouds
(`remove_noise_bias`); the seconds column is the whole `default` run (no skeleton, no preview).

    .venv/bin/python benchmarks/laplacian_ab.py
    .venv/bin/python benchmarks/laplacian_ab.py --cases mask:1.5 20000:1.0 --samples 300000
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import abkit
import robust_laplacian

from ribpull_core import curvature_bias

DEFAULT_CASES = ("mask:1.5", "mask:aniso", "sternum:mask:1.5", "20000:1.0", "60000:1.0")


def main() -> None:
    args = abkit.case_arguments(__doc__, DEFAULT_CASES).parse_args()
    laplacians = (("cotangent (default)", curvature_bias.cotangent_laplacian),
                  ("robust_laplacian", robust_laplacian.mesh_laplacian))
    print(abkit.TABLE_HEADER)
    with tempfile.TemporaryDirectory() as tmp:
        for spec in args.cases:
            case = abkit.bench_case(spec, Path(tmp))
            runs = [abkit.baseline_for(case)]
            for i, (name, laplacian) in enumerate(laplacians):
                curvature_bias.mesh_laplacian = laplacian
                try:
                    mesh, seconds = abkit.fit_default(Path(case.input_path), Path(tmp) / f"{case.name}-{i}", labels=case.labels)
                finally:
                    curvature_bias.mesh_laplacian = curvature_bias.cotangent_laplacian
                runs.append((name, mesh, seconds))
            abkit.print_runs(spec, case, runs, args.samples)


if __name__ == "__main__":
    main()
