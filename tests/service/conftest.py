"""Real parts for the API tests: a redis-server, uvicorn on 127.0.0.1, a worker, HTTP clients,
and a bare ASGI app under ``mcam api``'s uvicorn options for tests of its connection limits."""

from __future__ import annotations

import io
import select
import socket
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
import uvicorn
from fastapi import FastAPI

from models.formation import SensorParams, simulate
from models.frames import encode_frame
from models.hdr_io import encode_exr
from service.cli.api import uvicorn_options
from service.core.config import Settings
from service.main import create_app
from worker.embedded_redis import EmbeddedRedis
from worker.runner import Worker, WorkerConfig

FULL_KEY = "full-key-0123456789abcdef"
READ_KEY = "read-key-0123456789abcdef"
SUBMIT_KEY = "submit-key-0123456789abcdef"
PARAMS = SensorParams(encoding="mantissa", alpha=2.0, bits=8, gain=1.0)


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


@contextmanager
def serve(app: FastAPI, port: int = 0) -> Iterator[str]:
    """Run ``app`` under uvicorn on 127.0.0.1 in a thread; yields its base URL. ``port``
    0 takes a free one; a given port lets a test restart a server where its clients are."""
    listener = socket.socket()
    listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    listener.bind(("127.0.0.1", port))  # bound here and handed over: no other process takes it
    port = int(listener.getsockname()[1])
    server = uvicorn.Server(uvicorn.Config(app, log_level="warning"))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [listener]}, daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not server.started:
        if time.monotonic() > deadline or not thread.is_alive():
            raise RuntimeError("uvicorn did not start")
        time.sleep(0.02)
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(15)
        listener.close()


@contextmanager
def running_worker(settings: Settings) -> Iterator[Worker]:
    """A real worker (job consumers only) in a thread, on the settings' Redis and data dir."""
    assert settings.redis_url is not None
    worker = Worker(
        WorkerConfig(
            redis_url=settings.redis_url,
            data_dir=settings.data_dir,
            heartbeat_s=settings.heartbeat_s,
            devices=False,
        )
    )
    thread = threading.Thread(target=worker.run, daemon=True)
    thread.start()
    try:
        yield worker
    finally:
        worker.request_stop()
        thread.join(15)


@pytest.fixture
def redis_url(tmp_path: Path) -> Iterator[str]:
    with EmbeddedRedis(tmp_path / "redis-home") as url:
        yield url


def make_settings(tmp_path: Path, redis_url: str | None, **overrides: object) -> Settings:
    values: dict[str, object] = {
        "data_dir": tmp_path / "data",
        "redis_url": redis_url,
        "api_keys": f"{FULL_KEY},{READ_KEY}:read,{SUBMIT_KEY}:submit",
        "max_upload_bytes": 2_000_000,
        "max_pixels": 512 * 512,
        "max_video_samples": 2_000_000,
        "heartbeat_s": 0.5,
        "default_decoder": "itoh",
        "rate_limit_per_minute": 1_000_000,  # tests that poll must not be limited on slow CI
        **overrides,
    }
    return Settings(_env_file=None, **values)  # type: ignore[call-arg]


@pytest.fixture
def settings(tmp_path: Path, redis_url: str) -> Settings:
    return make_settings(tmp_path, redis_url)


@pytest.fixture
def api(settings: Settings) -> Iterator[str]:
    with serve(create_app(settings)) as url:
        yield url


@pytest.fixture
def worker(settings: Settings) -> Iterator[Worker]:
    with running_worker(settings) as running:
        yield running


@pytest.fixture
def client(api: str) -> Iterator[Callable[[str], httpx.Client]]:
    """``client(key)``: an HTTP client for the live API with that Bearer key."""
    opened: list[httpx.Client] = []

    def make(key: str = FULL_KEY) -> httpx.Client:
        headers = {"Authorization": f"Bearer {key}"} if key else {}
        opened.append(httpx.Client(base_url=api, headers=headers, timeout=60))
        return opened[-1]

    yield make
    for http in opened:
        http.close()


