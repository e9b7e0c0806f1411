"""A real Orthanc PACS with its DICOMweb plugin on a loopback port, for the DICOMweb tests.

Debian ships `orthanc` and `orthanc-dicomweb` (and `orthanc-python`); `ensure_orthanc()` installs them
with apt-get when missing and this process is root, else the tests skip with the reason. Each
`Orthanc` runs from a temp directory (config, storage, index) with DIMSE and remote access off.
`require_dcmtk()` does the same for DCMTK's `dcmdump`, which the DICOM output tests parse with.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import time
from pathlib import Path

import httpx

from app import launcher

PLUGIN_DIR = Path("/usr/share/orthanc/plugins")
PACKAGES = ("orthanc", "orthanc-dicomweb")
_install_error: list[str] = []


def ensure_orthanc(extra_packages: tuple[str, ...] = ()) -> str | None:
    """None when Orthanc (and the packages asked for) are usable; else why not (for pytest.skip)."""
    wanted = PACKAGES + tuple(extra_packages)
    plugins = {"orthanc-dicomweb": "libOrthancDicomWeb.so", "orthanc-python": "libOrthancPython.so"}
    missing = [p for p in wanted if (p == "orthanc" and shutil.which("Orthanc") is None)
               or (p in plugins and not (PLUGIN_DIR / plugins[p]).exists())]
    return apt_install(missing)


def require_dcmtk() -> None:
    """Return when DCMTK's `dcmdump` is on PATH (installing Debian's dcmtk if need be); else skip
    the calling test loudly, with the reason."""
    why = apt_install([] if shutil.which("dcmdump") else ["dcmtk"])
    if why:
        import pytest

        pytest.skip(f"NO DCMTK TO CHECK THE DICOM OUTPUTS WITH: {why}")


def apt_install(missing: list[str]) -> str | None:
    """Install the Debian packages `missing` with apt-get (root only; `apt-get update` and a retry
    when the first try fails). None when there is nothing missing or the install worked, else why
    not. A failure is remembered, so later callers skip at once instead of retrying."""
    if not missing:
        return None
    failed = [e for e in _install_error if any(p in e for p in missing)]
    if failed:
        return failed[0]
    if os.geteuid() != 0 or shutil.which("apt-get") is None:
        return f"{', '.join(missing)} not installed and apt-get cannot run here (not root / no apt)"
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    for cmd in (["apt-get", "install", "-y", "--no-install-recommends", *missing],
                ["apt-get", "update"], ["apt-get", "install", "-y", "--no-install-recommends", *missing]):
        r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=900, check=False)
        if r.returncode == 0 and cmd[1] == "install":
            return None
    _install_error.append(f"apt-get install {' '.join(missing)} failed: {r.stderr[-500:]}")
    return _install_error[-1]


class Orthanc:
    """One throw-away Orthanc: `url` (REST), `dicomweb` (DICOMweb root); `upload`, `study_series`, `stop`.
    env: extra environment of the Orthanc process ("{port}" in a value becomes its HTTP port)."""

    def __init__(self, root: Path, plugins: list[Path] | None = None, extra_config: dict | None = None,
                 env: dict[str, str] | None = None):
        self.root = root
        root.mkdir(parents=True, exist_ok=True)
        self.port = launcher.free_port()
        config = {
            "Name": "ribpull-test", "HttpPort": self.port, "DicomServerEnabled": False,
            "RemoteAccessAllowed": False, "AuthenticationEnabled": False,
            "StorageDirectory": str(root / "storage"), "IndexDirectory": str(root / "index"),
            "Plugins": [str(PLUGIN_DIR / "libOrthancDicomWeb.so"), *(str(p) for p in plugins or [])],
            "DicomWeb": {"Enable": True, "Root": "/dicom-web/"},
            "StableAge": 1,
        }
        config.update(extra_config or {})
        (root / "orthanc.json").write_text(json.dumps(config, indent=2))
        self.proc = launcher.spawn([shutil.which("Orthanc") or "Orthanc", str(root / "orthanc.json")],
                                   env={**os.environ, **{k: v.replace("{port}", str(self.port)) for k, v in (env or {}).items()}},
                                   log_path=root / "orthanc.log", cwd=root)
        launcher.wait_http(self.url + "/system", 60, self.proc)

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    @property
    def dicomweb(self) -> str:
        return self.url + "/dicom-web"

    def upload(self, paths) -> list[str]:
        """POST each DICOM file to /instances; returns Orthanc's instance ids."""
        ids = []
        with httpx.Client(timeout=60) as c:
            for p in paths:
                r = c.post(self.url + "/instances", content=Path(p).read_bytes())
                r.raise_for_status()
                ids.append(r.json()["ID"])
        return ids

    def study_series(self, study_uid: str) -> list[dict]:
        """QIDO-RS: the series of a study (DICOM JSON)."""
        r = httpx.get(f"{self.dicomweb}/studies/{study_uid}/series", timeout=30)
        r.raise_for_status()
        return r.json() if r.content else []

    def log(self) -> str:
        p = self.root / "orthanc.log"
        return p.read_text(errors="replace")[-4000:] if p.exists() else ""

    def stop(self) -> None:
        launcher.stop(self.proc, timeout=15)


def wait_until(predicate, timeout: float, what: str, interval: float = 0.3, detail=None):
    """Poll predicate() until it returns something truthy; AssertionError (with detail()) after timeout."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        got = predicate()
        if got:
            return got
        time.sleep(interval)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}" + (f"\n{detail()}" if detail else ""))
