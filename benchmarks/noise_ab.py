"""Why the default trails screened Poisson under 1 mm noise: changes to the default tried in one
run, beside screened Poisson on flood-fill normals (the bench's baseline), on the bench's phantom
cases scored like `ribpull bench` against the TRUE surface (CD-L1 / HD in mm, `--samples` per side;
mesh components). None of them is the default.

    .venv/bin/python benchmarks/noise_ab.py                      # 60k and 200k points x 1 mm noise
    .venv/bin/python benchmarks/noise_ab.py --cases 20000:1.0 --samples 300000

Rows: Poisson; the `default` preset (no skeleton, no preview) through run_pipeline; the default's
mesh after 3 Taubin passes (trimesh, lambda = nu = 0.5); the default with one SparseOcc setting
changed (the near-surface hinges twice as far off the points; the finest grid cell two sampling
gaps instead of one; eq. 1's quadric targets over 40 neighbours instead of 20; the near-surface
hinges' offset capped at 2 mm instead of 1; no near-surface hinges; the default before 21a7999, whose
eq. 1 target patches needed every neighbour's normal facing the point's way and whose near-surface
hinges sat on the points themselves even on noisy input; the default without the noise-bias flow
of too-noisy inputs' meshes, i.e. as before it came in).
"""

from __future__ import annotations

import abkit

DEFAULT_CASES = ("60000:1.0", "200000:1.0")  # 20000:1.0 is the other row the noise-bias flow changes


VARIANTS = {
    "near-surface offset x2": abkit.config_change("sign", near_surface_offset=1.0),
    "finest cell 2 gaps": abkit.config_change("field", grid_finest_cell=2.0),
    "quadric targets k40": abkit.config_change("queries", target_knn=40),
    "near-surface cap 2 mm": abkit.config_change("sign", near_surface_offset_max_mm=2.0),
    "no near-surface hinges": abkit.config_change("sign", near_surface_weight=0.0),
    "before 21a7999 (strict patches, hinges on the points)": lambda c: abkit.config_change(
        "sign", near_surface_centres="points")(abkit.config_change("queries", noisy_residual_mm=0.0)(c)),
    "without the noise-bias flow (RefineConfig.noise_flow_factor = 0)": abkit.RefineChange({"noise_flow_factor": 0.0}),
}


def main() -> None:
    import trimesh

    def taubin_copy(runs):  # runs[1] is the default (runs[0] the baseline)
        _, mesh, seconds = runs[1]
        smoothed = mesh.copy()
        trimesh.smoothing.filter_taubin(smoothed, iterations=3)
        runs.append(("default + 3 Taubin passes", smoothed, seconds))

    args = abkit.case_arguments(__doc__, DEFAULT_CASES).parse_args()
    abkit.compare_variants(args, [("default", None), *VARIANTS.items()], extra=taubin_copy)


if __name__ == "__main__":
    main()
