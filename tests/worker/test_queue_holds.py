"""QueueHolds: a job's hold on the queue, released once."""

from __future__ import annotations

import numpy as np
import redis

from models.formation import SensorParams
from worker.queue import JobQueue
from worker.queue_holds import QueueHolds
from worker.redis_keys import JOB_BYTES_PER_KEY, JOB_HOLDS, JOBS_HELD_BYTES, JOBS_PER_KEY

PARAMS = SensorParams(encoding="modulo", bits=8)
CODES = np.zeros((4, 6), np.uint8)


def test_release_gives_back_the_keys_share_and_the_queues_bytes_once(
    client: redis.Redis, queue: JobQueue
) -> None:
    keyed = queue.submit("reconstruction", CODES, PARAMS, "itoh", owner="alice")
    kept = queue.submit("reconstruction", CODES, PARAMS, "itoh", owner="alice")
    keyless = queue.submit("reconstruction", CODES, PARAMS, "itoh")
    assert client.hget(JOB_HOLDS, keyed.id) == f"alice {CODES.nbytes}".encode()
    assert client.hget(JOB_HOLDS, keyless.id) == f" {CODES.nbytes}".encode()
    assert int(client.get(JOBS_HELD_BYTES)) == 3 * CODES.nbytes
    holds = QueueHolds(client)
    assert holds.release(keyed.id) and holds.release(keyless.id)
    assert not holds.release(keyed.id) and not holds.release("0" * 32)
    assert int(client.hget(JOBS_PER_KEY, "alice")) == 1
    assert int(client.hget(JOB_BYTES_PER_KEY, "alice")) == CODES.nbytes
    assert int(client.get(JOBS_HELD_BYTES)) == CODES.nbytes
    holds.release(kept.id)
    assert client.hlen(JOBS_PER_KEY) == client.hlen(JOB_BYTES_PER_KEY) == 0
    assert client.hlen(JOB_HOLDS) == 0 and int(client.get(JOBS_HELD_BYTES)) == 0
