"""Opening the camera port (``device/serial_ports.py``): port URLs refused up front, ports
that do not open named with what to do, locked ports and rfc2217:// servers, through a
daemon on a real redis-server."""

from __future__ import annotations

import contextlib
import importlib.util
import logging
import os
import re
import socket
import stat
import threading
import tty
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import redis
import serial
import serial.rfc2217

from device import link_protocol as lp
from device.commands import FrameRateCommand, to_packet
from device.daemon import DaemonConfig, DeviceDaemon
from device.serial_ports import RFC2217_UNANSWERED, port_problem, serial_opener
from device.sim_link import PtyEndpoint
from models.errors import InvalidInputError
from tests.device.conftest import health, wait_for, wire


@pytest.mark.parametrize(("name", "missing"), [
    ("no-such-dir/tty", "directory {port.parent} does not exist"),
    ("no-such-tty", "{port} does not exist"),
    ("dangling", "{port} is a link to {port.parent}/gone, which does not exist"),
], ids=["directory", "file", "dangling-link"])
def test_a_port_that_does_not_exist_says_so_and_what_to_do_and_is_retried(
        client: redis.Redis, tmp_path: Path, caplog: pytest.LogCaptureFixture, name: str,
        missing: str) -> None:
    """pyserial said only 'No such file or directory', naming the path three times; the
    daemon goes on trying, and opens the port once it appears."""
    port = tmp_path / name
    (tmp_path / "dangling").symlink_to(tmp_path / "gone")
    reason = (f"{missing.format(port=port)}: check --port, or plug the camera in or start "
              "mcam simulate-device (it prints the path to give)")
    config = DaemonConfig(port=str(port), device="cam1", backoff_max_s=0.05)
    with caplog.at_level(logging.WARNING, logger="device.daemon"):
        daemon = DeviceDaemon(config, client).start()
        try:
            assert wait_for(lambda: health(client, "cam1").get("port_error") == reason, 10)
            port.parent.mkdir(exist_ok=True)
            port.unlink(missing_ok=True)
            camera = PtyEndpoint(port)
            # Read together while connected: once the camera closes, the retries set the
            # port's error again.
            assert wait_for(lambda: (daemon.health.state, daemon.health.port_error)
                            == ("connected", ""), 10)
            camera.close()
        finally:
            daemon.stop()
    assert f"cannot open {port}: {reason}; retrying" in caplog.records[0].getMessage()


def assert_port_named(client: redis.Redis, port: Path, kind: str) -> None:
    """A daemon on ``port`` reports it as ``kind`` (a directory, a disk...), not a serial
    port, with what to do."""
    reason = (f"{port} is {kind}, not a serial port: check --port (a camera is a terminal "
              "device such as /dev/ttyACM0; mcam simulate-device prints the path to give)")
    daemon = DeviceDaemon(DaemonConfig(port=str(port), device="cam1", backoff_max_s=0.05),
                          client).start()
    try:
        assert wait_for(lambda: health(client, "cam1").get("port_error") == reason, 10)
    finally:
        daemon.stop()


@pytest.mark.parametrize(("name", "kind"), [
    ("folder", "a directory"),
    ("plain", "a regular file"),
    ("/dev/null", "a character device that is not a terminal"),
], ids=["directory", "regular-file", "dev-null"])
def test_a_port_that_is_no_terminal_says_what_it_is(
        client: redis.Redis, tmp_path: Path, name: str, kind: str) -> None:
    """pyserial said 'Could not configure port: (25, 'Inappropriate ioctl for device')'
    for a regular file or /dev/null, naming neither the path nor what to do."""
    (tmp_path / "folder").mkdir()
    (tmp_path / "plain").write_bytes(b"")
    assert_port_named(client, tmp_path / name, kind)


def test_a_port_that_is_a_block_device_says_so(client: redis.Redis, tmp_path: Path) -> None:
    """pyserial said 'Could not configure port: (22, 'Invalid argument')' for a block
    device (a disk: a camera plugged in as USB storage shows as /dev/sdb), naming
    neither the path nor what to do. The node here is loop0's."""
    port = tmp_path / "disk"
    try:
        os.mknod(port, stat.S_IFBLK | 0o600, os.makedev(7, 0))
    except PermissionError:
        pytest.skip("making a block device node needs root (CAP_MKNOD)")
    assert_port_named(client, port, "a block device (a disk)")


