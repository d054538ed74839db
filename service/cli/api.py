"""``mcam api``: run the REST API and the web viewer (no worker) with uvicorn.

With ``MCAM_REDIS_URL`` unset it starts the embedded Redis in the data dir;
jobs then need a worker on the same data dir (``mcam worker``) or use
``mcam serve``, which runs everything in one command.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import signal
import socket
import sys
from types import FrameType
from typing import Any

import uvicorn
from pydantic import ValidationError
from uvicorn.config import STARTUP_FAILURE

from models.errors import InvalidInputError
from models.stop_signals import handle_stop_signals
from service.api.header_timeout import header_timeout_protocol
from service.api.state import embedded_redis_for
from service.core.config import Settings, get_settings
from service.core.security import KEY_FILE_NAME, KeyRing
from service.main import create_app


def settings_with(settings: Settings, **updates: Any) -> Settings:
    """``settings`` with the given (non-None) values replaced, validated; a bad value
    given as a flag (``--port 99999``) is blamed on the flag, not on ``MCAM_PORT``."""
    given = {name: value for name, value in updates.items() if value is not None}
    try:
        return Settings.model_validate({**settings.model_dump(), **given})
    except ValidationError as exc:
        flagged = [error for error in exc.errors() if error["loc"] and error["loc"][0] in given]
        if not flagged:
            raise
        raise InvalidInputError(
            "; ".join(
                f"--{str(error['loc'][0]).replace('_', '-')} {error['input']}: {error['msg']}"
                for error in flagged
            )
        ) from None


def check_listen_address(settings: Settings) -> None:
    """Refuse, before anything starts, a host and port this machine cannot listen on
    (an unknown name, an address not its own, a port in use or reserved): uvicorn found
    them only after the API had been announced, and said "[Errno -2] Name or service
    not known" without the host, exiting 3. Each address the host resolves to is bound
    once and released, as uvicorn then binds it."""
    host, port = settings.host, settings.port
    try:
        addresses = socket.getaddrinfo(
            host or None, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE
        )
        for family, kind, protocol, _, address in addresses:
            with socket.socket(family, kind, protocol) as probe:
                probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                probe.bind(address)
    except OSError as exc:
        raise InvalidInputError(
            f"cannot listen on {host}:{port} ({exc.strerror or exc}); give --host "
            "(MCAM_HOST) an address of this machine and --port (MCAM_PORT) a free port"
        ) from None


def api_url(settings: Settings) -> str:
    """The API's base URL; an IPv6 address in brackets, as URLs write it (it printed
    ``http://::1:8000/``, which no client takes)."""
    host = f"[{settings.host}]" if ":" in settings.host else settings.host
    return f"http://{host}:{settings.port}/"


def announce(settings: Settings, new_key: str | None) -> None:
    """Print where the API listens and, once, a newly generated API key."""
    print(f"MantissaCam API on {api_url(settings)} (docs: /docs)")
    if new_key is not None:
        print(
            f"generated API key (stored in {settings.data_dir / KEY_FILE_NAME}): {new_key}\n"
            f"use it as: Authorization: Bearer {new_key}"
        )
    sys.stdout.flush()


def uvicorn_options(settings: Settings) -> dict[str, Any]:
    """uvicorn's listen address, connection limits and timeouts from the settings.

    uvicorn (0.54, h11) has no timeout of its own for a request whose head never
    finishes: its h11 protocol gets one (:mod:`service.api.header_timeout`), and a
    body's pauses have theirs in the app (:mod:`service.api.body_timeout`).
    ``limit_concurrency`` bounds the connections and requests at once, beyond which
    requests get a 503; ``h11_max_incomplete_event_size`` bounds the bytes of an
    unfinished request line and headers; ``timeout_graceful_shutdown`` ends a stop that
    waits on open requests (an event stream never ends by itself: one kept the server
    from stopping for as long as its client stayed).
    """
    return {
        "host": settings.host,
        "port": settings.port,
        "log_level": "info",
        "http": header_timeout_protocol(settings.http_header_timeout_s),
        "timeout_keep_alive": settings.http_keep_alive_s,
        "limit_concurrency": settings.http_max_connections,
        "h11_max_incomplete_event_size": settings.http_max_header_bytes,
        "timeout_graceful_shutdown": settings.http_shutdown_grace_s,
    }


