"""Tests of device/daemon_claim.py: one daemon per device id, on a real redis-server."""

from __future__ import annotations

from pathlib import Path

import pytest
import redis

from device.daemon import DaemonConfig, DeviceDaemon
from device.daemon_claim import CLAIM_TTL_MS, DaemonClaim, DeviceTakenError
from device.sim_link import PtyEndpoint
from tests.device.conftest import health, newest_sequence, stream_frames, wait_for, wire
from worker.embedded_redis import EmbeddedRedis
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


def test_of_two_daemons_started_while_redis_is_down_one_streams_and_one_stops(
        client: redis.Redis, redis_server: EmbeddedRedis, tmp_path: Path) -> None:
    """Both skipped the claim while Redis was down, and both streamed once it was back:
    two cameras' frames on one stream, one health hash written in turn. The first to
    reach Redis takes the device; the other keeps its frames unpublished, waits the
    claim's TTL (a killed daemon's claim lapses in that time) and stops saying who holds
    the device, without touching the first one's stream, health or commands."""
    redis_server.stop()
    cameras = [PtyEndpoint(tmp_path / f"scamp5-{n}") for n in range(2)]
    daemons = [DeviceDaemon(DaemonConfig(port=camera.url, device="cam1", backoff_max_s=0.2),
                            client) for camera in cameras]
    try:
        for daemon in daemons:
            daemon.start()
        assert wait_for(lambda: all(d.health.state == "connected" for d in daemons), 30)
        for first, camera in zip((0, 100), cameras, strict=True):
            camera.write(wire(first, first + 1))
        assert wait_for(lambda: all(d.health.counts["dropped_redis_unavailable"] == 2
                                    for d in daemons), 30)
        redis_server.start()
        assert wait_for(lambda: client.exists(daemon_key("cam1")), 30)
        for first, camera in zip((2, 102), cameras, strict=True):
            camera.write(wire(first, first + 1))
        assert wait_for(lambda: any(not d._thread.is_alive() for d in daemons), 30)
        loser, winner = sorted(daemons, key=lambda d: d._thread.is_alive())
        assert winner._thread.is_alive()
        assert isinstance(loser.failure, DeviceTakenError)
        assert f"already has a daemon ({winner.claim.owner}" in loser.failure.message
        camera = cameras[daemons.index(winner)]
        base = 0 if winner is daemons[0] else 100
        camera.write(wire(base + 4))
        assert wait_for(lambda: newest_sequence(client, "cam1") == base + 4, 30)
        assert {f.sequence - base for f in stream_frames(client, "cam1")} <= {2, 3, 4}
        assert health(client, "cam1")["port"] == camera.url
        assert client.get(daemon_key("cam1")) == winner.claim.owner.encode()
    finally:
        for daemon in daemons:
            daemon.stop()
        for camera in cameras:
            camera.close()