def scene(size: int = 64) -> np.ndarray:
    """A smooth HDR ramp (1e-2 .. 30 wrap units) with a bright disc: a few wraps."""
    y, x = np.mgrid[0:size, 0:size] / size
    values = 0.01 * np.power(3000.0, x) * (1 + 0.2 * y)
    disc = (x - 0.3) ** 2 + (y - 0.6) ** 2 < 0.02
    return np.where(disc, values * 4, values)


def exr_bytes(size: int = 64) -> bytes:
    return encode_exr(scene(size))


def frame_png(size: int = 64, params: SensorParams = PARAMS) -> tuple[bytes, np.ndarray]:
    """A wrapped frame as a PNG (params embedded) and its codes."""
    frame = simulate(scene(size), params)
    return encode_frame(frame.codes, frame.params, "png"), frame.codes


def npy_bytes(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, array)
    return buffer.getvalue()


def finished_job(http: httpx.Client, job_id: str, timeout_s: float = 120.0) -> dict:
    """The job's JSON once it succeeded, failed or was cancelled (polled every 0.1 s).

    A 503 (Redis too slow to answer on a loaded host) is retried, as a client would, after
    its Retry-After or a second, whichever is shorter; any other status than 200 fails the
    test with the answer's body."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        reply = http.get(f"/v1/jobs/{job_id}")
        if reply.status_code == 503:
            time.sleep(min(float(reply.headers["Retry-After"]), 1.0))
            continue
        assert reply.status_code == 200, reply.text
        job = reply.json()
        if job["state"] in ("succeeded", "failed", "cancelled"):
            return job
        time.sleep(0.1)
    raise AssertionError(f"job {job_id} did not finish in {timeout_s} s")


def read_response(sock: socket.socket) -> bytes:
    """One whole HTTP/1.1 response from ``sock`` (head and a Content-Length body), however
    the server split it into segments."""
    data = b""
    while b"\r\n\r\n" not in data:
        chunk = sock.recv(65536)
        assert chunk, f"the connection closed mid-response: {data!r}"
        data += chunk
    head, _, body = data.partition(b"\r\n\r\n")
    length = next((int(line.split(b":")[1]) for line in head.split(b"\r\n")
                   if line.lower().startswith(b"content-length:")), 0)
    while len(body) < length:
        chunk = sock.recv(65536)
        assert chunk, f"the connection closed mid-body: {data!r}"
        body += chunk
    return head + b"\r\n\r\n" + body


async def hello(scope: dict[str, Any], receive: Any, send: Any) -> None:
    """A minimal ASGI app: 200 'ok' to every HTTP request."""
    if scope["type"] != "http":
        return
    await send({"type": "http.response.start", "status": 200,
                "headers": [(b"content-type", b"text/plain"), (b"content-length", b"2")]})
    await send({"type": "http.response.body", "body": b"ok"})


@contextmanager
def listening(settings: Settings) -> Iterator[int]:
    """uvicorn with :func:`uvicorn_options` serving :func:`hello` in a thread; its port."""
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    options = uvicorn_options(settings) | {"log_level": "warning"}
    server = uvicorn.Server(uvicorn.Config(hello, **options))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [listener]}, daemon=True)
    thread.start()
    while not server.started:
        assert thread.is_alive(), "uvicorn did not start"
        time.sleep(0.02)
    try:
        yield int(listener.getsockname()[1])
    finally:
        server.should_exit = True
        thread.join(15)
        listener.close()


def status_of(port: int, request: bytes) -> tuple[int, socket.socket]:
    """Send ``request`` on a new connection; the reply's status code and the open socket."""
    sock = socket.create_connection(("127.0.0.1", port), timeout=10)
    sock.sendall(request)
    reply = read_response(sock)
    return int(reply.split(b" ", 2)[1]), sock


def nothing_to_read(sock: socket.socket) -> bool:
    """True while ``sock`` has no reply and is not closed: the server has not answered
    yet (a check of behaviour, not of time)."""
    return not select.select([sock], [], [], 0)[0]


GET = b"GET / HTTP/1.1\r\nHost: x\r\n\r\n"
