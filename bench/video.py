"""Independent vs temporal decoding on the synthetic video clips (``python -m bench.video``).

For each clip of :mod:`models.video_clips`, each encoding and each spatial decoder:
mean PSNR and PU21-PSNR per frame, winding accuracy, temporal consistency, wrap
flicker (:mod:`models.video_metrics`) and the decode time per frame in ms, for the
``independent`` and ``temporal`` modes of :mod:`worker.temporal`, plus the share
of pixels each temporal path took. Prints a table per row as it goes, then a
Markdown summary (with the issue's targets each pair meets), and writes
``bench/results/video.json`` and ``video.md``. Timings are wall time, after one
untimed warm-up frame per row, on whatever else the machine runs: the report records
the load average.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from bench import (
    add_report_option,
    at_least,
    host_facts,
    one_line_errors,
    publish,
    refuse_given_twice,
    refuse_unknown,
    refuse_unknown_decoders,
)
from models.decoders.registry import available_decoders
from models.video_clips import CLIP_KINDS, DEFAULT_FRAMES, VIDEO_ENCODINGS, ClipEncoding, make_clip
from models.video_metrics import clip_metrics
from worker.stream_state import PATHS, StreamState
from worker.temporal import StreamDecoder
from worker.temporal_config import MODES, TemporalConfig

#: Decoders benchmarked unless named on the command line: the fast spatial ones.
DEFAULT_DECODERS: tuple[str, ...] = ("itoh", "herraez")


def run_mode(
    enc: ClipEncoding, decoder: StreamDecoder, clock: Callable[[], int] = time.perf_counter_ns
) -> dict[str, Any]:
    """Decode a clip in one mode; its metrics, ms/frame (wall time of ``clock``, in ns),
    keyframes and path shares. The clip's first frame is decoded once untimed on a
    stream of its own first (it creates a net's ONNX session): whichever mode ran first
    paid for it, which made the temporal mode look cheaper against the independent."""
    decoder.decode(enc.codes[0], enc.params, StreamState())
    state = StreamState()
    winding, irradiance, paths = [], [], []
    keyframes = 0
    start = clock()
    for codes in enc.codes:
        frame = decoder.decode(codes, enc.params, state)
        winding.append(frame.winding)
        irradiance.append(frame.irradiance)
        paths.append(frame.paths)
        keyframes += frame.keyframe is not None
    elapsed = clock() - start
    row: dict[str, Any] = clip_metrics(
        np.stack(irradiance), enc.irradiance, np.stack(winding), enc.winding
    )
    row["ms_per_frame"] = elapsed / len(enc.codes) / 1e6
    row["keyframes"] = keyframes
    row["paths"] = {p: float(np.mean([frame[p] for frame in paths])) for p in PATHS}
    return row


def run(
    clips: tuple[str, ...],
    encodings: tuple[str, ...],
    decoders: tuple[str, ...],
    frames: int,
    config: TemporalConfig,
) -> list[dict[str, Any]]:
    """Every (clip, encoding, decoder, mode) row."""
    rows = []
    for kind in clips:
        clip = make_clip(kind, frames=frames, encodings=encodings)
        for encoding, enc in clip.encodings.items():
            for name in decoders:
                for mode in MODES:
                    row = run_mode(enc, StreamDecoder(mode, name, config))
                    rows.append(
                        {"clip": kind, "encoding": encoding, "decoder": name, "mode": mode, **row}
                    )
                    print_row(rows[-1])
    return rows


def print_row(row: dict[str, Any]) -> None:
    """One table line."""
    print(
        f"{row['clip']:13s} {row['encoding']:8s} {row['decoder']:9s} {row['mode']:11s} "
        f"{row['psnr']:7.2f} {row['pu21_psnr']:7.2f} {row['winding_accuracy']:7.4f} "
        f"{row['temporal_consistency']:8.5f} {row['wrap_flicker']:8.5f} "
        f"{row['ms_per_frame']:7.1f} {row['paths']['local']:6.3f} {row['paths']['spatial']:6.3f}",
        flush=True,
    )


def summarize(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per (clip, encoding, decoder): both modes' headline numbers, temporal vs
    independent ratios and differences, and which of the issue's targets it meets."""
    pairs: dict[tuple[str, str, str], dict[str, dict[str, Any]]] = {}
    for row in rows:
        pairs.setdefault((row["clip"], row["encoding"], row["decoder"]), {})[row["mode"]] = row
    summary = []
    for (clip, encoding, decoder), modes in pairs.items():
        ind, tem = modes["independent"], modes["temporal"]
        item: dict[str, Any] = {"clip": clip, "encoding": encoding, "decoder": decoder}
        for key in ("wrap_flicker", "psnr", "ms_per_frame"):
            item[f"{key}_independent"], item[f"{key}_temporal"] = ind[key], tem[key]
        item["flicker_reduction"] = flicker_reduction(ind["wrap_flicker"], tem["wrap_flicker"])
        item["psnr_gain_db"] = tem["psnr"] - ind["psnr"]
        item["pu21_psnr_gain_db"] = tem["pu21_psnr"] - ind["pu21_psnr"]
        item["cost_ratio"] = tem["ms_per_frame"] / ind["ms_per_frame"]
        item["targets_met"] = {
            "flicker_10x": tem["wrap_flicker"] == 0 or item["flicker_reduction"] >= 10.0,
            "psnr_gain": item["psnr_gain_db"] > 0.0,
            "cheaper": item["cost_ratio"] < 1.0,
        }
        summary.append(item)
    return summary


def flicker_reduction(independent: float, temporal: float) -> float | None:
    """How many times less wrap flicker temporal decoding has; None when neither mode
    flickers (it read 0.0, and the 10x target as missed, on a clip with no flicker), inf
    when only the independent mode does (it read the independent flicker over 1e-12: a
    figure like 5e10 times, which no measurement made)."""
    if temporal == 0:
        return None if independent == 0 else float("inf")
    return independent / temporal


def shown_reduction(reduction: float | None) -> str:
    """A flicker reduction in the table (``-``: neither mode flickers; ``all``: temporal
    decoding has none left)."""
    if reduction is None:
        return "-"
    return "all" if reduction == float("inf") else f"{reduction:.1f}"


def markdown_table(summary: list[dict[str, Any]], load: list[Sequence[float]]) -> str:
    """The summary as Markdown, with the machine load the timings were taken under
    (``load``: the load averages at the start and at the end)."""
    start, end = ([round(value, 2) for value in values] for values in load)
    lines = [
        f"Load average (1/5/15 min) at start {start}, at end {end} on "
        f"{os.cpu_count()} cores: ms/frame are noisy (shared machine).",
        "",
        "| clip | encoding | decoder | wrap flicker ind -> tem | x less | PSNR ind -> tem (dB) "
        "| dPSNR | dPU21 | ms/frame ind -> tem | cost x | targets met |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for item in summary:
        met = [name for name, ok in item["targets_met"].items() if ok]
        lines.append(
            f"| {item['clip']} | {item['encoding']} | {item['decoder']} "
            f"| {item['wrap_flicker_independent']:.5f} -> {item['wrap_flicker_temporal']:.5f} "
            f"| {shown_reduction(item['flicker_reduction'])} "
            f"| {item['psnr_independent']:.2f} -> {item['psnr_temporal']:.2f} "
            f"| {item['psnr_gain_db']:+.2f} | {item['pu21_psnr_gain_db']:+.2f} "
            f"| {item['ms_per_frame_independent']:.1f} -> {item['ms_per_frame_temporal']:.1f} "
            f"| {item['cost_ratio']:.2f} | {', '.join(met) or 'none'} |"
        )
    return "\n".join(lines)


def comma_names(text: str) -> tuple[str, ...]:
    """An argparse ``type``: comma-separated names, else the parser's usage error when
    one is empty (``itoh,`` was refused as "unknown decoders ; choose from ...") or
    given twice (:func:`bench.refuse_given_twice`)."""
    names = tuple(text.split(","))
    if "" in names:
        raise argparse.ArgumentTypeError(
            f"an empty name in {text!r}: separate the names with single commas, none at the ends"
        )
    refuse_given_twice(names)
    return names


@one_line_errors
def main(argv: list[str] | None = None) -> int:
    """Run the benchmark, print the tables, write the JSON and Markdown reports."""
    parser = argparse.ArgumentParser(prog="python -m bench.video", description=__doc__)
    parser.add_argument("--clips", type=comma_names, default=",".join(CLIP_KINDS),
                        help="comma-separated")
    parser.add_argument("--encodings", type=comma_names, default=",".join(VIDEO_ENCODINGS),
                        help="comma-separated")
    parser.add_argument("--decoders", type=comma_names, default=",".join(DEFAULT_DECODERS),
                        help="comma-separated, or 'all' for every installed decoder")
    parser.add_argument("--frames", type=at_least(2), default=DEFAULT_FRAMES)
    parser.add_argument(
        "--keyframe-interval",
        type=at_least(0),
        default=TemporalConfig.keyframe_interval,
        help="frames between periodic keyframes (0: none)",
    )
    add_report_option(parser, "video.json", flag="--output")
    args = parser.parse_args(argv)
    if "all" in args.decoders and len(args.decoders) > 1:
        parser.error(
            f"argument --decoders: 'all' (every installed decoder) goes alone, got "
            f"{','.join(args.decoders)}; give --decoders all, or name the decoders only"
        )
    decoders = (
        tuple(spec.name for spec in available_decoders())
        if args.decoders == ("all",)
        else args.decoders
    )
    refuse_unknown(parser, "clips", args.clips, CLIP_KINDS)
    refuse_unknown(parser, "encodings", args.encodings, VIDEO_ENCODINGS)
    refuse_unknown_decoders(parser, decoders, encodings=args.encodings)
    config = TemporalConfig(keyframe_interval=args.keyframe_interval)
    load_at_start = os.getloadavg()
    print(
        f"{'clip':13s} {'encoding':8s} {'decoder':9s} {'mode':11s} {'PSNR':>7s} {'PU21':>7s} "
        f"{'W acc':>7s} {'tcons':>8s} {'flicker':>8s} {'ms/fr':>7s} {'local':>6s} {'spat':>6s}"
    )
    rows = run(
        args.clips, args.encodings, decoders,
        args.frames, config,
    )
    summary = summarize(rows)
    report = {
        **host_facts(),
        "load_average_at_start": load_at_start,
        "frames": args.frames,
        "config": dataclasses.asdict(config),
        "rows": rows,
        "summary": summary,
    }
    load = [load_at_start, report["load_average"]]
    return publish(report, markdown_table(summary, load), args.output, rows="rows")


if __name__ == "__main__":
    raise SystemExit(main())
