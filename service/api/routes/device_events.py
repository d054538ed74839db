"""``/v1/devices/{id}/events``: a server-sent event stream of what happens to a device's
frames, resumable by event id. Event types: ``frame`` (reconstructed), ``failed``,
``stale`` (a frame whose sequence number is not past the last stored one: a repeat, or a
second daemon under the same device id), ``drop`` (``new`` frames dropped, ``causes`` as
``cause:count`` pairs, e.g. ``redis_unavailable:33``) and ``reconnect``.

Each open stream holds a Redis connection blocked on ``XREAD``, so at most
``MCAM_MAX_EVENT_STREAMS`` are open at once; past that a new one gets 503 with
``Retry-After`` (200 streams from one read key took 213 Redis connections and 413 file
descriptors, and nothing ended them).
"""

from __future__ import annotations

import json
import re
from collections.abc import AsyncIterator
from typing import Annotated

import redis
from fastapi import APIRouter, Header, Query
from fastapi.responses import StreamingResponse

from models.errors import InvalidInputError, echo
from service.api.deps import ReadKey, StateDep
from service.api.errors import ApiError
from service.api.routes.devices import DEVICE_ERRORS, as_text, known_device
from service.api.schemas import error_response
from service.api.state import Slots
from worker.embedded_redis import connect_async
from worker.redis_keys import DEVICES_SET, events_stream

router = APIRouter(prefix="/v1/devices", tags=["devices"])
#: How long one events poll blocks before a keep-alive comment (ms).
EVENTS_BLOCK_MS = 1000
#: Seconds a client refused for want of a stream slot is asked to wait.
RETRY_AFTER_S = 5


#: An event id as the stream's ``id:`` lines send it: ``<ms>-<seq>``.
_ENTRY_ID = re.compile(r"[0-9]+-[0-9]+")
#: What ``since`` takes besides an event id, and what each means.
_SINCE_WORDS = {"$": "new events only", "0": "every kept event"}


def _check_entry_id(name: str, value: str | None, words: dict[str, str]) -> None:
    """Refuse what is not an event id (``<ms>-<seq>``) nor one of ``words`` (a value
    with its meaning), and an id Redis would reject once the stream has started: both
    parts of ``<ms>-<seq>`` are unsigned 64-bit integers."""
    if value is None or value in words:
        return
    if not _ENTRY_ID.fullmatch(value):
        others = "".join(f", {word} for {meaning}" for word, meaning in words.items())
        raise InvalidInputError(
            f"{name} {echo(value)} is not an event id: give the id of the last event "
            f"received ('<ms>-<seq>', as the stream's id: lines send it){others}, or leave "
            "it out for new events"
        )
    if any(len(part) > 20 or int(part) >= 2**64 for part in value.split("-")):
        raise InvalidInputError(
            f"{name} {echo(value)} is not an event id: both parts of '<ms>-<seq>' are below "
            "2^64; resume from the last id the stream sent, or leave it out for new events"
        )


def _entry_key(entry_id: str) -> tuple[int, int]:
    ms, _, seq = entry_id.partition("-")
    return int(ms), int(seq or 0)


def _resume_point(client: redis.Redis, device: str, requested: str) -> tuple[str, str | None]:
    """Where an event stream starts (an entry id; ``$``: after the newest), and a ``reset``
    event when ``requested`` lies beyond every event the device has had: Redis lost its
    data or the id was made up, so the client would otherwise wait for ever. It then
    gets every event kept, from the oldest."""
    newest = client.xrevrange(events_stream(device), count=1)
    newest_id = as_text(newest[0][0]) if newest else "0-0"
    if requested == "$":
        return newest_id, None
    if requested == "0" or _entry_key(requested) <= _entry_key(newest_id):
        return requested, None
    reset = {"type": "reset", "requested": requested, "newest": newest_id,
             "reason": "the requested event id is newer than any event of this device; "
                       "the stream starts again from its oldest kept event"}
    return "0", f"event: reset\ndata: {json.dumps(reset)}\n\n"


