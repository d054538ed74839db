"""``auto-<N>ms``: the most accurate routing predicted to decode a frame within N ms.

The scene analysis runs once per frame. For each quality of ``auto``, ``best``
first, the winding-prediction time is predicted as the analysis time plus the
quality's cost on this frame (:mod:`models.decoders.cost_model`, measured once per
process on this machine). The first quality predicted within the budget decodes the
frame. When none fits, ``itoh`` (one DCT solve per frame) decodes it if that is
predicted to fit, else the quickest option runs. The inversion from W to irradiance
is not part of the budget. A colour frame is decoded within the budget as a whole
(:meth:`BudgetDecoder.explain_planes`).

The predictions are scaled by the process's running measured / predicted ratio of
each option (:class:`SpeedFactors`), which follows load on the cores and each
option's own bias. The choice, every option's predicted ms, the measured ms and
whether the budget was met are reported with the routes (``GET /v1/jobs/{id}``, the
EXR header); bench.tradeoff reports the share of frames each budget met.
"""

from __future__ import annotations

import re
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from models.decoders.adaptive_policy import DEFAULT_TILE
from models.decoders.base import Decoder, refuse_empty
from models.decoders.colour import harmonise
from models.decoders.cost_model import (
    CLASSICAL,
    adaptive,
    calibrate,
    colour_ns_per_pixel,
    shared_fill_ns_per_pixel,
    unscaled_options,
)
from models.decoders.filling import filled_then_joined
from models.decoders.registry import DecoderSpec, get_decoder
from models.decoders.saturation import fill_saturated
from models.errors import InvalidInputError, echo
from models.formation import SensorParams
from models.scene_analysis import FrameAnalysis, analyse

NAME = re.compile(r"auto-([0-9]+(?:\.[0-9]+)?)ms")  # ASCII digits: one spelling a budget
NAME_PATTERNS = ("auto-<N>ms (the most accurate quality predicted to decode within N ms)",)
#: A name meant as a budget that :data:`NAME` does not take (``auto-nanms``,
#: ``auto-1e3ms``, ``auto--5ms``, ``auto-.5ms``, ``auto-40`` without its unit): refused
#: saying how to write N (:func:`check_budget_name`).
MISSPELT_NAME = re.compile(r"auto-(?:[^+]+ms|[-+.0-9eE]+)")
#: Budgets outside this range (ms) are refused.
BUDGET_RANGE_MS = (0.1, 600_000.0)
#: Weight of the latest decode in the running measured / predicted factors
#: (:class:`SpeedFactors`), their bounds, and the shortest prediction (ms) they learn from.
SPEED_WEIGHT = 0.2
SPEED_RANGE = (0.25, 4.0)
SPEED_MIN_MS = 1.0
#: Spreads (standard deviations of the log ratio) added to the mean factor: about 84%
#: of frames within the predicted time if the ratio is log-normal. With the mean alone,
#: auto-20ms met its budget on 54% of the val-256 frames (bench.tradeoff, 2026-11-26
#: 02:28 UTC), choosing fast, whose 16-21 ms straddle the budget, on 22 of 24.
SPEED_SPREADS = 1.0
#: The log ratio's spread assumed when an option's first decode is folded in (about 15%).
SPEED_PRIOR_SPREAD = 0.15
#: A colour frame's channels are made consistent when that is predicted to take at most
#: this share of its budget. The join gained 1.0-4.6 dB on colour frames (bench.colour:
#: auto-balanced and auto-best, both encodings, val-256 in colour and the tuning set),
#: more than a step of quality does on grayscale val-256 (fast -> balanced 2.1 dB, balanced
#: -> best 0.3 dB), so it may take up to half the time; a rule of thumb, not a fit.
JOIN_SHARE = 0.5
#: The join's name among the speed factors (:class:`SpeedFactors`).
COLOUR = "colour"


def check_budget(budget_ms: float) -> None:
    """Refuse a budget outside :data:`BUDGET_RANGE_MS` with a clear error."""
    low, high = BUDGET_RANGE_MS
    if not low <= budget_ms <= high:
        raise InvalidInputError(
            f"a latency budget must be {low:g} to {high:g} ms, got {budget_ms:g}"
        )


