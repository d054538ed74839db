"""Per-device health counters of the daemon, published as the ``device:<id>:health`` hash.

Fields (all strings in Redis): ``state`` (connecting / connected / disconnected, and
the daemon's last word: stopped, or crashed when it stopped on an unexpected error),
``crash`` (that error, on one line: its type and message; empty otherwise), ``port``,
``port_error`` (why the port last failed to open; empty once it is open),
``frames_ok`` (published), ``frames_received`` (valid data packets),
``dropped_<cause>`` for every parser cause plus ``queue_full`` (the daemon's own
queue), ``stream_full`` (oldest frames evicted from the Redis stream unread),
``redis_unavailable``, ``redis_full`` (Redis at its ``maxmemory``, refusing writes) and
``rejected``, ``garbage_bytes``, ``sequence_gaps``, ``frames_missing``
(sequence numbers never received), ``reconnects``, ``last_frame_ns`` (host
wall clock, ns since the epoch) and ``last_sequence`` of the device's newest frame (-1:
none yet; the host's number, on past wraps of the camera's 32-bit counter:
:func:`unwrap_sequence`), ``fps`` (measured over the last frames), ``brackets_saved``,
``brackets_incomplete``, ``brackets_saturated`` (complete, but saturated at every pixel:
not saved), ``control_sent``, ``control_rejected``, ``settings`` (JSON: encoding, alpha,
bits, gain, width, height of the newest streamed frame: a bracket's exposures are
not), ``updated_ns``.

The counters are the device's, not one daemon's: a daemon that takes over the device
(:meth:`DeviceHealth.carry_over`) goes on from those its previous daemon left in the
hash, and its first frame is seen against the previous daemon's last one (frames the
camera sent while no daemon ran are a gap); until that frame the newest frame's
``last_sequence`` and ``last_frame_ns`` stay the previous daemon's. A killed daemon's
hash is up to one health write old (0.25 s): the frames it published after that are
read from the device's frame stream, and only those it got but never published count
as missing. The gauges (state, crash, port error, fps, settings) are this daemon's own.
"""

from __future__ import annotations

import json
import threading
import time
from collections import Counter, deque
from collections.abc import Mapping
from typing import Any

from device.link_parser import DROP_CAUSES

#: Drop causes on the host side of the link, after the parser's: publish queue full, the
#: device's stream full, Redis unreachable or full (at its maxmemory), or a frame whose
#: header the formation model rejects.
HOST_DROP_CAUSES: tuple[str, ...] = ("queue_full", "stream_full", "redis_unavailable",
                                     "redis_full", "rejected")
ALL_DROP_CAUSES: tuple[str, ...] = DROP_CAUSES + HOST_DROP_CAUSES
#: States a daemon writes as it ends: its device streams no more until a daemon starts.
ENDED_STATES: tuple[str, ...] = ("stopped", "crashed")
#: A forward sequence jump counts its frames as missing up to this many (an hour at
#: 250 frames/s); a larger one is a counter that reset or was corrupted, not frames
#: lost, and counts as a gap only (a jump to 2^64 - 1 added 1.8e19 missing frames).
MAX_MISSING_PER_GAP = 1_000_000
#: One lap of the camera firmware's 32-bit sequence counter: its step from 2^32 - 1 to 0
#: is the next frame (:func:`unwrap_sequence`).
COUNTER_LAP = 1 << 32
_COUNTERS: tuple[str, ...] = (
    "frames_ok", "frames_received", "garbage_bytes", "sequence_gaps", "frames_missing",
    "reconnects", "brackets_saved", "brackets_incomplete", "brackets_saturated", "control_sent",
    "control_rejected",
) + tuple(f"dropped_{cause}" for cause in ALL_DROP_CAUSES)


