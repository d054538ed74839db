"""The ``Idempotency-Key`` request header (IETF httpapi draft) of the routes that queue a job.

A client that may send a job-creating POST twice (a camera rig retrying after a dropped
connection, the viewer's Cancel pressed before the answer came) sends a key of its own
making with it, one per job it means (a UUID, say). Per API key (two API keys may use the
same idempotency key):

- the first request with the key holds it before its body is read, and stores it with
  its job in the same Redis step that queues the job (:mod:`worker.idempotency`); a
  request refused or cut off gives it back, so that a retry may make the job;
- a repeat with the same route, parameters, file name and file bytes (compared by a
  SHA-256 of them) within ``MCAM_IDEMPOTENCY_TTL_S`` gets that job, answered as a
  first request is (202, or 200 with the finished job under ``Prefer: wait``), and
  queues nothing;
- a repeat with anything else is 422 ``idempotency_key_reused``;
- a repeat while the first is still being received, decoded or queued is 409
  ``idempotency_key_in_use`` with ``Retry-After`` (the draft's answer), without its body
  being read;
- ``GET /v1/jobs?idempotency_key=...`` finds the job (404 when no request with it is
  remembered, 409 while one is being handled), so a client that gave up on the answer
  can follow or cancel the job without sending the file again.

A key is 1-255 printable ASCII characters (space to ``~``), bare or, as the draft
writes it, in double quotes (``"8e03978e-..."`` and ``8e03978e-...`` are one key);
anything else, or the header on several lines naming different keys, is 400
``invalid_idempotency_key``.
"""

from __future__ import annotations

import hashlib
import json
import re
import uuid
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from dataclasses import dataclass
from typing import Annotated

import anyio
from fastapi import Header, Request
from pydantic import BaseModel
from starlette.concurrency import run_in_threadpool

from models.errors import echo
from service.api.errors import ApiError
from service.api.in_turn import decode_in_turn
from service.api.single_values import SHOWN
from service.api.state import ServiceState
from service.api.uploads import Model, Upload, read_upload_fields
from service.core.config import Settings
from service.core.security import ApiKey
from worker.idempotency import (
    Earlier,
    IdempotencyKeyInUseError,
    IdempotentSubmit,
    KeyHold,
    Pending,
    hold_key,
    lookup,
    release,
)
from worker.jobs import JobRecord
from worker.redis_keys import idempotency_key

#: Most characters of a key (a UUID takes 36).
MAX_KEY_CHARS = 255
#: Seconds a request may take to decode and queue its upload once it waited for its turn,
#: on top of the body's deadline and the decode wait: how long a key stays held by an API
#: process that died mid-request (its repeats get 409 meanwhile).
DECODE_ALLOWANCE_S = 300
_PRINTABLE = re.compile(r"[\x20-\x7e]*")
KEY_RULE = (
    "1-255 printable ASCII characters (space to '~'), e.g. a UUID, bare or in double "
    "quotes; send a new key for each new job and the same key when repeating a request"
)
HEADER_DESCRIPTION = (
    "makes the request safe to repeat (IETF httpapi Idempotency-Key draft): a repeat with "
    "this key from this API key within MCAM_IDEMPOTENCY_TTL_S gets the first request's "
    "job, never a second one; the same key with other parameters, another file or file name is 422 "
    "idempotency_key_reused, a repeat while the first is still being handled 409 "
    "idempotency_key_in_use (see Retry-After). GET /v1/jobs?idempotency_key=... finds the "
    f"job. A key is {KEY_RULE}"
)
IdempotencyHeader = Annotated[
    str | None, Header(alias="Idempotency-Key", description=HEADER_DESCRIPTION)
]


def client_key(value: str) -> str:
    """The idempotency key ``value`` names (the draft's quoted form unquoted); 400
    ``invalid_idempotency_key`` for an empty, too long or not printable ASCII one."""
    key = value[1:-1] if len(value) >= 2 and value[0] == value[-1] == '"' else value
    problem = (
        "is empty" if not key
        else f"has {len(key)} characters" if len(key) > MAX_KEY_CHARS
        else f"holds characters other than printable ASCII ({echo(key)})"
        if not _PRINTABLE.fullmatch(key)
        else None
    )  # fmt: skip
    if problem is not None:
        raise ApiError(400, "invalid_idempotency_key",
                       f"the Idempotency-Key {problem}: send {KEY_RULE}")
    return key


def refuse_repeated_key(request: Request) -> None:
    """400 ``invalid_idempotency_key`` for a request with ``Idempotency-Key`` lines naming
    different keys: which one names the job cannot be told (the first was taken, the
    others never remembered, and a lookup or repeat with one of them found no job)."""
    lines = request.headers.getlist("idempotency-key")
    if len({client_key(line) for line in lines}) > 1:
        sent = ", ".join(echo(line) for line in lines[:SHOWN])
        raise ApiError(
            400, "invalid_idempotency_key",
            f"the Idempotency-Key header came {len(lines)} times with different keys "
            f"({sent}{', ...' if len(lines) > SHOWN else ''}): send it once, {KEY_RULE}",
        )  # fmt: skip


def pending_s(settings: Settings) -> int:
    """Seconds a request holds its key before its job is queued, at most: its body's
    deadline, the wait for a decode turn and :data:`DECODE_ALLOWANCE_S`."""
    return int(settings.http_body_deadline_s + settings.decode_wait_s + DECODE_ALLOWANCE_S)


