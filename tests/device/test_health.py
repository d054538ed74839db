"""Tests of device/health.py: the daemon's counters and the hash it publishes."""

from __future__ import annotations

import json
from collections import Counter

import pytest

from device.health import (
    ALL_DROP_CAUSES,
    COUNTER_LAP,
    MAX_MISSING_PER_GAP,
    DeviceHealth,
    unwrap_sequence,
)
from device.link_parser import DROP_CAUSES


def test_fields_carry_counters_gauges_and_the_port_error() -> None:
    health = DeviceHealth("cam1", "/dev/ttyACM0")
    health.port_error = "could not open port"
    health.add("frames_ok", 3)
    health.frame_received(41, {"encoding": "mantissa"})
    fields = health.to_fields()
    assert fields["state"] == "connecting" and fields["port_error"] == "could not open port"
    assert fields["crash"] == ""  # a crashed predecessor's error is not this daemon's
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


@pytest.mark.parametrize(("sequence", "expected", "host"), [
    (0, COUNTER_LAP, COUNTER_LAP),  # 2^32 - 1, then the wrap: the next frame
    (2, COUNTER_LAP - 1, COUNTER_LAP + 2),  # frames lost across the wrap
    (5, COUNTER_LAP + 3, COUNTER_LAP + 5),  # later in the second lap
    (COUNTER_LAP + 5, COUNTER_LAP + 3, COUNTER_LAP + 5),  # already unwrapped
    (0, 12, 0),  # a counter that restarted: a reset
    (0, COUNTER_LAP + 100, 0),  # one that restarted in the second lap
    (MAX_MISSING_PER_GAP + 1, COUNTER_LAP, MAX_MISSING_PER_GAP + 1),  # too far: a jump
    (2**40, 5, 2**40),  # a 64-bit counter is taken as it is
])
def test_a_wrapped_32_bit_counter_is_numbered_on_and_a_reset_is_not(
        sequence: int, expected: int, host: int) -> None:
    assert unwrap_sequence(sequence, expected) == host


def test_a_wrap_is_no_gap_and_frames_lost_across_it_are_missing() -> None:
    health = DeviceHealth("cam1", "loop://")
    health.sequence_gap(COUNTER_LAP, 0)
    assert (health.counts["sequence_gaps"], health.counts["frames_missing"]) == (0, 0)
    health.sequence_gap(COUNTER_LAP - 1, 2)
    assert (health.counts["sequence_gaps"], health.counts["frames_missing"]) == (1, 3)
