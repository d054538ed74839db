"""The worker process end to end: real ``mcam worker`` processes on a real redis-server.

Crash (SIGKILL mid-job), Redis restart, dead letters, graceful SIGTERM, cancellation
(device frame streams: test_runner_streams.py).
"""

from __future__ import annotations

import errno
import io
import json
import os
import shutil
import signal
import threading
import time
from collections.abc import Callable, Collection
from pathlib import Path

import numpy as np
import OpenEXR
import pytest
import redis

from models.decoders import learned
from models.decoders.registry import get_decoder
from models.errors import McamError
from models.formation import SensorFrame, SensorParams
from tests.worker.conftest import OVERFLOW, overflowing_codes, residue_frame, result_files
from worker.child_process import ChildProcess
from worker.deliveries import GROUP, Delivery, StreamConsumer
from worker.embedded_redis import EmbeddedRedis, connect
from worker.job_processor import JobProcessor, start_job_child
from worker.jobs import JobRecord, JobState
from worker.metrics import counter_key, read_metrics
from worker.queue import JobQueue
from worker.recordings import frame_key, start_recording
from worker.redis_keys import (
    DEAD_LETTER_STREAM,
    DEVICES_SET,
    JOBS_PER_KEY,
    JOBS_STREAM,
    WORKERS_HEARTBEAT,
    job_key,
)
from worker.result_store import RESULTS_DIR, ResultStore
from worker.runner import RECONNECT_MAX_S, RECONNECT_S, Worker, WorkerConfig, reconnect_delay

#: Tests that stop or signal a worker mid-job decode 1024x1024 with this decoder: about
#: 0.5 s a frame (itoh: 0.05 s), so a loaded machine cannot finish the job before the
#: test sees it running.
SLOW_DECODER = "herraez"


def exr_pixels(data: bytes) -> np.ndarray:
    with OpenEXR.File(io.BytesIO(data)) as exr:
        return np.asarray(exr.channels()["Y"].pixels, dtype=np.float64)


def test_job_runs_and_cancelled_job_is_skipped(
    queue: JobQueue, client: redis.Redis, workers, data_dir: Path, make_frame, wait_until, finished
) -> None:
    frame: SensorFrame = make_frame()
    skipped = queue.submit("reconstruction", frame.codes, frame.params, "itoh", owner="k")
    queue.cancel(skipped.id)
    job = queue.submit("reconstruction", frame.codes, frame.params, "itoh", owner="k")
    workers.start()
    record = finished(queue, job.id)
    assert record.state is JobState.SUCCEEDED, record.error
    assert record.attempts == 1 and record.progress == 1.0
    assert set(record.timings_ns) == {"queue_wait", "decode", "encode", "total"}
    assert all(value > 0 for value in record.timings_ns.values())
    assert record.timings_ns["total"] >= record.timings_ns["queue_wait"]
    exr = (data_dir / RESULTS_DIR / record.results["exr"]).read_bytes()
    np.testing.assert_allclose(exr_pixels(exr), frame.irradiance, rtol=2**-8, atol=2**-8)
    winding = np.load(data_dir / RESULTS_DIR / record.results["winding"])
    np.testing.assert_array_equal(winding, frame.winding)
    assert result_files(data_dir) == sorted(record.results.values())
    assert queue.get(skipped.id).state is JobState.CANCELLED
    retention_s = 7 * 24 * 3600
    assert 0 < client.ttl(f"job:{job.id}") <= retention_s
    assert 0 < client.ttl(f"job:{skipped.id}") <= retention_s
    wait_until(lambda: queue.stats()["stream_depth"] == 0, 10, "entries acked and deleted")
    wait_until(lambda: queue.stats()["held_bytes"] == 0, 10, "the jobs' holds released")
    assert client.hlen(JOBS_PER_KEY) == 0
    assert len(queue.workers(max_age_s=10)) == 1


def test_sigkill_mid_job_completes_on_another_worker_once(
    queue: JobQueue, client: redis.Redis, workers, data_dir: Path, make_frame, wait_until, finished
) -> None:
    frame: SensorFrame = make_frame(size=1024)
    job = queue.submit("reconstruction", frame.codes, frame.params, SLOW_DECODER)
    first = workers.start()
    wait_until(lambda: queue.get(job.id).state is JobState.RUNNING, 60, "job running")
    first.send_signal(signal.SIGSTOP)
    assert queue.get(job.id).state is JobState.RUNNING, "the job finished before the kill"
    first.send_signal(signal.SIGKILL)
    first.wait(10)
    assert client.xpending(JOBS_STREAM, "workers")["pending"] == 1
    workers.start()
    record = finished(queue, job.id)
    assert record.state is JobState.SUCCEEDED, record.error
    assert record.attempts == 2
    assert result_files(data_dir) == sorted(record.results.values())
    wait_until(lambda: client.xlen(JOBS_STREAM) == 0, 10, "the entry acked and deleted")
    assert client.xlen(DEAD_LETTER_STREAM) == 0
    redelivered = {f.name: f for f in read_metrics(client)}["redeliveries_total"]
    assert redelivered.samples[0].value == 1


def test_long_job_is_not_reclaimed_from_a_live_worker(
    queue: JobQueue, client: redis.Redis, workers, make_frame, finished
) -> None:
    frame: SensorFrame = make_frame(size=1536)
    job = queue.submit("reconstruction", frame.codes, frame.params, "itoh")
    workers.start(MCAM_CLAIM_IDLE_MS="1000", MCAM_HEARTBEAT_S="0.1")
    workers.start(MCAM_CLAIM_IDLE_MS="1000", MCAM_HEARTBEAT_S="0.1")
    record = finished(queue, job.id)
    assert record.state is JobState.SUCCEEDED and record.attempts == 1
    redelivered = {f.name: f for f in read_metrics(client)}["redeliveries_total"]
    assert redelivered.samples[0].value == 0


