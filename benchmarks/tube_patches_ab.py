"""Too-noisy point clouds: the tube-aligned patches after the noise flow (RefineConfig.tube,
`ribpull_core.tube_patches`) on and off, beside screened Poisson on flood-fill normals, scored like
`ribpull bench` against the phantom's TRUE surface (CD-L1 / HD in mm, `--samples` per side; mesh
components; separable ribs that are their own component).

    .venv/bin/python benchmarks/tube_patches_ab.py
    .venv/bin/python benchmarks/tube_patches_ab.py --cases 20000:1.0 --samples 300000

Rows: the baseline; the `default` preset (no skeleton, no preview; 14 x 2.5 mm patches); 10 x 2.5
mm patches; off (the noise flow alone, as before 2026-12-05).
"""

from __future__ import annotations

import abkit

from ribpull_core.config import TubePatchConfig

DEFAULT_CASES = ("20000:1.0", "60000:1.0")


def main() -> None:
    args = abkit.case_arguments(__doc__, DEFAULT_CASES).parse_args()
    abkit.compare_variants(args, [("default (14 x 2.5 mm)", None),
                                  ("10 x 2.5 mm", abkit.RefineChange({"tube": TubePatchConfig(along_mm=10.0)})),
                                  ("off (the flow alone)", abkit.RefineChange({"tube": TubePatchConfig(along_mm=0.0)}))])


if __name__ == "__main__":
    main()
