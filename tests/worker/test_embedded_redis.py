"""EmbeddedRedis: a private redis-server on a unix socket with append-only persistence."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import pytest

from models.errors import McamError
from worker.embedded_redis import EmbeddedRedis, connect


def test_start_serves_unix_socket_and_stop_cleans_up(tmp_path: Path) -> None:
    server = EmbeddedRedis(tmp_path)
    url = server.start()
    assert url.startswith("unix://") and server.socket.exists()
    assert connect(url).ping()
    config = (tmp_path / "redis" / "redis.conf").read_text()
    assert "appendonly yes" in config and "appendfsync everysec" in config and "port 0" in config
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


def test_connect_accepts_tcp_urls_without_connecting() -> None:
    assert connect("redis://127.0.0.1:1/0").connection_pool.connection_kwargs["port"] == 1
    assert connect("rediss://127.0.0.1:1").connection_pool.connection_kwargs["port"] == 1
