"""Tests of ``mcam api`` (``service/cli/api.py``): its settings (flags override the
environment, and are blamed as flags); uvicorn's connection limits, on real sockets; and
``mcam api`` as a real subprocess: the embedded default alone (own redis-server, a generated
key printed once and kept in the data dir), and restarts that keep accepted jobs."""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from pathlib import Path

import httpx
import pytest
import redis as redis_module
from pydantic import ValidationError

from models.errors import InvalidInputError
from service.cli.api import announce, settings_with
from service.core.config import Settings
from tests.service.cli.conftest import assert_one_line_error, run_mcam
from tests.service.conftest import (
    FULL_KEY,
    GET,
    frame_png,
    free_port,
    listening,
    make_settings,
    nothing_to_read,
    running_worker,
    status_of,
)
from worker.embedded_redis import EmbeddedRedis
from worker.redis_keys import JOBS_STREAM

REPO = Path(__file__).resolve().parents[3]


def test_a_bad_flag_is_named_as_the_flag_not_the_environment() -> None:
    with pytest.raises(InvalidInputError, match=r"^--port 99999: .*65535"):
        settings_with(Settings(), port=99999)


@pytest.mark.parametrize("host", ["", "  "])
def test_an_empty_host_flag_is_refused_not_every_interface(host: str) -> None:
    """``--host ""`` (``--host "$HOST"``, HOST unset) had uvicorn listen on 0.0.0.0
    and ::, where an empty MCAM_HOST means 127.0.0.1."""
    with pytest.raises(InvalidInputError, match=r"^--host .*: .*is empty: .*127\.0\.0\.1"):
        settings_with(Settings(), host=host)


@pytest.mark.parametrize(("host", "url"), [("::1", "http://[::1]:8123/"),
                                         ("127.0.0.1", "http://127.0.0.1:8123/")])
