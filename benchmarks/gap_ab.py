"""The gap hinge (SignConfig.gap_weight: free space between differently labelled structures) on and
off, beside the bench baseline of each case, scored like `ribpull bench` against the phantom's TRUE
surface (CD-L1 / HD in mm, `--samples` per side; mesh components; separable ribs that are their own
component).

    .venv/bin/python benchmarks/gap_ab.py --samples 300000
    .venv/bin/python benchmarks/gap_ab.py --cases sternum:60000:0.3 60000:0.3

Rows: the baseline; the `default` preset (no skeleton, no preview; gap hinge on, 6 mm reach); the
default with the former 5 mm reach (SignConfig.gap_max_mm); the default with gap_weight 0.
"""

from __future__ import annotations

import abkit

DEFAULT_CASES = ("sternum:60000:0.3", "sternum:mask:1.5")


def main() -> None:
    args = abkit.case_arguments(__doc__, DEFAULT_CASES).parse_args()
    abkit.compare_variants(args, [("default (gap on)", None),
                                  ("gap reach 5 mm", abkit.config_change("sign", gap_max_mm=5.0)),
                                  ("gap off", abkit.config_change("sign", gap_weight=0.0))])


if __name__ == "__main__":
    main()