@pytest.mark.parametrize("port", [
    "socket://127.0.0.1", "socket://127.0.0.1:99999", "socket://127.0.0.1:abc",
    "socket://:5555", "rfc2217://127.0.0.1:0",
])
def test_a_network_port_url_without_host_or_valid_port_is_refused(
        client: redis.Redis, port: str) -> None:
    """pyserial could never open these and said "'<=' not supported between instances
    of 'int' and 'NoneType'" or "'debug|info|warning|error'"; the daemon retried them for
    good. They are refused up front, saying what a port URL needs."""
    scheme = port.partition("://")[0]
    with pytest.raises(InvalidInputError, match=f"bad port URL '{re.escape(port)}': use "
                       f"{scheme}://HOST:PORT with a host and a PORT from 1 to 65535"):
        DeviceDaemon(DaemonConfig(port=port, device="cam1"), client)


def refusal(client: redis.Redis, port: str) -> str:
    """The message of the InvalidInputError a daemon on ``port`` is refused with."""
    with pytest.raises(InvalidInputError) as refused:
        DeviceDaemon(DaemonConfig(port=port, device="cam1"), client)
    return refused.value.message


@pytest.mark.parametrize(("port", "why"), [
    ("loop://?logging=DEBUG", ";"),
    ("socket://127.0.0.1:5555?logging=bogus", ";"),
    ("rfc2217://127.0.0.1:5555?timeout=abc", "could not convert string to float: 'abc'"),
    ("loop://?baud=9600", ";"),
])
def test_a_port_url_with_an_option_pyserial_refuses_is_refused(
        client: redis.Redis, port: str, why: str) -> None:
    """pyserial refuses these at every open: ``loop://?logging=DEBUG`` (its levels are
    lower case) killed the daemon's thread with a bare KeyError traceback and ``mcam
    device`` exited 0; the others were retried for good with a cryptic reason. They are
    refused up front, naming the options a port URL takes."""
    message = refusal(client, port)
    assert message.startswith(f"bad option in port URL {port!r}")
    assert why in message and "?logging=debug, info, warning or error" in message


@pytest.mark.parametrize(("port", "why"), [
    ("alt:///dev/ttyACM0?class=Nope", " (unknown class: 'Nope');"),
    ("alt:///dev/ttyACM0?class=XON", ";"),  # a constant of pyserial's: a TypeError
    ("alt:///dev/ttyACM0?baud=9600", "unknown option: 'baud'"),
])
def test_an_alt_port_url_with_a_class_pyserial_refuses_is_refused(
        client: redis.Redis, port: str, why: str) -> None:
    """pyserial refuses these at every open: an unknown class or option was retried for
    good, and ``class=XON`` stopped the daemon on a TypeError. They are refused up front,
    naming the classes alt:// takes."""
    message = refusal(client, port)
    assert message.startswith(f"bad option in port URL {port!r}")
    assert why in message
    assert message.endswith(
        "pyserial's alt:// takes ?class= one of PosixPollSerial, Serial, VTIMESerial, or none")


def test_an_alt_port_url_with_a_serial_class_is_taken(client: redis.Redis) -> None:
    DeviceDaemon(DaemonConfig(port="alt:///dev/ttyACM0?class=PosixPollSerial", device="cam1"),
                 client)


@pytest.mark.parametrize("timeout", ["-1", "0", "nan", "inf", "61", "-1&timeout=5"])
def test_an_rfc2217_timeout_out_of_range_is_refused(client: redis.Redis, timeout: str) -> None:
    """pyserial takes any float: at 0 or below (or nan) every open failed as if the
    server did not answer RFC 2217 negotiation in time, retried for good; inf never
    ended the wait. The option and its range are named up front."""
    port = f"rfc2217://127.0.0.1:5555?timeout={timeout}"
    given = timeout.partition("&")[0]
    message = refusal(client, port)
    assert message == (
        f"bad option in port URL {port!r}: timeout={given} is out of range; give "
        "?timeout=SECONDS above 0 and at most 60 (how long the RFC 2217 server has to "
        "answer; 3 without it), or leave it out")


def test_an_rfc2217_timeout_in_range_is_taken(client: redis.Redis) -> None:
    DeviceDaemon(DaemonConfig(port="rfc2217://127.0.0.1:5555?timeout=0.5", device="cam1"),
                 client)