class StoppingServer(uvicorn.Server):
    """uvicorn's server that, on a stop signal, first tells the app's requests waiting
    for their jobs (``Prefer: wait``) to answer (202) at once
    (:attr:`service.api.state.ServiceState.stopping`): they held the stop for the whole
    grace period (``MCAM_HTTP_SHUTDOWN_GRACE_S``), and then their clients got a 500
    for jobs that were stored, and might submit them again."""

    def handle_exit(self, sig: int, frame: FrameType | None) -> None:
        state = getattr(self.config.app.state, "mcam", None)  # set once the app started
        if state is not None:
            state.stopping.set()
        super().handle_exit(sig, frame)

    async def shutdown(self, sockets: list[socket.socket] | None = None) -> None:
        """uvicorn's stop, where a second Ctrl-C (its force quit) cancels the open
        requests and still runs the app's shutdown: uvicorn skipped both, and when the
        event loop closed it cancelled them, each request and the lifespan logging a
        ``CancelledError`` traceback, with the Redis connections left open."""
        await super().shutdown(sockets)
        if self.force_exit:
            await self._cancel_requests()
            if not self.lifespan.shutdown_event.is_set():
                await self.lifespan.shutdown()

    async def _cancel_requests(self) -> None:
        """Cancel the requests still running and wait until they have ended."""
        tasks = list(self.server_state.tasks)
        if tasks:
            logging.getLogger("uvicorn.error").warning(
                "Cancel %d running task(s): Ctrl-C pressed again", len(tasks)
            )
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)


def without_cancelled_requests(record: logging.LogRecord) -> bool:
    """A filter for uvicorn's log: drops a request's ``CancelledError`` traceback. uvicorn
    cancels requests only when it stops (past ``MCAM_HTTP_SHUTDOWN_GRACE_S``, or at a
    second Ctrl-C) and says how many in a line of its own."""
    return not (record.exc_info and isinstance(record.exc_info[1], asyncio.CancelledError))


def serve_http(settings: Settings) -> None:
    """Run the API (``service.main:create_app``) under uvicorn until it is stopped; exit
    3 (uvicorn's startup failure) if it never started.

    Ctrl-C and SIGTERM (:data:`~models.stop_signals.STOP_SIGNALS`) stop the server from
    before its run to its end, and are ignored after it, while the caller stops Redis
    and the workers: outside uvicorn's own handlers, asyncio's SIGINT handler cancelled
    the server's task or raised ``KeyboardInterrupt`` in it (uvicorn passes each signal
    it caught on when it ends), and a second Ctrl-C printed a traceback out of the app's
    lifespan."""
    server = StoppingServer(uvicorn.Config(create_app(settings), **uvicorn_options(settings)))
    logging.getLogger("uvicorn.error").addFilter(without_cancelled_requests)
    handle_stop_signals(server.handle_exit)
    try:
        server.run()
    finally:
        handle_stop_signals(signal.SIG_IGN)
    if not server.started:
        sys.exit(STARTUP_FAILURE)


def add_listen_arguments(parser: argparse.ArgumentParser) -> None:
    """``--host`` and ``--port`` (defaults from the settings), for every command that listens."""
    parser.add_argument("--host", help="listen address (default: MCAM_HOST or 127.0.0.1)")
    parser.add_argument("--port", type=int, help="listen port (default: MCAM_PORT or 8000)")


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser(
        "api",
        help="run the REST API and web viewer",
        description="Run the REST API and web viewer (workers run separately: mcam worker).",
    )
    add_listen_arguments(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    settings = settings_with(get_settings(), host=args.host, port=args.port)
    check_listen_address(settings)
    embedded = embedded_redis_for(settings)
    try:
        if embedded is not None:
            settings = settings_with(settings, redis_url=embedded.start())
        _, new_key = KeyRing.from_settings(settings)
        announce(settings, new_key)
        serve_http(settings)
    finally:
        if embedded is not None:
            embedded.stop()
    return 0
