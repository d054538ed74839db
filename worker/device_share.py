"""How many device streams a worker keeps, and which one it hands over beyond its share.

Devices spread over the live device workers: a worker that owns more than its fair
share hands one over (:class:`worker.device_consumer.DeviceConsumer`). Only *active*
devices count, those whose frame stream received a frame within :data:`ACTIVE_MS`:
a camera that stopped long ago costs nothing to own, and counting it made a worker
that restarted beside a dead worker's fresh heartbeat give away live cameras, which
then waited several lease periods for an owner (the third audit measured a 20 s
stall). Of the active devices beyond the share, the one that received its last frame
longest ago is handed over: the least busy stream pauses.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping

import redis

from worker.redis_keys import frame_stream

#: A device whose newest frame is older than this (ms, Redis clock) is idle.
ACTIVE_MS = 30_000


def frame_clock(client: redis.Redis, devices: Iterable[str]) -> tuple[dict[str, int], int]:
    """Each device's newest frame time (ms, Redis clock: the ms part of its frame stream's
    last entry id, kept by Redis after the entries are deleted; 0 for a device with no
    stream), and Redis's clock now (ms), in one round trip."""
    names = list(devices)
    pipe = client.pipeline(transaction=False)
    for device in names:
        pipe.xinfo_stream(frame_stream(device))
    pipe.time()
    *infos, (seconds, micros) = pipe.execute(raise_on_error=False)
    newest = {}
    for device, info in zip(names, infos, strict=True):
        if isinstance(info, dict):
            last = info.get("last-generated-id", b"0-0")
            text = last.decode() if isinstance(last, bytes) else str(last)
            newest[device] = int(text.split("-")[0])
        else:
            newest[device] = 0
    return newest, int(seconds) * 1000 + int(micros) // 1000


def device_to_hand_over(
    owned: Iterable[str], newest: Mapping[str, int], now_ms: int, workers: int
) -> str | None:
    """The owned device to hand over, or None: when this worker owns more active devices
    than ``ceil(active devices / workers)``, the one whose newest frame is oldest."""
    active = {device for device, ms in newest.items() if now_ms - ms < ACTIVE_MS}
    mine = sorted(device for device in owned if device in active)
    if len(mine) <= math.ceil(len(active) / max(workers, 1)):
        return None
    return min(mine, key=lambda device: (newest[device], device))
