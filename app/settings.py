"""Service configuration: every knob is an environment variable (prefix RIBPULL_, except PORT and
DATABASE_URL / REDIS_URL which are also read unprefixed, as PaaS platforms set them).

The API (`app.main`), the worker (`worker.celery_app`) and the launcher (`scripts/serve.py`) all read
the same `Settings`, so one environment configures the whole service. See docs/service.md for the
table of variables.
"""

from __future__ import annotations

import hashlib
import os
from functools import lru_cache
from pathlib import Path

from pydantic import AliasChoices, Field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

#: bytes per voxel of a res^3 marching-cubes grid the worker needs (measured: 9 GB at 1024^3)
RESOLUTION_BYTES_PER_VOXEL = 8.5


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="RIBPULL_", extra="ignore", populate_by_name=True)

    # --- where things live -----------------------------------------------------------------------
    storage_dir: Path = Field(Path("var/storage"), description="Uploads, artifacts (jobs/<id>/) and the SQLite file.")
    database_url: str | None = Field(
        None,
        validation_alias=AliasChoices("RIBPULL_DATABASE_URL", "DATABASE_URL", "database_url"),
        description="SQLAlchemy URL; default sqlite:///<storage_dir>/ribpull.db (WAL mode).",
    )
    redis_url: str = Field(
        "redis://127.0.0.1:6379/0",
        validation_alias=AliasChoices("RIBPULL_REDIS_URL", "REDIS_URL", "redis_url"),
        description="Celery broker and worker heartbeats.",
    )

    # --- HTTP --------------------------------------------------------------------------------------
    host: str = Field("127.0.0.1", description="Bind address of the API (scripts/serve.py).")
    port: int = Field(8000, validation_alias=AliasChoices("PORT", "RIBPULL_PORT", "port"), ge=1, le=65535,
                      description="API port (scripts/serve.py, the Docker image).")
    public_url: str = Field("", description="Absolute base URL used for links in webhooks (optional).")
    api_keys: str = Field("", description="Comma-separated bearer keys; empty = no authentication.")
    max_upload_mb: float = Field(256.0, gt=0, description="Upload size cap (MiB); larger uploads get 413.")
    max_points: int = Field(2_000_000, ge=100, description="Most points an input may have.")
    max_query_points: int = Field(100_000, ge=1, description="Most points one /query request may carry.")
    max_inflated_mb: float = Field(
        1024.0, gt=0, description="Most MiB a compressed upload (.nii.gz, gzip) may inflate to; checked while "
                                  "streaming, before anything is decompressed in full (413).")
    max_nifti_mb: float = Field(
        1024.0, gt=0, description="Most MiB of voxel data (dims x dtype from the NIfTI header) a label map may "
                                  "have; checked before any voxel is read (413).")
    body_timeout_s: float = Field(
        30.0, gt=0, description="A request whose headers or next body chunk take longer than this gets 408 "
                                "(slow clients; the partial upload is removed).")
    min_extent_mm: float = Field(50.0, gt=0, description="Smallest bounding-box size (mm, after `units`) "
                                                         "accepted as a ribcage (422 below it).")
    max_extent_mm: float = Field(2000.0, gt=0, description="Largest bounding-box size (mm, after `units`) "
                                                           "accepted as a ribcage (422 above it).")
    readyz_require_worker: bool = Field(True, description="/readyz fails while no worker heartbeat is seen.")
    log_level: str = Field("INFO", description="Python log level of the API and the worker.")

    # --- jobs ----------------------------------------------------------------------------------------
    job_timeout_s: int = Field(7200, ge=1, description="A running job is stopped (failed, code timeout) after this.")
    visibility_timeout_s: int | None = Field(
        None, ge=1, description="Redis visibility timeout; default job_timeout_s + 1800 (must exceed the longest job)."
    )
    max_attempts: int = Field(3, ge=1, description="Deliveries of one job before it is failed (worker_lost).")
    heartbeat_s: float = Field(10.0, gt=0, description="How often a running job refreshes its heartbeat.")
    stale_after_s: float | None = Field(
        None, gt=0, description="A running job whose heartbeat is older is re-queued; default max(6*heartbeat_s, 60)."
    )
    sweep_interval_s: float = Field(30.0, gt=0, description="How often each worker sweeps for stale jobs.")
    progress_interval_s: float = Field(1.0, ge=0, description="Minimum seconds between progress writes.")
    cancel_check_interval_s: float = Field(1.0, ge=0, description="Minimum seconds between cancel-flag reads.")
    device: str = Field("auto", description="Torch device for fits: auto, cpu or cuda.")
    torch_threads: int = Field(0, ge=0, description="torch.set_num_threads per worker process; 0 = cores / concurrency.")
    worker_concurrency: int = Field(1, ge=1, description="Celery worker processes (scripts/serve.py, compose).")
    worker_pool: str = Field("prefork", description="Celery pool for scripts/serve.py: prefork or solo.")
    default_preset: str = Field("default", description="Preset used when params omit it.")
    worker_memory_mb: int = Field(
        4096, ge=256, description="Memory one worker process may use (MiB); caps params.resolution (the largest "
                                  "grid that fits) and is the child's recycle threshold.")
    max_resolution: int = Field(
        512, ge=16, le=1024, description="Largest params.resolution accepted (also capped by "
                                         "RIBPULL_WORKER_MEMORY_MB).")
    max_iterations: int = Field(40_000, ge=1, description="Largest params.iterations accepted (the most any "
                                                          "preset uses is 40000).")
    worker_max_memory_mb: int | None = Field(
        None, ge=64, description="A worker child whose resident memory passes this after a job is replaced "
                                 "(Celery max-memory-per-child); default RIBPULL_WORKER_MEMORY_MB / 2.")
    cancel_grace_s: float = Field(1.0, gt=0, description="A cancel not honoured by the running stage within "
                                                         "this is enforced by ending the worker child.")
    pipeline: str = Field(
        "ribpull_core.pipeline:run_pipeline",
        description="module:function the worker calls (same signature as run_pipeline); leave as is.",
    )

    # --- webhooks -----------------------------------------------------------------------------------
    webhook_secret: str = Field("", description="Standard Webhooks signing secret (whsec_<base64> or raw text).")
    webhook_timeout_s: float = Field(10.0, gt=0, description="Timeout of one webhook POST.")
    webhook_max_attempts: int = Field(6, ge=1, description="Webhook attempts before giving up.")
    webhook_backoff_s: float = Field(5.0, ge=0, description="First retry delay; doubles each retry.")
    webhook_allowlist: str = Field(
        "", description="Comma-separated private networks/hosts (CIDR or IP) webhooks may target; loopback, "
                        "link-local and the service's own ports are always refused.")

    # --- DICOMweb (PACS) sources and delivery --------------------------------------------------------
    dicomweb_urls: str = Field(
        "", description="Comma-separated DICOMweb base URLs (e.g. http://pacs:8042/dicom-web) that jobs may name as "
                        "source or delivery target; a job's URL must start with one of them. Empty = no DICOMweb jobs.")
    dicomweb_authorization: str = Field(
        "", description="Authorization header value sent to the PACS (e.g. 'Basic dXNlcjpwdw=='); never stored in jobs.")
    dicomweb_timeout_s: float = Field(60.0, gt=0, description="Timeout of one WADO-RS / QIDO-RS / STOW-RS request.")
    dicomweb_max_attempts: int = Field(5, ge=1, description="STOW-RS delivery attempts before the delivery fails.")
    dicomweb_backoff_s: float = Field(5.0, ge=0, description="First delivery retry delay; doubles each retry.")

    @field_validator("device")
    @classmethod
    def _device(cls, v: str) -> str:
        v = v.strip().lower()
        if v not in ("auto", "cpu", "cuda") and not v.startswith("cuda:"):
            raise ValueError("device must be auto, cpu, cuda or cuda:N")
        return v

    @field_validator("default_preset")
    @classmethod
    def _preset(cls, v: str) -> str:
        from .schemas import PRESETS

        if v not in PRESETS:
            raise ValueError(f"default_preset must be one of {PRESETS}")
        return v

    @field_validator("worker_pool")
    @classmethod
    def _pool(cls, v: str) -> str:
        if v not in ("prefork", "solo", "threads"):
            raise ValueError("worker_pool must be prefork, solo or threads")
        return v

    # --- derived ---------------------------------------------------------------------------------------
    @property
    def db_url(self) -> str:
        if self.database_url:
            return normalize_db_url(self.database_url)
        return f"sqlite:///{self.storage_path / 'ribpull.db'}"

    @property
    def storage_path(self) -> Path:
        return Path(self.storage_dir).expanduser().resolve()

    @property
    def jobs_dir(self) -> Path:
        return self.storage_path / "jobs"

    @property
    def uploads_dir(self) -> Path:
        return self.storage_path / "uploads"

    @property
    def max_upload_bytes(self) -> int:
        return int(self.max_upload_mb * 1024 * 1024)

    @property
    def max_inflated_bytes(self) -> int:
        return int(self.max_inflated_mb * 1024 * 1024)

    @property
    def max_nifti_bytes(self) -> int:
        return int(self.max_nifti_mb * 1024 * 1024)

    @property
    def resolution_limit(self) -> int:
        """Largest grid the worker's memory allows: ~RESOLUTION_BYTES_PER_VOXEL per voxel of res^3 (measured:
        9 GB at 1024^3), using half of RIBPULL_WORKER_MEMORY_MB, rounded down to a multiple of 16."""
        fit = int((self.worker_memory_mb * 1024 * 1024 / 2 / RESOLUTION_BYTES_PER_VOXEL) ** (1 / 3))
        return max(16, min(self.max_resolution, fit - fit % 16))

    @property
    def max_memory_per_child_kib(self) -> int:
        return int((self.worker_max_memory_mb or max(64, self.worker_memory_mb // 2)) * 1024)

    @property
    def redis_port(self) -> int | None:
        from urllib.parse import urlsplit

        try:
            return urlsplit(self.redis_url).port or 6379
        except ValueError:
            return None

    @property
    def visibility_timeout(self) -> int:
        return int(self.visibility_timeout_s or (self.job_timeout_s + 1800))

    @property
    def stale_after(self) -> float:
        return float(self.stale_after_s or max(6 * self.heartbeat_s, 60.0))

    @property
    def key_hashes(self) -> set[str]:
        return {hash_key(k) for k in self.api_keys.split(",") if k.strip()}

    @property
    def auth_enabled(self) -> bool:
        return bool(self.key_hashes)

    @property
    def effective_torch_threads(self) -> int:
        if self.torch_threads > 0:
            return self.torch_threads
        return max(1, (os.cpu_count() or 1) // max(1, self.worker_concurrency))


def normalize_db_url(url: str) -> str:
    """postgres:// (Heroku-style) and postgresql:// name the installed driver, psycopg2 (SQLAlchemy 2.1's
    default for a bare postgresql:// is psycopg 3, which is not a dependency); other URLs pass as they are."""
    for prefix in ("postgres://", "postgresql://"):
        if url.startswith(prefix):
            return "postgresql+psycopg2://" + url[len(prefix):]
    return url


def hash_key(key: str) -> str:
    """Owner id stored with each job: SHA-256 of the bearer key (the key itself is never stored)."""
    return hashlib.sha256(key.strip().encode()).hexdigest()


@lru_cache(maxsize=1)
def get_settings() -> Settings:
    """Process-wide settings read once from the environment."""
    return Settings()


#: env var names the service reads (for docs and for the Docker/compose consistency tests)
def env_var_names() -> set[str]:
    names: set[str] = set()
    for name, field in Settings.model_fields.items():
        alias = field.validation_alias
        if isinstance(alias, AliasChoices):
            names.update(a for a in alias.choices if isinstance(a, str) and a.isupper())
        else:
            names.add("RIBPULL_" + name.upper())
    return names
