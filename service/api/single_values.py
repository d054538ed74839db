"""Query parameters and form fields: each given once, and only those the route takes.

FastAPI reads a scalar query parameter given twice (``?part=image&part=winding``,
``?gain=2&gain=3``) as its last value and says nothing, and so did the upload routes'
form fields (``-F gain=2 -F gain=3``): the client got the W map, or a frame simulated
at a gain, it may not have meant. :func:`single_query_values`, a dependency of every
API route, and the upload reader (:mod:`service.api.uploads`) answer such a request
with 422 naming the parameter and the values it came with.

A query parameter the route does not take (``?exposur=2``, ``?fromat=png``) was
ignored on the routes that declare their query one parameter at a time: the misspelt
preview came at EV 0, or as the EXR, while the upload routes refused one
(``extra="forbid"``). :func:`known_query_names` answers it with 422 naming the
parameters the route takes.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterable

from fastapi import Request
from fastapi.dependencies.models import Dependant
from fastapi.exceptions import RequestValidationError
from pydantic import BaseModel

from models.errors import ECHO_CHARS, echo

#: How many of a repeated parameter's values its error names.
SHOWN = 3
#: Parameters that take several values as one comma-separated value (a video's
#: ``outputs``): repeated, they are told to join them, not to give one.
COMMA_SEPARATED = frozenset({"outputs"})


def shown(name: str) -> str:
    """A parameter's name for an error: whole, or cut short as :func:`echo` cuts text (a
    client's 10 KB name must not make a 10 KB error)."""
    return name if len(name) <= ECHO_CHARS else echo(name)


def repeated(items: Iterable[tuple[str, str]]) -> dict[str, list[str]]:
    """The names given more than once among ``items`` (name, value), with their values."""
    values: dict[str, list[str]] = defaultdict(list)
    for name, value in items:
        values[name].append(value)
    return {name: given for name, given in values.items() if len(given) > 1}


def refuse_repeated(items: Iterable[tuple[str, str]], where: tuple[str, ...] = ()) -> None:
    """422 ``invalid_input`` (a :class:`RequestValidationError` located under ``where``,
    e.g. ``("query",)``; form fields are located by their name alone, as the upload
    routes' other field errors) if any name among ``items`` is given more than once."""
    problems = [
        {
            "type": "repeated_parameter",
            "loc": (*where, shown(name)),
            "msg": f"given {len(given)} times ({', '.join(echo(v) for v in given[:SHOWN])}"
            f"{', ...' if len(given) > SHOWN else ''}); give it once{_joined(name, given)}",
        }
        for name, given in repeated(items).items()
    ]
    if problems:
        raise RequestValidationError(problems)


def _joined(name: str, given: list[str]) -> str:
    """For a :data:`COMMA_SEPARATED` parameter, how to give its values ``given`` at once
    (``name=A,B`` when that is short enough to echo); '' for any other."""
    if name not in COMMA_SEPARATED:
        return ""
    joined = ",".join(given)
    return f", its values comma-separated: {name}={joined if len(joined) <= ECHO_CHARS else 'A,B'}"


def single_query_values(request: Request) -> None:
    """Refuse a request that gives a query parameter more than once (a route dependency)."""
    refuse_repeated(request.query_params.multi_items(), ("query",))


def query_names(dependant: Dependant) -> frozenset[str]:
    """The query parameters a route's ``dependant`` (with its dependencies) takes; a
    pydantic model read from the query (``Annotated[Fields, Query()]``) takes its fields."""
    names: set[str] = set()
    pending = [dependant]
    while pending:
        current = pending.pop()
        for field in current.query_params:
            model = field.field_info.annotation
            if isinstance(model, type) and issubclass(model, BaseModel):
                names.update(info.alias or name for name, info in model.model_fields.items())
            else:
                names.add(field.alias)
        pending.extend(current.dependencies)
    return frozenset(names)


def known_query_names(request: Request) -> None:
    """Refuse (422) a query parameter that the matched route, one that declares query
    parameters, does not take (a route dependency). A route that declares none has none
    to misspell, or reads its query itself (a recording's start and stop)."""
    route = request.scope["route"]
    taken = query_names(route.dependant)
    if not taken:
        return
    problems = [
        {
            "type": "unknown_parameter",
            "loc": ("query", shown(name)),
            "msg": f"not a query parameter of {request.method} {route.path}; it takes "
            f"{', '.join(sorted(taken))}",
        }
        for name in dict.fromkeys(request.query_params) if name not in taken
    ]
    if problems:
        raise RequestValidationError(problems)
