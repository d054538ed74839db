"""What one API process holds while it runs: settings, Redis, keys, queue and result store.

Built at startup by :func:`open_state` and closed at shutdown. When
``MCAM_REDIS_URL`` is unset the API starts the embedded ``redis-server`` in the
data dir itself (the embedded default when the API runs alone).
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from dataclasses import dataclass, field

import redis

from service.core.config import Settings
from service.core.security import KeyRing, RateLimiter
from worker.embedded_redis import EmbeddedRedis, connect, durability_problem, redacted_url
from worker.queue import JobQueue
from worker.redis_memory import TroubleLog
from worker.result_store import RESULTS_DIR, ResultStore

log = logging.getLogger(__name__)

#: Seconds between looks for a free slot while a request waits for one.
SLOT_POLL_S = 0.05


class Slots:
    """At most ``limit`` of something held at once (thread-safe): requests waiting for
    their job, open event streams, uploads being decoded."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self._held = 0
        self._lock = threading.Lock()

    @property
    def full(self) -> bool:
        return self._held >= self.limit

    def take(self) -> bool:
        """Hold a slot if one is free."""
        with self._lock:
            if self._held >= self.limit:
                return False
            self._held += 1
            return True

    async def wait_take(self, wait_s: float) -> bool:
        """Hold a slot, waiting up to ``wait_s`` seconds for one to be freed (on the
        event loop: a waiting request holds no server thread); False if none was."""
        deadline = time.monotonic() + wait_s
        while not self.take():
            left_s = deadline - time.monotonic()
            if left_s <= 0:
                return False
            await asyncio.sleep(min(SLOT_POLL_S, left_s))
        return True

    def release(self) -> None:
        with self._lock:
            self._held -= 1


@dataclass
class ServiceState:
    """Per-process resources; the job queue is created on first use (it needs Redis up)."""

    settings: Settings
    client: redis.Redis
    keyring: KeyRing
    limiter: RateLimiter
    store: ResultStore
    redis_url: str
    #: Requests that may hold a server thread waiting for their job (``Prefer: wait``).
    wait_slots: Slots
    #: Server-sent event streams open at once (each holds a blocked Redis connection).
    event_slots: Slots
    #: Uploads decoded or simulated in this process at once (each may take gigabytes).
    decode_slots: Slots
    embedded: EmbeddedRedis | None = None
    #: Set when the server begins to stop (:class:`service.cli.api.StoppingServer`):
    #: requests waiting for their jobs answer at once.
    stopping: threading.Event = field(default_factory=threading.Event)
    #: Redis trouble met by requests (the rate limit): one warning per 30 s per app,
    #: not one per request (a module-wide one held back another app's first warning).
    redis_trouble: TroubleLog = field(
        default_factory=lambda: TroubleLog(logging.getLogger("service.api.deps"))
    )
    _queue: JobQueue | None = field(default=None, repr=False)

    @property
    def queue(self) -> JobQueue:
        """The job queue (raises a Redis ConnectionError, i.e. 503, while Redis is down)."""
        if self._queue is None:
            self._queue = JobQueue(
                self.client,
                maxlen=self.settings.jobs_maxlen,
                max_deliveries=self.settings.max_deliveries,
                claim_idle_ms=self.settings.claim_idle_ms,
                max_per_key=self.settings.max_queued_jobs_per_key,
                max_bytes_per_key=self.settings.max_queued_bytes_per_key,
                max_bytes=self.settings.jobs_max_bytes,
            )
        return self._queue

    def close(self) -> None:
        """Release the Redis connections and stop the embedded server if we started it."""
        self.client.close()
        if self.embedded is not None:
            self.embedded.stop()


def embedded_redis_for(settings: Settings) -> EmbeddedRedis | None:
    """The embedded Redis of the data dir when no ``MCAM_REDIS_URL`` is set (not started).
    ``mcam api`` and ``mcam serve`` start it before anything else, so that a data dir
    another command already serves is refused in one line, not by a traceback from the
    app's startup; they pass its URL on, and the app starts one only when run otherwise."""
    if settings.redis_url is not None:
        return None
    return EmbeddedRedis(settings.data_dir, keep_alive=True, maxmemory=settings.redis_maxmemory)


def open_state(settings: Settings, keyring: KeyRing) -> ServiceState:
    """Connect to Redis (starting the embedded one when no URL is set) and open the store."""
    embedded = embedded_redis_for(settings)
    url = settings.redis_url if embedded is None else embedded.start()
    client = connect(url, timeout_s=settings.redis_timeout_s, fail_fast=True)
    problem = durability_problem(client)
    if problem is not None:
        log.warning("Redis at %s may lose accepted jobs: %s", redacted_url(url), problem)
    return ServiceState(
        settings=settings,
        client=client,
        keyring=keyring,
        limiter=RateLimiter(client, settings.rate_limit_per_minute),
        store=ResultStore(settings.data_dir / RESULTS_DIR, settings.result_retention_s),
        redis_url=url,
        embedded=embedded,
        wait_slots=Slots(settings.max_waiting_requests),
        event_slots=Slots(settings.max_event_streams),
        decode_slots=Slots(settings.max_concurrent_decodes),
    )
