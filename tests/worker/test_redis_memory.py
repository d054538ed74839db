"""worker/redis_memory.py on a real redis-server: the bound, the policy check, a full server.

A server is made full by ``CONFIG SET maxmemory 1`` (any data is more than one byte):
under ``noeviction`` it then refuses every command that would grow its memory.
"""

from __future__ import annotations

import errno
import logging
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import redis
from redis.backoff import NoBackoff
from redis.retry import Retry

from models.formation import SensorFrame, SensorParams
from tests.worker.conftest import leave_free, wait_for
from worker.device_consumer import DeviceConsumer
from worker.device_registry import forget_device
from worker.device_state import make_frame_decoder
from worker.embedded_redis import EmbeddedRedis, connect, durability_problem
from worker.frame_message import FrameMessage
from worker.jobs import JobState
from worker.queue import GROUP, JobQueue, publish_frame
from worker.queue_holds import QueueHolds
from worker.redis_keys import JOBS_STREAM, events_stream, frame_stream
from worker.redis_memory import (
    DEFAULT_MAXMEMORY,
    NO_EVICTION,
    TroubleLog,
    eviction_problem,
    full_problem,
    is_out_of_memory,
    is_transient,
    redis_trouble,
    server_config,
    submit_room,
)
from worker.result_store import RESULTS_DIR, ResultStore

PARAMS = SensorParams(encoding="modulo", bits=8)
CODES = np.arange(64, dtype=np.uint8).reshape(8, 8)


def fill(client: redis.Redis) -> None:
    """Make the server full: every write that grows its memory is refused."""
    client.config_set("maxmemory", 1)


def make_room(client: redis.Redis) -> None:
    client.config_set("maxmemory", 0)


def test_server_config_bounds_memory_without_eviction() -> None:
    assert server_config(123) == ["maxmemory 123", f"maxmemory-policy {NO_EVICTION}"]
    with pytest.raises(ValueError, match="maxmemory must be > 0"):
        server_config(0)


@pytest.mark.parametrize(
    ("config", "problem"),
    [
        ({"maxmemory": "100", "maxmemory-policy": "noeviction"}, None),
        ({"maxmemory": "0", "maxmemory-policy": "allkeys-lru"}, None),  # never full
        ({}, None),  # a managed server that shows nothing
        ({"maxmemory": "100", "maxmemory-policy": "allkeys-lru"}, "'allkeys-lru'"),
        ({"maxmemory": "100", "maxmemory-policy": "volatile-ttl"}, "'volatile-ttl'"),
    ],
)
def test_eviction_problem_names_a_policy_that_drops_keys(
    config: dict[str, str], problem: str | None
) -> None:
    found = eviction_problem(config)
    if problem is None:
        assert found is None
    else:
        assert found is not None and problem in found and "noeviction" in found


def test_the_embedded_server_is_bounded_and_never_evicts(tmp_path: Path) -> None:
    with EmbeddedRedis(tmp_path, maxmemory=64 * 1024**2) as url:
        config = connect(url).config_get("maxmemory*")
    assert config["maxmemory"] == str(64 * 1024**2)
    assert config["maxmemory-policy"] == NO_EVICTION
    with EmbeddedRedis(tmp_path / "default") as url:
        assert connect(url).config_get("maxmemory")["maxmemory"] == str(DEFAULT_MAXMEMORY)


def test_durability_problem_names_an_evicting_server(client: redis.Redis) -> None:
    assert durability_problem(client) is None
    client.config_set("maxmemory-policy", "allkeys-lru")
    assert "evicts keys when full" in (durability_problem(client) or "")
    client.config_set("appendonly", "no")
    both = durability_problem(client) or ""
    assert "no append-only file" in both and "evicts keys when full" in both


def test_refusals_of_a_full_server_are_told_apart_from_other_errors(client: redis.Redis) -> None:
    client.set("text", "x")
    fill(client)
    with pytest.raises(redis.exceptions.RedisError) as command:
        client.hset("h", "a", "1")
    with pytest.raises(redis.exceptions.RedisError) as script:
        client.eval("return redis.call('HSET', KEYS[1], 'a', '1')", 1, "h")
    assert is_out_of_memory(command.value) and is_out_of_memory(script.value)
    assert is_transient(script.value) and "full" in redis_trouble(script.value)
    assert client.get("text") == b"x"  # reads go on
    make_room(client)
    with pytest.raises(redis.exceptions.ResponseError) as wrong_type:
        client.hset("text", "a", "1")
    assert not is_out_of_memory(wrong_type.value) and not is_transient(wrong_type.value)
    lost = redis.exceptions.ConnectionError("gone")
    assert is_transient(lost) and "unreachable" in redis_trouble(lost)
    # The setting to check is named (a worker's log said only redis-py's "gone").
    assert "check that MCAM_REDIS_URL names a running Redis" in redis_trouble(lost)
    path = client.connection_pool.connection_kwargs["path"]
    # Not retried: redis-py retries a timeout 3 times with backoff (5 s) by default.
    impatient = redis.Redis(unix_socket_path=path, socket_timeout=0.05, retry=Retry(NoBackoff(), 0))
    with pytest.raises(redis.exceptions.TimeoutError) as slow:
        impatient.blpop(["nothing"], timeout=1)
    assert is_transient(slow.value) and "did not answer in time" in redis_trouble(slow.value)


