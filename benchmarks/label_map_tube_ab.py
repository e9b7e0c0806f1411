"""Label maps: the tube-aligned patches after the isotropic ones (RefineConfig.label_map_tube,
`ribpull_core.tube_patches`) on, off and without their limits, beside marching cubes + 20 Taubin
iterations, scored like `ribpull bench` against the phantom's TRUE surface (CD-L1 / HD in mm,
`--samples` per side; mesh components; separable ribs that are their own component).

    .venv/bin/python benchmarks/label_map_tube_ab.py
    .venv/bin/python benchmarks/label_map_tube_ab.py --cases mask:1.5 --samples 300000

Rows: the baseline; the `default` preset (no skeleton, no preview; 8 x 2 mm patches, moves up to
0.5 mm, only where the surface is a tube's); off (as before 2026-12-05); the same patches on every
vertex (no axis-spread limit); 14 x 2.5 mm patches.
"""

from __future__ import annotations

import dataclasses

import abkit

from ribpull_core.config import RefineConfig, TubePatchConfig

DEFAULT_CASES = ("mask:1.5", "mask:aniso", "sternum:mask:1.5")


def main() -> None:
    args = abkit.case_arguments(__doc__, DEFAULT_CASES).parse_args()
    tube = RefineConfig().label_map_tube
    abkit.compare_variants(args, [
        ("default (8 x 2 mm)", None),
        ("off", abkit.RefineChange({"label_map_tube": TubePatchConfig(along_mm=0.0)})),
        ("every vertex", abkit.RefineChange({"label_map_tube": dataclasses.replace(tube, max_axis_spread=None)})),
        ("14 x 2.5 mm", abkit.RefineChange({"label_map_tube": dataclasses.replace(tube, along_mm=14.0, across_mm=2.5)})),
    ])


if __name__ == "__main__":
    main()
