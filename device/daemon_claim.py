"""One daemon per device id: a claim in Redis that the running daemon keeps fresh.

Two daemons under one ``--device-id`` (two cameras, a typo, a second rig) wrote one
health hash in turn, had every frame of one camera dropped as stale, and split the
control commands between the cameras, without a word. A daemon claims
``daemon:<device>`` (its own random id, expiring after :data:`CLAIM_TTL_MS`) before it
streams, and renews it at every health write; a second daemon finds the claim and
refuses to start. A daemon that was killed leaves a claim that expires within the TTL,
so a restarted one waits that long at most. A daemon started while Redis is down
takes the claim before it first publishes (:class:`device.publisher.FramePublisher`):
one that finds another daemon's keeps its frames unpublished, waits the TTL, and stops
with the same error.
"""

from __future__ import annotations

import os
import socket
import time
import uuid

import redis

from models.errors import McamError
from worker.redis_keys import daemon_key

#: How long a claim lives unless renewed (ms); daemons renew it every 0.25 s.
CLAIM_TTL_MS = 3000

# KEYS: the claim. ARGV: this daemon's id, the TTL (ms). 1 if held by this daemon now.
_CLAIM = """
local holder = redis.call('GET', KEYS[1])
if holder and holder ~= ARGV[1] then return 0 end
redis.call('SET', KEYS[1], ARGV[1], 'PX', ARGV[2])
return 1
"""


class DeviceTakenError(McamError):
    """Another daemon streams under this device id."""

    code = "device_taken"
    http_status = 409


class DaemonClaim:
    """This daemon's claim on ``device`` (an id naming the host and process)."""

    def __init__(self, client: redis.Redis, device: str) -> None:
        self.client = client
        self.device = device
        self.owner = f"{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex[:8]}"

    def renew(self) -> bool:
        """Take or renew the claim; False when another daemon holds it."""
        return bool(self.client.eval(_CLAIM, 1, daemon_key(self.device), self.owner,
                                     CLAIM_TTL_MS))

    def take(self, wait_s: float = CLAIM_TTL_MS / 1000) -> None:
        """Take the claim, waiting up to ``wait_s`` for a killed daemon's to expire;
        :class:`DeviceTakenError` naming the holder if another daemon keeps it."""
        deadline = time.monotonic() + wait_s
        while not self.renew():
            if time.monotonic() >= deadline:
                raise self.taken_error()
            time.sleep(0.1)

    def taken_error(self) -> DeviceTakenError:
        """The error naming the daemon that holds the device (read from Redis now)."""
        holder = self.client.get(daemon_key(self.device))
        name = holder.decode() if isinstance(holder, bytes) else holder
        return DeviceTakenError(
            f"device {self.device!r} already has a daemon ({name}: host, process); "
            "stop it, or give this camera another --device-id"
        )

    def release(self) -> None:
        """Drop the claim if it is still this daemon's (a clean stop)."""
        if self.client.get(daemon_key(self.device)) == self.owner.encode():
            self.client.delete(daemon_key(self.device))
