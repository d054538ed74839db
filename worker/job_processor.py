"""Running one job from the jobs stream: state, decoding, durable results, retries.

Usage (inside the worker)::

    processor = JobProcessor(client, store, max_deliveries=3, stop=stop_event,
                             child=ChildProcess(start_job_child, ("auto",)))
    processor.handle(consumer, delivery)      # never raises for a job's own failure

Each job kind has a handler ``handler(ctx: JobContext, codes) -> JobOutcome``
named in :data:`HANDLERS` as ``"module:function"`` and imported on first use;
``video`` is provided by ``worker/video_jobs.py``. A handler writes its files
with ``ctx.write(name, data)``, reports progress with ``ctx.progress(n)``,
calls ``ctx.check()`` between steps (raises when the job was cancelled) and, if
it runs long, ``ctx.check_stop()`` (raises when the worker is stopping: the job
is handed back to the queue). Results are keyed by job id (``jobs/<id>/...``), so a
redelivered job overwrites identical files and never duplicates them. A cancelled job's
folder is removed by each worker that drops its entry or stops working on it (as it
finds the job cancelled): the API never removes it, as a worker may still be writing
there, and a worker that wrote after another removed it removes it again.

A reconstruction's decode runs in the job thread's child process
(:class:`worker.child_process.ChildProcess`, warmed up on the worker's decoder when
the worker starts): a decode that holds the interpreter lock for minutes (graph cuts
on a large frame) cannot stall the worker's heartbeat, leases and streams, and a job
cancelled mid-decode ends it at once (the child is killed; the next job starts a new
one). A video job decodes its frames there too, a few at a time
(:data:`worker.video_jobs.CHUNK_FRAMES`); a worker that is stopping ends a video's
decode at once and hands the job back, while it finishes a still job's.
"""

from __future__ import annotations

import importlib
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import redis
from numpy.typing import NDArray

from models.allocator import keep_freed_memory
from models.decoders.learned import ModelFileError
from models.decoders.registry import get_decoder
from models.errors import McamError
from models.formation import SensorParams, narrow_winding
from worker.child_process import ChildDiedError, ChildProcess
from worker.deliveries import Delivery, StreamConsumer
from worker.device_state import warm_up
from worker.job_store import JobStore
from worker.jobs import JobError, JobNotFoundError, JobRecord, JobState, time_after
from worker.metrics import Metrics
from worker.outputs import OUTPUT_NAMES, encode_outputs
from worker.queue import entry_codes
from worker.queue_holds import QueueHolds
from worker.redis_memory import is_transient
from worker.result_store import ResultStore

log = logging.getLogger(__name__)

#: Job kind -> "module:function" of its handler.
HANDLERS: dict[str, str] = {
    "reconstruction": "worker.job_processor:reconstruct_job",
    "video": "worker.video_jobs:run_video_job",
}
#: Pause before retrying a failed job in place, doubled per delivery (s).
RETRY_BACKOFF_S = 0.05


class JobCancelled(Exception):
    """The job was cancelled (or settled elsewhere) while it ran: drop it."""


class EntryLost(Exception):
    """Another worker took the job's entry over while this one stalled: stop, leave it."""


class ShutdownRequested(Exception):
    """The worker is stopping; the job is handed back to the queue."""


@dataclass
class JobOutcome:
    """What a handler produced: result keys by output name, stage timings (ns), facts."""

    results: dict[str, str]
    timings_ns: dict[str, int]
    info: dict[str, Any] = field(default_factory=dict)


