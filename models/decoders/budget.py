"""``auto-<N>ms``: the most accurate routing predicted to decode a frame within N ms.

The scene analysis runs once per frame. For each quality of ``auto``, ``best``
first, the winding-prediction time is predicted as the analysis time plus the
pixels its network would see (:meth:`AdaptiveDecoder.network_pixels`) times that
network's cost per pixel, plus, when the quality refines a frame with residues,
the frame's pixels times the refinement's cost per pixel (at ``fast``, the cost per
pixel of the small-region check's ``itoh`` decode instead). The first quality
predicted within the budget decodes the frame. When none fits, ``itoh`` (one DCT
solve per frame) decodes it if that is predicted to fit, else the quickest option
runs and the report says the budget was not met. The inversion from W to
irradiance is not part of the budget.

Costs per pixel (ns) are measured once per process on this machine, by timing
each candidate on a seeded synthetic 256 x 256 frame exposed like val-256 (random
codes are the refinement's worst case, not a typical frame), so predictions follow
the hardware and the thread settings; the refinement is also timed on a 512 x 512
frame, used for frames larger than 256 x 256 (its cost per pixel grows with the
frame). Pass-through and exact integration are treated as free (about a
millisecond per 256 x 256 frame, inside the analysis time's order). The choice,
every option's predicted ms and whether the budget was met are reported with the
routes (``GET /v1/jobs/{id}``, the EXR header).
"""

from __future__ import annotations

import re
import time
from functools import cache
from typing import Any

import numpy as np
from numpy.typing import NDArray

from models.decoders.adaptive import (
    DEFAULT_TILE,
    QUALITIES,
    SMALL_REGION_CHECK,
    AdaptiveDecoder,
)
from models.decoders.base import Decoder
from models.decoders.registry import DecoderSpec, get_decoder
from models.errors import InvalidInputError
from models.formation import SensorParams, dequantize, simulate
from models.scene_analysis import FrameAnalysis, analyse
from models.scenes import VAL256_BITS, VAL256_MAX_WRAPS, VAL256_OVEREXPOSED, synthetic_scene
from models.timing import median_ns

NAME = re.compile(r"auto-(\d+(?:\.\d+)?)ms")
NAME_PATTERNS = ("auto-<N>ms (the most accurate quality predicted to decode within N ms)",)
#: Budgets outside this range (ms) are refused.
BUDGET_RANGE_MS = (0.1, 600_000.0)
#: Tried when no quality of ``auto`` is predicted to fit.
CLASSICAL = "itoh"
CALIBRATION_SIZE = 256
#: The refinement's cost per pixel grows with the frame (longer borders, more flow per
#: min-cut): it is calibrated at each of these sides (px), and a frame uses the smallest
#: at least as large as itself, else the largest. Measured on the synthetic 512 and 1024
#: px frames of bench.tradeoff, predicted (actual): best 4.5 s (3.6 s) and 18 s (13 s),
#: balanced 0.70 s (0.59 s) and 2.2 s (0.82 s: frames over 512 px are refined in windows,
#: and only where the network decided, which a whole 512-px frame does not show).
#: Calibrated at 256 px only, best was predicted at about 2.5 s for the 13 s.
REFINEMENT_CALIBRATION_SIZES = (256, 512)
CALIBRATION_SEED = 0
CALIBRATION_RUNS = 3


@cache
def calibration_frame(
    encoding: str, size: int = CALIBRATION_SIZE
) -> tuple[NDArray[np.float64], SensorParams]:
    """Stored values ``m`` (wrap units) of a seeded synthetic ``size`` x ``size`` scene
    exposed as val-256 is, and its sensor parameters."""
    params = SensorParams(
        encoding=encoding,  # type: ignore[arg-type]
        bits=VAL256_BITS,
        max_wraps=VAL256_MAX_WRAPS,
    )
    scene = synthetic_scene(CALIBRATION_SEED, size)
    frame = simulate(scene, params, overexposed=VAL256_OVEREXPOSED)
    return dequantize(frame.codes, params.bits), frame.params


@cache
def ns_per_pixel(name: str, encoding: str) -> float:
    """Median time per pixel (ns) of decoder ``name`` predicting W on the calibration
    frame of ``encoding``, after one warm-up run; measured once."""
    decoder = get_decoder(name)
    m, params = calibration_frame(encoding)
    return median_ns(lambda: decoder.predict_winding(m, params), CALIBRATION_RUNS) / m.size


