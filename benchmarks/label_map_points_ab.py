"""Label maps with fewer sign points a training step (free space, near-surface hinges, known
occupancy), each alone and all three, beside the bench baseline of each case (marching cubes + 20
Taubin), scored like `ribpull bench` against the phantom's TRUE surface (CD-L1 / HD in mm,
`--samples` per side; mesh components; separable ribs that are their own component).

    .venv/bin/python benchmarks/label_map_points_ab.py
    .venv/bin/python benchmarks/label_map_points_ab.py --cases sternum:mask:1.5 --samples 300000

Rows: the baseline; the `default` preset (no skeleton, no preview; 2048 free-space points, 4096
hinges, 4096 known-occupancy points a step); then each of those cut (to 512, 2048, 2048); then all
three. Measured 2026-12-04 (docs/benchmarks.md): up to 4 s saved, CD-L1 the same, HD worse.
"""

from __future__ import annotations

import abkit

DEFAULT_CASES = ("mask:1.5", "sternum:mask:1.5", "mask:aniso")


def main() -> None:
    args = abkit.case_arguments(__doc__, DEFAULT_CASES).parse_args()
    fewer = {"free_space_points": 512, "near_surface_points": 2048, "known_points": 2048}
    abkit.compare_variants(args, [("default", None)]
                           + [(f"{k} {v}", abkit.config_change("sign", **{k: v})) for k, v in fewer.items()]
                           + [("all three", abkit.config_change("sign", **fewer))])


if __name__ == "__main__":
    main()
