"""The daemon's Redis side: a bounded frame queue drained into ``frames:<device>``.

The link reader calls :meth:`FramePublisher.offer`, which never blocks: a full
queue drops the frame (``queue_full``). A thread publishes each frame with
:func:`worker.queue.publish_frame` (which registers the device; when the stream is
full the oldest unread frames are evicted, a DISCONT one at the front excepted, counted
as ``stream_full``), writes the health hash, and reads ``control:<device>`` for
commands to forward to the camera.
While Redis is unreachable, queued frames are dropped (``redis_unavailable``;
``redis_full`` while it is at its ``maxmemory`` and refuses writes) and the
connection is retried with backoff; the link keeps being read. After
any drop the frame that follows the dropped one carries ``discont`` (temporal state
broke): the next frame queued after a full queue's drop (frames queued before it
still follow their predecessors), the next frame published after a failed publish.
Growing drop and reconnect counters are also appended to ``events:<device>`` as
``drop`` / ``reconnect`` events for the API's server-sent events. Before its first health
write or frame the publisher takes the device over: holding the device's claim, it goes on
from the counters the previous daemon left in the health hash (not reported again as
events). It publishes, writes health and reads commands only while it holds the claim:
one that finds another daemon's (both started while Redis was down) keeps its frames
queued, waits out the claim's TTL and then stops (:attr:`FramePublisher.failure`).
"""

from __future__ import annotations

import dataclasses
import logging
import queue
import threading
import time
from collections.abc import Callable

import redis

from device.commands import Command, fields_to_command
from device.daemon_claim import CLAIM_TTL_MS, DaemonClaim, DeviceTakenError
from device.health import ALL_DROP_CAUSES, DeviceHealth
from models.errors import InvalidInputError
from worker.frame_message import FrameMessage
from worker.queue import publish_frame
from worker.redis_keys import (
    DEVICES_SET,
    control_cursor_key,
    control_stream,
    events_stream,
    frame_stream,
    health_key,
)
from worker.redis_memory import TroubleLog, is_out_of_memory

log = logging.getLogger(__name__)

#: Seconds between health hash writes and control stream polls.
HEALTH_INTERVAL_S = 0.25
#: Longest wait between Redis reconnection attempts (s).
MAX_REDIS_BACKOFF_S = 2.0
#: The events stream keeps about this many entries (the worker appends frame events too).
EVENTS_MAXLEN = 1000


