"""Tests of device/health.py: the daemon's counters and the hash it publishes."""

from __future__ import annotations

import json
from collections import Counter

from device.health import ALL_DROP_CAUSES, DeviceHealth
from device.link_parser import DROP_CAUSES


def test_fields_carry_counters_gauges_and_the_port_error() -> None:
    health = DeviceHealth("cam1", "/dev/ttyACM0")
    health.port_error = "could not open port"
    health.add("frames_ok", 3)
    health.frame_received(41, {"encoding": "mantissa"})
    fields = health.to_fields()
    assert fields["state"] == "connecting" and fields["port_error"] == "could not open port"
    assert fields["frames_ok"] == "3" and fields["frames_received"] == "1"
    assert fields["last_sequence"] == "41" and json.loads(fields["settings"]) == {
        "encoding": "mantissa"
    }
    assert all(f"dropped_{cause}" in fields for cause in ALL_DROP_CAUSES)
    assert all(isinstance(value, str) for value in fields.values())


def test_parser_counts_add_to_those_before_a_reconnect() -> None:
    health = DeviceHealth("cam1", "loop://")
    cause = DROP_CAUSES[0]
    health.set_parser_counts(Counter({cause: 2}), 10, Counter({cause: 5, "garbage_bytes": 7}))
    health.add("dropped_queue_full")
    assert health.counts[f"dropped_{cause}"] == 7 and health.counts["garbage_bytes"] == 17
    assert health.dropped() == 8


def test_fps_needs_two_recent_arrivals() -> None:
    health = DeviceHealth("cam1", "loop://")
    assert health.fps == 0.0
    health.frame_received(0, {})
    assert health.fps == 0.0