def fingerprint(route: str, fields: BaseModel, upload: Upload) -> str:
    """SHA-256 (hex) of what makes a request's job: its route, its parameters as read
    (query and form fields alike, defaults included), its file's name and bytes."""
    said = {"route": route, "fields": fields.model_dump(mode="json"), "file": upload.filename}
    digest = hashlib.sha256(json.dumps(said, sort_keys=True).encode())
    digest.update(b"\0")
    digest.update(upload.data)
    return digest.hexdigest()


@dataclass(frozen=True)
class Once:
    """A job-creating request's idempotency key: its own hold, or what an earlier request
    with the key left (its job and fingerprint)."""

    state: ServiceState
    found: KeyHold | Earlier

    def repeat_or_new(
        self, route: str, upload: Upload, fields: BaseModel
    ) -> tuple[JobRecord | None, IdempotentSubmit | None]:
        """The earlier request's job if this request repeats it (422 if it differs), else
        how to submit this one's job under the key."""
        made = fingerprint(route, fields, upload)
        if isinstance(self.found, KeyHold):
            return None, self.found.submit(uuid.uuid4().hex, made)
        if made != self.found.fingerprint:
            raise ApiError(
                422, "idempotency_key_reused",
                "this Idempotency-Key was sent before with another request (other "
                "parameters, another file or file name, or the other route): send a new "
                "key for a new job, or repeat the first request unchanged, its file under "
                "the same name, to get its job",
            )  # fmt: skip
        return self.state.queue.get(self.found.job_id), None


def _hold(state: ServiceState, owner: ApiKey, key: str) -> Once:
    """Hold ``key`` for ``owner``'s request, or what an earlier request left; 409 while
    that one is still being handled. The key, once its job is queued, is kept
    ``MCAM_IDEMPOTENCY_TTL_S`` seconds from the queueing, whatever
    ``MCAM_RESULT_RETENTION_S`` is (that counts from the job's end). A key naming a job
    whose record is gone (expired) is held anew: that request is not remembered any more
    than its job."""
    settings = state.settings
    ttl_s = int(settings.idempotency_ttl_s)
    store_key = idempotency_key(owner.id, key)
    found = hold_key(state.client, store_key, pending_s(settings), ttl_s)
    if isinstance(found, Earlier) and state.queue.jobs.state(found.job_id) is None:
        found = hold_key(state.client, store_key, pending_s(settings), ttl_s, found.job_id)
    if isinstance(found, Pending):
        raise in_use()
    return Once(state, found)


def in_use() -> IdempotencyKeyInUseError:
    """The 409 for a key whose first request is still being handled."""
    return IdempotencyKeyInUseError(
        "a request with this Idempotency-Key is still being received, decoded or queued; "
        "ask again after Retry-After (GET /v1/jobs?idempotency_key=... then finds its job)"
    )


@asynccontextmanager
async def idempotent(
    state: ServiceState, owner: ApiKey, header: str | None
) -> AsyncIterator[Once | None]:
    """The request's :class:`Once` (None without the header) for the body of the ``with``,
    in which the request reads its upload and queues its job; a hold the request did not
    turn into a job is given back on leaving, however it left."""
    if header is None:
        yield None
        return
    once = await run_in_threadpool(_hold, state, owner, client_key(header))
    try:
        yield once
    finally:
        if isinstance(once.found, KeyHold):
            with anyio.CancelScope(shield=True):
                await run_in_threadpool(release, state.client, once.found)


async def queued_job(
    request: Request,
    query: Model,
    model: type[Model],
    state: ServiceState,
    owner: ApiKey,
    header: str | None,
    submit: Callable[..., JobRecord],
) -> JobRecord:
    """The job of an upload route's request: read its upload with the parameters
    ``model`` takes, then the earlier request's job if it repeats one with its
    ``Idempotency-Key`` (``header``), else ``submit(state, upload, fields, owner,
    idempotent submit or None)``'s, run in a decode turn."""
    refuse_repeated_key(request)
    async with idempotent(state, owner, header) as once:
        upload, fields = await read_upload_fields(request, model, query)
        record, submission = None, None
        if once is not None:
            route = request.url.path
            record, submission = await run_in_threadpool(
                once.repeat_or_new, route, upload, fields
            )
        if record is None:
            record = await decode_in_turn(state, submit, state, upload, fields, owner, submission)
        return record


def job_by_key(state: ServiceState, owner: ApiKey, value: str) -> JobRecord:
    """The job ``owner``'s request with the idempotency key ``value`` made: 404 when no
    such request is remembered, 409 while it is still being handled."""
    earlier = lookup(state.client, idempotency_key(owner.id, client_key(value)))
    if earlier is None:
        raise ApiError(
            404, "not_found",
            "no request with this Idempotency-Key from this API key is remembered: none "
            "reached POST /v1/reconstructions or /v1/videos whole, or it was refused (no "
            "job was made for either), or it came more than MCAM_IDEMPOTENCY_TTL_S ago "
            "(its job, if any, is found by its id only); the other routes take no key",
        )  # fmt: skip
    if isinstance(earlier, Pending):
        raise in_use()
    return state.queue.get(earlier.job_id)