@cache
def refinement_ns_per_pixel(quality: str, encoding: str, size: int = CALIBRATION_SIZE) -> float:
    """Time per pixel (ns) of ``auto-<quality>``'s refinement (0 when it has none) on
    the ``size``-px calibration frame, from the W and the doubtful pixels that
    ``auto-<quality>`` hands it there; measured once: the median of
    :data:`CALIBRATION_RUNS` at 256 px, one run at larger sizes (a converged
    refinement of a 512x512 frame takes seconds)."""
    m, params = calibration_frame(encoding, size)
    decoder = adaptive(quality)
    refiner = decoder.refiner(params)
    if refiner is None:
        return 0.0
    guide, doubtful = decoder.unrefined_winding(m, params, analyse(m, params, decoder.tile))

    def refine() -> None:
        refiner.refine(m, guide, params, doubtful)

    if size == CALIBRATION_SIZE:
        return median_ns(refine, CALIBRATION_RUNS) / m.size
    start = time.perf_counter_ns()
    refine()
    return (time.perf_counter_ns() - start) / m.size


def refinement_size(shape: tuple[int, int]) -> int:
    """The refinement calibration side (px) for a frame of ``shape``."""
    pixels = shape[0] * shape[1]
    fitting = [size for size in REFINEMENT_CALIBRATION_SIZES if size * size >= pixels]
    return fitting[0] if fitting else REFINEMENT_CALIBRATION_SIZES[-1]


def adaptive(quality: str) -> AdaptiveDecoder:
    """The shared ``auto-<quality>`` decoder."""
    decoder = get_decoder(f"auto-{quality}")
    assert isinstance(decoder, AdaptiveDecoder)
    return decoder


def check_budget(budget_ms: float) -> None:
    """Refuse a budget outside :data:`BUDGET_RANGE_MS` with a clear error."""
    low, high = BUDGET_RANGE_MS
    if not low <= budget_ms <= high:
        raise InvalidInputError(
            f"a latency budget must be {low:g} to {high:g} ms, got {budget_ms:g}"
        )


def predicted_ms(
    quality: str, analysis: FrameAnalysis, shape: tuple[int, int], params: SensorParams
) -> float:
    """Predicted W time (ms, without the analysis) of ``auto-<quality>`` on this frame."""
    decoder = adaptive(quality)
    pixels = decoder.network_pixels(analysis, shape)
    if pixels == 0:
        return 0.0
    hard = decoder.hard_tile_decoder(params)
    network_ns = pixels * ns_per_pixel(hard.name, params.encoding)
    per_pixel = refinement_ns_per_pixel(quality, params.encoding, refinement_size(shape))
    if decoder.checks_small_regions(params):
        per_pixel += ns_per_pixel(SMALL_REGION_CHECK, params.encoding)
    refinement_ns = shape[0] * shape[1] * per_pixel
    return (network_ns + refinement_ns) / 1e6


class BudgetDecoder(Decoder):
    """``auto`` at the most accurate quality predicted to fit ``budget_ms``."""

    def __init__(self, budget_ms: float) -> None:
        check_budget(budget_ms)
        self.budget_ms = budget_ms
        self.name = f"auto-{budget_ms:g}ms"  # type: ignore[misc]

    def predict_winding(self, m: NDArray[np.float64], params: SensorParams) -> NDArray[np.int64]:
        return self.explain_winding(m, params)[0]

    def explain_winding(
        self, m: NDArray[np.float64], params: SensorParams
    ) -> tuple[NDArray[np.int64], dict[str, Any]]:
        start = time.perf_counter_ns()
        analysis = analyse(m, params, DEFAULT_TILE)
        analysis_ms = (time.perf_counter_ns() - start) / 1e6
        options = {
            quality: analysis_ms + predicted_ms(quality, analysis, m.shape, params)
            for quality in reversed(QUALITIES)
        }
        options[CLASSICAL] = ns_per_pixel(CLASSICAL, params.encoding) * m.size / 1e6
        fitting = [name for name, ms in options.items() if ms <= self.budget_ms]
        chosen = fitting[0] if fitting else min(options, key=options.__getitem__)
        if chosen == CLASSICAL:
            winding = get_decoder(CLASSICAL).predict_winding(m, params)
            reason = f"no quality of auto is predicted within {self.budget_ms:g} ms"
            info: dict[str, Any] = {"routes": {CLASSICAL: 1.0}, "reason": reason}
        else:
            winding, info = adaptive(chosen).explain_analysed(m, params, analysis)
        info["budget"] = {
            "budget_ms": self.budget_ms,
            "chosen": chosen,
            "met": bool(fitting),
            "predicted_ms": {name: round(ms, 2) for name, ms in options.items()},
        }
        return winding, info


def resolve(name: str) -> DecoderSpec | None:
    """The spec of ``auto-<N>ms``, or None for any other name."""
    match = NAME.fullmatch(name)
    if match is None:
        return None
    budget_ms = float(match.group(1))
    check_budget(budget_ms)
    return DecoderSpec(
        name=name,
        kind="adaptive",
        description=f"auto at the most accurate quality predicted to decode in {budget_ms:g} ms",
        factory=lambda: BudgetDecoder(budget_ms),
    )


def specs() -> list[DecoderSpec]:
    """No fixed names: budgets are resolved from the name (:func:`resolve`)."""
    return []
