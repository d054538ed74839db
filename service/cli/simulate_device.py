"""``mcam simulate-device``: a virtual SCAMP-5 streaming mcam-link v1.

Usage::

    mcam simulate-device --port pty                 # prints the pty path to give `mcam device`
    mcam simulate-device --port socket://127.0.0.1:5555 --encoding mantissa --alpha 2
    mcam simulate-device --port pty:/tmp/scamp5 --exr scene.exr --corrupt-bytes 0.01

The first line on stdout is the URL for ``mcam device --port``. It runs until
``--frames`` frames are sent (then keeps answering control packets) or SIGTERM.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from device.commands import FPS_RANGE
from device.faults import Faults
from device.link_protocol import MIN_GAIN
from device.scenes import ExrScene, ProceduralScene, SceneSequence
from device.sim_link import Endpoint, open_endpoint
from device.simulator import MAX_SEED, CameraSettings, VirtualScamp5
from models.errors import InvalidInputError
from models.formation import SensorParams
from models.stop_signals import noting_stop_signals, wait_for_stop
from service.cli.output_files import check_inputs


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser(
        "simulate-device",
        help="run a virtual SCAMP-5 camera",
        description="Render an HDR scene sequence, encode it in-pixel and stream mcam-link v1.",
    )
    parser.add_argument("--port", default="pty",
                        help="pty (default), pty:SYMLINK or socket://HOST:PORT (a server)")
    parser.add_argument("--exr", type=Path, action="append",
                        help="HDR image(s) to pan across (default: a procedural scene)")
    low, high = FPS_RANGE
    parser.add_argument("--fps", type=float, default=30.0,
                        help=f"frames per second, {low:g} to {high:g} (default 30)")
    parser.add_argument("--frames", type=int, help="stop streaming after this many frames")
    parser.add_argument("--encoding", choices=("modulo", "mantissa", "clip"), default="modulo",
                        help="how the pixels wrap (default: modulo)")
    parser.add_argument("--alpha", type=float, default=2.0, help="mantissa base (default 2)")
    parser.add_argument("--bits", type=int, default=8, help="code bits (default 8)")
    parser.add_argument("--gain", type=float, default=1.0,
                        help="wrap units per scene unit (default 1)")
    parser.add_argument("--read-noise", type=float, default=0.002,
                        help="sigma in wraps (default 0.002; 0: none)")
    parser.add_argument("--seed", type=int, default=0,
                        help=f"noise and fault seed, 0 to {MAX_SEED} (default 0)")
    faults = parser.add_argument_group("fault injection")
    faults.add_argument("--corrupt-bytes", type=float, default=0.0,
                        help="fraction of bytes overwritten, in bursts")
    faults.add_argument("--burst-len", type=int, default=256,
                        help="bytes per corrupt burst (default 256)")
    faults.add_argument("--drop", type=float, default=0.0, help="fraction of packets not sent")
    faults.add_argument("--truncate", type=float, default=0.0, help="fraction cut in half")
    faults.add_argument("--oversize", type=float, default=0.0,
                        help="fraction preceded by a bogus 16 MiB length header")
    faults.add_argument("--stall-every", type=int, default=0,
                        help="stall every N-th packet (0: never)")
    faults.add_argument("--stall-s", type=float, default=0.2,
                        help="stall length in seconds (default 0.2)")
    faults.add_argument("--disconnect-every", type=int, default=0,
                        help="unplug the link every N-th packet (0: never)")
    faults.add_argument("--disconnect-s", type=float, default=0.5,
                        help="seconds it stays out (default 0.5)")
    parser.set_defaults(func=run)


def check_flags(args: argparse.Namespace) -> None:
    """Refuse flag values the camera cannot run with, naming the flag, and an ``--exr``
    that is a folder or an empty file (:func:`check_inputs`)."""
    check_inputs([str(path) for path in args.exr or ()])
    low, high = FPS_RANGE
    if not low <= args.fps <= high:
        raise InvalidInputError(f"--fps must be from {low:g} to {high:g}, got {args.fps:g}")
    if not args.gain >= MIN_GAIN:  # NaN too
        raise InvalidInputError(
            f"--gain must be at least {MIN_GAIN:g}, the smallest gain a frame can carry "
            f"(the daemon drops frames with a smaller one), got {args.gain:g}"
        )
    if args.frames is not None and args.frames < 1:
        raise InvalidInputError(f"--frames must be at least 1, got {args.frames}")
    if not 0 <= args.seed <= MAX_SEED:
        raise InvalidInputError(f"--seed must be from 0 to {MAX_SEED}, got {args.seed}")
    if args.port == "loop://":
        raise InvalidInputError(
            "--port loop:// only reaches readers in this same process (tests); give pty, "
            "pty:PATH or socket://HOST:PORT for mcam device to read"
        )


def open_port(url: str) -> Endpoint:
    """The camera's end of the link at ``url``; a port it cannot open is named."""
    try:
        return open_endpoint(url)
    except OSError as exc:
        advice = ("name a path in a directory you can write" if url.startswith("pty:")
                  else "give a local address and a free port")
        raise InvalidInputError(
            f"--port {url}: cannot open it ({exc.strerror or exc}); {advice}, or pty"
        ) from None


def run(args: argparse.Namespace) -> int:
    check_flags(args)
    scene: SceneSequence = ExrScene(args.exr) if args.exr else ProceduralScene()
    settings = CameraSettings(encoding=args.encoding, alpha=args.alpha, bits=args.bits,
                              gain=args.gain, fps=args.fps, read_noise=args.read_noise)
    faults = Faults(corrupt_bytes=args.corrupt_bytes, burst_len=args.burst_len,
                    drop_packets=args.drop, truncate_packets=args.truncate,
                    oversize_packets=args.oversize, stall_every=args.stall_every,
                    stall_s=args.stall_s, disconnect_every=args.disconnect_every,
                    disconnect_s=args.disconnect_s, seed=args.seed)
    SensorParams.parse({"encoding": args.encoding, "alpha": args.alpha, "bits": args.bits,
                        "gain": args.gain, "read_noise": args.read_noise})
    camera = VirtualScamp5(open_port(args.port), scene, settings, faults, seed=args.seed,
                           max_frames=args.frames)
    print(camera.endpoint.url, flush=True)
    with noting_stop_signals() as received:
        camera.start()
        wait_for_stop(received)
        camera.stop()
        print(f"sent {camera.packets_sent} packets ({camera.packets_unsent} undelivered)",
              file=sys.stderr)
    return 0
