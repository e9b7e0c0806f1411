"""The fit's length and mesh where the vertex refinement runs (RefineConfig.fit_iterations, 400;
for point clouds above dense_points, dense_fit_iterations 800 and dense_mesh_resolution 384),
beside the bench baseline of each case, scored like `ribpull bench` against the phantom's TRUE surface (CD-L1 / HD in mm,
`--samples` per side; mesh components; separable ribs that are their own component).

    .venv/bin/python benchmarks/refine_ab.py                                 # 200k / 0.3 mm, label maps
    .venv/bin/python benchmarks/refine_ab.py --cases 200000:0.0 200000:1.0

Rows: the baseline; the `default` preset (no skeleton, no preview); 250 iterations instead of 400
(what a shorter label-map fit would give); the former 600 iterations and 256-cell mesh above 100k
points (each alone).
"""

from __future__ import annotations

import abkit

DEFAULT_CASES = ("200000:0.3", "mask:1.5", "sternum:mask:1.5")


def main() -> None:
    args = abkit.case_arguments(__doc__, DEFAULT_CASES).parse_args()
    abkit.compare_variants(args, [("default", None),
                                  ("fit 250 iterations", abkit.RefineChange({"fit_iterations": 250})),
                                  ("dense fit 600 iterations", abkit.RefineChange({"dense_fit_iterations": 600})),
                                  ("dense mesh 256 cells", abkit.RefineChange({"dense_mesh_resolution": 256}))])


if __name__ == "__main__":
    main()
