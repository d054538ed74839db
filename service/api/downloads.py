"""Files the API sends back: media types and the download response (W map files are
:func:`models.winding_files.encode_winding_file`'s)."""

from __future__ import annotations

import os
import re
from email.utils import parsedate_to_datetime
from pathlib import Path
from typing import Any, BinaryIO

from fastapi import Response
from fastapi.responses import FileResponse
from starlette.datastructures import Headers
from starlette.responses import MalformedRangeHeader, RangeNotSatisfiable
from starlette.types import Receive, Scope, Send

from service.api.errors import ApiError
from worker.result_store import ResultStore

MEDIA_TYPES: dict[str, str] = {
    "png": "image/png",
    "tiff": "image/tiff",
    "npy": "application/octet-stream",
    "exr": "image/x-exr",
}


#: Cache policy of a stored result: its URL names one job's file, which never changes.
IMMUTABLE = "private, max-age=31536000, immutable"


#: One range of a byte-range set (RFC 9110 14.1.2): FIRST-LAST, FIRST- or -LENGTH.
BYTE_RANGE = re.compile(r"[0-9]+-[0-9]*|-[0-9]+")


def malformed_ranges(spec: str) -> bool:
    """Whether the byte-range set ``spec`` (the Range header after ``bytes=``) holds a
    range that is not FIRST-LAST, FIRST- or -LENGTH, or a FIRST-LAST whose LAST is below
    its FIRST (RFC 9110 14.1.1-14.1.2), or no range at all; empty list elements are
    ignored (RFC 9110 5.6.1.2)."""
    parts = [part.strip(" \t") for part in spec.split(",")]
    ranges = [part for part in parts if part]
    return not ranges or any(
        not BYTE_RANGE.fullmatch(part) or _last_before_first(part) for part in ranges
    )


def _last_before_first(part: str) -> bool:
    """Whether the well-formed range ``part`` is FIRST-LAST with LAST below FIRST."""
    first, _, last = part.partition("-")
    return bool(first and last) and int(last) < int(first)


#: The headers of a stored file's response that its 304 repeats (RFC 9110 15.4.5).
NOT_MODIFIED_HEADERS = ("etag", "cache-control")


def _changed_since(response: Headers, date: str) -> bool | None:
    """Whether ``response``'s ``Last-Modified`` is later than the HTTP-date ``date``
    (None: ``date`` is no valid HTTP-date, and the condition that names it is ignored)."""
    try:
        return parsedate_to_datetime(response["last-modified"]) > parsedate_to_datetime(date)
    except (TypeError, ValueError):
        return None


def entity_tags(request: Headers, name: str) -> set[str] | None:
    """The entity tags of the request's ``name`` header (``If-Match``, ``If-None-Match``)
    on all its lines, read as one comma-separated list (RFC 9110 5.3, 13.1.1-13.1.2: a
    second ``If-Match`` line naming the file's tag got 412, one ``If-Match`` naming both
    tags 200); None without the header."""
    lines = request.getlist(name)
    if not lines:
        return None
    return {tag.strip() for line in lines for tag in line.split(",")}


def not_modified(request: Headers, response: Headers) -> bool:
    """Whether a GET of a file with ``response``'s ``ETag`` and ``Last-Modified`` may be
    answered 304: ``If-None-Match`` names its tag (weakly compared) or is ``*``; without
    it, ``If-Modified-Since`` is a valid date no earlier than ``Last-Modified``."""
    if_none_match = entity_tags(request, "if-none-match")
    if if_none_match is not None:
        tags = {tag.removeprefix("W/") for tag in if_none_match}
        return "*" in tags or response["etag"].removeprefix("W/") in tags
    since = request.get("if-modified-since")
    return since is not None and _changed_since(response, since) is False


def precondition_failed(request: Headers, response: Headers) -> bool:
    """Whether a request for a file with ``response``'s ``ETag`` and ``Last-Modified``
    must be answered 412 (RFC 9110 13.1.1-13.1.2): ``If-Match`` names neither its tag
    (strongly compared: a weak ``W/`` tag never matches) nor ``*``; without it,
    ``If-Unmodified-Since`` is a valid date earlier than ``Last-Modified``."""
    tags = entity_tags(request, "if-match")
    if tags is not None:
        return "*" not in tags and response["etag"] not in tags
    since = request.get("if-unmodified-since")
    return since is not None and _changed_since(response, since) is True


