"""application/problem+json (RFC 9457) for every error the API returns.

`type` is `urn:ribpull:problem:<code>`; `code` repeats the short code (for RibPull input errors it is
the core's `RibPullInputError.code`). FastAPI's own 422/404/405 and unexpected exceptions go through
the same handlers, so a client only ever has to parse one error shape.
"""

from __future__ import annotations

import json
import logging
import os
import re
import sys
import tempfile
from http import HTTPStatus
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from sqlalchemy.exc import OperationalError as SQLAlchemyOperationalError
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect

log = logging.getLogger("ribpull.api")

PROBLEM_MEDIA_TYPE = "application/problem+json"
TYPE_PREFIX = "urn:ribpull:problem:"

#: RibPullInputError code -> HTTP status (anything else: 422)
INPUT_ERROR_STATUS = {"too_large": 413, "unknown_format": 415}

_STATUS_CODES = {
    400: "bad_request",
    401: "unauthorized",
    403: "forbidden",
    404: "not_found",
    405: "method_not_allowed",
    406: "not_acceptable",
    408: "request_timeout",
    409: "conflict",
    413: "too_large",
    415: "unsupported_media_type",
    416: "range_not_satisfiable",
    422: "validation_error",
    429: "too_many_requests",
    500: "internal_error",
    503: "unavailable",
}


class ProblemError(Exception):
    """Raise anywhere in a request to answer with a problem+json response."""

    def __init__(
        self,
        status: int,
        code: str,
        detail: str,
        *,
        title: str | None = None,
        headers: dict[str, str] | None = None,
        errors: list[dict[str, Any]] | None = None,
    ):
        super().__init__(detail)
        self.status = status
        self.code = code
        self.detail = detail
        self.title = title
        self.headers = headers or {}
        self.errors = errors


_ROOTS = "tmp|var|usr|home|root|etc|opt|srv|work|proc|mnt|data|app|lib|lib64|run|dev|private|Users|nix|sys"
_ABS_PATH_RE = re.compile(r"(?<![\w.:/])/(?:" + _ROOTS + r")(?:/[^\s'\"(),;:<>]*)+")
_SECRET_PREFIXES: list[str] = []


def _prefixes() -> list[str]:
    if not _SECRET_PREFIXES:
        here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
        cands = {here, os.getcwd(), sys.prefix, tempfile.gettempdir(), os.path.expanduser("~")}
        storage = os.environ.get("RIBPULL_STORAGE_DIR")
        if storage:
            cands.add(os.path.abspath(storage))
        _SECRET_PREFIXES.extend(sorted((c for c in cands if c and len(c) > 1), key=len, reverse=True))
    return _SECRET_PREFIXES


def scrub_paths(text: str) -> str:
    """Remove server file-system paths from a message shown to clients (keep the file's base name)."""
    if not text or "/" not in text:
        return text
    for pre in _prefixes():
        text = re.sub(re.escape(pre) + r"(?:/[^\s'\"(),;:<>]*)?",
                      lambda m: os.path.basename(m.group(0).rstrip("/")) or "<server path>", text)
    return _ABS_PATH_RE.sub(lambda m: os.path.basename(m.group(0).rstrip("/")) or "<server path>", text)


def problem_body(status: int, code: str | None, detail: str, *, title: str | None = None,
                 instance: str | None = None) -> dict[str, Any]:
    code = code or _STATUS_CODES.get(status, "http_error")
    body: dict[str, Any] = {
        "type": TYPE_PREFIX + code,
        "title": title or _title(status),
        "status": status,
        "detail": scrub_paths(detail),
        "code": code,
    }
    if instance:
        body["instance"] = instance
    return body


def problem_response(
    status: int,
    code: str,
    detail: str,
    *,
    title: str | None = None,
    instance: str | None = None,
    headers: dict[str, str] | None = None,
    errors: list[dict[str, Any]] | None = None,
    extra: dict[str, Any] | None = None,
) -> JSONResponse:
    body = problem_body(status, code, detail, title=title, instance=instance)
    if errors is not None:
        body["errors"] = errors
    if extra:
        body.update({k: v for k, v in extra.items() if k not in body})
    headers = {**(headers or {}), "X-Content-Type-Options": "nosniff"}
    return JSONResponse(body, status_code=status, headers=headers, media_type=PROBLEM_MEDIA_TYPE)


def _title(status: int) -> str:
    try:
        return HTTPStatus(status).phrase
    except ValueError:
        return "Error"


def _clean_validation_errors(errs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """FastAPI's error dicts may hold the offending input (bytes, huge strings): keep them small."""
    out = []
    for e in errs[:50]:
        item = {
            "loc": [str(p) for p in e.get("loc", ())],
            "msg": scrub_paths(str(e.get("msg", ""))[:500]),
            "type": str(e.get("type", "")),
        }
        out.append(item)
    return out


def validation_problem(errors: list[dict[str, Any]], where: str = "request") -> ProblemError:
    clean = _clean_validation_errors(errors)
    parts = []
    for e in clean[:5]:
        loc = ".".join(p for p in e["loc"] if p not in ("body",)) or where
        parts.append(f"{loc}: {e['msg']}")
    detail = "invalid " + where + ": " + "; ".join(parts) if parts else f"invalid {where}"
    return ProblemError(422, "validation_error", detail, errors=clean)


def install_handlers(app: FastAPI) -> None:
    @app.exception_handler(ProblemError)
    async def _problem(request: Request, exc: ProblemError):
        return problem_response(
            exc.status, exc.code, exc.detail, title=exc.title, headers=exc.headers,
            errors=exc.errors, instance=request.url.path,
        )

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError):
        p = validation_problem(list(exc.errors()))
        return problem_response(422, p.code, p.detail, errors=p.errors, instance=request.url.path)

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException):
        status = exc.status_code
        code = _STATUS_CODES.get(status, "http_error")
        detail = exc.detail if isinstance(exc.detail, str) else json.dumps(exc.detail, default=str)
        if status == 404 and detail == "Not Found":
            detail = f"no such resource: {request.url.path}"
        if status == 405 and detail == "Method Not Allowed":
            detail = f"method {request.method} is not allowed on {request.url.path}"
        return problem_response(status, code, detail, headers=getattr(exc, "headers", None),
                                instance=request.url.path)

    @app.exception_handler(ClientDisconnect)
    async def _gone(request: Request, exc: ClientDisconnect):
        log.info("client disconnected during %s %s", request.method, request.url.path)
        return problem_response(400, "client_disconnected", "the client closed the connection")

    @app.exception_handler(SQLAlchemyOperationalError)
    async def _db_down(request: Request, exc: Exception):
        log.error("database error on %s %s: %s", request.method, request.url.path, exc)
        return problem_response(503, "database_unavailable", "the job database is not reachable; try again",
                                headers={"Retry-After": "5"}, instance=request.url.path)

    @app.exception_handler(Exception)
    async def _unexpected(request: Request, exc: Exception):
        log.exception("unhandled error on %s %s", request.method, request.url.path)
        return problem_response(500, "internal_error", "an unexpected error occurred; it has been logged",
                                instance=request.url.path)