def test_the_announced_url_brackets_an_ipv6_host(
    host: str, url: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--host ::1`` announced ``http://::1:8123/``, a URL no client takes."""
    announce(Settings(host=host, port=8123), None)
    assert capsys.readouterr().out == f"MantissaCam API on {url} (docs: /docs)\n"


def test_a_good_flag_overrides_and_a_bad_setting_stays_a_settings_error() -> None:
    assert settings_with(Settings(), port=8123, host=None).port == 8123
    with pytest.raises(ValidationError):
        settings_with(Settings.model_construct(port=99999), host="127.0.0.1")


@pytest.mark.parametrize("command", ["api", "serve"])
def test_an_address_it_cannot_listen_on_is_refused_before_anything_starts(
    tmp_path: Path, command: str
) -> None:
    """A port in use, or a host not of this machine (192.0.2.1: a documentation
    address): uvicorn found them only after the API was announced, its key generated and
    the embedded Redis (and serve's workers) started, logged '[Errno 98] ...' or, for a
    name, '[Errno -2] Name or service not known' without the host, and exited 3."""
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        in_use = run_mcam(command, "--port", str(port), cwd=tmp_path)
    assert_one_line_error(
        in_use, f"cannot listen on 127.0.0.1:{port} (Address already in use)",
        "--port (MCAM_PORT) a free port",
    )  # fmt: skip
    foreign = run_mcam(command, "--host", "192.0.2.1", "--port", str(port), cwd=tmp_path)
    assert_one_line_error(
        foreign, f"cannot listen on 192.0.2.1:{port}", "give --host (MCAM_HOST) an address"
    )
    assert in_use.stdout == foreign.stdout == ""
    assert list(tmp_path.iterdir()) == [], "the data dir was made: something started"


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
        with sock:
            assert status == 200 and nothing_to_read(sock)  # kept open after the reply
            assert sock.recv(1) == b""  # then closed by the server


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


def start_api(data_dir: Path, port: int, **env: str) -> subprocess.Popen[str]:
    variables = {k: v for k, v in os.environ.items() if not k.startswith("MCAM_")}
    variables |= {"MCAM_DATA_DIR": str(data_dir), **env}
    return subprocess.Popen(
        [sys.executable, "-m", "service.cli.main", "api", "--port", str(port)],
        env=variables,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


@contextmanager
def running_api(data_dir: Path, port: int, **env: str) -> Iterator[subprocess.Popen[str]]:
    """:func:`start_api`, killed on the way out if the test left it running."""
    process = start_api(data_dir, port, **env)
    try:
        yield process
    finally:
        if process.poll() is None:
            process.kill()
            process.communicate(timeout=30)


def wait_live(url: str, process: subprocess.Popen[str]) -> None:
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and process.poll() is None:
        try:
            if httpx.get(f"{url}/health/live", timeout=1).status_code == 200:
                return
        except httpx.HTTPError:
            time.sleep(0.1)
    if process.poll() is None:
        process.kill()
    raise AssertionError(f"mcam api did not come up: {process.communicate(timeout=30)[0]}")


def stop(process: subprocess.Popen[str]) -> str:
    process.send_signal(signal.SIGINT)
    output, _ = process.communicate(timeout=30)
    return output


@pytest.mark.slow
def test_embedded_default_generates_prints_and_reuses_a_key(tmp_path: Path) -> None:
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    with running_api(tmp_path, port) as first:
        wait_live(url, first)
        key = (tmp_path / "api_keys").read_text().strip()
        reply = httpx.get(f"{url}/v1/decoders", headers={"Authorization": f"Bearer {key}"})
        assert reply.status_code == 200
        assert (tmp_path / "redis" / "appendonly.aof").exists()  # the private redis-server ran
        output = stop(first)
    assert key in output and f"http://127.0.0.1:{port}/" in output
    with running_api(tmp_path, port) as second:
        wait_live(url, second)
        assert key not in stop(second)  # printed once, on first start only
    assert (tmp_path / "api_keys").read_text().strip() == key


@pytest.mark.slow
def test_accepted_jobs_survive_api_and_redis_restarts(tmp_path: Path) -> None:
    redis = EmbeddedRedis(tmp_path / "redis-home")
    redis_url = redis.start()
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    env = {"MCAM_REDIS_URL": redis_url, "MCAM_API_KEYS": FULL_KEY}
    headers = {"Authorization": f"Bearer {FULL_KEY}"}
    api = start_api(tmp_path / "data", port, **env)
    try:
        wait_live(url, api)
        data, _ = frame_png()
        job = httpx.post(
            f"{url}/v1/reconstructions", files={"file": ("f.png", data)}, headers=headers
        ).json()
        assert job["state"] == "queued"
        stop(api)
        redis.stop()
        assert redis.start() == redis_url
        api = start_api(tmp_path / "data", port, **env)
        wait_live(url, api)
        assert httpx.get(f"{url}/v1/jobs/{job['id']}", headers=headers).json()["state"] == "queued"
        with running_worker(make_settings(tmp_path, redis_url)):
            deadline = time.monotonic() + 60
            state = "queued"
            while state != "succeeded" and time.monotonic() < deadline:
                time.sleep(0.2)
                state = httpx.get(f"{url}/v1/jobs/{job['id']}", headers=headers).json()["state"]
        assert state == "succeeded"
        result = httpx.get(f"{url}/v1/jobs/{job['id']}/result", headers=headers)
        assert result.status_code == 200 and result.content[:4] == b"\x76\x2f\x31\x01"
    finally:
        if api.poll() is None:
            stop(api)
        redis.stop()


@pytest.mark.slow
def test_printed_key_line_format(tmp_path: Path) -> None:
    port = free_port()
    with running_api(tmp_path, port, MCAM_API_KEYS="k-0123456789") as process:
        wait_live(f"http://127.0.0.1:{port}", process)
        output = stop(process)
    assert re.search(r"MantissaCam API on http://127\.0\.0\.1:\d+/", output)
    assert "generated API key" not in output and not (tmp_path / "api_keys").exists()


@pytest.mark.slow
def test_a_request_waiting_for_its_job_gets_its_202_when_the_api_stops(tmp_path: Path) -> None:
    """A ``Prefer: wait`` request held the stop (SIGTERM) for the whole grace period and
    then got a 500, although its job was stored: its client might submit it again."""
    redis = EmbeddedRedis(tmp_path / "redis-home")
    redis_url = redis.start()
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    headers = {"Authorization": f"Bearer {FULL_KEY}", "Prefer": "wait=60"}
    data, _ = frame_png()
    try:
        with running_api(tmp_path / "data", port, MCAM_REDIS_URL=redis_url,
                         MCAM_API_KEYS=FULL_KEY) as api, ThreadPoolExecutor(1) as pool:
            wait_live(url, api)
            waiting = pool.submit(httpx.post, f"{url}/v1/reconstructions",
                                  files={"file": ("f.png", data)}, headers=headers, timeout=60)
            client = redis_module.Redis.from_url(redis_url)
            deadline = time.monotonic() + 30
            while client.xlen(JOBS_STREAM) == 0:  # submitted: the request waits (no worker)
                assert time.monotonic() < deadline and not waiting.done(), "no job was queued"
                time.sleep(0.05)
            api.send_signal(signal.SIGTERM)
            reply = waiting.result()
            api.communicate(timeout=30)
        assert reply.status_code == 202, reply.text
        job = reply.json()
        assert job["state"] == "queued" and client.xlen(JOBS_STREAM) == 1
    finally:
        redis.stop()
