"""Where the val-256 PSNR is lost, and how much of it the codes can give back at all.

``python -m bench.headroom`` answers two questions about the accuracy targets of the
learned decoders (38 dB on mantissa val-256) for each encoding:

1. Which pixels cost the PSNR? For each decoder, the PSNR once the true W is put
   back on one group of pixels: the clipped ones (``x >= max_wraps``), those with
   true ``W >= 3``, those with ``W < 3``, those a path-following unwrapper could
   reach (below; what a perfect unwrapper could add to the decoder) and those it could
   not (what only a prior could add).
2. How much W do the codes determine? A pixel is *reachable* when a 4-neighbour path
   links it to an unwrapped (``W = 0``) pixel with every step changing the true ``u``
   by less than half a wrap (the Itoh condition): along such a path the wrapped
   differences give W exactly. Elsewhere the codes are also consistent with another
   W, and only a prior (what scenes look like) can choose; the share is reported per
   true W.

Decoders: ``itoh`` and the installed winding net with the highest measured val-256
PSNR (``--decoders`` to choose). Prints Markdown; writes ``bench/results/headroom.json``.
"""

from __future__ import annotations

import argparse
import os
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from bench import (
    Distinct,
    add_report_option,
    add_val256_frames_option,
    bench_parser,
    entry_point,
    host_facts,
    host_line,
    refuse_unknown_decoders,
)
from models.decoders import get_decoder
from models.decoders.adaptive_policy import most_accurate_net
from models.formation import SensorParams, dequantize, from_unwrapped, to_unwrapped
from models.metrics import mean_capped_psnr, psnr, winding_accuracy
from models.scenes import ValFrame, val256_frames

ENCODINGS = ("mantissa", "modulo")
THREADS = 2
#: True W at and above this count as "high" (the nets' right-W share drops to 0 there).
HIGH_W = 3
#: Reachable share is reported per true W up to this value; larger W are pooled.
W_TOP = 5
GROUPS = ("clipped", "high_w", "low_w", "reachable", "unreachable")


def reachable(u: NDArray[np.float64], winding: NDArray[np.int64]) -> NDArray[np.bool_]:
    """Pixels linked to a ``W = 0`` pixel by 4-neighbour steps of true ``|du| < 1/2``."""
    height, width = u.shape
    index = np.arange(u.size).reshape(height, width)
    across = np.abs(np.diff(u, axis=1)) < 0.5
    down = np.abs(np.diff(u, axis=0)) < 0.5
    rows = np.concatenate([index[:, :-1][across], index[:-1][down]])
    cols = np.concatenate([index[:, 1:][across], index[1:][down]])
    graph = coo_matrix((np.ones(rows.size), (rows, cols)), shape=(u.size, u.size))
    labels = connected_components(graph, directed=False)[1].reshape(height, width)
    return np.isin(labels, np.unique(labels[winding == 0]))


def clipped(frame: ValFrame) -> NDArray[np.bool_]:
    """Pixels at or above ``max_wraps`` (none when the frame's parameters clip nothing)."""
    top = frame.params.max_wraps
    return np.zeros(frame.x.shape, bool) if top is None else frame.x >= top


def groups(frame: ValFrame, reach: NDArray[np.bool_]) -> dict[str, NDArray[np.bool_]]:
    """The pixel groups whose true W is put back, one at a time."""
    return {
        "clipped": clipped(frame),
        "high_w": frame.winding >= HIGH_W,
        "low_w": frame.winding < HIGH_W,
        "reachable": reach,
        "unreachable": ~reach,
    }


def reachable_share(frames: list[ValFrame], reach: list[NDArray[np.bool_]]) -> dict[str, Any]:
    """Share of pixels that are reachable, overall and per true W (``W_TOP``+ pooled)."""
    truth = np.concatenate([np.minimum(f.winding, W_TOP).ravel() for f in frames])
    linked = np.concatenate([r.ravel() for r in reach])
    per_w = {
        (f"{w}+" if w == W_TOP else str(w)): (
            float(linked[truth == w].mean()) if (truth == w).any() else None
        )
        for w in range(W_TOP + 1)
    }
    pixels = {
        (f"{w}+" if w == W_TOP else str(w)): float((truth == w).mean())
        for w in range(W_TOP + 1)
    }
    return {"overall": float(linked.mean()), "per_w": per_w, "pixel_share": pixels}


