"""The producer side of the queue: submit jobs, publish device frames, inspect the queue.

Usage (API)::

    queue = JobQueue(connect(url), maxlen=s.jobs_maxlen, max_deliveries=s.max_deliveries,
                     claim_idle_ms=s.claim_idle_ms)
    record = queue.submit("reconstruction", codes, params, "itoh", {"scene_referred": True})
    record = queue.wait(record.id, timeout_s=5.0)   # returns early when finished
    record = queue.get(record.id); queue.cancel(record.id); queue.stats()

Usage (device daemon)::

    dropped = publish_frame(client, frame_message, maxlen=s.frames_maxlen)

Job codes travel as raw bytes in the ``jobs`` stream entry (fields ``job``,
``kind``, ``shape``, ``dtype``, ``codes``), never JSON; the record lives at
``job:<id>``. The jobs stream rejects submissions beyond ``maxlen`` outstanding
entries or ``max_bytes`` of their codes (:class:`QueueFullError`, 503), and from an
API key that has ``max_per_key`` jobs or ``max_bytes_per_key`` bytes of codes in the
queue (:class:`TooManyJobsError`, 429): each job holds its share from its submit until
a worker deletes its entry (:mod:`worker.queue_holds`); a device stream drops its oldest frames
and counts them in ``frames_dropped_total``. Workers delete entries once done,
so stream length is the backlog.
"""

from __future__ import annotations

import json
import threading
import time
import uuid
from collections.abc import Sequence
from typing import Any

import numpy as np
import redis
from numpy.typing import NDArray

from models.decoders.registry import get_decoder, supporting_decoders
from models.errors import InvalidInputError, McamError
from models.formation import SensorParams, validate_codes
from worker.frame_message import FrameMessage
from worker.idempotency import IdempotencyKeyInUseError, IdempotentSubmit
from worker.job_store import JobStore, record_fields
from worker.jobs import JobRecord, JobState, time_after
from worker.metrics import Metrics, counter_key
from worker.redis_keys import (
    DEAD_LETTER_STREAM,
    DEVICES_SET,
    JOB_BYTES_PER_KEY,
    JOB_HOLDS,
    JOB_STATES,
    JOBS_HELD_BYTES,
    JOBS_PER_KEY,
    JOBS_STREAM,
    WORKERS_HEARTBEAT,
    frame_stream,
    job_done_channel,
    job_key,
    last_sequence_key,
    lease_key,
    recording_key,
)
from worker.redis_memory import is_out_of_memory

#: A queue bound that never binds (Lua compares it as a double).
UNBOUNDED = 2**62
#: Consumer group every worker joins on the jobs stream and on each frame stream.
GROUP = "workers"
JOB_KINDS = ("reconstruction", "video")
#: Longest pause (s) of :meth:`JobQueue.wait` between looks at its job and its stop event.
WAIT_POLL_S = 0.5
#: The submit script's refusal codes, as mcam_jobs_rejected_total's ``reason`` label.
REFUSALS: dict[int, str] = {
    0: "queue_full", -2: "queue_bytes", -1: "key_jobs", -3: "key_bytes",
}

