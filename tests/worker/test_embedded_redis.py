"""EmbeddedRedis: a private redis-server on a unix socket with append-only persistence."""

from __future__ import annotations

import errno
import os
import re
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from models.errors import McamError
from worker.embedded_redis import (
    WATCH_INTERVAL_S,
    EmbeddedRedis,
    RedisStartError,
    connect,
    durability_problem,
    redacted_url,
)


def test_start_serves_unix_socket_and_stop_cleans_up(tmp_path: Path) -> None:
    server = EmbeddedRedis(tmp_path)
    url = server.start()
    assert url.startswith("unix://") and server.socket.exists()
    assert connect(url).ping()
    config = (tmp_path / "redis" / "redis.conf").read_text()
    assert "appendonly yes" in config and "appendfsync always" in config and "port 0" in config
    assert stat.S_IMODE((tmp_path / "redis").stat().st_mode) == 0o700  # the AOF is private
    pid = server.pid
    assert pid is not None
    server.stop()
    assert not server.socket.exists()
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)
    server.stop()


def test_data_survives_stop_and_a_killed_server(tmp_path: Path) -> None:
    with EmbeddedRedis(tmp_path) as url:
        client = connect(url)
        client.xadd("s", {"codes": b"\x00\xff" * 10})
        client.set("k", "v")
    assert EmbeddedRedis(tmp_path).url == url
    server = EmbeddedRedis(tmp_path)
    client = connect(server.start())
    client.set("k2", "v2")
    assert server.pid is not None
    os.kill(server.pid, signal.SIGKILL)
    server.stop()
    with EmbeddedRedis(tmp_path) as url:
        client = connect(url)
        assert client.get("k") == b"v" and client.get("k2") == b"v2"
        assert client.xrange("s")[0][1] == {b"codes": b"\x00\xff" * 10}