def test_the_job_consumers_of_workers_gone_leave_the_group(
    queue: JobQueue, client: redis.Redis, workers, make_frame, finished, wait_until
) -> None:
    """Each worker start added consumers (``<worker id>-j<thread>``) to the jobs stream's
    group and none ever left: a service restarted for weeks kept every one. A live
    worker deletes those of workers without a heartbeat that hold no entry."""
    frame: SensorFrame = make_frame()
    job = queue.submit("reconstruction", frame.codes, frame.params, "itoh")
    gone = {"host-1-aaaaaa-j0", "host-2-bbbbbb-j0", "host-2-bbbbbb-j1"}
    for name in gone:
        client.xgroup_createconsumer(JOBS_STREAM, GROUP, name)
    workers.start(MCAM_HEARTBEAT_S="0.1")
    assert finished(queue, job.id).state is JobState.SUCCEEDED

    def names() -> set[str]:
        return {row["name"].decode() for row in client.xinfo_consumers(JOBS_STREAM, GROUP)}

    wait_until(lambda: not names() & gone, 30, "the gone workers' consumers deleted")
    (live,) = queue.workers(max_age_s=10)
    assert names() and all(name.startswith(f"{live}-j") for name in names())


def test_a_job_the_input_makes_impossible_fails_at_once_without_a_dead_letter(
    queue: JobQueue, client: redis.Redis, workers, data_dir: Path, wait_until, finished
) -> None:
    """Another try gives the same answer: the job fails at its first delivery and its
    entry is done; dead letters are for what an operator must look at."""
    job = queue.submit("reconstruction", overflowing_codes(), OVERFLOW, "itoh")
    workers.start()
    record = finished(queue, job.id)
    assert record.state is JobState.FAILED and record.attempts == 1
    assert record.error is not None and record.error.code == "output_overflow"
    wait_until(lambda: client.xlen(JOBS_STREAM) == 0, 10, "the entry done")
    wait_until(lambda: queue.stats()["held_bytes"] == 0, 10, "the job's hold released")
    assert client.xlen(DEAD_LETTER_STREAM) == 0 and result_files(data_dir) == []
    stats = queue.stats()
    assert stats["dead_letters"] == 0 and stats["jobs_by_state"]["failed"] == 1


def test_a_job_failing_for_the_worker_goes_to_dead_letters_after_max_deliveries(
    queue: JobQueue,
    client: redis.Redis,
    workers,
    data_dir: Path,
    wait_until,
    finished,
    make_frame,
) -> None:
    """A failure that is not the input's (here the job's result folder cannot be made:
    a file stands in its place) is retried, then dead-lettered. The client's record says
    what to do and shows no server path (it used to carry the exception's text); the
    dead letter keeps the exception for the operator."""
    frame: SensorFrame = make_frame()
    job = queue.submit("reconstruction", frame.codes, frame.params, "itoh")
    blocker = data_dir / RESULTS_DIR / "jobs" / job.id
    blocker.parent.mkdir(parents=True)
    blocker.write_bytes(b"not a folder")
    workers.start()
    record = finished(queue, job.id)
    assert record.state is JobState.FAILED and record.attempts == 3
    assert record.error is not None and record.error.code == "internal_error"
    assert str(data_dir) not in record.error.message and "retry later" in record.error.message
    # The record turns FAILED first, then the entry moves to the dead letters.
    wait_until(lambda: client.xlen(DEAD_LETTER_STREAM), 10, "the dead letter")
    [(_id, letter)] = client.xrange(DEAD_LETTER_STREAM)
    assert letter[b"job"].decode() == job.id and letter[b"deliveries"] == b"3"
    assert letter[b"code"] == b"internal_error" and job.id.encode() in letter[b"message"]
    wait_until(lambda: client.xlen(JOBS_STREAM) == 0, 10, "the entry dead-lettered")
    wait_until(lambda: queue.stats()["held_bytes"] == 0, 10, "the job's hold released")
    assert queue.stats()["dead_letters"] == 1


def test_entries_naming_no_readable_job_are_dead_lettered_and_their_holds_released(
    queue: JobQueue, client: redis.Redis, workers, make_frame, wait_until
) -> None:
    """A job whose record is gone (deleted by an operator), one whose record does not
    parse, and an entry with no job field: each goes to the dead letters once (the
    corrupt one as ``internal_error``; it used to be retried forever), and the jobs give
    back their key's share of the queue."""
    frame: SensorFrame = make_frame()
    gone = queue.submit("reconstruction", frame.codes, frame.params, "itoh", owner="k")
    corrupt = queue.submit("reconstruction", frame.codes, frame.params, "itoh", owner="k")
    client.delete(f"job:{gone.id}")
    client.hset(f"job:{corrupt.id}", "state", "not json")
    client.xadd(JOBS_STREAM, {"kind": "reconstruction"})
    workers.start()
    wait_until(lambda: client.xlen(DEAD_LETTER_STREAM) == 3, 30, "three dead letters")
    letters = [letter for _id, letter in client.xrange(DEAD_LETTER_STREAM)]
    assert [letter[b"code"] for letter in letters] == [
        b"not_found",
        b"internal_error",
        b"not_found",
    ]
    assert letters[0][b"job"].decode() == gone.id and letters[1][b"job"].decode() == corrupt.id
    assert b"corrupt" in letters[1][b"message"] and b"job" not in letters[2]
    assert client.xlen(JOBS_STREAM) == 0 and queue.stats()["held_bytes"] == 0
    assert client.hlen(JOBS_PER_KEY) == 0