@pytest.mark.parametrize(("query", "option"), [
    ("bogus=1", "bogus"), ("color&raw&Bogus", "Bogus"), ("=x", ""), ("dev=/tmp/spy.log", "dev"),
])
def test_a_spy_port_url_with_an_option_pyserial_refuses_is_refused(
        client: redis.Redis, query: str, option: str) -> None:
    """pyserial refuses an unknown spy:// option at every open, and the daemon retried it
    for good. It is refused up front, naming the option and those spy:// takes."""
    port = f"spy:///dev/ttyACM0?{query}"
    message = refusal(client, port)
    assert message == (
        f"bad option in port URL {port!r} (unknown option: {option!r}); pyserial's spy:// "
        "takes ?file=PATH (where it writes the traffic it sees; standard error without it), "
        "color, raw, all, or none")


@pytest.mark.parametrize(("port", "problem"), [
    ("spy://", "it names no port"), ("spy://?color", "it names no port"),
    ("spy://socket://127.0.0.1:5555", "pyserial's spy:// cannot watch socket:// ports"),
    ("spy://loop://?raw", "pyserial's spy:// cannot watch loop:// ports"),
])
def test_a_spy_port_url_without_a_device_path_is_refused(
        client: redis.Redis, port: str, problem: str) -> None:
    """pyserial's spy:// opens what follows spy:// as a device path: these failed at
    every open with "could not open port : [Errno 2] No such file or directory: ''" (or
    the URL in its place), retried for good."""
    assert refusal(client, port) == (
        f"bad port URL {port!r}: {problem}; give spy:// the device path of the port to "
        "watch, as in spy:///dev/ttyACM0")


@pytest.mark.parametrize(("file", "problem"), [
    ("", "names no file"), ("{dir}", "is a directory"),
    ("{dir}/nope/spy.log", "is in {dir}/nope, which is no directory"),
    ("{dir}/spy%00.log", "holds a NUL character, which no file name can"),
])
def test_a_spy_port_url_whose_file_cannot_be_created_is_refused(
        client: redis.Redis, tmp_path: Path, file: str, problem: str) -> None:
    """Opening such a file failed at every open ("No such file or directory"), retried
    for good."""
    file = file.format(dir=tmp_path)
    port = f"spy:///dev/ttyACM0?file={file}"
    message = refusal(client, port)
    assert message.startswith(
        f"bad option in port URL {port!r}: file={file} {problem.format(dir=tmp_path)}; give "
        "?file= a file in an existing directory")


def test_a_spy_port_url_with_valid_options_is_taken_without_opening_its_file(
        client: redis.Redis, tmp_path: Path) -> None:
    """pyserial's own parser opens the file for writing: checking the URL with it would
    empty a file the user keeps, or leave one behind for a daemon that never starts."""
    kept = tmp_path / "kept.log"
    kept.write_text("earlier traffic")
    for file in (kept, tmp_path / "new.log"):
        DeviceDaemon(DaemonConfig(port=f"spy:///dev/ttyACM0?color&raw&all&file={file}",
                                  device="cam1"), client)
    assert kept.read_text() == "earlier traffic"
    assert not (tmp_path / "new.log").exists()


@pytest.mark.parametrize("option", ["bogus", "n=1", "n=abc", "n=", "n", "N=2", "skip_busy&x"])
def test_a_hwgrep_port_url_with_an_option_pyserial_refuses_is_refused(
        client: redis.Redis, option: str) -> None:
    """pyserial refuses these at every open: most were retried for good ("unknown option:
    'bogus'"), and ``n`` without a value stopped the daemon on a TypeError, as a bug
    (exit 1). They are refused up front, naming the option and those hwgrep:// takes."""
    port = f"hwgrep://ttyACM?&{option}"
    bad = option.rpartition("&")[2]
    assert refusal(client, port) == (
        f"bad option {bad!r} in port URL {port!r}; pyserial's hwgrep:// takes &n=N (the Nth "
        "port that matches, N from 2; the first without it) and &skip_busy, or none")


def test_a_hwgrep_port_url_whose_regexp_does_not_compile_is_refused(
        client: redis.Redis) -> None:
    """pyserial compiles it at every open: its re.error stopped the daemon as a bug."""
    assert refusal(client, "hwgrep://ttyACM[0-&n=2").startswith(
        "bad port URL 'hwgrep://ttyACM[0-&n=2': 'ttyACM[0-' is no regular expression "
        "(unterminated character set at position 6); give hwgrep://REGEXP, a Python regular "
        "expression that matches the camera's port name")


def test_a_hwgrep_port_url_with_valid_options_is_taken(client: redis.Redis) -> None:
    DeviceDaemon(DaemonConfig(port="hwgrep://(?i)scamp|ttyACM[0-9]?&n=2&skip_busy",
                              device="cam1"), client)


