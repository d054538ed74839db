"""Lease: one owner per device stream, renewal, expiry and takeover."""

from __future__ import annotations

import redis

from tests.worker.conftest import wait_for
from worker.lease import Lease
from worker.redis_keys import lease_key


def test_single_owner_until_release(client: redis.Redis) -> None:
    first, second = Lease(client, "w1", 5000), Lease(client, "w2", 5000)
    assert first.acquire("cam")
    assert first.acquire("cam")
    assert not second.acquire("cam") and not second.renew("cam")
    assert first.holder("cam") == "w1"
    second.release("cam")
    assert first.holder("cam") == "w1"
    first.release("cam")
    assert first.holder("cam") is None
    assert second.acquire("cam") and second.holder("cam") == "w2"


def test_lapsed_lease_is_taken_over(client: redis.Redis) -> None:
    first, second = Lease(client, "w1", 5000), Lease(client, "w2", 5000)
    assert first.acquire("cam")
    client.pexpire(lease_key("cam"), 1000)
    assert first.renew("cam") and client.pttl(lease_key("cam")) > 1000  # renewed to the full term
    assert not second.acquire("cam")
    client.pexpire(lease_key("cam"), 1)  # the holder stalled past its term
    assert wait_for(lambda: second.acquire("cam"), 5)
    assert not first.renew("cam")
    assert second.holder("cam") == "w2"
