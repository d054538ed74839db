"""A live camera for the device API tests: a virtual SCAMP-5 on a real pty, the real daemon
and a real worker (device frames and jobs) on the test's Redis and data dir."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import redis

from device.daemon import DaemonConfig, DeviceDaemon
from device.sim_link import PtyEndpoint
from device.simulator import CameraSettings, VirtualScamp5
from service.core.config import Settings
from tests.device.conftest import start_streaming
from worker.embedded_redis import connect
from worker.redis_keys import DEVICES_SET, health_key
from worker.runner import Worker, WorkerConfig


@contextmanager
def live_camera(settings: Settings, tmp_path: Path, *, fps: float, seed: int,
                max_frames: int | None = None, history: int = 0) -> Iterator[VirtualScamp5]:
    """Device ``cam1`` streaming 256 x 256 modulo frames at ``fps``, read by its daemon and
    decoded (itoh) by a worker; all stopped on exit."""
    assert settings.redis_url is not None
    cam = VirtualScamp5(PtyEndpoint(tmp_path / "scamp5"), settings=CameraSettings(fps=fps),
                        seed=seed, history=history, max_frames=max_frames)
    daemon = DeviceDaemon(DaemonConfig(port=cam.endpoint.url, device="cam1",
                                       data_dir=settings.data_dir),
                          connect(settings.redis_url, timeout_s=1.0))
    worker = Worker(WorkerConfig(redis_url=settings.redis_url, data_dir=settings.data_dir,
                                 decoder="itoh", heartbeat_s=0.5, lease_ms=2000))
    thread = threading.Thread(target=worker.run, daemon=True)
    start_streaming(daemon, cam)
    thread.start()
    try:
        yield cam
    finally:
        cam.stop()
        daemon.stop()
        worker.request_stop()
        thread.join(15)


def stopped_device(settings: Settings, device: str) -> redis.Redis:
    """Register ``device`` as a daemon that has just stopped cleanly leaves it (it may be
    forgotten at once); returns a client of the test's Redis."""
    assert settings.redis_url is not None
    client = connect(settings.redis_url)
    client.sadd(DEVICES_SET, device)
    client.hset(health_key(device), mapping={"state": "stopped", "updated_ns": str(time.time_ns())})
    return client
