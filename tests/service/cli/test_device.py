"""``mcam simulate-device`` and ``mcam device`` as real processes, wired by a pty path."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
import redis

from device.simulator import MAX_SEED
from tests.device import conftest as device_fixtures
from tests.device.conftest import health, stream_frames, wait_for
from worker.embedded_redis import EmbeddedRedis
from worker.redis_keys import control_stream

MCAM = Path(sys.executable).parent / "mcam"
#: The device tests' private redis-server and a redis client of it (in tests/service/,
#: ``client`` is otherwise the API's HTTP client factory).
redis_server = device_fixtures.redis_server
client = device_fixtures.client


def env_for(redis_url: str, data_dir: Path) -> dict[str, str]:
    return {**os.environ, "MCAM_REDIS_URL": redis_url, "MCAM_DATA_DIR": str(data_dir)}


@contextmanager
def camera_and_daemon(env: dict[str, str], client: redis.Redis, tmp_path: Path,
                      *camera_flags: str) -> Iterator[None]:
    """``mcam simulate-device`` on a pty and ``mcam device`` (device ``rig-1``) reading
    it, both run with ``env``; once the daemon has a frame (``client``: its Redis),
    yields; both must then stop cleanly on SIGTERM."""
    camera = subprocess.Popen(
        [MCAM, "simulate-device", "--port", f"pty:{tmp_path / 'cam'}", "--fps", "30",
         *camera_flags],
        stdout=subprocess.PIPE, stderr=(tmp_path / "camera.log").open("w"), text=True, env=env,
        cwd=tmp_path)
    daemon = None
    try:
        assert camera.stdout is not None
        url = camera.stdout.readline().strip()
        assert url == str(tmp_path / "cam") and Path(url).exists()
        daemon = subprocess.Popen([MCAM, "device", "--port", url, "--device-id", "rig-1"],
                                  stdout=subprocess.DEVNULL,
                                  stderr=(tmp_path / "daemon.log").open("w"), text=True,
                                  env=env, cwd=tmp_path)
        assert wait_for(lambda: health(client, "rig-1").get("frames_ok", "0") != "0", 60)
        yield
    finally:
        for process in (daemon, camera):
            if process is not None:
                process.send_signal(signal.SIGTERM)
    assert daemon is not None and daemon.wait(20) == 0
    assert camera.wait(20) == 0


def test_simulate_device_feeds_mcam_device(redis_server: EmbeddedRedis, client: redis.Redis,
                                           tmp_path: Path) -> None:
    env = env_for(redis_server.url, tmp_path / "data")
    with camera_and_daemon(env, client, tmp_path, "--encoding", "mantissa", "--alpha", "4"):
        frames = stream_frames(client, "rig-1")
        assert frames[0].discont and frames[0].params.encoding == "mantissa"
        assert frames[0].params.alpha == 4.0 and frames[0].codes.shape == (256, 256)


@pytest.mark.parametrize(("setting", "value", "brackets", "kept"), [
    ("MCAM_DATASET_MAX_PAIRS", "2", 3, 2),
    ("MCAM_DATASET_MAX_BYTES", "1", 2, 1),  # the newest pair is kept, however large
])
def test_mcam_device_keeps_the_dataset_within_the_settings(
    redis_server: EmbeddedRedis, client: redis.Redis, tmp_path: Path, setting: str, value: str,
    brackets: int, kept: int,
) -> None:
    """``brackets`` bracketed captures, one after the other: ``kept`` pairs stay (the
    default limits, 1000 pairs and 1 GiB, would keep them all)."""
    env = {**env_for(redis_server.url, tmp_path / "data"), setting: value}
    with camera_and_daemon(env, client, tmp_path):
        for saved in range(1, brackets + 1):
            client.xadd(control_stream("rig-1"), {"command": "bracket"})
            assert wait_for(
                lambda saved=saved: health(client, "rig-1").get("brackets_saved") == str(saved),
                60,
            )
    folders = sorted((tmp_path / "data" / "datasets" / "rig-1").iterdir())
    assert len(folders) == kept, folders


def test_bad_arguments_exit_2_with_one_line(redis_server: EmbeddedRedis, tmp_path: Path) -> None:
    env = env_for(redis_server.url, tmp_path / "data")
    result = subprocess.run([MCAM, "device", "--port", "loop://", "--device-id", "no spaces"],
                            capture_output=True, text=True, env=env, timeout=60)
    assert result.returncode == 2
    assert result.stderr.strip().splitlines() == [
        "mcam device: error: invalid device id 'no spaces': use 1-64 letters, digits, '_' or '-'"]
    result = subprocess.run([MCAM, "device", "--port", "bogus://x", "--device-id", "rig1"],
                            capture_output=True, text=True, env=env, timeout=60)
    assert result.returncode == 2 and result.stderr.strip().splitlines() == [
        "mcam device: error: pyserial does not know the port URL scheme 'bogus' (bogus://x); "
        "use a device path (/dev/ttyACM0), socket://HOST:PORT, rfc2217://HOST:PORT or loop://"]
    result = subprocess.run([MCAM, "simulate-device", "--port", "/dev/ttyS0"],
                            capture_output=True, text=True, env=env, timeout=60)
    assert result.returncode == 2 and "unsupported simulator port" in result.stderr
    result = subprocess.run([MCAM, "simulate-device", "--bits", "40"],
                            capture_output=True, text=True, env=env, timeout=60)
    assert result.returncode == 2 and "bits" in result.stderr


def test_simulate_device_flags_out_of_range_are_named(tmp_path: Path) -> None:
    cases = [
        (("--port", "socket://127.0.0.1:99999"), "PORT from 0 to 65535"),
        (("--port", "socket://no.such.host.invalid:5555"), "--port socket://no.such.host.invalid"),
        (("--port", "loop://"), "--port loop:// only reaches readers in this same process"),
        (("--port", f"pty:{tmp_path / 'no-dir' / 'cam'}"),
         f"directory {tmp_path / 'no-dir'} does not exist, so the simulated camera's port"),
        (("--port", f"pty:{tmp_path / 'file' / 'cam'}"),
         "cannot open it (Not a directory); name a path in a directory you can write, or pty"),
        (("--fps", "1e-300"), "--fps must be from 0.1 to 10000"),
        (("--frames", "-5"), "--frames must be at least 1"),
        (("--seed", "-1"), f"--seed must be from 0 to {MAX_SEED}, got -1"),
        (("--seed", "9300000000000"), f"--seed must be from 0 to {MAX_SEED}, got 9300000000000"),
        (("--stall-every", "1", "--stall-s", "-1"),
         "stall_s must be a finite number of seconds, 0 or more, got -1.0"),
        (("--disconnect-every", "2", "--disconnect-s", "nan"),
         "disconnect_s must be a finite number of seconds, 0 or more, got nan"),
        (("--stall-every", "-1"), "stall_every must be a whole number of packets, 0 (never)"),
    ]
    (tmp_path / "file").touch()
    for flags, fragment in cases:
        result = subprocess.run([MCAM, "simulate-device", *flags], capture_output=True,
                                text=True, timeout=60, cwd=tmp_path)
        assert result.returncode == 2, result.stderr
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1 and fragment in lines[0], result.stderr


def test_a_second_daemon_under_the_same_device_id_exits_with_one_line(
        redis_server: EmbeddedRedis, client: redis.Redis, tmp_path: Path) -> None:
    env = env_for(redis_server.url, tmp_path / "data")
    first = subprocess.Popen([MCAM, "device", "--port", "loop://", "--device-id", "rig-1"],
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env,
                             cwd=tmp_path)
    try:
        assert wait_for(lambda: health(client, "rig-1").get("state") is not None, 60)
        second = subprocess.run([MCAM, "device", "--port", "loop://", "--device-id", "rig-1"],
                                capture_output=True, text=True, env=env, timeout=60)
        assert second.returncode == 2
        [line] = second.stderr.strip().splitlines()
        assert line.startswith("mcam device: error: device 'rig-1' already has a daemon")
    finally:
        first.send_signal(signal.SIGTERM)
    assert first.wait(20) == 0
