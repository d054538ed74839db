"""Forgetting a device: refused while anything still depends on it, then every key goes."""

from __future__ import annotations

import time

import numpy as np
import pytest
import redis
from redis.client import Pipeline

from models.formation import SensorParams
from worker.device_registry import (
    DeviceBusyError,
    DeviceNotFoundError,
    device_keys,
    forget_device,
)
from worker.embedded_redis import EmbeddedRedis
from worker.frame_message import FrameMessage
from worker.metrics import Metrics, read_metrics
from worker.queue import publish_frame
from worker.recordings import request_stop, start_recording
from worker.redis_keys import DEVICES_SET, events_stream, health_key, recording_key

PARAMS = SensorParams(encoding="modulo", bits=8)
CODES = np.arange(64, dtype=np.uint8).reshape(8, 8)


def _register(client: redis.Redis, device: str, *, reported_s_ago: float, frames: int) -> None:
    """What a daemon leaves behind: health, queued frames, an event."""
    updated = time.time_ns() - int(reported_s_ago * 1e9)
    client.hset(health_key(device), mapping={"state": "connected", "updated_ns": updated})
    client.sadd(DEVICES_SET, device)
    for seq in range(frames):
        publish_frame(client, FrameMessage(device, seq, seq, CODES, PARAMS), maxlen=16)
    client.xadd(events_stream(device), {"type": "frame"})


def test_forgets_a_silent_device_and_all_its_keys(client: redis.Redis) -> None:
    _register(client, "gone", reported_s_ago=60, frames=0)
    _register(client, "kept", reported_s_ago=60, frames=0)
    assert forget_device(client, "gone", silent_after_s=10) == 0
    assert client.smembers(DEVICES_SET) == {b"kept"}
    assert client.exists(*device_keys("gone")) == 0
    assert client.exists(health_key("kept"), events_stream("kept")) == 2


def _device_series(client: redis.Redis) -> dict[str, list[str]]:
    """The devices each device-labelled counter has a series for."""
    return {
        family.name: [sample.labels["device"] for sample in family.samples]
        for family in read_metrics(client)
        if family.name.startswith("frames_")
    }


def test_a_forgotten_device_leaves_no_counter_series(client: redis.Redis) -> None:
    """A camera that came and went kept its frames_processed_total and
    frames_dropped_total series (fields of their Redis hashes) for good: the scrape grew
    by two series per device ever seen."""
    metrics = Metrics(client)
    for device in ("gone", "kept"):
        _register(client, device, reported_s_ago=60, frames=0)
        metrics.inc("frames_processed_total", 5, device=device)
        metrics.inc("frames_dropped_total", 2, device=device)
    forget_device(client, "gone", silent_after_s=10)
    assert _device_series(client) == {
        "frames_processed_total": ["kept"], "frames_dropped_total": ["kept"],
    }  # fmt: skip


def test_a_reporting_daemon_keeps_its_device(client: redis.Redis) -> None:
    _register(client, "live", reported_s_ago=1, frames=0)
    with pytest.raises(DeviceBusyError, match="reported 10 s ago or less") as error:
        forget_device(client, "live", silent_after_s=10)
    assert error.value.http_status == 409 and error.value.code == "device_busy"
    assert client.sismember(DEVICES_SET, "live")


@pytest.mark.parametrize("state", ["stopped", "crashed"])
def test_a_device_whose_daemon_said_it_ended_is_forgotten_at_once(
        client: redis.Redis, state: str) -> None:
    """A daemon that stopped on an unexpected error says ``crashed``: it had ended, yet
    its device was refused for 10 s as if it still reported ("stop it ... and retry")."""
    _register(client, "ended", reported_s_ago=1, frames=0)
    client.hset(health_key("ended"), "state", state)
    assert forget_device(client, "ended", silent_after_s=10) == 0
    assert client.exists(*device_keys("ended")) == 0


