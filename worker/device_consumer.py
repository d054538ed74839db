"""Live device streams: one owner per device, results written strictly in sequence order.

Usage (inside the worker, one thread)::

    devices = DeviceConsumer(client, store, owner="w1", lease_ms=5000, max_deliveries=3,
                             decode=make_frame_decoder("independent", "itoh"), stop=stop)
    while not stop.is_set():
        devices.poll()        # True when it processed something
    devices.release_all()

For each device in the ``devices`` set the worker tries to take the lease (a
worker owning more than its share of the active devices hands one over, so devices
spread over the workers: :mod:`worker.device_share`). The owner first takes over every pending
entry of the stream (a previous owner's unfinished frames), then reads new ones,
and handles them one by one in stream order. Per frame: decode, write
``devices/<id>/<seq:012d>-<entry id>.exr`` durably (compressed as ``exr_compression`` says:
:data:`worker.outputs.STREAM_EXR_COMPRESSION` by default), then in one Lua step
(only while the lease is still ours) record the sequence, point ``device:<id>:latest`` at
the result, append a ``frame`` event to ``events:<id>``, extend the lease and XACK (and
delete) the entry: one round trip where there were three (record, ack, renew; each
write waits for Redis's fsync, about 0.3 ms here). Frames also go
to the device's live recording, if one is running (``worker/recorder.py``). A redelivered
entry at or before the recorded one is acked without a second result or event.
With a :class:`worker.decode_pool.DecodePool` as ``decode`` (independent decoding on
several processes), each batch read is handed to the pool first, so its frames decode
in parallel while they are written one by one in stream order as above; a device the
worker stops owning has its pending frames dropped.
A frame whose data cannot be reconstructed (a :class:`models.errors.McamError`: bad
codes or parameters, output beyond float32) goes to the dead letters at once with a
``failed`` event, since a retry would fail the same way and hold the stream up; one
that fails otherwise (a bug, a crashed pool process) after ``max_deliveries`` attempts.
A frame whose decoder's model file is broken (:class:`models.decoders.learned.ModelFileError`)
also fails at once, as ``model_unavailable``, and the frames after it go on.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from typing import Any

import redis

from models.decoders.learned import ModelFileError
from models.errors import (
    InvalidInputError,
    McamError,
    OutputOverflowError,
    OutputUnderflowError,
)
from worker.decode_pool import DecodePool
from worker.deliveries import GROUP, Delivery, StreamConsumer, entry_order, prune_consumers
from worker.device_share import device_to_hand_over, frame_clock
from worker.device_state import DeviceState, FrameDecoder
from worker.frame_message import FrameMessage
from worker.job_processor import RETRY_BACKOFF_S, dead_letter_of, error_of, model_unavailable
from worker.jobs import JobError
from worker.lease import Lease
from worker.metrics import Metrics, counter_key
from worker.outputs import STREAM_EXR_COMPRESSION, encode_exr_result
from worker.recorder import Recorder
from worker.redis_keys import (
    DEVICES_SET,
    events_stream,
    frame_stream,
    last_sequence_key,
    latest_key,
    lease_key,
)
from worker.redis_memory import TroubleLog, is_transient
from worker.result_store import ResultStore

log = logging.getLogger(__name__)

#: Frames read from one device per poll before looking at the other devices.
BATCH = 16
#: After handing a device over, do not take it back for this many lease times.
HAND_OVER_REST = 4
#: The events stream of a device keeps about this many entries.
EVENTS_MAXLEN = 1000

#: KEYS: lease, last sequence, latest, events, frames, and for a frame reconstructed the
#: counter of frames processed (counted in the commit: a worker stopped right after it
#: still has the frame counted). ARGV: owner, sequence, entry id, result key ('' for
#: none), events bound, lease ms, consumer group, device, then event fields.
_COMMIT = """
if redis.call('GET', KEYS[1]) ~= ARGV[1] then return 0 end
redis.call('PEXPIRE', KEYS[1], ARGV[6])
redis.call('HSET', KEYS[2], 'seq', ARGV[2], 'entry', ARGV[3])
if ARGV[4] ~= '' then redis.call('SET', KEYS[3], ARGV[4]) end
local event = {}
for i = 9, #ARGV do event[#event + 1] = ARGV[i] end
redis.call('XADD', KEYS[4], 'MAXLEN', '~', ARGV[5], '*', unpack(event))
redis.call('XACK', KEYS[5], ARGV[7], ARGV[3])
redis.call('XDEL', KEYS[5], ARGV[3])
if KEYS[6] then redis.call('HINCRBY', KEYS[6], ARGV[8], 1) end
return 1
"""


class LeaseLost(Exception):
    """Another worker owns the device now; stop processing its stream."""


def result_key(device: str, sequence: int, entry_id: str) -> str:
    """Result-store key of a device frame's EXR: by sequence number (files list in frame
    order), then stream entry id. A camera that restarts counts from 0 again, and a
    DISCONT frame may repeat a number: the entry id keeps each frame's file its own (a
    redelivered entry finds its file and keeps it)."""
    return f"devices/{device}/{sequence:012d}-{entry_id}.exr"


class DeviceConsumer:
    """Owns device streams through leases and reconstructs their frames in order."""

    def __init__(
        self,
        client: redis.Redis,
        store: ResultStore,
        *,
        owner: str,
        lease_ms: int,
        max_deliveries: int,
        decode: FrameDecoder | DecodePool,
        stop: threading.Event,
        peers: Callable[[], int] = lambda: 1,
        exr_compression: str = STREAM_EXR_COMPRESSION,
    ) -> None:
        self.client = client
        self.exr_options = {"exr_compression": exr_compression}
        self.store = store
        self.owner = owner
        self.max_deliveries = max_deliveries
        self.decode = decode
        self.stop = stop
        self.lease = Lease(client, owner, lease_ms)
        self.metrics = Metrics(client)
        self.states: dict[str, DeviceState] = {}
        self.recorder = Recorder(client, store, max_deliveries=max_deliveries)
        self._consumers: dict[str, StreamConsumer] = {}
        self._commit = client.register_script(_COMMIT)
        self.peers = peers
        self._share_checked = -math.inf
        self._resting: dict[str, float] = {}
        self._trouble = TroubleLog(log)
        self._broken_models = TroubleLog(log)

    def poll(self) -> bool:
        """Refresh leases, then handle up to :data:`BATCH` frames per owned device; then
        hand one device over if this worker owns more than its fair share."""
        busy = False
        devices = sorted(d.decode() for d in self.client.smembers(DEVICES_SET))
        now = time.monotonic()
        for device in devices:
            if self.stop.is_set():
                break
            if device not in self.states and self._resting.get(device, 0.0) > now:
                continue
            if not self._hold(device):
                continue
            try:
                busy |= self._drain(device)
                self.recorder.finish_if_due(device)
            except LeaseLost:
                self._forget(device)
        # A device removed from the registry (DELETE /v1/devices/{id}) is let go here.
        for gone in set(self.states) - set(devices):
            self._forget(gone)
        self._resting = {d: until for d, until in self._resting.items() if until > now}
        surplus = self._surplus(devices)
        if surplus is not None:
            self._hand_over(surplus)
        return busy

    def _surplus(self, devices: list[str]) -> str | None:
        """An owned device beyond this worker's fair share of the active devices
        (:mod:`worker.device_share`), looked at once a second."""
        if not self.states or time.monotonic() - self._share_checked < 1.0:
            return None
        self._share_checked = time.monotonic()
        newest, now_ms = frame_clock(self.client, devices)
        return device_to_hand_over(self.states, newest, now_ms, self.peers())

    def _hand_over(self, device: str) -> None:
        """Release a device for another worker, and leave it alone for a few leases."""
        self.lease.release(device)
        self._forget(device)
        self._resting[device] = time.monotonic() + HAND_OVER_REST * self.lease.ttl_ms / 1000
        log.info("worker %s hands device %s over (more than its share)", self.owner, device)

    def renew_all(self) -> None:
        """Extend the leases of every owned device (the heartbeat calls this, so a frame
        that decodes for longer than the lease does not lose it)."""
        for device in list(self.states):
            self.lease.renew(device)

    def release_all(self) -> None:
        """Give up every lease (graceful shutdown); unacked frames stay pending."""
        for device in list(self.states):
            self.lease.release(device)
            self._forget(device)

    def _hold(self, device: str) -> bool:
        if device in self.states:
            if self.lease.renew(device):
                return True
            self._forget(device)
        if not self.lease.acquire(device):
            return False
        self._take_over(device)
        return True

    def _take_over(self, device: str) -> None:
        consumer = StreamConsumer(
            self.client, frame_stream(device), self.owner, max_deliveries=self.max_deliveries,
            on_trimmed=lambda entry_id: self.recorder.count_lost(device, entry_id),
        )
        consumer.claim_idle(0, count=None)
        # The stream's earlier owners: their entries are ours now, their names go.
        prune_consumers(self.client, frame_stream(device), lambda name: name == self.owner)
        raw = self.client.hgetall(last_sequence_key(device))
        self.states[device] = DeviceState(
            device,
            last_sequence=int(raw[b"seq"]) if b"seq" in raw else None,
            last_entry=raw[b"entry"].decode() if b"entry" in raw else None,
        )
        self._consumers[device] = consumer
        log.info("worker %s owns device %s", self.owner, device)

    def _forget(self, device: str) -> None:
        self.states.pop(device, None)
        self._consumers.pop(device, None)
        self._trouble.forget(_trouble_place(device))
        self._broken_models.forget(device)
        if isinstance(self.decode, DecodePool):
            self.decode.forget(device)

    def _drain(self, device: str) -> bool:
        consumer = self._consumers[device]
        # Before new entries, any pending at another consumer (a worker that stopped
        # while it held frames, or one from before new entries were read under the lease).
        deliveries = consumer.read_own_pending(BATCH) or consumer.claim_others(BATCH)
        if not deliveries:
            # Only while the lease is ours: a worker that paused past its lease would
            # otherwise read entries after another took the device over, fail to commit
            # them, and leave them pending behind frames the new owner has done.
            new = consumer.read_new_while(lease_key(device), self.owner, BATCH)
            if new is None:
                raise LeaseLost(device)
            deliveries = new
        if isinstance(self.decode, DecodePool):
            self.decode.prefetch(device, self._fresh(self.states[device], deliveries))
        for delivery in deliveries:
            if self.stop.is_set():
                break
            self._handle(device, consumer, delivery)
        return bool(deliveries)

    @staticmethod
    def _fresh(state: DeviceState, deliveries: list[Delivery]) -> list[tuple[str, FrameMessage]]:
        """The (entry id, message) pairs of ``deliveries`` that will be decoded: after the
        newest done entry, well formed (a malformed one fails in :meth:`_reconstruct`)."""
        fresh = []
        for delivery in deliveries:
            if _done(state, delivery):
                continue
            try:
                fresh.append((delivery.entry_id, FrameMessage.from_fields(delivery.fields)))
            except McamError:
                continue
        return fresh

    def _handle(self, device: str, consumer: StreamConsumer, delivery: Delivery) -> None:
        state = self.states[device]
        if _done(state, delivery):
            consumer.done(delivery)
            return
        while True:
            try:
                self._reconstruct(device, state, delivery)
                return
            except Exception as exc:
                if isinstance(exc, LeaseLost) or is_transient(exc):
                    raise  # the frame stays pending: this owner retries it, in order
                if isinstance(exc, ModelFileError):
                    self._give_up_on_install(device, state, consumer, delivery, exc)
                    return
                if not isinstance(exc, McamError):
                    log.exception("frame %s of %s failed", delivery.entry_id, device)
                if isinstance(exc, McamError) or delivery.deliveries >= self.max_deliveries:
                    error = error_of(exc, logged_with="the device's name")
                    self._give_up(device, state, consumer, delivery, error, dead_letter_of(exc))
                    return
                time.sleep(RETRY_BACKOFF_S * 2 ** (delivery.deliveries - 1))
                consumer.retry(delivery)

    def _reconstruct(self, device: str, state: DeviceState, delivery: Delivery) -> None:
        message = FrameMessage.from_fields(delivery.fields)
        if message.device != device:
            # The stream names the device; a frame naming another would join its recording.
            raise InvalidInputError(
                f"the frame names device {message.device!r} but arrived on {device!r}'s stream"
            )
        if (
            state.last_sequence is not None
            and message.sequence <= state.last_sequence
            and not message.discont
        ):
            stale = _event("stale", message)
            self._record(device, state, delivery, state.last_sequence, "", stale)
            return
        if isinstance(self.decode, DecodePool):
            frame = self.decode.result(device, delivery.entry_id, message)
        else:
            frame = self.decode(state, message)
        start = time.perf_counter_ns()
        try:
            data = encode_exr_result(
                message.codes, frame.winding, message.params, frame.info, self.exr_options,
                f"frame {message.sequence} of device {device}",
            )
        except (OutputOverflowError, OutputUnderflowError) as exc:
            if message.params.gain is None:
                raise
            raise camera_gain_error(exc, device, message.params.gain) from None
        key = result_key(device, message.sequence, delivery.entry_id)
        # A frame's file is never replaced: an owner that lost its lease mid-frame would
        # overwrite the file its successor committed (a redelivery finds it complete).
        self.store.write(key, data, replace=False)
        self.recorder.add_frame(message, delivery.entry_id)
        encode_ns = time.perf_counter_ns() - start
        event = _event("frame", message, key=key, decode_ns=frame.timings_ns.get("decode", 0))
        self._record(device, state, delivery, message.sequence, key, event, counted=True)
        state.frames += 1
        pipe = self.client.pipeline(transaction=False)
        self.metrics.observe("decode_seconds", frame.timings_ns.get("decode", 0) / 1e9, pipe=pipe)
        self.metrics.observe("encode_seconds", encode_ns / 1e9, pipe=pipe)
        waited_ms = delivery.read_ms - entry_order(delivery.entry_id)[0]
        self.metrics.observe("queue_wait_seconds", max(waited_ms, 0) / 1e3, pipe=pipe)
        try:
            pipe.execute()
        except redis.exceptions.RedisError as exc:
            if not is_transient(exc):
                raise
            # The frame is committed: a retry would only redo it as stale.
            self._trouble.warn(_trouble_place(device), exc, then="frame timings not recorded")

    def _record(
        self,
        device: str,
        state: DeviceState,
        delivery: Delivery,
        sequence: int,
        key: str,
        event: dict[str, str],
        *,
        counted: bool = False,
    ) -> None:
        """Atomically, while we hold the lease (raises :class:`LeaseLost` otherwise): record
        ``sequence`` as the newest done frame, point ``latest`` at ``key`` (unless empty),
        publish ``event``, extend the lease, acknowledge and delete the entry and, when
        ``counted``, count the frame in ``frames_processed_total``."""
        args: list[Any] = [
            self.owner, sequence, delivery.entry_id, key, EVENTS_MAXLEN, self.lease.ttl_ms, GROUP,
            device,
        ]  # fmt: skip
        for name, value in {**event, "worker": self.owner}.items():
            args += [name, value]
        keys = [
            lease_key(device),
            last_sequence_key(device),
            latest_key(device),
            events_stream(device),
            frame_stream(device),
            *([counter_key("frames_processed_total")] if counted else []),
        ]
        if not self._commit(keys=keys, args=args):
            raise LeaseLost(device)
        state.last_sequence = sequence
        state.last_entry = delivery.entry_id

    def _give_up_on_install(
        self,
        device: str,
        state: DeviceState,
        consumer: StreamConsumer,
        delivery: Delivery,
        exc: ModelFileError,
    ) -> None:
        """The frame's decoder met a model file that is not its card's: every try would
        fail the same way until an operator restores it, and retrying held the stream up,
        so the frame fails now as ``model_unavailable`` (its ``failed`` event says so;
        its dead letter names the file and what to do) and the stream goes on. Logged at
        most once per :class:`TroubleLog` period per device, without a traceback."""
        encoding = FrameMessage.from_fields(delivery.fields).params.encoding
        self._broken_models.report(
            f"device {device}", f"the server's model install is broken: {exc}",
            f"its {encoding} frames fail as model_unavailable",
        )
        error = model_unavailable(
            "this worker's stream decoder", encoding, "the device's name",
            f"the device's {encoding} frames fail until then",
        )
        letter = JobError(code="model_unavailable", message=str(exc))
        self._give_up(device, state, consumer, delivery, error, letter)

    def _give_up(
        self,
        device: str,
        state: DeviceState,
        consumer: StreamConsumer,
        delivery: Delivery,
        error: JobError,
        letter: JobError,
    ) -> None:
        """Fail the frame for good: a ``failed`` event with the client's ``error``, and
        a dead letter with the operator's ``letter``."""
        # The entry failed to parse, perhaps here: its seq is shown, never trusted.
        sequence = delivery.fields.get("seq", b"-1").decode(errors="replace")
        self.recorder.count_failed(device, delivery.entry_id, f"{error.code}: {error.message}")
        event = {
            "type": "failed",
            "sequence": sequence,
            "code": error.code,
            "message": error.message,
        }
        self._record(device, state, delivery, _newest_done(state, delivery, sequence), "", event)
        consumer.dead_letter(
            delivery, letter.code, letter.message, device=device, sequence=sequence
        )


