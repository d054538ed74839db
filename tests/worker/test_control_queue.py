"""Tests of worker/control_queue.py: commands wait for the daemon, none is trimmed unread."""

from __future__ import annotations

import pytest
import redis

from device.commands import FrameRateCommand, command_fields
from device.health import DeviceHealth
from tests.device.conftest import Camera, poll_control
from worker.control_queue import ControlBacklogError, queue_command
from worker.device_registry import DeviceNotFoundError
from worker.redis_keys import DEVICES_SET, control_stream


@pytest.fixture(autouse=True)
def registered(client: redis.Redis) -> None:
    """cam0 is registered, as its daemon's first health write or frame does."""
    client.sadd(DEVICES_SET, "cam0")


def fields(fps: float) -> dict[str, str]:
    return command_fields(FrameRateCommand(command="set_frame_rate", fps=fps))


def test_a_command_is_appended_and_its_id_returned(client: redis.Redis) -> None:
    entry = queue_command(client, "cam0", fields(5.0))
    assert [as_id for as_id, _ in client.xrange(control_stream("cam0"))] == [entry.encode()]


def test_past_the_backlog_a_command_is_refused_and_none_is_lost(client: redis.Redis) -> None:
    """No daemon reads: the stream's bound (4) would have trimmed accepted commands."""
    for fps in range(1, 4):
        queue_command(client, "cam0", fields(float(fps)), backlog=3, maxlen=4)
    with pytest.raises(ControlBacklogError, match="3 commands already wait") as refused:
        queue_command(client, "cam0", fields(9.0), backlog=3, maxlen=4)
    assert refused.value.http_status == 503
    assert client.xlen(control_stream("cam0")) == 3


def test_once_the_daemon_read_them_more_are_queued_and_reach_it(client: redis.Redis) -> None:
    camera = Camera()
    publisher = camera.publisher_for(client, DeviceHealth("cam0", "loop://"))
    poll_control(publisher)  # the device's place: commands after now reach its daemons
    for fps in range(1, 4):
        queue_command(client, "cam0", fields(float(fps)), backlog=3, maxlen=4)
    poll_control(publisher)
    for fps in range(4, 7):
        queue_command(client, "cam0", fields(float(fps)), backlog=3, maxlen=4)
    poll_control(publisher)
    assert [getattr(c, "fps", None) for c in camera.seen] == [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]


def test_a_command_for_a_device_not_registered_is_refused(client: redis.Redis) -> None:
    """A device forgotten (or never registered) gets no command: checked in the step that
    appends it, so a forget between the API's look at the device and the append leaves
    no stream behind (its next daemon would have skipped the command)."""
    client.srem(DEVICES_SET, "cam0")
    with pytest.raises(DeviceNotFoundError, match="no device 'cam0'"):
        queue_command(client, "cam0", fields(5.0))
    assert client.exists(control_stream("cam0")) == 0
