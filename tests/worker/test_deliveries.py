"""StreamConsumer: reclaiming a stopped consumer's entries, retries, dead letters, trims."""

from __future__ import annotations

import time

import redis

from worker.deliveries import StreamConsumer, entry_order, prune_consumers
from worker.metrics import read_metrics
from worker.queue import GROUP
from worker.redis_keys import DEAD_LETTER_STREAM


def consumer(client: redis.Redis, name: str) -> StreamConsumer:
    return StreamConsumer(client, "s", name, max_deliveries=3)


def test_read_done_removes_entry(client: redis.Redis) -> None:
    alice = consumer(client, "alice")
    client.xadd("s", {"n": "1"})
    [delivery] = alice.read_new(block_ms=None)
    assert delivery.fields == {"n": b"1"} and delivery.deliveries == 1
    alice.done(delivery)
    assert client.xlen("s") == 0 and client.xpending("s", GROUP)["pending"] == 0


def test_new_entries_are_read_only_while_the_key_holds_the_value(client: redis.Redis) -> None:
    """Read under a lease: nothing is read (or left pending) once another holds it."""
    alice = consumer(client, "alice")
    assert alice.read_new_while("lease", "alice") is None
    client.set("lease", "alice")
    assert alice.read_new_while("lease", "alice") == []
    first = client.xadd("s", {"n": "1", "codes": b"\x00\xff"}).decode()
    client.xadd("s", {"n": "2"})
    [delivery] = alice.read_new_while("lease", "alice", count=1)
    assert delivery.entry_id == first and delivery.fields == {"n": b"1", "codes": b"\x00\xff"}
    client.set("lease", "bob")
    assert alice.read_new_while("lease", "alice", count=5) is None
    assert client.xpending("s", GROUP)["pending"] == 1


def test_idle_entries_are_reclaimed_with_delivery_count(client: redis.Redis) -> None:
    alice, bob = consumer(client, "alice"), consumer(client, "bob")
    client.xadd("s", {"n": "1"})
    [first] = alice.read_new(block_ms=None)
    assert bob.reclaim(min_idle_ms=60_000) == []
    time.sleep(0.05)
    [again] = bob.reclaim(min_idle_ms=10)
    assert again.entry_id == first.entry_id and again.deliveries == 2
    bob.retry(again)
    [pending] = client.xpending_range("s", GROUP, "-", "+", 10)
    assert pending["consumer"] == b"bob" and pending["times_delivered"] == 3
    assert again.deliveries == 3
    redeliveries = {f.name: f for f in read_metrics(client)}["redeliveries_total"]
    assert redeliveries.samples[0].value == 1


def test_entries_pending_at_others_are_claimed_at_once_and_own_ones_left(
    client: redis.Redis,
) -> None:
    alice, bob = consumer(client, "alice"), consumer(client, "bob")
    for n in range(3):
        client.xadd("s", {"n": str(n)})
    alice.read_new(block_ms=None, count=2)
    [own] = bob.read_new(block_ms=None)
    assert [d.fields["n"] for d in bob.claim_others()] == [b"0", b"1", b"2"]
    rows = client.xpending_range("s", GROUP, "-", "+", 10)
    assert {row["consumer"] for row in rows} == {b"bob"}
    assert [row["times_delivered"] for row in rows] == [2, 2, 1]
    assert bob.claim_others() == [] and own.deliveries == 1


def test_dead_letter_keeps_error_not_payload(client: redis.Redis) -> None:
    alice = consumer(client, "alice")
    client.xadd("s", {"codes": b"\x00" * 100, "job": "j"})
    [delivery] = alice.read_new(block_ms=None)
    alice.dead_letter(delivery, "output_overflow", "too bright", job="j")
    [(_id, letter)] = client.xrange(DEAD_LETTER_STREAM)
    assert letter[b"code"] == b"output_overflow" and letter[b"job"] == b"j"
    assert b"codes" not in letter
    assert client.xlen("s") == 0 and client.xpending("s", GROUP)["pending"] == 0


