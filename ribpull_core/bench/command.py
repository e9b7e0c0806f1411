"""`ribpull bench` itself: its options (add_arguments), run_bench (a plan plus the skeleton and
speed sections, then every output) and main (what the CLI calls).
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

from .common import GROUP_POINTS, METRIC_SAMPLES, REAL_LABEL_MAP
from .plan import (
    FULL_SEEDS,
    PLANS,
    QUICK_POINTS,
    SPEED_PAPER_ITERATIONS,
    SWEEP_SEEDS,
    Case,
    build_plan,
    skeleton_plan,
    speed_plan,
)
from .report import rewrite_outputs, speed_rows, write_csv, write_outputs
from .run import run_plan

#: what `--help` says each plan costs on the 2-core CPU (quick and docs measured; sweep estimated:
#: 24 default runs at ~25 s fit + ~35 s of other stages, scoring and process start, 19 Poisson runs
#: at ~15-40 s, 6 marching-cubes runs at ~15 s and ~2 min writing phantoms)
PLAN_HELP = ("quick (as --quick); docs: what docs/benchmarks.md shows (~65 min on 2 cores); "
             "full: every method on every case and seed, SparseOcc paper at 20k iterations (hours; default); "
             "sweep: the accuracy sweep (issue 9), SparseOcc default vs screened Poisson on 17 phantom point clouds "
             "(5k-200k points x noise 0 / 0.3 / 1 mm, 2%% outliers at 20k and 60k) and vs mc_taubin + mask "
             "marching cubes on partial-volume label maps (1.5 mm, 0.75x0.75x2.5 mm), plus the sternum phantom: "
             "45 runs for one seed, estimated ~35-40 min on 2 cores when the default fit takes ~20-30 s per case "
             "(~55 min at the 42 s measured in the docs run); no skeleton / speed sections")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The `ribpull bench` options."""
    parser.add_argument("-o", "--output", required=True, help="output directory (results.csv, results.md, PNGs, runs/)")
    parser.add_argument("--quick", action="store_true",
                        help="<= 15 min on 2 cores: one phantom case, short baselines, mask + real map, skeletons, "
                             "speed (same as --plan quick)")
    parser.add_argument("--plan", choices=PLANS, default=None, help=PLAN_HELP)
    parser.add_argument("--cases", default=None, help="folder of extra inputs (point files, label maps, phantom folders)")
    parser.add_argument("--seeds", type=int, nargs="+", default=None,
                        help=f"seeds (default {list(FULL_SEEDS)}; quick: 0; sweep: {list(SWEEP_SEEDS)})")
    parser.add_argument("--methods", nargs="+", default=None,
                        help="only methods whose label starts with one of these (or of this kind: pipeline, poisson, "
                             "mask_mc, mc_taubin)")
    parser.add_argument("--variants", nargs="+", default=None,
                        help="only the cases of these variants, e.g. n60000-noise0.3 mask1.5mm-pv "
                             "sternum-mask1.5mm-pv (a subset of a plan: a GPU run, a re-check)")
    parser.add_argument("--points", type=int, default=None,
                        help=f"points of the main phantom case (default {QUICK_POINTS}; not used by the sweep)")
    parser.add_argument("--label-map", default=str(REAL_LABEL_MAP), help="the real label map case ('' to leave out)")
    parser.add_argument("--metric-samples", type=int, default=METRIC_SAMPLES, help="surface samples per side for scoring")
    parser.add_argument("--device", default="auto", help="auto | cpu | cuda (neural methods)")
    parser.add_argument("--task-timeout", type=float, default=None, help="seconds after which one run is stopped")
    parser.add_argument("--no-skeleton-section", action="store_true")
    parser.add_argument("--no-speed-section", action="store_true")
    parser.add_argument("--rewrite", action="store_true",
                        help="run nothing: rebuild results.md and the plots in -o DIR from its CSVs")


def sparseocc_row(rows: list[dict], case: Case, preset: str) -> dict | None:
    """The plan's first successful SparseOcc pipeline row of `preset` on `case` (None if there is none)."""
    return next((r for r in rows if r["case"] == case.name and r.get("kind") == "pipeline" and r.get("preset") == preset
                 and r.get("fit_method") == "sparseocc" and r.get("status") == "ok"), None)


def run_bench(outdir: Path, plan: list, *, metric_samples: int = METRIC_SAMPLES, device: str = "auto",
              skeleton_case: Case | None = None, speed_case: Case | None = None, notes: list[str] | None = None,
              meta: dict | None = None, timeout_s: float | None = None, speed_iterations: int = SPEED_PAPER_ITERATIONS,
              log=print) -> dict:
    """Run a plan and the optional skeleton and speed sections, write every output (write_outputs).
    Returns write_outputs' dict plus "rows", "skeleton_rows", "speed"."""
    outdir = Path(outdir)
    t0 = time.perf_counter()
    # results.csv grows run by run: a bench stopped part way keeps what finished (`--rewrite` reports it)
    rows = run_plan(outdir, plan, metric_samples, device, timeout_s, log,
                    on_row=lambda done: write_csv(outdir / "results.csv", done))
    skel_rows = None
    if skeleton_case is not None:
        log("skeleton section ...")
        skel_rows = run_plan(outdir, skeleton_plan(skeleton_case), metric_samples, device, timeout_s, log)
    speed = None
    if speed_case is not None:
        log("speed section ...")
        default_row, paper_row = (sparseocc_row(rows, speed_case, p) for p in ("default", "paper"))
        timed = run_plan(outdir, speed_plan(speed_case, default_row, paper_row, speed_iterations), metric_samples,
                         device, timeout_s, log)
        speed = speed_rows(default_row, timed, paper_row)
    meta = {**(meta or {}), "bench wall time": f"{time.perf_counter() - t0:.0f} s"}
    result = write_outputs(outdir, rows, skel_rows, speed, meta, notes)
    return {**result, "rows": rows, "skeleton_rows": skel_rows, "speed": speed}


