"""A request body must keep arriving, and arrive whole in time: 408 otherwise.

uvicorn waits for ever for the rest of a body, so a client sending a byte now and then
(or nothing after its headers) held a connection and a server task indefinitely. While
a request's body is incomplete, each wait for its next chunk is bounded by
``MCAM_HTTP_BODY_TIMEOUT_S``, and the whole body, from the app's first read of it, by
``MCAM_HTTP_BODY_DEADLINE_S`` (a chunked upload sending a byte every 20 s paused less
than the timeout each time and stayed open for good: 260 such sockets held 123 of the
server's connections). Once the body is complete the wait is the app's own (a
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


def body_too_slow(deadline_s: float) -> ApiError:
    """The 408 for a body still incomplete ``deadline_s`` after it was first read."""
    return ApiError(
        408,
        "request_timeout",
        f"the request body did not arrive whole within {deadline_s:g} s; send it faster, "
        "or a smaller file (MCAM_HTTP_BODY_DEADLINE_S)",
    )


class BodyTimeoutMiddleware:
    """ASGI middleware: each chunk of an incomplete request body within ``timeout_s``
    seconds, and the whole body within ``deadline_s`` seconds of the app's first read."""

    def __init__(self, app: ASGIApp, timeout_s: float, deadline_s: float) -> None:
        self.app = app
        self.timeout_s = timeout_s
        self.deadline_s = deadline_s

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        complete = False
        loop = asyncio.get_running_loop()
        deadline: float | None = None  # loop time, set at the first read

        async def timed_receive() -> Message:
            nonlocal complete, deadline
            if complete:
                return await receive()
            deadline = loop.time() + self.deadline_s if deadline is None else deadline
            left_s = deadline - loop.time()
            if left_s <= 0:
                raise body_too_slow(self.deadline_s)
            try:
                message = await asyncio.wait_for(receive(), min(self.timeout_s, left_s))
            except TimeoutError:
                if left_s < self.timeout_s:
                    raise body_too_slow(self.deadline_s) from None
                raise body_timed_out(self.timeout_s) from None
            complete = message["type"] != "http.request" or not message.get("more_body")
            return message

        await self.app(scope, timed_receive, send)