def test_undecoded_frames_are_kept_unless_discarded(client: redis.Redis) -> None:
    _register(client, "cam", reported_s_ago=60, frames=3)
    with pytest.raises(DeviceBusyError, match="3 frame"):
        forget_device(client, "cam", silent_after_s=10)
    assert client.sismember(DEVICES_SET, "cam")
    assert forget_device(client, "cam", silent_after_s=10, discard_frames=True) == 3
    assert client.exists(*device_keys("cam")) == 0


def test_a_running_recording_keeps_its_device(client: redis.Redis) -> None:
    """A recording keeps its device until its video job is made. While it records, the
    refusal says to stop it; once stopped, that it waits for a worker. Before, a stopped
    one said "is recording; stop it ... and retry" too: with no worker running, each
    stop changed nothing and the forget was refused again."""
    _register(client, "rec", reported_s_ago=60, frames=0)
    assert start_recording(client, "rec", decoder="itoh", options={}, max_frames=5)
    with pytest.raises(DeviceBusyError, match="is recording; stop it"):
        forget_device(client, "rec", silent_after_s=10)
    stopping = request_stop(client, "rec")
    with pytest.raises(DeviceBusyError) as refused:
        forget_device(client, "rec", silent_after_s=10)
    assert f"recording {stopping.id} was stopped and waits for" in refused.value.message
    assert "is a worker running" in refused.value.message
    assert "stop it" not in refused.value.message
    client.hset(recording_key("rec"), "state", "submitted")
    assert forget_device(client, "rec", silent_after_s=10) == 0


def test_a_device_without_health_can_be_forgotten(client: redis.Redis) -> None:
    client.sadd(DEVICES_SET, "orphan")
    assert forget_device(client, "orphan", silent_after_s=10) == 0
    assert not client.sismember(DEVICES_SET, "orphan")


def test_a_device_never_registered_is_not_found(client: redis.Redis) -> None:
    with pytest.raises(DeviceNotFoundError, match="no device 'nobody'") as error:
        forget_device(client, "nobody", silent_after_s=10)
    assert error.value.http_status == 404 and error.value.code == "not_found"


class _RacingClient(redis.Redis):
    """A client whose first read of ``rig1``'s health hash inside a transaction is
    followed, on the connection ``other``, by another caller forgetting the device (as a
    concurrent DELETE does)."""

    def __init__(self, url: str, other: redis.Redis) -> None:
        super().__init__(connection_pool=redis.ConnectionPool.from_url(url))
        self.other, self.raced = other, False

    def pipeline(self, transaction: bool = True, shard_hint: object = None) -> Pipeline:
        racing = self

        class ForgottenMidRead(Pipeline):
            def immediate_execute_command(self, *args: object, **options: object) -> object:
                reply = super().immediate_execute_command(*args, **options)
                read = args[0] in ("HGET", "HMGET") and args[1] == health_key("rig1")
                if read and not racing.raced:
                    racing.raced = True
                    assert forget_device(racing.other, "rig1", silent_after_s=10) == 0
                return reply

        return ForgottenMidRead(self.connection_pool, self.response_callbacks,
                                transaction, shard_hint)


def test_a_device_forgotten_meanwhile_is_not_found_rather_than_busy(
        client: redis.Redis, embedded: EmbeddedRedis) -> None:
    """Six concurrent DELETEs of a stopped device: one that read the health hash as
    another deleted it saw 'updated_ns' from before and no 'stopped' state after, and was
    refused as if its daemon reported (409); the others forgot it again (200)."""
    client.hset(health_key("rig1"), mapping={"state": "stopped", "updated_ns": time.time_ns()})
    client.sadd(DEVICES_SET, "rig1")
    racing = _RacingClient(embedded.url, client)
    try:
        with pytest.raises(DeviceNotFoundError):
            forget_device(racing, "rig1", silent_after_s=10)
    finally:
        racing.close()
    assert racing.raced and client.exists(*device_keys("rig1")) == 0
