"""``mcam worker`` as a real process: clear errors without Redis, runs against a given one."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from worker.embedded_redis import EmbeddedRedis, connect
from worker.redis_keys import WORKERS_HEARTBEAT

REPO = Path(__file__).resolve().parents[3]


def mcam(*args: str, env: dict[str, str]) -> subprocess.Popen[str]:
    clean = {k: v for k, v in os.environ.items() if not k.startswith("MCAM_")}
    return subprocess.Popen(
        [sys.executable, "-m", "service.cli.main", *args],
        cwd=REPO,
        env={**clean, **env},
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def test_worker_without_redis_explains_what_to_do(tmp_path: Path) -> None:
    process = mcam("worker", env={"MCAM_DATA_DIR": str(tmp_path)})
    _out, err = process.communicate(timeout=60)
    assert process.returncode == 2
    assert "no Redis" in err and "MCAM_REDIS_URL" in err and "Traceback" not in err


def test_worker_rejects_zero_concurrency(tmp_path: Path) -> None:
    process = mcam("worker", "--concurrency", "0", env={"MCAM_DATA_DIR": str(tmp_path)})
    _out, err = process.communicate(timeout=60)
    assert process.returncode == 2 and "at least 1" in err


def test_worker_finds_the_embedded_redis_and_stops_on_sigterm(tmp_path: Path) -> None:
    with EmbeddedRedis(tmp_path) as url:
        client = connect(url)
        process = mcam(
            "worker",
            "--concurrency",
            "2",
            env={"MCAM_DATA_DIR": str(tmp_path), "MCAM_HEARTBEAT_S": "0.2"},
        )
        deadline = time.monotonic() + 60
        while not client.hlen(WORKERS_HEARTBEAT) and time.monotonic() < deadline:
            time.sleep(0.05)
        [beat] = client.hvals(WORKERS_HEARTBEAT)
        assert b'"concurrency": 2' in beat
        process.send_signal(signal.SIGTERM)
        assert process.wait(30) == 0
        assert client.hlen(WORKERS_HEARTBEAT) == 0
        process.communicate()
