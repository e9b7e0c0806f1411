"""Streaming multipart upload: the `file` part goes straight to disk and stops at the size cap.

Starlette's form parser would spool the whole body before the endpoint runs; this parser reads the
request stream chunk by chunk, hashes and writes the file part as it arrives and answers 413 as soon
as the cap is passed (or before reading anything when Content-Length already says so).
"""

from __future__ import annotations

import hashlib
import logging
import uuid
import zlib
from dataclasses import dataclass, field
from pathlib import Path

from fastapi import Request
from python_multipart.exceptions import FormParserError, MultipartParseError
from python_multipart.multipart import MultipartParser, parse_options_header
from starlette.concurrency import run_in_threadpool
from starlette.requests import ClientDisconnect

from .problems import ProblemError
from .settings import Settings
from .storage import rmtree_quiet, safe_filename

MAX_FIELD_BYTES = 64 * 1024  # params JSON and any other non-file field
MULTIPART_OVERHEAD = 64 * 1024  # boundaries, part headers and the params field on top of the file cap
INFLATE_STEP = 4 * 1024 * 1024  # most bytes inflated at once while measuring a gzip stream

log = logging.getLogger("ribpull.api")


class InflateMeter:
    """Counts the bytes a gzip stream inflates to, chunk by chunk as it arrives, without keeping
    them: memory stays O(INFLATE_STEP) however large the inflated size. Raises _Inflated at `cap`."""

    def __init__(self, cap: int):
        self.cap = cap
        self.total = 0
        self.broken = False
        self._d = zlib.decompressobj(wbits=31)

    def feed(self, data: bytes) -> None:
        if self.broken:
            return
        try:
            while data:
                out = self._d.decompress(data, INFLATE_STEP)
                self.total += len(out)
                if self.total > self.cap:
                    raise _Inflated()
                if self._d.eof:  # a multi-member gzip: the next member starts in unused_data
                    data = self._d.unused_data
                    self._d = zlib.decompressobj(wbits=31)
                    if data[:2] != b"\x1f\x8b":
                        return  # trailing garbage: the loader reports it
                else:
                    data = self._d.unconsumed_tail
                    if not data and out:
                        # input consumed but output may still be pending: drain with no new input
                        while True:
                            more = self._d.decompress(b"", INFLATE_STEP)
                            if not more:
                                break
                            self.total += len(more)
                            if self.total > self.cap:
                                raise _Inflated()
        except zlib.error:
            self.broken = True  # not valid gzip: the loader gives the user a proper message


class _Inflated(Exception):
    pass


class _TooLarge(Exception):
    pass


class _FieldTooLarge(Exception):
    pass


class _Duplicate(Exception):
    pass


@dataclass
class Upload:
    tmpdir: Path
    path: Path | None = None  # the saved file (tmpdir/<safe filename>)
    filename: str = ""
    size: int = 0
    sha256: str = ""
    fields: dict[str, str] = field(default_factory=dict)

    def cleanup(self) -> None:
        rmtree_quiet(self.tmpdir)