def _refusal(limit: int) -> str:
    """Why a stream was refused, and what to do."""
    return (f"{limit} event streams are open, the most this server keeps "
            "(MCAM_MAX_EVENT_STREAMS); close one or retry shortly")


def _stream_error(code: str, message: str) -> str:
    """An ``error`` event that ends a started stream, asking the client to retry in
    :data:`RETRY_AFTER_S`."""
    body = json.dumps({"code": code, "message": message})
    return f"retry: {RETRY_AFTER_S * 1000}\nevent: error\ndata: {body}\n\n"


async def _event_lines(
    url: str, device: str, since: str, limit: int | None, slots: Slots,
    preamble: str | None = None,
) -> AsyncIterator[str]:
    """Server-sent events from ``events:<device>``, after entry ``since``, while one of
    ``slots`` is held. Async, on a connection of its own: a waiting client holds no
    thread (as a blocking generator, each held one of the server's 40 for a second per
    poll, and 100 idle clients made every other request wait 3-8 s). It ends with an
    ``error`` event when Redis fails, or once the device is forgotten (looked at while
    no event comes: it kept a forgotten device's stream open for ever)."""
    if not slots.take():  # the route saw a free slot; another stream took it since
        yield _stream_error("too_many_streams", _refusal(slots.limit))
        return
    client = connect_async(url)
    sent = 0
    stream = events_stream(device)
    last = since
    try:
        yield "retry: 2000\n\n"
        if preamble:
            yield preamble
        while limit is None or sent < limit:
            try:
                reply = await client.xread({stream: last}, count=64, block=EVENTS_BLOCK_MS)
                forgotten = not reply and not await client.sismember(DEVICES_SET, device)
            except redis.RedisError as exc:
                # Redis went away (restarted, full, unreachable): the stream ends with
                # the reason, and the client resumes from its last id when told to retry.
                yield _stream_error("queue_unavailable", f"the event stream lost Redis "
                                    f"({exc}); reconnecting resumes after the last event")
                return
            if forgotten:
                yield _stream_error("not_found", (
                    f"device {device!r} was forgotten (DELETE /v1/devices/{device}): no more "
                    "events come; a daemon that comes back registers it again"
                ))
                return
            if not reply:
                yield ": keep-alive\n\n"
                continue
            for _, entries in reply:
                for entry_id, fields in entries:
                    last = as_text(entry_id)
                    data = {as_text(k): as_text(v) for k, v in fields.items()}
                    yield f"id: {last}\nevent: {data.get('type', 'message')}\n" \
                          f"data: {json.dumps(data)}\n\n"
                    sent += 1
                    if limit is not None and sent >= limit:
                        return
    finally:
        slots.release()
        await client.aclose()


@router.get("/{device_id}/events",
            responses={**DEVICE_ERRORS, 503: error_response(
                "too_many_streams (MCAM_MAX_EVENT_STREAMS open; see Retry-After) or the queue "
                "(Redis) is unavailable"
            )},
            summary="Server-sent events: frame, failed, stale, drop (with causes), reconnect",
            response_class=StreamingResponse)
def events(device_id: str, state: StateDep, _key: ReadKey,
           since: Annotated[str, Query(
               description="an event id '<ms>-<seq>' to resume after, 0 for every kept "
                           "event, or $ for new events only")] = "$",
           limit: Annotated[int | None, Query(ge=1, le=100_000)] = None,
           last_event_id: Annotated[str | None, Header(
               description="the id of the last event received ('<ms>-<seq>'); "
                           "overrides since")] = None,
           ) -> StreamingResponse:
    device = known_device(state, device_id)
    _check_entry_id("since", since, _SINCE_WORDS)
    _check_entry_id("Last-Event-ID", last_event_id, {})
    if state.event_slots.full:
        raise ApiError(503, "too_many_streams", _refusal(state.event_slots.limit),
                       headers={"Retry-After": str(RETRY_AFTER_S)})
    start, preamble = _resume_point(state.client, device, last_event_id or since)
    lines = _event_lines(state.redis_url, device, start, limit, state.event_slots, preamble)
    return StreamingResponse(lines, media_type="text/event-stream",
                             headers={"Cache-Control": "no-cache"})
