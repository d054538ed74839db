"""models/training/validate.py: the val-256 figures of a model card (``mcam train measure``)
and of ``bench.losses``."""

from __future__ import annotations

import json
from typing import Any

import numpy as np
from numpy.typing import NDArray

from models.decoders.base import DecodeResult
from models.decoders.classical import ItohDecoder
from models.formation import SensorParams
from models.metrics import PSNR_CAP
from models.scenes import val256_frames
from models.training.validate import val256_metrics


class Oracle(ItohDecoder):
    """Decodes the first val-256 mantissa frame to its true W and x, exactly."""

    def decode(self, codes: NDArray[Any], params: SensorParams) -> DecodeResult:
        truth = val256_frames("mantissa")[0]
        return DecodeResult(truth.winding, truth.x, {"total": 10**6})


class SessionOnFirstCall(ItohDecoder):
    """itoh whose first decode reports 1000 s (a session made on the first call) and every
    later one 1 ms."""

    def __init__(self) -> None:
        self.calls = 0

    def decode(self, codes: NDArray[Any], params: SensorParams) -> DecodeResult:
        result = super().decode(codes, params)
        self.calls += 1
        result.timings_ns["total"] = 10**12 if self.calls == 1 else 10**6
        return result


def test_an_exact_frame_counts_at_the_cap_not_infinity() -> None:
    """An exact frame's PSNR is infinite: the mean was inf, which a card's JSON cannot hold."""
    figures = val256_metrics(Oracle(), "mantissa", frames=1)
    assert figures["psnr"] == PSNR_CAP and figures["pu21_psnr"] == PSNR_CAP
    assert figures["winding_accuracy"] == 1.0
    json.dumps(figures, allow_nan=False)


def test_the_first_call_is_not_timed() -> None:
    """With one frame (bench.losses --frames 1) ms_per_frame was the session's creation."""
    decoder = SessionOnFirstCall()
    figures = val256_metrics(decoder, "mantissa", frames=1)
    assert figures["ms_per_frame"] == 1.0 and decoder.calls == 2
    assert np.isfinite(figures["psnr"])
