"""The web viewer, mounted at ``/`` behind the API's routes, and the API's own misses.

A mount at ``/`` matches every path, so without this module a request the API's routes
did not take (a wrong method on ``/v1/reconstructions``, or a misspelt ``/v1/jobz``)
reached the viewer's static files and got their answer: ``405 Allow: GET, HEAD`` for a
route that takes POST, or a 404 that named no way on. :class:`ViewerMount` answers those
for the API: a 405 whose ``Allow`` lists the methods the path's routes take, and a 404
under the API's prefixes that points to the documentation. Every other path is the
viewer's.
"""

from __future__ import annotations

import re

from starlette.exceptions import HTTPException
from starlette.routing import BaseRoute
from starlette.types import ASGIApp, Receive, Scope, Send

from service.api.errors import ApiError
from service.api.route_match import allowed_methods

#: Path prefixes that belong to the API, not to the viewer's files.
API_PREFIXES: tuple[str, ...] = ("/v1/", "/health/", "/metrics")
#: A job-creating collection followed by one more segment: where a client looks for the
#: job a POST made (``/v1/videos/{id}``), which lives at ``/v1/jobs/{id}``.
JOB_GUESS = re.compile(r"^/v1/(?:reconstructions|videos)/([^/]+)/?$")


def viewer_error(exc: HTTPException, scope: Scope) -> HTTPException:
    """The viewer's own 404 or 405 (from its static files) told in words; any other
    error as it was."""
    path = scope["path"]
    if exc.status_code == 405:
        return ApiError(
            405,
            "method_not_allowed",
            f"{scope['method']} is not accepted at {path}: the web viewer's files take GET "
            "and HEAD",
            headers=exc.headers,
        )
    if exc.status_code == 404:
        return ApiError(
            404, "not_found",
            f"no file {path} in the web viewer (open / for the viewer, /docs for the API)",
        )
    return exc


class ViewerMount:
    """ASGI app for the ``/`` mount: the API's 405s and 404s, else the viewer ``app``.

    ``routes`` are the API's routers' routes (their full path templates).
    """

    def __init__(self, viewer: ASGIApp, routes: list[BaseRoute]) -> None:
        self.viewer = viewer
        self.routes = routes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.viewer(scope, receive, send)
            return
        self.refuse_api_misses(scope)
        try:
            await self.viewer(scope, receive, send)
        except HTTPException as exc:
            raise viewer_error(exc, scope) from exc

    def refuse_api_misses(self, scope: Scope) -> None:
        """Raise the API's answer for a request no route took, if the path is the API's."""
        path = scope["path"]
        outer = {**scope, "root_path": scope.get("app_root_path", "")}  # not the mount's
        methods = allowed_methods(self.routes, outer)
        if methods:
            allow = ", ".join(sorted(methods))
            raise ApiError(
                405,
                "method_not_allowed",
                f"{scope['method']} is not accepted at {path}; it accepts {allow} "
                "(the API's routes and methods are listed at /docs)",
                headers={"Allow": allow},
            )
        if path.startswith(API_PREFIXES) or path in ("/v1", "/health"):
            raise ApiError(404, "not_found", miss_message(path))


def miss_message(path: str) -> str:
    """What a 404 under the API's prefixes says: where a job's status is, for a path
    that looks for one under the collection that made it (:data:`JOB_GUESS`), and
    where the API's routes are listed."""
    guess = JOB_GUESS.match(path)
    hint = f"; a job's status is at /v1/jobs/{guess.group(1)}" if guess else ""
    return f"no API resource at {path}{hint}; the API's routes are listed at /docs"
