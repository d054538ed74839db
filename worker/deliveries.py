"""One consumer's view of a stream in the workers' consumer group: read, reclaim, ack, retry.

Usage::

    consumer = StreamConsumer(client, "jobs", "worker-1-t0", max_deliveries=3)
    for delivery in consumer.reclaim(min_idle_ms=30_000) or consumer.read_new(block_ms=1000):
        ...                                   # write the result durably first
        consumer.done(delivery)               # XACK + XDEL in one transaction

Entries of a dead consumer stay pending; :meth:`reclaim` takes those idle longer
than ``min_idle_ms`` (XPENDING IDLE + XCLAIM, counting a delivery). Entries trimmed away
while pending (a full device stream) come back without fields and are acked, each
reported to ``on_trimmed`` when given (their frames are lost).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import redis

from worker.metrics import Metrics
from worker.queue import GROUP, ensure_group, is_missing_group
from worker.redis_keys import DEAD_LETTER_STREAM

#: The dead-letter stream keeps at most this many entries (oldest trimmed).
DEAD_LETTER_MAXLEN = 10_000
#: Reset an entry's idle time if consumer ARGV[2] of group ARGV[1] owns entry ARGV[3]
#: of stream KEYS[1]; 1 if it did, else 0. XCLAIM is not refused by a full Redis.
_TOUCH = """
local pending = redis.call('XPENDING', KEYS[1], ARGV[1], ARGV[3], ARGV[3], 1)
if #pending == 1 and pending[1][2] == ARGV[2] then
  redis.call('XCLAIM', KEYS[1], ARGV[1], ARGV[2], 0, ARGV[3], 'JUSTID')
  return 1
end
return 0
"""

#: Take over, for consumer ARGV[2] of group ARGV[1], the first ARGV[3] entries of stream
#: KEYS[1] pending at any other consumer (counting a delivery each); returns how many.
_CLAIM_OTHERS = """
local claimed = 0
for _, row in ipairs(redis.call('XPENDING', KEYS[1], ARGV[1], '-', '+', tonumber(ARGV[3]))) do
  if row[2] ~= ARGV[2] then
    redis.call('XCLAIM', KEYS[1], ARGV[1], ARGV[2], 0, row[1], 'RETRYCOUNT', row[4] + 1,
               'JUSTID')
    claimed = claimed + 1
  end
end
return claimed
"""

#: Read up to ARGV[4] new entries of stream KEYS[1] for consumer ARGV[3] of group ARGV[2],
#: only while key KEYS[2] holds ARGV[1]; 0 when it does not.
_READ_NEW_WHILE = """
if redis.call('GET', KEYS[2]) ~= ARGV[1] then return 0 end
local reply = redis.call('XREADGROUP', 'GROUP', ARGV[2], ARGV[3], 'COUNT', ARGV[4],
                         'STREAMS', KEYS[1], '>')
if not reply then return {} end
return reply[1][2]
"""

#: Delete consumer ARGV[2] of group ARGV[1] of stream KEYS[1] unless an entry is pending
#: at it (deleting it would drop the entry from the pending list: never reclaimed); 1 if
#: it was deleted, else 0.
_DELETE_IF_IDLE = """
if #redis.call('XPENDING', KEYS[1], ARGV[1], '-', '+', 1, ARGV[2]) > 0 then return 0 end
redis.call('XGROUP', 'DELCONSUMER', KEYS[1], ARGV[1], ARGV[2])
return 1
"""


def prune_consumers(client: redis.Redis, stream: str, keep: Callable[[str], bool]) -> int:
    """Delete the consumers of ``stream``'s group whose name ``keep`` refuses and at
    which no entry is pending; returns how many. Every worker that ever started left its
    consumers in the groups for good (six starts of ``mcam serve``, six consumers of
    ``jobs``). One deleted while its worker lives comes back with its next read."""
    try:
        consumers = client.xinfo_consumers(stream, GROUP)
    except redis.ResponseError:  # no such stream or group (yet): no consumer either
        return 0
    delete = client.register_script(_DELETE_IF_IDLE)
    names = [consumer["name"].decode() for consumer in consumers]
    return sum(delete(keys=[stream], args=[GROUP, name]) for name in names if not keep(name))


@dataclass
class Delivery:
    """A stream entry handed to this consumer; ``deliveries`` counts handings incl. this one,
    ``read_ms`` is when this consumer read it (ms since the epoch, as entry ids count).
    ``lost`` is set when another consumer has taken the entry over (this one stalled
    past the claim idle time): its work here is then wasted, and it is not ours to ack."""

    stream: str
    entry_id: str
    fields: dict[str, bytes]
    deliveries: int = 1
    read_ms: int = field(default_factory=lambda: time.time_ns() // 1_000_000)
    lost: threading.Event = field(default_factory=threading.Event, compare=False, repr=False)

    def text(self, name: str) -> str:
        """A header field as text (KeyError if missing)."""
        return self.fields[name].decode()


def entry_order(entry_id: str) -> tuple[int, int]:
    """Sort key of a stream id ``<ms>-<seq>``."""
    ms, _, seq = entry_id.partition("-")
    return int(ms), int(seq or 0)


def _pairs(flat: list[bytes]) -> dict[bytes, bytes]:
    """A stream entry's fields as Lua returns them, ``[name, value, ...]``, as a dict."""
    return dict(zip(flat[::2], flat[1::2], strict=True))