class HeldFileResponse(FileResponse):
    """A file response of a file opened before the response starts, so that removing
    the file (the retention purge) between the route and the send cannot turn the
    response into a 500 or cut it short after its headers: the response reads the open
    file's ``/proc/self/fd`` entry (the same file, named or not) and holds the file open
    as long as it lives."""

    def __init__(self, handle: BinaryIO, **kwargs: Any) -> None:
        held = Path(f"/proc/self/fd/{handle.fileno()}")
        path = held if held.exists() else Path(handle.name)
        super().__init__(path, stat_result=os.fstat(handle.fileno()), **kwargs)
        self.handle = handle

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        """Send the file; a 412 to a request whose ``If-Match`` or
        ``If-Unmodified-Since`` the file fails (a client fetching pieces of one version
        of a device's newest frame got pieces of another); a 304 without it to a GET or
        HEAD whose validators say the client's copy is current (RFC 9110 13.1.1-13.1.4),
        so a viewer revalidating a device's newest frame does not fetch it again."""
        if scope["type"] == "http" and precondition_failed(Headers(scope=scope), self.headers):
            raise ApiError(
                412, "precondition_failed",
                f"this file is now {self.headers['etag']}, last modified "
                f"{self.headers['last-modified']}: not the version that If-Match or "
                "If-Unmodified-Since names; fetch it again whole, without them",
                headers={"ETag": self.headers["etag"]},
            )  # fmt: skip
        if scope["type"] == "http" and scope["method"].upper() in ("GET", "HEAD"):
            if not_modified(Headers(scope=scope), self.headers):
                kept = {name: self.headers[name] for name in NOT_MODIFIED_HEADERS}
                return await Response(status_code=304, headers=kept)(scope, receive, send)
        return await super().__call__(scope, receive, send)

    @classmethod
    def _parse_range_header(cls, http_range: str, file_size: int) -> list[tuple[int, int]]:
        """Starlette's byte ranges of ``http_range`` in a file of ``file_size`` bytes
        ([] for the whole file), where a range in a unit other than bytes is ignored (RFC
        9110 14.2: it was 400) and a malformed or unsatisfiable one is the API's JSON 400
        or 416 (they were plain text). A set is malformed if any of its ranges is
        (:func:`malformed_ranges`; RFC 9110 14.2 lets a server reject it): Starlette
        left out a malformed range beside a good one, so ``bytes=0-9,-`` got a 206 of
        bytes 0-9 while ``bytes=0-9,5-2`` got the 400."""
        unit, equals, spec = http_range.partition("=")
        if equals and unit.strip().lower() != "bytes":
            return []
        if malformed_ranges(spec):
            raise cls._malformed()
        try:
            return super()._parse_range_header(http_range, file_size)
        except RangeNotSatisfiable:
            satisfiable = cls._satisfiable_parts(spec, file_size)
            if not satisfiable:
                raise cls._unsatisfiable(file_size) from None
            return super()._parse_range_header(f"bytes={','.join(satisfiable)}", file_size)

    @classmethod
    def _satisfiable_parts(cls, spec: str, file_size: int) -> list[str]:
        """The ranges of the byte-range set ``spec`` that are satisfiable on their own in
        a file of ``file_size`` bytes (RFC 9110 14.1.1: a set is satisfiable if any of
        its ranges is, and then the others are left out; one range past the end made
        ``bytes=0-1,99999-`` a 416)."""
        satisfiable = []
        for part in spec.split(","):
            try:
                super()._parse_range_header(f"bytes={part}", file_size)
            except (MalformedRangeHeader, RangeNotSatisfiable):
                continue
            satisfiable.append(part)
        return satisfiable

    @staticmethod
    def _malformed() -> ApiError:
        """The API's JSON 400 for a Range header that is not a byte-range set."""
        return ApiError(
            400, "bad_range",
            "the Range header is malformed; ask for bytes=FIRST-LAST, bytes=FIRST- or "
            "bytes=-LENGTH (FIRST <= LAST; several separated by commas), or send none for "
            "the whole file",
        )  # fmt: skip

    @staticmethod
    def _unsatisfiable(file_size: int) -> ApiError:
        """The API's JSON 416 for a Range none of whose ranges lies in the file."""
        return ApiError(
            416, "range_not_satisfiable",
            f"the Range header asks for no byte of this {file_size}-byte file (ranges "
            "past its end, or a last 0 bytes: bytes=-0); "
            + (f"ask for bytes within 0-{file_size - 1}" if file_size
                        else "send no Range for it"),
            headers={"Content-Range": f"bytes */{file_size}"},
        )  # fmt: skip


def stored_file(
    store: ResultStore, key: str, media_type: str, filename: str, *, immutable: bool = True
) -> FileResponse:
    """A stored result streamed from disk, with Range requests (a player seeks, a broken
    download resumes), ``ETag`` and ``Last-Modified`` (a current copy gets 304:
    :func:`not_modified`); ``immutable``: cacheable for good
    (a job's result), else revalidated each time (a device's newest frame). A result
    purged meanwhile is 404 ``not_found`` or, once opened here, sent whole."""
    return HeldFileResponse(
        store.open(key),
        media_type=media_type,
        filename=filename,
        content_disposition_type="attachment",
        headers={"Cache-Control": IMMUTABLE if immutable else "no-cache"},
    )


def download(
    content: bytes, fmt: str, stem: str, headers: dict[str, str] | None = None
) -> Response:
    """A file response named ``<stem>.<fmt>`` with the format's media type."""
    return Response(
        content,
        media_type=MEDIA_TYPES[fmt],
        headers={"Content-Disposition": f'attachment; filename="{stem}.{fmt}"', **(headers or {})},
    )
