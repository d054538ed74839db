"""Idempotency keys in Redis: one API key's ``Idempotency-Key`` -> the job its request made.

A request carrying an idempotency key holds it (:func:`hold_key`, one atomic script:
the value ``{"pending": token}`` set only where no value is, for ``pending_s`` seconds)
before its body is read. The submit that queues its job (:meth:`worker.queue.JobQueue.submit`
with an :class:`IdempotentSubmit`) stores, in the same script as the job, ``{"job": id,
"fingerprint": hex}`` for ``ttl_s`` seconds, and only while the hold is still this
request's: two requests with one key never both queue a job. A request that ends
without a job (refused, cut off) gives its hold back (:func:`release`), so that a retry
may make the job; a Redis that could not be told then (restarting) is told again in the
background until it is, or the hold has expired. A hold left by an API process that died
expires after ``pending_s``.
A key whose job's record is gone before the key (``MCAM_RESULT_RETENTION_S`` after the
job's end, which may come first) is held anew by the next request with it
(:func:`hold_key` with ``gone``), as if it were not remembered: that request makes a new
job, where a 404 for the gone job would answer every repeat for the rest of the key's
life.

The value is stored under :func:`worker.redis_keys.idempotency_key`: a hash of the
client's key, scoped to the API key's id (two API keys may use the same idempotency key).
"""

from __future__ import annotations

import json
import logging
import threading
import time
import uuid
from dataclasses import dataclass

import redis

from models.errors import McamError

log = logging.getLogger(__name__)

#: Seconds between the background tries to give back a hold Redis could not be told of.
RELEASE_RETRY_S = 1.0

#: Hold KEYS[1] with ARGV[1] for ARGV[2] s unless it has a value other than the one naming
#: the job ARGV[3] (whose record is gone; '': none); returns that value (or nil).
_HOLD = """
local held = redis.call('GET', KEYS[1])
if held and (ARGV[3] == '' or cjson.decode(held)['job'] ~= ARGV[3]) then return held end
redis.call('SET', KEYS[1], ARGV[1], 'EX', ARGV[2])
return false
"""
#: Delete KEYS[1] if its value is still ARGV[1].
_RELEASE = """
if redis.call('GET', KEYS[1]) == ARGV[1] then return redis.call('DEL', KEYS[1]) end
return 0
"""


class IdempotencyKeyInUseError(McamError):
    """Another request with the same idempotency key is still being handled (its upload
    received, decoded or queued); the client should ask again shortly."""

    code = "idempotency_key_in_use"
    http_status = 409
    retry_after_s = 1


@dataclass(frozen=True)
class Earlier:
    """What an earlier request with the key left: its job's id and its request's
    fingerprint."""

    job_id: str
    fingerprint: str


@dataclass(frozen=True)
class Pending:
    """An earlier request with the key is still being handled: it has no job yet."""


@dataclass(frozen=True)
class KeyHold:
    """This request's hold on an idempotency key (``value`` is what :func:`hold_key` wrote)."""

    store_key: str
    value: str
    ttl_s: int
    pending_s: int

    def submit(self, job_id: str, fingerprint: str) -> IdempotentSubmit:
        """What the submit of job ``job_id`` stores for the key, the request's body
        hashing to ``fingerprint``."""
        done = json.dumps({"job": job_id, "fingerprint": fingerprint})
        return IdempotentSubmit(job_id, self.store_key, self.value, done, self.ttl_s)


@dataclass(frozen=True)
class IdempotentSubmit:
    """A submit of the job ``job_id`` that records it under an idempotency key: only while
    ``held`` is the key's value (or it has none), then ``done`` for ``ttl_s`` s, with the
    job, atomically."""

    job_id: str
    store_key: str
    held: str
    done: str
    ttl_s: int


def parse(value: bytes | str) -> Earlier | Pending:
    """What a stored value says."""
    stored = json.loads(value)
    return Pending() if "pending" in stored else Earlier(stored["job"], stored["fingerprint"])


def hold_key(
    client: redis.Redis, store_key: str, pending_s: int, ttl_s: int, gone: str = ""
) -> KeyHold | Earlier | Pending:
    """Hold ``store_key`` for this request (for ``pending_s`` s; its job is then kept
    ``ttl_s`` s), or what an earlier request with it left. ``gone``, the id of a job whose
    record no longer exists, lets the hold replace what the request that made it left."""
    value = json.dumps({"pending": uuid.uuid4().hex})
    pending = max(int(pending_s), 1)
    held = client.register_script(_HOLD)(keys=[store_key], args=[value, pending, gone])
    if held is None:
        return KeyHold(store_key, value, max(int(ttl_s), 1), pending)
    return parse(held)


def lookup(client: redis.Redis, store_key: str) -> Earlier | Pending | None:
    """What the requests with the key left (None: no request with it is remembered)."""
    value = client.get(store_key)
    return None if value is None else parse(value)


def _give_back(client: redis.Redis, hold: KeyHold) -> None:
    """Delete the hold's key if its value is still the hold's."""
    client.register_script(_RELEASE)(keys=[hold.store_key], args=[hold.value])


def release(client: redis.Redis, hold: KeyHold) -> None:
    """Give the key back unless the request's job was stored under it: a request that
    ended without a job lets a retry make it. A Redis that cannot be told (restarting,
    unreachable) is told again every :data:`RELEASE_RETRY_S` s by a background thread
    until it is or the hold has expired (its ``pending_s``, 610 s by default), so that
    the request's retries are not answered 409 ``idempotency_key_in_use`` for all that
    time after the request ended with 503. That is logged, not raised: the request's own
    answer (an error, or its job) matters more."""
    try:
        _give_back(client, hold)
    except redis.exceptions.RedisError as exc:
        log.warning("idempotency key %s not given back yet, trying again in the background "
                    "for up to %d s: %s", hold.store_key, hold.pending_s, exc)  # fmt: skip
        deadline = time.monotonic() + hold.pending_s
        threading.Thread(
            target=_give_back_until, args=(client, hold, deadline), daemon=True,
            name="idempotency-release",
        ).start()  # fmt: skip


def _give_back_until(client: redis.Redis, hold: KeyHold, deadline: float) -> None:
    """Try :func:`_give_back` every :data:`RELEASE_RETRY_S` s until it succeeds or the
    monotonic ``deadline`` (the hold's expiry at the latest) passes."""
    while time.monotonic() < deadline:
        time.sleep(RELEASE_RETRY_S)
        try:
            _give_back(client, hold)
        except redis.exceptions.RedisError:
            continue
        log.info("idempotency key %s given back", hold.store_key)
        return
    log.warning("idempotency key %s left held until it expired", hold.store_key)
