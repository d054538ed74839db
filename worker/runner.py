"""The worker process: job consumers, the device-stream consumer, heartbeats, shutdown.

Usage::

    worker = Worker(WorkerConfig(redis_url="unix:///.../redis.sock", data_dir=Path("data")))
    exit_code = worker.run()     # blocks; SIGTERM / SIGINT stop it gracefully

Threads: ``concurrency`` job consumers on the ``jobs`` stream (each its own
consumer in the ``workers`` group: reclaim entries idle > ``claim_idle_ms``, else
read new ones; each decodes its jobs' frames in a child process of its own, see
:mod:`worker.job_processor`), one device consumer (leases + in-order frames, see
``worker/device_consumer.py``), and the main thread, which writes this worker's
heartbeat to the ``workers`` hash every ``heartbeat_s``, renews its device leases
(so ``heartbeat_s`` must be shorter than ``lease_ms``), keeps its in-flight jobs
from looking idle (so long jobs are not reclaimed from a live worker). A purge thread
deletes expired results every :data:`PURGE_EVERY_S`.
On SIGTERM the consumers finish the job or frame in hand (a long video job hands
itself back to the queue), leases are released and the heartbeat is removed. A
second signal exits at once; unacked work is then reclaimed by others.
"""

from __future__ import annotations

import json
import logging
import os
import random
import socket
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import redis

from models.errors import McamError
from models.hdr_io import EXR_COMPRESSIONS
from models.stop_signals import STOP_POLL_S, noting_stop_signals
from worker.child_process import ChildProcess
from worker.config_checks import heartbeat_problem
from worker.decode_pool import DecodePool
from worker.deliveries import Delivery, StreamConsumer, prune_consumers
from worker.device_consumer import DeviceConsumer
from worker.device_state import FrameDecoder, make_frame_decoder, warm_up
from worker.embedded_redis import connect, redacted_url
from worker.job_processor import JobProcessor, start_job_child
from worker.outputs import STREAM_EXR_COMPRESSION
from worker.queue import ensure_group, is_missing_group, server_time_ns
from worker.recordings import active_recording_folders
from worker.redis_keys import JOBS_STREAM, WORKERS_HEARTBEAT
from worker.redis_memory import UNREACHABLE, TroubleLog, is_transient
from worker.result_store import RESULTS_DIR, ResultStore

log = logging.getLogger(__name__)

#: How long a consumer blocks waiting for new entries (ms); bounds shutdown latency.
BLOCK_MS = 1000
#: Pause of the device consumer when no device had frames (s).
DEVICE_IDLE_S = 0.02
#: Pause of the device consumer while it owns no device (s): new devices start within it.
NO_DEVICE_IDLE_S = 0.25
#: Pause after a failed loop step (Redis unreachable or full, or an unexpected error)
#: before trying again (s); doubled after each failure in a row, up to
#: :data:`RECONNECT_MAX_S` (see :func:`reconnect_delay`).
RECONNECT_S = 1.0
RECONNECT_MAX_S = 8.0
#: Doublings past which the pause stays at the cap (bounds the power: a loop that has
#: failed for hours must not overflow).
RECONNECT_DOUBLINGS = 16
#: Purge expired results this often (s).
PURGE_EVERY_S = 300.0
#: Heartbeats older than this many heartbeat periods are removed by any worker.
STALE_HEARTBEATS = 30
#: Between a worker's id and its job thread's index in the name of its consumer.
JOB_CONSUMER_SEPARATOR = "-j"


@dataclass(frozen=True)
class WorkerConfig:
    """Everything a worker needs; the CLI fills it from the ``MCAM_*`` settings.

    Times: ``claim_idle_ms`` / ``lease_ms`` in ms, ``heartbeat_s`` / ``retention_s`` in s.
    ``decoder``, ``frame_mode``, ``stream_exr_compression`` and ``stream_processes``
    (independent decoding on a pool of that many processes when above 1:
    :mod:`worker.decode_pool`) apply to live device frames (jobs name their own).
    """

    redis_url: str
    data_dir: Path
    concurrency: int = 1
    decoder: str = "itoh"
    frame_mode: str = "independent"
    claim_idle_ms: int = 30_000
    max_deliveries: int = 3
    lease_ms: int = 5_000
    heartbeat_s: float = 2.0
    retention_s: float = 7 * 24 * 3600.0
    devices: bool = True
    stream_exr_compression: str = STREAM_EXR_COMPRESSION
    stream_processes: int = 1

    def __post_init__(self) -> None:
        if self.concurrency < 1:
            raise McamError(f"concurrency must be at least 1, got {self.concurrency}")
        if self.stream_processes < 1:
            raise McamError(
                f"stream processes must be at least 1, got {self.stream_processes}; set "
                "MCAM_STREAM_PROCESSES to 1 (decode in the worker) or more (a pool)"
            )
        if self.stream_exr_compression not in EXR_COMPRESSIONS:
            raise McamError(
                f"unknown stream EXR compression {self.stream_exr_compression!r}; set "
                f"MCAM_STREAM_EXR_COMPRESSION to one of: {', '.join(EXR_COMPRESSIONS)}"
            )
        problem = heartbeat_problem(self.heartbeat_s, self.lease_ms, self.claim_idle_ms)
        if problem:
            raise McamError(problem)


