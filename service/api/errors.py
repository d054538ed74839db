"""Every error the API returns is JSON ``{"code", "message"}`` with a stable code (and
``parameters``, the form fields the message asks to give, where it asks for some).

Caller mistakes (:class:`McamError`, validation, unknown routes, oversized bodies)
keep their own status; an unreachable queue is 503, and so is a full one (Redis at
its ``maxmemory``, :mod:`worker.redis_memory`); a client that closes the connection
before its body arrived is 499 (as nginx logs it), answered to no one; only a real bug is
a 500.
"""

from __future__ import annotations

import logging
import sys
from typing import Any

import redis
from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException
from starlette.requests import ClientDisconnect
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from models.errors import McamError
from service.api.media_types import media_type
from worker.redis_memory import UNREACHABLE, is_out_of_memory, store_full_error

log = logging.getLogger(__name__)

#: The status of a request whose client left before its body arrived (nginx's 499): no
#: response reaches anyone, but the metrics and the log say what happened.
CLIENT_CLOSED = 499

#: Stable codes for plain HTTP errors raised by the framework or by us.
STATUS_CODES: dict[int, str] = {
    400: "bad_request",
    401: "unauthorized",
    403: "forbidden",
    404: "not_found",
    405: "method_not_allowed",
    406: "not_acceptable",
    408: "request_timeout",
    409: "conflict",
    413: "image_too_large",
    415: "unsupported_format",
    422: "invalid_input",
    429: "rate_limited",
    CLIENT_CLOSED: "client_closed_request",
    503: "unavailable",
}


class ApiError(HTTPException):
    """An HTTP error with a stable code (raised inside request handling, e.g. auth)."""

    def __init__(
        self, status: int, code: str, message: str, headers: dict[str, str] | None = None
    ) -> None:
        super().__init__(status, detail={"code": code, "message": message}, headers=headers)


def error_body(code: str, message: str, **extra: Any) -> dict[str, Any]:
    """The JSON body of an error response."""
    return {"code": code, "message": message, **extra}


def _location(loc: tuple[Any, ...] | list[Any]) -> str:
    parts = [str(p) for p in loc if p not in ("body", "query", "path", "header")]
    return ".".join(parts) or "request"


async def mcam_error(_: Request, exc: Exception) -> JSONResponse:
    """The error's JSON, with ``Retry-After`` when retrying later mends it (a full
    queue, a key's share of it, a full store), and the ``parameters`` it asks for."""
    assert isinstance(exc, McamError)
    headers = None if exc.retry_after_s is None else {"Retry-After": str(exc.retry_after_s)}
    extra = {"parameters": list(exc.parameters)} if exc.parameters else {}
    return JSONResponse(
        error_body(exc.code, exc.message, **extra), status_code=exc.http_status, headers=headers
    )


def _problem(error: dict[str, Any], empty_body: bool) -> dict[str, str]:
    """One validation error as ``{"field", "message"}``; a body that is not JSON at all
    is named as such (FastAPI reports it at the character offset where parsing failed),
    and so is a request without a body (``empty_body``) where one is required (it was
    "request: Field required"), and a required query parameter left out (``GET
    /v1/jobs`` without ``idempotency_key`` said "idempotency_key: Field required")."""
    if error.get("type") == "json_invalid":
        reason = error.get("ctx", {}).get("error", "not JSON")
        offset = error["loc"][-1]
        return {
            "field": "body",
            "message": f"not valid JSON ({reason} at character {offset}); send a JSON "
            "object with the header 'Content-Type: application/json'",
        }
    if empty_body and error.get("type") == "missing" and tuple(error["loc"]) == ("body",):
        return {
            "field": "body",
            "message": "the request has no body; send a JSON object with the header "
            "'Content-Type: application/json'",
        }
    if error.get("type") == "missing" and tuple(error["loc"][:1]) == ("query",):
        name = error["loc"][-1]
        return {
            "field": str(name),
            "message": f"this route needs the query parameter {name} (?{name}=...; /docs "
            "says what it is)",
        }
    return {"field": _location(error["loc"]), "message": error["msg"]}


def _without_body(request: Request) -> bool:
    """Whether ``request`` came without a body (no length, or length 0, and not chunked)."""
    headers = request.headers
    return headers.get("content-length", "0") == "0" and "transfer-encoding" not in headers


async def validation_error(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, RequestValidationError)
    empty_body = _without_body(request)
    details = [_problem(err, empty_body) for err in exc.errors()]
    problems = [f"{detail['field']}: {detail['message']}" for detail in details]
    message = "invalid request: " + "; ".join(problems)
    media = media_type(request)
    body_errors = any(tuple(err["loc"][:1]) == ("body",) for err in exc.errors())
    if body_errors and media != "application/json" and not empty_body:
        message += (
            f" (the body came as {media or 'no content type'!r} and was not read: send a "
            "JSON object with the header 'Content-Type: application/json')"
        )
    return JSONResponse(error_body("invalid_input", message, details=details), status_code=422)


