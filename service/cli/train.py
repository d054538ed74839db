"""``mcam train``: train, export and measure the learned decoders (needs the ``train`` extra).

``mcam train all`` reruns the recipes of the shipped models (resumable: rerun it
after an interruption), exports them to ``models/onnx`` (plus the int8 QDQ version
of one tier), replacing the shipped models, and measures val-256; a model whose card
is up to date with its finished checkpoint is kept as it is.
``mcam train run`` trains one configuration; ``mcam train export`` exports a run;
``mcam train measure`` re-measures shipped cards on val-256.
Ctrl-C (SIGINT) or SIGTERM stops a run after its step in progress, with a checkpoint
that the same command resumes; the command then exits 130 or 143.
PyTorch is imported only when a command runs, so the runtime never needs it.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from collections.abc import Iterable
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from models.errors import InvalidInputError
from service.cli.options import take_dash_digit_values

if TYPE_CHECKING:
    from models.training.config import TrainConfig

#: The winding losses of ``models.training.losses.LOSSES`` (named here so that parsing
#: the command line does not import torch; a test keeps the two equal).
LOSS_CHOICES = ("ce", "ce-risk", "mse", "jumps")
#: The tiers of ``models.training.networks.TIERS`` (likewise kept equal by a test).
TIER_CHOICES = ("tiny", "small", "base", "small-s2d", "tiny-s2d", "base-s2d", "large")
#: ``models.training.losses.RISK_WEIGHT``, for the same reason.
RISK_WEIGHT = 0.1
#: ``models.training.config.PRECISIONS``, likewise.
PRECISION_CHOICES = ("fp32", "bf16")


def register(subparsers: Any) -> None:
    """Add the ``train`` command and its ``all`` / ``run`` / ``export`` / ``measure`` actions."""
    parser = subparsers.add_parser(
        "train",
        help="train and export the learned decoders (CPU is fine, slow; resumable)",
        description="Train MantissaCam winding nets in three (+1) stages, export ONNX + cards.",
    )
    actions = parser.add_subparsers(dest="action", required=True, metavar="ACTION")
    every = actions.add_parser("all", help="reproduce every shipped model (train, export, val)")
    every.add_argument("--no-val", action="store_true", help="skip the val-256 measurement")
    add_execution_options(every)
    every.set_defaults(func=run)
    one = actions.add_parser("run", help="train one configuration (resumes its checkpoint)")
    take_dash_digit_values(one)
    one.add_argument("--family", default="mantissanet", choices=("mantissanet", "unmodnet"))
    one.add_argument("--tier", default="small", choices=TIER_CHOICES)
    one.add_argument("--encoding", default="mantissa", choices=("mantissa", "modulo"))
    one.add_argument("--loss", default="ce", choices=LOSS_CHOICES)
    one.add_argument(
        "--stages", default="500,3500,2000,2000", help="steps per stage, comma separated"
    )
    one.add_argument(
        "--risk-weight", type=float, default=RISK_WEIGHT,
        help="ce-risk only: weight of the expected log-MSE term (>= 0)",
    )
    one.add_argument("--crop", type=int, default=64, help="training crop (px, multiple of 16)")
    one.add_argument(
        "--large-crop", type=int,
        help="stage 4's crop (px, multiple of 16; a quarter of the batch; default 128)",
    )  # fmt: skip
    one.add_argument(
        "--own-states", type=float,
        help="unmodnet: share of batches trained from the model's own states (default 0)",
    )  # fmt: skip
    one.add_argument(
        "--own-passes", type=int,
        help="unmodnet: passes rolled out for those batches (default 4)",
    )  # fmt: skip
    one.add_argument("--batch", type=int, default=8)
    one.add_argument("--read-noise", type=float, default=0.0, help="max read noise (wrap units)")
    one.add_argument(
        "--colour-fraction", type=float, default=0.0,
        help="share of HDRI crops taken as one channel of a colour frame (default 0)",
    )  # fmt: skip
    one.add_argument(
        "--glow-fraction", type=float, default=0.0,
        help="share of synthetic scenes with smooth bright lobes (default 0)",
    )  # fmt: skip
    one.add_argument("--init-from", help="start from this finished run's weights (a run name)")
    one.add_argument(
        "--label", default="", help="a tag in the run name (a run towards another model)"
    )
    one.add_argument("--seed", type=int, default=0)
    one.add_argument("--threads", type=int, default=1, help="torch threads (1 is fastest here)")
    one.add_argument("--runs-dir", type=Path, help="checkpoints and logs (default: runs/)")
    one.add_argument(
        "--precision", default="fp32", choices=PRECISION_CHOICES,
        help="fp32, or bf16 autocast (a GPU's fast path)",
    )
    add_execution_options(one)
    one.set_defaults(func=run)
    export = actions.add_parser("export", help="export a run's checkpoint to ONNX + card")
    export.add_argument("checkpoint", type=Path, help="runs/<name>/checkpoint.pt")
    export.add_argument("--onnx-dir", type=Path, help="output folder (default: models/onnx)")
    export.add_argument("--no-val", action="store_true", help="skip the val-256 measurement")
    export.add_argument(
        "--force", action="store_true",
        help="replace this run's model, or the model another card serves for the same "
        "decoder and encoding (that card and its .onnx are removed)",
    )  # fmt: skip
    export.set_defaults(func=run)
    measure = actions.add_parser("measure", help="re-measure model cards on val-256")
    measure.add_argument("cards", type=Path, nargs="+", help="models/onnx/<name>.json")
    measure.set_defaults(func=run)


def add_execution_options(parser: argparse.ArgumentParser) -> None:
    """Where the steps run; neither changes which batches a step sees."""
    parser.add_argument("--device", default="cpu", help="torch device: cpu (default) or cuda")
    parser.add_argument(
        "--workers", type=int, default=0, help="processes making batches ahead (0: in-process)"
    )


#: One stage's step count in ``--stages``.
STEP_COUNT = re.compile(r"[0-9]+")


def parse_stages(text: str) -> tuple[int, ...]:
    """``"500,3500,2000"`` -> ``(500, 3500, 2000)``; 3 or 4 non-negative integers in
    ASCII digits (``str.isdigit`` also took ``²``, which ``int`` refused with a bare
    traceback, and other scripts' digits)."""
    parts = text.split(",")
    if len(parts) not in (3, 4) or not all(STEP_COUNT.fullmatch(p.strip()) for p in parts):
        raise InvalidInputError(
            f"--stages takes 3 or 4 comma-separated step counts (e.g. 500,3500,2000), got {text!r}"
        )
    return tuple(int(p) for p in parts)


def duration(seconds: float) -> str:
    """Seconds as ``h:mm:ss``."""
    minutes, secs = divmod(round(seconds), 60)
    return f"{minutes // 60}:{minutes % 60:02d}:{secs:02d}"


class Progress:
    """Prints one line per logged step: ``[run] step=<step>/<total>``, the record's
    other fields and ``eta=h:mm:ss``, the time left at the steps per second since this
    command's first record (at that first record, the run's mean rate so far)."""

    def __init__(self, name: str, total_steps: int) -> None:
        self.name = name
        self.total_steps = total_steps
        self.first: tuple[int, float] | None = None

    def eta_s(self, step: int, wall_s: float) -> float | None:
        """Seconds left after ``step`` at ``wall_s`` (the run's wall seconds so far);
        None before any time has passed."""
        first_step, first_wall = self.first or (0, 0.0)
        if step <= first_step or wall_s <= first_wall:
            first_step, first_wall = 0, 0.0
        if wall_s <= first_wall:
            return None
        return (self.total_steps - step) * (wall_s - first_wall) / (step - first_step)

    def __call__(self, record: dict[str, Any]) -> None:
        from models.training.train import record_line

        step, wall_s = record["step"], record["wall_s"]
        if self.first is None:
            self.first = (step, wall_s)
        eta_s = self.eta_s(step, wall_s)
        line = record_line({**record, "step": f"{step}/{self.total_steps}"})
        eta = "?" if eta_s is None else duration(eta_s)
        print(f"[{self.name}] {line} eta={eta}", flush=True)


def measure_and_show(card_path: Path, measure: bool) -> None:
    """Optionally add val-256 metrics to a card; print it (without the training section)."""
    from models.training.export import add_val256

    card = add_val256(card_path) if measure else json.loads(card_path.read_text())
    print(json.dumps({"card": str(card_path), **{k: card[k] for k in card if k != "training"}}))


def export_and_measure(
    checkpoint: Path, onnx_dir: Path | None, measure: bool, force: bool
) -> None:
    """Export a checkpoint (refusing to replace a model unless ``force``), measure, print
    the card."""
    from models.training.export import ONNX_DIR, export_run

    card_path = export_run(checkpoint, onnx_dir or ONNX_DIR, force)
    training = json.loads(card_path.read_text())["training"]
    planned = sum(training["planned_stage_steps"])
    if training["steps"] < planned:
        print(
            f"mcam train export: warning: {checkpoint} stopped at step {training['steps']} "
            f"of {planned}; its card records that (resume the run to finish it)",
            file=sys.stderr,
        )
    measure_and_show(card_path, measure)


def reproduce(recipes: Iterable[TrainConfig], onnx_dir: Path, measure: bool) -> None:
    """``mcam train all``: train each recipe (resuming its checkpoint), then ship those
    that ship (:func:`ship`)."""
    from models.training.recipes import exported, quantized
    from models.training.train import train

    for config in recipes:
        checkpoint = train(config, Progress(config.name, config.total_steps))
        if exported(config):
            ship(checkpoint, onnx_dir / f"{config.name}.json", measure, quantized(config))


def ship(checkpoint: Path, card_path: Path, measure: bool, int8: bool) -> None:
    """Export a finished run to ``card_path`` (replacing the model there: ``train all``
    reproduces it) and measure it, then its int8 QDQ version likewise; a card already
    up to date with the checkpoint is kept (and only measured if it never was)."""
    from models.training.export import card_is_current, export_run
    from models.training.quantize import quantize_card, quantized_card_path

    if card_is_current(card_path, checkpoint):
        keep(card_path, checkpoint, measure)
    else:
        measure_and_show(export_run(checkpoint, card_path.parent, force=True), measure)
    if not int8:
        return
    int8_path = quantized_card_path(card_path)
    if card_is_current(int8_path, checkpoint):
        keep(int8_path, checkpoint, measure)
    else:
        measure_and_show(quantize_card(card_path), measure)


def keep(card_path: Path, checkpoint: Path, measure: bool) -> None:
    """Say that a card is up to date with its checkpoint; measure it if asked and it has
    no val-256 figures yet."""
    print(f"up to date: {card_path} (exported from {checkpoint})", flush=True)
    if measure and "val256" not in json.loads(card_path.read_text()):
        measure_and_show(card_path, measure)


def given(args: argparse.Namespace, names: Iterable[str]) -> dict[str, Any]:
    """The options among ``names`` given on the command line (the others keep the
    configuration's defaults, which live beside torch)."""
    return {name: getattr(args, name) for name in names if getattr(args, name) is not None}


def run(args: argparse.Namespace) -> int:
    """Run the action; a run stopped by SIGINT or SIGTERM (after saving its checkpoint)
    says where it will resume and exits 128 + the signal's number (130, 143), as a shell
    reports a process the signal ended."""
    from models.training.run_control import Stopped

    try:
        return dispatch(args)
    except Stopped as stopped:
        print(f"mcam train: {stopped}", file=sys.stderr, flush=True)
        return 128 + stopped.signum


def dispatch(args: argparse.Namespace) -> int:
    """Dispatch the action; imports the torch-based training code lazily."""
    from models.training.config import RUNS_DIR, TrainConfig
    from models.training.export import ONNX_DIR
    from models.training.recipes import SHIPPED
    from models.training.train import train

    if args.action == "export":
        if not args.checkpoint.exists():
            raise FileNotFoundError(2, "no such checkpoint", str(args.checkpoint))
        export_and_measure(args.checkpoint, args.onnx_dir, not args.no_val, args.force)
        return 0
    if args.action == "measure":
        for card_path in args.cards:
            if not card_path.exists():
                raise FileNotFoundError(2, "no such model card", str(card_path))
            measure_and_show(card_path, measure=True)
        return 0
    if args.action == "all":
        recipes = [replace(r, device=args.device, workers=args.workers) for r in SHIPPED]
        reproduce(recipes, ONNX_DIR, not args.no_val)
        return 0
    config = TrainConfig(
        family=args.family, tier=args.tier, encoding=args.encoding, loss=args.loss,
        stage_steps=parse_stages(args.stages), crop=args.crop, batch=args.batch,
        max_read_noise=args.read_noise, colour_fraction=args.colour_fraction,
        glow_fraction=args.glow_fraction, risk_weight=args.risk_weight,
        init_from=args.init_from, label=args.label, seed=args.seed, threads=args.threads,
        runs_dir=args.runs_dir or RUNS_DIR, device=args.device, precision=args.precision,
        workers=args.workers, **given(args, ("large_crop", "own_states", "own_passes")),
    )  # fmt: skip
    print(f"checkpoint: {train(config, Progress(config.name, config.total_steps))}")
    return 0
