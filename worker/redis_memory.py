"""Redis's memory bound: the embedded server's, an external server's policy, a full server.

A Redis at its ``maxmemory`` either evicts keys (every ``maxmemory-policy`` but
``noeviction``), which can drop an accepted job's record or codes without a word, or,
under ``noeviction``, refuses the commands that would grow its memory (``-OOM command
not allowed when used memory > 'maxmemory'``) and keeps everything it holds. So:

- the embedded server runs with ``maxmemory`` ``MCAM_REDIS_MAXMEMORY`` (bytes) and
  ``noeviction`` (:func:`server_config`): a runaway backlog meets a clear refusal
  rather than the host's out-of-memory killer;
- an external server whose policy evicts is named in the startup warning
  (:func:`eviction_problem`, part of :func:`worker.embedded_redis.durability_problem`);
- a refused write is told apart from a bug (:func:`is_out_of_memory`): the API answers
  503 ``store_full`` (:class:`StoreFullError`), and workers and device daemons wait and
  retry, as when Redis is unreachable (:func:`is_transient`);
- the API is ready (``/health/ready``) only while Redis has room below its
  ``maxmemory`` for the largest upload it accepts (:func:`submit_room`,
  :func:`full_problem`), so that a load balancer stops sending work before it fails.

A full server still reads, deletes, acknowledges and expires keys, so results can
be fetched and job records lapse at the end of their retention; but a worker cannot
record a job's end (a write that grows a hash) until there is room, so jobs wait
in the queue, not lost, until an operator raises ``maxmemory`` or data expires. The
queue's own byte bound (``MCAM_JOBS_MAX_BYTES``, 503 ``queue_full``) sits below
``MCAM_REDIS_MAXMEMORY`` so that it, not this one, is the bound clients normally meet.
"""

from __future__ import annotations

import errno
import logging
import math
import threading
import time
from collections.abc import Mapping
from typing import Any

import redis

from models.errors import McamError

#: Default ``maxmemory`` of the embedded server (bytes): the queue's 2 GiB of job codes,
#: device frame streams, job records and Redis's own overhead.
DEFAULT_MAXMEMORY = 4 * 1024**3
#: The only policy that never drops an accepted job.
NO_EVICTION = "noeviction"
#: What Redis says when it refuses a write for want of memory (also inside a script).
_OOM_REPLY = "OOM command not allowed"
#: What a submit of a job's codes costs Redis at the moment it checks its ``maxmemory``
#: (:func:`submit_room`). Measured on redis-server 6.2 with n bytes of codes sent on a
#: new connection: refused with 2 n free, taken with 2 n + min(n, 1 MiB) + 40 KiB, for n
#: from 128 KiB to 96 MiB. The codes arrive as one argument that Redis keeps as the
#: command's value (n); it sets aside a query buffer as large for the connection's next
#: argument (n), and grows one of them as it grows buffers: to twice the size, by at
#: most :data:`QUERY_BUFFER_STEP`.
QUERY_BUFFER_STEP = 1024**2
#: Bytes of a submit besides its codes: the job's record, the script's other arguments
#: and a new connection's buffers (together 25-40 KiB measured), with room to spare.
SUBMIT_OVERHEAD_BYTES = 64 * 1024


class StoreFullError(McamError):
    """Redis refused a write: it is at its ``maxmemory`` and evicts nothing."""

    code = "store_full"
    http_status = 503
    retry_after_s = 30


def server_config(maxmemory: int) -> list[str]:
    """``redis.conf`` lines bounding a server at ``maxmemory`` bytes without eviction."""
    if maxmemory <= 0:
        raise ValueError(f"maxmemory must be > 0 bytes, got {maxmemory}")
    return [f"maxmemory {maxmemory}", f"maxmemory-policy {NO_EVICTION}"]


def eviction_problem(config: dict[str, str]) -> str | None:
    """Why a server with this ``CONFIG GET maxmemory*`` reply could drop accepted jobs
    (it evicts keys once at ``maxmemory``), or None."""
    policy = config.get("maxmemory-policy", NO_EVICTION)
    if policy == NO_EVICTION or config.get("maxmemory", "0") == "0":
        return None
    return (
        f"it evicts keys when full (maxmemory-policy {policy!r}); set maxmemory-policy "
        f"{NO_EVICTION}"
    )


def submit_room(codes_bytes: int) -> int:
    """Bytes Redis must have free below its ``maxmemory`` to take a submit of a job
    whose codes take ``codes_bytes``: twice them, the growth of a query buffer
    (``codes_bytes``, at most :data:`QUERY_BUFFER_STEP`) and
    :data:`SUBMIT_OVERHEAD_BYTES`."""
    return 2 * codes_bytes + min(codes_bytes, QUERY_BUFFER_STEP) + SUBMIT_OVERHEAD_BYTES


def free_memory(memory: Mapping[str, Any]) -> int | None:
    """Bytes Redis has free below its ``maxmemory`` (negative: over it, refusing writes),
    from its ``INFO memory`` reply, leaving out the buffers Redis does not count against
    it; None when it is unbounded or evicts keys (never refuses a write)."""
    maxmemory = int(memory.get("maxmemory", 0))
    if maxmemory == 0 or memory.get("maxmemory_policy", NO_EVICTION) != NO_EVICTION:
        return None
    used = int(memory.get("used_memory", 0)) - int(memory.get("mem_not_counted_for_evict", 0))
    return maxmemory - used