class SpeedFactors:
    """This process's measured / predicted time of each option (a quality of ``auto``,
    or ``itoh``): the running mean and spread of its logarithm over the frames a
    latency budget decoded with that option. The costs are measured once, but other
    load on the cores comes and goes, one noisy calibration run would otherwise skew
    the predictions for the life of the process, and each option's cost model errs its
    own way (itoh's DCT grows faster than its pixels). A prediction is scaled by its
    option's :meth:`value`: the mean ratio times :data:`SPEED_SPREADS` spreads, so that
    a budget is met on most frames rather than on half of them when an option's time
    sits at the budget."""

    def __init__(self) -> None:
        #: Per option: (mean, variance) of log(measured / predicted).
        self.moments: dict[str, tuple[float, float]] = {}

    def value(self, option: str) -> float:
        """The factor of ``option``: ``exp(mean + SPEED_SPREADS * spread)`` of its log
        ratio; 1 until it has run (an option predicted too dear would otherwise never
        run and never learn its cost: the latency budget tries it once at face value)."""
        if option not in self.moments:
            return 1.0
        mean, variance = self.moments[option]
        return float(np.clip(np.exp(mean + SPEED_SPREADS * np.sqrt(variance)), *SPEED_RANGE))

    def update(self, option: str, predicted_ms: float, measured_ms: float) -> None:
        """Fold in one decode by ``option``: ``predicted_ms`` (unscaled) and
        ``measured_ms``; decodes predicted under :data:`SPEED_MIN_MS` are too short to
        time and are skipped."""
        if predicted_ms < SPEED_MIN_MS or measured_ms <= 0.0:
            return
        ratio = min(max(measured_ms / predicted_ms, SPEED_RANGE[0]), SPEED_RANGE[1])
        mean, variance = self.moments.get(option, (0.0, SPEED_PRIOR_SPREAD**2))
        step = np.log(ratio) - mean
        self.moments[option] = (
            mean + SPEED_WEIGHT * step,
            (1 - SPEED_WEIGHT) * (variance + SPEED_WEIGHT * step * step),
        )


#: The running corrections shared by every ``auto-<N>ms`` decoder of this process.
SPEED = SpeedFactors()


def factor_key(analysis: FrameAnalysis) -> Callable[[str], str]:
    """The speed factor an option's prediction is scaled by on this frame: a frame
    without residues (only integration and anchoring) learns its own, since the cost
    model's per-pixel rest fits it less well (measured 1.7x its prediction at 512x512),
    and it had taught frames with residues that every quality runs slow (auto-200ms:
    balanced instead of best on 24 of 25 busy frames)."""
    smooth = analysis.frame.difficulty in ("none", "smooth")
    return lambda option: f"{option} without residues" if smooth else option


