"""The API's routers: health, jobs (submit / list / get / cancel-delete), artifacts, query."""

from __future__ import annotations

from ..problems import PROBLEM_MEDIA_TYPE


def problems(*codes: int) -> dict:
    """OpenAPI `responses` entries for problem+json errors."""
    desc = {
        400: "Malformed request", 401: "Missing or unknown API key", 404: "Not found", 408: "Request too slow",
        409: "Conflict", 410: "Gone", 413: "Too large", 415: "Unsupported media type or file format",
        416: "Range not satisfiable",
        422: "Invalid input (parameters, file content, limits, webhook target or Idempotency-Key reuse)",
        503: "Unavailable",
    }
    return {
        c: {
            "description": desc.get(c, "Error"),
            "content": {PROBLEM_MEDIA_TYPE: {"schema": {"$ref": "#/components/schemas/Problem"}}},
        }
        for c in codes
    }
