"""``mcam device``: run the daemon of one camera link (mcam-link v1 -> Redis frame stream).

Usage::

    mcam device --port /dev/ttyACM0 --device-id rig1
    mcam device --port socket://10.0.0.7:5555 --device-id rig2
    MCAM_REDIS_URL=redis://queue:6379 mcam device --port /tmp/mcam-pty-x/scamp5 --device-id sim

Without ``MCAM_REDIS_URL`` it uses the embedded Redis of the data dir (started
by ``mcam serve`` or ``mcam api``). Bracketed reference pairs go to
``<data dir>/datasets/<device>/``, at most ``MCAM_DATASET_MAX_PAIRS`` of them and
``MCAM_DATASET_MAX_BYTES`` in all (the oldest are removed). SIGTERM / Ctrl-C stop it
(exit 0); another daemon of the device stops it with exit 2, an unexpected error (a bug,
logged with its traceback) with exit 1.
"""

from __future__ import annotations

import argparse
import contextlib
import sys

import redis

from device.daemon import DaemonConfig, DeviceDaemon, crash_line
from device.datasets import DatasetLimits
from device.health import crashed_daemon_text
from device.serial_ports import check_port_url
from models.stop_signals import noting_stop_signals, wait_for_stop
from service.cli.options import add_log_level_flag, start_logging
from service.cli.worker import redis_url_for
from service.core.config import get_settings
from worker.embedded_redis import connect
from worker.redis_keys import validate_device_id

#: Exit status of a daemon that stopped on an unexpected error (2 is a caller's mistake):
#: a service manager restarts it, as it does not one stopped by a signal (0).
CRASHED = 1


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser(
        "device",
        help="run the daemon of a camera link",
        description="Read mcam-link v1 packets from a camera port and publish frames to Redis.",
    )
    parser.add_argument("--port", required=True,
                        help="pyserial URL: /dev/ttyACM0, a pty path, socket://HOST:PORT, "
                             "rfc2217://HOST:PORT, loop://")
    parser.add_argument("--device-id", required=True, help="1-64 ASCII letters, digits, '_' or '-'")
    add_log_level_flag(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    settings = get_settings()
    device = validate_device_id(args.device_id)
    start_logging(args)  # before a port URL's ?logging= sets it up (check_port_url)
    check_port_url(args.port)
    client = connect(redis_url_for(settings), timeout_s=1.0)
    limits = DatasetLimits(settings.dataset_max_pairs, settings.dataset_max_bytes)
    config = DaemonConfig(port=args.port, device=device, frames_maxlen=settings.frames_maxlen,
                          data_dir=settings.data_dir, dataset_limits=limits)
    daemon = DeviceDaemon(config, client)
    with contextlib.suppress(redis.RedisError, OSError):  # Redis away: claimed once it answers
        daemon.claim.take()
    with noting_stop_signals() as received:
        daemon.start()
        wait_for_stop(received, daemon.wait)  # a signal, or the daemon's failure
        daemon.request_stop()
        daemon.wait()
    if daemon.failure is not None:  # another daemon took the device once Redis answered
        raise daemon.failure
    if daemon.crash is not None:
        print(f"mcam device: error: {crash_message(device, daemon.crash)}", file=sys.stderr)
        return CRASHED
    return 0


def crash_message(device: str, crash: Exception) -> str:
    """One line for a daemon that stopped on an unexpected error (a bug; the log holds its
    traceback), saying what to do."""
    return (f"{crashed_daemon_text(device, crash_line(crash))}; the log above has its "
            "traceback: please report it, and restart mcam device")
