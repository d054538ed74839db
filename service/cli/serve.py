"""``mcam serve``: the whole service in one command: embedded Redis, one worker, the API.

Usage::

    mcam serve --host 127.0.0.1 --port 8000

With ``MCAM_REDIS_URL`` unset it starts the private redis-server in the data dir
(``worker/embedded_redis.py``); the worker runs as a child process (``mcam
worker``) and the API (``service.main:create_app``) under uvicorn in this
process. It prints the URL and, on first start, the generated API key. Ctrl-C or
SIGTERM stops the API, then the worker (gracefully), then the embedded Redis.
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
from types import FrameType

import uvicorn

from service.cli.api import announce, settings_with
from service.core.config import get_settings
from service.core.security import KeyRing
from service.main import create_app
from worker.embedded_redis import EmbeddedRedis, terminate_with_parent

#: How long the worker may take to finish its in-flight work on shutdown (s).
WORKER_STOP_S = 30.0


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser(
        "serve",
        help="run API + worker + embedded queue",
        description="Run the API, one worker and (without MCAM_REDIS_URL) the embedded Redis.",
    )
    parser.add_argument("--host", help="listen address (default: MCAM_HOST or 127.0.0.1)")
    parser.add_argument("--port", type=int, help="listen port (default: MCAM_PORT or 8000)")
    parser.add_argument("--concurrency", type=int, help="the worker's concurrent jobs")
    parser.add_argument("--threads", type=int, help="the worker's ONNX intra-op threads")
    parser.set_defaults(func=run)


def start_worker(redis_url: str, data_dir: str, args: argparse.Namespace) -> subprocess.Popen:
    """The worker child process, pointed at the same Redis and data dir (its own session:
    a terminal's Ctrl-C reaches only us, and we stop it once, gracefully)."""
    command = [sys.executable, "-m", "service.cli.main", "worker"]
    if args.concurrency is not None:
        command += ["--concurrency", str(args.concurrency)]
    if args.threads is not None:
        command += ["--threads", str(args.threads)]
    env = {**os.environ, "MCAM_REDIS_URL": redis_url, "MCAM_DATA_DIR": data_dir}
    return subprocess.Popen(
        command, env=env, start_new_session=True, preexec_fn=terminate_with_parent
    )


def stop_worker(process: subprocess.Popen) -> None:
    """SIGTERM, wait for in-flight work, then kill if it hangs."""
    if process.poll() is None:
        process.terminate()
        try:
            process.wait(WORKER_STOP_S)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


def _interrupt(_signum: int, _frame: FrameType | None) -> None:
    raise KeyboardInterrupt


def run(args: argparse.Namespace) -> int:
    settings = settings_with(get_settings(), host=args.host, port=args.port)
    embedded = EmbeddedRedis(settings.data_dir) if settings.redis_url is None else None
    worker: subprocess.Popen | None = None
    signal.signal(signal.SIGTERM, _interrupt)
    try:
        if embedded is not None:
            settings = settings_with(settings, redis_url=embedded.start())
        _, new_key = KeyRing.from_settings(settings)
        worker = start_worker(str(settings.redis_url), str(settings.data_dir.resolve()), args)
        announce(settings, new_key)
        uvicorn.run(create_app(settings), host=settings.host, port=settings.port, log_level="info")
    except KeyboardInterrupt:
        pass
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        if worker is not None:
            stop_worker(worker)
        if embedded is not None:
            embedded.stop()
    return 0