@pytest.mark.parametrize("port", ["my.camera://x", "loop.x://", "..://x"])
def test_a_port_url_scheme_no_module_can_have_is_refused(client: redis.Redis, port: str) -> None:
    """A scheme with a dot looked its handler up as a submodule: ``mcam device`` stopped
    with a ModuleNotFoundError traceback (exit 1)."""
    scheme = repr(port.partition("://")[0])
    with pytest.raises(InvalidInputError,
                       match=f"pyserial does not know the port URL scheme {re.escape(scheme)}"):
        DeviceDaemon(DaemonConfig(port=port, device="cam1"), client)


@pytest.mark.skipif(importlib.util.find_spec("hid") is not None, reason="hid is installed")
def test_a_port_url_whose_handler_cannot_load_names_what_is_missing(client: redis.Redis) -> None:
    """pyserial's cp2110:// needs the hid module; without it every open said "protocol
    'cp2110' not known" and the daemon retried for good."""
    with pytest.raises(InvalidInputError, match="pyserial's cp2110:// ports need the Python "
                                                "module 'hid', which is not installed"):
        DeviceDaemon(DaemonConfig(port="cp2110://10c4:ea80:0", device="cam1"), client)


def test_a_port_url_with_valid_options_is_taken(client: redis.Redis) -> None:
    DeviceDaemon(DaemonConfig(port="loop://?logging=warning", device="cam1"), client)


@pytest.mark.parametrize("port", ["LOOP://", "Socket://127.0.0.1:1", "SPY:///dev/ttyACM0",
                                  "HWGREP://scamp", "RFC2217://127.0.0.1:1?timeout=2"])
def test_a_port_url_scheme_in_capitals_is_taken_as_pyserial_takes_it(
        client: redis.Redis, port: str) -> None:
    """pyserial reads a scheme in any case; such a URL was refused up front as a scheme
    "pyserial does not know"."""
    DeviceDaemon(DaemonConfig(port=port, device="cam1"), client)


def test_a_socket_port_url_in_capitals_is_opened_non_blocking() -> None:
    """``SOCKET://`` was opened as a device path is (blocking reads), not as socket://."""
    with socket.create_server(("127.0.0.1", 0)) as server:
        port = serial_opener(f"SOCKET://127.0.0.1:{server.getsockname()[1]}", 0.5)()
        try:
            assert port.timeout == 0
        finally:
            port.close()


def test_an_rfc2217_server_that_does_not_negotiate_is_named_whatever_the_scheme_case() -> None:
    reason = port_problem("RFC2217://127.0.0.1:1",
                          serial.SerialException(f"{RFC2217_UNANSWERED} or BINARY mode"))
    assert reason.startswith("the server at 127.0.0.1:1 did not answer RFC 2217"), reason


def test_a_second_daemon_on_one_port_waits_and_says_who_holds_it(client: redis.Redis) -> None:
    """Two daemons (two device ids) on one camera's pty each got a share of its bytes:
    most frames were lost as garbage and truncated packets. The first locks the port;
    the second says another process holds it, and the first gets every frame whole."""
    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    port = os.ttyname(slave)
    first = DeviceDaemon(DaemonConfig(port=port, device="cam1"), client)
    second = DeviceDaemon(DaemonConfig(port=port, device="cam2", backoff_max_s=0.1), client)
    try:
        first.start()
        assert wait_for(lambda: first.health.state == "connected", 30)
        second.start()
        assert wait_for(lambda: "open in another process that locked it"
                        in second.health.port_error, 30)
        codes = np.zeros((32, 32), np.uint8)
        for sequence in range(20):
            os.write(master, lp.encode_data(lp.DataPacket(sequence, 0, "modulo", 2.0, 8, 1.0,
                                                          codes)))
        assert wait_for(lambda: first.health.counts["frames_received"] == 20, 30)
    finally:
        second.stop()
        first.stop()
        os.close(master)
        os.close(slave)
    assert first.health.counts["garbage_bytes"] == 0
    assert second.health.counts["frames_received"] == 0


def stop_serving(server: socket.socket) -> None:
    """Close a listening socket, waking a thread waiting in its ``accept`` (a close alone
    does not)."""
    with contextlib.suppress(OSError):
        server.shutdown(socket.SHUT_RDWR)
    server.close()


