"""Speed against accuracy: every decoder, ``auto`` at each quality, and tile sizes.

``python -m bench.tradeoff`` measures, on 2 cores (onnxruntime threads from
``MCAM_WORKER_THREADS``, default 2; idle threads spin with ``MCAM_ORT_SPIN=1``):

- ``val-256``: the fixed val-256 protocol (mantissa, 8 bits, overexposed 0.2);
- ``large-512`` / ``large-1024``: seeded synthetic scenes at 512 and 1024 px;
- ``mostly-dark``: val-256 crops exposed so that only 1% of pixels wrap, plus
  unwrapped crops (realistic for streaming: most tiles need nothing);
- ``glows``: every other val-256 crop with smooth bright lobes added
  (:func:`models.scenes.glows`: a lamp's glare, a specular highlight), exposed like
  val-256: bright regions whose wrap rings the codes decide but the nets under-count;

for each decoder: PSNR and PU21-PSNR against the true irradiance, winding
accuracy, ms/frame (median of repeats; a latency budget's: one decode per frame) and
frames/s. It marks the Pareto front (no other point is both faster and more
accurate), measures the machine's peak GFLOP/s with a float32 matrix multiply and
reports each network's achieved GFLOP/s against it, prints Markdown tables and writes
JSON and a PNG plot.

Latency budgets: ``auto-<N>ms`` for each of :data:`BUDGETS_MS` is measured like any
decoder but on one timed decode per frame (:func:`measure`), plus the share of frames
it decoded within its budget and the qualities it chose; and per set, the budget's
cost model (:mod:`models.decoders.budget`) is checked against each quality of
``auto``: predicted over measured ms, frame by frame.
"""

from __future__ import annotations

import argparse
import time
from collections import Counter
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from onnx import TensorProto, helper

from bench import (
    RESULTS,
    Distinct,
    add_report_option,
    add_val256_frames_option,
    at_least,
    bench_parser,
    host_facts,
    import_extra,
    one_line_errors,
    refuse_unknown_decoders,
    report_path,
    write_report,
)
from models import metrics
from models.decoders import Decoder, available_decoders, get_decoder
from models.decoders.adaptive import AdaptiveDecoder
from models.decoders.adaptive_policy import DEFAULT_TILE, QUALITIES
from models.decoders.budget import BudgetDecoder
from models.decoders.cost_model import adaptive as budget_adaptive
from models.decoders.cost_model import predicted_ms
from models.decoders.learned import make_session, ort_spinning, worker_threads
from models.formation import SensorParams, dequantize, simulate
from models.scene_analysis import FrameAnalysis, analyse, has_residue
from models.scenes import (
    VAL256_BITS,
    VAL256_MAX_WRAPS,
    VAL256_OVEREXPOSED,
    ValFrame,
    add_glows,
    exposed_frames,
    synthetic_scene,
    val256_frames,
    val256_scenes,
)
from models.timing import median_ns

VAL_PARAMS = SensorParams(encoding="mantissa", bits=VAL256_BITS, max_wraps=VAL256_MAX_WRAPS)
TILE_SIZES = (32, 64, 128)
#: Latency budgets (ms per frame) whose ``auto-<N>ms`` decoders are measured.
BUDGETS_MS = (20, 60, 120)


def frames_at(scene: np.ndarray, overexposed: float | None, gain: float | None) -> ValFrame:
    """One mantissa frame of ``scene`` at the val-256 settings and the given exposure."""
    params = VAL_PARAMS.model_copy(update={"gain": gain})
    frame = simulate(scene, params, overexposed=overexposed)
    return ValFrame(frame.codes, frame.winding, frame.irradiance, frame.params)


def large_frames(size: int, count: int) -> list[ValFrame]:
    """Seeded synthetic scenes at ``size`` px, exposed like val-256."""
    scenes = [synthetic_scene(1000 + k, size) for k in range(count)]
    return [frames_at(scene, VAL256_OVEREXPOSED, None) for scene in scenes]


def mostly_dark_frames(count: int) -> list[ValFrame]:
    """Val crops where 1% of pixels wrap, and as many where none does (gain below 1/max)."""
    crops = [scene[:256, :256] for _, scene in val256_scenes()][:count]
    wrapped = [frames_at(crop, 0.01, None) for crop in crops]
    unwrapped = [frames_at(crop, None, 0.9 / float(crop.max())) for crop in crops]
    return wrapped + unwrapped


