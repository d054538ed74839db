"""Measure a decoder on the val-256 protocol (no torch: runs the shipped runtime decoder)."""

from __future__ import annotations

import numpy as np

from models.decoders.base import Decoder
from models.metrics import evaluate, mean_capped_psnr
from models.scenes import val256_frames

REPORTED = ("winding_accuracy", "psnr", "pu21_psnr", "ssim", "ms_ssim")


#: Metrics in dB whose per-frame value is infinite on an exact frame: averaged with
#: each frame at :data:`models.metrics.PSNR_CAP`, as the benchmarks do.
CAPPED = ("psnr", "pu21_psnr")


def val256_metrics(
    decoder: Decoder, encoding: str, read_noise: float = 0.0, frames: int | None = None
) -> dict[str, float]:
    """Mean val-256 metrics of ``decoder`` (winding accuracy, PSNR and PU21-PSNR in dB
    with an exact frame at the cap, SSIM, MS-SSIM) and the median decode time in ms,
    over the 24 frames of ``encoding`` (or the first ``frames``), timed after one untimed
    decode of the first (a net's first call creates its session)."""
    chosen = val256_frames(encoding, read_noise)[:frames]
    if chosen:
        decoder.decode(chosen[0].codes, chosen[0].params)
    scores: dict[str, list[float]] = {key: [] for key in REPORTED}
    times_ms = []
    for frame in chosen:
        result = decoder.decode(frame.codes, frame.params)
        metrics = evaluate(result.irradiance, frame.x, result.winding, frame.winding, flip=False)
        for key in REPORTED:
            scores[key].append(metrics[key])
        times_ms.append(result.timings_ns["total"] / 1e6)
    summary = {
        key: round(mean_capped_psnr(values) if key in CAPPED else float(np.mean(values)), 4)
        for key, values in scores.items()
    }
    return {**summary, "ms_per_frame": round(float(np.median(times_ms)), 2)}
