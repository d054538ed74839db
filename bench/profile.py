"""Where a winding net's inference time goes, per operator type, and which runtime settings help.

``python -m bench.profile`` runs one 256x256 mantissa frame through each network tier
(``mantissanet-tiny`` and ``mantissanet-small`` by default) with onnxruntime's profiler
in the shipped session (:func:`models.decoders.learned.make_session`) and reports:

- time per operator type (mean ms per inference over the profiled runs) and its share
  of the kernel time, grouped as convolution, layout (NCHWc reorders), normalisation,
  non-local block (MatMul, Softmax), resize, element-wise and other;
- the FLOPs of the convolutions (2 x multiply-adds, from the convolution shapes of an
  unoptimised session) and their achieved GFLOP/s, against the machine's measured
  float32 matrix-multiply peak (:func:`bench.tradeoff.matmul_gflops`);
- the runtime levers: median ms per inference of sessions that differ in graph
  optimisation level (``all`` adds the NCHWc layout transform to ``extended``),
  intra-op threads and ``session.intra_op.allow_spinning``, timed back to back
  (interleaved) so that load from other processes hits every variant alike.

It prints Markdown tables and writes ``bench/results/profile.json``.
"""

from __future__ import annotations

import argparse
import bisect
import json
import os
import tempfile
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import onnxruntime as ort

from bench import (
    Distinct,
    add_report_option,
    at_least,
    bench_parser,
    entry_point,
    host_facts,
    refuse_unknown,
)
from bench.tradeoff import header, matmul_gflops
from models.decoders.learned import load_cards, make_session, worker_threads

SIZE = 256
MODELS = ("mantissanet-tiny", "mantissanet-small")
CONV_OPS = frozenset({"Conv", "FusedConv"})
#: Operator type -> group in the report.
GROUPS = {
    **dict.fromkeys(CONV_OPS, "convolution"),
    **dict.fromkeys(("ReorderInput", "ReorderOutput"), "layout"),
    "InstanceNormalization": "normalisation",
    **dict.fromkeys(("MatMul", "FusedMatMul", "Softmax", "Transpose"), "non-local"),
    **dict.fromkeys(("Resize", "Upsample"), "resize"),
    **dict.fromkeys(
        ("Add", "Mul", "Sub", "Relu", "Sigmoid", "Tanh", "Clip", "Abs"), "element-wise"
    ),
}
#: Session variants compared: (label, graph optimisation level, intra-op threads, spinning).
LEVERS: tuple[tuple[str, str, int, bool], ...] = tuple(
    (f"{level}, {threads} thread{'s' * (threads > 1)}{spin_label}", level, threads, spin)
    for level in ("all", "extended", "basic")
    for threads, spin, spin_label in (
        (2, True, ", spinning"),
        (2, False, ", no spinning"),
        (1, False, ""),
    )
)
LEVELS = {
    "disabled": ort.GraphOptimizationLevel.ORT_DISABLE_ALL,
    "basic": ort.GraphOptimizationLevel.ORT_ENABLE_BASIC,
    "extended": ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED,
    "all": ort.GraphOptimizationLevel.ORT_ENABLE_ALL,
}


def frame(seed: int = 0) -> np.ndarray:
    """A 1x1xSIZExSIZE float32 input of stored values in [0, 1) (wrap units)."""
    return np.random.default_rng(seed).random((1, 1, SIZE, SIZE), dtype=np.float32)


def session(path: str, level: str, threads: int, spinning: bool, profile: str | None = None):
    """A CPU session with the given optimisation level, intra-op threads and spinning;
    profiling to files starting with ``profile`` when given."""
    options = ort.SessionOptions()
    options.graph_optimization_level = LEVELS[level]
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.add_session_config_entry("session.intra_op.allow_spinning", str(int(spinning)))
    if profile is not None:
        options.enable_profiling = True
        options.profile_file_prefix = profile
    return ort.InferenceSession(path, options, providers=["CPUExecutionProvider"])


def kernel_events(sess: ort.InferenceSession, x: np.ndarray, runs: int) -> list[list[dict]]:
    """Profiler node events of each of the last ``runs`` of ``runs + 1`` inferences (the
    first is a warm-up); ``sess`` must have been created with profiling on."""
    for _ in range(runs + 1):
        sess.run(None, {"m": x})
    path = Path(sess.end_profiling())
    events = json.loads(path.read_text())
    path.unlink()
    starts = sorted(int(e["ts"]) for e in events if e.get("name") == "model_run")[-runs:]
    per_run: list[list[dict]] = [[] for _ in starts]
    for event in events:
        if event.get("cat") == "Node" and event["name"].endswith("_kernel_time"):
            index = bisect.bisect_right(starts, int(event["ts"])) - 1
            if index >= 0:
                per_run[index].append(event)
    return per_run


