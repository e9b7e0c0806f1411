"""ASGI middleware of the API (outermost first):

- `Hardening`: `X-Content-Type-Options: nosniff` on every response, and any 4xx/5xx that is not
  already application/problem+json (Starlette's Range 416/400, anything plain text) is rewritten as
  one, so a client only ever parses one error shape.
- `BodyTimeout`: each chunk of a request body must arrive within RIBPULL_BODY_TIMEOUT_S, else 408
  (the streaming upload removes its partial file; see app/upload.py).
- `BodyLimit`: bodies of every route except the streaming upload are capped; /query gets a budget
  derived from RIBPULL_MAX_QUERY_POINTS, so an oversized query is refused before it is parsed.
"""

from __future__ import annotations

import asyncio
import json

from fastapi import (
    HTTPException as StarletteHTTPException,  # FastAPI re-raises its own subclass from body parsing
)

from .problems import PROBLEM_MEDIA_TYPE, problem_body, problem_response

NOSNIFF = (b"x-content-type-options", b"nosniff")
OTHER_BODY_LIMIT = 64 * 1024  # bytes of a body on routes that take none (DELETE, GET ...)
QUERY_BYTES_PER_POINT = 96  # "[-123.456789012345, -123.456789012345, -123.456789012345], " and slack


def query_body_budget(max_query_points: int) -> int:
    return max_query_points * QUERY_BYTES_PER_POINT + 4096


def _is_upload(scope) -> bool:
    return scope["method"] == "POST" and scope["path"].rstrip("/") == "/v1/jobs"


class Hardening:
    def __init__(self, app):
        self.app = app

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        held: dict = {}

        async def wrapped_send(msg):
            if msg["type"] == "http.response.start":
                headers = [(k, v) for k, v in msg.get("headers", []) if k.lower() != NOSNIFF[0]]
                headers.append(NOSNIFF)
                msg = {**msg, "headers": headers}
                ctype = next((v for k, v in headers if k.lower() == b"content-type"), b"")
                if msg["status"] >= 400 and not ctype.startswith(PROBLEM_MEDIA_TYPE.encode()):
                    held["start"] = msg
                    held["body"] = b""
                    return
                return await send(msg)
            if msg["type"] == "http.response.body" and "start" in held:
                if len(held["body"]) < 4096:
                    held["body"] += msg.get("body", b"")[:4096]
                if msg.get("more_body", False):
                    return
                return await self._send_problem(held, scope, send)
            return await send(msg)

        await self.app(scope, receive, wrapped_send)

    @staticmethod
    async def _send_problem(held: dict, scope, send) -> None:
        start = held.pop("start")
        status = int(start["status"])
        text = held["body"].decode("utf-8", "replace").strip()
        keep = [(k, v) for k, v in start.get("headers", [])
                if k.lower() not in (b"content-type", b"content-length", b"content-disposition", b"etag",
                                     b"last-modified", b"accept-ranges")]
        if status == 416:
            detail = "the requested Range is not satisfiable" + (f" ({text})" if text else "")
            code = "range_not_satisfiable"
        elif status == 400 and scope["path"].count("/artifacts/"):
            detail = f"malformed Range header: {text}" if text else "malformed Range header"
            code = "bad_range"
        else:
            detail = text or "error"
            code = None
        body = json.dumps(problem_body(status, code, detail, instance=scope.get("path"))).encode()
        keep += [(b"content-type", PROBLEM_MEDIA_TYPE.encode()), (b"content-length", str(len(body)).encode())]
        await send({"type": "http.response.start", "status": status, "headers": keep})
        await send({"type": "http.response.body", "body": body})


class BodyTimeout:
    """408 when the next request-body chunk takes longer than `timeout` seconds."""

    def __init__(self, app, timeout: float):
        self.app = app
        self.timeout = timeout

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        done = {"body": False}
        timeout = self.timeout

        async def timed_receive():
            if done["body"]:  # later receive() calls only wait for a disconnect: no limit
                return await receive()
            try:
                msg = await asyncio.wait_for(receive(), timeout)
            except asyncio.TimeoutError:
                raise StarletteHTTPException(
                    408, f"no request data for {timeout:g} s (RIBPULL_BODY_TIMEOUT_S); send the body faster",
                    headers={"Connection": "close"},
                ) from None
            if msg["type"] != "http.request" or not msg.get("more_body", False):
                done["body"] = True
            return msg

        return await self.app(scope, timed_receive, send)


class BodyLimit:
    """Cap request bodies of every route except the streaming upload (which has its own caps)."""

    def __init__(self, app, query_limit: int, other_limit: int = OTHER_BODY_LIMIT):
        self.app = app
        self.query_limit = query_limit
        self.other_limit = other_limit

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http" or _is_upload(scope):
            return await self.app(scope, receive, send)
        is_query = scope["path"].rstrip("/").endswith("/query")
        limit = self.query_limit if is_query else self.other_limit
        what = (f"a query body (RIBPULL_MAX_QUERY_POINTS points at most ~{QUERY_BYTES_PER_POINT} bytes each)"
                if is_query else "a request body on this route")
        msg = f"the request body is over {limit} bytes, the limit for {what}"
        for k, v in scope.get("headers", ()):
            if k == b"content-length":
                try:
                    too_big = int(v) > limit
                except ValueError:
                    too_big = False
                if too_big:
                    resp = problem_response(413, "too_large", msg, headers={"Connection": "close"})
                    return await resp(scope, receive, send)
        seen = 0

        async def limited_receive():
            nonlocal seen
            m = await receive()
            if m["type"] == "http.request":
                seen += len(m.get("body", b""))
                if seen > limit:
                    raise StarletteHTTPException(413, msg, headers={"Connection": "close"})
            return m

        return await self.app(scope, limited_receive, send)