def test_a_submit_to_a_full_server_stores_nothing_and_keeps_what_it_held(
    queue: JobQueue, client: redis.Redis
) -> None:
    kept = queue.submit("reconstruction", CODES, PARAMS, "itoh", owner="alice")
    before = queue.stats()
    fill(client)
    with pytest.raises(redis.exceptions.RedisError) as refused:
        queue.submit("reconstruction", CODES, PARAMS, "itoh", owner="alice")
    assert is_out_of_memory(refused.value)
    assert queue.stats() == before and client.xlen(JOBS_STREAM) == 1
    assert queue.get(kept.id).state is JobState.QUEUED
    make_room(client)
    queue.submit("reconstruction", CODES, PARAMS, "itoh", owner="alice")
    assert client.xlen(JOBS_STREAM) == 2


@pytest.mark.parametrize("side", [512, 1100])
def test_a_submit_needs_submit_room_and_full_problem_asks_for_it(
    embedded: EmbeddedRedis, client: redis.Redis, queue: JobQueue, side: int
) -> None:
    """What /health/ready asks Redis to have free for the largest upload (submit_room)
    is what its submit needs on a new connection (the API's pool may open one), for
    codes under and over the query buffer's growth step: with room for the codes
    twice, Redis refuses it and full_problem says so; with submit_room, it takes it and
    full_problem says nothing."""
    queue.submit("reconstruction", CODES, PARAMS, "itoh")  # the submit script loaded
    codes = np.zeros((side, side), np.uint16)  # 0.5 MiB; 2.3 MiB, no allocator class
    room = submit_room(codes.nbytes)
    clients = len(client.client_list())
    for free, taken in ((2 * codes.nbytes, False), (room, True)):
        leave_free(client, free)
        problem = full_problem(client.info("memory"), room)
        fresh = connect(embedded.url)
        try:
            try:
                JobQueue(fresh, maxlen=10, max_deliveries=3, claim_idle_ms=1000).submit(
                    "reconstruction", codes, PARAMS, "itoh"
                )
                accepted = True
            except redis.exceptions.RedisError as exc:
                assert is_out_of_memory(exc), exc
                accepted = False
        finally:
            fresh.close()
        make_room(client)
        assert accepted is taken, f"{free} bytes free for {codes.nbytes} bytes of codes"
        assert (problem is None) is taken, problem
        wait_for(lambda: len(client.client_list()) == clients, 10, "the connection closed")


def test_a_full_server_still_releases_holds(queue: JobQueue, client: redis.Redis) -> None:
    """Releasing a hold frees memory: it must not need room to run."""
    record = queue.submit("reconstruction", CODES, PARAMS, "itoh", owner="alice")
    fill(client)
    assert QueueHolds(client).release(record.id)
    assert queue.stats()["held_bytes"] == 0


def test_a_worker_waits_out_a_full_server_and_fails_no_job(
    queue: JobQueue, client: redis.Redis, workers, make_frame, finished, wait_until
) -> None:
    """A worker that cannot record a job's start keeps the entry and retries, touching
    it so that an idle worker does not reclaim it meanwhile (each claim counts a
    delivery: the job used to fail as worker_lost once there was room again); the job
    is neither failed nor dead-lettered, and runs once there is room.

    The heartbeat touches the entry five times per claim period, and the workers
    decode device frames in their own process (no decode pool to start on both cores:
    this test streams from no device)."""
    frame: SensorFrame = make_frame()
    job = queue.submit("reconstruction", frame.codes, frame.params, "itoh")
    fill(client)
    processes = [
        workers.start(MCAM_CLAIM_IDLE_MS="1500", MCAM_HEARTBEAT_S="0.3", MCAM_STREAM_PROCESSES="1")
        for _ in range(2)
    ]
    wait_until(lambda: client.xpending(JOBS_STREAM, GROUP)["pending"], 60, "a delivery")
    time.sleep(5.0)  # over three claim periods
    [pending] = client.xpending_range(JOBS_STREAM, GROUP, "-", "+", 10)
    assert pending["times_delivered"] == 1, "reclaimed from a live worker"
    assert all(p.poll() is None for p in processes), "a worker exited on a full Redis"
    assert queue.get(job.id).state is JobState.QUEUED
    make_room(client)
    record = finished(queue, job.id)
    assert record.state is JobState.SUCCEEDED and record.attempts == 1, record.error
    assert queue.stats()["dead_letters"] == 0
    for process in processes:
        process.terminate()  # both at once: each takes a second or two to stop
    outputs = [process.communicate(timeout=30)[0].decode() for process in processes]
    assert any("Redis is full" in output for output in outputs)
    assert not any("Traceback" in output for output in outputs)
    # One warning per loop and heartbeat step in 30 s, not one a second each.
    assert all(output.count("Redis is full") <= 4 for output in outputs), outputs