def camera_gain_error(
    exc: OutputOverflowError | OutputUnderflowError, device: str, gain: float
) -> McamError:
    """``exc`` (a frame's scene values that its EXR cannot hold) with the remedy a camera's
    user has: the gain is the camera's (``set_exposure``'s gain x integration_ns / 1 ms,
    wrap units per scene unit), changed by a control command, not given with the frame."""
    what, _, _ = exc.message.partition("; ")
    change = "higher" if isinstance(exc, OutputOverflowError) else "lower"
    return type(exc)(
        f"{what}; the scene values are x / gain with the camera's gain {gain:.4g} "
        f"(set_exposure's gain x integration_ns / 1 ms): send a set_exposure command "
        f"with a {change} gain to POST /v1/devices/{device}/control"
    )


def _trouble_place(device: str) -> str:
    """The place a device's transient Redis errors are logged under (:class:`TroubleLog`)."""
    return f"device {device}"


def _newest_done(state: DeviceState, delivery: Delivery, sequence: str) -> int:
    """The device's newest done sequence once failed entry ``delivery`` (its seq field
    ``sequence``) is given up: the entry's own for a DISCONT frame, which starts a new
    run (a camera that restarted counts from 0 again: keeping the old run's number made
    the frames after it stale), else never lower than before."""
    sequence_number = _sequence_number(sequence)
    if delivery.fields.get("discont") == b"1":
        return sequence_number
    last = state.last_sequence if state.last_sequence is not None else -1
    return max(sequence_number, last)


def _sequence_number(text: str) -> int:
    """A failed entry's sequence number as the device's newest done: -1 unless ``text``
    is a plain decimal integer (``"²"`` passes ``str.isdigit`` but not ``int``)."""
    try:
        return int(text) if text.isascii() else -1
    except ValueError:
        return -1


def _done(state: DeviceState, delivery: Delivery) -> bool:
    """Whether ``delivery``'s entry is at or before the newest one done for the device."""
    return state.last_entry is not None and entry_order(delivery.entry_id) <= entry_order(
        state.last_entry
    )


def _event(kind: str, message: FrameMessage, **extra: Any) -> dict[str, str]:
    event = {
        "type": kind,
        "sequence": str(message.sequence),
        "timestamp_ns": str(message.timestamp_ns),
        "written_ns": str(time.time_ns()),
        "discont": "1" if message.discont else "0",
    }
    event.update({name: str(value) for name, value in extra.items()})
    return event