def test_accepted_jobs_survive_a_redis_restart(
    embedded: EmbeddedRedis, workers, make_frame, finished
) -> None:
    frame: SensorFrame = make_frame()
    client = connect(embedded.url)
    queue = JobQueue(client, maxlen=100, max_deliveries=3, claim_idle_ms=1000)
    accepted = [queue.submit("reconstruction", frame.codes, frame.params, "itoh") for _ in range(3)]
    assert embedded.pid is not None
    os.kill(embedded.pid, signal.SIGKILL)
    embedded.stop()
    embedded.start()
    client = connect(embedded.url)
    queue = JobQueue(client, maxlen=100, max_deliveries=3, claim_idle_ms=1000)
    assert [queue.get(job.id).state for job in accepted] == [JobState.QUEUED] * 3
    worker = workers.start()
    for job in accepted:
        assert finished(queue, job.id).state is JobState.SUCCEEDED
    embedded.stop()
    embedded.start()
    queue = JobQueue(connect(embedded.url), maxlen=100, max_deliveries=3, claim_idle_ms=1000)
    late = queue.submit("reconstruction", frame.codes, frame.params, "itoh")
    assert finished(queue, late.id).state is JobState.SUCCEEDED
    assert worker.poll() is None


def test_a_redis_restarted_without_its_data_runs_the_jobs_queued_after(
    embedded: EmbeddedRedis, client: redis.Redis, queue: JobQueue, workers, make_frame, finished
) -> None:
    """A Redis that lost its data (its data dir, or an external server that keeps none)
    lost the jobs stream's consumer group; the API's next submit makes the stream again,
    without it. The worker failed every read with NOGROUP, and the job stayed queued."""
    frame: SensorFrame = make_frame()
    worker = workers.start()
    first = queue.submit("reconstruction", frame.codes, frame.params, "itoh")
    assert finished(queue, first.id).state is JobState.SUCCEEDED
    embedded.stop()
    shutil.rmtree(embedded.dir)
    embedded.start()
    late = queue.submit("reconstruction", frame.codes, frame.params, "itoh")
    assert client.xinfo_groups(JOBS_STREAM) == []
    assert finished(queue, late.id).state is JobState.SUCCEEDED
    assert worker.poll() is None


def test_sigterm_finishes_the_job_in_hand(
    queue: JobQueue, client: redis.Redis, workers, make_frame, wait_until, finished
) -> None:
    frame: SensorFrame = make_frame(size=1024)
    job = queue.submit("reconstruction", frame.codes, frame.params, SLOW_DECODER)
    worker = workers.start()
    wait_until(lambda: queue.get(job.id).state is JobState.RUNNING, 60, "job running")
    worker.send_signal(signal.SIGTERM)
    assert worker.wait(60) == 0
    assert queue.get(job.id).state is JobState.SUCCEEDED
    assert client.hlen(WORKERS_HEARTBEAT) == 0
    assert client.xpending(JOBS_STREAM, "workers")["pending"] == 0


def test_cancel_while_running_is_honoured(
    queue: JobQueue, client: redis.Redis, workers, make_frame, wait_until
) -> None:
    frame: SensorFrame = make_frame(size=1024)
    job = queue.submit("reconstruction", frame.codes, frame.params, SLOW_DECODER)
    worker = workers.start()
    wait_until(lambda: queue.get(job.id).state is JobState.RUNNING, 60, "job running")
    worker.send_signal(signal.SIGSTOP)
    assert queue.cancel(job.id).state is JobState.CANCELLED
    worker.send_signal(signal.SIGCONT)
    wait_until(lambda: client.xlen(JOBS_STREAM) == 0, 60, "the cancelled entry acked")
    record = queue.get(job.id)
    assert record.state is JobState.CANCELLED and record.results == {}
    assert client.xlen(DEAD_LETTER_STREAM) == 0


@pytest.mark.parametrize(
    ("kind", "frames", "options"),
    [("reconstruction", None, None), ("video", 2, {"mode": "independent"})],
)
def test_cancelling_a_long_decode_stops_it_and_the_worker_stays_live(
    queue: JobQueue,
    client: redis.Redis,
    workers,
    wait_until,
    finished,
    make_frame,
    kind: str,
    frames: int | None,
    options: dict | None,
) -> None:
    """Graph cuts on 1024 x 1024 random codes run about a minute on one core, most of it
    holding the interpreter lock: in the job's child process the worker keeps beating,
    and a cancel kills the decode at once (a video's mid-frame), leaving the worker
    ready for the next job."""
    shape = (1024, 1024) if frames is None else (frames, 1024, 1024)
    codes = np.random.default_rng(0).integers(0, 256, shape).astype(np.uint8)
    params = SensorParams(encoding="modulo")
    job = queue.submit(kind, codes, params, "graphcut", options)
    worker = workers.start()
    wait_until(lambda: queue.get(job.id).state is JobState.RUNNING, 60, "job running")

    def beat_ns() -> int:
        return json.loads(client.hvals(WORKERS_HEARTBEAT)[0])["ts_ns"]

    wait_until(lambda: client.hlen(WORKERS_HEARTBEAT), 20, "the worker's first heartbeat")
    first = beat_ns()
    wait_until(lambda: beat_ns() > first, 20, "a heartbeat while the decode runs")
    assert queue.cancel(job.id).state is JobState.CANCELLED
    wait_until(lambda: client.xlen(JOBS_STREAM) == 0, 20, "the cancelled decode stopped")
    frame: SensorFrame = make_frame()
    after = queue.submit("reconstruction", frame.codes, frame.params, "itoh")
    assert finished(queue, after.id).state is JobState.SUCCEEDED
    assert worker.poll() is None


def random_codes(*shape: int) -> np.ndarray:
    """Codes graph cuts take seconds on at 512 x 512 (no smooth region to settle)."""
    return np.random.default_rng(0).integers(0, 256, shape).astype(np.uint8)