def test_a_kept_alive_server_that_dies_is_restarted_with_its_data(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    server = EmbeddedRedis(tmp_path, keep_alive=True)
    client = connect(server.start())
    client.set("accepted", "job")
    first = server.pid
    assert first is not None
    # What redis-server logs before it exits by itself on a full disk.
    reason = "# Can't recover from AOF write error: No space left on device. Exiting..."
    with (tmp_path / "redis" / "redis.log").open("a") as log_file:
        log_file.write(reason + "\n")
    os.kill(first, signal.SIGKILL)
    deadline = time.monotonic() + 20
    while (server.pid in (None, first) or server.restarts == 0) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert server.restarts == 1 and server.pid not in (None, first)
    # The operator is told why it exited, not only that it did.
    assert f"its log ends: {reason}); restarting it" in caplog.text
    assert client.get("accepted") == b"job"  # the same client reconnects to the same socket
    with pytest.raises(ChildProcessError):
        os.waitpid(first, os.WNOHANG)  # the dead server was reaped, no zombie left
    second = server.pid
    server.stop()
    time.sleep(2.5 * WATCH_INTERVAL_S)
    assert server.pid is None and server.restarts == 1 and not server.socket.exists()
    with pytest.raises(ProcessLookupError):
        os.kill(second, 0)


class RefusedConfig:
    """Makes writes of a ``redis.conf`` fail with ``error`` while :attr:`on` (a full or
    read-only disk), counting the refusals; other files are written as usual."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch, error: OSError) -> None:
        self.on = True
        self.refusals = 0
        write_text = Path.write_text

        def refusing(path: Path, *args: Any, **kwargs: Any) -> int:
            if self.on and path.name == "redis.conf":
                self.refusals += 1
                raise error
            return write_text(path, *args, **kwargs)

        monkeypatch.setattr(Path, "write_text", refusing)


def test_a_full_disk_at_start_names_the_file_and_what_to_do(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A full disk raised the bare OSError of the write, which has no file name: `mcam
    serve` said "error: No space left on device" alone."""
    RefusedConfig(monkeypatch, OSError(errno.ENOSPC, "No space left on device"))
    server = EmbeddedRedis(tmp_path)
    with pytest.raises(RedisStartError) as caught:
        server.start()
    message = caught.value.message
    assert str(tmp_path / "redis" / "redis.conf") in message
    assert "No space left on device" in message and "free space" in message
    assert server.pid is None
    EmbeddedRedis(tmp_path)._own_the_dir()  # the refused start let go of the data dir


def test_a_server_that_died_on_an_unwritable_disk_is_restarted_once_it_is_writable(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The watcher's restart failing to write redis.conf ended the watcher thread with a
    traceback, and the server was never restarted: the service stayed down for good."""
    server = EmbeddedRedis(tmp_path, keep_alive=True)
    client = connect(server.start())
    client.set("accepted", "job")
    first = server.pid
    assert first is not None
    refused = RefusedConfig(monkeypatch, OSError(errno.EROFS, "Read-only file system"))
    os.kill(first, signal.SIGKILL)
    deadline = time.monotonic() + 20
    while refused.refusals < 2 and time.monotonic() < deadline:
        time.sleep(0.05)
    assert refused.refusals >= 1 and server.restarts == 0
    refused.on = False
    while server.restarts == 0 and time.monotonic() < deadline + 20:
        time.sleep(0.05)
    try:
        assert server.restarts == 1 and client.get("accepted") == b"job"
    finally:
        server.stop()


def test_long_data_dir_uses_a_short_socket_path(tmp_path: Path) -> None:
    deep = tmp_path / ("d" * 60) / ("e" * 60)
    with EmbeddedRedis(deep) as url:
        assert len(url) < 110
        assert connect(url).ping()
    assert EmbeddedRedis(deep).url == url


@pytest.mark.parametrize("url", ["http://localhost", "localhost:6379", ""])
def test_connect_rejects_unknown_schemes(url: str) -> None:
    with pytest.raises(McamError, match="unsupported Redis URL"):
        connect(url)


@pytest.mark.parametrize(
    ("url", "shown"),
    [
        ("redis://:s3cret@h:6379/0", "redis://:***@h:6379/0"),
        ("redis://user:s3cret@h/1", "redis://user:***@h/1"),
        ("rediss://user@h", "rediss://user@h"),
        ("unix:///run/r.sock?password=s3cret&db=2", "unix:///run/r.sock?password=***&db=2"),
        ("redis://h:6379", "redis://h:6379"),
        ("redis://:s3cret@[::1", "redis:***@[::1"),  # urlsplit refuses it
        ("redis://[::1?password=s3cret", "redis://[::1"),
        ("localhost:6379", "localhost:6379"),  # was shown as '://localhost:6379'
    ],
)
def test_a_logged_url_has_its_password_masked(url: str, shown: str) -> None:
    """The API logged 'Redis at redis://:<password>@...' when the server could lose jobs."""
    assert redacted_url(url) == shown


def test_an_unsupported_url_is_refused_without_its_password() -> None:
    with pytest.raises(McamError, match="unsupported Redis URL") as refused:
        connect("redis:/:s3cret@h:6379")
    assert "s3cret" not in refused.value.message


def test_connect_accepts_tcp_urls_without_connecting() -> None:
    assert connect("redis://127.0.0.1:1/0").connection_pool.connection_kwargs["port"] == 1
    assert connect("rediss://127.0.0.1:1").connection_pool.connection_kwargs["port"] == 1


def test_second_server_on_the_same_data_dir_is_refused(tmp_path: Path) -> None:
    with EmbeddedRedis(tmp_path):
        with pytest.raises(RedisStartError, match="already serves"):
            EmbeddedRedis(tmp_path).start()


def test_a_refused_second_server_leaves_the_running_one_its_socket(tmp_path: Path) -> None:
    """A second ``mcam serve`` on the same data dir was refused, then stopped its
    EmbeddedRedis on the way out, which removed the running server's socket: the
    running API and workers said 'queue unreachable' until restarted."""
    with EmbeddedRedis(tmp_path) as url:
        second = EmbeddedRedis(tmp_path)
        with pytest.raises(RedisStartError, match="already serves"):
            second.start()
        second.stop()
        assert connect(url).ping()


def test_a_second_server_is_refused_while_the_first_ones_server_is_down(tmp_path: Path) -> None:
    """The only sign of another owner was a server that answers: a second `mcam serve`
    started while the first's server was down (killed, and about to be restarted by its
    keep-alive), or two started at once, ran two redis-servers on one append-only file."""
    first = EmbeddedRedis(tmp_path)
    first.start()
    assert first.pid is not None
    os.kill(first.pid, signal.SIGKILL)
    deadline = time.monotonic() + 10
    while first._answers() and time.monotonic() < deadline:
        time.sleep(0.02)
    second = EmbeddedRedis(tmp_path)
    with pytest.raises(RedisStartError, match="already serves"):
        second.start()
    assert second.pid is None
    first.stop()
    with EmbeddedRedis(tmp_path) as url:  # the first let go of the data dir
        assert connect(url).ping()


def test_a_damaged_append_only_file_is_refused_with_a_repair_that_works(tmp_path: Path) -> None:
    """redis-server's log said to run redis-check-aof, which is not installed: the
    service stayed down with no way given to repair its data dir."""
    with EmbeddedRedis(tmp_path) as url:
        connect(url).set("kept", "1")
    aof = tmp_path / "redis" / "appendonly.aof"
    with aof.open("ab") as file:  # a damaged command, then a good one
        file.write(b"*3\r\n$3\r\nSET\r\n$1\r\nk\r\nDAMAGE\r\n*1\r\n$4\r\nPING\r\n")
    with pytest.raises(RedisStartError) as refused:
        EmbeddedRedis(tmp_path, startup_timeout_s=5).start()
    repair = re.search(r"\(exec -a redis-check-aof (\S+) --fix (\S+)\) in bash", str(refused.value))
    assert repair is not None and repair[2] == str(aof)
    subprocess.run(["redis-check-aof", "--fix", repair[2]], executable=repair[1],
                   input=b"y\n", capture_output=True, check=True)  # fmt: skip
    with EmbeddedRedis(tmp_path) as url:
        assert connect(url).get("kept") == b"1"


def test_server_stops_when_its_parent_is_killed(tmp_path: Path) -> None:
    script = (
        "import sys, time; from pathlib import Path; from worker.embedded_redis import "
        "EmbeddedRedis; s = EmbeddedRedis(Path(sys.argv[1])); s.start(); "
        "print(s.pid, flush=True); time.sleep(120)"
    )
    parent = subprocess.Popen(
        [sys.executable, "-c", script, str(tmp_path)], stdout=subprocess.PIPE, text=True
    )
    assert parent.stdout is not None
    server_pid = int(parent.stdout.readline())
    parent.kill()
    parent.wait()
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        try:
            os.kill(server_pid, 0)
        except ProcessLookupError:
            break
        time.sleep(0.05)
    else:
        pytest.fail("the embedded redis-server outlived its parent")
    parent.stdout.close()


def test_durability_problem_names_a_redis_that_could_lose_accepted_jobs(tmp_path: Path) -> None:
    with EmbeddedRedis(tmp_path) as url:
        client = connect(url)
        assert durability_problem(client) is None  # the embedded default is durable
        client.config_set("appendfsync", "everysec")
        assert "'everysec', not 'always'" in (durability_problem(client) or "")
        client.config_set("appendonly", "no")
        assert "no append-only file" in (durability_problem(client) or "")
    assert durability_problem(connect(url, timeout_s=1.0)) is None  # unreachable: no claim
