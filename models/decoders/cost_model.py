"""What each quality of ``auto`` will cost on a frame, measured on this machine.

The latency budget (:mod:`models.decoders.budget`) predicts, for each quality of
``auto``, the winding-prediction time of a frame (:func:`predicted_ms`) from its scene
analysis:

- the network's calls (:meth:`AdaptiveDecoder.network_calls`: the whole frame, or
  one window per group of hard tiles), each split into the runs the decoder makes
  (:meth:`Decoder.run_pixels`), at a fixed cost per run plus a cost per pixel;
- when the quality refines, each box it refines
  (:func:`models.decoders.guided_puma.refinement_boxes` of the network's pixels; the
  whole frame when the network decided all of it) at the cost per pixel of a frame of
  the box's size class; at ``fast``, the small-region check's cost per pixel of the
  frame instead;
- the routing's own work (tile integration, stitching, anchoring), per pixel of the
  frame.

A colour frame's join (:func:`colour_ns_per_pixel`) and its clips' fill in every channel
(:func:`shared_fill_ns_per_pixel`; 5 ms a 256 x 256 frame, uncharged until session 44)
are charged per pixel of the frame.
The inversion from W to irradiance is not part of it. Costs are measured once per
process on this machine, by timing each stage on a seeded synthetic 256 x 256 frame
exposed like val-256 (and its top-left quarter, for the fixed cost of a run), so
predictions follow the hardware and the thread settings; the refinement is also timed
on a 512 x 512 frame, used for boxes larger than 256 x 256 (its cost per pixel changes
with the size). Pass-through and exact integration tiles cost nothing beyond the
routing's own work. A process measures these costs on its first budgeted frame of
each encoding and size class (:func:`calibrate`; seconds, reported apart).

Measured (2026-11-26, AMD EPYC, 2 cores; predicted / measured ms of each quality
after the analysis, frame by frame): the cost per pixel of the network and of a
whole-frame refinement, as before, predicted ``fast`` at 0.44-0.87, ``balanced`` at
0.65-2.38 (mostly-dark frames 2.4: it charged the whole frame's refinement) and
``best`` at 1.2-1.6; the model above (bench.tradeoff, 03:42 UTC, geometric means per
frame set) ``fast`` at 0.94-1.02, ``balanced`` at 1.01-1.48 and ``best`` at 1.05-1.47
(a converged refinement's cost varies by frame; sparse frames' boxes refine faster
per pixel than the calibration frame's). bench.tradeoff reports these ratios.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from functools import cache

import numpy as np
from numpy.typing import NDArray

from models.decoders.adaptive import AdaptiveDecoder
from models.decoders.adaptive_policy import QUALITIES
from models.decoders.colour import harmonise
from models.decoders.guided_puma import refinement_boxes
from models.decoders.registry import get_decoder
from models.decoders.saturation import fill_shared
from models.formation import SensorParams, dequantize
from models.scene_analysis import FrameAnalysis, analyse
from models.scenes import synthetic_val256_frame
from models.timing import fastest_ns

#: The classical option: tried when no quality of ``auto`` is predicted to fit.
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
#: Timed runs per calibration (after a warm-up); the least time is kept: the cost
#: without interference. A calibration that caught other load would make an option
#: look too dear to be chosen, and an option never chosen never corrects its factor
#: (:class:`models.decoders.budget.SpeedFactors`), while one predicted too cheap runs
#: and learns its cost.
CALIBRATION_RUNS = 5


@cache
def calibration_frame(
    encoding: str, size: int = CALIBRATION_SIZE
) -> tuple[NDArray[np.float64], SensorParams]:
    """Stored values ``m`` (wrap units) of a seeded synthetic ``size`` x ``size`` scene
    exposed as val-256 is, and its sensor parameters."""
    frame = synthetic_val256_frame(encoding, size, CALIBRATION_SEED)
    return dequantize(frame.codes, frame.params.bits), frame.params


@dataclass(frozen=True)
class CallCost:
    """A decoder's measured time for one call: ``call_ns`` fixed, plus ``pixel_ns`` per
    pixel of its input."""

    call_ns: float
    pixel_ns: float

    def ns(self, pixels: int) -> float:
        """Predicted time (ns) of one call on ``pixels`` pixels."""
        return self.call_ns + self.pixel_ns * pixels


@cache
def call_cost(name: str, encoding: str) -> CallCost:
    """Decoder ``name``'s :class:`CallCost` predicting W, fitted through its least times
    (:data:`CALIBRATION_RUNS`) on the calibration frame of ``encoding`` and on that
    frame's top-left quarter (a network call has a fixed cost, padding and session
    overhead, that a cost per pixel alone charges small windows too little); measured
    once."""
    decoder = get_decoder(name)
    m, params = calibration_frame(encoding)
    quarter = m[: m.shape[0] // 2, : m.shape[1] // 2]
    whole_ns, quarter_ns = (
        fastest_ns(lambda frame=frame: decoder.predict_winding(frame, params), CALIBRATION_RUNS)
        for frame in (m, quarter)
    )
    pixel_ns = max(whole_ns - quarter_ns, 0.0) / (m.size - quarter.size)
    return CallCost(max(quarter_ns - pixel_ns * quarter.size, 0.0), pixel_ns)


@cache
def check_ns_per_pixel(quality: str, encoding: str) -> float:
    """Time per pixel (ns) of ``auto-<quality>``'s small-region check
    (:meth:`AdaptiveDecoder.check_small_regions`, an itoh decode and a region vote) on
    the calibration frame; 0 when the quality does not check. Measured once."""
    m, params = calibration_frame(encoding)
    decoder = adaptive(quality)
    if not decoder.checks_small_regions(params):
        return 0.0
    guide, _ = decoder.unrefined_winding(m, params, analyse(m, params, decoder.tile))
    return fastest_ns(lambda: decoder.check_small_regions(m, guide, params), CALIBRATION_RUNS) / (
        m.size
    )


@cache
def refinement_ns_per_pixel(quality: str, encoding: str, size: int) -> float:
    """Time per refined pixel (ns: per pixel of the boxes it refines, see
    :func:`refined_shapes`) of ``auto-<quality>``'s refinement (0 when it has none) on
    the ``size``-px calibration frame, from the W and the doubtful pixels that
    ``auto-<quality>`` hands it there; measured once: the least of
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

    pixels = sum(h * w for h, w in refined_shapes(doubtful, m.shape))
    if size == CALIBRATION_SIZE:
        return fastest_ns(refine, CALIBRATION_RUNS) / pixels
    start = time.perf_counter_ns()
    refine()
    return (time.perf_counter_ns() - start) / pixels


