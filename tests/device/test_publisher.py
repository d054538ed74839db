"""Tests of device/publisher.py: frames reach the stream; a full stream's evictions are counted."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import redis

from device.commands import Command, FrameRateCommand, command_fields
from device.health import DeviceHealth
from device.publisher import FramePublisher
from models.formation import SensorParams
from tests.device.conftest import Camera, poll_control
from worker.embedded_redis import connect
from worker.frame_message import FrameMessage
from worker.redis_keys import DEVICES_SET, control_stream, frame_stream, health_key


def message(sequence: int, discont: bool = False) -> FrameMessage:
    codes = np.full((4, 4), sequence % 256, np.uint8)
    return FrameMessage("cam0", sequence, sequence * 1000, codes, SensorParams(), discont)


def test_full_stream_evicts_the_oldest_and_counts_them(client: redis.Redis) -> None:
    health = DeviceHealth("cam0", "loop://")
    publisher = FramePublisher(client, "cam0", health, lambda *_: True, frames_maxlen=3)
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
    delivered: the API accepted it, so a restart must not lose it."""
    health = DeviceHealth("cam0", "loop://")
    camera = Camera()
    first = camera.publisher_for(client, health)
    poll_control(first)  # a device's first daemon skips older commands
    send_frame_rate(client, 5.0)
    poll_control(first)
    send_frame_rate(client, 7.0)  # while no daemon runs
    poll_control(camera.publisher_for(client, health))
    assert [getattr(command, "fps", None) for command in camera.seen] == [5.0, 7.0]


def test_a_command_sent_once_the_daemon_shows_up_reaches_the_camera(
        client: redis.Redis, monkeypatch: pytest.MonkeyPatch) -> None:
    """A client waits for the device's health hash, then sends a command: it arrives
    after the first health write, before that housekeeping reads the control stream.
    The first daemon's start was fixed before the daemon showed up, so the command is
    forwarded (it was skipped as 'older' when the start was fixed at the first read)."""
    health = DeviceHealth("cam0", "loop://")
    camera = Camera()
    publisher = camera.publisher_for(client, health)
    read_control = publisher._read_control

    def sent_on_seeing_the_health() -> None:
        assert client.exists(health_key("cam0"))
        send_frame_rate(client, 5.0)
        read_control()

    monkeypatch.setattr(publisher, "_read_control", sent_on_seeing_the_health)
    publisher._housekeeping()
    assert [getattr(command, "fps", None) for command in camera.seen] == [5.0]


def test_a_daemon_that_handled_no_command_yet_keeps_its_place(client: redis.Redis) -> None:
    """The first daemon's starting point is the device's cursor from its first read: a
    command sent while it was down after handling none still reaches the next daemon."""
    health = DeviceHealth("cam0", "loop://")
    camera = Camera()
    poll_control(camera.publisher_for(client, health))
    send_frame_rate(client, 7.0)  # while no daemon runs
    poll_control(camera.publisher_for(client, health))
    assert [getattr(command, "fps", None) for command in camera.seen] == [7.0]


def test_a_command_taken_but_not_delivered_is_handed_to_the_next_daemon(
        client: redis.Redis) -> None:
    """The camera was away: the daemon took the command, could not send it, and stopped.
    The cursor had moved past it when taken, so no daemon ever sent it."""
    health = DeviceHealth("cam0", "loop://")
    taken: list[str] = []
    away = FramePublisher(client, "cam0", health, lambda entry, _: taken.append(entry) or True)
    poll_control(away)
    send_frame_rate(client, 5.0)
    poll_control(away)
    assert len(taken) == 1  # taken, never delivered
    camera = Camera()
    poll_control(camera.publisher_for(client, health))
    assert [getattr(command, "fps", None) for command in camera.seen] == [5.0]


def test_a_full_outbox_leaves_commands_in_redis_until_there_is_room(
        client: redis.Redis) -> None:
    health = DeviceHealth("cam0", "loop://")
    room = [0]
    handed: list[str] = []

    def take(entry_id: str, _: Command | None) -> bool:
        if not room[0]:
            return False
        room[0] -= 1
        handed.append(entry_id)
        return True

    publisher = FramePublisher(client, "cam0", health, take)
    poll_control(publisher)
    for fps in (1.0, 2.0, 3.0):
        send_frame_rate(client, fps)
    poll_control(publisher)
    room[0] = 2
    poll_control(publisher)
    room[0] = 5
    poll_control(publisher)
    assert handed == [entry.decode() for entry, _ in client.xrange(control_stream("cam0"))]


