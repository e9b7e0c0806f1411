"""The smoothing bias of a label map's boundary points, and what the default does about it: the
variants in one run, beside marching cubes + 20 Taubin iterations (the bench's label-map
baseline), on the bench's partial-volume phantom label maps scored like `ribpull bench` against the
TRUE surface (CD-L1 / HD in mm, `--samples` per side; mesh components; ribs isolated).

    .venv/bin/python benchmarks/label_map_bias_ab.py              # 1.5 mm, 0.75 x 0.75 x 2.5 mm, sternum 1.5 mm
    .venv/bin/python benchmarks/label_map_bias_ab.py --cases mask:1.5 --samples 300000

Rows: the baseline; the `default` preset (no skeleton, no preview) through run_pipeline; the
default without the smoothing-bias restore (RefineConfig.smoothing_bias_factor = 0); the boundary
points blurred by 0.6 mm instead of the default's 0.9, with and without the restore (0.6 without
it is the default before the restore came in); blurred by 1.2 mm.
"""

from __future__ import annotations

import abkit

DEFAULT_CASES = ("mask:1.5", "mask:aniso", "sternum:mask:1.5")

NO_RESTORE = abkit.RefineChange({"smoothing_bias_factor": 0.0})

VARIANTS = {
    "without the smoothing-bias restore": NO_RESTORE,
    "blur 0.6 mm": abkit.LabelMapChange({"boundary_sigma_mm": 0.6}),
    "blur 0.6 mm, without the restore (the default before it)": abkit.Changes(
        (abkit.LabelMapChange({"boundary_sigma_mm": 0.6}), NO_RESTORE)),
    "blur 1.2 mm": abkit.LabelMapChange({"boundary_sigma_mm": 1.2}),
}


def main() -> None:
    args = abkit.case_arguments(__doc__, DEFAULT_CASES).parse_args()
    abkit.compare_variants(args, [("default", None), *VARIANTS.items()])


if __name__ == "__main__":
    main()
