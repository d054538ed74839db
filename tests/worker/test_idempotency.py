"""Idempotency keys in Redis: held before a request's body is read, stored with its job in
the submit's own step, given back by a request that made no job."""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any

import pytest
import redis

from tests.worker.test_queue import CODES, PARAMS
from worker.idempotency import (
    Earlier,
    IdempotencyKeyInUseError,
    KeyHold,
    Pending,
    hold_key,
    lookup,
    release,
)
from worker.queue import JobQueue
from worker.redis_keys import JOBS_STREAM, idempotency_key

STORE_KEY = idempotency_key("owner", "key-1")


def held(client: redis.Redis) -> KeyHold:
    """A new hold on :data:`STORE_KEY` (none there before)."""
    hold = hold_key(client, STORE_KEY, pending_s=60, ttl_s=3600)
    assert isinstance(hold, KeyHold)
    return hold


def test_the_submit_stores_the_job_under_the_key(queue: JobQueue, client: redis.Redis) -> None:
    hold = held(client)
    assert isinstance(hold_key(client, STORE_KEY, 60, 3600), Pending)
    assert isinstance(lookup(client, STORE_KEY), Pending)
    record = queue.submit("reconstruction", CODES, PARAMS, "itoh",
                          idempotency=hold.submit("a" * 32, "f" * 64))
    assert record.id == "a" * 32
    assert lookup(client, STORE_KEY) == Earlier("a" * 32, "f" * 64)
    assert hold_key(client, STORE_KEY, 60, 3600) == Earlier("a" * 32, "f" * 64)
    assert 3500 < client.ttl(STORE_KEY) <= 3600
    release(client, hold)  # a hold turned into a job stays
    assert lookup(client, STORE_KEY) == Earlier("a" * 32, "f" * 64)


def test_a_hold_lost_to_another_request_queues_nothing(
    queue: JobQueue, client: redis.Redis
) -> None:
    """A request whose hold expired while it decoded, and which another request with the
    key then took, makes no second job."""
    first = held(client)
    client.delete(STORE_KEY)  # expired
    second = held(client)
    with pytest.raises(IdempotencyKeyInUseError):
        queue.submit("reconstruction", CODES, PARAMS, "itoh",
                     idempotency=first.submit("a" * 32, "f" * 64))
    assert client.xlen(JOBS_STREAM) == 0
    release(client, first)  # not its hold any more: the other's stays
    assert json.loads(client.get(STORE_KEY)) == json.loads(second.value)


def test_a_request_that_made_no_job_gives_the_key_back(client: redis.Redis) -> None:
    release(client, held(client))
    assert lookup(client, STORE_KEY) is None
    held(client)


def test_a_key_whose_job_is_gone_is_held_anew_only_for_that_job(
    queue: JobQueue, client: redis.Redis
) -> None:
    """``gone`` names the job whose record expired: a hold replaces what its request left,
    never another job's value or a hold still pending."""
    record = queue.submit("reconstruction", CODES, PARAMS, "itoh",
                          idempotency=held(client).submit("a" * 32, "f" * 64))
    assert hold_key(client, STORE_KEY, 60, 3600, gone="b" * 32) == Earlier(record.id, "f" * 64)
    assert isinstance(hold_key(client, STORE_KEY, 60, 3600, gone=record.id), KeyHold)
    assert isinstance(hold_key(client, STORE_KEY, 60, 3600, gone=record.id), Pending)


class RestartingRedis:
    """A Redis client whose first script call fails as a restarting Redis's does."""

    def __init__(self, client: redis.Redis) -> None:
        self.client = client
        self.refused = False

    def register_script(self, script: str) -> Callable[..., Any]:
        """The script, run on the real client once one call has been refused."""
        run = self.client.register_script(script)

        def call(**kwargs: Any) -> Any:
            if not self.refused:
                self.refused = True
                raise redis.exceptions.ConnectionError("Connection refused")
            return run(**kwargs)

        return call


def test_a_hold_redis_could_not_be_told_of_is_given_back_once_it_answers(
    client: redis.Redis, wait_until: Callable[..., object]
) -> None:
    """A request that ended (503) while Redis restarted: its hold is given back once Redis
    answers, not kept till it expires (10 min by default), answering its retries 409."""
    release(RestartingRedis(client), held(client))  # type: ignore[arg-type]
    wait_until(lambda: lookup(client, STORE_KEY) is None, what="the hold given back")
    held(client)
