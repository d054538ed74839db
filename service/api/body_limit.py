"""Upload size limit enforced while the body streams in (never buffered whole first).

A declared ``Content-Length`` above the limit is refused before any byte is
read; a chunked body is counted as it arrives and refused the moment it
crosses the limit. Both answer 413 with code ``image_too_large``.
"""

from __future__ import annotations

import json

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.api.errors import ApiError, error_body


def too_large(limit: int) -> ApiError:
    """The 413 error for a body above ``limit`` bytes."""
    return ApiError(
        413,
        "image_too_large",
        f"the request body exceeds the upload limit of {limit} bytes; "
        "send a smaller file or raise MCAM_MAX_UPLOAD_BYTES",
    )


class BodyLimitMiddleware:
    """ASGI middleware: at most ``limit`` request-body bytes per request."""

    def __init__(self, app: ASGIApp, limit: int) -> None:
        self.app = app
        self.limit = limit

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = dict(scope["headers"]).get(b"content-length")
        if declared is not None and declared.isdigit() and int(declared) > self.limit:
            await self._refuse(send)
            return
        received = 0

        async def limited_receive() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.limit:
                    raise too_large(self.limit)
            return message

        await self.app(scope, limited_receive, send)

    async def _refuse(self, send: Send) -> None:
        detail = too_large(self.limit).detail
        body = json.dumps(error_body(detail["code"], detail["message"])).encode()
        await send(
            {
                "type": "http.response.start",
                "status": 413,
                "headers": [
                    (b"content-type", b"application/json"),
                    (b"content-length", str(len(body)).encode()),
                    (b"connection", b"close"),
                ],
            }
        )
        await send({"type": "http.response.body", "body": body})
