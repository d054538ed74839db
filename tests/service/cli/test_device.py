"""``mcam device`` as a real process, reading ``mcam simulate-device`` through a pty path
(its own flags: test_simulate_device.py)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import redis

from tests.device import conftest as device_fixtures
from tests.device.conftest import health, wait_for
from tests.service.cli.conftest import (
    MCAM,
    camera_and_daemon,
    env_for,
    run_mcams,
    stopped_by_signal_flood,
)
from worker.embedded_redis import EmbeddedRedis
from worker.redis_keys import control_stream

#: The device tests' private redis-server and a redis client of it (in tests/service/,
#: ``client`` is otherwise the API's HTTP client factory).
redis_server = device_fixtures.redis_server
client = device_fixtures.client


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
    wrong_id, scheme, dotted, empty, option, spy, port, bits = run_mcams([
        ("device", "--port", "loop://", "--device-id", "no spaces"),
        ("device", "--port", "bogus://x", "--device-id", "rig1"),
        ("device", "--port", "my.camera://x", "--device-id", "rig1"),
        ("device", "--port", " ", "--device-id", "rig1"),
        ("device", "--port", "loop://?logging=DEBUG", "--device-id", "rig1"),
        ("device", "--port", "spy:///dev/ttyACM0?bogus=1", "--device-id", "rig1"),
        ("simulate-device", "--port", "/dev/ttyS0"),
        ("simulate-device", "--bits", "40"),
    ], cwd=tmp_path, env=env)  # fmt: skip
    assert wrong_id.returncode == 2
    assert wrong_id.stderr.strip().splitlines() == [
        "mcam device: error: invalid device id 'no spaces': use 1-64 letters, digits, '_' or '-' "
        "(ASCII: A-Z, a-z, 0-9)"]
    assert scheme.returncode == 2 and scheme.stderr.strip().splitlines() == [
        "mcam device: error: pyserial does not know the port URL scheme 'bogus' (bogus://x); "
        "use a device path (/dev/ttyACM0), socket://HOST:PORT, rfc2217://HOST:PORT or loop://"]
    assert dotted.returncode == 2, dotted.stderr  # a ModuleNotFoundError traceback, exit 1
    assert dotted.stderr.strip().splitlines() == [
        "mcam device: error: pyserial does not know the port URL scheme 'my.camera' "
        "(my.camera://x); use a device path (/dev/ttyACM0), socket://HOST:PORT, "
        "rfc2217://HOST:PORT or loop://"]
    assert empty.returncode == 2 and empty.stderr.strip().splitlines() == [
        "mcam device: error: the port is empty; give a device path (/dev/ttyACM0), "
        "socket://HOST:PORT or rfc2217://HOST:PORT"]
    assert option.returncode == 2, option.stderr  # a KeyError traceback, and exit 0
    assert option.stderr.strip().splitlines()[0].startswith(
        "mcam device: error: bad option in port URL 'loop://?logging=DEBUG'; pyserial's loop:// "
        "takes ?logging=debug, info, warning or error")
    assert spy.returncode == 2, spy.stderr  # retried for good
    assert spy.stderr.strip().splitlines() == [
        "mcam device: error: bad option in port URL 'spy:///dev/ttyACM0?bogus=1' (unknown "
        "option: 'bogus'); pyserial's spy:// takes ?file=PATH (where it writes the traffic "
        "it sees; standard error without it), color, raw, all, or none"]
    assert port.returncode == 2 and "unsupported simulator port" in port.stderr
    assert "loop:// reaches readers in the same process only" in port.stderr
    assert bits.returncode == 2 and "bits" in bits.stderr


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


def test_of_two_daemons_started_while_redis_is_down_the_second_exits_once_it_is_back(
        redis_server: EmbeddedRedis, tmp_path: Path) -> None:
    """Both runs skipped the claim while Redis was down, and both streamed once it was
    back. The one that finds the other's claim then exits 2 with the one-line error a
    second daemon gets when Redis is up; the other runs on."""
    env = env_for(redis_server.url, tmp_path / "data")
    redis_server.stop()
    logs = [tmp_path / f"daemon-{n}.log" for n in range(2)]
    runs = []
    for log in logs:
        with log.open("w") as stderr:
            runs.append(subprocess.Popen(
                [MCAM, "device", "--port", "loop://", "--device-id", "rig-1"],
                stdout=subprocess.DEVNULL, stderr=stderr, env=env, cwd=tmp_path))
    try:
        assert wait_for(lambda: all("Redis unreachable" in log.read_text() for log in logs), 60)
        redis_server.start()
        assert wait_for(lambda: any(run.poll() is not None for run in runs), 60)
        loser = next(n for n, run in enumerate(runs) if run.poll() is not None)
        assert runs[loser].returncode == 2
        assert logs[loser].read_text().strip().splitlines()[-1].startswith(
            "mcam device: error: device 'rig-1' already has a daemon (")
        assert runs[1 - loser].poll() is None
    finally:
        for run in runs:
            if run.poll() is None:
                run.send_signal(signal.SIGTERM)
    assert runs[1 - loser].wait(20) == 0


#: ``mcam device`` on loop:// as the console script runs it, with pyserial's open raising
#: what it never does: a bug in the daemon's thread.
BROKEN_OPEN = """
import sys, serial
def broken(*args, **kwargs):
    raise RuntimeError("not a client mistake")
