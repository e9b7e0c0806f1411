"""Artifacts on disk.

    <storage>/ribpull.db                      SQLite job store (default)
    <storage>/uploads/<tmp>/                  uploads being received / validated
    <storage>/jobs/<id>/input/<filename>      the validated input
    <storage>/jobs/<id>/.work-<token>/        a running attempt's output (removed when it ends)
    <storage>/jobs/<id>/artifacts/            the finished outputs, moved in with one rename
"""

from __future__ import annotations

import re
import shutil
from pathlib import Path

from .settings import Settings

#: media type per artifact name (documented in docs/service.md)
ARTIFACT_MEDIA_TYPES = {
    "mesh.ply": "application/x-ply",
    "mesh.stl": "model/stl",
    "mesh.obj": "model/obj",
    "mesh.glb": "model/gltf-binary",
    "sdf.nii.gz": "application/gzip",
    "model.safetensors": "application/octet-stream",
    "model.json": "application/json",
    "metrics.json": "application/json",
    "skeleton.json": "application/json",
    "skeleton.glb": "model/gltf-binary",
    "skeleton.obj": "model/obj",
    "scene.glb": "model/gltf-binary",
    "preview.png": "image/png",
}

JOB_ID_RE = re.compile(r"^[0-9a-f]{32}$")
_SAFE_NAME_RE = re.compile(r"[^A-Za-z0-9._-]+")


def media_type(name: str) -> str:
    return ARTIFACT_MEDIA_TYPES.get(name, "application/octet-stream")


def job_dir(settings: Settings, job_id: str) -> Path:
    if not JOB_ID_RE.match(job_id):  # never build a path from an unchecked id
        raise ValueError("bad job id")
    return settings.jobs_dir / job_id


def input_dir(settings: Settings, job_id: str) -> Path:
    return job_dir(settings, job_id) / "input"


def artifacts_dir(settings: Settings, job_id: str) -> Path:
    return job_dir(settings, job_id) / "artifacts"


def safe_filename(name: str | None, default: str = "input") -> str:
    """A harmless file name that keeps the user's extension (.nii.gz included)."""
    base = Path((name or "").replace("\\", "/")).name
    base = _SAFE_NAME_RE.sub("_", base).strip("._") or default
    if len(base) > 120:
        lower = base.lower()
        ext = ".nii.gz" if lower.endswith(".nii.gz") else Path(base).suffix[:16]
        base = base[: 120 - len(ext)] + ext
    return base


def input_file(settings: Settings, job_id: str) -> Path | None:
    d = input_dir(settings, job_id)
    if not d.is_dir():
        return None
    files = sorted(p for p in d.iterdir() if p.is_file())
    return files[0] if files else None


def rmtree_quiet(path: Path) -> None:
    shutil.rmtree(path, ignore_errors=True)


def ensure_dirs(settings: Settings) -> None:
    for d in (settings.storage_path, settings.jobs_dir, settings.uploads_dir):
        d.mkdir(parents=True, exist_ok=True)