def refined_shapes(
    doubtful: NDArray[np.bool_] | None, shape: tuple[int, int]
) -> list[tuple[int, int]]:
    """The shapes of what a refinement handed these doubtful pixels works on: the whole
    frame when None, else each box around them (:func:`refinement_boxes`)."""
    if doubtful is None:
        return [shape]
    boxes = refinement_boxes(doubtful)
    return [(rows.stop - rows.start, cols.stop - cols.start) for rows, cols in boxes]


def refinement_ns(quality: str, encoding: str, shapes: list[tuple[int, int]]) -> float:
    """Predicted time (ns) of ``auto-<quality>``'s refinement of boxes of these shapes,
    each at the cost per pixel of its own size class (:func:`refinement_size`): a box
    of a large frame costs per pixel what a frame of its size does."""
    return sum(
        h * w * refinement_ns_per_pixel(quality, encoding, refinement_size((h, w)))
        for h, w in shapes
    )


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


@cache
def overhead_ns_per_pixel(quality: str, encoding: str) -> float:
    """The routing's own time per pixel (ns, at least 0: tile integration, stitching,
    anchoring): ``auto-<quality>``'s W before refinement on the calibration frame (whose
    hard tiles take two network windows) less its predicted network calls; measured
    once. (Taken as the whole decode less every predicted stage it measured 20-130
    ns/px from run to run: the difference of two times ten times larger.)"""
    m, params = calibration_frame(encoding)
    decoder = adaptive(quality)
    analysis = analyse(m, params, decoder.tile)
    unrefined = fastest_ns(
        lambda: decoder.unrefined_winding(m, params, analysis), CALIBRATION_RUNS
    )
    return max(unrefined - network_ns(quality, analysis, m.shape, params), 0.0) / m.size


def network_ns(
    quality: str, analysis: FrameAnalysis, shape: tuple[int, int], params: SensorParams
) -> float:
    """Predicted time (ns) of ``auto-<quality>``'s network calls on a frame
    (:meth:`AdaptiveDecoder.network_calls`, each split into the decoder's runs)."""
    decoder = adaptive(quality)
    hard = decoder.hard_tile_decoder(params)
    cost = call_cost(hard.name, params.encoding)
    calls = decoder.network_calls(analysis, shape)
    return sum(cost.ns(pixels) for call in calls for pixels in hard.run_pixels(call, params))


def predicted_ms(
    quality: str, analysis: FrameAnalysis, shape: tuple[int, int], params: SensorParams
) -> float:
    """Predicted W time (ms, without the analysis) of ``auto-<quality>`` on this frame:
    its stages (:func:`stage_ns`) and the rest, per pixel (:func:`overhead_ns_per_pixel`).
    A frame without residues has no costly stage, only the rest (integration,
    anchoring): predicted as the rest alone (0 ms when its cost per pixel calibrates to
    0), its measured time had taught the budget's speed factors that every quality runs
    slow."""
    overhead_ns = shape[0] * shape[1] * overhead_ns_per_pixel(quality, params.encoding)
    if analysis.frame.difficulty in ("none", "smooth"):
        return overhead_ns / 1e6
    return (stage_ns(quality, analysis, shape, params) + overhead_ns) / 1e6


