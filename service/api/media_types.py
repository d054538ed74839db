"""The media type a request declares, as the API's body readers and errors compare it."""

from __future__ import annotations

from starlette.requests import Request


def media_type(request: Request) -> str:
    """The request's ``Content-Type`` without parameters, lower case ('' when absent)."""
    return request.headers.get("content-type", "").split(";")[0].strip().lower()
