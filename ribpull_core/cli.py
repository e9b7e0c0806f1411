"""`ribpull` command line: fit, skeleton, phantom, bench, warmup; submit, status, download (service client).

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
        dicom_outputs=args.dicom_outputs,
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
                        missing_ribs=tuple(args.missing or ()), mirror=args.mirror, sternum=args.sternum)
    files = write_phantom(Path(args.output), cfg, nifti=args.nifti, spacing_mm=args.spacing,
                          partial_volume=args.partial_volume)
    print("wrote " + ", ".join(str(p) for p in files.values()))
    return 0


def cmd_warmup(args: argparse.Namespace) -> int:
    import time

    from .warmup import warm_up

    t = time.perf_counter()
    warm_up(Path(args.workdir) if args.workdir else None)
    print(f"warm-up done in {time.perf_counter() - t:.1f} s: numba's kernels are compiled and cached")
    return 0


def _spacing_arg(text: str) -> float | tuple[float, float, float]:
    """--spacing: one voxel size in mm ("1.5") or three comma-separated ones ("0.75,0.75,2.5")."""
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) not in (1, 3) or not all(v > 0 for v in values):
        raise argparse.ArgumentTypeError(f"expected one size in mm or three comma-separated (sx,sy,sz), got {text!r}")
    return values[0] if len(values) == 1 else tuple(values)


def cmd_bench(args: argparse.Namespace) -> int:
    from . import bench

    return bench.main(args)


# --- service client: submit / status / download (ribpull_core.client, httpx only) ---------------

def _client(args: argparse.Namespace):
    from .client import RibPullClient

    if not args.url:
        raise SystemExit("ribpull: error: --url (or RIBPULL_URL) is required, e.g. http://127.0.0.1:8000")
    return RibPullClient(args.url, key=args.key or None, timeout=args.http_timeout)


def _service_call(fn) -> int:
    """Run fn(); a refused request prints the problem's detail (exit 2), no answer / 5xx exits 3."""
    from .client import ServiceError

    try:
        return fn()
    except ServiceError as exc:
        print(f"ribpull: error: {exc}", file=sys.stderr)
        return 2 if 400 <= exc.status < 500 or exc.code in ("not_succeeded", "artifact_not_found") else 3


def _wait_and_fetch(c, job: dict, args: argparse.Namespace) -> int:
    from .client import describe

    def show(j):
        if not args.quiet:
            print(describe(j), file=sys.stderr, flush=True)

    job = c.wait(job["id"], poll_s=args.poll, timeout_s=args.timeout, on_progress=show)
    if job["status"] != "succeeded":
        err = job.get("error") or {}
        print(f"ribpull: job {job['id']} {job['status']}"
              + (f" [{err.get('code')}]: {err.get('message')}" if err else ""), file=sys.stderr)
        return 1
    if args.output:
        saved = c.download(job, args.output)
        print(f"downloaded {len(saved)} files to {args.output}", file=sys.stderr)
    return 0


def cmd_submit(args: argparse.Namespace) -> int:
    import json

    try:
        params = json.loads(args.params) if args.params else None
    except ValueError as exc:
        print(f"ribpull: error: --params is not JSON: {exc}", file=sys.stderr)
        return 2
    if not Path(args.input).is_file():
        print(f"ribpull: error: no such file: {args.input}", file=sys.stderr)
        return 2

    def run() -> int:
        with _client(args) as c:
            job = c.submit(args.input, params, idempotency_key=args.idempotency_key)
            print(job["id"], flush=True)  # stdout: the job id alone (JOB=$(ribpull submit ...))
            if not (args.wait or args.output):
                return 0
            return _wait_and_fetch(c, job, args)

    return _service_call(run)


def cmd_status(args: argparse.Namespace) -> int:
    import json

    from .client import describe

    def run() -> int:
        with _client(args) as c:
            if args.wait:
                return _wait_and_fetch(c, c.job(args.job), args)
            job = c.job(args.job)
            print(json.dumps(job, indent=2) if args.json else f"{job['id']} {describe(job)}")
            return 0

    return _service_call(run)


def cmd_download(args: argparse.Namespace) -> int:
    def run() -> int:
        with _client(args) as c:
            saved = c.download(args.job, args.output, names=args.name or None)
            for p in saved:
                print(p)
            return 0

    return _service_call(run)