def node_flops(event: dict[str, Any]) -> float:
    """FLOPs (2 per multiply-add) of one convolution event, from its weight and output
    shapes (padded channels count when the session uses the NCHWc layout)."""
    weight = next(iter(event["args"]["input_type_shape"][1].values()))
    output = next(iter(event["args"]["output_type_shape"][0].values()))
    return 2.0 * float(np.prod(output)) * float(np.prod(weight[1:]))


def conv_flops(path: str) -> float:
    """FLOPs of every convolution of the model at SIZE x SIZE, from the shapes an
    unoptimised session reports (the useful work, whatever the layout)."""
    with tempfile.TemporaryDirectory() as folder:
        sess = session(path, "disabled", 1, False, profile=os.path.join(folder, "shapes"))
        (events,) = kernel_events(sess, frame(), 1)
    return sum(node_flops(e) for e in events if e["args"]["op_name"] in CONV_OPS)


def conv_by_resolution(per_run: list[list[dict]]) -> list[dict[str, Any]]:
    """Convolutions grouped by output resolution: count, output channels, GFLOP, ms
    (median over runs) and GFLOP/s (where the thin full-resolution layers lose throughput)."""
    levels: dict[int, dict[str, Any]] = {}
    for index, events in enumerate(per_run):
        for event in events:
            if event["args"]["op_name"] not in CONV_OPS:
                continue
            output = next(iter(event["args"]["output_type_shape"][0].values()))
            level = levels.setdefault(
                int(output[-1]),
                {"convs": 0, "channels": set(), "gflop": 0.0, "ms": [0.0] * len(per_run)},
            )
            level["convs"] += 1
            level["channels"].add(int(output[1]))
            level["gflop"] += node_flops(event) / 1e9 / len(per_run)
            level["ms"][index] += float(event["dur"]) / 1000.0
    rows = []
    for width, level in sorted(levels.items(), reverse=True):
        ms = float(np.median(level["ms"]))
        rows.append(
            {
                "width": width,
                "convs": level["convs"] // len(per_run),
                "out_channels": sorted(level["channels"]),
                "gflop": level["gflop"],
                "ms": ms,
                "gflops_per_s": level["gflop"] / (ms / 1000),
            }
        )
    return rows


def op_table(per_run: list[list[dict]]) -> list[dict[str, Any]]:
    """Median ms per inference and share of kernel time per operator type, largest first."""
    per_op: dict[str, list[float]] = defaultdict(lambda: [0.0] * len(per_run))
    for index, events in enumerate(per_run):
        for event in events:
            per_op[event["args"]["op_name"]][index] += float(event["dur"]) / 1000.0
    medians = {op: float(np.median(ms)) for op, ms in per_op.items()}
    total = sum(medians.values())
    return [
        {"op": op, "group": GROUPS.get(op, "other"), "ms": ms, "share": ms / total}
        for op, ms in sorted(medians.items(), key=lambda item: -item[1])
    ]


def profile_model(card: dict[str, Any], runs: int, peak: float) -> dict[str, Any]:
    """Per-operator profile of one model in the shipped session, and its conv GFLOP/s."""
    with tempfile.TemporaryDirectory() as folder:
        prefix = os.path.join(folder, "run")
        sess = make_session(card["path"], worker_threads(), profile_prefix=prefix)
        per_run = kernel_events(sess, frame(), runs)
    ops = op_table(per_run)
    groups: dict[str, float] = defaultdict(float)
    for row in ops:
        groups[row["group"]] += row["share"]
    kernel_ms = sum(row["ms"] for row in ops)
    conv_ms = sum(row["ms"] for row in ops if row["op"] in CONV_OPS)
    flops = conv_flops(card["path"])
    conv_rate = flops / (conv_ms / 1000) / 1e9
    return {
        "model": card["name"],
        "card_gflops_256": card["gflops_256"],
        "conv_gflops": flops / 1e9,
        "kernel_ms": kernel_ms,
        "conv_ms": conv_ms,
        "conv_gflops_per_s": conv_rate,
        "conv_fraction_of_peak": conv_rate / peak,
        "whole_net_gflops_per_s": card["gflops_256"] / (kernel_ms / 1000),
        "groups": dict(sorted(groups.items(), key=lambda item: -item[1])),
        "conv_by_resolution": conv_by_resolution(per_run),
        "ops": ops,
    }


