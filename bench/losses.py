"""Which winding loss measures best: cross-entropy over W classes (alone or plus the
expected PSNR loss), MSE on W, MSE on jumps.

``python -m bench.losses`` trains (or resumes) the same net once per loss, differing
only in the winding loss -- the ``tiny`` tier, one encoding, the shipped tiny
recipe's stages and seed -- exports each to ONNX and measures it through the
runtime decoder on val-256 (read noise 0 and 0.01). Needs the ``train`` extra;
a run already trained under ``runs/`` is reused (the shipped tiny models' runs:
``ce-risk`` on mantissa, ``ce`` on modulo). Prints a Markdown table and writes
``bench/results/losses.json``.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path
from typing import Any

from bench import (
    add_report_option,
    add_val256_frames_option,
    bench_parser,
    entry_point,
    host_facts,
    host_line,
    missing_extra,
)
from models.decoders.learned import LearnedDecoder, load_cards
from models.errors import InvalidInputError
from service.cli.options import take_dash_digit_values
from service.cli.train import parse_stages

try:
    from models.training.config import RUNS_DIR, TrainConfig
    from models.training.export import export_run
    from models.training.losses import LOSSES
    from models.training.recipes import TINY_STAGES
    from models.training.train import train
    from models.training.validate import val256_metrics
except ModuleNotFoundError as exc:
    missing_extra(exc, "train", "bench.losses")

NOISE_LEVELS = (0.0, 0.01)
THREADS = 2


def study_configs(args: argparse.Namespace) -> list[TrainConfig]:
    """One run per loss, identical otherwise (by default the shipped tiny recipe)."""
    return [
        TrainConfig(tier=args.tier, encoding=args.encoding, loss=loss,
                    stage_steps=args.stages, runs_dir=args.runs_dir)
        for loss in LOSSES
    ]  # fmt: skip


def measure_run(config: TrainConfig, frames: int) -> dict[str, Any]:
    """Train or resume the run, export it (to ``<runs>/loss-study/<run>/``: the runs of
    every loss make the same decoder, one model per folder; a rerun replaces it), measure
    it on val-256."""
    study_dir = config.runs_dir / "loss-study" / config.name
    study_dir.mkdir(parents=True, exist_ok=True)
    card_path = export_run(train(config), study_dir, force=True)
    onnx_name = card_path.with_suffix(".onnx").name
    cards = [c for c in load_cards(study_dir) if c["file"] == onnx_name]
    decoder = LearnedDecoder(cards[0]["decoder"], cards)
    row: dict[str, Any] = {
        "loss": config.loss,
        "run": config.name,
        "steps": config.total_steps,
        "train_wall_s": cards[0]["training"]["wall_s"],
    }
    for noise in NOISE_LEVELS:
        row[f"read_noise_{noise:g}"] = val256_metrics(decoder, config.encoding, noise, frames)
    return row


def run(args: argparse.Namespace) -> dict[str, Any]:
    """The whole study as a JSON-ready report."""
    os.environ.setdefault("MCAM_WORKER_THREADS", str(THREADS))
    rows = [measure_run(config, args.frames) for config in study_configs(args)]
    best = max(rows, key=lambda r: r["read_noise_0"]["psnr"])["loss"]
    return {
        "benchmark": "losses",
        **host_facts(),
        "protocol": {"name": "val-256", "tier": args.tier, "encoding": args.encoding,
                     "stage_steps": list(args.stages), "frames": args.frames,
                     "read_noise": list(NOISE_LEVELS)},
        "results": rows,
        "best": best,
    }  # fmt: skip


def markdown(report: dict[str, Any]) -> str:
    """The study as one Markdown table."""
    proto = report["protocol"]
    lines = [
        f"Winding loss study: mantissanet-{proto['tier']} on {proto['encoding']} val-256, "
        f"stages {proto['stage_steps']}, {host_line(report)}",
        "",
        "| loss | W acc % | PSNR dB | PU21-PSNR dB | SSIM | PSNR at noise 0.01 | ms/frame |",
        "|---|---|---|---|---|---|---|",
    ]
    for row in report["results"]:
        clean, noisy = row["read_noise_0"], row["read_noise_0.01"]
        lines.append(
            f"| {row['loss']} | {100 * clean['winding_accuracy']:.2f} | {clean['psnr']:.2f} | "
            f"{clean['pu21_psnr']:.2f} | {clean['ssim']:.4f} | {noisy['psnr']:.2f} | "
            f"{clean['ms_per_frame']:.1f} |"
        )
    lines += ["", f"Best by PSNR: {report['best']}."]
    return "\n".join(lines)


def stage_list(text: str) -> tuple[int, ...]:
    """``--stages``'s value (:func:`service.cli.train.parse_stages`), its refusal told by
    argparse in its own words rather than as "invalid parse_stages value"."""
    try:
        return parse_stages(text)
    except InvalidInputError as exc:
        raise argparse.ArgumentTypeError(exc.message) from exc


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = bench_parser(__name__, __doc__)
    take_dash_digit_values(parser)
    parser.add_argument("--tier", default="tiny", choices=("tiny", "small", "base"))
    parser.add_argument("--encoding", default="mantissa", choices=("mantissa", "modulo"))
    parser.add_argument(
        "--stages", type=stage_list, default=TINY_STAGES,
        help="steps per stage, comma separated (default: the shipped tiny recipe's)",
    )  # fmt: skip
    add_val256_frames_option(parser)
    parser.add_argument("--runs-dir", type=Path, default=RUNS_DIR, help="checkpoints (resumed)")
    add_report_option(parser, "losses.json")
    return parser.parse_args(argv)


main = entry_point(parse_args, run, markdown, rows="results")


if __name__ == "__main__":
    raise SystemExit(main())
