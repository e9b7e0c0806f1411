"""Request and response models of the HTTP API (they define the OpenAPI schema)."""

from __future__ import annotations

import math
from datetime import datetime
from typing import Annotated, Any, Literal
from urllib.parse import urlsplit

from pydantic import BaseModel, ConfigDict, Field, field_validator

#: must equal ribpull_core.methods.RUN_PRESETS / METHOD_CLASSES (a test checks); kept literal here so
#: the API does not import torch just to validate a form field
PRESETS = ("default", "paper", "smoke")
METHODS = ("sparseocc", "neuralpull", "digs")

Preset = Literal["default", "paper", "smoke"]
MethodName = Literal["sparseocc", "neuralpull", "digs"]
Status = Literal["queued", "running", "succeeded", "failed", "canceled"]
Label = Annotated[int, Field(ge=1, le=255)]
Units = Literal["mm", "cm", "m"]


class JobParams(BaseModel):
    """Options of one job, sent as the JSON text of the multipart field `params`.

    Every field is optional. Types are strict: `"iterations": "100"` or `"labels": [1.5]` are rejected.
    """

    model_config = ConfigDict(extra="forbid", strict=True)

    preset: Preset | None = Field(None, description="Run preset (default: the server's RIBPULL_DEFAULT_PRESET).")
    method: MethodName | None = Field(None, description="Override the preset's method.")
    iterations: int | None = Field(
        None, ge=1, le=100_000, description="Override the fit's iteration count (server cap: RIBPULL_MAX_ITERATIONS, "
                                            "default 40000).")
    resolution: int | None = Field(
        None, ge=16, le=1024, description="Finest marching-cubes resolution (server cap: the largest grid that fits "
                                          "RIBPULL_WORKER_MEMORY_MB, at most RIBPULL_MAX_RESOLUTION, default 512).")
    labels: list[Label] | None = Field(
        None, min_length=1, max_length=255, description="NIfTI label values to keep (1..255)."
    )
    skeleton: bool = Field(True, description="Also extract the rib skeleton.")
    preview: bool = Field(True, description="Also render preview.png.")
    dicom_outputs: bool = Field(
        False, description="A NIfTI label map also gets the DICOM outputs (seg.dcm, measurements_sr.dcm, mesh_stl.dcm, "
                           "in the LPS patient frame) on a generated CT study, study_ct.zip. A DICOM SEG input gets "
                           "them anyway; a point cloud is refused (422 dicom_outputs_need_label_map).")
    seed: int = Field(0, ge=0, le=2**31 - 1)
    units: Units = Field(
        "mm", description="Unit of the input's coordinates (point clouds) or affine (NIfTI): mm, cm or m. The "
                          "input is converted to mm on load; every output is in mm in the input's frame.")
    webhook_url: str | None = Field(
        None, max_length=2048, description="http(s) URL that receives a signed POST when the job finishes."
    )

    @field_validator("webhook_url")
    @classmethod
    def _url(cls, v: str | None) -> str | None:
        if v is None:
            return v
        if any(c.isspace() or ord(c) < 32 for c in v):
            raise ValueError("webhook_url must not contain spaces or control characters")
        try:
            parts = urlsplit(v)
            port = parts.port  # raises ValueError for a bad port
        except ValueError as exc:
            raise ValueError(f"webhook_url is not a valid URL: {exc}") from None
        if parts.scheme not in ("http", "https") or not parts.hostname:
            raise ValueError("webhook_url must be an absolute http:// or https:// URL")
        del port
        return v

    @field_validator("labels")
    @classmethod
    def _labels(cls, v: list[int] | None) -> list[int] | None:
        return sorted(set(v)) if v else v


def _http_url(v: str, what: str) -> str:
    if any(c.isspace() or ord(c) < 32 for c in v):
        raise ValueError(f"{what} must not contain spaces or control characters")
    try:
        parts = urlsplit(v)
        parts.port  # noqa: B018 - raises ValueError for a bad port
    except ValueError as exc:
        raise ValueError(f"{what} is not a valid URL: {exc}") from None
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise ValueError(f"{what} must be an absolute http:// or https:// URL")
    return v


#: a DICOM UID: dot-separated numbers, at most 64 characters
DicomUID = Annotated[str, Field(pattern=r"^[0-9]+(\.[0-9]+)*$", max_length=64)]


class DicomwebSeries(BaseModel):
    """A series on a DICOMweb server: the job's input (a DICOM SEG series, retrieved by WADO-RS)."""

    model_config = ConfigDict(extra="forbid", strict=True)

    url: str = Field(..., max_length=2048, description="DICOMweb base URL, e.g. http://pacs:8042/dicom-web "
                                                       "(must be under one of RIBPULL_DICOMWEB_URLS).")
    study_uid: DicomUID = Field(..., description="StudyInstanceUID of the study holding the SEG.")
    series_uid: DicomUID = Field(..., description="SeriesInstanceUID of the rib SEG series.")

    @field_validator("url")
    @classmethod
    def _url(cls, v: str) -> str:
        return _http_url(v, "url")