#: Seed of the lobes of the ``glows`` set.
GLOW_SEED = 77


def glow_frames(count: int) -> list[ValFrame]:
    """``count`` val-256 crops (every other one) with seeded lobes, at the val-256 settings."""
    crops = val256_scenes()[::2][:count]
    lit = [
        (label, add_glows(crop, np.random.default_rng([GLOW_SEED, index])))
        for index, (label, crop) in enumerate(crops)
    ]
    return exposed_frames(lit, "mantissa")


def median_ms(run: Callable[[], Any], repeats: int) -> float:
    """Median wall time of ``run`` in ms over ``repeats`` calls (after one warm-up)."""
    return median_ns(run, repeats) / 1e6


def measure(
    decoder: Decoder,
    frames: list[ValFrame],
    repeats: int,
    clock: Callable[[], int] = time.perf_counter_ns,
) -> dict[str, Any]:
    """Mean accuracy and ms/frame (the mean over frames of each frame's median of
    ``repeats`` decodes) of one decoder on a frame set. An exact frame's PSNR counts at
    :data:`models.metrics.PSNR_CAP` (it was left out, so one 30 dB frame among exact
    ones read 30 dB), and ``exact_frames`` says how many there were.

    A latency budget (``auto-<N>ms``) learns from every decode and may choose another
    quality the next time it sees a frame, so each frame is decoded once, timed
    (``clock``, ns), after one untimed decode of the first frame (its cost calibration):
    its accuracy, ms, the qualities it chose and the share of frames decoded within the
    budget are all of those decodes. Its ms were the median of three later decodes,
    which may have chosen otherwise than the decode its PSNR came from, and a median of
    repeats hid the decodes over budget."""
    budget = isinstance(decoder, BudgetDecoder)
    if budget:
        decoder.decode(frames[0].codes, frames[0].params)
    psnr, pu21, accuracy, ms, chosen = [], [], [], [], []
    for frame in frames:
        start = clock()
        result = decoder.decode(frame.codes, frame.params)
        once_ms = (clock() - start) / 1e6
        psnr.append(metrics.psnr(result.irradiance, frame.x))
        pu21.append(metrics.pu21_psnr(result.irradiance, frame.x))
        accuracy.append(metrics.winding_accuracy(result.winding, frame.winding))
        if budget:
            ms.append(once_ms)
            chosen.append(result.info["details"]["budget"]["chosen"])
        else:
            ms.append(median_ms(lambda f=frame: decoder.decode(f.codes, f.params), repeats))
    mean_ms = float(np.mean(ms))
    row: dict[str, Any] = {
        "psnr_db": metrics.mean_capped_psnr(psnr),
        "pu21_psnr_db": metrics.mean_capped_psnr(pu21),
        "winding_accuracy": float(np.mean(accuracy)),
        "ms_per_frame": mean_ms,
        "frames_per_s": 1000.0 / mean_ms,
        "exact_frames": int(sum(1 for p in psnr if not np.isfinite(p))),
    }
    if budget:
        row["within_budget"] = float(np.mean([t <= decoder.budget_ms for t in ms]))
        row["chosen"] = dict(Counter(chosen))
    return row


#: A cost model's predicted ms of a quality of ``auto`` on a frame (its analysis, shape
#: and parameters): :func:`models.decoders.cost_model.predicted_ms`.
Predictor = Callable[[str, FrameAnalysis, tuple[int, int], SensorParams], float]


def prediction_ratios(
    frames: list[ValFrame], repeats: int, predict: Predictor = predicted_ms
) -> dict[str, dict[str, float]]:
    """How well the latency-budget cost model (``predict``:
    :func:`models.decoders.cost_model.predicted_ms`) predicts each quality of ``auto``:
    per quality, the geometric mean, least and greatest ratio of predicted to measured ms
    (median of ``repeats``) of the W prediction after the scene analysis, over the
    frames with residues. A frame without residues is known by its analysis; it was
    known by a prediction of 0 ms, which it gets only when the routing's own cost per
    pixel calibrates to 0 (on this host it measures 0 or 3-13 ns a pixel from process to
    process), so in some runs such frames were counted."""
    ratios: dict[str, list[float]] = {quality: [] for quality in QUALITIES}
    for frame in frames:
        m = dequantize(frame.codes, frame.params.bits)
        analysis = analyse(m, frame.params, DEFAULT_TILE)
        if analysis.itoh_likely:
            continue
        for quality in QUALITIES:
            predicted = predict(quality, analysis, m.shape, frame.params)
            decode = partial(budget_adaptive(quality).explain_analysed, m, frame.params, analysis)
            measured = median_ms(decode, repeats)
            ratios[quality].append(predicted / measured)
    return {
        quality: {
            "geometric_mean": float(np.exp(np.mean(np.log(values)))),
            "min": float(np.min(values)),
            "max": float(np.max(values)),
            "frames": len(values),
        }
        for quality, values in ratios.items()
        if values
    }


