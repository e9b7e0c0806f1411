"""Label maps too noisy for the refinement's patches (`refine.plan_refinement`; the real
TotalSegmentator map in ../shared/data is one: 3 mm voxels, 0.95 mm RMS off its patches): the
`default` preset fits them for the method's whole schedule (1000 iterations, which their loss never
stops early), against shorter schedules (what `ribpull fit --iterations N` gives), beside the bench
baseline (marching cubes + 20 Taubin). The phantom's partial-volume map is roughened first
(`phantom.roughen_label_map`, --flip-fraction of the boundary voxels flipped in patches) so that it
takes the same path, and is scored like `ribpull bench` against the phantom's TRUE surface (CD-L1 /
HD in mm, `--samples` per side; mesh components; ribs isolated).

    .venv/bin/python benchmarks/noisy_label_map_ab.py --samples 300000
    .venv/bin/python benchmarks/noisy_label_map_ab.py --cases mask:3 --seeds 0 --flip-fraction 0.05

Measured 2026-12-08 (docs/benchmarks.md): 400 iterations took half the time, with CD-L1 the same or
lower, but more mesh parts; on the real map it split a rib the map joins only along voxel edges in
2 of 3 seeds (1000: 0 of 3). Not the default.
"""

from __future__ import annotations

import abkit

DEFAULT_CASES = ("mask:3",)


def main() -> None:
    import nibabel as nib
    import numpy as np

    from ribpull_core.phantom import roughen_label_map

    ap = abkit.case_arguments(__doc__, DEFAULT_CASES)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="phantom seeds (each its own roughening)")
    ap.add_argument("--flip-fraction", type=float, default=0.08, help="boundary voxels flipped")
    ap.add_argument("--iterations", type=int, nargs="+", default=[400], help="the shorter schedules to compare")
    args = ap.parse_args()

    def roughen(case) -> None:
        image = nib.load(case.input_path)
        rough = roughen_label_map(np.asarray(image.dataobj), args.flip_fraction, seed=case.seed)
        nib.save(nib.Nifti1Image(rough.astype(image.get_data_dtype()), image.affine, image.header), case.input_path)

    abkit.compare_variants(args, [("default (the whole schedule)", None)]
                           + [(f"{n} iterations", abkit.config_change("schedule", iterations=n)) for n in args.iterations],
                           prepare=roughen)


if __name__ == "__main__":
    main()
