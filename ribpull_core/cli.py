"""`ribpull` command line: fit, skeleton, phantom, bench.

Every command calls the same library functions the service uses (fit -> pipeline.run_pipeline).
Bad input prints one line saying what to fix and exits with status 2; a cancel (Ctrl-C) exits 130.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .errors import JobCanceled, RibPullInputError


def _progress_bar():
    """Progress on stderr: a tqdm bar on a terminal, one line per 5 % otherwise (logs, CI)."""
    from tqdm import tqdm

    if not sys.stderr.isatty():
        last = {"step": -1}

        def on_line(p):
            step = int(p.fraction * 20)
            if step != last["step"]:
                last["step"] = step
                extra = f" it {p.iteration}/{p.iterations} loss {p.loss:.4f}" if p.iteration is not None else ""
                print(f"[{p.fraction * 100:5.1f}%] {p.stage}{extra}", file=sys.stderr, flush=True)

        return None, on_line

    bar = tqdm(total=1000, bar_format="{desc} {percentage:3.0f}%|{bar}| {elapsed}<{remaining}", file=sys.stderr,
               mininterval=0.2)

    def on_progress(p):
        bar.n = int(p.fraction * 1000)
        desc = p.stage
        if p.iteration is not None:
            desc += f" {p.iteration}/{p.iterations}"
        if p.loss is not None:
            desc += f" loss {p.loss:.4f}"
        bar.set_description_str(desc.ljust(28), refresh=False)
        bar.update(0)

    return bar, on_progress


def cmd_fit(args: argparse.Namespace) -> int:
    from .pipeline import PipelineOptions, run_pipeline

    options = PipelineOptions(
        preset=args.preset, method=args.method, iterations=args.iterations, resolution=args.resolution,
        labels=args.labels, skeleton=not args.no_skeleton, preview=not args.no_preview, device=args.device,
        seed=args.seed, reference=args.reference, metrics_samples=args.metrics_samples,
    )
    bar, on_progress = _progress_bar() if not args.quiet else (None, None)
    try:
        result = run_pipeline(Path(args.input), Path(args.output), options, progress=on_progress)
    finally:
        if bar is not None:
            bar.close()
    s = result.metrics["surface"]
    print(f"wrote {len(result.artifacts)} files to {result.outdir}")
    print(f"method {result.metrics['method']} preset {result.metrics['preset']}: {result.metrics['iterations_run']} iterations, "
          f"{result.metrics['mesh']['components']} mesh components, total {result.metrics['timings_s']['total']:.1f} s")
    print(f"vs {result.metrics['reference']}: CD-L1 {s['cd_l1_mm']:.3f} mm, Hausdorff {s['hausdorff_mm']:.2f} mm, "
          f"F-score@{s.get('tau_mm', 1.0)}mm {s['fscore']:.3f}")
    return 0


def cmd_skeleton(args: argparse.Namespace) -> int:
    import trimesh

    from .io import load_point_cloud
    from .skeleton import export_skeleton, skeleton_from_mesh, skeletonize

    path = Path(args.input)
    mesh = None
    if path.suffix.lower() in (".stl", ".obj", ".glb", ".off") or (path.suffix.lower() == ".ply" and _has_faces(path)):
        mesh = trimesh.load(path, force="mesh")
        skel = skeleton_from_mesh(mesh, n_points=args.points)
    else:
        cloud = load_point_cloud(path, labels=args.labels)
        skel = skeletonize(cloud.points, normals=cloud.normals, point_labels=cloud.labels, label_names=cloud.label_names)
    files = export_skeleton(skel, Path(args.output), mesh_mm=mesh)
    print(f"{len(skel.curves)} rib curves: " + ", ".join(f"{c.label} {c.length_mm:.0f} mm" for c in skel.curves))
    print("wrote " + ", ".join(sorted(Path(p).name for p in files.values())))
    return 0


def _has_faces(path: Path) -> bool:
    from .pipeline import _ply_has_faces

    return _ply_has_faces(path)


def cmd_phantom(args: argparse.Namespace) -> int:
    from .phantom import PhantomConfig, write_phantom

    cfg = PhantomConfig(seed=args.seed, n_points=args.points, noise_mm=args.noise,
                        missing_ribs=tuple(args.missing or ()), mirror=args.mirror)
    files = write_phantom(Path(args.output), cfg, nifti=args.nifti, spacing_mm=args.spacing)
    print("wrote " + ", ".join(str(p) for p in files.values()))
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    from . import bench

    return bench.main(args)


def build_parser() -> argparse.ArgumentParser:
    from .methods import METHOD_CLASSES, RUN_PRESETS

    p = argparse.ArgumentParser(prog="ribpull", description="Ribcage surfaces (SparseOcc) and rib skeletons from CT segmentations.")
    sub = p.add_subparsers(dest="command", required=True)

    f = sub.add_parser("fit", help="fit a neural occupancy field; write mesh, SDF, skeleton, weights, metrics")
    f.add_argument("input", help="point cloud (.ply .xyz .txt .csv .npy .npz .pcd) or label map (.nii .nii.gz)")
    f.add_argument("-o", "--output", required=True, help="output directory")
    f.add_argument("--preset", default="default", choices=sorted(RUN_PRESETS))
    f.add_argument("--method", default=None, choices=sorted(METHOD_CLASSES), help="override the preset's method")
    f.add_argument("--iterations", type=int, default=None, help="override the training schedule length")
    f.add_argument("--resolution", type=int, default=None, help="finest marching-cubes cells along the longest side")
    f.add_argument("--labels", type=int, nargs="+", default=None, help="NIfTI label values to reconstruct")
    f.add_argument("--device", default="auto", help="auto | cpu | cuda")
    f.add_argument("--seed", type=int, default=0)
    f.add_argument("--reference", default=None, help="mesh or points to measure against instead of the input")
    f.add_argument("--metrics-samples", type=int, default=None, help="samples per side for the surface metrics (default 100k)")
    f.add_argument("--no-skeleton", action="store_true")
    f.add_argument("--no-preview", action="store_true")
    f.add_argument("-q", "--quiet", action="store_true")
    f.set_defaults(func=cmd_fit)

    s = sub.add_parser("skeleton", help="medial axis of each rib from a mesh or point cloud")
    s.add_argument("input", help="a mesh (.ply with faces, .stl, .obj, .glb) or a point cloud")
    s.add_argument("-o", "--output", required=True)
    s.add_argument("--points", type=int, default=20_000, help="points sampled on a mesh input")
    s.add_argument("--labels", type=int, nargs="+", default=None)
    s.set_defaults(func=cmd_skeleton)

    ph = sub.add_parser("phantom", help="write a synthetic ribcage with its true surface and centerlines")
    ph.add_argument("output")
    ph.add_argument("--seed", type=int, default=0)
    ph.add_argument("--points", type=int, default=60_000)
    ph.add_argument("--noise", type=float, default=0.3, help="noise std in mm")
    ph.add_argument("--missing", nargs="*", help="rib names to leave out, e.g. L11 R3")
    ph.add_argument("--mirror", action="store_true")
    ph.add_argument("--nifti", action="store_true", help="also write a voxelised label map mask.nii.gz")
    ph.add_argument("--spacing", type=float, default=1.0, help="voxel size of the label map in mm")
    ph.set_defaults(func=cmd_phantom)

    b = sub.add_parser("bench", help="methods x cases benchmark; writes results.csv, tables and plots")
    try:
        from . import bench

        bench.add_arguments(b)
    except ImportError:  # pragma: no cover - bench module not installed
        pass
    b.set_defaults(func=cmd_bench)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except RibPullInputError as exc:
        print(f"ribpull: error [{exc.code}]: {exc.message}", file=sys.stderr)
        return 2
    except (JobCanceled, KeyboardInterrupt):
        print("ribpull: canceled", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
