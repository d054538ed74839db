"""``mcam serve``: the whole service in one command: embedded Redis, the workers, the API.

Usage::

    mcam serve --host 127.0.0.1 --port 8000
    mcam serve --workers 2 --threads 1      # one single-threaded worker per core

With ``MCAM_REDIS_URL`` unset it starts the private redis-server in the data dir
(``worker/embedded_redis.py``); each worker runs as a child process (``mcam
worker``) and the API (``service.main:create_app``) under uvicorn in this
process. It prints the URL and, on first start, the generated API key. A worker
that dies is restarted (with backoff), and so is the embedded Redis (from its
append-only file, within a second). Ctrl-C or SIGTERM stops the API, then the
workers (gracefully), then the embedded Redis, and exits 0; another Ctrl-C meanwhile
stops waiting for open requests, and is ignored once the workers are stopping.

One worker (the default) decodes one job at a time on all its onnxruntime threads: the
least latency for one upload. Uploads and batches are decoded faster by one
single-threaded worker per core, since most of a refined decode runs on one core
(``python -m bench.throughput``, README: auto-balanced on val-256, 2 cores, 23.8
frames/s with one worker of 2 threads, 41.8 with two workers of one thread). A camera's
stream uses every core either way: its owner decodes it on a pool of processes
(:mod:`worker.decode_pool`; 40.0 frames/s for one stream in the same run).
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from types import FrameType

from models.stop_signals import handle_stop_signals
from service.api.state import embedded_redis_for
from service.cli.api import (
    announce,
    check_listen_address,
    serve_http,
    settings_with,
)
from service.cli.worker import limit_problem
from service.core.config import get_settings
from service.core.security import KeyRing
from worker.embedded_redis import terminate_with_parent

#: How long the worker may take to finish its in-flight work on shutdown (s).
WORKER_STOP_S = 30.0
#: Backoff before restarting a worker that died: first and longest wait (s).
RESTART_MIN_S = 1.0
RESTART_MAX_S = 30.0
#: A worker up this long (s) counts as healthy: its next death waits RESTART_MIN_S again.
#: (Reset as soon as a new worker was alive at a poll, the wait never passed 2 s: a
#: worker that dies at start takes over a second to import.)
HEALTHY_AFTER_S = 30.0


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser(
        "serve",
        help="run API + workers + embedded queue",
        description="Run the API, the workers and (without MCAM_REDIS_URL) the embedded Redis.",
    )
    parser.add_argument("--host", help="listen address (default: MCAM_HOST or 127.0.0.1)")
    parser.add_argument("--port", type=int, help="listen port (default: MCAM_PORT or 8000)")
    parser.add_argument(
        "--workers", type=within_limit("--workers"), default=1,
        help="worker processes to run (default: 1, at most 256)",
    )
    parser.add_argument(
        "--concurrency", type=within_limit("--concurrency"), help="each worker's concurrent jobs"
    )
    parser.add_argument(
        "--threads", type=within_limit("--threads"), help="each worker's ONNX intra-op threads"
    )
    parser.set_defaults(func=run)


def positive(text: str) -> int:
    """An argparse type: a whole number of at least 1."""
    if not text.isdigit() or int(text) < 1:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 1, got {text!r}")
    return int(text)


def within_limit(flag: str) -> Callable[[str], int]:
    """An argparse type for ``flag``: a whole number from 1 to its limit
    (:data:`service.cli.worker.FLAG_LIMITS`: a worker refuses more, and a worker that
    exits at start is restarted for ever; more workers than that only exhaust memory)."""

    def parse(text: str) -> int:
        value = positive(text)
        problem = limit_problem(flag, value)
        if problem:
            raise argparse.ArgumentTypeError(problem.removeprefix(f"{flag} "))
        return value

    return parse


def worker_command(args: argparse.Namespace) -> list[str]:
    """``mcam worker`` with serve's worker flags."""
    command = [sys.executable, "-m", "service.cli.main", "worker"]
    if args.concurrency is not None:
        command += ["--concurrency", str(args.concurrency)]
    if args.threads is not None:
        command += ["--threads", str(args.threads)]
    return command


