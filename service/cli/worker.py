"""``mcam worker``: run one reconstruction worker (jobs + live device streams).

Usage::

    MCAM_REDIS_URL=redis://queue:6379 mcam worker --concurrency 2 --threads 2
    mcam worker                 # no MCAM_REDIS_URL: the embedded Redis of the data dir
                                # (started by `mcam api` or `mcam serve`)

Settings come from ``MCAM_*`` (``service/core/config.py``); flags override them.
SIGTERM / Ctrl-C stop it gracefully (in-flight work is finished or handed back).
"""

from __future__ import annotations

import argparse
import os

from models.decoders.learned import THREAD_VARIABLES
from models.decoders.registry import resolve
from models.errors import McamError, naming
from service.cli.options import add_log_level_flag, start_logging
from service.core.config import (
    MAX_SERVE_WORKERS,
    MAX_STREAM_POOL_PROCESSES,
    MAX_WORKER_CONCURRENCY,
    MAX_WORKER_THREADS,
    Settings,
    get_settings,
)
from worker.embedded_redis import EmbeddedRedis
from worker.temporal_config import MODES


def redis_url_for(settings: Settings) -> str:
    """``MCAM_REDIS_URL``, else the socket of the embedded Redis in the data dir."""
    if settings.redis_url:
        return settings.redis_url
    embedded = EmbeddedRedis(settings.data_dir)
    if not embedded.socket.exists():
        raise McamError(
            f"no Redis: MCAM_REDIS_URL is unset and no embedded Redis runs for the data dir "
            f"{settings.data_dir} (its socket {embedded.socket} is missing); start `mcam api` "
            "or `mcam serve` first, or set MCAM_REDIS_URL"
        )
    return embedded.url


#: Default ceiling of a worker's stream decode processes (one per core below it): a
#: device is read in batches of 16 frames, and each process holds its own networks.
MAX_STREAM_PROCESSES = 8


def usable_cores() -> int:
    """The cores this process may run on (its CPU affinity where the OS reports one)."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


#: The flags of ``mcam worker`` and ``mcam serve`` that count threads or processes:
#: their most, and what they count.
FLAG_LIMITS: dict[str, tuple[int, str]] = {
    "--threads": (MAX_WORKER_THREADS, "onnxruntime threads per session"),
    "--concurrency": (MAX_WORKER_CONCURRENCY, "jobs decoded at once, each in a process of its own"),
    "--stream-processes": (MAX_STREAM_POOL_PROCESSES, "processes decoding device streams"),
    "--workers": (MAX_SERVE_WORKERS, "worker processes, each with its decoding processes"),
}


def limit_problem(flag: str, value: int) -> str | None:
    """Why ``value`` of ``flag`` (one of :data:`FLAG_LIMITS`) is refused, and what to
    give; None when it is from 1 to the flag's limit."""
    most, what = FLAG_LIMITS[flag]
    if value < 1:
        return f"{flag} must be at least 1 ({what}), got {value}"
    if value <= most:
        return None
    return (
        f"{flag} must be at most {most} ({what}; this machine has {usable_cores()} cores), "
        f"got {value}"
    )


def set_thread_limits(threads: int, spin: bool = False) -> None:
    """Intra-op threads for onnxruntime and numerical libraries, and whether onnxruntime's
    idle threads spin (``MCAM_ORT_SPIN``), set before decoders load."""
    for name in THREAD_VARIABLES:
        os.environ[name] = str(threads)
    os.environ["MCAM_ORT_SPIN"] = "1" if spin else "0"


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser(
        "worker",
        help="run a reconstruction worker",
        description="Consume reconstruction jobs and live device frames from the queue.",
    )
    parser.add_argument(
        "--concurrency", type=int, help="jobs decoded at once (default: MCAM_WORKER_CONCURRENCY)"
    )
    parser.add_argument(
        "--threads", type=int, help="ONNX intra-op threads per session (MCAM_WORKER_THREADS)"
    )
    parser.add_argument(
        "--decoder", help="decoder for live device frames (default: MCAM_DEFAULT_DECODER)"
    )
    parser.add_argument(
        "--frame-mode",
        choices=MODES,
        default="independent",
        help="decode device frames one by one, or along time (default: independent)",
    )
    parser.add_argument(
        "--stream-processes",
        type=int,
        help="processes decoding a device stream in independent mode "
        "(default: MCAM_STREAM_PROCESSES, else one per core up to 8; 1: in the worker)",
    )
    parser.add_argument(
        "--no-devices", action="store_true", help="only run jobs, leave device streams alone"
    )
    add_log_level_flag(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    settings = get_settings()
    concurrency = settings.worker_concurrency if args.concurrency is None else args.concurrency
    threads = settings.worker_threads if args.threads is None else args.threads
    processes = args.stream_processes
    if processes is None:
        processes = settings.stream_processes or min(usable_cores(), MAX_STREAM_PROCESSES)
    given = {"--threads": threads, "--concurrency": concurrency, "--stream-processes": processes}
    for flag, value in given.items():
        problem = limit_problem(flag, value)
        if problem:
            raise McamError(problem)
    if args.decoder:
        with naming("--decoder"):  # else each job child died at start, with a traceback
            resolve(args.decoder)
    start_logging(args)
    set_thread_limits(threads, settings.ort_spin)
    from worker.runner import Worker, WorkerConfig

    config = WorkerConfig(
        redis_url=redis_url_for(settings),
        data_dir=settings.data_dir,
        concurrency=concurrency,
        decoder=args.decoder or settings.default_decoder,
        frame_mode=args.frame_mode,
        claim_idle_ms=settings.claim_idle_ms,
        max_deliveries=settings.max_deliveries,
        lease_ms=settings.device_lease_ms,
        heartbeat_s=settings.heartbeat_s,
        retention_s=settings.result_retention_s,
        devices=not args.no_devices,
        stream_exr_compression=settings.stream_exr_compression,
        stream_processes=processes,
    )
    return Worker(config).run()
