"""Bearer-key authentication. With RIBPULL_API_KEYS unset every caller is the anonymous owner "";
with keys set, /v1 needs `Authorization: Bearer <key>` and each key sees only its own jobs
(jobs store sha256(key), never the key)."""

from __future__ import annotations

import hmac

from fastapi import Request

from .problems import ProblemError
from .settings import hash_key


def current_owner(request: Request) -> str:
    settings = request.app.state.settings
    hashes: set[str] = request.app.state.key_hashes
    if not hashes:
        return ""
    header = request.headers.get("authorization", "")
    scheme, _, token = header.partition(" ")
    token = token.strip()
    if scheme.lower() != "bearer" or not token:
        raise ProblemError(
            401, "unauthorized", "send `Authorization: Bearer <key>`",
            headers={"WWW-Authenticate": 'Bearer realm="ribpull"'},
        )
    h = hash_key(token)
    if not any(hmac.compare_digest(h, k) for k in hashes):
        raise ProblemError(
            401, "unauthorized", "unknown API key",
            headers={"WWW-Authenticate": 'Bearer realm="ribpull", error="invalid_token"'},
        )
    del settings
    return h
