"""Tests of worker/device_share.py: a worker's share of the active devices."""

from __future__ import annotations

import redis
from hypothesis import given
from hypothesis import strategies as st

from worker.device_share import (
    ACTIVE_MS,
    device_to_hand_over,
    frame_clock,
)
from worker.redis_keys import frame_stream

NOW = 10_000_000


def test_idle_devices_do_not_count_and_a_live_camera_is_kept() -> None:
    """A worker restarted beside a dead worker's fresh heartbeat (2 workers counted)
    owns 16 devices of which one still streams: it keeps them all."""
    newest = {f"dead{i}": NOW - 10 * ACTIVE_MS for i in range(15)} | {"live": NOW - 50}
    assert device_to_hand_over(newest, newest, NOW, workers=2) is None


def test_beyond_the_share_the_least_recent_active_device_goes() -> None:
    newest = {"a": NOW - 100, "b": NOW - 5_000, "c": NOW - 10, "old": NOW - 2 * ACTIVE_MS}
    assert device_to_hand_over(newest, newest, NOW, workers=2) == "b"
    assert device_to_hand_over(["a", "c"], newest, NOW, workers=2) is None
    assert device_to_hand_over(newest, newest, NOW, workers=1) is None


@given(
    st.dictionaries(st.text("abcdef", min_size=1, max_size=3), st.integers(0, 3 * ACTIVE_MS)),
    st.integers(1, 5),
)
def test_after_handing_over_a_worker_is_within_its_share(ages: dict, workers: int) -> None:
    newest = {device: NOW - age for device, age in ages.items()}
    owned = set(newest)
    while (device := device_to_hand_over(owned, newest, NOW, workers)) is not None:
        assert device in owned and NOW - newest[device] < ACTIVE_MS
        owned.remove(device)
    active = sum(NOW - ms < ACTIVE_MS for ms in newest.values())
    assert sum(NOW - newest[d] < ACTIVE_MS for d in owned) <= -(-active // workers)


def test_newest_frame_times_come_from_the_streams(client: redis.Redis) -> None:
    client.xadd(frame_stream("old"), {"seq": "0"}, id="1000-0")
    entry = client.xadd(frame_stream("new"), {"seq": "0"})
    client.xdel(frame_stream("new"), entry)  # consumed frames are deleted: the id remains
    newest, now_ms = frame_clock(client, ["old", "new", "never"])
    assert newest["old"] == 1000 and newest["never"] == 0
    assert abs(newest["new"] - now_ms) < 5_000
    seconds, _micros = client.time()
    assert abs(now_ms - int(seconds) * 1000) < 5_000
