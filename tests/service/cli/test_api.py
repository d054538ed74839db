"""Tests of ``mcam api``'s settings: flags override the environment, and are blamed as flags;
uvicorn's connection limits, on real sockets."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
import uvicorn
from pydantic import ValidationError

from models.errors import InvalidInputError
from service.api.header_timeout import timeout_response
from service.cli.api import settings_with, uvicorn_options
from service.core.config import Settings
from tests.service.conftest import free_port, read_response
from worker.embedded_redis import EmbeddedRedis

REPO = Path(__file__).resolve().parents[3]


def test_a_bad_flag_is_named_as_the_flag_not_the_environment() -> None:
    with pytest.raises(InvalidInputError, match=r"^--port 99999: .*65535"):
        settings_with(Settings(), port=99999)


def test_a_good_flag_overrides_and_a_bad_setting_stays_a_settings_error() -> None:
    assert settings_with(Settings(), port=8123, host=None).port == 8123
    with pytest.raises(ValidationError):
        settings_with(Settings.model_construct(port=99999), host="127.0.0.1")


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


GET = b"GET / HTTP/1.1\r\nHost: x\r\n\r\n"


def status_soon(port: int, wanted: int, within_s: float = 10.0) -> int:
    """The status of a GET on a new connection, asked again until it is ``wanted`` or
    ``within_s`` has passed (the server takes in other connections meanwhile)."""
    deadline = time.monotonic() + within_s
    while True:
        status, sock = status_of(port, GET)
        sock.close()
        if status == wanted or time.monotonic() > deadline:
            return status
        time.sleep(0.05)


def test_an_idle_keep_alive_connection_is_closed_after_the_setting() -> None:
    with listening(Settings(http_keep_alive_s=1)) as port:
        status, sock = status_of(port, GET)
        started = time.monotonic()
        with sock:
            assert status == 200 and sock.recv(1) == b""  # closed by the server
        assert time.monotonic() - started > 0.8  # after the setting, not at once


def test_requests_beyond_the_connection_limit_get_503() -> None:
    with listening(Settings(http_max_connections=3)) as port:
        stalled = [socket.create_connection(("127.0.0.1", port)) for _ in range(2)]
        for sock in stalled:
            sock.sendall(b"GET / HTTP/1.1\r\nHost: x\r\nX-Slow: ")  # headers never finish
        assert status_soon(port, 503) == 503
        for sock in stalled:
            sock.close()
        assert status_soon(port, 200) == 200


def test_headers_longer_than_the_setting_are_refused() -> None:
    with listening(Settings(http_max_header_bytes=1024)) as port:
        status, sock = status_of(port, b"GET / HTTP/1.1\r\nX-Big: " + b"a" * 2048)
        sock.close()
        assert status == 400


def test_a_request_head_that_never_finishes_gets_408_and_is_closed() -> None:
    """A slow-headers client held its connection for as long as it liked."""
    with listening(Settings(http_header_timeout_s=1)) as port:
        started = time.monotonic()
        status, sock = status_of(port, b"GET / HTTP/1.1\r\nHost: x\r\nX-Slow: ")
        with sock:
            assert status == 408 and sock.recv(1) == b""
        assert time.monotonic() - started > 0.8


def test_the_408_carries_the_headers_every_response_has() -> None:
    """It had only content-type, content-length and connection: no nosniff."""
    head = timeout_response(1.0).split(b"\r\n\r\n", 1)[0].decode().lower()
    assert "x-content-type-options: nosniff" in head.splitlines()


def test_a_connection_that_sends_nothing_is_closed_after_the_header_timeout() -> None:
    with listening(Settings(http_header_timeout_s=1)) as port:
        started = time.monotonic()
        with socket.create_connection(("127.0.0.1", port), timeout=10) as sock:
            assert sock.recv(1) == b""
        assert 0.8 < time.monotonic() - started < 8


def test_the_header_timeout_applies_to_each_request_of_a_keep_alive_connection() -> None:
    """The deadline is per request head: one armed at the connection's start must not cut
    off a later request, and a later request's unfinished head gets its own 408."""
    with listening(Settings(http_header_timeout_s=1, http_keep_alive_s=5)) as port:
        status, sock = status_of(port, GET)
        with sock:
            assert status == 200
            time.sleep(1.2)  # past the first deadline, within keep-alive
            sock.sendall(GET)
            assert int(read_response(sock).split(b" ", 2)[1]) == 200
            sock.sendall(b"GET / HTTP/1.1\r\nHo")
            assert int(read_response(sock).split(b" ", 2)[1]) == 408
            assert sock.recv(1) == b""


def test_the_header_timeout_covers_a_request_after_a_body_the_app_did_not_read() -> None:
    """The app answered before reading the body; the body's last bytes then end that
    request and start the next, with uvicorn's keep-alive timer cancelled: the next
    request's unfinished head still gets its 408."""
    with listening(Settings(http_header_timeout_s=1, http_keep_alive_s=5)) as port:
        head = b"POST / HTTP/1.1\r\nHost: x\r\nContent-Length: 10\r\n\r\n"
        status, sock = status_of(port, head)
        with sock:
            assert status == 200
            sock.sendall(b"0123456789GET / HT")
            assert int(read_response(sock).split(b" ", 2)[1]) == 408
            assert sock.recv(1) == b""


def test_a_data_dir_whose_embedded_redis_already_runs_is_refused_in_one_line(
    tmp_path: Path,
) -> None:
    """Another ``mcam api`` or ``serve`` serves the data dir: refused before the API
    announces itself (it printed its URL, then a traceback from the app's startup)."""
    clean = {k: v for k, v in os.environ.items() if not k.startswith("MCAM_")}
    with EmbeddedRedis(tmp_path):
        done = subprocess.run(
            [sys.executable, "-m", "service.cli.main", "api", "--port", str(free_port())],
            cwd=REPO, env={**clean, "MCAM_DATA_DIR": str(tmp_path)},
            capture_output=True, text=True, timeout=60,
        )  # fmt: skip
    assert done.returncode == 2 and "already serves this data dir" in done.stderr
    assert "Traceback" not in done.stderr and "MantissaCam API on" not in done.stdout