class Rfc2217Camera:
    """A camera behind a real RFC 2217 server (pyserial's ``PortManager``) on 127.0.0.1,
    for one client: once the client has spoken, it sends a data packet every 20 ms (the
    sequence counting up), and keeps what the client writes (``received``, Telnet
    negotiation left out). Use as a context manager."""

    def __init__(self) -> None:
        self.server = socket.create_server(("127.0.0.1", 0))
        self.url = f"rfc2217://127.0.0.1:{self.server.getsockname()[1]}"
        self.received = bytearray()
        self._closed = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)

    def __enter__(self) -> Rfc2217Camera:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._closed.set()
        stop_serving(self.server)
        self._thread.join(10)

    def _serve(self) -> None:
        with contextlib.suppress(OSError):
            connection, _ = self.server.accept()
            with connection:
                self._talk(connection)

    def _talk(self, connection: socket.socket) -> None:
        connection.settimeout(0.02)
        manager = serial.rfc2217.PortManager(
            serial.serial_for_url("loop://"), SimpleNamespace(write=connection.sendall)
        )
        sequence, spoken = 0, False
        while not self._closed.is_set():
            with contextlib.suppress(TimeoutError):
                data = connection.recv(4096)
                if not data:
                    return
                self.received += b"".join(manager.filter(data))
                spoken = True
            if spoken:
                connection.sendall(b"".join(manager.escape(wire(sequence))))
                sequence += 1


def test_an_rfc2217_port_carries_frames_and_commands(client: redis.Redis) -> None:
    """pyserial opens an rfc2217:// port only without a write timeout, and the daemon
    asked for one: at a real RFC 2217 server its thread died with a traceback of
    "NotImplementedError: write_timeout is currently not supported" and ``mcam device``
    exited 0 at once, so rfc2217:// never worked."""
    with Rfc2217Camera() as camera:
        daemon = DeviceDaemon(DaemonConfig(port=camera.url, device="cam1"), client).start()
        try:
            assert wait_for(lambda: daemon.health.counts["frames_ok"] >= 3, 30)
            command = FrameRateCommand(command="set_frame_rate", fps=5.0)
            daemon.send_command("1-0", command)
            packet = lp.encode_control(to_packet(command))
            assert wait_for(lambda: packet in camera.received, 30)
        finally:
            daemon.stop()
    assert daemon.failure is None and daemon.health.port_error == ""


class PlainTcpServer:
    """A TCP server on 127.0.0.1 that speaks no RFC 2217: it sends each client ``data``
    and then keeps it, until closed. Use as a context manager."""

    def __init__(self, data: bytes) -> None:
        self.server = socket.create_server(("127.0.0.1", 0))
        self.address = f"127.0.0.1:{self.server.getsockname()[1]}"
        self.data = data
        self.connections: list[socket.socket] = []
        self._thread = threading.Thread(target=self._serve, daemon=True)

    def __enter__(self) -> PlainTcpServer:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        stop_serving(self.server)
        self._thread.join(10)
        for connection in self.connections:
            connection.close()

    def _serve(self) -> None:
        with contextlib.suppress(OSError):
            while True:
                connection, _ = self.server.accept()
                self.connections.append(connection)
                connection.sendall(self.data)


@pytest.mark.parametrize("data", [b"", b"SSH-2.0-OpenSSH_9.6\r\n\xff\xf0\xff\xfa,"],
                         ids=["silent", "garbage"])
def test_a_server_that_does_not_speak_rfc2217_is_named_with_what_to_do(
        client: redis.Redis, monkeypatch: pytest.MonkeyPatch, data: bytes) -> None:
    """pyserial said "Remote does not seem to support RFC2217 or BINARY mode
    [we-BINARY:False(INACTIVE), we-RFC2217:False(REQUESTED)]"; a server that sent bytes
    that are not Telnet (an IAC SE outside a subnegotiation) also killed pyserial's
    reader thread at every attempt, printing "Exception in thread pySerial RFC 2217
    reader thread" and a TypeError traceback."""
    crashes: list[object] = []
    monkeypatch.setattr(threading, "excepthook", crashes.append)
    with PlainTcpServer(data) as server:
        url = f"rfc2217://{server.address}?timeout=0.3"
        reason = (f"the server at {server.address} did not answer RFC 2217 negotiation "
                  "(Telnet binary mode and COM port control) in time: it is no RFC 2217 "
                  f"server, or not the camera's; check the address, or give socket://"
                  f"{server.address} for a server that passes the camera's bytes as they are")
        config = DaemonConfig(port=url, device="cam1", backoff_max_s=0.05)
        daemon = DeviceDaemon(config, client).start()
        try:
            assert wait_for(lambda: daemon.health.port_error.startswith(reason)
                            and len(server.connections) >= 2, 30)
        finally:
            daemon.stop()
    assert crashes == []
