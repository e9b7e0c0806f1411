"""uvicorn's h11 protocol with two hardening changes (used by `uvicorn --http app.httpserver:HardenedH11Protocol`,
see app/launcher.api_cmd):

- a header timeout: a request whose headers are not complete RIBPULL_BODY_TIMEOUT_S after its first
  byte gets a 408 application/problem+json and the connection is closed (slowloris); body chunks
  have the same limit in the ASGI app (app/middleware.BodyTimeout);
- protocol errors (malformed request line or headers) are answered as problem+json, not text/plain.
"""

from __future__ import annotations

import json
import logging

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol

from .settings import get_settings

log = logging.getLogger("ribpull.api")


def _problem_bytes(status: int, code: str, title: str, detail: str) -> bytes:
    return json.dumps({"type": f"urn:ribpull:problem:{code}", "title": title, "status": status,
                       "detail": detail, "code": code}).encode()


class HardenedH11Protocol(H11Protocol):
    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._header_timeout = float(get_settings().body_timeout_s)
        self._header_timer = None
        self._seen_cycle = None

    # --- header timeout --------------------------------------------------------------------------
    def data_received(self, data: bytes) -> None:
        super().data_received(data)
        if self.transport.is_closing():
            return
        if self.cycle is not None and self.cycle is not self._seen_cycle:  # a request's headers arrived
            self._seen_cycle = self.cycle
            self._cancel_header_timer()
        elif (self.cycle is None or self.cycle.response_complete) and self._header_timer is None \
                and self.conn.their_state is h11.IDLE and data:
            self._header_timer = self.loop.call_later(self._header_timeout, self._on_header_timeout)

    def _cancel_header_timer(self) -> None:
        if self._header_timer is not None:
            self._header_timer.cancel()
            self._header_timer = None

    def _on_header_timeout(self) -> None:
        self._header_timer = None
        if self.transport.is_closing():
            return
        if self.cycle is not None and not self.cycle.response_complete:
            return  # a request is being handled
        if self.conn.their_state is not h11.IDLE:
            return
        body = _problem_bytes(408, "request_timeout", "Request Timeout",
                              f"the request headers did not arrive within {self._header_timeout:g} s "
                              "(RIBPULL_BODY_TIMEOUT_S)")
        head = (b"HTTP/1.1 408 Request Timeout\r\ncontent-type: application/problem+json\r\n"
                b"x-content-type-options: nosniff\r\nconnection: close\r\ncontent-length: "
                + str(len(body)).encode() + b"\r\n\r\n")
        log.info("closed a connection whose request headers took over %g s", self._header_timeout)
        self.transport.write(head + body)
        self.transport.close()

    def connection_lost(self, exc) -> None:
        self._cancel_header_timer()
        super().connection_lost(exc)

    # --- protocol errors as problem+json ----------------------------------------------------------
    def send_400_response(self, msg: str) -> None:
        body = _problem_bytes(400, "bad_request", "Bad Request", f"malformed HTTP request: {msg}")
        headers = [
            (b"content-type", b"application/problem+json"),
            (b"x-content-type-options", b"nosniff"),
            (b"content-length", str(len(body)).encode()),
            (b"connection", b"close"),
        ]
        try:
            self.transport.write(self.conn.send(h11.Response(status_code=400, headers=headers, reason=b"Bad Request")))
            self.transport.write(self.conn.send(h11.Data(data=body)))
            self.transport.write(self.conn.send(h11.EndOfMessage()))
        except h11.LocalProtocolError:  # h11 cannot answer in this state: close without a response
            pass
        self.transport.close()