class BudgetDecoder(Decoder):
    """``auto`` at the most accurate quality predicted to fit ``budget_ms``. Like ``auto``
    it fills clipped blobs (also on the itoh fallback), which temporal decoding and
    ``+puma`` rely on (:attr:`fills_saturation`)."""

    fills_saturation = True

    def __init__(self, budget_ms: float) -> None:
        check_budget(budget_ms)
        self.budget_ms = budget_ms
        self.name = f"auto-{budget_ms:g}ms"  # type: ignore[misc]

    def predict_winding(self, m: NDArray[np.float64], params: SensorParams) -> NDArray[np.int64]:
        return self.explain_winding(m, params)[0]

    def explain_winding(
        self, m: NDArray[np.float64], params: SensorParams
    ) -> tuple[NDArray[np.int64], dict[str, Any]]:
        """:meth:`explain_within` the whole budget."""
        return self.explain_within(m, params, self.budget_ms)

    def explain_planes(
        self, planes: NDArray[np.float64], params: SensorParams
    ) -> tuple[NDArray[np.int64], dict[str, Any]]:
        """A colour frame is decoded within the budget as a whole. Its channels are made
        consistent (:func:`models.decoders.colour.harmonise`) when that is predicted to
        take at most :data:`JOIN_SHARE` of the budget; that and the predicted time of
        filling the clips in every channel that holds them (:func:`fill_model_ms`) are
        set aside, and the rest is shared among the channels: each gets the time left
        divided by the channels left, 0 once it is spent (a budget smaller than what is
        set aside, or channels before that ran over, gave later channels a negative
        budget, reported as theirs: -16.71 ms at auto-0.1ms). The frame's facts
        (``budget``: the budget, whether the channels were joined, the join's and the
        fill's predicted ms, the measured ms of it all, whether the budget was met) come
        with each channel's (``channels``) and the join's (``colour``, with the clips filled in
        every channel that holds them first, :func:`models.decoders.filling.filled_then_joined`).
        A frame without pixels is refused before anything is calibrated."""
        refuse_empty(planes)
        if planes.shape[2] == 1:
            return super().explain_planes(planes, params)
        calibration_start = time.perf_counter_ns()
        calibrate(params, planes.shape[:2], colour=True)
        start = time.perf_counter_ns()
        join_ms = join_model_ms(planes, params) * SPEED.value(COLOUR)
        joined = join_ms <= JOIN_SHARE * self.budget_ms
        fill_ms = fill_model_ms(planes, params)
        channels_ms = self.budget_ms - fill_ms - (join_ms if joined else 0.0)
        windings, channels = [], []
        for channel in range(planes.shape[2]):
            left_ms = channels_ms - (time.perf_counter_ns() - start) / 1e6
            share_ms = max(left_ms, 0.0) / (planes.shape[2] - channel)
            winding, facts = self.explain_within(planes[:, :, channel], params, share_ms)
            windings.append(winding)
            channels.append(facts)
        info: dict[str, Any] = {"channels": channels}
        join = self.timed_harmonise if joined else super().join_channels
        winding, colour = filled_then_joined(planes, np.stack(windings, axis=2), params, join)
        if colour:
            info["colour"] = colour
        measured_ms = (time.perf_counter_ns() - start) / 1e6
        info["budget"] = {
            "budget_ms": self.budget_ms,
            "joined": joined,
            "join_predicted_ms": round(join_ms, 2),
            "fill_predicted_ms": round(fill_ms, 2),
            "measured_ms": round(measured_ms, 2),
            "met": measured_ms <= self.budget_ms,
            "calibration_ms": round((start - calibration_start) / 1e6, 2),
        }
        return winding, info

    def timed_harmonise(
        self, planes: NDArray[np.float64], winding: NDArray[np.int64], params: SensorParams
    ) -> tuple[NDArray[np.int64], dict[str, Any]]:
        """:func:`models.decoders.colour.harmonise`, its measured ms folded into the join's
        speed factor (:class:`SpeedFactors`)."""
        start = time.perf_counter_ns()
        harmonised = harmonise(planes, winding, params)
        elapsed_ms = (time.perf_counter_ns() - start) / 1e6
        SPEED.update(COLOUR, join_model_ms(planes, params), elapsed_ms)
        return harmonised

    def explain_within(
        self, m: NDArray[np.float64], params: SensorParams, budget_ms: float
    ) -> tuple[NDArray[np.int64], dict[str, Any]]:
        """W of one channel from the most accurate option predicted to fit ``budget_ms``,
        and the facts: the choice, each option's predicted ms, the factor applied, the
        measured ms (from the analysis to the W) and whether ``budget_ms`` was met, and
        the ms spent calibrating the costs first (once per process, encoding and size
        class: seconds, not part of the frame's time). A channel without pixels is
        refused before anything is calibrated."""
        refuse_empty(m)
        calibration_start = time.perf_counter_ns()
        calibrate(params, m.shape)
        start = time.perf_counter_ns()
        analysis = analyse(m, params, DEFAULT_TILE)
        analysis_ms = (time.perf_counter_ns() - start) / 1e6
        model = unscaled_options(analysis, analysis_ms, m.shape, params)
        factor = factor_key(analysis)
        options = {name: ms * SPEED.value(factor(name)) for name, ms in model.items()}
        fitting = [name for name, ms in options.items() if ms <= budget_ms]
        chosen = fitting[0] if fitting else min(options, key=options.__getitem__)
        decode_start = time.perf_counter_ns()
        if chosen == CLASSICAL:
            winding = get_decoder(CLASSICAL).predict_winding(m, params)
            winding, saturation = fill_saturated(winding, m, params)
            reason = f"no quality of auto is predicted within {budget_ms:g} ms"
            info: dict[str, Any] = {"routes": {CLASSICAL: 1.0}, "reason": reason}
            if saturation:
                info["saturation"] = saturation
        else:
            winding, info = adaptive(chosen).explain_analysed(m, params, analysis)
        done = time.perf_counter_ns()
        speed = SPEED.value(factor(chosen))
        SPEED.update(factor(chosen), model[chosen], analysis_ms + (done - decode_start) / 1e6)
        measured_ms = (done - start) / 1e6
        info["budget"] = {
            "budget_ms": round(budget_ms, 2),
            "chosen": chosen,
            "predicted_to_fit": bool(fitting),
            "predicted_ms": {name: round(ms, 2) for name, ms in options.items()},
            "speed_factor": round(speed, 3),
            "measured_ms": round(measured_ms, 2),
            "met": measured_ms <= budget_ms,
            "calibration_ms": round((start - calibration_start) / 1e6, 2),
        }
        return winding, info


def fill_model_ms(planes: NDArray[np.float64], params: SensorParams) -> float:
    """The cost model's ms to fill a colour frame's clips in every channel that holds them
    (:func:`models.decoders.saturation.fill_shared`), which the channels' shares leave
    aside."""
    return planes[:, :, 0].size * shared_fill_ns_per_pixel(params.encoding) / 1e6


def join_model_ms(planes: NDArray[np.float64], params: SensorParams) -> float:
    """The cost model's ms to join the channels of a colour frame ``planes`` (H x W x C),
    before the speed factor."""
    return planes[:, :, 0].size * colour_ns_per_pixel(params.encoding) / 1e6


def resolve(name: str) -> DecoderSpec | None:
    """The spec of ``auto-<N>ms``, or None for any other name."""
    check_budget_name(name)
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
        budgeted=True,
    )


def check_budget_name(name: str) -> None:
    """Refuse a name meant as a budget that is not ``auto-<N>ms`` with N a plain
    decimal number (:data:`MISSPELT_NAME`): it was an "unknown decoder" listing every
    decoder, without a word on how to write N."""
    if NAME.fullmatch(name) or not MISSPELT_NAME.fullmatch(name):
        return
    low, high = BUDGET_RANGE_MS
    raise InvalidInputError(
        f"decoder {echo(name)}: a latency budget is auto-<N>ms, N the milliseconds as a "
        f"plain decimal number from {low:g} to {high:g} (e.g. 'auto-40ms', 'auto-0.5ms')"
    )


def specs() -> list[DecoderSpec]:
    """No fixed names: budgets are resolved from the name (:func:`resolve`)."""
    return []
