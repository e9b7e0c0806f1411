"""The worker's DICOMweb client side (dicomweb-client): fetch a job's SEG series from the PACS by
WADO-RS (and check by QIDO-RS that the series it was made from is there too), and store the DICOM
results into the source's study by STOW-RS.

Every URL is checked against RIBPULL_DICOMWEB_URLS again right before it is used (the API checked it
at submission); the optional RIBPULL_DICOMWEB_AUTHORIZATION header is sent with each request and is
never written to the job record. Failures raise DicomwebError(code, message, retryable): the job (or
its delivery) records the code; a retryable delivery is tried again later without refitting.
"""

from __future__ import annotations

import logging
from pathlib import Path

from app.netpolicy import dicomweb_target_problem
from app.settings import Settings

log = logging.getLogger("ribpull.worker")

SEG_SOP_CLASS_UID = "1.2.840.10008.5.1.4.1.1.66.4"
#: the DICOM results stored into the PACS, in this order (ribpull_core.dicom.export.DICOM_ARTIFACTS)
DELIVERED_ARTIFACTS = ("seg.dcm", "measurements_sr.dcm", "mesh_stl.dcm")


class DicomwebError(Exception):
    """A PACS problem: `code` (job error code), `message` (what to fix), `retryable` (worth another try)."""

    def __init__(self, code: str, message: str, retryable: bool = False):
        super().__init__(message)
        self.code, self.message, self.retryable = code, message, retryable


def client(url: str, settings: Settings):
    """A DICOMweb client for `url` after the target check, with the configured Authorization header."""
    from dicomweb_client.api import DICOMwebClient

    why = dicomweb_target_problem(url, settings)
    if why:
        raise DicomwebError("dicomweb_refused", f"{url[:200]} is not an allowed DICOMweb server: {why}")
    headers = {"Authorization": settings.dicomweb_authorization} if settings.dicomweb_authorization else None
    web = DICOMwebClient(url, headers=headers, timeout=settings.dicomweb_timeout_s)
    # no silent in-request retries (dicomweb-client would wait up to ~30 s inside the worker): a
    # failed request is one attempt, and the delivery's own back-off through the queue decides
    web.set_http_retry_params(retry=False)
    return web


def _http_error(exc: Exception, what: str, not_found_code: str) -> DicomwebError:
    """Map a requests / dicomweb-client exception onto a DicomwebError."""
    import requests

    if isinstance(exc, requests.HTTPError) and exc.response is not None:
        status = exc.response.status_code
        if status == 404:
            return DicomwebError(not_found_code, f"{what}: the PACS answered 404 (not found)")
        if status in (401, 403):
            return DicomwebError("dicomweb_unauthorized", f"{what}: the PACS answered {status}; check "
                                                          "RIBPULL_DICOMWEB_AUTHORIZATION")
        return DicomwebError("dicomweb_error", f"{what}: the PACS answered HTTP {status}", retryable=status >= 500)
    if isinstance(exc, (requests.ConnectionError, requests.Timeout)):
        return DicomwebError("dicomweb_unreachable", f"{what}: the PACS did not answer ({type(exc).__name__})",
                             retryable=True)
    return DicomwebError("dicomweb_error", f"{what}: {type(exc).__name__}: {str(exc)[:300]}")


def fetch_seg(source: dict, settings: Settings, dest_dir: Path) -> Path:
    """Retrieve the SEG series named by source["dicomweb"] into dest_dir/seg.dcm (the job's input) and
    check that the series it references (the CT) is in the same study. Returns the file's path."""
    ref = source["dicomweb"]
    study, series = ref["study_uid"], ref["series_uid"]
    web = client(ref["url"], settings)
    try:
        instances = web.retrieve_series(study, series)
    except Exception as exc:  # noqa: BLE001 - any transport problem is the job's error
        raise _http_error(exc, f"retrieving series {series} of study {study}", "source_not_found") from None
    if not instances:
        raise DicomwebError("source_not_found", f"series {series} of study {study} is empty or not on the PACS")
    segs = [ds for ds in instances if str(getattr(ds, "SOPClassUID", "")) == SEG_SOP_CLASS_UID]
    if not segs:
        kinds = sorted({getattr(getattr(ds, "SOPClassUID", None), "name", "?") for ds in instances})
        raise DicomwebError("source_not_seg", f"series {series} holds {', '.join(kinds)}, not a Segmentation "
                                              "(SEG); name the rib SEG series")
    seg = segs[0]  # one SEG instance per series is the norm (TotalSegmentator writes one)
    nbytes = len(seg.get("PixelData", b"") or b"")
    if nbytes > settings.max_upload_bytes:
        raise DicomwebError("too_large", f"the SEG's pixel data is {nbytes / 2**20:.0f} MiB, over this server's "
                                         f"limit of {settings.max_upload_mb:g} MiB (RIBPULL_MAX_UPLOAD_MB)")
    for item in seg.get("ReferencedSeriesSequence") or []:
        uid = str(item.SeriesInstanceUID)
        try:
            found = web.search_for_series(study, search_filters={"SeriesInstanceUID": uid})
        except Exception as exc:  # noqa: BLE001
            raise _http_error(exc, f"looking up the referenced series {uid}", "referenced_series_missing") from None
        if not found:
            raise DicomwebError(
                "referenced_series_missing",
                f"the SEG references series {uid}, which is not in study {study} on the PACS; store the CT "
                "series the segmentation was made from")
    dest_dir.mkdir(parents=True, exist_ok=True)
    path = dest_dir / "seg.dcm"
    tmp = dest_dir / ".seg.dcm.part"
    seg.save_as(str(tmp), enforce_file_format=True)
    tmp.replace(path)  # a partial download never looks like an input
    log.info("fetched SEG %s (%d bytes) of series %s", seg.SOPInstanceUID, path.stat().st_size, series)
    return path


def store_results(url: str, study_uid: str, artifacts_dir: Path, settings: Settings) -> list[str]:
    """STOW-RS the DICOM artifacts of a finished job into `study_uid`; returns their SOP Instance UIDs."""
    import pydicom

    paths = [artifacts_dir / n for n in DELIVERED_ARTIFACTS if (artifacts_dir / n).is_file()]
    if not paths:
        raise DicomwebError("nothing_to_deliver", "the job produced no DICOM results to store")
    datasets = [pydicom.dcmread(str(p)) for p in paths]
    web = client(url, settings)
    try:
        answer = web.store_instances(datasets, study_instance_uid=study_uid)
    except Exception as exc:  # noqa: BLE001
        raise _http_error(exc, f"storing the results into study {study_uid}", "study_not_found") from None
    failed = answer.get("FailedSOPSequence") if answer is not None else None
    if failed:
        reasons = sorted({str(item.get("FailureReason", "?")) for item in failed})
        raise DicomwebError("stow_refused", f"the PACS refused {len(failed)} of {len(datasets)} instances "
                                            f"(failure reasons {', '.join(reasons)})")
    sent = [str(ds.SOPInstanceUID) for ds in datasets]
    stored = {str(item.get("ReferencedSOPInstanceUID", "")) for item in
              (answer.get("ReferencedSOPSequence") or [] if answer is not None else [])}
    if not set(sent) <= stored:  # a 200 that does not confirm every instance is not a delivery
        raise DicomwebError("stow_incomplete", f"the PACS confirmed {len(stored & set(sent))} of {len(sent)} "
                                               "instances in its STOW-RS answer", retryable=True)
    return sent
