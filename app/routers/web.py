"""The web page: `/` (upload form + the key's jobs), `/jobs/{id}` (progress, 3D view, metrics,
downloads) and its static files under `/ui/`.

The pages hold no data: their scripts call the public API (`/v1/...`) with the key the user entered
(kept in sessionStorage), so these routes need no key. They are left out of the OpenAPI schema (they
are not part of the API contract). Every page and file is sent with a strict Content-Security-Policy:
scripts only from this origin plus the one inline import map (allowed by its hash), no framing, no
plugins, network access only to this origin; three.js is vendored by scripts/build_web.py, no CDN.
"""

from __future__ import annotations

import base64
import hashlib
import re
from pathlib import Path
from typing import Annotated

from fastapi import APIRouter
from fastapi import Path as PathParam
from fastapi.responses import FileResponse

from ..problems import ProblemError

STATIC_DIR = Path(__file__).resolve().parent.parent / "web" / "static"
PAGES = {"index": STATIC_DIR / "index.html", "job": STATIC_DIR / "job.html"}
STATIC_MEDIA_TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8",
                      ".css": "text/css; charset=utf-8", ".png": "image/png", ".svg": "image/svg+xml",
                      "": "text/plain; charset=utf-8"}  # "": LICENSE
_IMPORT_MAP_RE = re.compile(r'<script type="importmap">(.*?)</script>', re.DOTALL)
_STATIC_PATH_RE = re.compile(r"^[A-Za-z0-9_.-]+(/[A-Za-z0-9_.-]+)*$")

router = APIRouter(include_in_schema=False)


def import_map_hashes() -> list[str]:
    """CSP source expressions ('sha256-...') of the inline import maps of the pages."""
    out = set()
    for page in PAGES.values():
        for body in _IMPORT_MAP_RE.findall(page.read_text(encoding="utf-8")):
            out.add("'sha256-" + base64.b64encode(hashlib.sha256(body.encode()).digest()).decode() + "'")
    return sorted(out)


CONTENT_SECURITY_POLICY = "; ".join([
    "default-src 'none'",
    "script-src 'self' " + " ".join(import_map_hashes()),
    "style-src 'self'",
    "img-src 'self' data: blob:",  # GLTFLoader hands embedded textures to the GPU through object URLs
    "connect-src 'self'",
    "base-uri 'none'",
    "form-action 'self'",
    "frame-ancestors 'none'",
])
PAGE_HEADERS = {
    "Content-Security-Policy": CONTENT_SECURITY_POLICY,
    "X-Frame-Options": "DENY",
    "Referrer-Policy": "no-referrer",
    "Cross-Origin-Opener-Policy": "same-origin",
    "Cache-Control": "no-cache",  # revalidate (ETag) so a new build is picked up at once
}


def _file(path: Path) -> FileResponse:
    return FileResponse(path, media_type=STATIC_MEDIA_TYPES.get(path.suffix, "application/octet-stream"),
                        headers=PAGE_HEADERS)


@router.get("/")
def index_page() -> FileResponse:
    """Upload form and the key's jobs."""
    return _file(PAGES["index"])


@router.get("/jobs/{job_id}")
def job_page(job_id: Annotated[str, PathParam(max_length=64)]) -> FileResponse:
    """One job: progress, 3D view, metrics, downloads (an unknown id is reported by the page, from the API)."""
    del job_id  # the page reads it from its own URL
    return _file(PAGES["job"])


@router.get("/ui/{path:path}")
def static_file(path: Annotated[str, PathParam(max_length=200)]) -> FileResponse:
    """A file of app/web/static (names of letters, digits, `._-` only: no traversal, no dot files)."""
    target = STATIC_DIR / path
    if (not _STATIC_PATH_RE.match(path) or any(part.startswith(".") for part in path.split("/"))
            or not target.is_file() or target.suffix not in STATIC_MEDIA_TYPES):
        hint = " (three.js is vendored by `make web`)" if path.startswith("vendor/") else ""
        raise ProblemError(404, "not_found", f"no web file '{path[:200]}'{hint}")
    return _file(target)
