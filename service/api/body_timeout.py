"""A request body must keep arriving: a pause longer than the limit ends it with 408.

uvicorn waits for ever for the rest of a body, so a client sending a byte now and then
(or nothing after its headers) held a connection and a server task indefinitely. While
a request's body is incomplete, each wait for its next chunk is bounded by
``MCAM_HTTP_BODY_TIMEOUT_S``; once the body is complete the wait is the app's own (a
server-sent event stream waits for the client to leave). A request whose *headers*
never finish never reaches the app: the server's protocol times that out
(:mod:`service.api.header_timeout`).
"""

from __future__ import annotations

import asyncio

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.api.errors import ApiError


def body_timed_out(timeout_s: float) -> ApiError:
    """The 408 for a body that paused longer than ``timeout_s``."""
    return ApiError(
        408,
        "request_timeout",
        f"the request body stopped arriving for {timeout_s:g} s; send it again without "
        "pauses (MCAM_HTTP_BODY_TIMEOUT_S)",
    )


class BodyTimeoutMiddleware:
    """ASGI middleware: each chunk of an incomplete request body within ``timeout_s``."""

    def __init__(self, app: ASGIApp, timeout_s: float) -> None:
        self.app = app
        self.timeout_s = timeout_s

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        complete = False

        async def timed_receive() -> Message:
            nonlocal complete
            if complete:
                return await receive()
            try:
                message = await asyncio.wait_for(receive(), self.timeout_s)
            except TimeoutError:
                raise body_timed_out(self.timeout_s) from None
            complete = message["type"] != "http.request" or not message.get("more_body")
            return message

        await self.app(scope, timed_receive, send)
