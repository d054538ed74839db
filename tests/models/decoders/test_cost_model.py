"""Tests of models/decoders/cost_model.py: what each quality of ``auto`` is predicted
to cost on a frame, from costs measured once on this machine (no timings asserted)."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from models.decoders import get_decoder
from models.decoders.cost_model import (
    calibrate,
    call_cost,
    check_ns_per_pixel,
    colour_ns_per_pixel,
    overhead_ns_per_pixel,
    predicted_ms,
    refined_shapes,
    refinement_ns,
    refinement_ns_per_pixel,
    refinement_size,
    stage_ns,
)
from models.formation import SensorParams, encode
from models.scene_analysis import analyse

MODULO = SensorParams(encoding="modulo", bits=8)


def test_a_frame_without_wraps_costs_no_network_time_only_the_rest() -> None:
    x = np.full((64, 64), 0.3)
    frame = encode(x, MODULO)
    analysis = analyse(frame.codes / 256.0, MODULO, 64)
    for quality in ("fast", "balanced", "best"):
        rest = x.size * overhead_ns_per_pixel(quality, "modulo") / 1e6
        assert predicted_ms(quality, analysis, x.shape, MODULO) == pytest.approx(rest)
    result = get_decoder("auto-600000ms").decode(frame.codes, MODULO)
    assert result.info["details"]["budget"]["chosen"] == "best"
    assert result.info["details"]["routes"] == {"pass-through": 1.0}
    np.testing.assert_array_equal(result.winding, frame.winding)


def test_call_costs_are_measured_and_grow_with_the_pixels() -> None:
    for name in ("itoh", "mantissanet-small-s2d"):
        cost = call_cost(name, "modulo")
        assert cost.call_ns >= 0.0 and cost.pixel_ns > 0.0
        assert cost.ns(256 * 256) > cost.ns(64 * 64)


def test_a_routed_frame_is_charged_the_refinement_of_its_boxes_only() -> None:
    """Two rough corners of a dark frame: balanced refines two boxes round them, and the
    prediction charges those, not the whole frame."""
    x = np.full((256, 256), 0.2)
    rng = np.random.default_rng(0)
    for row, col in ((20, 20), (200, 200)):
        x[row : row + 20, col : col + 20] += rng.uniform(0, 3, (20, 20))
    codes = encode(x, MODULO).codes
    m = codes / 256.0
    analysis = analyse(m, MODULO, 64)
    decoder = get_decoder("auto-balanced")
    doubtful = decoder.doubtful_pixels(analysis, m.shape)
    assert doubtful is not None
    shapes = refined_shapes(doubtful, m.shape)
    assert len(shapes) == 2 and sum(h * w for h, w in shapes) < m.size
    assert refined_shapes(None, m.shape) == [m.shape]
    boxes_ns = refinement_ns("balanced", "modulo", shapes)
    per_pixel = refinement_ns_per_pixel("balanced", "modulo", 256)
    assert boxes_ns == pytest.approx(sum(h * w for h, w in shapes) * per_pixel)
    assert stage_ns("balanced", analysis, m.shape, MODULO) >= boxes_ns
    assert stage_ns("balanced", analysis, m.shape, MODULO) < stage_ns(
        "best", analysis, m.shape, MODULO
    )


def test_each_box_is_charged_at_its_own_size_class() -> None:
    """A box of a large frame costs per pixel what a frame of its size does."""
    small, large = (200, 200), (400, 400)
    assert refinement_ns("balanced", "modulo", [small]) == pytest.approx(
        200 * 200 * refinement_ns_per_pixel("balanced", "modulo", 256)
    )
    assert refinement_ns("balanced", "modulo", [large]) == pytest.approx(
        400 * 400 * refinement_ns_per_pixel("balanced", "modulo", 512)
    )


def test_refinement_costs_are_calibrated_by_frame_size() -> None:
    assert refinement_ns_per_pixel("fast", "modulo", 256) == 0.0
    assert refinement_ns_per_pixel("balanced", "modulo", 256) > 0.0
    assert [refinement_size(s) for s in ((64, 64), (256, 256), (300, 300), (2048, 2048))] == [
        256,
        256,
        512,
        512,
    ]


def test_the_colour_join_is_timed_once_per_encoding() -> None:
    colour_ns_per_pixel.cache_clear()
    cost = colour_ns_per_pixel("modulo")
    assert cost > 0.0
    assert colour_ns_per_pixel("modulo") == cost
    assert colour_ns_per_pixel.cache_info().hits == 1


def test_two_threads_first_frames_calibrate_once() -> None:
    """Unlocked, both threads calibrated, each timed under the other's load (best's
    prediction 150-178 ms against 120-125 alone)."""
    cached = (call_cost, check_ns_per_pixel, overhead_ns_per_pixel, refinement_ns_per_pixel)
    for function in cached:
        function.cache_clear()
    threads = [threading.Thread(target=calibrate, args=(MODULO, (64, 64))) for _ in range(2)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    for function in cached:
        info = function.cache_info()
        assert info.misses == info.currsize, function.__name__
