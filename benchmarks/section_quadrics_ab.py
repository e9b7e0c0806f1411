"""Input the round patches do not refine (too noisy or too sparse): the section quadrics
(RefineConfig.section, `ribpull_core.section_quadrics`) on, off, and with two passes, beside screened
Poisson on flood-fill normals, scored like `ribpull bench` against the phantom's TRUE surface
(CD-L1 / HD in mm, `--samples` per side; mesh components; separable ribs that are their own component).

    .venv/bin/python benchmarks/section_quadrics_ab.py
    .venv/bin/python benchmarks/section_quadrics_ab.py --cases 10000:1.0 --samples 300000
"""

from __future__ import annotations

import abkit

from ribpull_core.config import SectionQuadricConfig

DEFAULT_CASES = ("10000:1.0", "20000:1.0", "5000:0.0", "5000:0.3", "5000:1.0", "10000:0.0", "10000:0.3", "60000:1.0")


def main() -> None:
    args = abkit.case_arguments(__doc__, DEFAULT_CASES).parse_args()
    abkit.compare_variants(args, [("default (one pass)", None),
                                  ("two passes", abkit.RefineChange({"section": SectionQuadricConfig(passes=2)})),
                                  ("off", abkit.RefineChange({"section": SectionQuadricConfig(along_mm=0.0)}))])


if __name__ == "__main__":
    main()
