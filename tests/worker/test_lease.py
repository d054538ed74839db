"""Lease: one owner per device stream, renewal, expiry and takeover."""

from __future__ import annotations

import time

import redis

from worker.lease import Lease


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
    first, second = Lease(client, "w1", 150), Lease(client, "w2", 150)
    assert first.acquire("cam")
    time.sleep(0.1)
    assert first.renew("cam")
    time.sleep(0.1)
    assert not second.acquire("cam")
    time.sleep(0.2)
    assert second.acquire("cam")
    assert not first.renew("cam")
    assert second.holder("cam") == "w2"
