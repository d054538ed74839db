"""JobQueue and publish_frame: submission, reject-when-full, drop-oldest, cancel, wait, stats."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import pytest
import redis

from models.errors import InvalidInputError
from models.formation import SensorParams
from tests.worker.test_device_consumer import device_worker, frame
from worker.frame_message import FrameMessage
from worker.job_store import JobStore
from worker.jobs import JobNotFoundError, JobState
from worker.metrics import read_metrics
from worker.queue import (
    GROUP,
    JobQueue,
    QueueFullError,
    TooManyJobsError,
    entry_codes,
    publish_frame,
)
from worker.queue_holds import QueueHolds
from worker.redis_keys import (
    JOB_BYTES_PER_KEY,
    JOBS_PER_KEY,
    JOBS_STREAM,
    events_stream,
    frame_stream,
)

PARAMS = SensorParams(encoding="modulo", bits=8)
CODES = np.arange(64, dtype=np.uint8).reshape(8, 8)


def test_submit_stores_record_and_raw_codes(queue: JobQueue, client: redis.Redis) -> None:
    record = queue.submit("reconstruction", CODES, PARAMS, "itoh", {"half": True})
    assert record.state is JobState.QUEUED and len(record.id) == 32
    assert record.frames_total == 1
    assert queue.get(record.id) == record
    [(_entry_id, fields)] = client.xrange(JOBS_STREAM)
    fields = {k.decode(): v for k, v in fields.items()}
    assert fields["job"].decode() == record.id
    assert fields["codes"] == CODES.tobytes()
    np.testing.assert_array_equal(entry_codes(fields), CODES)
    assert queue.stats()["jobs_by_state"]["queued"] == 1


def test_a_submit_retried_with_its_job_id_queues_the_job_once(
    queue: JobQueue, client: redis.Redis
) -> None:
    first = queue.submit("reconstruction", CODES, PARAMS, "itoh", job_id="a" * 32)
    again = queue.submit("reconstruction", CODES, PARAMS, "herraez", job_id="a" * 32)
    assert first.id == again.id == "a" * 32 and again.decoder == "itoh"
    assert client.xlen(JOBS_STREAM) == 1


def test_video_jobs_count_frames(queue: JobQueue) -> None:
    clip = np.zeros((5, 8, 8), np.uint8)
    record = queue.submit("video", clip, PARAMS, "itoh", {"mode": "temporal"})
    assert record.kind == "video" and record.frames_total == 5


def test_int_codes_are_stored_as_sensor_dtype(queue: JobQueue, client: redis.Redis) -> None:
    queue.submit("reconstruction", CODES.astype(np.int64), PARAMS, "itoh")
    fields = {k.decode(): v for k, v in client.xrange(JOBS_STREAM)[0][1].items()}
    assert entry_codes(fields).dtype == np.uint8


@pytest.mark.parametrize(
    ("kind", "codes", "decoder", "message"),
    [
        ("reconstruction", CODES.astype(np.float32), "itoh", "integers"),
        ("reconstruction", CODES.astype(np.uint16) + 300, "itoh", r"codes are >= 2\^8"),
        ("reconstruction", np.zeros((2, 2, 2, 2), np.uint8), "itoh", "H x W"),
        ("video", CODES, "itoh", "T x H x W"),
        ("reconstruction", CODES, "no-such-decoder", "unknown decoder"),
        ("sculpture", CODES, "itoh", "unknown job kind"),
        ("reconstruction", np.zeros((0, 4), np.uint8), "itoh", "empty"),
        # accepted, then failed in the worker: the net has no modulo model
        ("reconstruction", CODES, "mantissanet-base-noise", "no model for modulo frames"),
    ],
)
def test_bad_submissions_rejected(
    queue: JobQueue, client: redis.Redis, kind: str, codes: np.ndarray, decoder: str, message: str
) -> None:
    with pytest.raises(InvalidInputError, match=message):
        queue.submit(kind, codes, PARAMS, decoder)
    assert client.xlen(JOBS_STREAM) == 0


def test_full_jobs_stream_rejects_and_counts(client: redis.Redis) -> None:
    queue = JobQueue(client, maxlen=2, max_deliveries=3, claim_idle_ms=1000)
    queue.submit("reconstruction", CODES, PARAMS, "itoh")
    queue.submit("reconstruction", CODES, PARAMS, "itoh")
    with pytest.raises(QueueFullError) as info:
        queue.submit("reconstruction", CODES, PARAMS, "itoh")
    assert info.value.code == "queue_full" and info.value.http_status == 503
    assert client.xlen(JOBS_STREAM) == 2
    assert queue.stats()["jobs_by_state"]["queued"] == 2
    assert rejections(client) == {"queue_full": 1}


def rejections(client: redis.Redis) -> dict[str, float]:
    """mcam_jobs_rejected_total by reason."""
    rejected = {f.name: f for f in read_metrics(client)}["jobs_rejected_total"]
    return {sample.labels["reason"]: sample.value for sample in rejected.samples}


def bounded_queue(
    client: redis.Redis, *, per_key: int = 100, per_key_bytes: int = 10**6, max_bytes: int = 10**6
) -> JobQueue:
    return JobQueue(
        client, maxlen=100, max_deliveries=3, claim_idle_ms=1000, max_per_key=per_key,
        max_bytes_per_key=per_key_bytes, max_bytes=max_bytes,
    )  # fmt: skip


def test_a_key_with_its_limit_of_jobs_in_the_queue_is_refused_others_are_not(
    client: redis.Redis,
) -> None:
    queue = bounded_queue(client, per_key=2)
    first = queue.submit("reconstruction", CODES, PARAMS, "itoh", owner="alice")
    queue.submit("reconstruction", CODES, PARAMS, "itoh", owner="alice")
    with pytest.raises(TooManyJobsError, match="2 jobs in the queue") as info:
        queue.submit("reconstruction", CODES, PARAMS, "itoh", owner="alice")
    assert info.value.code == "too_many_jobs" and info.value.http_status == 429
    assert rejections(client) == {"key_jobs": 1}  # counted as a full stream before
    queue.submit("reconstruction", CODES, PARAMS, "itoh", owner="bob")
    queue.submit("reconstruction", CODES, PARAMS, "itoh")
    assert client.xlen(JOBS_STREAM) == 4
    QueueHolds(client).release(first.id)
    queue.submit("reconstruction", CODES, PARAMS, "itoh", owner="alice")


@pytest.mark.parametrize("end", [JobState.SUCCEEDED, JobState.FAILED, JobState.CANCELLED])
def test_a_job_holds_its_share_until_its_entry_is_released_once(
    client: redis.Redis, end: JobState
) -> None:
    """A finished or cancelled job whose entry is still in the stream still counts: a
    cancel-and-resubmit loop cannot grow the stream past a key's share."""
    queue = bounded_queue(client, per_key=1)
    record = queue.submit("reconstruction", CODES, PARAMS, "itoh", owner="alice")
    assert queue.stats()["held_bytes"] == CODES.nbytes
    store = JobStore(client)
    store.transition(record.id, JobState.RUNNING, {JobState.QUEUED})
    store.transition(record.id, end, {JobState.RUNNING})
    with pytest.raises(TooManyJobsError, match="until a worker drops it"):
        queue.submit("reconstruction", CODES, PARAMS, "itoh", owner="alice")
    holds = QueueHolds(client)
    assert holds.release(record.id) and not holds.release(record.id)
    assert queue.stats()["held_bytes"] == 0
    assert client.hlen(JOBS_PER_KEY) == client.hlen(JOB_BYTES_PER_KEY) == 0
    queue.submit("reconstruction", CODES, PARAMS, "itoh", owner="alice")


