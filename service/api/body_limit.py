"""Body size limits enforced while the body streams in (never buffered whole first).

A declared ``Content-Length`` above the limit is refused before any byte is
kept; a chunked body is counted as it arrives and refused the moment it crosses the
limit. Either way the rest of the body is then read and dropped, within the body
timeouts, and the connection closed (:func:`closing_send`). Uploads (any body but JSON
or a URL-encoded form) answer 413 ``image_too_large``; a JSON or URL-encoded body has a
limit of its own, ``MCAM_MAX_JSON_BYTES``, and answers 413 ``body_too_large``: a control
command or a recording request is a few hundred bytes, and FastAPI parses a JSON body
before the API key is checked (a 22 MB body from no key at all took the API 650 MB).
"""

from __future__ import annotations

import json

from starlette.datastructures import Headers
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.api.errors import ApiError, error_body

#: Media types of small bodies (commands, forms of fields): :attr:`json_limit` applies.
SMALL_BODY_TYPES = (b"application/json", b"application/x-www-form-urlencoded")


def too_large(limit: int) -> ApiError:
    """The 413 error for an upload above ``limit`` bytes."""
    return ApiError(
        413,
        "image_too_large",
        f"the request body exceeds the upload limit of {limit} bytes; "
        "send a smaller file or raise MCAM_MAX_UPLOAD_BYTES",
    )


def body_too_large(limit: int) -> ApiError:
    """The 413 error for a JSON or URL-encoded body above ``limit`` bytes."""
    return ApiError(
        413,
        "body_too_large",
        f"the JSON or form body exceeds {limit} bytes; commands and fields are a few "
        "hundred bytes (files go as multipart uploads); or raise MCAM_MAX_JSON_BYTES",
    )


class BodyLimitMiddleware:
    """ASGI middleware: at most ``limit`` request-body bytes per upload, ``json_limit``
    per JSON or URL-encoded body."""

    def __init__(self, app: ASGIApp, limit: int, json_limit: int) -> None:
        self.app = app
        self.limit = limit
        self.json_limit = json_limit

    def _error(self, headers: Headers) -> tuple[int, ApiError]:
        """The limit for a request with ``headers``, and the error past it. The media
        type is the first ``Content-Type``, as the body readers see it (the last let a
        request with two send 60 MB of JSON past the JSON limit)."""
        media = headers.get("content-type", "").split(";")[0].strip().lower().encode()
        if media in SMALL_BODY_TYPES or media.endswith(b"+json"):
            return self.json_limit, body_too_large(self.json_limit)
        return self.limit, too_large(self.limit)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = Headers(scope=scope)
        limit, error = self._error(headers)
        declared = headers.get("content-length")
        if declared is not None and declared.isdigit() and int(declared) > limit:
            await self._refuse(receive, send, error, headers)
            return
        received = 0
        refusing: Send | None = None  # the answer's send, once the body crossed the limit

        async def limited_receive() -> Message:
            nonlocal received, refusing
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > limit:  # the rest, if any, is read and dropped
                    refusing = closing_send(send, receive, bool(message.get("more_body")))
                    raise error
            return message

        async def limited_send(message: Message) -> None:
            await (refusing or send)(message)

        await self.app(scope, limited_receive, limited_send)

    async def _refuse(
        self, receive: Receive, send: Send, error: ApiError, headers: Headers
    ) -> None:
        """Answer 413 to a request whose declared length is over the limit, through
        :func:`closing_send`; a client that asked ``Expect: 100-continue`` (curl, for
        large files) sends no body after it, and none is waited for."""
        detail = error.detail
        body = json.dumps(error_body(detail["code"], detail["message"])).encode()
        expects = "100-continue" in headers.get("expect", "").lower()
        reply = closing_send(send, receive, drain=not expects)
        await reply(
            {
                "type": "http.response.start",
                "status": 413,
                "headers": [
                    (b"content-type", b"application/json"),
                    (b"content-length", str(len(body)).encode()),
                ],
            }
        )
        await reply({"type": "http.response.body", "body": body})


def closing_send(send: Send, receive: Receive, drain: bool) -> Send:
    """``send`` for the answer to a body over its limit: the response says
    ``Connection: close``, and before its last message ends it, the rest of the request
    body is read and dropped (``drain``, where some of it has not arrived:
    :func:`drop_body`; a read past a body's end waits for the client to leave); the
    connection then closes.

    Closed with the body unread, the connection was reset (TCP RST), and a client still
    sending its upload, as most do before they read the answer (httpx), often lost the
    413: 7 of 22 uploads of 2.2 to 100 MB over a 2 MB limit ended in "peer closed
    connection without sending complete message body". Kept open (a chunked body
    refused as it crossed the limit), uvicorn read the rest of the body with no bound:
    a client sending a byte every 2 s after its 413 still held the connection 70 s on."""

    async def closing(message: Message) -> None:
        if message["type"] == "http.response.start":
            kept = [(name, value) for name, value in message.get("headers", [])
                    if name.lower() != b"connection"]
            message = {**message, "headers": [*kept, (b"connection", b"close")]}
        elif message["type"] == "http.response.body" and not message.get("more_body"):
            await send({**message, "more_body": True})
            if drain:
                await drop_body(receive)
            message = {"type": "http.response.body", "body": b""}
        await send(message)

    return closing


async def drop_body(receive: Receive) -> None:
    """Read the request body to its end and drop it, holding none of it; stop early when
    the client leaves, or when the body pauses or runs past its deadline (the 408 that
    :class:`service.api.body_timeout.BodyTimeoutMiddleware` raises bounds this wait as
    it bounds every body's)."""
    try:
        while True:
            message = await receive()
            if message["type"] != "http.request" or not message.get("more_body"):
                return
    except ApiError:
        return
