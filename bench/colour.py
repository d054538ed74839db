"""Colour frames: each channel decoded on its own, against the channels made consistent.

``python -m bench.colour`` measures, for each encoding and decoder, the decoder on
each channel alone and with :func:`models.decoders.colour.harmonise` after it
(``<decoder>+colour``; ``auto`` at balanced and best with ``joint_colour`` off and
on), on two sets of 256 x 256 linear-RGB frames at the val-256 settings (overexposed
0.2 on luminance, max_wraps 16, 8 bits; read noise 0, or ``--read-noise``):

- ``val``: val-256 in colour, the validation crops (:func:`models.scenes.val256_frames`
  with ``colour=True``);
- ``tuning``: 2 seeded crops of each *training* scene, the set the parameters of
  :mod:`models.decoders.colour` were chosen on (``--sets tuning``).

Per row: winding accuracy (per pixel-channel), the share of pixels with all three
channels right, mean PSNR and PU21-PSNR over the frames, the largest loss of PSNR on
one frame against decoding the channels alone, and the median ms per frame (one
decode per frame, after one warm-up frame). Prints Markdown; writes
``bench/results/colour.json``.
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import numpy as np

from bench import (
    Distinct,
    add_report_option,
    at_least,
    bench_parser,
    entry_point,
    host_facts,
    host_line,
    read_noise,
    refuse_unknown_decoders,
)
from models import metrics
from models.decoders import Decoder, get_decoder
from models.decoders.adaptive import AdaptiveDecoder
from models.decoders.budget import BudgetDecoder
from models.decoders.colour import ColourDecoder
from models.scenes import TRAIN_SCENES, ValFrame, exposed_frames, panorama_crops, val256_frames

ENCODINGS = ("mantissa", "modulo")
SETS = ("val", "tuning")
#: Decoders measured unless named: classical, the router's fast path, and its qualities.
DEFAULT_DECODERS = ("itoh", "herraez", "auto-fast", "auto-balanced", "auto-best")
#: Seed of the tuning crops' offsets (val-256 uses 256; any other keeps them apart).
TUNING_SEED = 900
TUNING_CROPS_PER_SCENE = 2


def frame_set(name: str, encoding: str, read_noise: float = 0.0) -> list[ValFrame]:
    """The colour frames of set ``name`` for ``encoding``, at ``read_noise`` (wrap units)."""
    if name == "val":
        return val256_frames(encoding, read_noise, colour=True)
    crops = panorama_crops(TRAIN_SCENES, TUNING_CROPS_PER_SCENE, TUNING_SEED, colour=True)
    return exposed_frames(crops, encoding, read_noise, seed=TUNING_SEED)


def pair(name: str) -> tuple[Decoder, Decoder]:
    """Decoder ``name`` with its channels decoded alone, and made consistent (``auto``
    is ``auto-balanced``)."""
    alone = get_decoder(name)
    if isinstance(alone, AdaptiveDecoder):
        quality = alone.quality
        return AdaptiveDecoder(quality, joint_colour=False), AdaptiveDecoder(
            quality, joint_colour=True
        )
    return alone, ColourDecoder(alone)


def refuse_joint_decoders(parser: argparse.ArgumentParser, names: list[str]) -> None:
    """Stop with the parser's usage error when a decoder of ``names`` makes the channels
    consistent itself (``<decoder>+colour``, a latency budget ``auto-<N>ms``): measured
    as 'alone', it was already joint."""
    joint = [name for name in names if isinstance(get_decoder(name), ColourDecoder | BudgetDecoder)]
    if joint:
        parser.error(
            f"decoders {', '.join(joint)} make the channels consistent themselves; name the "
            "decoder alone (itoh for itoh+colour, auto-fast, auto-balanced or auto-best): "
            "this benchmark runs each one alone and made consistent"
        )


def measure(decoder: Decoder, frames: list[ValFrame]) -> dict[str, Any]:
    """Accuracy per frame and the median ms per frame of ``decoder`` on ``frames``."""
    decoder.decode(frames[0].codes, frames[0].params)
    psnr, pu21, accuracy, all_right, ms = [], [], [], [], []
    for frame in frames:
        start = time.perf_counter_ns()
        result = decoder.decode(frame.codes, frame.params)
        ms.append((time.perf_counter_ns() - start) / 1e6)
        psnr.append(metrics.psnr(result.irradiance, frame.x))
        pu21.append(metrics.pu21_psnr(result.irradiance, frame.x))
        accuracy.append(metrics.winding_accuracy(result.winding, frame.winding))
        all_right.append(float(np.mean((result.winding == frame.winding).all(axis=2))))
    return {
        "psnr_db": psnr,
        "pu21_psnr_db": pu21,
        "winding_accuracy": float(np.mean(accuracy)),
        "all_channels_right": float(np.mean(all_right)),
        "ms_per_frame": float(np.median(ms)),
    }


def summary(alone: dict[str, Any], joint: dict[str, Any]) -> dict[str, Any]:
    """One table row: both modes' means and the largest loss on one frame. An exact
    frame's PSNR counts at :data:`models.metrics.PSNR_CAP`, in the means and in the
    changes; it was left out of both, so a frame exact alone and wrong once made
    consistent was not counted as a loss."""
    losses = [
        metrics.capped_psnr(b) - metrics.capped_psnr(a)
        for a, b in zip(alone["psnr_db"], joint["psnr_db"], strict=True)
    ]
    row: dict[str, Any] = {}
    for mode, result in (("alone", alone), ("joint", joint)):
        row[mode] = {
            "psnr_db": metrics.mean_capped_psnr(result["psnr_db"]),
            "pu21_psnr_db": metrics.mean_capped_psnr(result["pu21_psnr_db"]),
            "winding_accuracy": result["winding_accuracy"],
            "all_channels_right": result["all_channels_right"],
            "ms_per_frame": result["ms_per_frame"],
            "psnr_per_frame_db": result["psnr_db"],
        }
    row["worst_frame_change_db"] = min(losses) if losses else 0.0
    row["frames_gaining_0_5_db"] = sum(d > 0.5 for d in losses)
    row["frames_losing_0_5_db"] = sum(d < -0.5 for d in losses)
    return row


def run(args: argparse.Namespace) -> dict[str, Any]:
    rows = []
    for set_name in args.sets:
        for encoding in args.encodings:
            frames = frame_set(set_name, encoding, args.read_noise)[: args.frames]
            for name in args.decoders:
                alone, joint = pair(name)
                row = summary(measure(alone, frames), measure(joint, frames))
                rows.append(
                    {"set": set_name, "encoding": encoding, "decoder": name,
                     "frames": len(frames), **row}
                )  # fmt: skip
                print(markdown_row(rows[-1]), flush=True)
    return {
        "benchmark": "colour",
        **host_facts(),
        "read_noise": args.read_noise,
        "rows": rows,
    }


def markdown_row(row: dict[str, Any]) -> str:
    """One table row, with the frames measured (a ``--frames`` subset showed as the whole
    set)."""
    alone, joint = row["alone"], row["joint"]
    return (
        f"| {row['set']} | {row['encoding']} | {row['decoder']} | {row['frames']} | "
        f"{alone['psnr_db']:.2f} -> {joint['psnr_db']:.2f} | "
        f"{alone['pu21_psnr_db']:.2f} -> {joint['pu21_psnr_db']:.2f} | "
        f"{100 * alone['winding_accuracy']:.2f} -> {100 * joint['winding_accuracy']:.2f} | "
        f"{100 * alone['all_channels_right']:.2f} -> {100 * joint['all_channels_right']:.2f} | "
        f"{row['frames_gaining_0_5_db']} / {row['frames_losing_0_5_db']} | "
        f"{row['worst_frame_change_db']:+.2f} | "
        f"{alone['ms_per_frame']:.0f} -> {joint['ms_per_frame']:.0f} |"
    )


def markdown(report: dict[str, Any]) -> str:
    lines = [
        f"Colour frames (read noise {report['read_noise']:g}), channels alone -> made "
        f"consistent, {host_line(report)}",
        "",
        "| set | encoding | decoder | frames | PSNR dB | PU21-PSNR dB | W acc % "
        "| all 3 right % | frames +/- 0.5 dB | worst frame dB | ms/frame |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    lines += [markdown_row(row) for row in report["rows"]]
    return "\n".join(lines)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = bench_parser(__name__, __doc__)
    parser.add_argument("--decoders", nargs="+", action=Distinct, default=list(DEFAULT_DECODERS))
    parser.add_argument(
        "--encodings", nargs="+", action=Distinct, default=list(ENCODINGS), choices=ENCODINGS
    )
    parser.add_argument("--sets", nargs="+", action=Distinct, default=list(SETS), choices=SETS)
    parser.add_argument(
        "--frames", type=at_least(1), default=None, help="first N frames of each set"
    )
    parser.add_argument("--read-noise", type=read_noise, default=0.0, help="wrap units (default 0)")
    add_report_option(parser, "colour.json")
    args = parser.parse_args(argv)
    refuse_unknown_decoders(parser, args.decoders, encodings=args.encodings)
    refuse_joint_decoders(parser, args.decoders)
    return args


main = entry_point(parse_args, run, markdown, rows="rows")


if __name__ == "__main__":
    raise SystemExit(main())