# KEYS: the jobs stream, the job's record, states, holds, per-key jobs and bytes, held
# bytes, and (an idempotent submit) the idempotency key. ARGV: maxlen, owner, the key's
# bounds, the codes' bytes, the queue's, the job id, the idempotency key's value while
# held, once done and its ttl (s), the number of the record's fields, then the record's
# and the entry's fields (name, value pairs).
_SUBMIT = """
if KEYS[8] then
  local held = redis.call('GET', KEYS[8])
  if held and held ~= ARGV[8] then return 3 end
end
if redis.call('EXISTS', KEYS[2]) == 1 then return 2 end
if redis.call('XLEN', KEYS[1]) >= tonumber(ARGV[1]) then return 0 end
local owner, bytes = ARGV[2], tonumber(ARGV[5])
if owner ~= '' then
  if tonumber(redis.call('HGET', KEYS[5], owner) or '0') >= tonumber(ARGV[3]) then return -1 end
  if tonumber(redis.call('HGET', KEYS[6], owner) or '0') + bytes > tonumber(ARGV[4]) then
    return -3
  end
end
if tonumber(redis.call('GET', KEYS[7]) or '0') + bytes > tonumber(ARGV[6]) then return -2 end
local n = tonumber(ARGV[11])
for i = 12, 11 + 2 * n, 2 do redis.call('HSET', KEYS[2], ARGV[i], ARGV[i + 1]) end
local entry = {}
for i = 12 + 2 * n, #ARGV do entry[#entry + 1] = ARGV[i] end
redis.call('XADD', KEYS[1], '*', unpack(entry))
redis.call('HINCRBY', KEYS[3], 'queued', 1)
redis.call('HSET', KEYS[4], ARGV[7], owner .. ' ' .. ARGV[5])
if owner ~= '' then
  redis.call('HINCRBY', KEYS[5], owner, 1)
  redis.call('HINCRBY', KEYS[6], owner, bytes)
end
redis.call('INCRBY', KEYS[7], bytes)
if KEYS[8] then redis.call('SET', KEYS[8], ARGV[9], 'EX', ARGV[10]) end
return 1
"""

# KEYS: frame stream, devices set, dropped counter, the device's recording. ARGV: maxlen,
# device, the workers' group, then fields. Over maxlen the oldest frame goes, unless it is
# a DISCONT frame followed by one that is not: then that second frame goes (the run's
# start is kept, the next frame of it is not). A frame that goes before any worker read
# it (after the group's last delivered id), sent within the window of the device's active
# recording (after its start_entry and, once stopping, at or before its stop_entry),
# counts in the recording's frames_lost: one a worker already read is in its hands.
_PUBLISH = """
local function discont(fields)
  for i = 1, #fields, 2 do
    if fields[i] == 'discont' then return fields[i + 1] == '1' end
  end
  return false
end
local function later(a, b)
  local a_ms, a_seq = string.match(a, '^(%d+)-(%d+)$')
  local b_ms, b_seq = string.match(b, '^(%d+)-(%d+)$')
  a_ms, b_ms = tonumber(a_ms), tonumber(b_ms)
  return a_ms > b_ms or (a_ms == b_ms and tonumber(a_seq) > tonumber(b_seq))
end
local function last_delivered(stream)
  for _, group in ipairs(redis.call('XINFO', 'GROUPS', stream)) do
    local info = {}
    for i = 1, #group, 2 do info[group[i]] = group[i + 1] end
    if info['name'] == ARGV[3] then return info['last-delivered-id'] end
  end
  return '0-0'
end
local function recording_window()
  local r = redis.call('HMGET', KEYS[4], 'state', 'start_entry', 'stop_entry')
  if r[1] ~= 'recording' and r[1] ~= 'stopping' then return nil end
  return {start = r[2] or '0-0', stop = r[1] == 'stopping' and r[3] or nil,
          read = last_delivered(KEYS[1])}
end
local function lost_to(window, victim)
  return window ~= nil and later(victim, window.start) and later(victim, window.read)
    and (window.stop == nil or not later(victim, window.stop))
end
local maxlen = tonumber(ARGV[1])
local entry = {}
for i = 4, #ARGV do entry[#entry + 1] = ARGV[i] end
redis.call('XADD', KEYS[1], '*', unpack(entry))
redis.call('SADD', KEYS[2], ARGV[2])
local dropped, lost, window = 0, 0, nil
while redis.call('XLEN', KEYS[1]) > maxlen do
  local oldest = redis.call('XRANGE', KEYS[1], '-', '+', 'COUNT', 2)
  local victim = oldest[1][1]
  if maxlen > 1 and discont(oldest[1][2]) and not discont(oldest[2][2]) then
    victim = oldest[2][1]
  end
  redis.call('XDEL', KEYS[1], victim)
  if dropped == 0 then window = recording_window() end
  if lost_to(window, victim) then lost = lost + 1 end
  dropped = dropped + 1
end
if dropped > 0 then redis.call('HINCRBY', KEYS[3], ARGV[2], dropped) end
if lost > 0 then redis.call('HINCRBY', KEYS[4], 'frames_lost', lost) end
return dropped
"""


