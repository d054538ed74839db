"""Job records in Redis (``job:<id>`` hashes) with atomic state transitions.

Usage::

    store = JobStore(client)
    record = store.load(job_id)                         # JobNotFoundError if absent
    store.state(job_id)                                 # JobState, None if absent
    store.transition(job_id, JobState.RUNNING, {JobState.QUEUED}, started_ns=...)
    store.update(job_id, progress=0.5, frames_done=3)  # fields other than state

Each top-level field of :class:`~worker.jobs.JobRecord` is one hash field holding
its JSON value, so the API's cancel and the worker's progress writes never
overwrite each other. State changes go through one Lua script that checks the
current state and keeps the ``jobs:states`` counts and, for a job that ends, the
``jobs_processed_total`` counter (:mod:`worker.metrics`) in the same step: a process
stopped right after the change still has the job counted, once.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from typing import Any

import redis

from worker.jobs import JobNotFoundError, JobRecord, JobState, validate_job_id
from worker.metrics import counter_key
from worker.redis_keys import JOB_STATES, job_done_channel, job_key

_TRANSITION = """
local current = redis.call('HGET', KEYS[1], 'state')
if not current then return {0, ''} end
local allowed = false
for i = 3, 2 + tonumber(ARGV[2]) do
  if ARGV[i] == current then allowed = true end
end
if not allowed then return {0, current} end
redis.call('HSET', KEYS[1], 'state', ARGV[1])
local ttl = tonumber(ARGV[3 + tonumber(ARGV[2])])
for i = 4 + tonumber(ARGV[2]), #ARGV, 2 do
  redis.call('HSET', KEYS[1], ARGV[i], ARGV[i + 1])
end
if ttl > 0 then redis.call('EXPIRE', KEYS[1], ttl) end
redis.call('HINCRBY', KEYS[2], cjson.decode(current), -1)
redis.call('HINCRBY', KEYS[2], cjson.decode(ARGV[1]), 1)
if KEYS[3] then redis.call('HINCRBY', KEYS[3], cjson.decode(ARGV[1]), 1) end
return {1, current}
"""


#: Set fields ARGV (name, value, ...) of hash KEYS[1] only if it exists; 1 if it did.
_UPDATE = """
if redis.call('EXISTS', KEYS[1]) == 0 then return 0 end
redis.call('HSET', KEYS[1], unpack(ARGV))
return 1
"""

#: Let KEYS[1] expire ARGV[1] s from now unless it expires already.
_EXPIRE_UNSET = """
if redis.call('TTL', KEYS[1]) == -1 then redis.call('EXPIRE', KEYS[1], ARGV[1]) end
"""


def encode_fields(values: dict[str, Any]) -> dict[str, str]:
    """JSON-encode each field value (JobRecord fields, already in JSON mode)."""
    return {name: json.dumps(value, separators=(",", ":")) for name, value in values.items()}


def record_fields(record: JobRecord) -> dict[str, str]:
    """The hash fields of a whole record."""
    return encode_fields(record.model_dump(mode="json"))


def field_pairs(fields: dict[str, Any]) -> list[str]:
    """Record ``fields`` as a script's ARGV: name, JSON value, name, JSON value, ..."""
    values = JobRecord.model_construct(**fields).model_dump(mode="json", include=set(fields))
    return [item for pair in encode_fields(values).items() for item in pair]


class JobStore:
    """Reads and updates job records."""

    def __init__(self, client: redis.Redis) -> None:
        self.client = client
        self._transition = client.register_script(_TRANSITION)
        self._update = client.register_script(_UPDATE)
        self._expire_unset = client.register_script(_EXPIRE_UNSET)

    def load(self, job_id: str) -> JobRecord:
        """The record of ``job_id``; :class:`JobNotFoundError` if unknown or malformed id."""
        raw = self.client.hgetall(job_key(validate_job_id(job_id)))
        if not raw:
            raise JobNotFoundError(
                f"no job {job_id!r}: unknown, or finished longer ago than this server keeps "
                "jobs (MCAM_RESULT_RETENTION_S), its record and results expired; check the "
                "id, or submit the job again"
            )
        return JobRecord.model_validate({k.decode(): json.loads(v) for k, v in raw.items()})

    def state(self, job_id: str) -> JobState | None:
        """The job's state now; None when it has no record (expired, or never was)."""
        raw = self.client.hget(job_key(job_id), "state")
        return None if raw is None else JobState(json.loads(raw))

    def update(self, job_id: str, **fields: Any) -> bool:
        """Set fields other than ``state`` (progress, timings, info, ...) of an existing
        record; returns whether there was one. A record that is gone (expired after a
        worker that stalled past the claim idle time finished elsewhere, or lost with
        Redis's data) is not made again from these fields alone: such a half record
        broke every later read of the job (its other fields missing), for ever."""
        if "state" in fields:
            raise ValueError("change the state with transition()")
        pairs = field_pairs(fields)
        return bool(self._update(keys=[job_key(job_id)], args=pairs))

    def transition(
        self,
        job_id: str,
        to: JobState,
        allowed_from: Iterable[JobState],
        expire_s: float | None = None,
        **fields: Any,
    ) -> tuple[bool, JobState | None]:
        """Move to state ``to`` if the current state is in ``allowed_from`` and set
        ``fields`` with it, atomically; with ``expire_s``, the record expires that many
        seconds later, set in the same step (no reader sees a finished job that would
        never expire). Returns (changed, previous state or None if the record does not
        exist). Finished states are counted in ``jobs_processed_total`` (in the same
        step) and notify waiters."""
        allowed = [json.dumps(state.value) for state in allowed_from]
        pairs = field_pairs(fields)
        ttl = max(int(expire_s), 1) if expire_s is not None else 0
        counted = [counter_key("jobs_processed_total")] if to.finished else []
        changed, previous = self._transition(
            keys=[job_key(job_id), JOB_STATES, *counted],
            args=[json.dumps(to.value), len(allowed), *allowed, ttl, *pairs],
        )
        if changed and to.finished:
            self.client.publish(job_done_channel(job_id), to.value)
        return bool(changed), JobState(json.loads(previous)) if previous else None

    def expire(self, job_id: str, seconds: float) -> None:
        """Let a finished job's record expire (with its results) after ``seconds``,
        unless it expires already: a job that succeeded or failed got its expiry with its
        end, as its result files their age, and a later delivery of its entry (a worker
        stopped before it dropped it) that set the full term again kept the record, with
        its links, for that long after the retention purge had deleted its files."""
        self._expire_unset(keys=[job_key(job_id)], args=[max(int(seconds), 1)])

    def states(self) -> dict[str, int]:
        """Jobs per state (every state listed, zeros included): queued and running count
        current jobs; finished states count every job that ended so, including records
        since expired by retention."""
        raw = self.client.hgetall(JOB_STATES)
        counts = {k.decode(): int(v) for k, v in raw.items()}
        return {state.value: max(counts.get(state.value, 0), 0) for state in JobState}
