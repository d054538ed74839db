"""The virtual camera's end of the link: a pty, a TCP server, or pyserial's ``loop://``.

Every endpoint offers the same small interface: :meth:`write` (returns False if
the bytes could not be delivered, e.g. nobody is connected), :meth:`read`
(non-blocking, host -> device bytes), :meth:`disconnect` / :meth:`reconnect`
(the cable is pulled and plugged back) and :meth:`close`. ``url`` is what the
host passes to ``mcam device --port``.
"""

from __future__ import annotations

import contextlib
import os
import queue
import select
import socket
import tempfile
import tty
from pathlib import Path
from typing import Protocol

import serial

from models.errors import InvalidInputError

#: How long a write waits for the host to drain the link before giving up (s).
WRITE_TIMEOUT_S = 1.0
#: Largest TCP port number.
MAX_TCP_PORT = 65_535


class Endpoint(Protocol):
    """Device side of a link."""

    url: str

    def write(self, data: bytes) -> bool: ...
    def read(self) -> bytes: ...
    def disconnect(self) -> None: ...
    def reconnect(self) -> None: ...
    def close(self) -> None: ...


def _write_fd(fd: int, data: bytes, timeout_s: float) -> bool:
    """Write all of ``data`` to a non-blocking fd, waiting up to ``timeout_s`` per stall."""
    view = memoryview(data)
    while view:
        _, ready, _ = select.select([], [fd], [], timeout_s)
        if not ready:
            return False
        try:
            sent = os.write(fd, view)
        except BlockingIOError:
            continue
        except OSError:
            return False
        view = view[sent:]
    return True


def _is_pty_link(path: Path) -> bool:
    """Whether ``path`` is a symlink to a pseudo-terminal (ours, or a run's left over)."""
    return path.is_symlink() and os.readlink(path).startswith("/dev/pts/")


def _remove_pty_link(path: Path) -> None:
    """Remove ``path`` if it is a pty symlink; anything else there is left alone."""
    if _is_pty_link(path):
        with contextlib.suppress(FileNotFoundError):
            path.unlink()


class PtyEndpoint:
    """A pseudo-terminal; ``url`` is a stable symlink to the current slave (like /dev/serial/by-id).

    Disconnecting closes the pty (the host's reads fail); reconnecting opens a new
    one and re-points the symlink, so the host finds the camera at the same path.
    """

    def __init__(self, link_path: Path | None = None) -> None:
        self._own_dir: Path | None = None
        if link_path is None:
            self._own_dir = Path(tempfile.mkdtemp(prefix="mcam-pty-"))
            link_path = self._own_dir / "scamp5"
        self.link_path = Path(link_path)
        if not self.link_path.parent.exists():
            raise InvalidInputError(
                f"directory {self.link_path.parent} does not exist, so the simulated "
                f"camera's port {self.link_path} cannot be made there; create the "
                "directory, or name a path in an existing one (pty alone picks a temporary one)"
            )
        for path in (self.link_path, self._new_link()):
            if os.path.lexists(path) and not _is_pty_link(path):
                raise InvalidInputError(
                    f"{path} exists and is not a link to a pseudo-terminal; the simulated "
                    "camera's port is a symlink it makes and removes: name a new path"
                )
        if os.path.exists(self.link_path):  # a link to a pty that is open: a live camera's
            raise InvalidInputError(
                f"{self.link_path} is the port of a simulated camera that is running (it "
                f"links to {os.path.realpath(self.link_path)}); stop that one, or name "
                "another path (remove the link if no camera runs)"
            )
        self.url = str(self.link_path)
        self._master = -1
        self._slave = -1
        self.reconnect()

    @property
    def slave_path(self) -> str:
        """The current /dev/pts/N path."""
        return os.ttyname(self._slave)

    def reconnect(self) -> None:
        """Open a fresh pty in raw mode and point the symlink at it."""
        self.disconnect()
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        tmp = self._new_link()
        _remove_pty_link(tmp)
        tmp.symlink_to(self.slave_path)
        tmp.replace(self.link_path)

    def _new_link(self) -> Path:
        """Where the next symlink is made before it replaces :attr:`link_path`."""
        return self.link_path.with_name(self.link_path.name + ".new")

    def disconnect(self) -> None:
        """Close both ends and remove the symlink (the port disappears)."""
        _remove_pty_link(self.link_path)
        for fd in (self._master, self._slave):
            if fd >= 0:
                os.close(fd)
        self._master = self._slave = -1

    def write(self, data: bytes) -> bool:
        """Send bytes to the host; False if the host did not drain the pty in time."""
        return self._master >= 0 and _write_fd(self._master, data, WRITE_TIMEOUT_S)

    def read(self) -> bytes:
        """Host -> device bytes waiting now (never blocks)."""
        if self._master < 0:
            return b""
        try:
            return os.read(self._master, 65536)
        except (BlockingIOError, OSError):
            return b""

    def close(self) -> None:
        """Disconnect for good (and remove the temporary folder of the symlink, if ours)."""
        self.disconnect()
        if self._own_dir is not None:
            with contextlib.suppress(OSError):
                self._own_dir.rmdir()


