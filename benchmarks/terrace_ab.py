"""Label maps: the refinement's terrace weighting (RefineConfig.terrace_weight, refine.terrace_weights)
on and off, beside the bench baseline of each case (marching cubes + 20 Taubin), scored like
`ribpull bench` against the phantom's TRUE surface (CD-L1 / HD in mm, `--samples` per side; mesh
components; separable ribs that are their own component).

    .venv/bin/python benchmarks/terrace_ab.py
    .venv/bin/python benchmarks/terrace_ab.py --cases mask:1.5 --samples 300000

Rows: the baseline; the `default` preset (no skeleton, no preview; terraces weighted 0.3); weight
0.5; weight 1 (off: every boundary point counts the same).
"""

from __future__ import annotations

import abkit

DEFAULT_CASES = ("mask:1.5", "mask:aniso", "sternum:mask:1.5")


def main() -> None:
    args = abkit.case_arguments(__doc__, DEFAULT_CASES).parse_args()
    abkit.compare_variants(args, [("default (terraces 0.3)", None),
                                  ("terraces 0.5", abkit.RefineChange({"terrace_weight": 0.5})),
                                  ("off (1.0)", abkit.RefineChange({"terrace_weight": 1.0}))])


if __name__ == "__main__":
    main()
