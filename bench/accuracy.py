"""Accuracy and speed of every decoder on the val-256 protocol.

``python -m bench.accuracy`` decodes the val-256 frames (:func:`models.scenes.val256_frames`:
24 grayscale 256 x 256 crops of the validation scenes, overexposed 0.2, max_wraps 16,
8 bits) with every installed decoder, for both encodings, and reports the mean over
frames of winding accuracy, PSNR, PU21-PSNR, SSIM and MS-SSIM
(:func:`models.metrics.evaluate` against the exact irradiance ``x``, wrap units) and the
median over frames of the wall time per frame in ms (onnxruntime on
``MCAM_WORKER_THREADS`` = 2 threads).

A second table gives PSNR against read noise (sigma in wraps) for the best
``mantissanet`` tier on mantissa frames, trained without and with noise
(``<tier>-noise``), next to ``itoh``; missing models are named, and when the best tier
has no noise-aware twin the best tier that has one is shown with it.

It prints Markdown and writes ``bench/results/accuracy.json`` and ``.md``.
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from bench import (
    Distinct,
    add_report_option,
    add_val256_frames_option,
    at_least,
    bench_parser,
    entry_point,
    host_facts,
    host_line,
    read_noise,
    refuse_unknown_decoders,
)
from models import metrics
from models.decoders import Decoder, available_decoders, get_decoder
from models.errors import InvalidInputError, McamError
from models.scenes import (
    VAL256_BITS,
    VAL256_MAX_WRAPS,
    VAL256_OVEREXPOSED,
    VAL256_SIZE,
    ValFrame,
    val256_frames,
)

ENCODINGS = ("modulo", "mantissa")
NOISE_LEVELS = (0.0, 0.005, 0.01, 0.02)
METRICS = ("winding_accuracy", "psnr", "pu21_psnr", "ssim", "ms_ssim")
#: Threads for onnxruntime (the learned decoders read MCAM_WORKER_THREADS).
THREADS = 2
#: The noise table's "missing" when no ``mantissanet`` tier was measured.
UNMEASURED_TIERS = ("mantissanet-<best tier>", "mantissanet-<best tier>-noise")
#: The classical reference shown beside the networks in the noise table.
NOISE_REFERENCE = "itoh"


#: Recall is reported per true W up to this value; larger W are pooled into "N+".
RECALL_TOP = 5


def winding_recall(pairs: list[tuple[np.ndarray, np.ndarray]]) -> dict[str, float | None]:
    """Fraction of pixels decoded with the right W, per true W (0 .. ``RECALL_TOP``+),
    over ``(estimated W, true W)`` pairs; None for a W no pixel has."""
    hits = np.zeros(RECALL_TOP + 1)
    counts = np.zeros(RECALL_TOP + 1)
    for estimate, truth in pairs:
        classes = np.minimum(truth, RECALL_TOP).ravel()
        counts += np.bincount(classes, minlength=RECALL_TOP + 1)
        hits += np.bincount(classes[(estimate == truth).ravel()], minlength=RECALL_TOP + 1)
    labels = [str(w) for w in range(RECALL_TOP)] + [f"{RECALL_TOP}+"]
    return {
        label: (float(hit / count) if count else None)
        for label, hit, count in zip(labels, hits, counts, strict=True)
    }


def timed_decode(
    decoder: Decoder, frame: ValFrame, clock: Callable[[], int] = time.perf_counter_ns
) -> tuple[Any, float]:
    """Decode one frame; returns the result and the wall time in ms (``clock``: ns)."""
    start = clock()
    result = decoder.decode(frame.codes, frame.params)
    return result, (clock() - start) / 1e6


def mean_metrics(per_frame: list[dict[str, float]]) -> dict[str, float | int]:
    """Mean of each metric over the frames that have it; a PSNR counts at most
    ``PSNR_CAP`` dB, as in bench.video (an exact frame's inf counts as the cap: it was
    left out, so one 30 dB frame among 23 exact ones read 30 dB), and ``exact_frames``
    says how many were exact. A metric that is NaN is a bug and is refused."""
    summary: dict[str, float | int] = {}
    for key in METRICS:
        values = [row[key] for row in per_frame if key in row]
        if key in ("psnr", "pu21_psnr"):
            values = [metrics.capped_psnr(value) for value in values]
        elif not np.isfinite(values).all():
            raise InvalidInputError(f"{key} is not a finite number on a frame: {values}")
        summary[key] = float(np.mean(values)) if values else float("nan")
    summary["exact_frames"] = sum(1 for row in per_frame if row["psnr"] == np.inf)
    return summary


def measure(
    decoder: Decoder,
    frames: list[ValFrame],
    repeats: int,
    time_frames: int,
    clock: Callable[[], int] = time.perf_counter_ns,
) -> dict[str, Any]:
    """Metrics over ``frames`` and the ms/frame: the median over the frames of each
    frame's median time (``clock``: ns).

    Every frame is decoded once for the metrics (timed too); the first
    ``time_frames`` frames are decoded ``repeats - 1`` more times, their median standing
    for them (all the times were pooled, which counted those frames ``repeats`` times
    over the others: 12 of 32 times from 4 of 24 frames, all of the first scene). One
    untimed warm-up decode comes first (it creates ONNX sessions).
    """
    decoder.decode(frames[0].codes, frames[0].params)
    per_frame, times, windings = [], [], []
    for frame in frames:
        result, ms = timed_decode(decoder, frame, clock)
        times.append([ms])
        per_frame.append(
            metrics.evaluate(result.irradiance, frame.x, result.winding, frame.winding, flip=False)
        )
        windings.append((result.winding, frame.winding))
    for frame, frame_times in zip(frames[:time_frames], times, strict=False):
        frame_times += [timed_decode(decoder, frame, clock)[1] for _ in range(repeats - 1)]
    return {
        **mean_metrics(per_frame),
        "recall_by_winding": winding_recall(windings),
        "ms_per_frame": float(np.median([np.median(frame_times) for frame_times in times])),
        "timed_runs": sum(len(frame_times) for frame_times in times),
        "frames": len(frames),
    }


def bench_row(name: str, encoding: str, frames: list[ValFrame], args: argparse.Namespace) -> dict:
    """One table row; a decoder that cannot run an encoding gets ``missing`` and why."""
    spec = {s.name: s for s in available_decoders()}.get(name)
    row: dict[str, Any] = {"decoder": name, "kind": spec.kind if spec else None}
    row["encoding"] = encoding
    try:
        row.update(measure(get_decoder(name), frames, args.repeats, args.time_frames))
    except McamError as exc:
        row["missing"] = exc.message
    return row


def noise_candidates(rows: list[dict[str, Any]]) -> tuple[list[str], list[str]]:
    """The decoders of the noise table and the ones of them that are not installed: the
    best mantissanet tier on mantissa frames and its noise-aware twin; when that twin is
    not installed, also the best tier that has one, with its twin; then the classical
    reference."""
    installed = {s.name for s in available_decoders()}
    tiers = sorted(
        (
            r
            for r in rows
            if r["kind"] == "learned"
            and r["decoder"].startswith("mantissanet-")
            and not r["decoder"].endswith("-noise")
            and r["encoding"] == "mantissa"
            and "psnr" in r
        ),
        key=lambda r: r["psnr"],
        reverse=True,
    )
    if not tiers:
        return [NOISE_REFERENCE], list(UNMEASURED_TIERS)
    best = tiers[0]["decoder"]
    wanted = [best, noise_twin(best)]
    if noise_twin(best) not in installed:
        paired = next((r["decoder"] for r in tiers if noise_twin(r["decoder"]) in installed), None)
        wanted += [paired, noise_twin(paired)] if paired else []
    wanted = list(dict.fromkeys([*wanted, NOISE_REFERENCE]))
    return [n for n in wanted if n in installed], [n for n in wanted if n not in installed]


def noise_twin(tier: str) -> str:
    """The noise-aware decoder of a ``mantissanet`` tier (an int8 tier's float one's)."""
    return f"{tier.removesuffix('-int8')}-noise"


def noise_table(rows: list[dict[str, Any]], args: argparse.Namespace) -> dict[str, Any]:
    """PSNR and winding accuracy against read noise on mantissa frames."""
    names, missing = noise_candidates(rows)
    results = []
    for level in args.noise_levels:
        frames = val256_frames("mantissa", read_noise=level)[: args.frames]
        for name in names:
            row = bench_row(name, "mantissa", frames, args)
            results.append({"read_noise": level, **row})
    return {
        "encoding": "mantissa",
        "levels": list(args.noise_levels),
        "decoders": names,
        "missing": missing,
        "results": results,
    }


def run(args: argparse.Namespace) -> dict[str, Any]:
    """The whole benchmark as a JSON-ready report."""
    os.environ.setdefault("MCAM_WORKER_THREADS", str(THREADS))
    names = args.decoders or [spec.name for spec in available_decoders()]
    rows = []
    for encoding in ENCODINGS:
        frames = val256_frames(encoding)[: args.frames]
        rows += [bench_row(name, encoding, frames, args) for name in names]
    noise = noise_table(rows, args)
    return {
        "benchmark": "accuracy",
        **host_facts(),
        "threads": int(os.environ["MCAM_WORKER_THREADS"]),
        "protocol": {
            "name": "val-256",
            "frames": len(frames),
            "size": VAL256_SIZE,
            "overexposed": VAL256_OVEREXPOSED,
            "max_wraps": VAL256_MAX_WRAPS,
            "bits": VAL256_BITS,
            "repeats": args.repeats,
            "timed_frames": min(args.time_frames, len(frames)),
        },
        "results": rows,
        "noise": noise,
    }


def _cell(row: dict[str, Any], key: str, scale: float = 1.0, digits: int = 2) -> str:
    value = row.get(key)
    if value is None or not np.isfinite(value):
        return "-"
    return f"{value * scale:.{digits}f}"


def markdown(report: dict[str, Any]) -> str:
    """The report as two Markdown tables with a header line (date, machine)."""
    proto = report["protocol"]
    lines = [
        f"val-256 ({proto['frames']} frames of {proto['size']}x{proto['size']}, overexposed "
        f"{proto['overexposed']}, max_wraps {proto['max_wraps']:g}, {proto['bits']} bits), "
        f"{host_line(report)}; {report['threads']} threads",
        "",
        "| decoder | kind | encoding | W acc % | PSNR dB | PU21-PSNR dB | SSIM | MS-SSIM "
        "| ms/frame |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for row in report["results"]:
        head = f"| {row['decoder']} | {row['kind']} | {row['encoding']} |"
        if "missing" in row:
            lines.append(f"{head} n/a: {row['missing']} | | | | | |")
            continue
        lines.append(
            f"{head} {_cell(row, 'winding_accuracy', 100)} | {_cell(row, 'psnr')} | "
            f"{_cell(row, 'pu21_psnr')} | {_cell(row, 'ssim', digits=4)} | "
            f"{_cell(row, 'ms_ssim', digits=4)} | {_cell(row, 'ms_per_frame', digits=1)} |"
        )
    lines += recall_table(report["results"])
    return "\n".join(lines + noise_lines(report["noise"]))


def noise_lines(noise: dict[str, Any]) -> list[str]:
    """Markdown lines of the noise table and its note on missing decoders; none when no
    read noise level was asked (``--noise-levels`` with no value)."""
    if not noise["levels"]:
        return []
    lines = ["", f"PSNR dB (W acc %) against read noise, {noise['encoding']} frames:", ""]
    lines += ["| decoder | " + " | ".join(f"{v:g}" for v in noise["levels"]) + " |"]
    lines += ["|---|" + "---|" * len(noise["levels"])]
    for name in noise["decoders"]:
        cells = [
            f"{_cell(r, 'psnr')} ({_cell(r, 'winding_accuracy', 100, 1)})"
            if "missing" not in r
            else "n/a"
            for r in noise["results"]
            if r["decoder"] == name
        ]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    if noise["missing"]:
        lines += ["", missing_note(noise["missing"])]
    return lines


def missing_note(missing: list[str]) -> str:
    """The noise table's note on the decoders it lacks: those not installed, or, when no
    ``mantissanet`` tier was measured at all, that (none installed, or ``--decoders``
    named none)."""
    if missing == list(UNMEASURED_TIERS):
        return (
            "No mantissanet tier was measured (none is installed, or --decoders named none), "
            "so the noise table has none."
        )
    return f"Not installed, so not in the noise table: {', '.join(missing)}."


def recall_table(rows: list[dict[str, Any]]) -> list[str]:
    """Markdown lines: the share of pixels with the right W, per true W, per decoder."""
    measured = [row for row in rows if "recall_by_winding" in row]
    if not measured:
        return []
    labels = list(measured[0]["recall_by_winding"])
    lines = ["", "Right W (%) by true W:", "",
             "| decoder | encoding | " + " | ".join(f"W={w}" for w in labels) + " |",
             "|---|---|" + "---|" * len(labels)]  # fmt: skip
    for row in measured:
        cells = [
            "-" if value is None else f"{100 * value:.1f}"
            for value in row["recall_by_winding"].values()
        ]
        lines.append(f"| {row['decoder']} | {row['encoding']} | " + " | ".join(cells) + " |")
    return lines


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = bench_parser(__name__, __doc__)
    parser.add_argument(
        "--decoders", nargs="+", action=Distinct, help="only these decoders (default: all)"
    )
    add_val256_frames_option(parser)
    parser.add_argument(
        "--repeats", type=at_least(1), default=3, help="timed decodes per timed frame"
    )
    parser.add_argument(
        "--time-frames", type=at_least(0), default=4, help="frames timed repeatedly"
    )
    parser.add_argument(
        "--noise-levels",
        type=read_noise,
        nargs="*",
        action=Distinct,
        default=list(NOISE_LEVELS),
        help="read noise sigmas (wraps) of the noise table; none skips it",
    )
    add_report_option(parser, "accuracy.json")
    args = parser.parse_args(argv)
    refuse_unknown_decoders(parser, args.decoders)
    return args


main = entry_point(parse_args, run, markdown, rows="results")


if __name__ == "__main__":
    raise SystemExit(main())
