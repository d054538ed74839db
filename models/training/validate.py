"""Measure a decoder on the val-256 protocol (no torch: runs the shipped runtime decoder)."""

from __future__ import annotations

import numpy as np

from models.decoders.base import Decoder
from models.metrics import evaluate
from models.scenes import val256_frames

REPORTED = ("winding_accuracy", "psnr", "pu21_psnr", "ssim", "ms_ssim")


def val256_metrics(
    decoder: Decoder, encoding: str, read_noise: float = 0.0, frames: int | None = None
) -> dict[str, float]:
    """Mean val-256 metrics of ``decoder`` (winding accuracy, PSNR, PU21-PSNR, SSIM, MS-SSIM)
    and the median decode time in ms, over the 24 frames of ``encoding`` (or the first
    ``frames``)."""
    scores: dict[str, list[float]] = {key: [] for key in REPORTED}
    times_ms = []
    for frame in val256_frames(encoding, read_noise)[:frames]:
        result = decoder.decode(frame.codes, frame.params)
        metrics = evaluate(result.irradiance, frame.x, result.winding, frame.winding, flip=False)
        for key in REPORTED:
            scores[key].append(metrics[key])
        times_ms.append(result.timings_ns["total"] / 1e6)
    summary = {key: round(float(np.mean(values)), 4) for key, values in scores.items()}
    return {**summary, "ms_per_frame": round(float(np.median(times_ms)), 2)}
