"""Accuracy and speed of `ribpull fit` on the project's phantom, and on the real label map.

Runs the same pipeline as the CLI and the service (run_pipeline), timing the whole call, then scores
the reconstruction against the phantom's TRUE surface with >= 1M samples per side (mm), counts mesh
components, and scores the skeleton of the reconstruction against the true centerlines.

    .venv/bin/python benchmarks/fit_phantom.py                      # default preset, 60k pts, 0.3 mm noise
    .venv/bin/python benchmarks/fit_phantom.py --preset paper --iterations 50   # per-iteration cost
    .venv/bin/python benchmarks/fit_phantom.py --nifti ../shared/data/totalseg_example_seg.nii.gz
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np


def phantom_case(args, workdir: Path):
    from ribpull_core.phantom import PhantomConfig, write_phantom

    cfg = PhantomConfig(seed=args.seed, n_points=args.points, noise_mm=args.noise)
    files = write_phantom(workdir / "phantom", cfg)
    return files["points"], cfg


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="default")
    ap.add_argument("--method", default=None)
    ap.add_argument("--iterations", type=int, default=None)
    ap.add_argument("--resolution", type=int, default=None)
    ap.add_argument("--points", type=int, default=60_000)
    ap.add_argument("--noise", type=float, default=0.3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--samples", type=int, default=1_000_000, help="samples per side against the truth")
    ap.add_argument("--no-skeleton", action="store_true")
    ap.add_argument("--nifti", default=None, help="a label map instead of the phantom")
    ap.add_argument("--json", default=None, help="also write the figures here")
    ap.add_argument("--keep", default=None, help="keep the outputs in this directory")
    args = ap.parse_args()

    import trimesh

    from ribpull_core.metrics import surface_metrics
    from ribpull_core.pipeline import PipelineOptions, run_pipeline

    work = Path(args.keep or tempfile.mkdtemp(prefix="ribpull-bench-"))
    work.mkdir(parents=True, exist_ok=True)
    options = PipelineOptions(preset=args.preset, method=args.method, iterations=args.iterations,
                              resolution=args.resolution, skeleton=not args.no_skeleton, seed=args.seed)
    report: dict = {"preset": args.preset, "method": args.method or "(preset)", "machine_threads": None}
    if args.nifti:
        input_path, phantom_cfg = Path(args.nifti), None
    else:
        input_path, phantom_cfg = phantom_case(args, work)
    t0 = time.perf_counter()
    result = run_pipeline(input_path, work / "out", options)
    report["pipeline_seconds"] = round(time.perf_counter() - t0, 2)
    m = result.metrics
    report.update(iterations_run=m["iterations_run"], fit_seconds=m["fit_seconds"], timings_s=m["timings_s"],
                  ms_per_iteration=round(1000 * m["fit_seconds"] / max(1, m["iterations_run"]), 1),
                  components=m["mesh"]["components"], torch_threads=m["torch_threads"], weights=m["weights"])
    mesh = trimesh.load(result.artifacts["mesh.ply"], force="mesh")
    if phantom_cfg is not None:
        from ribpull_core.phantom import make_phantom

        phantom = make_phantom(phantom_cfg)
        t = time.perf_counter()
        truth = surface_metrics(mesh, phantom.mesh, n_samples=args.samples, tau_mm=1.0,
                                paper_units_per_mm=m["frame"]["half_extent_mm"] ** -1)
        report["vs_true_surface"] = {k: truth[k] for k in ("cd_l1_mm", "cd_l2_mm2", "hausdorff_mm", "normal_consistency",
                                                           "fscore", "cd_l1_paper", "cd_l2_paper", "hausdorff_paper")}
        report["vs_true_surface"]["n_samples_per_side"] = args.samples
        report["metric_seconds"] = round(time.perf_counter() - t, 1)
        if "skeleton.json" in result.artifacts:
            from ribpull_core.skeleton.metrics import skeleton_metrics
            from ribpull_core.skeleton.model import Skeleton

            skel = Skeleton.from_json(json.loads(result.artifacts["skeleton.json"].read_text()))
            sk = skeleton_metrics(skel, phantom.centerlines())
            report["skeleton_vs_true_centerlines"] = sk
    else:
        import nibabel as nib

        from ribpull_core.io import load_point_cloud

        cloud = load_point_cloud(input_path)
        report["labels"] = sorted(int(v) for v in np.unique(cloud.labels))
        from scipy.spatial import cKDTree

        d = cKDTree(cloud.points).query(mesh.sample(200_000), workers=-1)[0]
        report["mesh_to_voxel_centres_mm"] = {"mean": round(float(d.mean()), 3), "p95": round(float(np.percentile(d, 95)), 3),
                                             "voxel_mm": [float(v) for v in nib.load(str(input_path)).header.get_zooms()[:3]]}
        report["vs_input"] = {k: m["surface"][k] for k in ("cd_l1_mm", "hausdorff_mm", "fscore")}
    print(json.dumps(report, indent=2, default=str))
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=2, default=str))


if __name__ == "__main__":
    main()