def full_problem(memory: Mapping[str, Any], room_bytes: int) -> str | None:
    """Why Redis refuses, or would refuse, a submit now, from its ``INFO memory`` reply:
    it evicts nothing and is over its ``maxmemory`` (less the buffers Redis leaves out
    of that count), so every submit gets 503 ``store_full``, or it has less than
    ``room_bytes`` free below it, the room the largest upload needs (:func:`submit_room`),
    which would get 503 ``store_full``. None when it has that room (or is unbounded)."""
    free = free_memory(memory)
    if free is None:
        return None
    maxmemory = int(memory["maxmemory"])
    used = maxmemory - free
    if free < 0:
        return (
            f"Redis is full ({used} bytes used, maxmemory {maxmemory}) and refuses writes: "
            "every submit gets 503 store_full and queued jobs wait; raise "
            "MCAM_REDIS_MAXMEMORY (an external Redis: its maxmemory), or wait until "
            "finished jobs' records expire (MCAM_RESULT_RETENTION_S)"
        )
    if free >= room_bytes:
        return None
    return (
        f"Redis has {free} bytes free below its maxmemory ({maxmemory}), less "
        f"than the largest upload needs ({room_bytes}: Redis holds its codes twice, and a "
        "buffer's growth, while it takes them): that upload would get 503 store_full; raise "
        "MCAM_REDIS_MAXMEMORY (an external Redis: its maxmemory), lower the largest upload "
        "(MCAM_MAX_PIXELS, MCAM_MAX_VIDEO_SAMPLES), or wait until queued jobs finish and "
        "finished jobs' records expire (MCAM_RESULT_RETENTION_S)"
    )


#: Redis errors of a server that cannot be reached or does not answer in time.
UNREACHABLE = (redis.exceptions.ConnectionError, redis.exceptions.TimeoutError)


def is_out_of_memory(exc: BaseException) -> bool:
    """Whether ``exc`` is Redis refusing a write at ``maxmemory`` (a command's
    ``OutOfMemoryError``, or the same refusal inside a Lua script)."""
    if isinstance(exc, redis.exceptions.OutOfMemoryError):
        return True
    return isinstance(exc, redis.exceptions.ResponseError) and _OOM_REPLY in str(exc)


def is_disk_full(exc: BaseException) -> bool:
    """Whether ``exc`` is a write refused for want of disk space or quota (the result
    store's disk): it succeeds once results expire or an operator frees space."""
    return isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT)


def is_transient(exc: BaseException) -> bool:
    """Whether a step may succeed if tried again later: Redis unreachable, not answering
    within the socket timeout, or full, or the results disk full (workers keep the entry
    and retry; nothing counts against the job)."""
    return isinstance(exc, UNREACHABLE) or is_out_of_memory(exc) or is_disk_full(exc)


def redis_trouble(exc: BaseException) -> str:
    """A log line's words for a transient error (:func:`is_transient`)."""
    if is_disk_full(exc):
        return (
            f"the results disk is full ({exc}); jobs and frames wait, not lost, until there "
            "is room (free space, or lower MCAM_RESULT_RETENTION_S)"
        )
    if is_out_of_memory(exc):
        return (
            "Redis is full (at its maxmemory) and refuses writes; jobs wait in the queue "
            "until it has room (raise MCAM_REDIS_MAXMEMORY or the server's maxmemory)"
        )
    if isinstance(exc, redis.exceptions.TimeoutError):
        return f"Redis did not answer in time ({exc})"
    return (
        f"Redis unreachable ({exc}): check that MCAM_REDIS_URL names a running Redis "
        "server this host can reach"
    )


class TroubleLog:
    """Warns of transient Redis errors (:func:`is_transient`) at most once per ``every_s``
    seconds per place: the loops retry every 0.5-8 s (:func:`worker.runner.reconnect_delay`)
    and a device stream's frames come faster, so a long outage wrote a warning every few
    seconds or more for each. The ones in between go to DEBUG and are counted in the next
    warning. Safe to share between threads."""

    def __init__(self, logger: logging.Logger, every_s: float = 30.0) -> None:
        self.logger = logger
        self.every_s = every_s
        self._lock = threading.Lock()
        self._last: dict[str, tuple[float, int]] = {}

    def warn(self, where: str, exc: BaseException, then: str = "retrying",
             now_s: float | None = None) -> None:
        """Log ``exc`` (transient) at ``where`` (a phrase naming the place), and ``then``,
        what the caller does about it (``now_s``: as for :meth:`report`)."""
        self.report(where, redis_trouble(exc), then, now_s)

    def report(self, where: str, trouble: str, then: str, now_s: float | None = None) -> None:
        """Log ``trouble`` (words) at ``where`` and ``then``, at most once per
        ``every_s`` per place. ``now_s``: the time of the trouble on the
        :func:`time.monotonic` clock, in s (default: now)."""
        now = time.monotonic() if now_s is None else now_s
        with self._lock:
            last, held_back = self._last.get(where, (-math.inf, 0))
            if now - last < self.every_s:
                self._last[where] = (last, held_back + 1)
                self.logger.debug("%s: %s", where, trouble)
                return
            self._last[where] = (now, 0)
        since = f" ({held_back} more times since the last warning)" if held_back else ""
        self.logger.warning("%s: %s; %s%s", where, trouble, then, since)

    def forget(self, where: str) -> None:
        """Drop what is kept for place ``where`` (a device the worker let go: one entry
        per device ever troubled, for the life of the worker, otherwise)."""
        with self._lock:
            self._last.pop(where, None)


def store_full_error() -> StoreFullError:
    """The client's answer to a refused write: nothing was stored, retry later."""
    return StoreFullError(
        "the job store (Redis) is full (at its maxmemory): nothing from this request was "
        "stored and everything accepted before is kept; retry later (an operator can raise "
        "MCAM_REDIS_MAXMEMORY, or an external server's maxmemory)"
    )