def machine_meta() -> dict:
    """Where and how the benchmark ran (for results.md)."""
    import torch

    from ..pipeline import configure_torch_threads

    return {"machine": f"{platform.machine()} {platform.processor() or ''}, {os.cpu_count()} cores, "
                       f"torch {torch.__version__} with {configure_torch_threads()} threads, "
                       f"CUDA {'yes' if torch.cuda.is_available() else 'no'}, Python {platform.python_version()}",
            "date": time.strftime("%Y-%m-%d %H:%M %Z")}


def importlib_missing(name: str) -> bool:
    """True when module `name` cannot be found (without importing it)."""
    import importlib.util

    return importlib.util.find_spec(name) is None


def only_variants(plan: list, cases: list[Case], variants: list[str], notes: list[str]) -> tuple[list, list[Case]]:
    """The plan and cases cut to the cases whose variant is one of `variants`; a note names the
    variants asked for that the plan does not have, and those it has."""
    wanted = set(variants)
    have = [c.variant for c in cases if c.variant]
    unknown = sorted(wanted - set(have))
    if unknown:
        notes.append(f"--variants {', '.join(unknown)}: not in this plan; it has {', '.join(dict.fromkeys(have))}")
    return [(m, c) for m, c in plan if c.variant in wanted], [c for c in cases if c.variant in wanted]


def main(args: argparse.Namespace) -> int:
    """`ribpull bench`: build the plan, run it, write the outputs, print results.md. 0 if any row succeeded."""
    outdir = Path(args.output)
    if args.rewrite:
        result = rewrite_outputs(outdir, {"rewritten from": str(outdir / "results.csv"),
                                          "date": time.strftime("%Y-%m-%d %H:%M %Z")})
        print(result["markdown"])
        return 0
    outdir.mkdir(parents=True, exist_ok=True)
    mode = "quick" if args.quick else (args.plan or "full")
    if args.quick and args.plan not in (None, "quick"):
        print(f"ribpull bench: --quick and --plan {args.plan} disagree; choose one", file=sys.stderr)
        return 2
    seeds = tuple(args.seeds) if args.seeds else {"quick": (0,), "sweep": SWEEP_SEEDS}.get(mode, FULL_SEEDS)
    notes: list[str] = []
    plan, cases = build_plan(mode, outdir / "cases", seeds, args.points,
                             Path(args.cases) if args.cases else None,
                             Path(args.label_map) if args.label_map else None, args.methods, notes)
    if args.variants:
        plan, cases = only_variants(plan, cases, args.variants, notes)
    if importlib_missing("pymeshlab"):
        notes.append("screened Poisson skipped: pymeshlab is not installed (pip install 'ribpull[bench]')")
        plan = [(m, c) for m, c in plan if m.kind != "poisson"]
    truth_points = next((c for c in cases if c.group == GROUP_POINTS), None)  # none in the sweep
    its = {m.label: (m.iterations or "preset schedule") for m, _ in plan if m.kind == "pipeline"}
    meta = {"command": "ribpull " + " ".join(sys.argv[1:]) if Path(sys.argv[0]).name == "ribpull" else f"ribpull bench ({mode})",
            "mode": mode, "seeds": list(seeds), "iterations": ", ".join(f"{k}: {v}" for k, v in its.items()) or "—",
            "surface metric samples per side": f"{args.metric_samples:,}",
            "surface distances": "each sample to the other surface's triangles (exact); sample to sample in "
                                 "results.csv's *_sampled_mm columns", **machine_meta()}
    if not args.no_speed_section and truth_points is not None:
        meta["speed section"] = ("paper preset's full schedule extrapolated from its run in the plan, else from "
                                 f"{SPEED_PAPER_ITERATIONS} timed iterations")
    print(f"ribpull bench ({mode}): {len(plan)} runs on {len(cases)} cases -> {outdir}", file=sys.stderr)
    for label, n in its.items():
        print(f"  {label}: {n} iterations", file=sys.stderr)
    for n in notes:
        print(f"  note: {n}", file=sys.stderr)
    result = run_bench(outdir, plan, metric_samples=args.metric_samples, device=args.device,
                       skeleton_case=None if args.no_skeleton_section else truth_points,
                       speed_case=None if args.no_speed_section else truth_points, notes=notes, meta=meta,
                       timeout_s=args.task_timeout, log=lambda s: print(s, file=sys.stderr, flush=True))
    print(result["markdown"])
    print(f"\nwrote {outdir / 'results.csv'}, {outdir / 'results.md'} and the PNGs", file=sys.stderr)
    return 0 if any(r.get("status") == "ok" for r in result["rows"]) else 1