def test_a_stopping_worker_keeps_its_job_from_being_reclaimed(
    queue: JobQueue, workers, wait_until, finished
) -> None:
    """Worker A finishes the job in hand after SIGTERM; all that time it keeps the job's
    entry fresh, so worker B (claiming entries idle for 1 s) does not decode it again."""
    modulo = SensorParams(encoding="modulo")
    job = queue.submit("reconstruction", random_codes(512, 512), modulo, "graphcut")
    first = workers.start("--no-devices")
    wait_until(lambda: queue.get(job.id).state is JobState.RUNNING, 60, "job running")
    workers.start("--no-devices")
    first.send_signal(signal.SIGTERM)
    assert first.wait(120) == 0
    record = finished(queue, job.id)
    assert record.state is JobState.SUCCEEDED and record.attempts == 1


def test_sigterm_hands_a_video_back_at_once_with_its_progress_reset(
    queue: JobQueue, client: redis.Redis, workers, wait_until
) -> None:
    modulo = SensorParams(encoding="modulo")
    job = queue.submit(
        "video", random_codes(3, 512, 512), modulo, "graphcut", {"mode": "independent"}
    )
    worker = workers.start("--no-devices")
    wait_until(lambda: queue.get(job.id).state is JobState.RUNNING, 60, "job running")
    worker.send_signal(signal.SIGTERM)
    assert worker.wait(60) == 0
    record = queue.get(job.id)
    assert record.state is JobState.QUEUED and record.attempts == 1
    assert record.frames_done == 0 and record.progress == 0.0
    # A queued job shows no start (it kept the first attempt's).
    assert record.started_ns is None
    assert client.xpending(JOBS_STREAM, GROUP)["pending"] == 0


def test_worker_config_checks_heartbeat_against_lease(tmp_path: Path) -> None:
    with pytest.raises(McamError, match="must be shorter than the lease"):
        WorkerConfig(redis_url="unix:///x", data_dir=tmp_path, heartbeat_s=1.0, claim_idle_ms=500)
    with pytest.raises(McamError, match="must be shorter than the lease"):
        WorkerConfig(redis_url="unix:///x", data_dir=tmp_path, heartbeat_s=5.0, lease_ms=5000)
    with pytest.raises(McamError, match="at least 1"):
        WorkerConfig(redis_url="unix:///x", data_dir=tmp_path, concurrency=0)
    with pytest.raises(McamError, match="MCAM_STREAM_EXR_COMPRESSION to one of: zip, none"):
        WorkerConfig(redis_url="unix:///x", data_dir=tmp_path, stream_exr_compression="lzw")
    with pytest.raises(McamError, match="set MCAM_STREAM_PROCESSES to 1"):
        WorkerConfig(redis_url="unix:///x", data_dir=tmp_path, stream_processes=0)


class _InstantStop(threading.Event):
    """A stop event whose waits return at once, recording the seconds each asked for."""

    def __init__(self) -> None:
        super().__init__()
        self.asked: list[float] = []

    def wait(self, timeout: float | None = None) -> bool:
        assert timeout is not None
        self.asked.append(timeout)
        return self.is_set()


def test_a_loop_waits_longer_after_each_failure_in_a_row_and_briefly_after_a_success(
    tmp_path: Path,
) -> None:
    """Five failed steps (Redis unreachable), one that works, one more failure: the
    waits double up to the cap, each jittered down by at most half, and start again
    from the shortest after the success."""
    worker = Worker(WorkerConfig(redis_url="unix:///x", data_dir=tmp_path))
    stop = _InstantStop()
    worker.stop = stop
    outcomes = iter(["fail"] * 5 + ["ok", "fail"])

    def step() -> None:
        outcome = next(outcomes, "stop")
        if outcome == "stop":
            stop.set()
        elif outcome == "fail":
            raise redis.exceptions.ConnectionError("Connection refused")

    worker._resilient(step)
    expected = [RECONNECT_S, 2 * RECONNECT_S, 4 * RECONNECT_S, RECONNECT_MAX_S]
    expected += [RECONNECT_MAX_S, RECONNECT_S]
    assert len(stop.asked) == len(expected)
    for asked, longest in zip(stop.asked, expected, strict=True):
        assert 0.5 * longest <= asked <= longest


@pytest.mark.parametrize(
    ("failures", "jitter", "seconds"),
    [
        (1, 1.0, RECONNECT_S),
        (2, 0.5, RECONNECT_S),
        (3, 1.0, 4 * RECONNECT_S),
        (60, 1.0, RECONNECT_MAX_S),
        (100_000, 1.0, RECONNECT_MAX_S),
    ],
    ids=["first", "jittered", "doubled", "capped", "hours of failures"],
)
def test_the_reconnect_delay_doubles_to_its_cap(
    failures: int, jitter: float, seconds: float
) -> None:
    assert reconnect_delay(failures, jitter) == pytest.approx(seconds)


def job_in_hand(
    url: str, client: redis.Redis, queue: JobQueue, data_dir: Path, frame: SensorFrame
) -> tuple[str, Worker, StreamConsumer, Delivery]:
    """A queued itoh job read by job thread 0 of an in-process worker and in its care
    (in flight), as the job loop holds it before handling: (job id, worker, consumer,
    delivery)."""
    job = queue.submit("reconstruction", frame.codes, frame.params, "itoh")
    worker = Worker(WorkerConfig(redis_url=url, data_dir=data_dir))
    consumer = StreamConsumer(client, JOBS_STREAM, "w-j0", max_deliveries=3)
    [delivery] = consumer.read_new(block_ms=None)
    worker._in_flight[0] = (consumer, delivery)
    return job.id, worker, consumer, delivery


class _BuggyProcessor(JobProcessor):
    """A processor with a bug: every job raises an error that is not Redis's."""

    def handle(self, consumer: StreamConsumer, delivery: Delivery) -> None:
        raise RuntimeError("a bug")


