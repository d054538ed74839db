"""/health/live and /health/ready: decoders, Redis, worker heartbeats and the result store,
really checked."""

from __future__ import annotations

import logging
import os
import shutil
import signal
import socket
import subprocess
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx
import numpy as np
import pytest

from models.decoders import learned
from service.core.config import Settings
from service.main import create_app
from tests.models.decoders.test_model_install import install_one
from tests.service.conftest import (
    FULL_KEY,
    frame_png,
    make_settings,
    npy_bytes,
    running_worker,
    serve,
)
from tests.worker.conftest import leave_free
from worker.embedded_redis import EmbeddedRedis, connect
from worker.result_store import RESULTS_DIR


def wait_ready(url: str, want: int, timeout_s: float = 10.0) -> httpx.Response:
    deadline = time.monotonic() + timeout_s
    while True:
        reply = httpx.get(f"{url}/health/ready")
        if reply.status_code == want or time.monotonic() > deadline:
            return reply
        time.sleep(0.1)


def with_a_worker(url: str, timeout_s: float = 30.0) -> httpx.Response:
    """``/health/ready``'s answer once it counts a worker's heartbeat."""
    deadline = time.monotonic() + timeout_s
    while True:
        reply = httpx.get(f"{url}/health/ready")
        if reply.json()["workers"] or time.monotonic() > deadline:
            return reply
        time.sleep(0.1)


def test_live(api: str) -> None:
    assert httpx.get(f"{api}/health/live").json() == {"status": "ok"}


def test_ready_needs_a_worker_heartbeat(api: str, settings: Settings) -> None:
    reply = httpx.get(f"{api}/health/ready")
    assert reply.status_code == 503
    body = reply.json()
    assert body["checks"] == {"decoders": True, "queue": True, "workers": False, "store": True}
    assert "mcam worker" in body["detail"]["workers"]
    with running_worker(settings):
        ready = wait_ready(api, 200)
        assert ready.status_code == 200 and ready.json()["workers"] == 1
    assert wait_ready(api, 503).status_code == 503  # the worker removed its heartbeat


def test_a_parametrized_default_decoder_is_ready(tmp_path: Path, redis_url: str) -> None:
    """/health/ready compared the name with the listed decoders: 'auto-40ms' (valid
    everywhere else) kept the service not ready for ever."""
    settings = make_settings(tmp_path, redis_url, default_decoder="auto-40ms")
    with serve(create_app(settings)) as api:
        assert httpx.get(f"{api}/health/ready").json()["checks"]["decoders"] is True