class WorkerSupervisor:
    """Keeps one worker child running on the given Redis and data dir: restarts it (with
    backoff) if it dies, stops it gracefully at the end. The child runs in its own session
    (a terminal's Ctrl-C reaches only us) and gets SIGTERM if we die."""

    def __init__(self, command: list[str], redis_url: str, data_dir: str) -> None:
        self.command = command
        self.env = {**os.environ, "MCAM_REDIS_URL": redis_url, "MCAM_DATA_DIR": data_dir}
        self.process: subprocess.Popen[bytes] | None = None
        self._spawned_at = 0.0
        self._stopping = threading.Event()
        self._lock = threading.Lock()  # no restart once terminate() has signalled
        self._thread = threading.Thread(target=self._watch, name="worker-watch", daemon=True)

    def start(self) -> WorkerSupervisor:
        self.process = self._spawn()
        self._thread.start()
        return self

    def _spawn(self) -> subprocess.Popen[bytes]:
        self._spawned_at = time.monotonic()
        return subprocess.Popen(
            self.command, env=self.env, start_new_session=True, preexec_fn=terminate_with_parent
        )

    def _watch(self) -> None:
        """Restart the worker when it exits. A worker this thread restarted gets its
        parent-death signal when this *thread* ends (``PR_SET_PDEATHSIG`` follows the
        thread that forked), so after the last restart the thread stays until that
        worker has exited: ending earlier sent a stopping worker a second SIGTERM, and
        it dropped the job in hand."""
        backoff = RESTART_MIN_S
        while not self._stopping.wait(1.0):
            if self.process is None or self.process.poll() is None:
                if time.monotonic() - self._spawned_at >= HEALTHY_AFTER_S:
                    backoff = RESTART_MIN_S
                continue
            print(
                f"mcam serve: the worker exited ({self.process.returncode}); "
                f"restarting in {backoff:.0f} s",
                file=sys.stderr,
                flush=True,
            )
            if self._stopping.wait(backoff):
                break
            with self._lock:
                if self._stopping.is_set():
                    break
                self.process = self._spawn()
            backoff = min(backoff * 2, RESTART_MAX_S)
        if self.process is not None:
            self.process.wait()

    def terminate(self) -> None:
        """Stop restarting the worker and SIGTERM it (it finishes its in-flight work)."""
        with self._lock:
            self._stopping.set()
            if self.process is not None and self.process.poll() is None:
                self.process.terminate()

    def wait(self) -> None:
        """Wait for a terminated worker to exit, killing it if it hangs."""
        if self.process is not None:
            try:
                self.process.wait(WORKER_STOP_S)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        if self._thread.is_alive():
            self._thread.join()


def _interrupt(_signum: int, _frame: FrameType | None) -> None:
    raise KeyboardInterrupt


def run(args: argparse.Namespace) -> int:
    settings = settings_with(get_settings(), host=args.host, port=args.port)
    check_listen_address(settings)
    embedded = embedded_redis_for(settings)
    workers: list[WorkerSupervisor] = []
    signal.signal(signal.SIGTERM, _interrupt)
    try:
        if embedded is not None:
            settings = settings_with(settings, redis_url=embedded.start())
        _, new_key = KeyRing.from_settings(settings)
        for _ in range(args.workers):
            workers.append(
                WorkerSupervisor(
                    worker_command(args), str(settings.redis_url), str(settings.data_dir.resolve())
                ).start()
            )
        announce(settings, new_key)
        serve_http(settings)
    except KeyboardInterrupt:
        pass
    finally:
        handle_stop_signals(signal.SIG_IGN)  # the stop below finishes: no traceback midway
        for worker in workers:
            worker.terminate()
        for worker in workers:
            worker.wait()
        if embedded is not None:
            embedded.stop()
    return 0