#: FastAPI's words for a JSON body its parser gave up on (too deeply nested, say).
UNPARSED_BODY = "There was an error parsing the body"


def unparsed_body_message(cause: BaseException | None) -> str:
    """What was wrong with a JSON body FastAPI's parser gave up on (``cause``: what
    ``json.loads`` raised), and what to send instead. An integer past Python's digit
    limit (``sys.get_int_max_str_digits``, 4300) is valid JSON, not nesting."""
    if isinstance(cause, ValueError) and "integer string conversion" in str(cause):
        return (
            f"the JSON body could not be parsed: an integer in it has more than "
            f"{sys.get_int_max_str_digits()} digits; send each number within its field's "
            "documented range"
        )
    return (
        "the JSON body could not be parsed (nested too deeply, or not JSON); send a flat "
        "JSON object of the documented fields"
    )


async def client_closed(request: Request, _: Exception) -> JSONResponse:
    """The client closed the connection while its body was arriving (Starlette's
    :class:`ClientDisconnect`): one line in the log and a 499 that no one receives,
    counted as such in ``mcam_http_request_duration_seconds``; it was logged as an
    internal error with a 50-line traceback and counted as a 500."""
    log.info("%s %s: the client closed the connection before its body arrived (499)",
             request.method, request.url.path)  # fmt: skip
    return JSONResponse(
        error_body(STATUS_CODES[CLIENT_CLOSED], "the client closed the connection "
                   "before the request body arrived; send the whole body"),
        status_code=CLIENT_CLOSED,
    )


async def http_error(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, HTTPException)
    if isinstance(exc.__cause__, ClientDisconnect):  # FastAPI's 400 for a JSON body cut off
        return await client_closed(request, exc.__cause__)
    if isinstance(exc.detail, dict):
        body = error_body(exc.detail["code"], exc.detail["message"])
    elif exc.status_code == 400 and exc.detail == UNPARSED_BODY:
        body = error_body("bad_request", unparsed_body_message(exc.__cause__))
    else:
        body = error_body(STATUS_CODES.get(exc.status_code, "error"), str(exc.detail))
    return JSONResponse(body, status_code=exc.status_code, headers=exc.headers)


async def redis_error(_: Request, exc: Exception) -> JSONResponse:
    log.warning("queue unreachable: %s", exc)
    return JSONResponse(
        error_body("queue_unavailable", "the job queue (Redis) is unreachable; retry shortly"),
        status_code=503,
        headers={"Retry-After": "5"},
    )


def internal_error() -> JSONResponse:
    """The 500 answered for a bug (logged by the caller)."""
    return JSONResponse(
        error_body("internal_error", "an internal error occurred; it has been logged"),
        status_code=500,
    )


async def redis_refusal(request: Request, exc: Exception) -> JSONResponse:
    """Redis answered with an error: at its ``maxmemory`` (503 ``store_full``: nothing of
    the request was stored, retry later), else a bug (logged, 500)."""
    if is_out_of_memory(exc):
        log.warning("Redis is full (maxmemory): %s %s refused", request.method, request.url.path)
        return await mcam_error(request, store_full_error())
    log.error("Redis refused a command on %s %s", request.method, request.url.path, exc_info=exc)
    return internal_error()


class InternalErrorMiddleware:
    """ASGI middleware turning a bug (any exception no handler took) into a logged JSON
    500. Starlette's own handler for ``Exception`` answers and then re-raises, so the
    server drops the connection and the client's next request on it fails too; this
    one answers and lets the connection live. A bug after the response started (a
    stream) can only end that response."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = False

        async def tracked_send(message: Message) -> None:
            nonlocal started
            started = started or message["type"] == "http.response.start"
            await send(message)

        try:
            await self.app(scope, receive, tracked_send)
        except Exception:
            if started:
                raise
            log.exception("internal error on %s %s", scope["method"], scope["path"])
            await internal_error()(scope, receive, send)


def install_error_handlers(app: FastAPI) -> None:
    """Register the JSON error handlers on ``app`` and, innermost of its middleware,
    :class:`InternalErrorMiddleware` (install before any other middleware)."""
    app.add_exception_handler(McamError, mcam_error)
    app.add_exception_handler(RequestValidationError, validation_error)
    app.add_exception_handler(HTTPException, http_error)
    app.add_exception_handler(ClientDisconnect, client_closed)
    for unreachable in UNREACHABLE:
        app.add_exception_handler(unreachable, redis_error)
    app.add_exception_handler(redis.exceptions.ResponseError, redis_refusal)
    app.add_middleware(InternalErrorMiddleware)