class QueueFullError(McamError):
    """The jobs stream holds ``maxlen`` unfinished jobs, or their codes ``max_bytes``; the
    client should retry later."""

    code = "queue_full"
    http_status = 503
    retry_after_s = 5


class TooManyJobsError(McamError):
    """The submitting API key already has ``max_per_key`` jobs, or ``max_bytes_per_key``
    bytes of codes, in the queue."""

    code = "too_many_jobs"
    http_status = 429
    retry_after_s = 5


def ensure_group(client: redis.Redis, stream: str) -> None:
    """Create the workers' consumer group on ``stream`` (and the stream) if missing. A full
    Redis refuses the create even when the group exists (no ``BUSYGROUP``), so that
    refusal counts only when the group is missing."""
    try:
        client.xgroup_create(stream, GROUP, id="0", mkstream=True)
    except redis.exceptions.ResponseError as exc:
        if "BUSYGROUP" in str(exc) or (is_out_of_memory(exc) and _has_group(client, stream)):
            return
        raise


def is_missing_group(exc: BaseException) -> bool:
    """Whether ``exc`` is Redis saying a stream or its workers' group does not exist
    (``NOGROUP``, also inside a script): a Redis restarted without its data (a lost
    data dir, an external server that keeps none) lost both, and the API's next submit
    makes the stream again, without the group."""
    return isinstance(exc, redis.exceptions.ResponseError) and "NOGROUP" in str(exc)


def _has_group(client: redis.Redis, stream: str) -> bool:
    """Whether ``stream`` exists with the workers' consumer group."""
    try:
        groups = client.xinfo_groups(stream)
    except redis.exceptions.ResponseError:  # no such stream
        return False
    return any(group["name"] in (GROUP, GROUP.encode()) for group in groups)


def server_time_ns(client: redis.Redis) -> int:
    """Redis's clock in ns since the epoch: the one clock the API and workers on other
    hosts share, for heartbeats stamped by one process and aged by another."""
    seconds, microseconds = client.time()
    return int(seconds) * 1_000_000_000 + int(microseconds) * 1_000


def publish_frame(client: redis.Redis, message: FrameMessage, *, maxlen: int) -> int:
    """Append a frame to ``frames:<device>`` (registering the device); when the stream
    holds ``maxlen`` frames the oldest are dropped, but a DISCONT frame at the front is
    kept (the frame after it goes instead): the worker sees each frame against its run's
    first, and without it took the frames of a camera that restarted its counter for
    stale ones of the old run. A dropped frame no worker had read, sent within the
    window of the device's active recording, counts in its ``frames_lost``
    (:mod:`worker.recordings`). Returns how many were dropped."""
    args: list[Any] = [maxlen, message.device, GROUP]
    for name, value in message.to_fields().items():
        args += [name, value]
    script = client.register_script(_PUBLISH)
    keys = [
        frame_stream(message.device), DEVICES_SET, counter_key("frames_dropped_total"),
        recording_key(message.device),
    ]
    return int(script(keys=keys, args=args))


def _check_submission(
    kind: str, codes: NDArray[Any], params: SensorParams, decoder: str
) -> NDArray[np.unsignedinteger]:
    if kind not in JOB_KINDS:
        raise InvalidInputError(f"unknown job kind {kind!r}; use one of {', '.join(JOB_KINDS)}")
    codes = validate_codes(codes, params.bits)
    if codes.dtype not in (np.uint8, np.uint16):
        codes = codes.astype(params.code_dtype)
    codes = np.ascontiguousarray(codes)
    want_ndim = (2, 3) if kind == "reconstruction" else (3, 4)
    if codes.ndim not in want_ndim:
        layout = "H x W or H x W x C" if kind == "reconstruction" else "T x H x W or T x H x W x C"
        raise InvalidInputError(f"a {kind} job takes {layout} codes, got shape {codes.shape}")
    check_decoder_supports(decoder, params)
    return codes