def _fields(raw: dict[bytes, bytes] | None) -> dict[str, bytes]:
    return {k.decode(): v for k, v in (raw or {}).items()}


class StreamConsumer:
    """Consumer ``name`` of the ``workers`` group on ``stream``; ``on_trimmed`` is told
    the id of each entry found trimmed away while pending here."""

    def __init__(
        self, client: redis.Redis, stream: str, name: str, *, max_deliveries: int,
        on_trimmed: Callable[[str], None] | None = None,
    ) -> None:
        self.client = client
        self.stream = stream
        self.name = name
        self.max_deliveries = max_deliveries
        self.on_trimmed = on_trimmed
        self.metrics = Metrics(client)
        self._touch = client.register_script(_TOUCH)
        self._claim_others = client.register_script(_CLAIM_OTHERS)
        self._read_new_while = client.register_script(_READ_NEW_WHILE)
        ensure_group(client, stream)

    def read_new(self, *, block_ms: int | None, count: int = 1) -> list[Delivery]:
        """Entries never delivered before (blocks up to ``block_ms``; None: do not block)."""
        reply = self.client.xreadgroup(
            GROUP, self.name, {self.stream: ">"}, count=count, block=block_ms
        )
        return [
            Delivery(self.stream, entry_id.decode(), _fields(raw))
            for _stream, entries in reply or []
            for entry_id, raw in entries
        ]

    def read_new_while(self, key: str, value: str, count: int = 1) -> list[Delivery] | None:
        """Entries never delivered before (not blocking), read only while Redis key
        ``key`` holds ``value``, in one step: None when it does not. A reader under a
        lease that lapsed while it paused can then not strand entries in its own pending
        list after another reader took the stream over."""
        reply = self._read_new_while(keys=[self.stream, key], args=[value, GROUP, self.name, count])
        if reply == 0:
            return None
        return [
            Delivery(self.stream, entry_id.decode(), _fields(_pairs(raw)))
            for entry_id, raw in reply
        ]

    def read_own_pending(self, count: int = 100) -> list[Delivery]:
        """Entries delivered to this consumer and not acked, oldest first (reading them
        does not count a delivery); entries trimmed away meanwhile are acked, reported to
        ``on_trimmed`` and skipped."""
        rows = self.client.xpending_range(self.stream, GROUP, "-", "+", count, self.name)
        found = []
        for row in rows:
            entry_id = row["message_id"].decode()
            entries = self.client.xrange(self.stream, entry_id, entry_id, count=1)
            delivery = Delivery(
                self.stream,
                entry_id,
                _fields(entries[0][1] if entries else None),
                int(row["times_delivered"]),
            )
            if delivery.fields:
                found.append(delivery)
                continue
            self.done(delivery)
            if self.on_trimmed is not None:
                self.on_trimmed(entry_id)
        return found

    def claim_idle(self, min_idle_ms: int, count: int | None = 10) -> int:
        """Take over entries pending longer than ``min_idle_ms`` at any consumer (each
        counts one more delivery): up to ``count``, or all of them when None. Returns how
        many were taken (XCLAIM re-checks the idle time, so two claimers never both win)."""
        rows = self.client.xpending_range(
            self.stream, GROUP, "-", "+", count or 10_000, idle=min_idle_ms or None
        )
        claimed = 0
        for row in rows:
            won = self.client.xclaim(
                self.stream,
                GROUP,
                self.name,
                min_idle_ms,
                [row["message_id"]],
                retrycount=int(row["times_delivered"]) + 1,
                justid=True,
            )
            claimed += len(won)
        if claimed and min_idle_ms > 0:
            self.metrics.inc("redeliveries_total", claimed)
        return claimed

    def claim_others(self, count: int = 100) -> list[Delivery]:
        """Entries pending at other consumers, taken over whatever their idle time (each
        counts a delivery) and returned with their fields, oldest first. Only for a
        stream one consumer reads at a time (a device's, under its lease): there any
        entry pending elsewhere was stranded by a reader that lost the right to it."""
        claimed = int(self._claim_others(keys=[self.stream], args=[GROUP, self.name, count]))
        if not claimed:
            return []
        self.metrics.inc("redeliveries_total", claimed)
        return self.read_own_pending(count)

    def reclaim(self, min_idle_ms: int, count: int = 10) -> list[Delivery]:
        """Claim idle entries of other consumers and return them with their fields."""
        if not self.claim_idle(min_idle_ms, count):
            return []
        return self.read_own_pending(count)

    def retry(self, delivery: Delivery) -> None:
        """Deliver the entry to this consumer again (counts a delivery)."""
        delivery.deliveries += 1
        self.client.xclaim(
            self.stream,
            GROUP,
            self.name,
            0,
            [delivery.entry_id],
            retrycount=delivery.deliveries,
            justid=True,
        )

    def touch(self, delivery: Delivery) -> bool:
        """Reset the entry's idle time (no delivery counted) so that a long job is not
        reclaimed from this live consumer; only while this consumer owns it (a plain
        XCLAIM would take back an entry another worker reclaimed meanwhile, and both would
        run it). Returns whether it still owns the entry (not when the entry went with
        its group: a Redis restarted without its data)."""
        try:
            return bool(self._touch(keys=[self.stream], args=[GROUP, self.name, delivery.entry_id]))
        except redis.exceptions.ResponseError as exc:
            if is_missing_group(exc):  # gone with its group (Redis lost its data)
                return False
            raise

    def done(self, delivery: Delivery) -> None:
        """Acknowledge and delete the entry (call only after its result is durable)."""
        pipe = self.client.pipeline(transaction=True)
        pipe.xack(self.stream, GROUP, delivery.entry_id)
        pipe.xdel(self.stream, delivery.entry_id)
        pipe.execute()

    def give_back(self, delivery: Delivery) -> None:
        """Return unfinished work: re-append the entry as new and drop this delivery."""
        pipe = self.client.pipeline(transaction=True)
        pipe.xadd(self.stream, delivery.fields)
        pipe.xack(self.stream, GROUP, delivery.entry_id)
        pipe.xdel(self.stream, delivery.entry_id)
        pipe.execute()

    def dead_letter(self, delivery: Delivery, code: str, message: str, **about: str) -> None:
        """Move the entry to the dead-letter stream with its error (payload not copied)."""
        record = {
            "stream": self.stream,
            "entry": delivery.entry_id,
            "deliveries": str(delivery.deliveries),
            "code": code,
            "message": message,
            "ts_ns": str(time.time_ns()),
            "consumer": self.name,
            **about,
        }
        pipe = self.client.pipeline(transaction=True)
        pipe.xadd(DEAD_LETTER_STREAM, record, maxlen=DEAD_LETTER_MAXLEN, approximate=True)
        pipe.xack(self.stream, GROUP, delivery.entry_id)
        pipe.xdel(self.stream, delivery.entry_id)
        self.metrics.inc("dead_letters_total", pipe=pipe)
        pipe.execute()