def pareto(rows: list[dict[str, Any]]) -> None:
    """Mark rows no other row beats on both ms/frame and PSNR."""
    for row, front in zip(rows, undominated(rows, "psnr_db"), strict=True):
        row["pareto"] = front


def undominated(rows: list[dict[str, Any]], key: str) -> list[bool]:
    """Whether each row is on the Pareto front of ms/frame against ``key`` (a PSNR, dB):
    no other row is at least as fast and as accurate and better in one of them."""
    return [
        not any(
            other is not row
            and other["ms_per_frame"] <= row["ms_per_frame"]
            and other[key] >= row[key]
            and (other["ms_per_frame"], other[key]) != (row["ms_per_frame"], row[key])
            for other in rows
        )
        for row in rows
    ]


#: ONNX opset of the peak's MatMul graph (that of the exported nets).
MATMUL_OPSET = 17


def matmul_gflops(size: int = 2048, repeats: int = 5) -> dict[str, float]:
    """This machine's float32 throughput in GFLOP/s by runtime: a ``size``-square matrix
    multiply in numpy and in onnxruntime (the nets' runtime, with their threads), each the
    best of ``repeats``. The peak is the faster of the two: measured 2026-11-27 on this
    host, numpy's alone put mantissanet-large's convolutions at 111% of "peak"."""
    rng = np.random.default_rng(0)
    a = rng.random((size, size), dtype=np.float32)
    b = rng.random((size, size), dtype=np.float32)
    session = make_session(matmul_model(), worker_threads())
    runs = {
        "numpy": lambda: a @ b,
        "onnxruntime": lambda: session.run(None, {"a": a, "b": b}),
    }
    return {
        name: 2 * size**3 / (min(median_ms(run, 1) for _ in range(repeats)) / 1000) / 1e9
        for name, run in runs.items()
    }


def matmul_model() -> bytes:
    """A serialized ONNX graph ``c = a @ b`` of float32 matrices of any size."""
    dims = [("n", "k"), ("k", "m"), ("n", "m")]
    a, b, c = (
        helper.make_tensor_value_info(name, TensorProto.FLOAT, list(shape))
        for name, shape in zip("abc", dims, strict=True)
    )
    node = helper.make_node("MatMul", ["a", "b"], ["c"])
    graph = helper.make_graph([node], "matmul", [a, b], [c])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", MATMUL_OPSET)])
    return model.SerializeToString()


def tile_variants() -> dict[str, AdaptiveDecoder]:
    """``auto`` at each quality and each tile size of :data:`TILE_SIZES` but the default,
    by name (``auto-<quality>-tile<px>``)."""
    return {
        f"auto-{q}-tile{t}": AdaptiveDecoder(q, tile=t)
        for q in QUALITIES
        for t in TILE_SIZES
        if t != DEFAULT_TILE
    }


def default_names() -> list[str]:
    """Every installed decoder, the tile variants and the latency budgets of
    :data:`BUDGETS_MS`."""
    installed = [spec.name for spec in available_decoders() if spec.name != "auto"]
    return installed + list(tile_variants()) + [f"auto-{b:g}ms" for b in BUDGETS_MS]


def candidates(names: list[str] | None) -> list[tuple[str, Decoder]]:
    """The named decoders (any the registry resolves, or a tile variant), else
    :func:`default_names`."""
    variants = tile_variants()
    return [(n, variants[n] if n in variants else get_decoder(n)) for n in names or default_names()]