def test_a_keys_bytes_are_bounded_as_well_as_its_jobs(client: redis.Redis) -> None:
    queue = bounded_queue(client, per_key_bytes=CODES.nbytes * 2)
    queue.submit("reconstruction", CODES, PARAMS, "itoh", owner="alice")
    queue.submit("reconstruction", CODES, PARAMS, "itoh", owner="alice")
    with pytest.raises(TooManyJobsError, match="MCAM_MAX_QUEUED_BYTES_PER_KEY"):
        queue.submit("reconstruction", CODES, PARAMS, "itoh", owner="alice")
    queue.submit("reconstruction", CODES, PARAMS, "itoh", owner="bob")
    with pytest.raises(InvalidInputError, match="one key's jobs may hold"):
        queue.submit("video", np.zeros((3, 8, 8), np.uint8), PARAMS, "itoh", owner="bob")


def test_codes_past_the_queues_bytes_are_refused_until_a_job_is_released(
    client: redis.Redis,
) -> None:
    queue = bounded_queue(client, max_bytes=CODES.nbytes * 2)
    first = queue.submit("reconstruction", CODES, PARAMS, "itoh", owner="alice")
    queue.submit("reconstruction", CODES, PARAMS, "itoh", owner="bob")
    with pytest.raises(QueueFullError, match="MCAM_JOBS_MAX_BYTES"):
        queue.submit("reconstruction", CODES, PARAMS, "itoh", owner="carol")
    QueueHolds(client).release(first.id)
    queue.submit("reconstruction", CODES, PARAMS, "itoh", owner="carol")
    with pytest.raises(InvalidInputError, match="the queue holds for all jobs"):
        queue.submit("video", np.zeros((3, 8, 8), np.uint8), PARAMS, "itoh")
    assert client.xlen(JOBS_STREAM) == 3


