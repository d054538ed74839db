"""Train several chains of runs at once on one machine within a wall-clock budget.

A GPU machine is lent for minutes, so its runs are sized by time, not by steps:
``python -m models.training.timed --seconds 460 --device cuda --lanes s2d`` starts one
process per lane of the named set of :data:`models.training.recipes.TIMED_LANES` (a
chain of runs, e.g. a model and then its noise-aware fine-tune). Each lane

1. probes: counts the end-to-end steps (stage 3, the dearest) of its first run on a
   throwaway model in a window of wall-clock time common to all lanes, so that every
   lane is measured while all the others run (they share the GPU);
2. plans: scales the chain's stage steps, given in proportion, so that the chain ends
   :data:`MARGIN` before the deadline at the probed rate (:func:`planned_steps`);
3. trains the chain with those step counts, stopping at the deadline at the latest.

Each checkpoint records its configuration, the planned step counts included, so
``mcam train run --stages ...`` (or a recipe in :mod:`models.training.recipes`) repeats
the run on any machine, seeded exactly as before.
"""

from __future__ import annotations

import argparse
import math
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

from models.errors import InvalidInputError, McamError
from models.training.config import PRECISIONS, RUNS_DIR, TrainConfig, check_config
from models.training.recipes import TIMED_LANES
from models.training.train import record_line, train

#: The probe's window (s after the lanes start): every lane counts its steps from
#: :data:`PROBE_FROM` to :data:`PROBE_TO`, after its start-up (imports, batch workers,
#: cuDNN autotuning). A probe of 30 steps each, the first way (H200, 2026-11-26), timed
#: the base tier's lanes while the small-s2d lanes were still starting: 23 steps/s
#: probed, 15 in the run, so two runs were cut short by the deadline.
PROBE_FROM = 20.0
PROBE_TO = 40.0
#: How many times a probe measures again, each time one window later, when no two of its
#: steps ended in the window: on a cold H100 (2026-11-26) start-up took over 40 s and the
#: lanes failed their probe, 55 s of the lease lost; warm, the same command ran.
PROBE_RETRIES = 2
#: Share of the time left after the probe that the plan leaves unused (stage changes,
#: checkpoints, the other lanes' probes ending).
MARGIN = 0.1
#: A lane logs one line per this many optimizer steps.
LOG_EVERY = 100


def planned_steps(
    units: tuple[tuple[int, ...], ...], steps_per_s: float, seconds: float
) -> tuple[tuple[int, ...], ...]:
    """Stage steps of each run of a chain, in proportion to ``units``, so that all of them
    together take ``(1 - MARGIN) * seconds`` at ``steps_per_s``. A stage with units keeps
    at least one step; one without stays at 0."""
    if steps_per_s <= 0 or seconds <= 0:
        raise ValueError(f"need a positive rate and time, got {steps_per_s} steps/s, {seconds} s")
    total_units = sum(sum(run) for run in units)
    if total_units <= 0:
        raise ValueError("a chain needs at least one stage with steps")
    scale = (1 - MARGIN) * seconds * steps_per_s / total_units
    return tuple(tuple(max(round(u * scale), 1) if u else 0 for u in run) for run in units)


def probe_rate(config: TrainConfig, window: tuple[float, float]) -> float:
    """End-to-end optimizer steps per second of ``config`` on its device in ``window``
    (:func:`time.monotonic` seconds), measured on a throwaway model in a temporary
    folder. When fewer than two steps ended in the window (a slow start-up), the probe
    resumes and measures the next window of the same length, up to
    :data:`PROBE_RETRIES` times; then it raises RuntimeError."""
    stamps: list[float] = []

    def note(record: dict[str, Any]) -> None:
        stamps.append(time.monotonic())

    span = window[1] - window[0]
    with tempfile.TemporaryDirectory() as folder:
        probe = replace(
            config, stage_steps=(0, 0, 10**9), init_from=None, label="probe", log_every=1,
            checkpoint_every=10**9, runs_dir=Path(folder),
        )  # fmt: skip
        for attempt in range(PROBE_RETRIES + 1):
            start, end = window[0] + attempt * span, window[1] + attempt * span
            train(probe, note, deadline=end)
            inside = [stamp for stamp in stamps if start <= stamp <= end]
            if len(inside) >= 2:
                return (len(inside) - 1) / (inside[-1] - inside[0])
    raise RuntimeError(
        f"{config.name}: fewer than 2 probe steps ended in any of {PROBE_RETRIES + 1} windows "
        f"of {span:.0f} s from {PROBE_FROM} s; start-up took longer, or one step takes "
        "longer than the window"
    )