def new_worker_id() -> str:
    """A unique, readable worker id: host, pid and a random suffix."""
    return f"{socket.gethostname()}-{os.getpid()}-{uuid.uuid4().hex[:6]}"


def job_consumer(worker_id: str, index: int) -> str:
    """The name of worker ``worker_id``'s job thread ``index`` in the jobs stream's group."""
    return f"{worker_id}{JOB_CONSUMER_SEPARATOR}{index}"


def worker_of(consumer: str) -> str:
    """The worker id of a job consumer named by :func:`job_consumer`."""
    return consumer.rpartition(JOB_CONSUMER_SEPARATOR)[0]


def reconnect_delay(failures: int, jitter: float) -> float:
    """Seconds to wait after ``failures`` (>= 1) failed steps in a row: :data:`RECONNECT_S`
    doubled per further failure, at most :data:`RECONNECT_MAX_S`, times ``jitter`` (0.5
    to 1, drawn per wait) so that the loops that lost Redis together do not all retry in
    the same instant. A long outage then costs a loop one try per 4-8 s, not one a
    second, and a short one is noticed within a second or two."""
    doublings = min(failures - 1, RECONNECT_DOUBLINGS)
    return min(RECONNECT_S * 2.0**doublings, RECONNECT_MAX_S) * jitter