class FramePublisher:
    """Publishes frames and health of one device; hands control commands to ``on_command``.

    ``on_command(entry_id, command)`` takes each control entry in order (``command`` None
    when the entry was refused) and returns False when it has no room for it now (the
    entry is handed over again later). The device's control cursor, where its next
    daemon goes on, moves only as far as :meth:`delivered` says the camera got them: a
    daemon that stops with commands not yet sent leaves them to the next one.
    ``on_failure`` is told when the publisher stops because another daemon holds the
    device's claim (:meth:`_hold_claim`), or on an unexpected error (a bug: :meth:`run`)."""

    def __init__(self, client: redis.Redis, device: str, health: DeviceHealth,
                 on_command: Callable[[str, Command | None], bool], frames_maxlen: int = 256,
                 queue_size: int = 64, claim: DaemonClaim | None = None,
                 on_failure: Callable[[Exception], None] | None = None) -> None:
        self.client = client
        self.device = device
        self.health = health
        self.on_command = on_command
        self.frames_maxlen = frames_maxlen
        self._queue: queue.Queue[FrameMessage] = queue.Queue(maxsize=queue_size)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        # A drop at the queue (reader thread) and a failed publish (publishing thread)
        # each mark the frame after it; each flag is written by one thread only.
        self._dropped_at_queue = False
        self._failed_publish = False
        self._redis_ok = True
        # The drop cause of a frame while Redis is down: why it last failed.
        self._down_cause = "redis_unavailable"
        self._retry_at = 0.0
        self._backoff = 0.05
        self._control_id: str | None = None  # read from Redis when it is first reachable
        # The last entry the camera got (set by the link's thread), and the last written.
        self._delivered: str | None = None
        self._cursor_written: str | None = None
        self._next_health = 0.0
        self._taken_over = False
        self._reported = {"dropped": 0, "reconnects": 0}
        self._reported_causes: dict[str, int] = {}
        self._trouble = TroubleLog(log)
        self.claim = claim
        self.on_failure = on_failure
        #: Why the publisher stopped on its own (another daemon keeps the device), or None.
        self.failure: DeviceTakenError | None = None
        #: Whether this publisher has written the device's health at least once.
        self.health_written = False
        # Since when (monotonic s) another daemon holds the claim; None while this one does.
        self._refused_since: float | None = None
        # The frame taken from the queue when the claim was found refused: published first.
        self._held: FrameMessage | None = None

    def offer(self, message: FrameMessage) -> None:
        """Queue a frame for publishing; drop it (counted) if the queue is full. The frame
        queued after a drop carries ``discont``. Called from one thread (the link reader)."""
        if self._dropped_at_queue and not message.discont:
            message = dataclasses.replace(message, discont=True)
        try:
            self._queue.put_nowait(message)
        except queue.Full:
            self.health.add("dropped_queue_full")
            self._dropped_at_queue = True
            return
        self._dropped_at_queue = False

    def start(self) -> FramePublisher:
        """Run the publishing loop in a daemon thread."""
        self._thread = threading.Thread(target=self.run, name=f"publish-{self.device}",
                                        daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout_s: float = 5.0) -> None:
        """Publish what is queued (while Redis answers), then stop."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=timeout_s)

    def run(self) -> None:
        """Loop until stopped with every frame published (or kept back: another daemon
        holds the device), or until the publisher fails (:attr:`failure`). An error the
        loop does not expect (a bug) ends it, logged once with its traceback and told to
        ``on_failure``: it went to threading's excepthook, and the daemon read on, its
        frames dropped as queue_full and its health no longer written."""
        try:
            self._publish_until_stopped()
        except Exception as exc:
            log.exception("device %s: publishing stopped on an unexpected error; its frames "
                          "are no longer published", self.device)
            if self.on_failure is not None:
                self.on_failure(exc)

    def _publish_until_stopped(self) -> None:
        """:meth:`run` without its handling of unexpected errors."""
        while self.failure is None and not (self._stop.is_set() and self._idle()):
            message = self._next_message()
            if message is not None:
                self._publish(message)
            if time.monotonic() >= self._next_health:
                self._housekeeping()
        if self.failure is None:
            self._housekeeping()

    def _idle(self) -> bool:
        """Nothing left that this daemon may publish."""
        return self._refused_since is not None or (self._queue.empty() and self._held is None)

    def _next_message(self) -> FrameMessage | None:
        """The frame to publish next: none while another daemon holds the claim (frames
        stay queued), then the one held back, then the queue's next (waiting 0.05 s)."""
        if self._refused_since is not None:
            time.sleep(0.05)
            return None
        if self._held is not None:
            message, self._held = self._held, None
            return message
        try:
            return self._queue.get(timeout=0.05)
        except queue.Empty:
            return None

    def _redis(self, action: Callable[[], object]) -> bool:
        """Run a Redis action unless Redis is known down; mark it down on any Redis error
        (unreachable, loading, out of memory, read-only replica...), noting the drop
        cause of the frames meanwhile: ``redis_full`` when it refused a write at its
        ``maxmemory``, else ``redis_unavailable``."""
        if not self._redis_ok and time.monotonic() < self._retry_at:
            return False
        try:
            action()
        except (redis.RedisError, OSError) as exc:
            full = is_out_of_memory(exc)
            self._down_cause = "redis_full" if full else "redis_unavailable"
            self._trouble.warn(
                f"device {self.device}", exc,
                then=f"frames are dropped (dropped_{self._down_cause}) until it "
                     f"{'has room' if full else 'answers'}",
            )  # fmt: skip
            self._redis_ok = False
            self._retry_at = time.monotonic() + self._backoff
            self._backoff = min(self._backoff * 2, MAX_REDIS_BACKOFF_S)
            return False
        self._redis_ok = True
        self._backoff = 0.05
        return True

    def _publish(self, message: FrameMessage) -> None:
        if self._failed_publish and not message.discont:
            message = dataclasses.replace(message, discont=True)

        def xadd() -> None:
            if not self._taken_over:  # before this daemon's first frame is on the stream
                self._take_over()
            if self._refused_since is not None:  # another daemon holds the device
                return
            evicted = publish_frame(self.client, message, maxlen=self.frames_maxlen)
            if evicted:
                self.health.add("dropped_stream_full", evicted)

        reached = self._redis(xadd)
        if reached and self._refused_since is not None:
            self._held = message  # published once this daemon holds the claim
        elif reached:
            self._failed_publish = False
            self.health.add("frames_ok")
        else:
            self.health.add(f"dropped_{self._down_cause}")
            self._failed_publish = True

    def _new_events(self) -> list[dict[str, str]]:
        """``drop`` / ``reconnect`` events for counters that grew since the last report."""
        now = {"dropped": self.health.dropped(), "reconnects": self.health.counts["reconnects"]}
        events = []
        causes = self.health.drop_counts()
        if now["dropped"] > self._reported["dropped"]:
            new = {cause: count - self._reported_causes.get(cause, 0)
                   for cause, count in causes.items()}
            events.append({"type": "drop", "dropped": str(now["dropped"]),
                           "new": str(now["dropped"] - self._reported["dropped"]),
                           "causes": ",".join(f"{c}:{n}" for c, n in new.items() if n > 0)})
        self._reported_causes = causes
        if now["reconnects"] > self._reported["reconnects"]:
            events.append({"type": "reconnect", "reconnects": str(now["reconnects"])})
        self._reported = now
        return events

    def _housekeeping(self) -> None:
        """Write the health hash and link events, and forward new control commands."""
        self._next_health = time.monotonic() + HEALTH_INTERVAL_S
        if not self._redis(self._hold_claim if self._taken_over else self._take_over):
            return
        if not self._taken_over or self._refused_since is not None:
            return  # another daemon holds the device: its health and commands are not ours
        if self._control_id is None and not self._redis(self._find_control_start):
            return
        fields = self.health.to_fields()
        reported, reported_causes = dict(self._reported), dict(self._reported_causes)
        events = self._new_events()

        def write_health() -> None:
            pipe = self.client.pipeline(transaction=False)
            pipe.hset(health_key(self.device), mapping=fields)
            pipe.sadd(DEVICES_SET, self.device)
            for event in events:
                pipe.xadd(events_stream(self.device), {**event, "written_ns": fields["updated_ns"]},
                          maxlen=EVENTS_MAXLEN, approximate=True)
            pipe.execute()

        if self._redis(write_health):
            self.health_written = True
            self._redis(self._write_cursor)
            self._redis(self._read_control)
        else:
            self._reported, self._reported_causes = reported, reported_causes

    def _take_over(self) -> None:
        """Go on from the counters the device's previous daemon left in its health hash
        once the device's claim is this daemon's (with no claim, they start from 0; while
        another daemon holds it, the device is not taken over: :meth:`_hold_claim`). The
        counts carried over are not new drops or reconnects. The newest frame on the
        device's stream tells which frames the previous daemon published after its last
        health write (one killed in between wrote no more)."""
        if not self._hold_claim():
            return
        if self.claim is not None:
            raw = self.client.hgetall(health_key(self.device))
            carried = self.health.carry_over(
                {(k.decode() if isinstance(k, bytes) else k): v for k, v in raw.items()},
                self._newest_published())
            self._reported_causes = {c: carried[f"dropped_{c}"] for c in ALL_DROP_CAUSES}
            self._reported = {"dropped": sum(self._reported_causes.values()),
                              "reconnects": carried["reconnects"]}
        self._taken_over = True

    def _hold_claim(self) -> bool:
        """Take or renew this daemon's claim on the device; True when it holds it (or has
        none to keep). Another daemon's claim (both started while Redis was down, or
        Redis lost this one's and another took it) is waited out for its TTL, as a
        killed daemon's lapses in that time, publishing nothing meanwhile; then the
        publisher fails with the error naming the holder (:meth:`_fail`)."""
        if self.claim is None or self.claim.renew():
            self._refused_since = None
            return True
        now = time.monotonic()
        if self._refused_since is None:
            self._refused_since = now
            log.warning("device %s: another daemon holds the device id; waiting up to %.1f s "
                        "for its claim to lapse", self.device, CLAIM_TTL_MS / 1000)
        elif now - self._refused_since >= CLAIM_TTL_MS / 1000:
            self._fail(self.claim.taken_error())
        return False

    def _fail(self, error: DeviceTakenError) -> None:
        """Stop publishing for good: another daemon keeps the device."""
        self.failure = error
        unpublished = self._queue.qsize() + (self._held is not None)
        log.error("%s (%d frames of this daemon not published)", error.message, unpublished)
        if self.on_failure is not None:
            self.on_failure(error)

    def delivered(self, entry_id: str) -> None:
        """Control entry ``entry_id`` (and every one before it) reached the camera or was
        refused; the device's cursor moves there at the next housekeeping."""
        self._delivered = entry_id

    def _write_cursor(self) -> None:
        delivered = self._delivered
        if delivered is not None and delivered != self._cursor_written:
            self.client.set(control_cursor_key(self.device), delivered)
            self._cursor_written = delivered

    def _newest_published(self) -> int | None:
        """The sequence number of the newest frame on the device's stream (None: none)."""
        newest = self.client.xrevrange(frame_stream(self.device), count=1)
        return int(newest[0][1][b"seq"]) if newest else None

    def _find_control_start(self) -> None:
        """Fix where control commands start, before the first health write shows the
        daemon up: after the last command the device's previous daemon delivered
        (commands the API accepted while no daemon ran, or that a stopped daemon had not
        sent yet, are not lost), or, for a device's first daemon, after the newest one
        (older ones are skipped, and one sent once the daemon shows up is not)."""
        stream = control_stream(self.device)
        done = self.client.get(control_cursor_key(self.device))
        newest = self.client.xrevrange(stream, count=1) if done is None else []
        start = done or (newest[0][0] if newest else b"0-0")
        self._control_id = start.decode() if isinstance(start, bytes) else start
        if done is None:  # the device's place from now on, for its next daemon
            self.client.set(control_cursor_key(self.device), self._control_id, nx=True)

    def _read_control(self) -> None:
        """Forward the control commands after the last one handed over (by this daemon,
        or from the start :meth:`_find_control_start` fixed, which comes first)."""
        reply = self.client.xread({control_stream(self.device): self._control_id}, count=16)
        for _, entries in reply or []:
            for raw_id, fields in entries:
                entry_id = raw_id.decode() if isinstance(raw_id, bytes) else raw_id
                if not self.on_command(entry_id, self._command(entry_id, fields)):
                    return  # no room now: handed over again from here next time
                self._control_id = entry_id

    def _command(self, entry_id: str, fields: dict[bytes | str, bytes | str]) -> Command | None:
        """The command of a control entry, or None (counted and logged) when it is refused."""
        try:
            return fields_to_command(fields)
        except InvalidInputError as exc:
            log.warning("control entry %s of %s refused: %s", entry_id, self.device, exc.message)
        except Exception:
            # One bad entry must not stop publishing; the cursor still moves past it.
            log.exception("control entry %s of %s failed", entry_id, self.device)
        self.health.add("control_rejected")
        return None
