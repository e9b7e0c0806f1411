"""Orthanc auto-route to RibPull: a script for Orthanc's Python plugin (Debian: orthanc-python).

When a DICOM SEG series with rib segments becomes stable in Orthanc (a segmenter such as
TotalSegmentator stored it), post a RibPull job that names the series by DICOMweb and asks RibPull to
store its results (seg.dcm, measurements_sr.dcm, mesh_stl.dcm) back into the same study by STOW-RS.

In orthanc.json:  "Plugins": [".../libOrthancDicomWeb.so", ".../libOrthancPython.so"],
                  "PythonScript": "/path/to/orthanc_autoroute.py"
In Orthanc's environment:
  RIBPULL_URL              RibPull's API, e.g. http://ribpull:8000
  RIBPULL_API_KEY          a key of RIBPULL_API_KEYS (optional)
  RIBPULL_PACS_DICOMWEB    this Orthanc's DICOMweb root as RibPull reaches it, e.g. http://orthanc:8042/dicom-web
                           (RibPull must list it in RIBPULL_DICOMWEB_URLS)
  RIBPULL_DELIVER_DICOMWEB where the results go (default: RIBPULL_PACS_DICOMWEB)
  RIBPULL_PARAMS           job params as JSON (default {})
RibPull's own objects (Manufacturer "RibPull") never trigger a job, and the SEG's SeriesInstanceUID is
the job's Idempotency-Key, so a series that becomes stable twice is fitted once.
"""

import json
import os
import urllib.error
import urllib.request

import orthanc

RIB_CODE = "113197003"  # SNOMED CT "Rib"


def _is_rib_seg(series: dict) -> bool:
    tags = series.get("MainDicomTags", {})
    if tags.get("Modality") != "SEG" or tags.get("Manufacturer") == "RibPull" or not series.get("Instances"):
        return False
    instance = json.loads(orthanc.RestApiGet(f"/instances/{series['Instances'][0]}/simplified-tags"))
    for segment in instance.get("SegmentSequence", []):
        label = f"{segment.get('SegmentLabel', '')} {segment.get('TrackingID', '')}".lower()
        codes = [c.get("CodeValue") for c in segment.get("SegmentedPropertyTypeCodeSequence", [])]
        if "rib" in label or RIB_CODE in codes:
            return True
    return False


def _post_job(study_uid: str, series_uid: str) -> None:
    pacs = os.environ["RIBPULL_PACS_DICOMWEB"]
    body = {"source": {"dicomweb": {"url": pacs, "study_uid": study_uid, "series_uid": series_uid}},
            "params": json.loads(os.environ.get("RIBPULL_PARAMS") or "{}"),
            "deliver": {"dicomweb": {"url": os.environ.get("RIBPULL_DELIVER_DICOMWEB") or pacs}}}
    headers = {"Content-Type": "application/json", "Idempotency-Key": f"orthanc-{series_uid}"}
    if os.environ.get("RIBPULL_API_KEY"):
        headers["Authorization"] = f"Bearer {os.environ['RIBPULL_API_KEY']}"
    req = urllib.request.Request(os.environ["RIBPULL_URL"].rstrip("/") + "/v1/jobs",
                                 data=json.dumps(body).encode(), headers=headers, method="POST")
    try:
        with urllib.request.urlopen(req, timeout=30) as r:
            job = json.loads(r.read())
        orthanc.LogWarning(f"RibPull job {job['id']} for SEG series {series_uid}: {job['status']}")
    except urllib.error.HTTPError as exc:
        orthanc.LogError(f"RibPull refused the job for {series_uid}: {exc.code} {exc.read()[:500]!r}")
    except OSError as exc:
        orthanc.LogError(f"RibPull is not reachable for {series_uid}: {exc}")


def _on_stable_series(series_id: str) -> None:
    try:
        series = json.loads(orthanc.RestApiGet(f"/series/{series_id}"))
        if not _is_rib_seg(series):
            orthanc.LogInfo(f"RibPull auto-route: series {series_id} is no rib SEG from a segmenter; skipped")
            return
        study = json.loads(orthanc.RestApiGet(f"/studies/{series['ParentStudy']}"))
        _post_job(study["MainDicomTags"]["StudyInstanceUID"], series["MainDicomTags"]["SeriesInstanceUID"])
    except Exception as exc:  # noqa: BLE001 - a failed hook must never disturb Orthanc
        orthanc.LogError(f"RibPull auto-route failed for series {series_id}: {exc}")


def on_change(change_type, level, resource_id):
    # synchronous: the plugin only runs Python while a callback does (a thread started here would
    # starve); the POST is quick, RibPull queues the job and answers at once
    if change_type == orthanc.ChangeType.STABLE_SERIES:
        _on_stable_series(resource_id)


orthanc.RegisterOnChangeCallback(on_change)