def time_levers(path: str, repeats: int) -> list[dict[str, Any]]:
    """Median and minimum ms per inference of each session variant, timed interleaved in a
    new random order each round (so that no variant always runs after the same one)."""
    sessions = [session(path, level, threads, spin) for _, level, threads, spin in LEVERS]
    x = frame()
    for sess in sessions:
        sess.run(None, {"m": x})
    times: list[list[float]] = [[] for _ in sessions]
    rng = np.random.default_rng(0)
    for _ in range(repeats):
        for index in rng.permutation(len(sessions)):
            start = time.perf_counter_ns()
            sessions[index].run(None, {"m": x})
            times[index].append((time.perf_counter_ns() - start) / 1e6)
    return [
        {"variant": label, "median_ms": float(np.median(t)), "min_ms": float(np.min(t))}
        for (label, *_), t in zip(LEVERS, times, strict=True)
    ]


def run(args: argparse.Namespace) -> dict[str, Any]:
    cards = [card for card in mantissa_cards() if card["decoder"] in args.models]
    rates = matmul_gflops()
    profiles = [profile_model(card, args.runs, max(rates.values())) for card in cards]
    levers = {card["name"]: time_levers(card["path"], args.repeats) for card in cards}
    return {
        **host_facts(),
        "size": SIZE,
        "threads": worker_threads(),
        "runs": args.runs,
        "repeats": args.repeats,
        "peak_gflops_per_s": max(rates.values()),
        "matmul_gflops_per_s": rates,
        "profiles": profiles,
        "levers": levers,
    }


def markdown(report: dict[str, Any]) -> str:
    """The report as Markdown: per-model operator tables, then the lever timings."""
    lines = [header(report)]
    for p in report["profiles"]:
        lines += [
            "",
            f"### {p['model']}: {p['kernel_ms']:.1f} ms kernel time per {SIZE}x{SIZE} frame; "
            f"convolutions {p['conv_gflops']:.2f} GFLOP in {p['conv_ms']:.1f} ms = "
            f"{p['conv_gflops_per_s']:.1f} GFLOP/s ({100 * p['conv_fraction_of_peak']:.0f}% "
            f"of peak); whole net {p['whole_net_gflops_per_s']:.1f} GFLOP/s",
            "",
            "| operator | group | ms | share |",
            "|---|---|---|---|",
        ]
        lines += [
            f"| {r['op']} | {r['group']} | {r['ms']:.2f} | {100 * r['share']:.1f}% |"
            for r in p["ops"]
            if r["share"] >= 0.002
        ]
        groups = ", ".join(f"{g} {100 * s:.0f}%" for g, s in p["groups"].items())
        lines += [
            "",
            f"By group: {groups}",
            "",
            "Convolutions by output width, as run (channels padded to the NCHWc block when the "
            "session uses that layout):",
            "",
            "| conv output width | convs | out channels | GFLOP | ms | GFLOP/s |",
            "|---|---|---|---|---|---|",
        ]
        lines += [
            f"| {c['width']} | {c['convs']} | {', '.join(map(str, c['out_channels']))} | "
            f"{c['gflop']:.3f} | {c['ms']:.2f} | {c['gflops_per_s']:.1f} |"
            for c in p["conv_by_resolution"]
        ]
    for model, rows in report["levers"].items():
        lines += [
            "",
            f"### Runtime levers, {model} ({report['repeats']} interleaved runs)",
            "",
            "onnxruntime's defaults are `all` with spinning threads.",
            "",
            "| session | median ms | min ms |",
            "|---|---|---|",
        ]
        lines += [f"| {r['variant']} | {r['median_ms']:.1f} | {r['min_ms']:.1f} |" for r in rows]
    return "\n".join(lines)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = bench_parser(__name__, __doc__)
    parser.add_argument(
        "--models", nargs="+", action=Distinct, default=list(MODELS), help="decoders to profile"
    )
    parser.add_argument(
        "--runs", type=at_least(1), default=10, help="profiled inferences per model"
    )
    parser.add_argument(
        "--repeats", type=at_least(1), default=15, help="timed runs per lever variant"
    )
    add_report_option(parser, "profile.json")
    args = parser.parse_args(argv)
    profiled = sorted({card["decoder"] for card in mantissa_cards()})
    refuse_unknown(parser, "models", args.models, profiled)
    return args


def mantissa_cards() -> list[dict[str, Any]]:
    """The cards of the mantissa models, the ones profiled (:func:`frame` is mantissa)."""
    return [card for card in load_cards() if card["encoding"] == "mantissa"]


main = entry_point(parse_args, run, markdown, rows="profiles")


if __name__ == "__main__":
    raise SystemExit(main())