@pytest.mark.parametrize(
    ("bounds", "owner", "refusal"),
    [({"max_bytes": CODES.nbytes}, "", "the queue holds for all jobs"),
     ({"per_key_bytes": CODES.nbytes}, "alice", "one key's jobs may hold")],
)  # fmt: skip
def test_codes_exactly_as_large_as_a_bound_are_taken_one_byte_more_is_not(
    client: redis.Redis, bounds: dict[str, int], owner: str, refusal: str
) -> None:
    queue = bounded_queue(client, **bounds)
    too_large = np.zeros(CODES.nbytes + 1, np.uint8).reshape(1, -1)
    with pytest.raises(InvalidInputError, match=refusal):
        queue.submit("reconstruction", too_large, PARAMS, "itoh", owner=owner)
    queue.submit("reconstruction", CODES, PARAMS, "itoh", owner=owner)
    assert client.xlen(JOBS_STREAM) == 1


def test_full_device_stream_drops_oldest_and_counts(client: redis.Redis, queue: JobQueue) -> None:
    dropped = [
        publish_frame(client, FrameMessage("cam-1", seq, seq * 10, CODES, PARAMS), maxlen=5)
        for seq in range(8)
    ]
    assert dropped == [0, 0, 0, 0, 0, 1, 1, 1]
    kept = [FrameMessage.from_fields(f).sequence for _id, f in client.xrange(frame_stream("cam-1"))]
    assert kept == [3, 4, 5, 6, 7]
    stats = queue.stats()
    assert stats["frames_dropped"] == {"cam-1": 3}
    assert stats["devices"]["cam-1"]["depth"] == 5
    assert stats["devices"]["cam-1"]["frames_dropped"] == 3


def test_publish_frame_rejects_bad_device_id(client: redis.Redis) -> None:
    with pytest.raises(InvalidInputError, match="device id"):
        publish_frame(client, FrameMessage("../x", 0, 0, CODES, PARAMS), maxlen=5)


def test_get_unknown_and_malformed_ids(queue: JobQueue) -> None:
    with pytest.raises(JobNotFoundError):
        queue.get("0" * 32)
    with pytest.raises(JobNotFoundError):
        queue.get("../../etc/passwd")
    with pytest.raises(JobNotFoundError):
        queue.cancel("f" * 32)