class Worker:
    """One worker process (see the module docstring)."""

    def __init__(self, config: WorkerConfig, worker_id: str | None = None) -> None:
        self.config = config
        self.id = worker_id or new_worker_id()
        self.client: redis.Redis = connect(config.redis_url)
        self.store = ResultStore(Path(config.data_dir) / RESULTS_DIR, config.retention_s)
        self.stop = threading.Event()
        self.jobs_done = 0
        self.started_ns = time.time_ns()
        self._devices: DeviceConsumer | None = None
        self._in_flight: dict[int, tuple[StreamConsumer, Delivery]] = {}
        self._trouble = TroubleLog(log)
        self._signals_acted_on = 0

    def request_stop(self, *_args: object) -> None:
        """Ask every loop to finish its current item and exit (a second call exits now)."""
        if self.stop.is_set():
            log.warning("worker %s: second stop signal, exiting now", self.id)
            os._exit(1)
        log.info("worker %s stopping", self.id)
        self.stop.set()

    def run(self) -> int:
        """Run until stopped; returns the process exit code. On the main thread, stop
        signals are noted and acted on by the heartbeat loop (:meth:`_act_on_signals`):
        a handler that stopped the worker itself set a ``threading.Event``, whose lock a
        second signal's handler then waited for (or nested into a RecursionError)."""
        if threading.current_thread() is not threading.main_thread():
            return self._run([])
        with noting_stop_signals() as received:
            return self._run(received)

    def _run(self, signals: list[int]) -> int:
        """:meth:`run` with the stop signals noted in ``signals``."""
        threads = [
            threading.Thread(target=self._job_loop, args=(i,), name=f"jobs-{i}", daemon=True)
            for i in range(self.config.concurrency)
        ]
        if self.config.devices:
            decode = self._stream_decoder()
            threads.append(
                threading.Thread(
                    target=self._device_loop, args=(decode,), name="devices", daemon=True
                )
            )
        purger = threading.Thread(target=self._purge_loop, name="purge", daemon=True)
        for thread in [*threads, purger]:
            thread.start()
        log.info("worker %s running (%d job threads) on Redis at %s", self.id,
                 self.config.concurrency, redacted_url(self.config.redis_url))
        self._heartbeat_loop(threads, signals)
        for thread in [*threads, purger]:
            thread.join()
        self._forget_heartbeat()
        self.client.close()
        return 0

    def _act_on_signals(self, signals: list[int]) -> None:
        """:meth:`request_stop` for each stop signal noted in ``signals`` since the last
        call (the first stops the worker, the next exits now)."""
        while self._signals_acted_on < len(signals):
            self._signals_acted_on += 1
            self.request_stop()

    def _pause(self, seconds: float, signals: list[int], done: Callable[[], bool]) -> None:
        """Wait up to ``seconds`` (s) or until ``done()``, acting on the stop signals
        noted in ``signals`` every :data:`models.stop_signals.STOP_POLL_S`."""
        deadline = time.monotonic() + seconds
        while (left := deadline - time.monotonic()) > 0:
            self._act_on_signals(signals)
            if done():
                return
            time.sleep(min(STOP_POLL_S, left))

    def _resilient(self, step: Callable[[], None]) -> None:
        """Run ``step`` until stopped, surviving Redis outages and unexpected errors, each
        retry after :func:`reconnect_delay`."""
        failures = 0
        while not self.stop.is_set():
            try:
                step()
                failures = 0
            except Exception as exc:
                failures += 1
                if is_transient(exc):
                    where = f"worker {self.id} ({threading.current_thread().name})"
                    self._trouble.warn(where, exc)
                else:
                    log.exception("worker %s: unexpected error; continuing", self.id)
                self.stop.wait(reconnect_delay(failures, random.uniform(0.5, 1.0)))

    def _job_loop(self, index: int) -> None:
        child = ChildProcess(start_job_child, (self.config.decoder,))
        processor = JobProcessor(
            self.client,
            self.store,
            max_deliveries=self.config.max_deliveries,
            stop=self.stop,
            child=child,
        )
        consumer: StreamConsumer | None = None

        def step() -> None:
            nonlocal consumer
            if consumer is None:
                consumer = StreamConsumer(
                    self.client,
                    JOBS_STREAM,
                    job_consumer(self.id, index),
                    max_deliveries=self.config.max_deliveries,
                )
            try:
                self._job_step(processor, consumer, index)
            except redis.exceptions.ResponseError as exc:
                if not is_missing_group(exc):
                    raise
                self._in_flight.pop(index, None)
                log.warning(
                    "worker %s: the jobs stream's consumer group is gone (Redis restarted "
                    "without its data?); making it again", self.id
                )
                ensure_group(self.client, JOBS_STREAM)

        self._resilient(step)
        child.close()

    def _job_step(self, processor: JobProcessor, consumer: StreamConsumer, index: int) -> None:
        """One turn of job thread ``index``: its own pending entry (kept after a
        transient error), else an idle one reclaimed, else a new one; handled."""
        deliveries = consumer.read_own_pending(1)
        for delivery in deliveries:  # again after a transient error: not idle meanwhile
            consumer.touch(delivery)
        if not deliveries:
            self._in_flight.pop(index, None)
        deliveries = deliveries or consumer.reclaim(self.config.claim_idle_ms, count=1)
        if not deliveries and not self.stop.is_set():
            deliveries = consumer.read_new(block_ms=BLOCK_MS, count=1)
        for delivery in deliveries:
            self._in_flight[index] = (consumer, delivery)
            self._handle(processor, consumer, delivery, index)
            self._in_flight.pop(index, None)
            self.jobs_done += 1

    def _handle(
        self, processor: JobProcessor, consumer: StreamConsumer, delivery: Delivery, index: int
    ) -> None:
        """Handle one job entry of job thread ``index``. When Redis is unreachable or full
        the entry stays in flight, so the heartbeat keeps touching it while the loop
        waits to retry it; after any other error it counts a delivery and leaves the
        heartbeat's care, so that the processor fails it past ``max_deliveries``."""
        try:
            processor.handle(consumer, delivery)
        except Exception as exc:
            if not is_transient(exc):
                self._in_flight.pop(index, None)
                consumer.retry(delivery)
            raise

    def _stream_decoder(self) -> FrameDecoder | DecodePool:
        """The live frames' decoder, warmed up: a pool of ``stream_processes`` processes
        for independent decoding (:mod:`worker.decode_pool`), else this process's own."""
        config = self.config
        if config.frame_mode == "independent" and config.stream_processes > 1:
            log.info("worker %s: stream decoder %s on %d processes", self.id, config.decoder,
                     config.stream_processes)  # fmt: skip
            return DecodePool(config.decoder, config.stream_processes)
        took = warm_up(config.decoder)
        log.info("worker %s: stream decoder %s warmed up (%s)", self.id, config.decoder,
                 ", ".join(f"{enc} {ms:.0f} ms" for enc, ms in took.items()))  # fmt: skip
        return make_frame_decoder(config.frame_mode, config.decoder)

    def _device_loop(self, decode: FrameDecoder | DecodePool) -> None:
        """Consume device streams until stopped. The consumer is made within the retry
        loop: making it writes to Redis (consumer groups), which may be down or full."""

        def step() -> None:
            if self._devices is None:
                self._devices = DeviceConsumer(
                    self.client,
                    self.store,
                    owner=self.id,
                    lease_ms=self.config.lease_ms,
                    max_deliveries=self.config.max_deliveries,
                    decode=decode,
                    stop=self.stop,
                    peers=self._device_workers,
                    exr_compression=self.config.stream_exr_compression,
                )
            if not self._devices.poll():
                self.stop.wait(DEVICE_IDLE_S if self._devices.states else NO_DEVICE_IDLE_S)

        self._resilient(step)
        if self._devices is not None:
            try:
                self._devices.release_all()
            except UNREACHABLE:
                log.warning(
                    "worker %s: could not release device leases (they will lapse)", self.id
                )
        if isinstance(decode, DecodePool):
            decode.close()

    def _heartbeat_loop(self, threads: list[threading.Thread], signals: list[int]) -> None:
        """Beat and keep in-flight jobs and device leases alive every ``heartbeat_s``
        until the worker stops and ``threads`` have finished: a job in hand while the
        worker stops is still this worker's (another would reclaim it and decode it
        again). Meanwhile it acts on the stop signals noted in ``signals``."""

        def finished() -> bool:
            return self.stop.is_set() and not any(thread.is_alive() for thread in threads)

        while not finished():
            # Each on its own: a full Redis refuses the beat (a write that grows a hash)
            # but not the touches, which keep in-flight jobs from being reclaimed.
            self._heartbeat_step("touch in-flight jobs", self._touch_in_flight)
            if self._devices is not None:
                self._heartbeat_step("renew device leases", self._devices.renew_all)
            self._heartbeat_step("beat", self._beat)
            stopped = self.stop.is_set()
            self._pause(
                self.config.heartbeat_s, signals, finished if stopped else self.stop.is_set
            )

    def _purge_loop(self) -> None:
        """Purge expired results now and every :data:`PURGE_EVERY_S` until the worker
        stops, on a thread of its own: walking a store of millions of stream frames
        takes minutes, longer than a device lease or a job's idle time, and must not
        hold up the heartbeat. A failing purge (a folder we may not read) is logged
        and tried again next time."""
        while not self.stop.is_set():
            try:
                removed = self.store.purge_expired(
                    stop=self.stop, keep=active_recording_folders(self.client)
                )
            except (OSError, redis.exceptions.RedisError) as exc:
                log.warning("worker %s: could not purge expired results: %s", self.id, exc)
            else:
                if removed:
                    log.info("worker %s purged %d expired results", self.id, removed)
            self.stop.wait(PURGE_EVERY_S)

    def _heartbeat_step(self, what: str, step: Callable[[], object]) -> None:
        """Run one step of the heartbeat; a transient Redis error is logged, not raised."""
        try:
            step()
        except Exception as exc:
            if not is_transient(exc):
                raise
            self._trouble.warn(f"worker {self.id}: could not {what}", exc)

    def _touch_in_flight(self) -> None:
        """Keep in-flight job entries from being reclaimed; mark those another worker
        took over meanwhile (this one stalled) as lost, so their jobs stop here."""
        for consumer, delivery in list(self._in_flight.values()):
            if not consumer.touch(delivery):
                delivery.lost.set()

    def _beat(self) -> None:
        now = server_time_ns(self.client)  # other hosts' clocks age the beat too
        beat = {
            "ts_ns": now,
            "started_ns": self.started_ns,
            "pid": os.getpid(),
            "host": socket.gethostname(),
            "concurrency": self.config.concurrency,
            "jobs_done": self.jobs_done,
            "devices": sorted(list(self._devices.states)) if self._devices else [],
            "device_consumer": self.config.devices,
        }
        self.client.hset(WORKERS_HEARTBEAT, self.id, json.dumps(beat))
        stale_ns = STALE_HEARTBEATS * self.config.heartbeat_s * 1e9
        live = set()
        for worker_id, raw in self.client.hgetall(WORKERS_HEARTBEAT).items():
            if now - int(json.loads(raw).get("ts_ns", 0)) > stale_ns:
                self.client.hdel(WORKERS_HEARTBEAT, worker_id)
            else:
                live.add(worker_id.decode())
        # Consumers of workers gone (stopped, or silent too long) with nothing pending.
        prune_consumers(self.client, JOBS_STREAM, lambda name: worker_of(name) in live)

    def _device_workers(self) -> int:
        """Workers consuming device streams whose heartbeat is fresh (3 periods)."""
        now = server_time_ns(self.client)
        beats = [json.loads(raw) for raw in self.client.hvals(WORKERS_HEARTBEAT)]
        return sum(
            1
            for beat in beats
            if beat.get("device_consumer")
            and now - beat["ts_ns"] < 3 * self.config.heartbeat_s * 1e9
        )

    def _forget_heartbeat(self) -> None:
        try:
            self.client.hdel(WORKERS_HEARTBEAT, self.id)
        except UNREACHABLE:
            log.warning("worker %s: could not remove its heartbeat", self.id)