async def receive_upload(request: Request, settings: Settings) -> Upload:
    """Parse multipart/form-data from `request`; raise ProblemError for anything malformed."""
    ctype = request.headers.get("content-type", "")
    mime, opts = parse_options_header(ctype)
    if mime != b"multipart/form-data":
        raise ProblemError(
            415, "unsupported_media_type",
            "send the job as multipart/form-data with a `file` part and an optional `params` JSON field",
        )
    boundary = opts.get(b"boundary")
    if not boundary or len(boundary) > 200:
        raise ProblemError(400, "bad_multipart", "multipart/form-data without a valid boundary")
    cap = settings.max_upload_bytes
    declared = request.headers.get("content-length")
    if declared is not None:
        try:
            declared_n = int(declared)
        except ValueError:
            raise ProblemError(400, "bad_request", "invalid Content-Length header") from None
        if declared_n > cap + MULTIPART_OVERHEAD:
            raise ProblemError(413, "too_large", _too_large_msg(settings))

    settings.uploads_dir.mkdir(parents=True, exist_ok=True)
    up = Upload(tmpdir=settings.uploads_dir / uuid.uuid4().hex)
    up.tmpdir.mkdir(parents=True)

    state: dict = {"headers": {}, "hname": b"", "hval": b"", "part": None}
    fh = {"f": None, "h": None, "meter": None, "head": b""}
    icap = settings.max_inflated_bytes
    field_buf: dict[str, bytearray] = {}
    total = {"n": 0}

    def on_part_begin():
        state["headers"] = {}
        state["part"] = None

    def on_header_field(data, start, end):
        state["hname"] += data[start:end]

    def on_header_value(data, start, end):
        state["hval"] += data[start:end]

    def on_header_end():
        state["headers"][state["hname"].strip().lower()] = state["hval"].strip()
        state["hname"] = b""
        state["hval"] = b""

    def on_headers_finished():
        _disp, dopts = parse_options_header(state["headers"].get(b"content-disposition", b""))
        name = dopts.get(b"name", b"").decode("utf-8", "replace")
        if name == "file":
            if up.path is not None:
                raise _Duplicate("file")
            fname = dopts.get(b"filename", b"").decode("utf-8", "replace")
            up.filename = fname
            up.path = up.tmpdir / safe_filename(fname)
            fh["f"] = open(up.path, "wb")  # noqa: SIM115 (spans parser callbacks; closed at the part's end)
            fh["h"] = hashlib.sha256()
            state["part"] = ("file", name)
        else:
            if name in field_buf:
                raise _Duplicate(name)
            field_buf[name] = bytearray()
            state["part"] = ("field", name)

    def on_part_data(data, start, end):
        part = state["part"]
        if part is None:
            return
        chunk = data[start:end]
        if part[0] == "file":
            up.size += len(chunk)
            if up.size > cap:
                raise _TooLarge()
            fh["f"].write(chunk)
            fh["h"].update(chunk)
            if len(fh["head"]) < 2:
                fh["head"] += bytes(chunk[:2])
                if fh["head"][:2] == b"\x1f\x8b" and fh["meter"] is None:
                    fh["meter"] = InflateMeter(icap)
                    fh["pending"] = []
            if fh["meter"] is not None:
                fh["pending"].append(bytes(chunk))
        else:
            buf = field_buf[part[1]]
            if len(buf) + len(chunk) > MAX_FIELD_BYTES:
                raise _FieldTooLarge(part[1])
            buf.extend(chunk)

    def on_part_end():
        if state["part"] and state["part"][0] == "file" and fh["f"] is not None:
            fh["f"].close()
            fh["f"] = None
        state["part"] = None

    parser = MultipartParser(
        boundary,
        {
            "on_part_begin": on_part_begin,
            "on_header_field": on_header_field,
            "on_header_value": on_header_value,
            "on_header_end": on_header_end,
            "on_headers_finished": on_headers_finished,
            "on_part_data": on_part_data,
            "on_part_end": on_part_end,
        },
    )
    ok = False
    try:
        async for chunk in request.stream():
            total["n"] += len(chunk)
            if total["n"] > cap + MULTIPART_OVERHEAD:
                raise _TooLarge()
            if chunk:
                parser.write(chunk)
                if fh["meter"] is not None and fh.get("pending"):
                    todo, fh["pending"] = b"".join(fh["pending"]), []
                    await run_in_threadpool(fh["meter"].feed, todo)  # CPU work off the event loop
        parser.finalize()
        if fh["f"] is not None:  # body ended inside the file part
            raise ProblemError(400, "bad_multipart", "the multipart body ended before the file part was complete")
        ok = True
    except _TooLarge:
        raise ProblemError(413, "too_large", _too_large_msg(settings)) from None
    except _Inflated:
        raise ProblemError(
            413, "too_large",
            f"the compressed upload inflates to more than {settings.max_inflated_mb:g} MiB "
            "(RIBPULL_MAX_INFLATED_MB); crop the volume or store it with a smaller data type",
        ) from None
    except ClientDisconnect:
        log.info("client disconnected during an upload (%d bytes received); upload discarded", total["n"])
        raise ProblemError(400, "client_disconnected", "the client closed the connection during the upload") from None
    except _FieldTooLarge as exc:
        raise ProblemError(413, "too_large", f"form field '{exc}' is larger than {MAX_FIELD_BYTES} bytes") from None
    except _Duplicate as exc:
        raise ProblemError(422, "validation_error", f"form field '{exc}' was sent more than once") from None
    except (MultipartParseError, FormParserError) as exc:
        raise ProblemError(400, "bad_multipart", f"malformed multipart body: {exc}") from None
    except OSError as exc:  # disk full, storage gone
        raise ProblemError(503, "storage_unavailable", f"could not store the upload: {exc.strerror or exc}",
                           headers={"Retry-After": "30"}) from None
    finally:
        if fh["f"] is not None:
            fh["f"].close()
        if not ok:
            up.cleanup()

    for name, buf in field_buf.items():
        try:
            up.fields[name] = bytes(buf).decode("utf-8")
        except UnicodeDecodeError:
            up.cleanup()
            raise ProblemError(422, "validation_error", f"form field '{name}' is not UTF-8 text") from None
    if up.path is not None:
        up.sha256 = fh["h"].hexdigest()
    return up


def _too_large_msg(settings: Settings) -> str:
    return (
        f"the upload is larger than the limit of {settings.max_upload_mb:g} MiB "
        "(RIBPULL_MAX_UPLOAD_MB); subsample the cloud or use a binary format"
    )
