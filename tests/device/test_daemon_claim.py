"""Tests of device/daemon_claim.py: one daemon per device id, on a real redis-server."""

from __future__ import annotations

from pathlib import Path

import pytest
import redis

from device.daemon import DaemonConfig, DeviceDaemon
from device.daemon_claim import CLAIM_TTL_MS, DaemonClaim, DeviceTakenError
from tests.device.conftest import wait_for
from worker.redis_keys import daemon_key


def test_a_second_daemon_under_one_device_id_is_refused_naming_the_first(
        client: redis.Redis) -> None:
    first, second = DaemonClaim(client, "cam1"), DaemonClaim(client, "cam1")
    first.take()
    with pytest.raises(DeviceTakenError, match=r"already has a daemon \(") as refused:
        second.take(wait_s=0.2)
    assert first.owner in refused.value.message and "--device-id" in refused.value.message
    assert DaemonClaim(client, "cam2").renew()  # another device is free
    first.release()
    second.take(wait_s=0.2)


def test_a_killed_daemons_claim_expires_and_a_restarted_one_takes_it(
        client: redis.Redis) -> None:
    DaemonClaim(client, "cam1").take()  # never renewed: its process was killed
    assert 0 < client.pttl(daemon_key("cam1")) <= CLAIM_TTL_MS
    DaemonClaim(client, "cam1").take()  # waits for the expiry


def test_a_running_daemon_keeps_its_claim_and_drops_it_when_stopped(
        client: redis.Redis, tmp_path: Path) -> None:
    """Two daemons under one id wrote one health hash in turn, split the commands between
    the cameras and dropped one camera's frames as stale, without a word."""
    config = DaemonConfig(port=str(tmp_path / "none"), device="cam1", backoff_max_s=0.2)
    running = DeviceDaemon(config, client)
    running.claim.take()
    running.start()
    try:
        assert wait_for(lambda: client.exists(daemon_key("cam1")), 5)
        with pytest.raises(DeviceTakenError):
            DeviceDaemon(config, client).claim.take(wait_s=CLAIM_TTL_MS / 1000 + 0.5)
    finally:
        running.stop()
    assert not client.exists(daemon_key("cam1"))
