"""Names of every Redis key and stream the system uses, in one place.

Device daemons write ``frames:<device>`` and ``device:<device>:health``; workers
read frame and job streams and write ``events:<device>``; the API reads all of
them and writes ``control:<device>`` for daemons to forward to the camera.
"""

from __future__ import annotations

import hashlib
import re

from models.errors import InvalidInputError, echo

DEVICES_SET = "devices"
JOBS_STREAM = "jobs"
DEAD_LETTER_STREAM = "deadletter"
WORKERS_HEARTBEAT = "workers"
#: Hash: job state -> number of job records in that state (kept by state transitions).
JOB_STATES = "jobs:states"
#: Hash: job id -> "<owner's key id> <bytes of its codes>", its hold on the queue while
#: its entry is in the ``jobs`` stream (see ``worker/queue_holds.py``).
JOB_HOLDS = "jobs:holds"
#: Hash: API key id -> its jobs in the ``jobs`` stream.
JOBS_PER_KEY = "jobs:per_key"
#: Hash: API key id -> bytes of codes of its jobs in the ``jobs`` stream.
JOB_BYTES_PER_KEY = "jobs:bytes_per_key"
#: Bytes of codes of all jobs in the ``jobs`` stream (with a hold).
JOBS_HELD_BYTES = "jobs:held_bytes"
#: Prefix of the worker's Redis-backed metrics (see ``worker/metrics.py``).
METRICS_PREFIX = "metrics:"
_DEVICE_ID = re.compile(r"^[A-Za-z0-9_-]{1,64}$")


def validate_device_id(device: str) -> str:
    """Device ids are 1-64 ASCII letters, digits, '_' or '-' (they become key and path
    parts); the error says ASCII (an id of other scripts' letters, 'caméra', was told to
    use letters)."""
    if not _DEVICE_ID.fullmatch(device):
        raise InvalidInputError(
            f"invalid device id {echo(device)}: use 1-64 letters, digits, '_' or '-' "
            "(ASCII: A-Z, a-z, 0-9)"
        )
    return device


def frame_stream(device: str) -> str:
    """Stream of wrapped frames from one device (entries: :class:`FrameMessage` fields)."""
    return f"frames:{validate_device_id(device)}"


def health_key(device: str) -> str:
    """Hash of the daemon's health counters for one device."""
    return f"device:{validate_device_id(device)}:health"


def control_stream(device: str) -> str:
    """Stream of control commands from the API to the device's daemon."""
    return f"control:{validate_device_id(device)}"


def control_cursor_key(device: str) -> str:
    """The id of the last control command the device's daemon handled, so that a daemon
    that restarts goes on with the commands sent while it was down."""
    return f"control:{validate_device_id(device)}:done"


def daemon_key(device: str) -> str:
    """The claim of the daemon streaming the device (:mod:`device.daemon_claim`)."""
    return f"daemon:{validate_device_id(device)}"


def events_stream(device: str) -> str:
    """Stream of events (frame reconstructed, drop, reconnect) for server-sent events."""
    return f"events:{validate_device_id(device)}"


def latest_key(device: str) -> str:
    """String key holding the result-store key of the device's newest reconstruction."""
    return f"device:{validate_device_id(device)}:latest"


def job_key(job_id: str) -> str:
    """Hash holding one job's record."""
    return f"job:{job_id}"


def job_done_channel(job_id: str) -> str:
    """Pub/sub channel announcing that a job finished (waiters subscribe to it)."""
    return f"job:{job_id}:done"


def lease_key(device: str) -> str:
    """String key naming the worker that owns a device stream (SET NX PX, renewed)."""
    return f"device:{validate_device_id(device)}:lease"


def last_sequence_key(device: str) -> str:
    """Hash ``seq`` / ``entry``: sequence number and stream entry id of the device's newest
    handled frame (the ordering cursor of its owning worker)."""
    return f"device:{validate_device_id(device)}:seq"


def rate_limit_key(key_id: str) -> str:
    """Sorted set logging one API key's recent requests (member: a random tag, score: the
    request's time in ms); the key id is a hash, never the key itself."""
    return f"ratelimit:{key_id}"


def recording_key(device: str) -> str:
    """Hash of the device's current (or last) live recording (see ``worker/recordings.py``)."""
    return f"device:{validate_device_id(device)}:recording"


def idempotency_key(owner: str, key: str) -> str:
    """String naming the job the API key ``owner`` (its id) made with the idempotency key
    ``key`` (see ``worker/idempotency.py``): a SHA-256 of the client's key, whatever
    characters and length it has."""
    return f"idempotency:{owner}:{hashlib.sha256(key.encode()).hexdigest()}"