def stage_ns(
    quality: str, analysis: FrameAnalysis, shape: tuple[int, int], params: SensorParams
) -> float:
    """Predicted time (ns) of ``auto-<quality>``'s costly stages on a frame with residues:
    its network calls (:meth:`AdaptiveDecoder.network_calls`), then its refinement of
    the boxes around the network's pixels, or its small-region check of the frame."""
    decoder = adaptive(quality)
    total_ns = network_ns(quality, analysis, shape, params)
    frame_pixels = shape[0] * shape[1]
    if decoder.refiner(params) is not None:
        shapes = refined_shapes(decoder.doubtful_pixels(analysis, shape), shape)
        total_ns += refinement_ns(quality, params.encoding, shapes)
    else:
        total_ns += frame_pixels * check_ns_per_pixel(quality, params.encoding)
    return total_ns


@cache
def colour_calibration(
    encoding: str,
) -> tuple[NDArray[np.float64], NDArray[np.int64], SensorParams]:
    """The colour calibration frame (the calibration scene tinted,
    :func:`models.scenes.synthetic_val256_frame`): its channels' ``m`` (wraps, H x W x C),
    the W ``auto-balanced`` gives each channel alone, and its parameters."""
    frame = synthetic_val256_frame(encoding, CALIBRATION_SIZE, CALIBRATION_SEED, colour=True)
    planes = dequantize(frame.codes, frame.params.bits)
    channels_alone = AdaptiveDecoder("balanced", joint_colour=False)
    return planes, channels_alone.explain_planes(planes, frame.params)[0], frame.params


@cache
def colour_ns_per_pixel(encoding: str) -> float:
    """Time per pixel (ns) of making a colour frame's channels consistent
    (:func:`models.decoders.colour.harmonise`) on the colour calibration frame
    (:func:`colour_calibration`); the least of :data:`CALIBRATION_RUNS`, measured once."""
    planes, winding, params = colour_calibration(encoding)
    runs = fastest_ns(lambda: harmonise(planes, winding, params), CALIBRATION_RUNS)
    return runs / (planes.shape[0] * planes.shape[1])


@cache
def shared_fill_ns_per_pixel(encoding: str) -> float:
    """Time per pixel (ns) of filling a colour frame's clips in every channel that holds
    them (:func:`models.decoders.saturation.fill_shared`, which every colour frame of
    ``auto`` gets, joined or not) on the colour calibration frame; the least of
    :data:`CALIBRATION_RUNS`, measured once."""
    planes, winding, params = colour_calibration(encoding)
    runs = fastest_ns(lambda: fill_shared(winding, planes, params), CALIBRATION_RUNS)
    return runs / (planes.shape[0] * planes.shape[1])


#: One calibration at a time: two threads' first frames timed each other's calibrations
#: under their load (costs up to 1.9x, so a quality predicted too dear never ran again).
_CALIBRATING = threading.Lock()


def calibrate(params: SensorParams, shape: tuple[int, int], colour: bool = False) -> None:
    """Measure (once; cached) every cost :func:`unscaled_options` needs for frames of
    ``params.encoding`` and of ``shape``'s size class (and, with ``colour``, the cost of
    making channels consistent), one thread at a time."""
    sizes = [size for size in REFINEMENT_CALIBRATION_SIZES if size <= refinement_size(shape)]
    with _CALIBRATING:
        call_cost(CLASSICAL, params.encoding)
        for quality in QUALITIES:
            call_cost(adaptive(quality).hard_tile_decoder(params).name, params.encoding)
            check_ns_per_pixel(quality, params.encoding)
            overhead_ns_per_pixel(quality, params.encoding)
            for size in sizes:
                refinement_ns_per_pixel(quality, params.encoding, size)
        if colour:
            colour_ns_per_pixel(params.encoding)
            shared_fill_ns_per_pixel(params.encoding)


def unscaled_options(
    analysis: FrameAnalysis, analysis_ms: float, shape: tuple[int, int], params: SensorParams
) -> dict[str, float]:
    """Each option's predicted ms for a frame, before :data:`SPEED`: the qualities of
    ``auto``, most accurate first, then :data:`CLASSICAL`; each includes the analysis
    time already spent."""
    options = {
        quality: analysis_ms + predicted_ms(quality, analysis, shape, params)
        for quality in reversed(QUALITIES)
    }
    pixels = shape[0] * shape[1]
    options[CLASSICAL] = analysis_ms + call_cost(CLASSICAL, params.encoding).ns(pixels) / 1e6
    return options
