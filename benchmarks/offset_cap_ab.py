"""The near-surface hinges' offset cap (SignConfig.near_surface_offset_max_mm) in one run, beside
the bench baseline of each case (screened Poisson on flood-fill normals; marching cubes + 20
Taubin iterations on label maps), scored like `ribpull bench` against the phantom's TRUE surface
(CD-L1 / HD in mm, `--samples` per side; mesh components; separable ribs that are their own
component).

    .venv/bin/python benchmarks/offset_cap_ab.py --samples 300000
    .venv/bin/python benchmarks/offset_cap_ab.py --cases sternum:60000:0.3 mask:1.5 --caps 0 0.7

Rows: the baseline; the `default` preset (no skeleton, no preview; its cap is 1 mm); the default
with each cap of --caps (mm; 0 = no cap: the hinges half a sampling gap off the points, the
previous default).
"""

from __future__ import annotations

import abkit

DEFAULT_CASES = ("5000:0", "10000:0.3", "10000:1.0", "60000:0.3", "sternum:60000:0.3")


def main() -> None:
    ap = abkit.case_arguments(__doc__, DEFAULT_CASES)
    ap.add_argument("--caps", nargs="+", type=float, default=[0.0], help="offset caps to run beside the default (mm)")
    args = ap.parse_args()
    caps = [(f"cap {cap:g} mm" if cap > 0 else "no cap", abkit.config_change("sign", near_surface_offset_max_mm=cap))
            for cap in args.caps]
    abkit.compare_variants(args, [("default", None), *caps])


if __name__ == "__main__":
    main()
