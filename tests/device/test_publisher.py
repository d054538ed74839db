"""Tests of device/publisher.py: frames reach the stream; a full stream's evictions are counted."""

from __future__ import annotations

import numpy as np
import redis

from device.commands import Command, FrameRateCommand, command_fields
from device.health import DeviceHealth
from device.publisher import FramePublisher
from models.formation import SensorParams
from worker.frame_message import FrameMessage
from worker.redis_keys import DEVICES_SET, control_stream, frame_stream


def message(sequence: int) -> FrameMessage:
    codes = np.full((4, 4), sequence % 256, np.uint8)
    return FrameMessage("cam0", sequence, sequence * 1000, codes, SensorParams())


def test_full_stream_evicts_the_oldest_and_counts_them(client: redis.Redis) -> None:
    health = DeviceHealth("cam0", "loop://")
    publisher = FramePublisher(client, "cam0", health, lambda _: None, frames_maxlen=3)
    publisher.start()
    for sequence in range(10):
        publisher.offer(message(sequence))
    publisher.stop()
    entries = client.xrange(frame_stream("cam0"))
    assert [int(fields[b"seq"]) for _, fields in entries] == [7, 8, 9]
    assert health.counts["frames_ok"] == 10
    assert health.counts["dropped_stream_full"] == 7
    assert client.sismember(DEVICES_SET, "cam0")


def send_frame_rate(client: redis.Redis, fps: float) -> None:
    command = FrameRateCommand(command="set_frame_rate", fps=fps)
    client.xadd(control_stream("cam0"), command_fields(command))


def test_commands_sent_while_no_daemon_ran_reach_the_next_one(client: redis.Redis) -> None:
    """A daemon forwards what came after the last command any daemon of the device
    handled: the API accepted it, so a restart must not lose it."""
    health = DeviceHealth("cam0", "loop://")
    seen: list[Command] = []
    first = FramePublisher(client, "cam0", health, seen.append)
    first._read_control()  # a device's first daemon skips older commands
    send_frame_rate(client, 5.0)
    first._read_control()
    send_frame_rate(client, 7.0)  # while no daemon runs
    second = FramePublisher(client, "cam0", health, seen.append)
    second._read_control()
    second._read_control()
    assert [getattr(command, "fps", None) for command in seen] == [5.0, 7.0]