class DeviceHealth:
    """Thread-safe counters and gauges of one device link."""

    def __init__(self, device: str, port: str, fps_window: int = 30) -> None:
        self.device = device
        self.port = port
        self.state = "connecting"
        self.crash = ""
        self.port_error = ""
        self.counts: Counter[str] = Counter({name: 0 for name in _COUNTERS})
        self._carried: Counter[str] = Counter()  # the previous daemons' counts
        self._first_sequence: int | None = None  # this daemon's first frame
        self._resume_after: int | None = None  # the previous daemon's last, until then
        self.last_frame_ns = 0
        self.last_sequence = -1
        self.settings: dict[str, Any] = {}
        self._arrivals: deque[float] = deque(maxlen=fps_window)
        self._lock = threading.Lock()

    def add(self, name: str, n: int = 1) -> None:
        """Increase counter ``name`` by ``n``."""
        with self._lock:
            self.counts[name] += n

    def set(self, name: str, value: int) -> None:
        """Set counter ``name`` to this daemon's ``value`` (for counts kept elsewhere)."""
        with self._lock:
            self.counts[name] = self._carried[name] + value

    def set_parser_counts(self, drops: Counter[str], garbage_bytes: int,
                          base: Counter[str]) -> None:
        """Counters of the current parser, on top of those of parsers before a reconnect."""
        with self._lock:
            for cause in DROP_CAUSES:
                name = f"dropped_{cause}"
                self.counts[name] = self._carried[name] + base[cause] + drops[cause]
            self.counts["garbage_bytes"] = (self._carried["garbage_bytes"]
                                            + base["garbage_bytes"] + garbage_bytes)

    def carry_over(self, previous: Mapping[str, bytes | str],
                   published: int | None = None) -> Counter[str]:
        """Go on from the counters of the device's previous daemon (``previous``: the
        health hash it left; a counter missing there, or not a whole number, counts 0):
        they are added to this daemon's, now and at every later :meth:`set`. This
        daemon's first frame, now or when it comes, is seen against the previous
        daemon's last (:meth:`sequence_gap`): the hash's ``last_sequence``, or
        ``published`` (the newest frame on the device's stream) when that is later, as
        when the previous daemon was killed after publishing frames its hash does not
        show. Returns the counters carried over."""
        carried = Counter({name: max(_whole(previous.get(name)), 0) for name in _COUNTERS})
        last = _whole(previous.get("last_sequence"))
        if last >= 0 and published is not None:
            last = max(last, published)
        with self._lock:
            self._carried = carried
            self.counts.update(carried)
            if last >= 0 and self._first_sequence is not None:
                self._count_gap(last + 1, self._first_sequence)
            elif last >= 0:
                self._resume_after = last
                self.last_sequence = last
                self.last_frame_ns = max(_whole(previous.get("last_frame_ns")), 0)
        return carried

    def sequence_gap(self, expected: int, sequence: int) -> None:
        """Count frame ``sequence`` coming where ``expected`` was due: a gap, and the
        frames skipped as missing (none for a step back or one past
        :data:`MAX_MISSING_PER_GAP`)."""
        with self._lock:
            self._count_gap(expected, sequence)

    def _count_gap(self, expected: int, sequence: int) -> None:
        """:meth:`sequence_gap` with the lock held; nothing when ``sequence`` is due (also
        once unwrapped: :func:`unwrap_sequence`)."""
        sequence = unwrap_sequence(sequence, expected)
        if sequence == expected:
            return
        self.counts["sequence_gaps"] += 1
        missing = sequence - expected
        if 0 < missing <= MAX_MISSING_PER_GAP:
            self.counts["frames_missing"] += missing

    def frame_received(self, sequence: int, settings: dict[str, Any] | None) -> None:
        """Record a valid data packet's arrival (for fps and last-frame gauges); this
        daemon's first is seen against the previous daemon's last (:meth:`carry_over`).
        ``settings`` None (a bracket's packet, not streamed) keeps the streamed frames'."""
        with self._lock:
            if self._first_sequence is None:
                self._first_sequence = sequence
                if self._resume_after is not None:
                    self._count_gap(self._resume_after + 1, sequence)
            self.counts["frames_received"] += 1
            self.last_sequence = sequence
            self.last_frame_ns = time.time_ns()
            if settings is not None:
                self.settings = settings
            self._arrivals.append(time.monotonic())

    def crashed(self, error: str) -> dict[str, str]:
        """Mark the daemon stopped on an unexpected error (``error``: its line); returns
        the hash fields that say so (at 0 fps), for a write of their own."""
        with self._lock:
            self.state, self.crash = "crashed", error
        return {"state": "crashed", "crash": error, "fps": "0.000",
                "updated_ns": str(time.time_ns())}

    @property
    def fps(self) -> float:
        """Frames per second over the last arrivals (0 with fewer than two, or if stale)."""
        with self._lock:
            if len(self._arrivals) < 2 or time.monotonic() - self._arrivals[-1] > 5.0:
                return 0.0
            span = self._arrivals[-1] - self._arrivals[0]
            return (len(self._arrivals) - 1) / span if span > 0 else 0.0

    def drop_counts(self) -> dict[str, int]:
        """Frames dropped so far, by cause (:data:`ALL_DROP_CAUSES`)."""
        with self._lock:
            return {cause: self.counts[f"dropped_{cause}"] for cause in ALL_DROP_CAUSES}

    def dropped(self) -> int:
        """Frames dropped for any cause."""
        with self._lock:
            return sum(self.counts[f"dropped_{cause}"] for cause in ALL_DROP_CAUSES)

    def to_fields(self) -> dict[str, str]:
        """The Redis hash fields."""
        fps = self.fps
        with self._lock:
            fields = {name: str(value) for name, value in self.counts.items()}
            fields.update(
                device=self.device, port=self.port, state=self.state, crash=self.crash,
                port_error=self.port_error,
                last_frame_ns=str(self.last_frame_ns), last_sequence=str(self.last_sequence),
                fps=f"{fps:.3f}", settings=json.dumps(self.settings),
                updated_ns=str(time.time_ns()),
            )
        return fields


def unwrap_sequence(sequence: int, expected: int) -> int:
    """The host's number for the camera's ``sequence`` arriving where ``expected`` was due.

    The firmware's counter is 32 bits: after 2^32 - 1 it sends 0. A number below
    :data:`COUNTER_LAP` that lies, modulo a lap, 0 to :data:`MAX_MISSING_PER_GAP` frames
    on from ``expected`` is read in the lap that makes it so (2^32 - 1 then 0 is 2^32 - 1
    then 2^32: consecutive); any other number is taken as it is (a counter that
    restarted, or jumped, is a gap). Idempotent: an unwrapped number maps to itself.
    """
    if sequence == expected or sequence >= COUNTER_LAP or expected < 0:
        return sequence
    lap_start = expected - expected % COUNTER_LAP
    for candidate in (lap_start + sequence, lap_start + COUNTER_LAP + sequence):
        if 0 <= candidate - expected <= MAX_MISSING_PER_GAP:
            return candidate
    return sequence


def crashed_daemon_text(device: str, crash: str) -> str:
    """The words for the daemon of ``device`` that stopped on an unexpected error
    (``crash``: its line, as in the health's ``crash`` field): each message saying so
    starts with them, then says where its traceback is and what to do."""
    return f"the daemon of device {device!r} stopped on an unexpected error ({crash})"


def _whole(value: bytes | str | None) -> int:
    """A whole number read back from the health hash; -1 if missing or malformed."""
    try:
        return int(value or -1)
    except ValueError:
        return -1