def test_trimmed_pending_entries_are_acked(client: redis.Redis) -> None:
    alice, bob = consumer(client, "alice"), consumer(client, "bob")
    for n in range(3):
        client.xadd("s", {"n": str(n)})
    alice.read_new(block_ms=None, count=3)
    client.xtrim("s", maxlen=1, approximate=False)
    bob.claim_idle(0, count=None)
    [kept] = bob.read_own_pending()
    assert kept.fields == {"n": b"2"}
    assert client.xpending("s", GROUP)["pending"] == 1


def test_give_back_requeues_as_new_entry(client: redis.Redis) -> None:
    alice = consumer(client, "alice")
    client.xadd("s", {"n": "1"})
    [delivery] = alice.read_new(block_ms=None)
    alice.give_back(delivery)
    assert client.xpending("s", GROUP)["pending"] == 0 and client.xlen("s") == 1
    [again] = alice.read_new(block_ms=None)
    assert again.fields == {"n": b"1"} and again.entry_id != delivery.entry_id
    assert entry_order(again.entry_id) > entry_order(delivery.entry_id)


def test_entry_order() -> None:
    assert entry_order("10-2") > entry_order("9-99") > entry_order("9-1")


def idle_for_a_minute(client: redis.Redis, entry_id: str, owner: str) -> None:
    """Make a pending entry look idle for 60 s (XCLAIM IDLE, no delivery counted)."""
    client.xclaim("s", GROUP, owner, 0, [entry_id], idle=60_000, justid=True)


def test_a_touch_keeps_an_entry_idle_free_only_for_its_owner(client: redis.Redis) -> None:
    """A worker cut off from Redis longer than the claim period lost its entry to another;
    its heartbeat's touch must not take it back (both would run the job)."""
    alice, bob = consumer(client, "alice"), consumer(client, "bob")
    client.xadd("s", {"n": "1"})
    [delivery] = alice.read_new(block_ms=None)
    idle_for_a_minute(client, delivery.entry_id, "alice")
    assert alice.touch(delivery)
    assert bob.reclaim(min_idle_ms=30_000) == []  # the touch made it fresh again
    idle_for_a_minute(client, delivery.entry_id, "alice")
    [reclaimed] = bob.reclaim(min_idle_ms=30_000)
    assert not alice.touch(delivery)
    [pending] = client.xpending_range("s", GROUP, "-", "+", 1)
    assert pending["consumer"] == b"bob" and pending["times_delivered"] == 2
    assert bob.touch(reclaimed)
    alice.done(delivery)
    assert not bob.touch(reclaimed)


def test_an_entry_lost_with_redis_data_is_no_longer_owned(client: redis.Redis) -> None:
    """A Redis restarted without its data lost the stream and its group: the heartbeat's
    touch of a job in hand failed with NOGROUP, which ended the worker's heartbeat loop
    (and the worker), where the entry is simply no longer this consumer's."""
    alice = consumer(client, "alice")
    client.xadd("s", {"n": "1"})
    [delivery] = alice.read_new(block_ms=None)
    client.flushall()
    assert not alice.touch(delivery)
    client.xadd("s", {"n": "2"})  # the stream made again, without the group
    assert not alice.touch(delivery)


def consumer_names(client: redis.Redis, stream: str) -> set[str]:
    return {consumer["name"].decode() for consumer in client.xinfo_consumers(stream, GROUP)}


def test_consumers_not_kept_go_unless_an_entry_is_pending_at_them(client: redis.Redis) -> None:
    """Deleting a consumer drops its pending entries from the group: those never come back."""
    for name in ("gone-idle", "gone-busy", "kept"):
        StreamConsumer(client, "s", name, max_deliveries=3)
        client.xgroup_createconsumer("s", GROUP, name)
    client.xadd("s", {"n": "1"})
    (busy,) = StreamConsumer(client, "s", "gone-busy", max_deliveries=3).read_new(block_ms=None)
    assert prune_consumers(client, "s", lambda name: name == "kept") == 1
    assert consumer_names(client, "s") == {"gone-busy", "kept"}
    assert client.xpending_range("s", GROUP, "-", "+", 10)[0]["message_id"].decode() == (
        busy.entry_id
    )
    assert prune_consumers(client, "no-such-stream", lambda name: False) == 0
