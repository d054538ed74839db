"""HEAD on every GET URL: the headers a GET would send (status, type, length), no body.

FastAPI routes answer only the methods they declare, so a HEAD fell through to the
viewer's static mount and got 404 on every API URL (a download manager or a link
checker asks HEAD first). This middleware runs the GET and sends its headers and an
empty body; a streamed GET (server-sent events) is told the client left, so it stops.
"""

from __future__ import annotations

import asyncio

from starlette.types import ASGIApp, Message, Receive, Scope, Send


class HeadRequestMiddleware:
    """ASGI middleware answering ``HEAD`` as the ``GET`` of the same URL without its body."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] != "HEAD":
            await self.app(scope, receive, send)
            return
        answered = asyncio.Event()

        async def head_receive() -> Message:
            """The client's messages, or a disconnect once the headers went out."""
            if answered.is_set():
                return {"type": "http.disconnect"}
            receiving = asyncio.ensure_future(receive())
            waiting = asyncio.ensure_future(answered.wait())
            done, pending = await asyncio.wait(
                {receiving, waiting}, return_when=asyncio.FIRST_COMPLETED
            )
            for task in pending:
                task.cancel()
            return receiving.result() if receiving in done else {"type": "http.disconnect"}

        async def head_send(message: Message) -> None:
            """Headers as the GET sends them; its body replaced by one empty message."""
            if message["type"] != "http.response.body":
                await send(message)
            elif not answered.is_set():
                answered.set()
                await send({"type": "http.response.body", "body": b"", "more_body": False})

        await self.app({**scope, "method": "GET"}, head_receive, head_send)