class TcpEndpoint:
    """A TCP server for one host at a time; ``url`` is ``socket://HOST:PORT``."""

    def __init__(self, host: str = "127.0.0.1", port: int = 0) -> None:
        self.host = host
        self.port = port
        self._server: socket.socket | None = None
        self._client: socket.socket | None = None
        self.reconnect()
        self.url = f"socket://{self.host}:{self.port}"

    def reconnect(self) -> None:
        """Listen again on the same port."""
        self.disconnect()
        server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        server.bind((self.host, self.port))
        server.listen(1)
        server.setblocking(False)
        self.port = server.getsockname()[1]
        self._server = server

    def disconnect(self) -> None:
        """Drop the host and stop listening."""
        for sock in (self._client, self._server):
            if sock is not None:
                sock.close()
        self._client = self._server = None

    def _accept(self) -> socket.socket | None:
        if self._client is None and self._server is not None:
            try:
                client, _ = self._server.accept()
            except BlockingIOError:
                return None
            client.setblocking(False)
            client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self._client = client
        return self._client

    def write(self, data: bytes) -> bool:
        """Send bytes to the connected host; False if none is connected or it stalls."""
        client = self._accept()
        if client is None:
            return False
        if not _write_fd(client.fileno(), data, WRITE_TIMEOUT_S):
            client.close()
            self._client = None
            return False
        return True

    def read(self) -> bytes:
        """Host -> device bytes waiting now (never blocks)."""
        client = self._accept()
        if client is None:
            return b""
        try:
            data = client.recv(65536)
        except BlockingIOError:
            return b""
        except OSError:
            data = b""
        if not data:
            client.close()
            self._client = None
        return data

    def close(self) -> None:
        """Stop serving."""
        self.disconnect()


class LoopEndpoint:
    """pyserial ``loop://``: what the device writes, the host reads from :attr:`port`.

    Output only: the host's control writes would loop back to the host, so the
    device never reads (use a pty or TCP to test control packets). pyserial's loop
    holds only 4096 bytes, so the host must read while the device writes.
    """

    url = "loop://"

    def __init__(self) -> None:
        self.port = serial.serial_for_url(
            "loop://", timeout=0.05, write_timeout=WRITE_TIMEOUT_S, baudrate=4_000_000
        )

    def write(self, data: bytes) -> bool:
        """Append bytes for the host; False if it does not read them in time."""
        try:
            return self.port.is_open and self.port.write(data) == len(data)
        except (serial.SerialException, queue.Full):  # the loop's queue stayed full
            return False

    def read(self) -> bytes:
        """Nothing: see the class docstring."""
        return b""

    def disconnect(self) -> None:
        """loop:// cannot be unplugged; ignored."""

    def reconnect(self) -> None:
        """loop:// cannot be unplugged; ignored."""

    def close(self) -> None:
        """Close the loop port."""
        self.port.close()


def pty_link_path(url: str) -> Path:
    """The symlink a ``pty:PATH`` port names; refused when PATH names no file (``pty:``,
    ``pty:/``, ``pty:.``), which ended in a bare ValueError traceback ("PosixPath('.')
    has an empty name")."""
    path = Path(url[len("pty:"):])
    if not path.name:
        raise InvalidInputError(
            f"bad simulator port {url!r}: pty:PATH names the symlink to make, such as "
            "pty:/tmp/scamp5 (not a folder); or give pty alone for a temporary one"
        )
    return path


def open_endpoint(url: str) -> Endpoint:
    """``pty`` or ``pty:PATH`` (symlink), ``socket://HOST:PORT`` (server), or ``loop://``."""
    if url == "pty":
        return PtyEndpoint()
    if url.startswith("pty:"):
        return PtyEndpoint(pty_link_path(url))
    if url.startswith("socket://"):
        host, _, port = url[len("socket://") :].rpartition(":")
        if not port.isdigit() or int(port) > MAX_TCP_PORT:
            raise InvalidInputError(
                f"bad socket URL {url!r}: use socket://HOST:PORT, PORT from 0 to {MAX_TCP_PORT}"
            )
        return TcpEndpoint(host or "127.0.0.1", int(port))
    if url == "loop://":
        return LoopEndpoint()
    raise InvalidInputError(
        f"unsupported simulator port {url!r}: use pty, pty:PATH or socket://HOST:PORT "
        "(loop:// reaches readers in the same process only)"
    )