def check_decoder_supports(decoder: str, params: SensorParams) -> None:
    """Refuse ``decoder`` (an unknown name too) for frames with ``params`` it has no
    model for (a learned decoder decodes only the encodings it was trained on), naming
    the decoders that have one: a property of a whole job or video, checked before any
    frame is decoded."""
    if not get_decoder(decoder).supports(params):  # models load lazily
        raise InvalidInputError(
            f"decoder {decoder!r} has no model for {params.encoding} frames (GET /v1/decoders "
            "and mcam reconstruct --list-decoders say what each decodes); choose one that "
            f"does: {', '.join(supporting_decoders(params))}"
        )


def job_entry(record: JobRecord, codes: NDArray[np.unsignedinteger]) -> dict[str, bytes | str]:
    """The jobs-stream entry of a job: its id, kind, and the codes as raw bytes."""
    return {
        "job": record.id,
        "kind": record.kind,
        "shape": ",".join(str(n) for n in codes.shape),
        "dtype": codes.dtype.str,
        "codes": codes.tobytes(),
    }


def entry_codes(fields: dict[str, bytes]) -> NDArray[np.unsignedinteger]:
    """The codes of a jobs-stream entry (InvalidInputError if the entry is malformed)."""
    try:
        shape = tuple(int(n) for n in fields["shape"].decode().split(","))
        dtype = np.dtype(fields["dtype"].decode())
        if dtype.kind != "u" or dtype.itemsize not in (1, 2):
            raise ValueError(f"dtype {dtype} is not uint8/uint16")
        return np.frombuffer(fields["codes"], dtype=dtype).reshape(shape)
    except (KeyError, ValueError, TypeError) as exc:
        raise InvalidInputError(f"malformed job entry: {exc}") from None