@dataclass
class JobContext:
    """What a handler may use while it runs one job; ``child`` decodes its frame (None:
    in this process)."""

    record: JobRecord
    jobs: JobStore
    store: ResultStore
    stop: threading.Event
    child: ChildProcess | None = None
    lost: threading.Event = field(default_factory=threading.Event)

    def run(self, function: Callable[..., Any], *args: Any, hand_back: bool = False) -> Any:
        """``function(*args)`` in the job's child process when there is one (both
        picklable), else here; raises :class:`JobCancelled` as soon as the job is
        cancelled or settled elsewhere. A worker that is stopping lets the call finish,
        as it would here, unless ``hand_back``: then :class:`ShutdownRequested` ends it
        at once (a video job, which the next worker redoes from its first frame)."""
        if self.child is None:
            return function(*args)
        return self.child.call(function, args, self.check_all if hand_back else self.check)

    def check_all(self) -> None:
        """:meth:`check_stop`, then :meth:`check`."""
        self.check_stop()
        self.check()

    def decode(self, codes: NDArray[np.unsignedinteger]) -> StillDecode:
        """The job's frame (codes, DN) decoded by its decoder (:meth:`run`)."""
        result: StillDecode = self.run(
            decode_still, self.record.decoder, codes, self.record.params
        )
        return result

    def check(self) -> None:
        """Raise :class:`EntryLost` when another worker has taken the job's entry over
        (this one stalled), :class:`JobCancelled` when the job was cancelled or has been
        settled by another worker."""
        if self.lost.is_set():
            raise EntryLost
        if self.jobs.load(self.record.id).state.finished:
            raise JobCancelled

    def check_stop(self) -> None:
        """Raise :class:`ShutdownRequested` when the worker is stopping (long handlers call
        this between frames; the job goes back to the queue and resumes elsewhere)."""
        if self.stop.is_set():
            raise ShutdownRequested

    def progress(self, frames_done: int, fraction: float | None = None) -> None:
        """Record ``frames_done`` of ``frames_total`` frames and the share of the job's
        work done (0..1; by default the share of frames done)."""
        if fraction is None:
            fraction = frames_done / max(self.record.frames_total, 1)
        self.jobs.update(
            self.record.id, frames_done=frames_done, progress=min(max(fraction, 0.0), 1.0)
        )

    def key(self, name: str) -> str:
        """The result-store key of output file ``name`` of this job."""
        return f"{job_folder(self.record.id)}/{name}"

    def write(self, name: str, data: bytes) -> str:
        """Write output file ``name`` durably; returns its key."""
        key = self.key(name)
        self.store.write(key, data)
        return key


JobHandler = Callable[[JobContext, NDArray[np.unsignedinteger]], JobOutcome]


def job_folder(job_id: str) -> str:
    """The result-store folder of a job's files."""
    return f"jobs/{job_id}"


@dataclass(frozen=True)
class StillDecode:
    """A decoded still frame as it travels back from the child: W in its narrowest
    integer type, the decoder's facts and its timings (ns)."""

    winding: NDArray[np.signedinteger]
    info: dict[str, Any]
    timings_ns: dict[str, int]


def decode_still(
    decoder: str, codes: NDArray[np.unsignedinteger], params: SensorParams
) -> StillDecode:
    """Decode one frame with ``decoder`` (run in a job's child process)."""
    result = get_decoder(decoder).decode(codes, params)
    return StillDecode(narrow_winding(result.winding), result.info, result.timings_ns)


def start_job_child(decoder: str) -> None:
    """A job child's initializer: the command line's allocator settings, and
    ``decoder`` (the worker's) built and warmed so a first job does not wait for it. A
    model file of ``decoder`` that is not its card's is logged, not raised
    (:func:`worker.device_state.warm_up`): the child would die at start and fail every
    job, whatever its decoder, as a crash; a job that needs that model fails as
    ``model_unavailable`` instead."""
    keep_freed_memory()
    warm_up(decoder)


def reconstruct_job(ctx: JobContext, codes: NDArray[np.unsignedinteger]) -> JobOutcome:
    """Decode one frame with the job's decoder; write the EXR and the winding map. (Its
    progress is set with its final state: a write per job fewer, each an fsync.)"""
    record = ctx.record
    result = ctx.decode(codes)
    ctx.check()
    start = time.perf_counter_ns()
    files = encode_outputs(codes, result.winding, record.params, result.info, record.options)
    results = {name: ctx.write(OUTPUT_NAMES[name], data) for name, data in files.items()}
    return JobOutcome(
        results=results,
        timings_ns={"decode": result.timings_ns["total"], "encode": time.perf_counter_ns() - start},
        info=result.info,
    )


