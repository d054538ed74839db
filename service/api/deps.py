"""Typed FastAPI dependencies: the process state, the settings, and authenticated callers.

``ReadKey`` / ``SubmitKey`` authenticate the Bearer API key (401 without or with
an unknown key, 403 without the scope) and count the request against the key's
rate limit (429 with ``Retry-After``).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Annotated

import redis
from fastapi import Depends, Query, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from models.errors import InvalidInputError
from service.api.errors import ApiError
from service.api.state import ServiceState
from service.core.config import Settings
from service.core.security import ApiKey
from worker.redis_memory import is_transient

log = logging.getLogger(__name__)

bearer = HTTPBearer(
    auto_error=False,
    description="An API key: `Authorization: Bearer <key>`. The embedded default prints "
    "the generated key on first start and stores it in `<data dir>/api_keys`.",
)


def get_state(request: Request) -> ServiceState:
    """The running process's :class:`ServiceState`."""
    state: ServiceState = request.app.state.mcam
    return state


StateDep = Annotated[ServiceState, Depends(get_state)]


def get_settings(state: StateDep) -> Settings:
    """The settings the app was created with."""
    return state.settings


SettingsDep = Annotated[Settings, Depends(get_settings)]
Credentials = Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)]


def _unauthorized(message: str) -> ApiError:
    return ApiError(401, "unauthorized", message, headers={"WWW-Authenticate": "Bearer"})


def _check_rate(state: ServiceState, key: ApiKey) -> None:
    try:
        retry_after = state.limiter.retry_after(key)
    except redis.exceptions.TimeoutError:
        raise  # a hung Redis: answer 503 now rather than wait for it again in the route
    except redis.exceptions.RedisError as exc:
        if is_transient(exc):
            state.redis_trouble.warn("rate limit", exc, then="not enforced meanwhile")
        else:
            log.warning("rate limit not enforced: Redis refused it (%s)", exc)
        return
    if retry_after is not None:
        raise ApiError(
            429,
            "rate_limited",
            f"this API key made more than {state.limiter.per_minute} requests in the last minute; "
            f"retry in {retry_after} s",
            headers={"Retry-After": str(retry_after)},
        )


def _no_bearer_key(request: Request) -> ApiError:
    """The 401 of a request without a Bearer key: none sent, or an ``Authorization``
    header of another form (the key alone, another scheme, ``Bearer`` with no key), which
    was told the key was missing. The header is not echoed: it may hold the key."""
    if request.headers.get("authorization") is None:
        return _unauthorized("missing API key: send the header 'Authorization: Bearer <key>'")
    return _unauthorized(
        "the Authorization header is not 'Bearer <key>' (the key alone, another scheme, or "
        "no key after Bearer): send the header 'Authorization: Bearer <key>'"
    )


def require(scope: str) -> Callable[[Request, ServiceState, Credentials], ApiKey]:
    """A dependency accepting keys that hold ``scope`` (``read`` or ``submit``)."""

    def authenticated(request: Request, state: StateDep, credentials: Credentials) -> ApiKey:
        if credentials is None:
            raise _no_bearer_key(request)
        key = state.keyring.authenticate(credentials.credentials)
        if key is None:
            raise _unauthorized("unknown API key: check the key (see the data dir's api_keys)")
        if scope not in key.scopes:
            raise ApiError(
                403, "forbidden",
                f"this API key lacks the {scope!r} scope needed here; use a key that has it "
                f"(in MCAM_API_KEYS or the data dir's api_keys: KEY for every scope, or "
                f"KEY:{scope})",
            )  # fmt: skip
        _check_rate(state, key)
        return key

    return authenticated


ReadKey = Annotated[ApiKey, Depends(require("read"))]
SubmitKey = Annotated[ApiKey, Depends(require("submit"))]

#: A preview's exposure in EV, finite (``nan`` was refused as "less than or equal to 30").
Exposure = Annotated[
    float,
    Query(
        ge=-30, le=30, allow_inf_nan=False,
        description="EV of the PNG preview (format=png; any other file refuses it)",
    ),
]  # fmt: skip


def refuse_unused_exposure(request: Request, asked: str, preview: str) -> None:
    """422 ``invalid_input`` when the query gives ``exposure`` but asks (``asked``, e.g.
    ``part=winding&format=npy``) for another file than the tonemapped ``preview`` (e.g.
    ``format=png``), which alone it shapes: ``?exposure=2`` alone got the EXR, unchanged,
    as if it had not been given."""
    if asked != preview and "exposure" in request.query_params:
        raise InvalidInputError(
            f"exposure sets the EV of the tonemapped preview ({preview}) only, and this asks "
            f"for {asked}, which it does not change; ask for {preview} with it, or leave "
            "exposure out"
        )
