"""Which of the API's routes a request's path is for, whatever its method.

The router answers this only for the requests it routes. A request refused before
routing (a body over the limit) or answered by the viewer's mount at ``/`` (a wrong
method) still belongs to an API route: its metrics are labelled with that route's
template and its 405 lists that route's methods.
"""

from __future__ import annotations

from collections.abc import Iterable

from starlette.routing import BaseRoute, Match, Route
from starlette.types import Scope


def path_routes(routes: Iterable[BaseRoute], scope: Scope) -> list[Route]:
    """The routes among ``routes`` whose path template matches ``scope``'s path."""
    return [
        route
        for route in routes
        if isinstance(route, Route) and route.matches(scope)[0] is not Match.NONE
    ]


def allowed_methods(routes: Iterable[BaseRoute], scope: Scope) -> set[str]:
    """The methods the routes at ``scope``'s path take, with HEAD where GET is
    (:mod:`service.api.head_requests` answers it)."""
    methods = {method for route in path_routes(routes, scope) for method in route.methods or ()}
    return methods | {"HEAD"} if "GET" in methods else methods


def route_template(routes: Iterable[BaseRoute], scope: Scope) -> str | None:
    """The path template of the first route at ``scope``'s path, or None."""
    found = path_routes(routes, scope)
    return found[0].path if found else None