def load_handler(kind: str) -> JobHandler:
    """The handler of job kind ``kind`` (McamError when this installation has none)."""
    target = HANDLERS.get(kind)
    if target is None:
        raise McamError(f"unknown job kind {kind!r}")
    module_name, _, name = target.partition(":")
    try:
        return getattr(importlib.import_module(module_name), name)
    except (ModuleNotFoundError, AttributeError):
        raise McamError(f"this worker cannot run {kind} jobs ({target} is missing)") from None


def error_of(exc: BaseException, logged_with: str = "this job's id") -> JobError:
    """The job error a client sees for an exception: the McamError's code and message,
    else ``internal_error`` with a message that says what to do and shows none of the
    host's internals (paths, exception text); the worker's log has the traceback, found
    by ``logged_with``, and the dead letter the exception (:func:`dead_letter_of`)."""
    if isinstance(exc, McamError):
        return JobError(code=exc.code, message=exc.message)
    return JobError(
        code="internal_error",
        message=f"the worker failed on an internal error (logged with {logged_with}); "
        "retry later, or report it if it persists",
    )


def model_unavailable(decoder: str, encoding: str, logged_with: str, then: str) -> JobError:
    """The error a client sees for a job or frame whose decoder's model file is not the
    one its card describes (:class:`models.decoders.learned.ModelFileError`): the
    server's install, not the request, is at fault, and no retry mends it until an
    operator restores the file (its name is in the worker's log, found by
    ``logged_with``, and the dead letter, not here). ``decoder``: words naming the
    decoder; ``then``: what the client can do."""
    return JobError(
        code="model_unavailable",
        message=f"{decoder} cannot decode {encoding} frames on this server: its model file "
        "is missing or not the one its card describes (logged with "
        f"{logged_with} for the operator to restore); {then}",
    )


def dead_letter_of(exc: BaseException) -> JobError:
    """The error an operator reads in the dead letters for an exception: the client's
    (:func:`error_of`), but an internal error's message is the exception's type and text."""
    if isinstance(exc, McamError):
        return error_of(exc)
    return JobError(code="internal_error", message=f"{type(exc).__name__}: {exc}")