class JobQueue:
    """Submit, inspect, wait for and cancel jobs; read queue statistics."""

    def __init__(
        self,
        client: redis.Redis,
        *,
        maxlen: int,
        max_deliveries: int,
        claim_idle_ms: int,
        max_per_key: int = UNBOUNDED,
        max_bytes_per_key: int = UNBOUNDED,
        max_bytes: int = UNBOUNDED,
    ) -> None:
        self.client = client
        self.maxlen = maxlen
        self.max_per_key = max_per_key
        self.max_bytes_per_key = max_bytes_per_key
        self.max_bytes = max_bytes
        self.max_deliveries = max_deliveries
        self.claim_idle_ms = claim_idle_ms
        self.jobs = JobStore(client)
        self.metrics = Metrics(client)
        self._submit = client.register_script(_SUBMIT)
        ensure_group(client, JOBS_STREAM)

    def submit(
        self,
        kind: str,
        codes: NDArray[Any],
        params: SensorParams,
        decoder: str,
        options: dict[str, Any] | None = None,
        owner: str = "",
        job_id: str | None = None,
        warnings: Sequence[str] = (),
        idempotency: IdempotentSubmit | None = None,
    ) -> JobRecord:
        """Queue a job (codes in DN: one frame, or T frames for ``video``) for the API key
        ``owner`` (its id; ``""``: no key, as for a device's recording); returns its record.
        ``job_id`` (default: a new uuid) makes a retried submit safe: a job of that id that
        already exists is returned, not queued again. ``warnings`` (what reading the
        uploaded file noticed) are kept with the job for its client. ``idempotency``
        (with no ``job_id``: the job's id is its) records the job under the request's
        idempotency key in the same step, if the request still holds the key
        (:mod:`worker.idempotency`).

        Raises :class:`InvalidInputError` for bad codes/kind/decoder or codes larger than
        a bound, :class:`TooManyJobsError` when ``owner`` has ``max_per_key`` jobs or
        would pass ``max_bytes_per_key`` bytes in the queue, and :class:`QueueFullError`
        when ``maxlen`` jobs are outstanding or the queue would pass ``max_bytes``, and
        :class:`IdempotencyKeyInUseError` when another request holds the idempotency key."""
        codes = _check_submission(kind, codes, params, decoder)
        self._check_size(codes.nbytes, owner)
        record = JobRecord(
            id=job_id or (idempotency.job_id if idempotency else "") or uuid.uuid4().hex,
            kind=kind,  # type: ignore[arg-type]
            decoder=decoder,
            params=params,
            options=dict(options or {}),
            frames_total=codes.shape[0] if kind == "video" else 1,
            created_ns=time.time_ns(),
            warnings=list(warnings),
        )
        fields = record_fields(record)
        entry = job_entry(record, codes)
        once = idempotency or IdempotentSubmit("", "", "", "", 0)
        args: list[Any] = [
            self.maxlen, owner, self.max_per_key, self.max_bytes_per_key, codes.nbytes,
            self.max_bytes, record.id, once.held, once.done, once.ttl_s, len(fields),
        ]  # fmt: skip
        for pairs in (fields, entry):
            for name, value in pairs.items():
                args += [name, value]
        keys = [JOBS_STREAM, job_key(record.id), JOB_STATES, JOB_HOLDS, JOBS_PER_KEY,
                JOB_BYTES_PER_KEY, JOBS_HELD_BYTES, *([once.store_key] if idempotency else [])]
        accepted = int(self._submit(keys=keys, args=args))
        if accepted == 2:
            return self.get(record.id)
        if accepted == 3:
            raise IdempotencyKeyInUseError(
                "another request with this Idempotency-Key took it while this one was "
                "decoded; ask GET /v1/jobs?idempotency_key=... for its job"
            )
        if accepted != 1:
            self.metrics.inc("jobs_rejected_total", reason=REFUSALS[accepted])
            raise self._refusal(accepted, codes.nbytes)
        return record

    def _check_size(self, nbytes: int, owner: str) -> None:
        """Refuse codes of ``nbytes`` that no queue, however empty, would take."""
        bounds = [(self.max_bytes, "the queue holds for all jobs", "MCAM_JOBS_MAX_BYTES")]
        if owner:
            bounds.append(
                (self.max_bytes_per_key, "one key's jobs may hold", "MCAM_MAX_QUEUED_BYTES_PER_KEY")
            )
        for bound, what, setting in bounds:
            if nbytes > bound:
                raise InvalidInputError(
                    f"this job's codes take {nbytes} bytes, more than {what} ({bound}, "
                    f"{setting}): send fewer frames or pixels"
                )

    def _refusal(self, reason: int, nbytes: int) -> McamError:
        """The error for a submit the script refused (``reason``: 0 queue length, -1 the
        key's jobs, -3 the key's bytes, -2 the queue's bytes)."""
        if reason in (-1, -3):
            held = (
                f"{self.max_per_key} jobs in the queue, the most one key may have "
                "(MCAM_MAX_QUEUED_JOBS_PER_KEY)"
                if reason == -1
                else f"as many bytes of codes in the queue as one key may "
                f"({self.max_bytes_per_key}, MCAM_MAX_QUEUED_BYTES_PER_KEY; this job: {nbytes})"
            )
            return TooManyJobsError(
                f"this API key has {held}: wait for a job to finish (a cancelled job counts "
                "until a worker drops it), then submit again"
            )
        if reason == -2:
            return QueueFullError(
                f"the job queue holds as many bytes of codes as it may ({self.max_bytes}, "
                f"MCAM_JOBS_MAX_BYTES; this job: {nbytes}); retry in a few seconds"
            )
        return QueueFullError(
            f"the job queue is full ({self.maxlen} jobs waiting); retry in a few seconds"
        )

    def get(self, job_id: str) -> JobRecord:
        """The job's record; :class:`JobNotFoundError` if there is none."""
        return self.jobs.load(job_id)

    def cancel(self, job_id: str) -> JobRecord:
        """Cancel a queued or running job (a worker stops at its next check); a finished
        job is returned unchanged. Its files, any written, are removed by the worker that
        drops it (:mod:`worker.job_processor`), not here: a worker may still be writing."""
        record = self.jobs.load(job_id)
        self.jobs.transition(
            job_id,
            JobState.CANCELLED,
            (JobState.QUEUED, JobState.RUNNING),
            finished_ns=time_after(record.created_ns, record.started_ns),
        )
        return self.jobs.load(job_id)

    def wait(
        self, job_id: str, timeout_s: float, stop: threading.Event | None = None
    ) -> JobRecord:
        """Block until the job finishes, ``timeout_s`` passes or ``stop`` is set (checked
        every :data:`WAIT_POLL_S`); returns the latest record."""
        record = self.jobs.load(job_id)
        if record.state.finished or timeout_s <= 0:
            return record
        deadline = time.monotonic() + timeout_s
        pubsub = self.client.pubsub(ignore_subscribe_messages=True)
        try:
            pubsub.subscribe(job_done_channel(job_id))
            while True:
                record = self.jobs.load(job_id)
                remaining = deadline - time.monotonic()
                if record.state.finished or remaining <= 0 or (stop and stop.is_set()):
                    return record
                pubsub.get_message(timeout=min(remaining, WAIT_POLL_S))
        finally:
            pubsub.close()

    def workers(self, max_age_s: float) -> dict[str, dict[str, Any]]:
        """Workers whose last heartbeat is younger than ``max_age_s`` (id -> heartbeat),
        aged by Redis's clock, which stamped them (:func:`server_time_ns`)."""
        now = server_time_ns(self.client)
        alive: dict[str, dict[str, Any]] = {}
        for worker_id, raw in self.client.hgetall(WORKERS_HEARTBEAT).items():
            beat = json.loads(raw)
            if now - int(beat.get("ts_ns", 0)) <= max_age_s * 1e9:
                alive[worker_id.decode()] = beat
        return alive

    def stats(self) -> dict[str, Any]:
        """Queue depth, pending entries, bytes of codes the queued entries hold, jobs by
        state, dead letters, per-device streams."""
        devices = sorted(d.decode() for d in self.client.smembers(DEVICES_SET))
        pipe = self.client.pipeline(transaction=False)
        pipe.xlen(JOBS_STREAM)
        pipe.xpending(JOBS_STREAM, GROUP)
        pipe.xlen(DEAD_LETTER_STREAM)
        pipe.hgetall(counter_key("frames_dropped_total"))
        pipe.get(JOBS_HELD_BYTES)
        for device in devices:
            pipe.xlen(frame_stream(device))
            pipe.get(lease_key(device))
            pipe.hget(last_sequence_key(device), "seq")
        replies = pipe.execute()
        depth, pending, dead, dropped, held = replies[:5]
        dropped_by_device = {k.decode(): int(v) for k, v in dropped.items()}
        per_device = {}
        for i, device in enumerate(devices):
            length, owner, last_seq = replies[5 + 3 * i : 8 + 3 * i]
            per_device[device] = {
                "depth": int(length),
                "owner": owner.decode() if owner else None,
                "last_sequence": int(last_seq) if last_seq is not None else None,
                "frames_dropped": dropped_by_device.get(device, 0),
            }
        return {
            "stream_depth": int(depth),
            "pending": int(pending["pending"]),
            "held_bytes": int(held or 0),
            "jobs_by_state": self.jobs.states(),
            "dead_letters": int(dead),
            "frames_dropped": dropped_by_device,
            "devices": per_device,
        }
