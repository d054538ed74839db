"""Each job's hold on the job queue, released once its entry leaves the ``jobs`` stream.

A submit (:meth:`worker.queue.JobQueue.submit`, one Lua script with the ``XADD``) takes
the hold: ``jobs:holds[<job id>] = "<owner's key id> <bytes of its codes>"`` and the
owner's job count and bytes (``jobs:per_key``, ``jobs:bytes_per_key``) and the queue's
bytes (``jobs:held_bytes``) go up. The worker that deletes the entry (the job done,
failed, cancelled or dead-lettered) releases it with :meth:`QueueHolds.release` just
before: a job counts against its key and the queue for as long as its codes sit in
Redis, a cancelled one until a worker drops its entry (at once when a worker is free).
Releasing twice is harmless; a worker that dies between the release and the delete
leaves the entry to be reclaimed, counted short meanwhile, never held for ever.
"""

from __future__ import annotations

import redis

from worker.redis_keys import JOB_BYTES_PER_KEY, JOB_HOLDS, JOBS_HELD_BYTES, JOBS_PER_KEY

_RELEASE = """
local hold = redis.call('HGET', KEYS[1], ARGV[1])
if not hold then return 0 end
redis.call('HDEL', KEYS[1], ARGV[1])
local owner, bytes = string.match(hold, '^(.-) (%d+)$')
if owner ~= '' then
  if redis.call('HINCRBY', KEYS[2], owner, -1) <= 0 then redis.call('HDEL', KEYS[2], owner) end
  if redis.call('HINCRBY', KEYS[3], owner, -tonumber(bytes)) <= 0 then
    redis.call('HDEL', KEYS[3], owner)
  end
end
redis.call('DECRBY', KEYS[4], bytes)
return 1
"""


class QueueHolds:
    """Releases jobs' holds on the queue (the worker's side)."""

    def __init__(self, client: redis.Redis) -> None:
        self._release = client.register_script(_RELEASE)

    def release(self, job_id: str) -> bool:
        """Release the job's hold (call just before deleting its entry); False when it
        held nothing (released before, or submitted before holds were kept)."""
        keys = [JOB_HOLDS, JOBS_PER_KEY, JOB_BYTES_PER_KEY, JOBS_HELD_BYTES]
        return bool(self._release(keys=keys, args=[job_id]))