class DicomwebTarget(BaseModel):
    """Where the results are stored by STOW-RS (into the source's study)."""

    model_config = ConfigDict(extra="forbid", strict=True)

    url: str = Field(..., max_length=2048, description="DICOMweb base URL (under one of RIBPULL_DICOMWEB_URLS).")

    @field_validator("url")
    @classmethod
    def _url(cls, v: str) -> str:
        return _http_url(v, "url")


class JobSource(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)

    dicomweb: DicomwebSeries


class JobDeliver(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)

    dicomweb: DicomwebTarget


class DicomwebJobIn(BaseModel):
    """A job that names its input on a PACS instead of uploading it (JSON body of POST /v1/jobs)."""

    model_config = ConfigDict(extra="forbid", strict=True)

    source: JobSource
    params: JobParams = Field(default_factory=JobParams)
    deliver: JobDeliver | None = Field(None, description="Store seg.dcm, measurements_sr.dcm and mesh_stl.dcm "
                                                         "into the source's study when the job succeeds.")


class Progress(BaseModel):
    stage: str | None = Field(None, description="load|fit|mesh|sdf|skeleton|metrics|export|done")
    fraction: float = Field(0.0, description="Overall progress in [0, 1].")
    iteration: int | None = None
    iterations: int | None = None
    loss: float | None = None
    message: str = ""


class ErrorInfo(BaseModel):
    code: str
    message: str


class ArtifactLink(BaseModel):
    name: str
    href: str
    media_type: str
    bytes: int


class InputInfo(BaseModel):
    filename: str
    format: str
    bytes: int
    sha256: str
    points: int


class WebhookInfo(BaseModel):
    url: str
    status: str | None = Field(None, description="pending | delivered | failed")
    attempts: int = 0
    error: str | None = None


class DeliveryInfo(BaseModel):
    url: str
    status: str | None = Field(None, description="pending | delivered | failed")
    attempts: int = 0
    error: str | None = Field(None, description="`<code>: <message>` of the last failed attempt")


class JobOut(BaseModel):
    id: str
    status: Status
    created_at: datetime
    updated_at: datetime
    started_at: datetime | None = None
    finished_at: datetime | None = None
    params: dict[str, Any]
    input: InputInfo
    progress: Progress
    error: ErrorInfo | None = None
    attempts: int = Field(0, description="Times a worker started this job.")
    cancel_requested: bool = False
    artifacts: list[ArtifactLink] = Field(default_factory=list)
    artifacts_deleted: bool = Field(False, description="True after DELETE removed a finished job's files.")
    metrics: dict[str, Any] | None = None
    webhook: WebhookInfo | None = None
    source: dict[str, Any] | None = Field(None, description="The DICOMweb series a job named as its input.")
    delivery: DeliveryInfo | None = Field(None, description="STOW-RS delivery of the DICOM results.")
    links: dict[str, str] = Field(default_factory=dict)


class JobList(BaseModel):
    items: list[JobOut]
    next_cursor: str | None = Field(None, description="Pass as `cursor` for the next (older) page; null at the end.")
    limit: int


FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]


class QueryIn(BaseModel):
    model_config = ConfigDict(extra="forbid")

    points_mm: list[tuple[FiniteFloat, FiniteFloat, FiniteFloat]] = Field(
        ..., min_length=1, description="Points [x, y, z] in mm, in the input's frame (cap: RIBPULL_MAX_QUERY_POINTS)."
    )


class QueryOut(BaseModel):
    occupancy: list[float | None] = Field(..., description="Probability of being inside, per point.")
    U: list[float | None] = Field(..., description="Inside score p_in - p_out in [-1, 1] (paper's U).")
    inside: list[bool]
    sdf_mm: list[float | None] | None = Field(None, description="Signed distance in mm, negative inside.")


class Problem(BaseModel):
    """RFC 9457 problem details (application/problem+json) plus a machine-readable `code`."""

    type: str
    title: str
    status: int
    detail: str
    code: str
    instance: str | None = None
    errors: list[dict[str, Any]] | None = None


class Health(BaseModel):
    status: str


class Ready(BaseModel):
    status: str
    checks: dict[str, Any]


def finite_or_none(x: Any) -> float | None:
    try:
        f = float(x)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def json_safe(obj: Any) -> Any:
    """Replace NaN/inf by None recursively (JSON has no NaN; Postgres JSON rejects it)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if hasattr(obj, "item") and callable(obj.item):  # numpy scalar
        try:
            return json_safe(obj.item())
        except Exception:  # noqa: BLE001
            return str(obj)
    if isinstance(obj, (str, int, bool)) or obj is None:
        return obj
    return str(obj)
