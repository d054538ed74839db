"""JobStore: records as per-field hashes, atomic state transitions, state counts."""

from __future__ import annotations

import numpy as np
import pytest
import redis

from models.formation import SensorParams
from worker.job_store import JobStore
from worker.jobs import JobError, JobNotFoundError, JobState, validate_job_id
from worker.queue import JobQueue
from worker.redis_keys import job_done_channel

PARAMS = SensorParams(encoding="modulo", bits=8)


@pytest.fixture
def job_id(queue: JobQueue) -> str:
    return queue.submit("reconstruction", np.zeros((4, 4), np.uint8), PARAMS, "itoh").id


def test_transition_checks_current_state(client: redis.Redis, job_id: str) -> None:
    store = JobStore(client)
    assert store.transition(job_id, JobState.RUNNING, [JobState.QUEUED], attempts=1) == (
        True,
        JobState.QUEUED,
    )
    assert store.transition(job_id, JobState.RUNNING, [JobState.QUEUED]) == (
        False,
        JobState.RUNNING,
    )
    record = store.load(job_id)
    assert record.state is JobState.RUNNING and record.attempts == 1
    assert store.states()["running"] == 1 and store.states()["queued"] == 0


def test_transition_of_missing_job(client: redis.Redis) -> None:
    assert JobStore(client).transition("a" * 32, JobState.RUNNING, [JobState.QUEUED]) == (
        False,
        None,
    )


def test_a_finishing_transition_sets_the_expiry_in_the_same_step(
    client: redis.Redis, job_id: str
) -> None:
    store = JobStore(client)
    store.transition(job_id, JobState.RUNNING, [JobState.QUEUED])
    assert client.ttl(f"job:{job_id}") == -1
    changed, _ = store.transition(
        job_id, JobState.SUCCEEDED, [JobState.RUNNING], expire_s=3600, progress=1.0
    )
    assert changed
    assert 3590 <= client.ttl(f"job:{job_id}") <= 3600
    assert store.load(job_id).progress == 1.0


def test_a_refused_transition_sets_no_expiry(client: redis.Redis, job_id: str) -> None:
    store = JobStore(client)
    changed, previous = store.transition(
        job_id, JobState.SUCCEEDED, [JobState.RUNNING], expire_s=60
    )
    assert (changed, previous) == (False, JobState.QUEUED)
    assert client.ttl(f"job:{job_id}") == -1


def test_update_keeps_state_and_other_fields(client: redis.Redis, job_id: str) -> None:
    store = JobStore(client)
    store.update(job_id, progress=0.5, frames_done=3, timings_ns={"decode": 7})
    store.transition(job_id, JobState.CANCELLED, [JobState.QUEUED])
    store.update(job_id, info={"note": "x"})
    record = store.load(job_id)
    assert record.state is JobState.CANCELLED
    assert (record.progress, record.frames_done, record.timings_ns) == (0.5, 3, {"decode": 7})
    assert record.info == {"note": "x"}
    with pytest.raises(ValueError, match="transition"):
        store.update(job_id, state=JobState.QUEUED)


def test_an_update_of_a_record_that_is_gone_makes_no_half_record(
    client: redis.Redis, job_id: str
) -> None:
    """A worker's progress for a job whose record is gone (expired after a stalled
    worker's job finished elsewhere, or lost with Redis's data) made a record of those
    fields alone, never expiring: every later read of the job failed on its missing
    fields, and the API answered 500 where it answers 404."""
    store = JobStore(client)
    client.delete(f"job:{job_id}")
    assert store.update(job_id, progress=0.5, frames_done=3) is False
    assert not client.exists(f"job:{job_id}")
    with pytest.raises(JobNotFoundError):
        store.load(job_id)


def test_finished_transition_announces(client: redis.Redis, job_id: str) -> None:
    pubsub = client.pubsub(ignore_subscribe_messages=True)
    pubsub.subscribe(job_done_channel(job_id))
    error = JobError(code="output_overflow", message="too bright")
    JobStore(client).transition(job_id, JobState.FAILED, [JobState.QUEUED], error=error)
    messages = [pubsub.get_message(timeout=1) for _ in range(3)]
    assert [m["data"] for m in messages if m is not None] == [b"failed"]
    assert JobStore(client).load(job_id).error == error
    pubsub.close()


def test_load_rejects_bad_ids(client: redis.Redis) -> None:
    with pytest.raises(JobNotFoundError, match="32 hexadecimal"):
        JobStore(client).load("job:1")


def test_a_long_malformed_job_id_is_echoed_cut_short() -> None:
    with pytest.raises(JobNotFoundError, match=r"\(and 9920 more characters\): job ids are"):
        validate_job_id("z" * 10_000)