def speedups(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """``auto`` against always running a network, alone or refined (``<net>+puma``): for
    each :func:`auto_rows` row and each :func:`network_rows` row at most as accurate
    (W accuracy), how many times faster auto is, and both PSNRs."""
    return [
        {
            "auto": auto["decoder"],
            "network": net["decoder"],
            "speedup": net["ms_per_frame"] / auto["ms_per_frame"],
            "auto_winding_accuracy": auto["winding_accuracy"],
            "network_winding_accuracy": net["winding_accuracy"],
            "auto_psnr_db": auto["psnr_db"],
            "network_psnr_db": net["psnr_db"],
        }
        for auto in auto_rows(rows)
        for net in network_rows(rows)
        if net["winding_accuracy"] <= auto["winding_accuracy"]
    ]


def auto_rows(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The rows of ``auto`` at one quality (but the latency budgets, which mix qualities)."""
    return [r for r in rows if r["decoder"].startswith("auto") and "within_budget" not in r]


def network_rows(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The rows of a network, alone (it has GFLOP/s) or refined (``<net>+puma``)."""
    return [r for r in rows if "gflops_per_s" in r or r["decoder"].endswith("+puma")]


def no_speedups_reason(rows: list[dict[str, Any]]) -> str:
    """Why :func:`speedups` of ``rows`` is empty, and what to name in ``--decoders``."""
    if not auto_rows(rows):
        return (
            "Skipped: no quality of `auto` (auto, auto-fast, auto-balanced, auto-best) was "
            "measured on mostly-dark; name one in --decoders."
        )
    if not network_rows(rows):
        return (
            "Skipped: no network (e.g. mantissanet-small, or refined: mantissanet-small+puma) "
            "was measured on mostly-dark; name one in --decoders."
        )
    return "None: every network measured is more accurate (W acc) than every `auto` quality."


def gflops_of(name: str) -> float | None:
    """GFLOPs per 256x256 mantissa frame from the decoder's model card, if it is a network
    (for unmodnet: per pass)."""
    for spec in available_decoders():
        if spec.name == name:
            flops = spec.figures.get(VAL_PARAMS.encoding, {}).get("gflops_256")
            return None if flops is None else float(flops)
    return None


def network_pixels(frames: list[ValFrame]) -> float:
    """Mean pixels per frame of ``frames`` that a network alone runs on: every pixel of a
    frame with a residue, none of one without (it is integrated, or has one W: its GFLOP/s
    had counted the net's work on the glows' and mostly-dark sets' frames that have no
    residue, 144% of the peak on the glows)."""
    sizes = [f.codes.size if has_residue(dequantize(f.codes, f.params.bits)) else 0 for f in frames]
    return float(np.mean(sizes))


def add_throughput(row: dict[str, Any], pixels: float, peak: float) -> None:
    """Achieved GFLOP/s of a network row on ``pixels`` a frame, and its fraction of the
    machine's peak; none when the network ran on no pixel."""
    flops = gflops_of(row["decoder"])
    if flops is not None and pixels > 0:
        row["gflops_per_s"] = flops * pixels / 256**2 / (row["ms_per_frame"] / 1000)
        row["fraction_of_peak"] = row["gflops_per_s"] / peak


def run(args: argparse.Namespace) -> dict[str, Any]:
    sets = {"val-256": val256_frames("mantissa")[: args.frames]}
    if not args.quick:
        sets["large-512"] = large_frames(512, 2)
        sets["large-1024"] = large_frames(1024, 1)
    sets["mostly-dark"] = mostly_dark_frames(args.dark)
    if args.glows:
        sets["glows"] = glow_frames(args.glows)
    rates = matmul_gflops()
    peak = max(rates.values())
    table: dict[str, list[dict[str, Any]]] = {}
    predictions: dict[str, dict[str, dict[str, float]]] = {}
    for set_name, frames in sets.items():
        rows = []
        pixels = network_pixels(frames)
        for name, decoder in candidates(args.decoders):
            if set_name != "val-256" and "tile" in name:
                continue
            row = {"decoder": name, **measure(decoder, frames, args.repeats)}
            add_throughput(row, pixels, peak)
            rows.append(row)
        pareto(rows)
        table[set_name] = rows
        repeats = args.repeats if frames[0].codes.size <= 256**2 else 1
        predictions[set_name] = prediction_ratios(frames, repeats)
    dark_speedups = speedups(table["mostly-dark"])
    return {
        **host_facts(),
        "peak_gflops_per_s": peak,
        "matmul_gflops_per_s": rates,
        "repeats": args.repeats,
        "ort_threads": worker_threads(),
        "ort_spinning": ort_spinning(),
        "sets": {name: len(frames) for name, frames in sets.items()},
        "results": table,
        "mostly_dark_speedups": dark_speedups,
        "latency_predictions": predictions,
    }


def header(report: dict[str, Any]) -> str:
    """A report's first Markdown line: the measured peak, the load average when it was
    taken (other processes share the cores) and the date."""
    load = ", ".join(f"{v:.1f}" for v in report["load_average"])
    rates = report["matmul_gflops_per_s"]
    runtimes = ", ".join(f"{name} {rate:.1f}" for name, rate in rates.items())
    return (
        f"Peak float32 matmul: {report['peak_gflops_per_s']:.1f} GFLOP/s ({runtimes}); load "
        f"average {load} on {report['machine']['cores']} cores ({report['date']})"
    )


def markdown(report: dict[str, Any]) -> str:
    """The report as Markdown tables, one per frame set; a table with nothing to show
    is replaced by why (the decoders measured had none of what it compares)."""
    lines = [header(report)]
    for set_name, rows in report["results"].items():
        lines += set_lines(f"{set_name} ({report['sets'][set_name]} frames)", rows)
    lines += budget_lines(report)
    lines += table_or_reason(
        "mostly-dark: auto against always running a network (alone or refined) at most as "
        "accurate",
        ("auto", "network", "speed-up", "auto W acc", "network W acc", "auto PSNR",
         "network PSNR"),
        [
            f"| {s['auto']} | {s['network']} | {s['speedup']:.2f}x | "
            f"{100 * s['auto_winding_accuracy']:.2f}% | "
            f"{100 * s['network_winding_accuracy']:.2f}% "
            f"| {s['auto_psnr_db']:.2f} | {s['network_psnr_db']:.2f} |"
            for s in report["mostly_dark_speedups"]
        ],
        no_speedups_reason(report["results"].get("mostly-dark", [])),
    )  # fmt: skip
    return "\n".join(lines)


def set_lines(title: str, rows: list[dict[str, Any]]) -> list[str]:
    """The Markdown table of one frame set's rows, fastest first, and a note on its
    columns that compare nothing: GFLOP/s when no network alone was measured, the Pareto
    front when one decoder was."""
    body = []
    for r in sorted(rows, key=lambda r: r["ms_per_frame"]):
        flops = (
            f"{r['gflops_per_s']:.1f} ({100 * r['fraction_of_peak']:.0f}%)"
            if "gflops_per_s" in r
            else "-"
        )
        body.append(
            f"| {r['decoder']} | {r['psnr_db']:.2f} | {r['pu21_psnr_db']:.2f} | "
            f"{100 * r['winding_accuracy']:.2f}% | {r['ms_per_frame']:.2f} | "
            f"{r['frames_per_s']:.1f} | {flops} | {'*' if r['pareto'] else ''} |"
        )
    lines = table_or_reason(
        title,
        ("decoder", "PSNR dB", "PU21-PSNR dB", "W acc", "ms/frame", "frames/s",
         "GFLOP/s (% peak)", "Pareto"),
        body,
        "Skipped: the tile variants (`auto-<quality>-tile<px>`) are measured on val-256 "
        "only, and --decoders named nothing else.",
    )  # fmt: skip
    notes = [
        note
        for note, missing in (
            ("GFLOP/s: none of these decoders is a network alone, whose model card gives "
             "its GFLOPs.",
             bool(rows) and not any("gflops_per_s" in r for r in rows)),
            ("Pareto: one decoder was measured, so it is the front by itself.", len(rows) == 1),
        )
        if missing
    ]  # fmt: skip
    return lines + (["", " ".join(notes)] if notes else [])


def table_or_reason(
    title: str, columns: tuple[str, ...], body: list[str], reason: str
) -> list[str]:
    """A Markdown table (:func:`table_head`, then ``body``), or, when ``body`` has no
    line, its title and ``reason``: why there is nothing to show (an empty table read as
    a measurement of nothing)."""
    if not body:
        return ["", f"### {title}", "", reason]
    return table_head(title, columns) + body


def table_head(title: str, columns: tuple[str, ...]) -> list[str]:
    """The Markdown lines that open a table: a blank line, its title (a level-3
    heading), a blank line, the column names and the separator."""
    return ["", f"### {title}", "", f"| {' | '.join(columns)} |", "|---" * len(columns) + "|"]


def budget_lines(report: dict[str, Any]) -> list[str]:
    """Markdown tables of the latency budgets: what each ``auto-<N>ms`` chose and how
    many frames it decoded within its budget, and the cost model's predicted / measured
    ms per quality of ``auto``."""
    lines = table_or_reason(
        "Latency budgets (`auto-<N>ms`): frames decoded within the budget",
        ("set", "decoder", "within budget", "chosen", "ms/frame", "PSNR dB"),
        [
            f"| {set_name} | {r['decoder']} | {100 * r['within_budget']:.0f}% | "
            + ", ".join(f"{name} {count}" for name, count in r["chosen"].items())
            + f" | {r['ms_per_frame']:.1f} | {r['psnr_db']:.2f} |"
            for set_name, rows in report["results"].items()
            for r in rows
            if "within_budget" in r
        ],
        "Skipped: no latency budget was measured; name one in --decoders (e.g. auto-60ms).",
    )
    return lines + table_or_reason(
        "Latency cost model: predicted / measured ms of each quality of `auto` (after the "
        "scene analysis; frames with residues)",
        ("set", "quality", "geometric mean", "least", "greatest", "frames"),
        [
            f"| {set_name} | {quality} | {r['geometric_mean']:.2f} | {r['min']:.2f} | "
            f"{r['max']:.2f} | {r['frames']} |"
            for set_name, qualities in report["latency_predictions"].items()
            for quality, r in qualities.items()
        ],
        "None: no frame of any set has residues (its scene analysis sends it to itoh), so "
        "no quality of `auto` was timed.",
    )


def plot(report: dict[str, Any], path: Path) -> None:
    """PSNR and PU21-PSNR against ms/frame on val-256, each panel's own Pareto front
    marked and joined (the PU21 panel showed the PSNR front, which leaves out decoders
    on the PU21 one: mantissanet-small and -small-noise on 2026-11-27)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = report["results"]["val-256"]
    fig, axes = plt.subplots(1, 2, figsize=(12, 5))
    panels = (("psnr_db", "PSNR"), ("pu21_psnr_db", "PU21-PSNR"))
    for ax, (key, label) in zip(axes, panels, strict=True):
        on_front = undominated(rows, key)
        for r, marked in zip(rows, on_front, strict=True):
            ax.scatter(r["ms_per_frame"], r[key], color="C1" if marked else "C0")
            ax.annotate(r["decoder"], (r["ms_per_frame"], r[key]), fontsize=7)
        front = sorted(
            (r for r, marked in zip(rows, on_front, strict=True) if marked),
            key=lambda r: r["ms_per_frame"],
        )
        ax.plot([r["ms_per_frame"] for r in front], [r[key] for r in front], "C1--")
        ax.set_xscale("log")
        ax.set_xlabel("ms per 256x256 frame (2 cores)")
        ax.set_ylabel(f"{label} (dB)")
        ax.grid(True, alpha=0.3)
    fig.suptitle(f"val-256 speed/accuracy trade-off, {report['date'][:10]}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def refuse_plot_over_report(parser: argparse.ArgumentParser, plot: Path, out: Path) -> None:
    """A usage error when ``--plot`` names the report (``--out``) or its Markdown copy:
    the plot, written last, replaced it after the whole measurement."""
    if plot.resolve() in (out.resolve(), out.with_suffix(".md").resolve()):
        parser.error(
            f"argument --plot: {plot} is a file of the report (--out {out} and its .md "
            f"copy), which the plot would replace; give the plot its own file, e.g. "
            f"{out.with_suffix('.png')}"
        )


@one_line_errors
def main(argv: list[str] | None = None) -> int:
    parser = bench_parser(__name__, __doc__)
    add_val256_frames_option(parser)
    parser.add_argument("--dark", type=at_least(1), default=3, help="mostly-dark crops per kind")
    parser.add_argument("--glows", type=at_least(0), default=12, help="glows frames (0: none)")
    parser.add_argument("--repeats", type=at_least(1), default=3)
    parser.add_argument(
        "--decoders",
        nargs="+",
        action=Distinct,
        help="only these decoders (default: every installed one)",
    )
    parser.add_argument("--quick", action="store_true", help="skip the 512/1024 sets")
    add_report_option(parser, "tradeoff.json")
    parser.add_argument(
        "--plot", type=report_path, default=RESULTS / "tradeoff.png",
        help="PNG of speed against accuracy (default bench/results/tradeoff.png)",
    )
    args = parser.parse_args(argv)
    refuse_plot_over_report(parser, args.plot, args.out)
    refuse_unknown_decoders(
        parser, args.decoders, extra=tile_variants(), encodings=[VAL_PARAMS.encoding]
    )
    import_extra("matplotlib", "bench", "bench.tradeoff (its --plot)")
    report = run(args)
    write_report(report, markdown(report), args.out, rows="results")
    plot(report, args.plot)
    print(markdown(report))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
