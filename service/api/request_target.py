"""A request target in absolute form (``GET http://host/v1/decoders``) is routed by its path.

RFC 9112 3.2.2: a server must accept a request target in absolute form, which clients
send to a proxy and may send to a server. uvicorn passes the whole URL on as the path,
which no route matched: ``GET http://x/v1/decoders`` got 404 "Not Found", naming no way
on, and its metrics were labelled ``unmatched``. :class:`RequestTargetMiddleware` makes
such a request the one its path names, with the URL's authority as its ``Host`` (the RFC
has the server ignore the Host header then), and answers a target that is neither a path
nor an absolute URL (``v1/decoders``, ``*``) with 400.
"""

from __future__ import annotations

from urllib.parse import unquote, urlsplit

from fastapi.responses import JSONResponse
from starlette.types import ASGIApp, Receive, Scope, Send

from service.api.errors import error_body

#: URL schemes an absolute-form target may have.
SCHEMES = ("http", "https")


def origin_form(scope: Scope) -> bool:
    """Rewrite ``scope`` (in place, so that the middleware outside sees the route) from an
    absolute-form target to its path and ``Host``; False if its target is neither that
    nor a path."""
    if scope["path"].startswith("/"):
        return True
    raw = scope.get("raw_path") or scope["path"].encode()
    try:
        url = urlsplit(raw.decode("latin-1"))
        hostname = url.hostname
    except ValueError:  # e.g. "Invalid IPv6 URL" for http://[/x
        return False
    if url.scheme.lower() not in SCHEMES or not hostname:
        return False
    path = url.path or "/"
    scope["path"] = unquote(path)
    scope["raw_path"] = path.encode("latin-1")
    host = url.netloc.rpartition("@")[2].encode("latin-1")
    scope["headers"] = [(name, value) for name, value in scope["headers"] if name != b"host"]
    scope["headers"].append((b"host", host))
    return True


class RequestTargetMiddleware:
    """ASGI middleware routing an absolute-form request by its path (see the module)."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or origin_form(scope):
            await self.app(scope, receive, send)
            return
        refusal = JSONResponse(
            error_body(
                "bad_request",
                "the request target must be a path starting with / (or an absolute "
                "http:// URL); send e.g. 'GET /v1/decoders HTTP/1.1'",
            ),
            status_code=400,
        )
        await refusal(scope, receive, send)