def test_ready_reports_a_model_file_that_is_not_its_card(
    api: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A model file cut short: /health/ready only resolved the default decoder's name and
    said the decoders were ready, while the workers' warm-up logged the broken file and
    every job that needed it failed as model_unavailable. It names the file (not where it
    lies on the server) and what to do; a card that is not one is reported too."""
    onnx = install_one(tmp_path / "onnx")
    onnx.write_bytes(onnx.read_bytes()[:1000])
    monkeypatch.setattr(learned, "ONNX_DIR", onnx.parent)
    body = httpx.get(f"{api}/health/ready").json()
    assert body["checks"]["decoders"] is False
    detail = body["detail"]["decoders"]
    assert "mantissanet-tiny-modulo.onnx" in detail and "model_unavailable" in detail
    assert "restore it" in detail and str(tmp_path) not in detail
    (onnx.parent / "notes.json").write_text("[]")
    reply = httpx.get(f"{api}/health/ready")
    assert reply.status_code == 503 and reply.json()["checks"]["decoders"] is False
    assert "model card is not usable" in reply.json()["detail"]["decoders"]


def test_ready_reports_redis_down_and_unknown_default_decoder(tmp_path: Path) -> None:
    embedded = EmbeddedRedis(tmp_path / "r")
    url = embedded.start()
    # a decoder gone since the settings were read (the settings refuse an unknown one)
    settings = make_settings(tmp_path, url).model_copy(update={"default_decoder": "missing"})
    with serve(create_app(settings)) as api:
        embedded.stop()
        body = httpx.get(f"{api}/health/ready").json()
        assert body["checks"]["queue"] is False and body["checks"]["decoders"] is False
        assert "redis.sock" not in body["detail"]["queue"]  # no internal address to anyone
        assert httpx.get(f"{api}/health/live").status_code == 200
        jobs = httpx.get(
            f"{api}/v1/jobs/{'0' * 32}", headers={"Authorization": f"Bearer {FULL_KEY}"}
        )
        assert jobs.status_code == 503 and jobs.json()["code"] == "queue_unavailable"


def test_an_unreachable_redis_is_logged_with_its_url_and_what_to_do(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """An MCAM_REDIS_URL naming a server that is no Redis (an HTTP server) was logged as
    "readiness: Redis unreachable: Connection closed by server.": no URL, nothing to do."""
    with socket.socket() as other:
        other.bind(("127.0.0.1", 0))
        other.listen()
        port = other.getsockname()[1]
        closer = threading.Thread(target=lambda: other.accept()[0].close(), daemon=True)
        closer.start()
        settings = make_settings(tmp_path, f"redis://:secret@127.0.0.1:{port}/0")
        with caplog.at_level(logging.WARNING, logger="service.api.routes.health"):
            with serve(create_app(settings)) as api:
                body = httpx.get(f"{api}/health/ready").json()
    assert body["checks"]["queue"] is False and "127.0.0.1" not in body["detail"]["queue"]
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("readiness")]
    assert lines and f"redis://:***@127.0.0.1:{port}/0 unreachable" in lines[0]
    assert "MCAM_REDIS_URL" in lines[0] and "secret" not in lines[0]


def test_a_hung_redis_gets_a_quick_503_not_a_hang(tmp_path: Path) -> None:
    """A Redis that accepts connections but never answers (stopped, swapping, stuck on
    disk) costs a request one ``redis_timeout_s``: with retries it cost 20-80 s."""
    embedded = EmbeddedRedis(tmp_path / "r")
    settings = make_settings(tmp_path, embedded.start(), redis_timeout_s=0.5)
    auth = {"Authorization": f"Bearer {FULL_KEY}"}
    try:
        with serve(create_app(settings)) as api:
            assert httpx.get(f"{api}/v1/jobs/{'0' * 32}", headers=auth).status_code == 404
            assert embedded.pid is not None
            os.kill(embedded.pid, signal.SIGSTOP)
            try:
                ready = httpx.get(f"{api}/health/ready", timeout=8)
                job = httpx.get(f"{api}/v1/jobs/{'0' * 32}", headers=auth, timeout=8)
            finally:
                os.kill(embedded.pid, signal.SIGCONT)
            assert ready.status_code == 503 and ready.json()["checks"]["queue"] is False
            assert job.status_code == 503 and job.json()["code"] == "queue_unavailable"
            assert httpx.get(f"{api}/v1/jobs/{'0' * 32}", headers=auth).status_code == 404
    finally:
        embedded.stop()


def test_ready_reports_a_result_store_disk_without_room(tmp_path: Path, redis_url: str) -> None:
    """A results disk with less free than one upload was reported ready, while every
    job's results waited (running, for ever) for room (made to happen on a 64 KiB
    tmpfs: the worker logged "the results disk is full")."""
    free = shutil.disk_usage(tmp_path).free
    settings = make_settings(tmp_path, redis_url, max_upload_bytes=2 * free + 1)
    with serve(create_app(settings)) as api, running_worker(settings):
        reply = with_a_worker(api)
        assert reply.status_code == 503
        body = reply.json()
        assert body["checks"] == {"decoders": True, "queue": True, "workers": True,
                                  "store": False}
        assert "MCAM_MAX_UPLOAD_BYTES" in body["detail"]["store"]


def test_ready_reports_a_full_redis(tmp_path: Path) -> None:
    """Redis at its maxmemory (noeviction) refused every submit with 503 store_full while
    /health/ready answered ready."""
    embedded = EmbeddedRedis(tmp_path / "r")
    url = embedded.start()
    settings = make_settings(tmp_path, url)
    auth = {"Authorization": f"Bearer {FULL_KEY}"}
    direct = connect(url)
    try:
        with serve(create_app(settings)) as api, running_worker(settings):
            assert with_a_worker(api).status_code == 200
            # A maxmemory below what Redis holds, as once a backlog filled it (filling it
            # to the byte leaves it full for one write and not the next).
            used = int(direct.info("memory")["used_memory"])
            direct.config_set("maxmemory", used // 2)
            data, _ = frame_png()
            submit = httpx.post(
                f"{api}/v1/reconstructions", files={"file": ("f.png", data)}, headers=auth
            )
            assert submit.status_code == 503 and submit.json()["code"] == "store_full"
            reply = httpx.get(f"{api}/health/ready")
            assert reply.status_code == 503
            body = reply.json()
            assert body["checks"]["queue"] is False
            assert "Redis is full" in body["detail"]["queue"]
            assert "raise MCAM_REDIS_MAXMEMORY" in body["detail"]["queue"]
            direct.config_set("maxmemory", 0)
            assert with_a_worker(api).status_code == 200
    finally:
        direct.close()
        embedded.stop()


def test_ready_on_a_full_redis_does_not_ask_for_a_worker_that_runs(tmp_path: Path) -> None:
    """A full Redis refuses the workers' heartbeats too, so a running worker's heartbeat
    ages out. Before, /health/ready then said "no worker heartbeat: start one with 'mcam
    worker'": an operator who did got one more worker that could not beat either. Now it
    says the heartbeats are refused while Redis is full."""
    embedded = EmbeddedRedis(tmp_path / "r")
    url = embedded.start()
    settings = make_settings(tmp_path, url)
    direct = connect(url)
    try:
        with serve(create_app(settings)) as api, running_worker(settings):
            assert with_a_worker(api).status_code == 200
            direct.config_set("maxmemory", 1)
            deadline = time.monotonic() + 30
            while httpx.get(f"{api}/health/ready").json()["workers"]:
                assert time.monotonic() < deadline, "the heartbeat did not age out"
                time.sleep(0.1)
            body = httpx.get(f"{api}/health/ready").json()
            direct.config_set("maxmemory", 0)
            assert body["checks"]["workers"] is False
            assert "Redis is full and refuses the workers' heartbeats" in body["detail"]["workers"]
            assert with_a_worker(api).status_code == 200
    finally:
        direct.close()
        embedded.stop()


def test_ready_only_with_room_for_the_largest_upload(tmp_path: Path) -> None:
    """Redis with room for the largest upload's codes once, but not for what it holds
    while it takes them (the codes as the command's argument, and a query buffer of
    their size set aside for the next), answered ready while that upload got 503
    store_full: a load balancer kept sending work that failed. It is now not ready
    below the room that upload needs (:func:`worker.redis_memory.submit_room`), and
    ready with room to spare, where it is accepted (Redis's maxmemory a few MB here)."""
    side = 256
    codes = np.random.default_rng(0).integers(0, 4096, (side, side, 3)).astype(np.uint16)
    embedded = EmbeddedRedis(tmp_path / "r")
    # The largest upload: a still frame of MCAM_MAX_PIXELS RGB 16-bit codes (a video may
    # hold as many code values, no more).
    settings = make_settings(tmp_path, embedded.start(), max_pixels=side * side,
                             max_video_samples=codes.size)  # fmt: skip
    direct = connect(settings.redis_url or "")
    auth = {"Authorization": f"Bearer {FULL_KEY}"}
    upload = {"file": ("f.npy", npy_bytes(codes))}
    fields = {"bits": "12", "encoding": "modulo"}
    try:
        with serve(create_app(settings)) as api, running_worker(settings):
            assert with_a_worker(api).status_code == 200
            leave_free(direct, codes.nbytes * 3 // 2)
            reply = httpx.get(f"{api}/health/ready")
            refused = httpx.post(f"{api}/v1/reconstructions", files=upload, data=fields,
                                 headers=auth)  # fmt: skip
            assert refused.status_code == 503 and refused.json()["code"] == "store_full"
            assert reply.status_code == 503, reply.json()
            body = reply.json()
            assert body["checks"]["queue"] is False
            assert "largest upload" in body["detail"]["queue"]
            assert "MCAM_REDIS_MAXMEMORY" in body["detail"]["queue"]
            leave_free(direct, 4 * codes.nbytes)
            assert wait_ready(api, 200).status_code == 200
            accepted = httpx.post(f"{api}/v1/reconstructions", files=upload, data=fields,
                                  headers=auth)  # fmt: skip
            assert accepted.status_code == 202, accepted.text
    finally:
        direct.close()
        embedded.stop()


@contextmanager
def read_only(folder: Path) -> Iterator[None]:
    """``folder`` unwritable: a read-only tmpfs mounted over it (root, whom modes do not
    stop), else its mode; skips the test where neither can be done."""
    if os.geteuid() != 0:
        folder.chmod(0o500)
        try:
            yield
        finally:
            folder.chmod(0o700)
        return
    mount = subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=64k", "tmpfs", str(folder)],
                           capture_output=True, check=False)
    if mount.returncode:
        pytest.skip(f"cannot mount a read-only tmpfs here: {mount.stderr.decode().strip()}")
    try:
        yield
    finally:
        subprocess.run(["umount", str(folder)], check=True)


def test_ready_reports_a_read_only_result_store(settings: Settings, api: str) -> None:
    """A read-only results folder was reported ready, while every job failed with
    'OSError: [Errno 30] Read-only file system' (made to happen with a remounted tmpfs)."""
    with running_worker(settings), read_only(settings.data_dir / RESULTS_DIR):
        reply = with_a_worker(api)
        assert reply.status_code == 503
        assert reply.json()["checks"]["store"] is False
        assert "not writable" in reply.json()["detail"]["store"]


def test_a_removed_results_folder_is_not_reported_unwritable(
    settings: Settings, api: str
) -> None:
    """Workers create the results folder again (at start, and for each result): a folder
    an operator removed is judged by its parent, not called 'not writable'."""
    shutil.rmtree(settings.data_dir / RESULTS_DIR)
    body = httpx.get(f"{api}/health/ready").json()
    assert body["checks"]["store"] is True, body["detail"]


class _ClockBehind:
    """The ``time`` module as seen on a host whose clock is ``behind_s`` seconds behind."""

    def __init__(self, behind_s: float) -> None:
        self.behind_ns = int(behind_s * 1e9)

    def __getattr__(self, name: str) -> object:
        return getattr(time, name)

    def time_ns(self) -> int:
        return time.time_ns() - self.behind_ns


def test_a_worker_on_a_host_whose_clock_is_behind_counts(
    settings: Settings, api: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Heartbeats were stamped with the worker's clock and aged with the API's: a worker
    on a host a minute behind was never counted, and /health/ready said to start one."""
    monkeypatch.setattr("worker.runner.time", _ClockBehind(60))
    with running_worker(settings):
        reply = wait_ready(api, 200)
    assert reply.status_code == 200, reply.json()
    assert reply.json()["workers"] == 1