def decoder_row(name: str, frames: list[ValFrame], reach: list[NDArray[np.bool_]]) -> dict:
    """Mean PSNR and W accuracy of ``name`` as decoded and with each group's W put right;
    an exact frame's PSNR counts at :data:`models.metrics.PSNR_CAP` (its inf made the mean
    inf)."""
    decoder = get_decoder(name)
    scores: dict[str, list[float]] = {"as_decoded": [], **{g: [] for g in GROUPS}}
    accuracy = []
    for frame, linked in zip(frames, reach, strict=True):
        m = dequantize(frame.codes, frame.params.bits)
        estimate = decoder.decode(frame.codes, frame.params).winding
        accuracy.append(winding_accuracy(estimate, frame.winding))
        scores["as_decoded"].append(psnr(from_unwrapped(estimate + m, frame.params), frame.x))
        for group, mask in groups(frame, linked).items():
            fixed = np.where(mask, frame.winding, estimate)
            scores[group].append(psnr(from_unwrapped(fixed + m, frame.params), frame.x))
    return {
        "decoder": name,
        "winding_accuracy": float(np.mean(accuracy)),
        "psnr": {key: mean_capped_psnr(values) for key, values in scores.items()},
    }


def encoding_report(encoding: str, decoders: list[str], frames: int | None) -> dict[str, Any]:
    """Reachable shares and every decoder's PSNR headroom on one encoding's val-256."""
    chosen = val256_frames(encoding)[:frames]
    reach = [reachable(to_unwrapped(f.x, f.params), f.winding) for f in chosen]
    return {
        "encoding": encoding,
        "frames": len(chosen),
        "clipped_share": float(np.mean([clipped(f).mean() for f in chosen])),
        "reachable": reachable_share(chosen, reach),
        "decoders": [decoder_row(name, chosen, reach) for name in decoders],
    }


def default_decoders(encoding: str) -> list[str]:
    """``itoh`` and the most accurate installed winding net for ``encoding``."""
    best = most_accurate_net(SensorParams(encoding=encoding))  # type: ignore[arg-type]
    return ["itoh", *([best] if best else [])]


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Measure every encoding; the report with :func:`bench.host_facts`."""
    os.environ.setdefault("MCAM_WORKER_THREADS", str(THREADS))
    reports = [
        encoding_report(encoding, args.decoders or default_decoders(encoding), args.frames)
        for encoding in args.encodings
    ]
    return {
        "benchmark": "headroom",
        **host_facts(),
        "protocol": {"name": "val-256", "high_w": HIGH_W},
        "results": reports,
    }


def markdown(report: dict[str, Any]) -> str:
    """Per encoding: the reachable share per true W, then each decoder's PSNR headroom."""
    lines = [f"PSNR headroom on val-256, {host_line(report)}", ""]
    for result in report["results"]:
        share = result["reachable"]
        labels = list(share["per_w"])
        lines += [
            f"{result['encoding']}: {result['frames']} frames, "
            f"{100 * result['clipped_share']:.2f}% of pixels clipped, "
            f"{100 * share['overall']:.1f}% reachable by an Itoh path from W = 0",
            "",
            "| true W | " + " | ".join(labels) + " |",
            "|---|" + "---|" * len(labels),
            "| share of pixels % | "
            + " | ".join(f"{100 * share['pixel_share'][w]:.2f}" for w in labels) + " |",
            "| reachable % | "
            + " | ".join("-" if (v := share["per_w"][w]) is None else f"{100 * v:.1f}"
                         for w in labels) + " |",
            "",
            "| decoder | W acc % | PSNR dB | true W on clipped | on W >= 3 | on W < 3 "
            "| on reachable | on unreachable |",
            "|---|---|---|---|---|---|---|---|",
        ]  # fmt: skip
        for row in result["decoders"]:
            p = row["psnr"]
            lines.append(
                f"| {row['decoder']} | {100 * row['winding_accuracy']:.2f} | "
                f"{p['as_decoded']:.2f} | {p['clipped']:.2f} | {p['high_w']:.2f} | "
                f"{p['low_w']:.2f} | {p['reachable']:.2f} | {p['unreachable']:.2f} |"
            )
        lines.append("")
    return "\n".join(lines).rstrip()


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = bench_parser(__name__, __doc__)
    parser.add_argument(
        "--decoders", nargs="+", action=Distinct, help="default: itoh and the best winding net"
    )
    parser.add_argument(
        "--encodings", nargs="+", action=Distinct, default=list(ENCODINGS), choices=ENCODINGS
    )
    add_val256_frames_option(parser)
    add_report_option(parser, "headroom.json")
    args = parser.parse_args(argv)
    refuse_unknown_decoders(parser, args.decoders, encodings=args.encodings)
    return args


main = entry_point(parse_args, run, markdown, rows="results")


if __name__ == "__main__":
    raise SystemExit(main())
