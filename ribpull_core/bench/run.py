"""Running a plan: every (method, case) pair in a fresh child process (multiprocessing "spawn"), so
its peak resident memory (VmHWM, MB) is its own; a sampler thread in the child records the largest
resident size seen during each stage, a stage timer the wall seconds of each. A child that dies or
runs past its timeout gives a failed row, never a crash of the benchmark.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import resource
import shutil
import sys
import threading
import time
import traceback
from dataclasses import asdict
from pathlib import Path

from .common import FSCORE_TAU_MM, STAGES, finite, json_default, merge_row, num, slug, spacing_label
from .plan import Case, MethodSpec, ensure_case_files

# ------------------------------------------------------------------------------ child side


class RssSampler:
    """Largest resident set size (MB) of this process per stage, sampled every interval_s by a thread.
    `set(stage)` switches the stage being charged. Linux (/proc/self/statm); elsewhere only the
    process peak (ru_maxrss) is known and the per-stage values stay empty."""

    def __init__(self, interval_s: float = 0.02):
        self.interval_s, self.stage, self.peaks = interval_s, "start", {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self._page = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096

    def rss_mb(self) -> float | None:
        """Current resident set size in MB (None when /proc is unavailable)."""
        try:
            with open("/proc/self/statm") as fh:
                return int(fh.read().split()[1]) * self._page / 2**20
        except (OSError, ValueError, IndexError):
            return None

    def _sample(self) -> None:
        v = self.rss_mb()
        if v is not None:
            self.peaks[self.stage] = max(self.peaks.get(self.stage, 0.0), v)

    def _loop(self) -> None:
        while not self._stop.wait(self.interval_s):
            self._sample()

    def start(self) -> RssSampler:
        self._sample()
        self._thread.start()
        return self

    def set(self, stage: str) -> None:
        """Charge what follows to `stage` (samples now for the stage that ends and the one that starts)."""
        self._sample()
        self.stage = stage
        self._sample()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=1.0)
        self._sample()

    def columns(self) -> dict:
        """rss_<stage>_mb for the known stages (MB, rounded) and peak_rss_mb (this process's peak)."""
        out = {f"rss_{s}_mb": round(v, 1) for s, v in self.peaks.items() if s in STAGES}
        out["peak_rss_mb"] = round(peak_rss_mb(), 1)
        return out


def peak_rss_mb() -> float:
    """This process's peak resident set size in MB: VmHWM of /proc/self/status on Linux, else
    ru_maxrss (KB on Linux, bytes on macOS). Not ru_maxrss on Linux: it survives fork + exec, so a
    spawned child would report its parent's peak whenever that is larger than its own."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024
    except (OSError, ValueError, IndexError):
        pass
    r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return r / 2**20 if sys.platform == "darwin" else r / 1024


class StageTimer:
    """`with timer("fit"):` adds the block's wall seconds to time_fit_s and charges its memory to it."""

    def __init__(self, sampler: RssSampler):
        self.sampler, self.times = sampler, {}

    def __call__(self, stage: str):
        timer = self

        class _Block:
            def __enter__(self):
                timer.sampler.set(stage)
                self.t = time.perf_counter()

            def __exit__(self, *exc):
                timer.times[stage] = timer.times.get(stage, 0.0) + time.perf_counter() - self.t
                return False

        return _Block()

    def columns(self, exclude=("score",)) -> dict:
        """time_<stage>_s (rounded) and time_total_s (the method's own stages: scoring excluded)."""
        out = {f"time_{s}_s": round(v, 3) for s, v in self.times.items()}
        out["time_total_s"] = round(sum(v for s, v in self.times.items() if s not in exclude), 3)
        return out


def base_row(task: dict) -> dict:
    """The identifying columns of a task's row (spacing_mm as "1.5" / "0.75x0.75x2.5")."""
    case, spec = task["case"], task["spec"]
    return {"method": spec["label"], "kind": spec["kind"], "preset": spec.get("preset"), "case": case["name"],
            "variant": case.get("variant"), "group": case["group"], "input_kind": case["input_kind"],
            "seed": case["seed"], "noise_mm": case.get("noise_mm"), "n_points": case.get("n_points"),
            "outlier_fraction": case.get("outlier_fraction") or None,
            "spacing_mm": spacing_label(case["spacing_mm"]) if case.get("spacing_mm") else None,
            "partial_volume": case.get("partial_volume") or None, "sternum": case.get("sternum") or None,
            "status": "failed", "note": ""}


def child_main(task: dict, result_path: str) -> None:
    """Entry point of the spawned child: run the task, write its row (JSON) to result_path."""
    from .tasks import TASK_RUNNERS

    sampler = RssSampler().start()
    timer = StageTimer(sampler)
    row = base_row(task)
    try:
        merge_row(row, TASK_RUNNERS[task["spec"]["kind"]](task, sampler, timer))
        row["status"] = "ok"
    except Exception as exc:  # noqa: BLE001  (the row records the failure; the benchmark goes on)
        row["note"] = f"{type(exc).__name__}: {getattr(exc, 'message', None) or exc}"[:400]
        Path(task["rundir"], "error.txt").write_text(traceback.format_exc())
    finally:
        sampler.stop()
    row.update(sampler.columns())
    Path(result_path).write_text(json.dumps(row, default=json_default))


# ----------------------------------------------------------------------------- parent side


def make_task(spec: MethodSpec, case: Case, outdir: Path, metric_samples: int, device: str, render: bool) -> dict:
    """JSON-able description of one run for the child (its own folder under outdir/runs/)."""
    rundir = Path(outdir) / "runs" / f"{slug(case.name)}-seed{case.seed}__{slug(spec.label)}"
    return {"spec": asdict(spec), "case": asdict(case), "rundir": str(rundir), "metric_samples": int(metric_samples),
            "device": device, "render": bool(render)}


def run_task(task: dict, timeout_s: float | None = None) -> dict:
    """Run one task in a fresh spawned child and return its row; a child that dies or runs past
    timeout_s gives a failed row. wall_s: the child's whole life (start-up and imports included)."""
    rundir = Path(task["rundir"])
    if rundir.exists():
        shutil.rmtree(rundir)
    rundir.mkdir(parents=True)
    result = rundir / "row.json"
    proc = mp.get_context("spawn").Process(target=child_main, args=(task, str(result)), daemon=False)
    t0 = time.perf_counter()
    proc.start()
    proc.join(timeout_s)
    if proc.is_alive():
        proc.terminate()
        proc.join()
    wall = round(time.perf_counter() - t0, 2)
    if result.exists():
        row = json.loads(result.read_text())
    else:
        row = base_row(task)
        if timeout_s and wall >= timeout_s:
            why = f"stopped after running past --task-timeout {timeout_s:g} s"
        elif proc.exitcode == -9:
            why = "killed by SIGKILL: out of memory?"
        else:
            why = f"exit code {proc.exitcode}; see the log above"
        row["note"] = f"child process died ({why})"
    row["wall_s"] = wall
    return row


def run_plan(outdir: Path, plan: list, metric_samples: int, device: str = "auto", timeout_s: float | None = None,
             log=print, on_row=None) -> list[dict]:
    """Run every (MethodSpec, Case) of the plan in order (writing phantom cases not on disk yet);
    renders each method on its first case with ground truth (copied to outdir/renders/). Returns the
    rows. on_row(rows so far), if given, is called after each run (the bench keeps a results.csv
    of the finished runs, so a bench stopped part way still leaves them)."""
    rows, rendered = [], set()
    for i, (spec, case) in enumerate(plan, 1):
        render = case.truth_mesh is not None and spec.label not in rendered
        if render:
            rendered.add(spec.label)
        ensure_case_files(case)
        task = make_task(spec, case, outdir, metric_samples, device, render)
        log(f"[{i}/{len(plan)}] {spec.label} on {case.name} (seed {case.seed}) ...")
        row = run_task(task, timeout_s)
        rows.append(row)
        if on_row is not None:
            on_row(rows)
        copy_render(task, outdir)
        log(f"    {row_summary(row)}")
    return rows


def copy_render(task: dict, outdir: Path) -> Path | None:
    """Copy a run's render.png to outdir/renders/<method>__<case>.png (None when there is none)."""
    src = Path(task["rundir"]) / "render.png"
    if not src.exists():
        return None
    dst = Path(outdir) / "renders" / f"{slug(task['spec']['label'])}__{slug(task['case']['name'])}.png"
    dst.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(src, dst)
    return dst


def row_summary(row: dict) -> str:
    """One line: status, time, CD-L1, F-score, separation, skeleton, ms/iteration, peak memory."""
    if row.get("status") != "ok":
        return f"{row.get('status')}: {row.get('note', '')}"
    parts = ["ok", f"{num(row.get('time_total_s')):.1f} s"]
    if finite(row.get("cd_l1_mm")):
        parts.append(f"CD-L1 {row['cd_l1_mm']:.3f} mm ({row['reference']}), F@{FSCORE_TAU_MM:g}mm {row['fscore']:.3f}")
    if finite(row.get("n_separable")):
        parts.append(f"{row.get('n_isolated')}/{row['n_separable']} separable ribs isolated")
    if finite(row.get("skel_mean_dist_mm")):
        parts.append(f"skeleton mean {row['skel_mean_dist_mm']:.2f} mm")
    if finite(row.get("ms_per_iteration")):
        parts.append(f"{row['ms_per_iteration']:.1f} ms/it")
    parts.append(f"peak {num(row.get('peak_rss_mb')):.0f} MB")
    return ", ".join(parts)