def test_a_device_frame_decoded_while_redis_is_full_is_committed_once(
    client: redis.Redis, data_dir: Path, make_frame, caplog: pytest.LogCaptureFixture
) -> None:
    """The frame's commit (its result key, event, ack and count) runs on a full Redis;
    its timings cannot be written and are skipped, not retried as a failure of the frame
    (which redid it as a 'stale' frame, with a traceback)."""
    frame: SensorFrame = make_frame()
    device = "cam-full"
    consumer = DeviceConsumer(
        client,
        ResultStore(data_dir / RESULTS_DIR, retention_s=3600),
        owner="w-1",
        lease_ms=5000,
        max_deliveries=3,
        decode=make_frame_decoder("independent", "itoh"),
        stop=threading.Event(),
    )
    publish_frame(client, FrameMessage(device, 0, 0, frame.codes, frame.params), maxlen=10)
    assert consumer.poll()  # takes the lease and decodes frame 0 with room
    publish_frame(client, FrameMessage(device, 1, 1000, frame.codes, frame.params), maxlen=10)
    fill(client)
    consumer.poll()
    make_room(client)
    events = [fields[b"type"] for _id, fields in client.xrange(events_stream(device))]
    assert events == [b"frame", b"frame"]
    assert client.xlen(frame_stream(device)) == 0
    assert "frame timings not recorded" in caplog.text and "Traceback" not in caplog.text


def test_a_device_let_go_leaves_no_trouble_behind(
    client: redis.Redis, data_dir: Path, make_frame
) -> None:
    """The worker's once-per-30-s warning kept an entry per device whose frame metrics a
    full Redis refused, for the life of the worker: one per camera ever troubled."""
    frame: SensorFrame = make_frame()
    consumer = DeviceConsumer(
        client, ResultStore(data_dir / RESULTS_DIR, retention_s=3600), owner="w-1",
        lease_ms=5000, max_deliveries=3, decode=make_frame_decoder("independent", "itoh"),
        stop=threading.Event(),
    )  # fmt: skip
    for device in ("cam-a", "cam-b"):
        publish_frame(client, FrameMessage(device, 0, 0, frame.codes, frame.params), maxlen=10)
    assert consumer.poll()
    for device in ("cam-a", "cam-b"):
        publish_frame(client, FrameMessage(device, 1, 1000, frame.codes, frame.params), maxlen=10)
    fill(client)
    consumer.poll()
    make_room(client)
    assert set(consumer._trouble._last) == {"device cam-a", "device cam-b"}
    forget_device(client, "cam-a", silent_after_s=0.0)
    consumer.poll()
    assert set(consumer._trouble._last) == {"device cam-b"}


def test_a_queue_opened_on_a_full_redis_with_its_group_reads_on(
    queue: JobQueue, client: redis.Redis
) -> None:
    """An API process started while Redis is full must still serve reads: making its
    queue (the consumer group already there) used to fail with 503 store_full."""
    record = queue.submit("reconstruction", CODES, PARAMS, "itoh")
    fill(client)
    reopened = JobQueue(client, maxlen=100, max_deliveries=3, claim_idle_ms=1000)
    assert reopened.get(record.id).state is JobState.QUEUED
    make_room(client)
    client.delete(JOBS_STREAM)
    fill(client)
    with pytest.raises(redis.exceptions.ResponseError) as missing:
        JobQueue(client, maxlen=100, max_deliveries=3, claim_idle_ms=1000)
    assert is_out_of_memory(missing.value)


def test_trouble_is_warned_once_per_period_and_place(caplog: pytest.LogCaptureFixture) -> None:
    """At given times: on the wall clock, a pause of the test as long as the period
    between the first warnings (a loaded machine) let one more through."""
    trouble = TroubleLog(logging.getLogger("test.trouble"), every_s=0.2)
    full = redis.exceptions.OutOfMemoryError("command not allowed when used memory > 'maxmemory'.")
    with caplog.at_level(logging.WARNING, logger="test.trouble"):
        for step in range(5):
            trouble.warn("jobs", full, now_s=100.0 + 0.01 * step)
        trouble.warn("heartbeat", redis.exceptions.ConnectionError("gone"), now_s=100.05)
        trouble.warn("jobs", full, now_s=100.25)
    lines = [record.getMessage() for record in caplog.records]
    assert len(lines) == 3
    assert lines[0].startswith("jobs: Redis is full") and "more times" not in lines[0]
    assert lines[1].startswith("heartbeat: Redis unreachable (gone)")
    assert lines[2].endswith("(4 more times since the last warning)")


def test_a_full_results_disk_is_waited_out_and_said_so() -> None:
    """Writing to /dev/full is what a full filesystem answers: ENOSPC."""
    with pytest.raises(OSError) as full, open("/dev/full", "wb") as device:
        device.write(b"x")
        device.flush()
    assert is_transient(full.value) and "results disk is full" in redis_trouble(full.value)
    assert not is_transient(PermissionError(errno.EACCES, "Permission denied"))
