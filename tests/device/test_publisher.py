"""Tests of device/publisher.py: frames reach the stream; a full stream's evictions are counted."""

from __future__ import annotations

import numpy as np
import redis

from device.health import DeviceHealth
from device.publisher import FramePublisher
from models.formation import SensorParams
from worker.frame_message import FrameMessage
from worker.redis_keys import DEVICES_SET, frame_stream


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
