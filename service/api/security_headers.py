"""Security response headers: ``nosniff`` on every response, a strict policy on the viewer.

The web viewer keeps the API key in ``localStorage``, so its pages get a Content
Security Policy that runs only the viewer's own scripts and styles, loads images only
from itself, ``blob:`` (decoded results) and ``data:`` (the inline SVG favicon), talks
only to its own origin and cannot be framed (clickjacking), plus ``no-referrer``; a
browser revalidates them on each load (``no-cache``), so it never runs an old script.
The API documentation (``/docs``, :mod:`service.api.routes.docs`) has a policy of its
own that still allows no other origin.
"""

from __future__ import annotations

from starlette.datastructures import MutableHeaders
from starlette.types import ASGIApp, Message, Receive, Scope, Send

#: The web viewer's Content Security Policy.
VIEWER_CSP = "; ".join(
    (
        "default-src 'self'",
        "img-src 'self' blob: data:",
        "script-src 'self'",
        "style-src 'self'",
        "connect-src 'self'",
        "frame-ancestors 'none'",
        "base-uri 'none'",
        "form-action 'self'",
        "object-src 'none'",
    )
)
#: The API documentation's policy (``/docs``): Swagger UI from this server only; its page
#: starts it with an inline script and styles its own elements inline.
DOCS_CSP = "; ".join(
    (
        "default-src 'self'",
        "img-src 'self' data:",
        "script-src 'self' 'unsafe-inline'",
        "style-src 'self' 'unsafe-inline'",
        "connect-src 'self'",
        "frame-ancestors 'none'",
        "base-uri 'none'",
        "object-src 'none'",
    )
)
#: Headers of every response: no content-type sniffing of results or errors.
API_HEADERS: dict[str, str] = {"X-Content-Type-Options": "nosniff"}


def page_headers(policy: str) -> dict[str, str]:
    """Headers of a page for a browser: ``policy`` as its Content Security Policy, no
    framing, no referrer."""
    return {
        **API_HEADERS,
        "Content-Security-Policy": policy,
        "X-Frame-Options": "DENY",
        "Referrer-Policy": "no-referrer",
    }


#: Headers of the viewer's files (``service/static``): revalidated on each load (304
#: while unchanged). Sent with ``Last-Modified`` alone, a browser kept them fresh for a
#: tenth of their age and ran an old ``app.js``, holding the key, against an upgraded API.
VIEWER_HEADERS = {**page_headers(VIEWER_CSP), "Cache-Control": "no-cache"}
#: Headers of the API documentation page (``/docs``).
DOCS_HEADERS = page_headers(DOCS_CSP)


class SecurityHeaders:
    """ASGI middleware setting ``headers`` on every HTTP response of ``app`` (replacing
    any the app set under the same names)."""

    def __init__(self, app: ASGIApp, headers: dict[str, str]) -> None:
        self.app = app
        self.headers = headers

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return

        async def send_with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                response_headers = MutableHeaders(scope=message)
                for name, value in self.headers.items():
                    response_headers[name] = value
            await send(message)

        await self.app(scope, receive, send_with_headers)