def test_cancel_queued_job_and_finished_job_unchanged(
    queue: JobQueue, client: redis.Redis
) -> None:
    record = queue.submit("reconstruction", CODES, PARAMS, "itoh")
    cancelled = queue.cancel(record.id)
    assert cancelled.state is JobState.CANCELLED and cancelled.finished_ns is not None
    assert queue.cancel(record.id) == cancelled
    ended = {f.name: f for f in read_metrics(client)}["jobs_processed_total"]
    assert [(s.labels, s.value) for s in ended.samples] == [({"state": "cancelled"}, 1)]
    assert queue.stats()["jobs_by_state"] == {
        "queued": 0,
        "running": 0,
        "succeeded": 0,
        "failed": 0,
        "cancelled": 1,
    }


def test_a_job_started_on_a_clock_ahead_of_the_apis_is_not_cancelled_before_it_started(
    queue: JobQueue, client: redis.Redis
) -> None:
    """A worker whose clock is 10 s ahead of the API's started the job; the API's cancel
    took its finish on its own clock, 10 s before the start."""
    record = queue.submit("reconstruction", CODES, PARAMS, "itoh")
    started = record.created_ns + 10**10
    queue.jobs.transition(record.id, JobState.RUNNING, (JobState.QUEUED,), started_ns=started)
    cancelled = queue.cancel(record.id)
    assert cancelled.finished_ns is not None and cancelled.finished_ns >= started


def test_wait_returns_at_timeout_or_when_finished(queue: JobQueue, client: redis.Redis) -> None:
    record = queue.submit("reconstruction", CODES, PARAMS, "itoh")
    start = time.monotonic()
    assert queue.wait(record.id, 0.3).state is JobState.QUEUED
    assert time.monotonic() - start >= 0.3
    finisher = threading.Timer(
        0.2,
        lambda: JobStore(client).transition(
            record.id, JobState.SUCCEEDED, (JobState.QUEUED,), progress=1.0
        ),
    )
    finisher.start()
    waited = queue.wait(record.id, 30)
    finisher.join()
    assert waited.state is JobState.SUCCEEDED and waited.progress == 1.0


def test_stats_shape(queue: JobQueue, client: redis.Redis) -> None:
    queue.submit("reconstruction", CODES, PARAMS, "itoh")
    client.xreadgroup(GROUP, "c", {JOBS_STREAM: ">"})
    stats = queue.stats()
    assert stats["stream_depth"] == 1 and stats["pending"] == 1
    assert stats["held_bytes"] == CODES.nbytes
    assert stats["dead_letters"] == 0 and stats["devices"] == {}
    assert queue.workers(max_age_s=10) == {}


def test_a_full_device_stream_keeps_the_discont_frame_that_starts_a_run(
    client: redis.Redis, tmp_path: Path
) -> None:
    """A camera restarts its counter while the worker is behind: the stream is full when
    the new run's DISCONT frame 0 comes, and eviction reaches it. It is kept (frame 1
    after it goes), so the worker decodes the new run; evicting it made every frame of
    the new run up to the old run's newest sequence 'stale', without a result."""
    worker = device_worker(client, tmp_path)
    for seq in range(10):
        publish_frame(client, frame("a", seq), maxlen=5)
    while worker.poll():
        pass
    restart = frame("a", 0)
    publish_frame(client, FrameMessage("a", 0, 0, restart.codes, restart.params, discont=True),
                  maxlen=5)
    dropped = [publish_frame(client, frame("a", seq), maxlen=5) for seq in range(1, 6)]
    assert dropped == [0, 0, 0, 0, 1]
    kept = [FrameMessage.from_fields(f) for _id, f in client.xrange(frame_stream("a"))]
    assert [(m.sequence, m.discont) for m in kept] == [
        (0, True), (2, False), (3, False), (4, False), (5, False)]
    while worker.poll():
        pass
    events = [fields for _, fields in client.xrange(events_stream("a"))][-5:]
    assert [(e[b"type"], int(e[b"sequence"])) for e in events] == [
        (b"frame", seq) for seq in (0, 2, 3, 4, 5)]
