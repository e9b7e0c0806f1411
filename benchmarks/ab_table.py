"""Tabulate a `benchmarks/bench_ab.sh` run: one markdown row per method and side of each variant.

    .venv/bin/python benchmarks/ab_table.py OUT > docs/bench_ab_<rev>/ab_table.md  (then add the heading)

Reads OUT/{base,new}-<variant>/results.csv (what `ribpull bench` writes); times in s, lengths in mm,
"fit overhead" is fit_overhead_s (the fit's time less its iterations). Plain mask marching cubes is
left out (mc_taubin is the label maps' baseline).
"""

from __future__ import annotations

import csv
import sys
from pathlib import Path

VARIANTS = ("mask0.75x0.75x2.5mm-pv", "mask1.5mm-pv", "sternum-mask1.5mm-pv", "n60000-noise0.3")
HEADER = ("| case | side | method | CD-L1 mm | HD mm | parts | iso/sep | total s | load | fit | its x ms | fit overhead "
          "| mesh | sdf | skeleton | metrics | export | peak RSS MB |")


def cell(row: dict, key: str, digits: int = 2) -> str:
    """A number of a results.csv row at `digits` decimals, '-' where it is empty."""
    try:
        return f"{float(row.get(key, '')):.{digits}f}"
    except ValueError:
        return "-"


def table(out: Path) -> list[str]:
    lines = [HEADER, "|---|---|---|" + "---:|" * 15]
    for variant in VARIANTS:
        for side in ("base", "new"):
            path = out / f"{side}-{variant}" / "results.csv"
            if not path.exists():
                continue
            for r in csv.DictReader(path.open()):
                if r["method"] == "mask marching cubes":
                    continue
                its = f"{r['iterations_run'] or '-'} x {cell(r, 'ms_per_iteration', 1)}"
                times = " | ".join(cell(r, f"time_{k}_s") for k in ("total", "load", "fit"))
                later = " | ".join(cell(r, f"time_{k}_s") for k in ("mesh", "sdf", "skeleton", "metrics", "export"))
                lines.append(f"| {variant} | {side} | {r['method']} | {cell(r, 'cd_l1_mm', 4)} | {cell(r, 'hausdorff_mm', 3)} "
                             f"| {r['mesh_components']} | {r['n_isolated']}/{r['n_separable']} | {times} | {its} "
                             f"| {cell(r, 'fit_overhead_s')} | {later} | {cell(r, 'peak_rss_mb', 0)} |")
    return lines


if __name__ == "__main__":
    print("\n".join(table(Path(sys.argv[1]))))
