"""Job files on disk, and the artifact store: the one interface through which outputs are published,
read and deleted (so an object store can replace the local directories later).

    <storage>/ribpull.db                      SQLite job store (default)
    <storage>/uploads/<tmp>/                  uploads being received / validated
    <storage>/jobs/<id>/input/<filename>      the validated input
    <storage>/jobs/<id>/.work-<token>/        a running attempt's output (private to that attempt)
    <storage>/jobs/<id>/artifacts-<token>/    an attempt's finished outputs, published with one rename
    <storage>/jobs/<id>/artifacts/            the outputs of jobs from before revision 0002

Every attempt of a job (a claim token, app/state.py) writes only under its own token, and the job row
names the winning attempt (`jobs.artifacts_ref`) in the same compare-and-swap that marks it succeeded.
So with several workers on one shared storage directory (NFS, a shared volume) a slow or duplicate
attempt can never half-write, replace or delete the artifacts a finished job serves: rename within one
directory is atomic, the published name is unique, and losers only remove their own files.
"""

from __future__ import annotations

import os
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
    "seg.dcm": "application/dicom",
    "measurements_sr.dcm": "application/dicom",
    "mesh_stl.dcm": "application/dicom",
    "study_ct.zip": "application/zip",
}

JOB_ID_RE = re.compile(r"^[0-9a-f]{32}$")
_REF_RE = re.compile(r"^[0-9a-f]{32}$")  # artifacts refs are claim tokens (uuid4 hex)
_SAFE_NAME_RE = re.compile(r"[^A-Za-z0-9._-]+")


def media_type(name: str) -> str:
    return ARTIFACT_MEDIA_TYPES.get(name, "application/octet-stream")


def job_dir(settings: Settings, job_id: str) -> Path:
    if not JOB_ID_RE.match(job_id):  # never build a path from an unchecked id
        raise ValueError("bad job id")
    return settings.jobs_dir / job_id


def input_dir(settings: Settings, job_id: str) -> Path:
    return job_dir(settings, job_id) / "input"


def artifacts_dir(settings: Settings, job_id: str, ref: str | None = None) -> Path:
    """Published outputs of attempt `ref`; None = the single directory of jobs before revision 0002."""
    if ref is None:
        return job_dir(settings, job_id) / "artifacts"
    if not _REF_RE.match(ref):
        raise ValueError("bad artifacts ref")
    return job_dir(settings, job_id) / f"artifacts-{ref}"


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


class LocalArtifactStore:
    """Artifacts as directories under <storage>/jobs/<id>/ (see the module docstring).

    The interface an object store would implement too: `work_dir` (local scratch an attempt writes
    into), `publish` (make that attempt's outputs visible, all at once, never replacing another's),
    `discard` / `keep_only` (remove one attempt's / every other attempt's files), `local_dir` (where
    the API reads a published set: an object store would fetch it into a local cache there) and
    `delete_job`.
    """

    def __init__(self, settings: Settings):
        self.settings = settings

    def work_dir(self, job_id: str, ref: str) -> Path:
        if not _REF_RE.match(ref):
            raise ValueError("bad artifacts ref")
        return job_dir(self.settings, job_id) / f".work-{ref}"

    def local_dir(self, job_id: str, ref: str | None) -> Path:
        return artifacts_dir(self.settings, job_id, ref)

    def publish(self, job_id: str, ref: str) -> list[str]:
        """Move attempt `ref`'s work dir to its published name in one rename; the artifact names in it.
        The name is unique to the attempt, so this never overwrites anything (rename fails if it exists)."""
        final = self.local_dir(job_id, ref)
        os.rename(self.work_dir(job_id, ref), final)
        return [n for n in ARTIFACT_MEDIA_TYPES if (final / n).is_file()]

    def discard(self, job_id: str, ref: str) -> None:
        """Remove attempt `ref`'s files (work dir and published outputs) and nobody else's."""
        rmtree_quiet(self.work_dir(job_id, ref))
        rmtree_quiet(self.local_dir(job_id, ref))

    def keep_only(self, job_id: str, ref: str | None) -> None:
        """Once the job is final: remove what other (crashed or lost) attempts left behind."""
        jdir = job_dir(self.settings, job_id)
        keep = self.local_dir(job_id, ref).name if ref else None
        try:
            entries = list(jdir.iterdir())
        except OSError:
            return
        for p in entries:
            if p.name != keep and (p.name == "artifacts" or p.name.startswith(("artifacts-", ".work-", ".ribpull-"))):
                rmtree_quiet(p)

    def delete_job(self, job_id: str) -> None:
        """Every file of the job: input and artifacts (DELETE of a finished job)."""
        rmtree_quiet(job_dir(self.settings, job_id))


def artifact_store(settings: Settings) -> LocalArtifactStore:
    """The configured artifact store (local directories; the place to choose an object store later)."""
    return LocalArtifactStore(settings)
