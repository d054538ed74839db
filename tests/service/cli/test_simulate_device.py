"""``mcam simulate-device`` as a real process: it feeds ``mcam device`` through a pty
path, and its out-of-range flags are named."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest
import redis

from device.simulator import MAX_SEED
from tests.device import conftest as device_fixtures
from tests.device.conftest import stream_frames
from tests.service.cli.conftest import (
    MCAM,
    camera_and_daemon,
    env_for,
    run_mcams,
    stopped_by_signal_flood,
)
from worker.embedded_redis import EmbeddedRedis

#: The device tests' private redis-server and a redis client of it (in tests/service/,
#: ``client`` is otherwise the API's HTTP client factory).
redis_server = device_fixtures.redis_server
client = device_fixtures.client


def test_simulate_device_feeds_mcam_device(redis_server: EmbeddedRedis, client: redis.Redis,
                                           tmp_path: Path) -> None:
    env = env_for(redis_server.url, tmp_path / "data")
    with camera_and_daemon(env, client, tmp_path, "--encoding", "mantissa", "--alpha", "4"):
        frames = stream_frames(client, "rig-1")
        assert frames[0].discont and frames[0].params.encoding == "mantissa"
        assert frames[0].params.alpha == 4.0 and frames[0].codes.shape == (256, 256)


def test_simulate_device_flags_out_of_range_are_named(tmp_path: Path) -> None:
    cases = [
        (("--port", "socket://127.0.0.1:99999"), "PORT from 0 to 65535"),
        (("--port", "socket://no.such.host.invalid:5555"), "--port socket://no.such.host.invalid"),
        (("--port", "loop://"), "--port loop:// only reaches readers in this same process"),
        (("--port", f"pty:{tmp_path / 'no-dir' / 'cam'}"),
         f"directory {tmp_path / 'no-dir'} does not exist, so the simulated camera's port"),
        (("--port", "pty:"), "bad simulator port 'pty:': pty:PATH names the symlink to make"),
        (("--port", "pty:/"), "bad simulator port 'pty:/': pty:PATH names the symlink to make"),
        (("--port", f"pty:{tmp_path / 'file' / 'cam'}"),
         "cannot open it (Not a directory); name a path in a directory you can write, or pty"),
        (("--fps", "1e-300"), "--fps must be from 0.1 to 10000"),
        (("--frames", "-5"), "--frames must be at least 1"),
        (("--gain", "5e-324"), "--gain must be at least 2.22507e-308, the smallest gain a frame"),
        (("--gain", "nan"), "--gain must be at least 2.22507e-308"),
        (("--seed", "-1"), f"--seed must be from 0 to {MAX_SEED}, got -1"),
        (("--seed", "9300000000000"), f"--seed must be from 0 to {MAX_SEED}, got 9300000000000"),
        (("--stall-every", "1", "--stall-s", "-1"),
         "stall_s must be a finite number of seconds, 0 to 3600, got -1"),
        (("--disconnect-every", "2", "--disconnect-s", "nan"),
         "disconnect_s must be a finite number of seconds, 0 to 3600, got nan"),
        (("--disconnect-every", "1", "--disconnect-s", "1e12"),
         "disconnect_s must be a finite number of seconds, 0 to 3600, got 1e+12"),
        (("--stall-every", "-1"), "stall_every must be a whole number of packets, 0 (never)"),
        # It was "empty.exr: not an OpenEXR or Radiance HDR ...; convert it to OpenEXR".
        (("--exr", "empty.exr"), "error: the file empty.exr is empty; send the whole file"),
    ]
    (tmp_path / "file").touch()
    (tmp_path / "empty.exr").touch()
    results = run_mcams([("simulate-device", *flags) for flags, _ in cases], cwd=tmp_path)
    for result, (_, fragment) in zip(results, cases, strict=True):
        assert result.returncode == 2, result.stderr
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1 and fragment in lines[0], result.stderr


def test_help_offers_only_the_ports_it_opens_and_gives_the_defaults() -> None:
    """--help offered 'loop://', which the command then refused, and hid the defaults
    of --gain, --read-noise (a noise the camera adds unless told 0) and the fault flags."""
    result = subprocess.run([MCAM, "simulate-device", "--help"], capture_output=True,
                            text=True, timeout=60, check=True)
    text = " ".join(result.stdout.split())
    assert "loop://" not in text
    for fragment in ("pty (default), pty:SYMLINK or socket://HOST:PORT", "(default 30)",
                     "scene unit (default 1)", "(default 0.002; 0: none)", "(default 256)",
                     "seconds (default 0.2)", "stays out (default 0.5)"):
        assert fragment in text, fragment


@pytest.mark.parametrize("start", range(6))
def test_a_burst_of_stop_signals_stops_the_camera(tmp_path: Path, start: int) -> None:
    """SIGINT and SIGTERM as fast as another process can send them. The handler set the
    threading.Event the main thread waited on, and a signal that came while the lock
    inside it was held (by the main thread waking, or an earlier handler) hung the
    process for good, or killed it by the handlers' nesting. It exits 0, saying what
    it sent."""
    process = subprocess.Popen([MCAM, "simulate-device", "--port", f"pty:{tmp_path / 'cam'}"],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               cwd=tmp_path)
    with stopped_by_signal_flood(process) as stderr:
        assert process.stdout is not None and process.stdout.readline().strip()  # the port
    assert process.returncode == 0, stderr
    assert stderr[0].startswith("sent "), stderr