def test_a_job_stays_in_flight_through_a_full_redis_and_counts_a_delivery_after_a_bug(
    embedded: EmbeddedRedis, client: redis.Redis, queue: JobQueue, data_dir: Path, make_frame
) -> None:
    """While Redis refuses the job's writes the entry stays in flight (the heartbeat keeps
    touching it while the loop backs off); after any other error it leaves the
    heartbeat's care and counts a delivery, so max_deliveries ends it."""
    store = ResultStore(data_dir / RESULTS_DIR, retention_s=3600)
    _, worker, consumer, delivery = job_in_hand(embedded.url, client, queue, data_dir, make_frame())
    processor = JobProcessor(client, store, max_deliveries=3, stop=worker.stop)
    client.config_set("maxmemory", 1)
    with pytest.raises(redis.exceptions.ResponseError, match="OOM"):
        worker._handle(processor, consumer, delivery, 0)
    client.config_set("maxmemory", 0)
    assert worker._in_flight[0] == (consumer, delivery) and delivery.deliveries == 1
    buggy = _BuggyProcessor(client, store, max_deliveries=3, stop=worker.stop)
    with pytest.raises(RuntimeError, match="a bug"):
        worker._handle(buggy, consumer, delivery, 0)
    assert 0 not in worker._in_flight and delivery.deliveries == 2
    [pending] = client.xpending_range(JOBS_STREAM, GROUP, "-", "+", 1)
    assert pending["times_delivered"] == 2


class _SlowStore(ResultStore):
    """A result store whose purge takes as long as a week of 30 frames/s streams
    (minutes): it fails once, as an unreadable folder would, then walks until released."""

    def __init__(self, root: Path) -> None:
        super().__init__(root, retention_s=3600)
        self.purging = threading.Event()
        self.release = threading.Event()
        self.calls = 0

    def purge_expired(self, now_s: float | None = None, stop: threading.Event | None = None,
                      keep: Collection[str] = ()) -> int:
        self.calls += 1
        if self.calls == 1:
            raise PermissionError("[Errno 13] Permission denied: 'results/devices'")
        self.purging.set()
        self.release.wait(60)
        return super().purge_expired(now_s, stop, keep)


def test_a_long_purge_does_not_hold_up_the_heartbeat(
    embedded: EmbeddedRedis, client: redis.Redis, data_dir: Path, monkeypatch, wait_until
) -> None:
    """The heartbeat (which renews device leases and in-flight jobs) keeps beating while
    the purge walks the store, and a purge that fails is tried again later."""
    monkeypatch.setattr("worker.runner.PURGE_EVERY_S", 0.05)
    worker = Worker(
        WorkerConfig(redis_url=embedded.url, data_dir=data_dir, devices=False, heartbeat_s=0.1),
        worker_id="w-purge",
    )
    worker.store = store = _SlowStore(data_dir / RESULTS_DIR)
    running = threading.Thread(target=worker.run, daemon=True)
    running.start()
    try:
        wait_until(store.purging.is_set, 30, "the second purge")

        def beat_ns() -> int:
            raw = client.hget(WORKERS_HEARTBEAT, "w-purge")
            return json.loads(raw)["ts_ns"] if raw else 0

        first = beat_ns()
        wait_until(lambda: beat_ns() > first, 30, "a beat during the purge")
        assert store.purging.is_set() and not store.release.is_set()
    finally:
        store.release.set()
        worker.request_stop()
        running.join(30)
    assert not running.is_alive()


class _FullDisk(ResultStore):
    """A result store on a disk with no room left until ``room`` is set (as the result
    of a write on a full filesystem: the errno Linux gives)."""

    room = False

    def write(self, key: str, data: bytes, *, replace: bool = True) -> Path:
        if not self.room:
            raise OSError(errno.ENOSPC, "No space left on device", str(self.path(key)))
        return super().write(key, data, replace=replace)


def test_a_full_results_disk_keeps_the_job_waiting_not_failed(
    embedded: EmbeddedRedis, client: redis.Redis, queue: JobQueue, data_dir: Path, make_frame
) -> None:
    """A job whose result cannot be written for want of space stays in flight without
    counting a delivery, as with a full Redis, and succeeds once there is room (it used
    to fail for good, dead-lettered as an internal error, within a second)."""
    store = _FullDisk(data_dir / RESULTS_DIR, retention_s=3600)
    job_id, worker, consumer, delivery = job_in_hand(
        embedded.url, client, queue, data_dir, make_frame()
    )
    processor = JobProcessor(client, store, max_deliveries=3, stop=worker.stop)
    for _ in range(3):
        with pytest.raises(OSError, match="No space left"):
            worker._handle(processor, consumer, delivery, 0)
    assert worker._in_flight[0] == (consumer, delivery) and delivery.deliveries == 1
    assert queue.get(job_id).state is not JobState.FAILED
    assert queue.stats()["dead_letters"] == 0
    store.room = True
    worker._handle(processor, consumer, delivery, 0)
    assert queue.get(job_id).state is JobState.SUCCEEDED


def handled_here(client: redis.Redis, data_dir: Path) -> tuple[JobProcessor, StreamConsumer]:
    """Handle the next queued job in this process (consumer ``w-j0``, no child process,
    results kept an hour); the processor and the consumer, to handle more."""
    store = ResultStore(data_dir / RESULTS_DIR, retention_s=3600)
    processor = JobProcessor(client, store, max_deliveries=3, stop=threading.Event())
    consumer = StreamConsumer(client, JOBS_STREAM, "w-j0", max_deliveries=3)
    [delivery] = consumer.read_new(block_ms=None)
    processor.handle(consumer, delivery)
    return processor, consumer