def _service_args(sp: argparse.ArgumentParser) -> None:
    import os

    sp.add_argument("--url", default=os.environ.get("RIBPULL_URL", ""), help="service base URL (RIBPULL_URL)")
    sp.add_argument("--key", default=os.environ.get("RIBPULL_API_KEY", ""), help="API key (RIBPULL_API_KEY)")
    sp.add_argument("--http-timeout", type=float, default=120.0, help="seconds per HTTP request")


def _wait_args(sp: argparse.ArgumentParser) -> None:
    sp.add_argument("--poll", type=float, default=1.0, help="seconds between status polls")
    sp.add_argument("--timeout", type=float, default=None, help="give up waiting after this many seconds")
    sp.add_argument("-q", "--quiet", action="store_true", help="no progress lines on stderr")


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
    f.add_argument("--labels", type=int, nargs="+", default=None,
                   help="NIfTI label values (DICOM SEG: segment numbers) to reconstruct")
    f.add_argument("--device", default="auto", help="auto | cpu | cuda")
    f.add_argument("--seed", type=int, default=0)
    f.add_argument("--reference", default=None, help="mesh or points to measure against instead of the input")
    f.add_argument("--metrics-samples", type=int, default=None, help="samples per side for the surface metrics (default 100k)")
    f.add_argument("--no-skeleton", action="store_true")
    f.add_argument("--no-preview", action="store_true")
    f.add_argument("--dicom-outputs", action="store_true",
                   help="a NIfTI label map also gets seg.dcm, measurements_sr.dcm, mesh_stl.dcm (LPS mm) on a "
                        "generated CT study, study_ct.zip (a DICOM SEG input gets them anyway)")
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
    ph.add_argument("--spacing", type=_spacing_arg, default=1.0,
                    help="voxel size of the label map in mm: one number or sx,sy,sz (e.g. 0.75,0.75,2.5)")
    ph.add_argument("--sternum", action="store_true", help="add the sternum (116) and costal cartilages (117)")
    ph.add_argument("--partial-volume", action="store_true",
                    help="label a voxel iff more than half of its volume is inside (default: its centre)")
    ph.set_defaults(func=cmd_phantom)

    w = sub.add_parser("warmup", help="compile and cache the CPU kernels (numba) by running the pipeline on small "
                                      "synthetic inputs, so the first real job does not pay for it (~1-2 min once)")
    w.add_argument("--workdir", default=None, help="keep the inputs and outputs here (default: a temporary directory)")
    w.set_defaults(func=cmd_warmup)

    b = sub.add_parser("bench", help="methods x cases benchmark; writes results.csv, tables and plots")
    try:
        from . import bench

        bench.add_arguments(b)
    except ImportError:  # pragma: no cover - bench module not installed
        pass
    b.set_defaults(func=cmd_bench)

    sm = sub.add_parser("submit", help="upload FILE to a RibPull service; --wait polls, -o DIR downloads the results")
    sm.add_argument("input", help="the point cloud / label map to upload")
    _service_args(sm)
    sm.add_argument("--params", default=None, help='job params as JSON, e.g. \'{"preset": "smoke"}\'')
    sm.add_argument("--idempotency-key", default=None, help="resubmitting with the same key returns the same job")
    sm.add_argument("--wait", action="store_true", help="poll until the job ends (exit 0 only if it succeeded)")
    sm.add_argument("-o", "--output", default=None, help="download every artifact here once it succeeded (implies --wait)")
    _wait_args(sm)
    sm.set_defaults(func=cmd_submit)

    st = sub.add_parser("status", help="a job's status and progress on a RibPull service")
    st.add_argument("job", help="job id")
    _service_args(st)
    st.add_argument("--json", action="store_true", help="print the whole job resource")
    st.add_argument("--wait", action="store_true", help="poll until the job ends")
    st.add_argument("-o", "--output", default=None, help="with --wait: download the artifacts here")
    _wait_args(st)
    st.set_defaults(func=cmd_status)

    dl = sub.add_parser("download", help="download a succeeded job's artifacts")
    dl.add_argument("job", help="job id")
    _service_args(dl)
    dl.add_argument("-o", "--output", default=".", help="directory (default: current)")
    dl.add_argument("--name", nargs="+", default=None, help="only these artifacts (e.g. mesh.glb skeleton.glb)")
    dl.set_defaults(func=cmd_download)
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
