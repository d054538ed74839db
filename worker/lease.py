"""Single ownership of a device stream: a Redis lease (SET NX PX) renewed while alive.

Usage::

    lease = Lease(client, owner="worker-abc", ttl_ms=5000)
    if lease.acquire("cam1"):      # nobody else owns it (or their lease lapsed)
        ...
        lease.renew("cam1")        # False: we lost it, stop touching the device
    lease.release("cam1")

A worker that dies stops renewing; its lease expires after ``ttl_ms`` and
another worker's ``acquire`` succeeds. Renew and release only act on a lease
this owner still holds (compare-and-set in Lua).
"""

from __future__ import annotations

import redis

from worker.redis_keys import lease_key

_RENEW = """
if redis.call('GET', KEYS[1]) == ARGV[1] then
  return redis.call('PEXPIRE', KEYS[1], ARGV[2])
end
return 0
"""

_RELEASE = """
if redis.call('GET', KEYS[1]) == ARGV[1] then return redis.call('DEL', KEYS[1]) end
return 0
"""


class Lease:
    """Leases on device streams held by ``owner``, each valid ``ttl_ms`` after renewal."""

    def __init__(self, client: redis.Redis, owner: str, ttl_ms: int) -> None:
        self.client = client
        self.owner = owner
        self.ttl_ms = ttl_ms
        self._renew = client.register_script(_RENEW)
        self._release = client.register_script(_RELEASE)

    def acquire(self, device: str) -> bool:
        """Take the lease if nobody holds it; True if we hold it now."""
        if self.client.set(lease_key(device), self.owner, nx=True, px=self.ttl_ms):
            return True
        return self.renew(device)

    def renew(self, device: str) -> bool:
        """Extend our lease; False when it lapsed or another owner holds it."""
        return bool(self._renew(keys=[lease_key(device)], args=[self.owner, self.ttl_ms]))

    def release(self, device: str) -> None:
        """Give the lease up (only if we hold it)."""
        self._release(keys=[lease_key(device)], args=[self.owner])

    def holder(self, device: str) -> str | None:
        """Who holds the device's lease now, if anyone."""
        value = self.client.get(lease_key(device))
        return value.decode() if value is not None else None