def lane_report(record: dict[str, Any], name: str) -> None:
    """Print every :data:`LOG_EVERY`-th step's record, prefixed with the run's name."""
    if record["step"] % LOG_EVERY == 0:
        print(f"[{name}] {record_line(record)}", flush=True)


def run_lane(chain: tuple[TrainConfig, ...], started: float, deadline: float) -> list[Path]:
    """Probe, plan and train one chain (:func:`time.monotonic` times: the lanes'
    common start and the ``deadline``); returns the checkpoints. The runs take the
    chain's ``stage_steps`` as proportions."""
    rate = probe_rate(chain[0], (started + PROBE_FROM, started + PROBE_TO))
    left = deadline - time.monotonic()
    if left <= 0:
        print(f"[{chain[0].name}] the probe ({rate:.2f} steps/s) took all the time", flush=True)
        return []
    plan = planned_steps(tuple(config.stage_steps for config in chain), rate, left)
    print(f"[{chain[0].name}] {rate:.2f} steps/s, {left:.0f} s left: stages {plan}", flush=True)
    checkpoints = []
    for config, steps in zip(chain, plan, strict=True):
        planned = replace(config, stage_steps=steps, log_every=20)
        checkpoints.append(train(planned, lambda r, n=planned.name: lane_report(r, n), deadline))
        print(f"[{planned.name}] done: {checkpoints[-1]}", flush=True)
    return checkpoints


def lane_command(index: int, args: argparse.Namespace, start: float) -> list[str]:
    """The command line of lane ``index`` of the lanes started at ``start``
    (:func:`time.time`)."""
    return [
        sys.executable, "-m", "models.training.timed", "--lane", str(index), "--seconds",
        str(args.seconds), "--start", repr(start), "--device", args.device,
        "--precision", args.precision,
        "--workers", str(args.workers), "--runs-dir", str(args.runs_dir), "--lanes", args.lanes,
    ]  # fmt: skip


def lanes(args: argparse.Namespace) -> tuple[tuple[TrainConfig, ...], ...]:
    """The named set of lanes with this invocation's device, precision, workers and folder."""
    return tuple(
        tuple(
            replace(c, device=args.device, precision=args.precision, workers=args.workers,
                    runs_dir=args.runs_dir)  # fmt: skip
            for c in chain
        )
        for chain in TIMED_LANES[args.lanes]
    )


def check_lanes(args: argparse.Namespace) -> None:
    """Refuse, before any lane starts, a budget that is not a positive number of seconds
    or a run of the lanes that :func:`models.training.config.check_config` refuses (each
    lane's process raised it in a traceback of its own)."""
    if not 0 < args.seconds < math.inf:
        raise InvalidInputError(f"--seconds must be a positive number, got {args.seconds}")
    for chain in lanes(args):
        for config in chain:
            check_config(config)


def main(argv: list[str] | None = None) -> int:
    """Start every lane in its own process and wait for them (or run one, ``--lane``)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=460.0, help="wall-clock budget (s)")
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--precision", default="bf16", choices=PRECISIONS)
    parser.add_argument("--workers", type=int, default=3, help="batch processes per lane")
    parser.add_argument("--runs-dir", type=Path, default=RUNS_DIR)
    parser.add_argument(
        "--lanes", default="s2d", choices=sorted(TIMED_LANES),
        help="set of lanes in recipes.TIMED_LANES",
    )  # fmt: skip
    parser.add_argument("--lane", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--start", type=float, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    try:
        check_lanes(args)
    except McamError as exc:
        parser.error(exc.message)
    if args.lane is not None:
        started = time.monotonic() + args.start - time.time()
        run_lane(lanes(args)[args.lane], started, started + args.seconds)
        return 0
    start = time.time()
    processes = [
        subprocess.Popen(lane_command(index, args, start)) for index in range(len(lanes(args)))
    ]
    codes = [process.wait() for process in processes]
    print(f"lanes ended with exit codes {codes}", flush=True)
    return max(codes, default=0)


if __name__ == "__main__":
    sys.exit(main())
