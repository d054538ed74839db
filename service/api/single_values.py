"""A query parameter or form field given more than once is refused, not read as its last value.

FastAPI reads a scalar query parameter given twice (``?part=image&part=winding``,
``?gain=2&gain=3``) as its last value and says nothing, and so did the upload routes'
form fields (``-F gain=2 -F gain=3``): the client got the W map, or a frame simulated
at a gain, it may not have meant. :func:`single_query_values`, a dependency of every
API route, and the upload reader (:mod:`service.api.uploads`) answer such a request
with 422 naming the parameter and the values it came with.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterable

from fastapi import Request
from fastapi.exceptions import RequestValidationError

from models.errors import echo

#: How many of a repeated parameter's values its error names.
SHOWN = 3


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
            "loc": (*where, name),
            "msg": f"given {len(given)} times ({', '.join(echo(v) for v in given[:SHOWN])}"
            f"{', ...' if len(given) > SHOWN else ''}); give it once",
        }
        for name, given in repeated(items).items()
    ]
    if problems:
        raise RequestValidationError(problems)


def single_query_values(request: Request) -> None:
    """Refuse a request that gives a query parameter more than once (a route dependency)."""
    refuse_repeated(request.query_params.multi_items(), ("query",))
