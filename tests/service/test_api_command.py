"""``mcam api`` as a real subprocess: the embedded default alone (own redis-server, a
generated key printed once and kept in the data dir), and restarts that keep accepted jobs.

(The CLI tests of tests/service/cli/ belong to the simulate/reconstruct owner; this
file covers ``service/cli/api.py``.)
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx
import pytest

from tests.service.conftest import FULL_KEY, frame_png, free_port, make_settings, running_worker
from worker.embedded_redis import EmbeddedRedis

pytestmark = pytest.mark.slow


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


def test_printed_key_line_format(tmp_path: Path) -> None:
    port = free_port()
    with running_api(tmp_path, port, MCAM_API_KEYS="k-0123456789") as process:
        wait_live(f"http://127.0.0.1:{port}", process)
        output = stop(process)
    assert re.search(r"MantissaCam API on http://127\.0\.0\.1:\d+/", output)
    assert "generated API key" not in output and not (tmp_path / "api_keys").exists()