serial.serial_for_url = broken
from service.cli.main import main
sys.exit(main(["device", "--port", "loop://", "--device-id", "rig-1"]))
"""


def test_a_daemon_that_stops_on_an_unexpected_error_exits_1_with_one_line(
        redis_server: EmbeddedRedis, client: redis.Redis, tmp_path: Path) -> None:
    """threading printed the traceback and ``mcam device`` exited 0, as if stopped: a
    service manager would not restart it. The log has the traceback once, then one line
    says what happened and what to do; exit 1, and the last health says it crashed, and
    on what."""
    env = env_for(redis_server.url, tmp_path / "data")
    done = subprocess.run([sys.executable, "-c", BROKEN_OPEN], capture_output=True, text=True,
                          env=env, cwd=tmp_path, timeout=120)
    assert done.returncode == 1, done.stderr
    lines = done.stderr.strip().splitlines()
    assert lines[-1] == (
        "mcam device: error: the daemon of device 'rig-1' stopped on an unexpected error "
        "(RuntimeError: not a client mistake); the log above has its traceback: please "
        "report it, and restart mcam device")
    assert done.stderr.count("Traceback") == 1, done.stderr
    assert "the daemon stopped on an unexpected error; loop:// is no longer read" in done.stderr
    last = health(client, "rig-1")
    assert (last["state"], last["crash"]) == ("crashed", "RuntimeError: not a client mistake")


@pytest.mark.parametrize("start", range(3))
def test_ctrl_c_pressed_on_and_on_stops_the_daemon_cleanly(
        redis_server: EmbeddedRedis, client: redis.Redis, tmp_path: Path, start: int) -> None:
    """Ctrl-C to the process group, again and again until the daemon exits: the first
    stops it; one that came after its stop, while the interpreter exited and signals had
    their default action again, ended it by SIGINT (exit -2, no message; two SIGINTs
    50 ms apart did it in 2 of 3 runs). It exits 0, its last health says stopped."""
    env = env_for(redis_server.url, tmp_path / "data")
    process = subprocess.Popen([MCAM, "device", "--port", "loop://", "--device-id", "rig-1"],
                               stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                               env=env, cwd=tmp_path, start_new_session=True)
    try:
        assert wait_for(lambda: health(client, "rig-1").get("state") is not None, 60)
        deadline = time.monotonic() + 60
        while process.poll() is None and time.monotonic() < deadline:
            os.killpg(process.pid, signal.SIGINT)
            time.sleep(0.01)  # a key pressed on and on: not a wait for anything
        _, stderr = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait(30)
    assert process.returncode == 0, stderr
    assert "Traceback" not in stderr, stderr
    assert health(client, "rig-1")["state"] == "stopped"


@pytest.mark.parametrize("start", range(6))
def test_a_burst_of_stop_signals_stops_the_daemon(
        redis_server: EmbeddedRedis, client: redis.Redis, tmp_path: Path, start: int) -> None:
    """SIGINT and SIGTERM, one after the other as fast as another process can send them.
    The daemon's handler set a threading.Event, which takes a lock: a signal that came
    while an earlier handler held it ran a handler that waited for that lock for good,
    and the process hung, ignoring every later signal, or died of the handlers' nesting
    with a traceback (10 of 18 starts). It exits 0, its last health says stopped."""
    env = env_for(redis_server.url, tmp_path / "data")
    process = subprocess.Popen([MCAM, "device", "--port", "loop://", "--device-id", "rig-1"],
                               stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                               env=env, cwd=tmp_path)
    with stopped_by_signal_flood(process) as stderr:
        assert wait_for(lambda: health(client, "rig-1").get("state") is not None, 60)
    assert process.returncode == 0, stderr
    assert "Traceback" not in stderr[0], stderr
    assert health(client, "rig-1")["state"] == "stopped"