def test_a_finished_job_delivered_past_the_limit_is_dropped_not_dead_lettered(
    client: redis.Redis, queue: JobQueue, data_dir: Path, make_frame
) -> None:
    """A worker stopped between a job's success and its ack, on the job's last allowed
    delivery: the next worker finds the job succeeded and drops the entry (it used to
    add a worker_lost dead letter for a job that had succeeded)."""
    frame: SensorFrame = make_frame()
    job = queue.submit("reconstruction", frame.codes, frame.params, "itoh")
    processor, consumer = handled_here(client, data_dir)
    assert queue.get(job.id).state is JobState.SUCCEEDED
    entry = client.xadd(JOBS_STREAM, {"job": job.id}).decode()
    [again] = consumer.read_new(block_ms=None)
    assert again.entry_id == entry
    again.deliveries = 4
    processor.handle(consumer, again)
    assert client.xlen(DEAD_LETTER_STREAM) == 0 and client.xlen(JOBS_STREAM) == 0
    record = queue.get(job.id)
    assert record.state is JobState.SUCCEEDED and record.error is None


def test_a_job_meeting_a_broken_model_install_fails_at_once_for_the_operator(
    client: redis.Redis, queue: JobQueue, data_dir: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A model file that is not its card's (cut short, replaced: here its sha256 differs)
    raised ModelFileError, an OSError: the job was retried to its last delivery, though
    no retry mends a file, then failed as ``internal_error`` ("retry later"), which told
    its client nothing. It now fails at its first delivery as ``model_unavailable``,
    naming the decoder but no server path, and the dead letter keeps the file's name and
    what to do for the operator."""
    decoder = get_decoder("mantissanet-tiny")
    monkeypatch.setattr(decoder.models["modulo"], "_session", None)
    monkeypatch.setattr(learned, "sha256_of", lambda path: "0" * 64)
    frame = residue_frame()
    job = queue.submit("reconstruction", frame.codes, frame.params, "mantissanet-tiny")
    handled_here(client, data_dir)
    record = queue.get(job.id)
    assert record.state is JobState.FAILED and record.attempts == 1
    assert record.error is not None and record.error.code == "model_unavailable"
    assert "'mantissanet-tiny'" in record.error.message
    assert str(learned.ONNX_DIR) not in record.error.message
    [(_id, letter)] = client.xrange(DEAD_LETTER_STREAM)
    assert letter[b"code"] == b"model_unavailable" and letter[b"deliveries"] == b"1"
    assert b"mantissanet-tiny-modulo.onnx" in letter[b"message"]
    assert b"restore it" in letter[b"message"]
    assert client.xlen(JOBS_STREAM) == 0 and queue.stats()["held_bytes"] == 0


def test_a_job_child_whose_warm_up_meets_a_broken_model_still_serves(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """With ``mcam worker --decoder mantissanet-tiny --no-devices`` and that decoder's
    model file not its card's, each job child's warm-up raised ModelFileError, so the
    child died at start: every job, whatever decoder it named (itoh), failed after its
    retries as "decoder_crashed: the decoding process died ... try a smaller frame".
    The warm-up (an optimisation) now logs the file and lets the child serve."""
    decoder = get_decoder("mantissanet-tiny")
    monkeypatch.setattr(decoder.models["modulo"], "_session", None)
    monkeypatch.setattr(learned, "sha256_of", lambda path: "0" * 64)
    start_job_child("mantissanet-tiny")
    assert "mantissanet-tiny-modulo.onnx is not the one its card describes" in caplog.text


def test_a_job_from_an_api_whose_clock_is_ahead_shows_no_negative_time(
    client: redis.Redis, queue: JobQueue, data_dir: Path, make_frame
) -> None:
    """The API (created) and the worker (started, finished) take a job's times on their
    own clocks: with the API's 10 s ahead, the job started before it was created and
    its queue wait and total were negative."""
    frame: SensorFrame = make_frame()
    job = queue.submit("reconstruction", frame.codes, frame.params, "itoh")
    client.hset(job_key(job.id), "created_ns", str(job.created_ns + 10**10))
    handled_here(client, data_dir)
    record = queue.get(job.id)
    assert record.state is JobState.SUCCEEDED
    assert record.started_ns is not None and record.finished_ns is not None
    assert record.created_ns <= record.started_ns <= record.finished_ns
    assert min(record.timings_ns.values()) >= 0, record.timings_ns


def test_a_finished_job_delivered_again_keeps_the_expiry_of_its_results(
    client: redis.Redis, queue: JobQueue, data_dir: Path, make_frame
) -> None:
    """A worker stopped between a job's success and its ack; the next took the entry an
    hour later (no worker ran meanwhile) and set the record's full retention again: the
    record outlived its files by that hour, a succeeded job whose result was gone."""
    frame: SensorFrame = make_frame()
    job = queue.submit("reconstruction", frame.codes, frame.params, "itoh")
    processor, consumer = handled_here(client, data_dir)
    client.expire(job_key(job.id), 60)  # an hour of its retention has passed
    client.xadd(JOBS_STREAM, {"job": job.id})
    [again] = consumer.read_new(block_ms=None)
    processor.handle(consumer, again)
    assert 0 < client.ttl(job_key(job.id)) <= 60
    cancelled = queue.submit("reconstruction", frame.codes, frame.params, "itoh")
    queue.cancel(cancelled.id)
    [dropped] = consumer.read_new(block_ms=None)
    processor.handle(consumer, dropped)
    assert 3500 < client.ttl(job_key(cancelled.id)) <= 3600  # a cancel's: set on drop


def test_a_job_reclaimed_from_a_dead_worker_shows_its_progress_from_0(
    client: redis.Redis, queue: JobQueue, data_dir: Path, make_frame,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A worker SIGKILLed at 60 % of a video left that progress in the record; the worker
    that reclaimed the job redid it from its first frame, but the record said 60 % (24
    frames done) until that worker's first report."""
    frame: SensorFrame = make_frame()
    job = queue.submit("reconstruction", frame.codes, frame.params, "itoh")
    queue.jobs.transition(job.id, JobState.RUNNING, (JobState.QUEUED,), started_ns=job.created_ns,
                          attempts=1, progress=0.6, frames_done=24)  # fmt: skip
    store = ResultStore(data_dir / RESULTS_DIR, retention_s=3600)
    processor = JobProcessor(client, store, max_deliveries=3, stop=threading.Event())
    at_start: list[JobRecord] = []
    transition = processor.jobs.transition

    def seen(job_id: str, to: JobState, *args: object, **fields: object) -> object:
        changed = transition(job_id, to, *args, **fields)  # type: ignore[arg-type]
        if to is JobState.RUNNING:
            at_start.append(processor.jobs.load(job_id))
        return changed

    monkeypatch.setattr(processor.jobs, "transition", seen)
    consumer = StreamConsumer(client, JOBS_STREAM, "w-j0", max_deliveries=3)
    [delivery] = consumer.read_new(block_ms=None)
    delivery.deliveries = 2
    processor.handle(consumer, delivery)
    [record] = at_start
    assert (record.attempts, record.progress, record.frames_done) == (2, 0.0, 0)
    assert queue.get(job.id).state is JobState.SUCCEEDED


def test_a_stalled_worker_whose_job_was_taken_over_stops_decoding_it(
    client: redis.Redis, embedded: EmbeddedRedis, queue: JobQueue, data_dir: Path, wait_until
) -> None:
    """Worker A stalled past the claim idle time and B reclaimed A's job: A's heartbeat
    touch finds the entry gone and A stops its decode (it ran on to the end before),
    leaving the entry, unacked, and the job to B."""
    modulo = SensorParams(encoding="modulo")
    job = queue.submit("reconstruction", random_codes(1024, 1024), modulo, "graphcut")
    store = ResultStore(data_dir / RESULTS_DIR, retention_s=3600)
    child = ChildProcess(start_job_child, ("itoh",))
    processor = JobProcessor(client, store, max_deliveries=3, stop=threading.Event(),
                             child=child)
    stalled = StreamConsumer(client, JOBS_STREAM, "a-j0", max_deliveries=3)
    [delivery] = stalled.read_new(block_ms=None)
    handler = threading.Thread(target=processor.handle, args=(stalled, delivery))
    handler.start()
    wait_until(lambda: queue.get(job.id).state is JobState.RUNNING, 60, "job running")
    wait_until(lambda: child.pid is not None, 60, "the decode running in the child")
    rescuer = StreamConsumer(client, JOBS_STREAM, "b-j0", max_deliveries=3)
    assert rescuer.claim_idle(0) == 1
    worker = Worker(WorkerConfig(redis_url=embedded.url, data_dir=data_dir))
    worker._in_flight[0] = (stalled, delivery)
    worker._touch_in_flight()
    handler.join(30)
    try:
        assert not handler.is_alive(), "the decode went on after its entry was taken over"
        consumers = client.xpending(JOBS_STREAM, GROUP)["consumers"]
        assert [(c["name"], c["pending"]) for c in consumers] == [(b"b-j0", 1)]
        assert queue.get(job.id).state is JobState.RUNNING  # B's to settle
        assert client.hget(counter_key("jobs_abandoned_total"), "") == b"1"
    finally:
        child.close()


class _StoppedBeforeTheAck(JobProcessor):
    """A processor whose worker stops (here: loses Redis) right after the job's result,
    before the entry's ack: as a worker killed there, or a Redis restart, leaves it."""

    def _drop(self, consumer: StreamConsumer, delivery: Delivery, job_id: str,
              dead_letter: object = None) -> None:
        raise redis.exceptions.ConnectionError("Redis went away before the ack")


def test_a_job_that_ended_just_before_its_worker_stopped_is_counted_once(
    embedded: EmbeddedRedis, client: redis.Redis, queue: JobQueue, data_dir: Path, make_frame
) -> None:
    """The succeeded job was counted after its entry's ack: a worker stopped between
    them left it succeeded and never in jobs_processed_total (its redelivery, finding it
    finished, only drops the entry)."""
    store = ResultStore(data_dir / RESULTS_DIR, retention_s=3600)
    job_id, worker, consumer, delivery = job_in_hand(
        embedded.url, client, queue, data_dir, make_frame()
    )
    stopped = _StoppedBeforeTheAck(client, store, max_deliveries=3, stop=worker.stop)
    with pytest.raises(redis.exceptions.ConnectionError):
        worker._handle(stopped, consumer, delivery, 0)
    assert queue.get(job_id).state is JobState.SUCCEEDED
    processor = JobProcessor(client, store, max_deliveries=3, stop=worker.stop)
    worker._handle(processor, consumer, delivery, 0)
    assert client.xlen(JOBS_STREAM) == 0
    ended = {f.name: f for f in read_metrics(client)}["jobs_processed_total"]
    assert [(s.labels, s.value) for s in ended.samples] == [({"state": "succeeded"}, 1)]


def test_a_job_submitted_by_a_clock_ahead_has_no_negative_times(
    embedded: EmbeddedRedis, client: redis.Redis, queue: JobQueue, data_dir: Path, make_frame
) -> None:
    """The queue wait and total were the worker's clock minus the submitting API's: an
    API host a minute ahead gave a job's timings_ns and the histograms -60 s (their
    _sum went down, which Prometheus reads as a counter reset)."""
    store = ResultStore(data_dir / RESULTS_DIR, retention_s=3600)
    job_id, worker, consumer, delivery = job_in_hand(
        embedded.url, client, queue, data_dir, make_frame()
    )
    queue.jobs.update(job_id, created_ns=queue.get(job_id).created_ns + 60 * 10**9)
    worker._handle(JobProcessor(client, store, max_deliveries=3, stop=worker.stop),
                   consumer, delivery, 0)
    record = queue.get(job_id)
    assert record.state is JobState.SUCCEEDED
    assert record.timings_ns["queue_wait"] == 0 and record.timings_ns["total"] == 0
    families = {f.name: f for f in read_metrics(client)}
    for name in ("queue_wait_seconds", "total_seconds"):
        assert families[name].samples[0].value == 0.0, name


class _CancelledWhileWriting(ResultStore):
    """A result store whose first write lets the API's cancel in first: the job passed
    its last check and the worker writes its files as the cancel lands."""

    def __init__(self, root: Path, cancel: Callable[[], object]) -> None:
        super().__init__(root, retention_s=3600)
        self.cancel: Callable[[], object] | None = cancel

    def write(self, key: str, data: bytes, *, replace: bool = True) -> Path:
        if self.cancel is not None:
            self.cancel()
            self.cancel = None
        return super().write(key, data, replace=replace)


def test_a_job_cancelled_while_its_files_are_written_leaves_none(
    client: redis.Redis, queue: JobQueue, data_dir: Path, make_frame
) -> None:
    """A cancel that landed after the job's last check: the worker wrote the EXR, the
    winding map and the codes, found the job cancelled and dropped it, and the files
    stayed, listed nowhere, until the retention purge a week later. They now go when
    the worker drops the job; another job's files stay."""
    frame: SensorFrame = make_frame()
    kept = queue.submit("reconstruction", frame.codes, frame.params, "itoh")
    handled_here(client, data_dir)
    job = queue.submit("reconstruction", frame.codes, frame.params, "itoh")
    store = _CancelledWhileWriting(data_dir / RESULTS_DIR, lambda: queue.cancel(job.id))
    processor = JobProcessor(client, store, max_deliveries=3, stop=threading.Event())
    consumer = StreamConsumer(client, JOBS_STREAM, "w-j0", max_deliveries=3)
    [delivery] = consumer.read_new(block_ms=None)
    processor.handle(consumer, delivery)
    assert queue.get(job.id).state is JobState.CANCELLED
    assert client.xlen(JOBS_STREAM) == 0
    assert store.keys() == sorted(queue.get(kept.id).results.values())
    assert not (store.root / "jobs" / job.id).exists()


class _StalledMidWrites(ResultStore):
    """A result store whose writer stalls after its first file until ``resume`` is set,
    as a worker paused mid-writes (SIGSTOP, a swapping host)."""

    def __init__(self, root: Path) -> None:
        super().__init__(root, retention_s=3600)
        self.stalled = threading.Event()
        self.resume = threading.Event()

    def write(self, key: str, data: bytes, *, replace: bool = True) -> Path:
        path = super().write(key, data, replace=replace)
        if not self.stalled.is_set():
            self.stalled.set()
            self.resume.wait(60)
        return path


def test_a_cancelled_job_taken_from_a_stalled_worker_keeps_no_files(
    client: redis.Redis, queue: JobQueue, data_dir: Path, make_frame, wait_until
) -> None:
    """Worker A stalled between two of a job's files; the job was cancelled and B,
    which took the entry over, dropped it, leaving A's first file. The files now go
    when B drops the job, and when A wakes and writes the rest, A removes them as it
    finds the job cancelled: none is left, as none was written."""
    frame: SensorFrame = make_frame()
    job = queue.submit("reconstruction", frame.codes, frame.params, "itoh")
    stalled_store = _StalledMidWrites(data_dir / RESULTS_DIR)
    stalled = JobProcessor(client, stalled_store, max_deliveries=3, stop=threading.Event())
    a = StreamConsumer(client, JOBS_STREAM, "a-j0", max_deliveries=3)
    [delivery] = a.read_new(block_ms=None)
    handler = threading.Thread(target=stalled.handle, args=(a, delivery))
    handler.start()
    try:
        wait_until(stalled_store.stalled.is_set, 60, "A's first file written")
        folder = stalled_store.root / "jobs" / job.id
        assert folder.exists()
        assert queue.cancel(job.id).state is JobState.CANCELLED
        b = StreamConsumer(client, JOBS_STREAM, "b-j0", max_deliveries=3)
        assert b.claim_idle(0) == 1
        [taken] = b.read_own_pending(1)
        store = ResultStore(data_dir / RESULTS_DIR, retention_s=3600)
        JobProcessor(client, store, max_deliveries=3, stop=threading.Event()).handle(b, taken)
        assert client.xlen(JOBS_STREAM) == 0
        assert not folder.exists(), "B left the cancelled job's files"
    finally:
        stalled_store.resume.set()
        handler.join(60)
    assert not handler.is_alive()
    assert not folder.exists(), "A's later files stayed"
    assert queue.get(job.id).state is JobState.CANCELLED


def test_the_purge_keeps_the_frames_of_a_running_recording_however_old(
    embedded: EmbeddedRedis, client: redis.Redis, data_dir: Path, monkeypatch, wait_until
) -> None:
    """A recording's frames exist nowhere else until its video job is queued: the
    retention purge leaves them, however long the recording runs, and purges the rest.
    Before, a recording longer than ``MCAM_RESULT_RETENTION_S`` (600 frames at 0.1 fps
    under a retention of an hour; a camera unplugged for a week mid-recording) lost its
    first frames, and its stop failed ("no result ... never written or expired")."""
    monkeypatch.setattr("worker.runner.PURGE_EVERY_S", 0.05)
    client.sadd(DEVICES_SET, "cam1")
    recording = start_recording(client, "cam1", decoder="itoh", options={}, max_frames=10)
    store = ResultStore(data_dir / RESULTS_DIR, retention_s=3600)
    recorded, other = frame_key(recording.id, 0), "devices/cam1/000000000001-1-0.exr"
    two_hours_ago = time.time() - 7200
    for key in (recorded, other):
        store.write(key, b"old")
        os.utime(store.path(key), (two_hours_ago, two_hours_ago))
    worker = Worker(WorkerConfig(redis_url=embedded.url, data_dir=data_dir, devices=False,
                                 heartbeat_s=0.1, retention_s=3600), worker_id="w-purge")
    running = threading.Thread(target=worker.run, daemon=True)
    running.start()
    try:
        wait_until(lambda: not store.exists(other), 30, "the purge")
        assert store.exists(recorded)
    finally:
        worker.request_stop()
        running.join(30)
