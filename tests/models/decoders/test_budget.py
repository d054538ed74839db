"""Tests of models/decoders/budget.py: ``auto-<N>ms`` picks the most accurate routing
predicted to fit the budget, and says what it chose and why (no timings asserted)."""

from __future__ import annotations

import numpy as np
import pytest

from models.decoders import get_decoder
from models.decoders.budget import (
    BudgetDecoder,
    ns_per_pixel,
    predicted_ms,
    refinement_ns_per_pixel,
    refinement_size,
    resolve,
)
from models.decoders.registry import name_patterns
from models.errors import InvalidInputError
from models.formation import SensorParams, encode, quantize
from models.scene_analysis import analyse

MODULO = SensorParams(encoding="modulo", bits=8)


def hard_frame(size: int = 64) -> np.ndarray:
    """Codes whose wrapped differences leave residues everywhere (random m)."""
    return quantize(np.random.default_rng(4).random((size, size)), 8)


def test_budget_names_resolve_and_others_do_not() -> None:
    spec = resolve("auto-40ms")
    assert spec is not None and spec.name == "auto-40ms" and spec.kind == "adaptive"
    assert resolve("auto-12.5ms") is not None
    assert resolve("auto-40") is None and resolve("itoh") is None
    assert get_decoder("auto-40ms").name == "auto-40ms"


def test_an_unknown_name_lists_the_budget_pattern() -> None:
    with pytest.raises(InvalidInputError, match="auto-<N>ms"):
        get_decoder("auto-soon")
    assert any("auto-<N>ms" in text for text in name_patterns())


@pytest.mark.parametrize("budget", [0.0, 0.05, 1e9])
def test_budgets_out_of_range_are_refused(budget: float) -> None:
    with pytest.raises(InvalidInputError, match="latency budget"):
        BudgetDecoder(budget)


def test_a_generous_budget_decodes_like_auto_best() -> None:
    codes = hard_frame()
    result = get_decoder("auto-600000ms").decode(codes, MODULO)
    budget = result.info["details"]["budget"]
    assert budget["chosen"] == "best" and budget["met"] is True
    assert set(budget["predicted_ms"]) == {"best", "balanced", "fast", "itoh"}
    best = get_decoder("auto-best").decode(codes, MODULO)
    np.testing.assert_array_equal(result.winding, best.winding)


def test_an_impossible_budget_runs_the_quickest_option_and_says_so() -> None:
    """0.1 ms is below even itoh's time for a 256x256 frame (about 2 ms)."""
    result = get_decoder("auto-0.1ms").decode(hard_frame(256), MODULO)
    budget = result.info["details"]["budget"]
    assert budget["met"] is False
    predicted = budget["predicted_ms"]
    assert predicted[budget["chosen"]] == min(predicted.values())
    assert np.isfinite(result.irradiance).all()


def test_a_frame_without_wraps_costs_no_network_time() -> None:
    x = np.full((64, 64), 0.3)
    frame = encode(x, MODULO)
    analysis = analyse(frame.codes / 256.0, MODULO, 64)
    for quality in ("fast", "balanced", "best"):
        assert predicted_ms(quality, analysis, x.shape, MODULO) == 0.0
    result = get_decoder("auto-600000ms").decode(frame.codes, MODULO)
    assert result.info["details"]["budget"]["chosen"] == "best"
    assert result.info["details"]["routes"] == {"pass-through": 1.0}
    np.testing.assert_array_equal(result.winding, frame.winding)


def test_costs_per_pixel_are_measured_and_positive() -> None:
    assert ns_per_pixel("itoh", "modulo") > 0.0


def test_refinement_costs_are_calibrated_by_frame_size() -> None:
    assert refinement_ns_per_pixel("fast", "modulo") == 0.0
    assert refinement_ns_per_pixel("balanced", "modulo") > 0.0
    assert [refinement_size(s) for s in ((64, 64), (256, 256), (300, 300), (2048, 2048))] == [
        256,
        256,
        512,
        512,
    ]