class JobProcessor:
    """Runs jobs handed to a consumer, with in-place retries and dead-lettering."""

    def __init__(
        self,
        client: redis.Redis,
        store: ResultStore,
        *,
        max_deliveries: int,
        stop: threading.Event,
        child: ChildProcess | None = None,
    ) -> None:
        self.jobs = JobStore(client)
        self.holds = QueueHolds(client)
        self.metrics = Metrics(client)
        self.store = store
        self.max_deliveries = max_deliveries
        self.stop = stop
        self.child = child

    def handle(self, consumer: StreamConsumer, delivery: Delivery) -> None:
        """Process one entry to a final outcome: done, failed (dead letter) or handed back.
        A lost Redis connection, or a full Redis refusing a write, propagates (the entry
        stays pending and is handled again; :func:`worker.redis_memory.is_transient`)."""
        try:
            record = self.jobs.load(delivery.text("job"))
        except (KeyError, UnicodeDecodeError) as exc:
            consumer.dead_letter(delivery, "not_found", f"entry names no job: {exc}")
            return
        except JobNotFoundError as exc:
            error = JobError(code="not_found", message=f"entry names no known job: {exc}")
            self._drop(consumer, delivery, delivery.text("job"), dead_letter=error)
            return
        except (ValueError, redis.exceptions.ResponseError) as exc:
            # A record that does not parse, or a key of the wrong type: it would never
            # run (a full Redis refuses writes, never this read).
            log.error("job %s: its record is corrupt; dead-lettered: %s", delivery.text("job"), exc)
            error = JobError(code="internal_error", message=f"the job's record is corrupt: {exc}")
            self._drop(consumer, delivery, delivery.text("job"), dead_letter=error)
            return
        while True:
            if record.state.finished:
                # Settled before (a worker stopped between its result and the ack, or a
                # cancel): dropped, however often it was delivered.
                self._finish(consumer, delivery, record.id)
                return
            if delivery.deliveries > self.max_deliveries:
                self._fail(
                    consumer,
                    delivery,
                    record,
                    JobError(
                        code="worker_lost",
                        message=f"delivered {delivery.deliveries} times without finishing "
                        "(workers stopped while running it)",
                    ),
                )
                return
            try:
                self._run(consumer, delivery, record)
                return
            except JobCancelled:
                self._finish(consumer, delivery, record.id)
                return
            except EntryLost:
                self.metrics.inc("jobs_abandoned_total")
                log.warning("job %s: another worker took its entry over while this one "
                            "stalled; stopped here, left to it", record.id)
                return
            except Exception as exc:
                if is_transient(exc):
                    raise
                if isinstance(exc, ShutdownRequested) or (
                    self.stop.is_set() and isinstance(exc, ChildDiedError)
                ):
                    self._hand_back(consumer, delivery, record)
                    return
                if isinstance(exc, McamError) and not isinstance(exc, ChildDiedError):
                    self._fail(consumer, delivery, record, error_of(exc), caller_error=True)
                    return
                if isinstance(exc, ModelFileError):
                    self._fail_install(consumer, delivery, record, exc)
                    return
                if not isinstance(exc, McamError):
                    log.exception("job %s failed (delivery %d)", record.id, delivery.deliveries)
                if delivery.deliveries >= self.max_deliveries:
                    self._fail(
                        consumer, delivery, record, error_of(exc), dead_letter=dead_letter_of(exc)
                    )
                    return
                time.sleep(RETRY_BACKOFF_S * 2 ** (delivery.deliveries - 1))
                consumer.retry(delivery)
                record = self.jobs.load(record.id)

    def _fail_install(
        self, consumer: StreamConsumer, delivery: Delivery, record: JobRecord,
        exc: ModelFileError,
    ) -> None:
        """The job's decoder met a model file that is not its card's: the same on every
        try until an operator restores it, so the job fails now (:func:`model_unavailable`)
        and its dead letter names the file and what to do."""
        log.error("job %s: the server's model install is broken: %s", record.id, exc)
        letter = JobError(code="model_unavailable", message=str(exc))
        error = model_unavailable(
            f"decoder {record.decoder!r}", record.params.encoding, "this job's id",
            "choose another decoder, or submit again once it is restored",
        )
        self._fail(consumer, delivery, record, error, dead_letter=letter)

    def _hand_back(self, consumer: StreamConsumer, delivery: Delivery, record: JobRecord) -> None:
        """The worker is stopping: the job goes back to the queue, to be redone from its
        start by the next worker (its progress starts again from 0, and it shows no start
        until then: a queued job with a ``started_ns`` read as running)."""
        self.jobs.transition(
            record.id, JobState.QUEUED, (JobState.RUNNING,),
            started_ns=None, frames_done=0, progress=0.0,
        )  # fmt: skip
        consumer.give_back(delivery)

    def _run(self, consumer: StreamConsumer, delivery: Delivery, record: JobRecord) -> None:
        """One attempt at the job. Its progress starts at 0: another attempt (retried
        here, or reclaimed from a worker that died) redoes the job from its start."""
        started = record.started_ns or time_after(record.created_ns)
        changed, _ = self.jobs.transition(
            record.id,
            JobState.RUNNING,
            (JobState.QUEUED, JobState.RUNNING),
            started_ns=started,
            attempts=record.attempts + 1,
            frames_done=0,
            progress=0.0,
        )
        if not changed:
            self._finish(consumer, delivery, record.id)
            return
        ctx = JobContext(record, self.jobs, self.store, self.stop, self.child, delivery.lost)
        outcome = load_handler(record.kind)(ctx, entry_codes(delivery.fields))
        finished = time_after(started)
        timings = {
            "queue_wait": started - record.created_ns,
            **outcome.timings_ns,
            "total": finished - record.created_ns,
        }
        changed, _ = self.jobs.transition(
            record.id,
            JobState.SUCCEEDED,
            (JobState.RUNNING,),
            expire_s=self.store.retention_s,
            finished_ns=finished,
            timings_ns=timings,
            results=outcome.results,
            info=outcome.info,
            progress=1.0,
            frames_done=record.frames_total,
        )
        if changed:
            self._drop(consumer, delivery, record.id)
            self._observe(timings, record.frames_total)
        else:
            self._finish(consumer, delivery, record.id)

    def _finish(self, consumer: StreamConsumer, delivery: Delivery, job_id: str) -> None:
        """The job is final, settled here or elsewhere (:meth:`_settled`); drop the entry."""
        self._settled(job_id)
        self._drop(consumer, delivery, job_id)

    def _settled(self, job_id: str) -> None:
        """The job ended elsewhere (a cancel, another worker): its record expires with its
        results (set here for jobs the API cancelled, whose transition carried no
        expiry), and a cancelled job's files go now, before its entry: those this worker
        wrote before it saw the cancel, or a worker stopped or stalled mid-job left. They
        used to stay, listed nowhere, until the retention purge."""
        self.jobs.expire(job_id, self.store.retention_s)
        if self.jobs.state(job_id) is JobState.CANCELLED:
            removed = self.store.delete_folder(job_folder(job_id))
            if removed:
                log.info("job %s: cancelled; removed its %d files", job_id, removed)

    def _drop(
        self,
        consumer: StreamConsumer,
        delivery: Delivery,
        job_id: str,
        dead_letter: JobError | None = None,
    ) -> None:
        """Release the finished job's hold on the queue, then delete its entry: done, or
        moved to the dead letters with ``dead_letter``'s code and message."""
        self.holds.release(job_id)
        if dead_letter is None:
            consumer.done(delivery)
        else:
            consumer.dead_letter(delivery, dead_letter.code, dead_letter.message, job=job_id)

    def _fail(
        self, consumer: StreamConsumer, delivery: Delivery, record: JobRecord, error: JobError,
        *, caller_error: bool = False, dead_letter: JobError | None = None,
    ) -> None:
        """The job fails with ``error``. A ``caller_error`` (the input's fault: another try
        gives the same answer) fails at the first delivery and its entry is simply done;
        any other failure, after its retries, goes to the dead letters for an operator,
        as ``dead_letter`` (default ``error``)."""
        changed, _ = self.jobs.transition(
            record.id,
            JobState.FAILED,
            (JobState.QUEUED, JobState.RUNNING),
            expire_s=self.store.retention_s,
            finished_ns=time_after(record.created_ns, record.started_ns),
            error=error,
        )
        if not changed:
            self._settled(record.id)
        letter = None if caller_error else dead_letter or error
        self._drop(consumer, delivery, record.id, dead_letter=letter)

    def _observe(self, timings_ns: dict[str, int], frames: int) -> None:
        """Record a succeeded job's stage times; its decode as ``frames`` frames, each at
        the mean (a video's whole decode was one sample of 'time to decode one frame').
        The job itself was counted by its transition (:class:`worker.job_store.JobStore`)."""
        pipe = self.metrics.client.pipeline(transaction=False)
        for stage in ("queue_wait", "decode", "encode", "total"):
            if stage not in timings_ns:
                continue
            seconds, times = timings_ns[stage] / 1e9, 1
            if stage == "decode":
                seconds, times = seconds / max(frames, 1), max(frames, 1)
            self.metrics.observe(f"{stage}_seconds", seconds, pipe=pipe, times=times)
        pipe.execute()