def published(client: redis.Redis) -> list[tuple[int, bool]]:
    """(sequence, discont) of each frame on the stream, oldest first."""
    return [(int(fields[b"seq"]), fields.get(b"discont", b"0") not in (b"0", b""))
            for _, fields in client.xrange(frame_stream("cam0"))]


def test_after_a_full_queue_drops_a_frame_the_next_one_queued_is_the_discontinuity(
        client: redis.Redis) -> None:
    """Frames queued before the drop still follow their predecessors; the first frame
    queued after it (here the camera restarted its counter) carries discont, so the
    worker does not discard it and the ones after as stale."""
    health = DeviceHealth("cam0", "loop://")
    publisher = FramePublisher(client, "cam0", health, lambda *_: True, queue_size=4)
    for sequence in (100, 101, 102, 103):
        publisher.offer(message(sequence))
    publisher.offer(message(0, discont=True))  # dropped: the queue is full
    publisher.start()
    publisher.stop()
    publisher.offer(message(1))
    publisher.offer(message(2))
    publisher.start()
    publisher.stop()
    assert published(client) == [(100, False), (101, False), (102, False), (103, False),
                                 (1, True), (2, False)]
    assert health.counts["dropped_queue_full"] == 1


def test_a_control_entry_that_is_not_text_is_refused_and_publishing_goes_on(
        client: redis.Redis) -> None:
    health = DeviceHealth("cam0", "loop://")
    camera = Camera()
    publisher = camera.publisher_for(client, health)
    poll_control(publisher)
    client.xadd(control_stream("cam0"), {"command": b"st\xffart"})
    send_frame_rate(client, 5.0)
    poll_control(publisher)
    assert [getattr(command, "fps", None) for command in camera.seen] == [5.0]
    assert health.counts["control_rejected"] == 1
    publisher.start()
    publisher.offer(message(7))
    publisher.stop()
    assert published(client) == [(7, False)]


def test_frames_dropped_while_redis_is_away_are_warned_of_once(
        caplog: pytest.LogCaptureFixture) -> None:
    """They were counted without a log line: an operator saw nothing of 33 lost frames."""
    away = connect("redis://127.0.0.1:1", timeout_s=0.2)
    health = DeviceHealth("cam0", "loop://")
    publisher = FramePublisher(away, "cam0", health, lambda *_: True)
    with caplog.at_level(logging.WARNING, logger="device.publisher"):
        for sequence in range(5):
            publisher._publish(message(sequence))
            publisher._retry_at = 0.0  # try Redis again for each frame
    assert health.counts["dropped_redis_unavailable"] == 5
    warnings = [r.getMessage() for r in caplog.records if r.name == "device.publisher"]
    assert len(warnings) == 1 and "dropped_redis_unavailable" in warnings[0]


def test_frames_dropped_while_redis_is_full_are_counted_as_such(
        client: redis.Redis, caplog: pytest.LogCaptureFixture) -> None:
    """Redis at its maxmemory (noeviction) answers but refuses writes. Before, its
    dropped frames counted as ``redis_unavailable`` and the warning said they were
    dropped "until it answers", though it answered all along: an operator looked for a
    network fault instead of raising maxmemory."""
    health = DeviceHealth("cam0", "loop://")
    publisher = FramePublisher(client, "cam0", health, lambda *_: True)
    client.config_set("maxmemory", 1)
    with caplog.at_level(logging.WARNING, logger="device.publisher"):
        for sequence in range(3):
            publisher._publish(message(sequence))
            publisher._retry_at = 0.0  # try Redis again for each frame
    assert health.counts["dropped_redis_full"] == 3
    assert health.counts["dropped_redis_unavailable"] == 0
    [warning] = [r.getMessage() for r in caplog.records if r.name == "device.publisher"]
    assert "Redis is full" in warning and "(dropped_redis_full) until it has room" in warning
    client.config_set("maxmemory", 0)
    publisher._retry_at = 0.0
    publisher._publish(message(3))
    assert published(client) == [(3, True)]  # after the drops: a discontinuity


def test_a_drop_event_names_its_causes(client: redis.Redis) -> None:
    health = DeviceHealth("cam0", "loop://")
    publisher = FramePublisher(client, "cam0", health, lambda *_: True)
    health.add("dropped_redis_unavailable", 33)
    health.add("dropped_bad_crc", 2)
    [event] = publisher._new_events()
    assert event["type"] == "drop" and event["new"] == "35"
    assert set(event["causes"].split(",")) == {"redis_unavailable:33", "bad_crc:2"}
    health.add("dropped_bad_crc", 1)
    assert publisher._new_events()[0]["causes"] == "bad_crc:1"
