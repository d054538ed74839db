"""Tests of worker/arrivals.py: arriving content found by its misfit, refined on a crop."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from models.decoders.guided_puma import GuidedPumaDecoder
from models.decoders.registry import get_decoder
from models.errors import InvalidInputError
from models.formation import SensorParams
from worker.arrivals import REACH, ArrivalConfig, refine_arrivals
from worker.temporal import StreamDecoder, decode_frames
from worker.temporal_config import TemporalConfig

PARAMS = SensorParams(encoding="modulo", bits=8)
SIZE = 160


def light(cy: float, cx: float, peak: float = 3.6) -> np.ndarray:
    """u (wraps) of a smooth light on a flat 0.3-wrap background: at most 0.3 wrap/px."""
    yy, xx = np.mgrid[0:SIZE, 0:SIZE].astype(np.float64)
    return 0.3 + peak * np.exp(-((yy - cy) ** 2 + (xx - cx) ** 2) / (2 * 8.0**2))


def refiner() -> GuidedPumaDecoder:
    return GuidedPumaDecoder(get_decoder("itoh"), max_moves=8, region_moves=0)


def test_a_light_left_at_its_old_winding_is_unwrapped() -> None:
    u = light(80, 80)
    m, truth = u - np.floor(u), np.floor(u).astype(np.int64)
    tracked = np.zeros_like(truth)
    change = np.abs(m - 0.3)
    merged, taken = refine_arrivals(m, tracked, change, PARAMS, refiner(), ArrivalConfig())
    assert taken.any() and not taken[:8].any()
    near = ndimage.binary_dilation(change > ArrivalConfig().change, iterations=REACH)
    assert not taken[~near].any()
    np.testing.assert_array_equal(merged[~near], tracked[~near])
    wrong_before = int((tracked != truth).sum())
    assert wrong_before > 500
    assert (merged != truth).sum() <= wrong_before // 100


def test_noise_sized_misfits_and_small_clusters_are_left_alone() -> None:
    u = light(80, 80)
    m = u - np.floor(u)
    truth = np.floor(u).astype(np.int64)
    rng = np.random.default_rng(0)
    noise = np.abs(rng.normal(0.0, 0.03, m.shape))
    for change, config in (
        (noise, ArrivalConfig()),
        (np.where(np.hypot(*np.mgrid[-80:80, -80:80]) < 3, 0.3, 0.0), ArrivalConfig()),
        (np.full(m.shape, 0.3), ArrivalConfig(min_cluster=0)),
    ):
        merged, taken = refine_arrivals(m, truth, change, PARAMS, refiner(), config)
        np.testing.assert_array_equal(merged, truth)
        assert not taken.any()


def test_a_light_jumping_across_a_still_view_is_tracked_by_the_stream() -> None:
    """The light moves 20 px between frames: without arrival refinement the temporal
    rule keeps most of the new light at the background's W."""
    frames = [light(80, 50), light(80, 70), light(80, 90)]
    codes = [np.floor((u - np.floor(u)) * 256).astype(np.uint8) for u in frames]
    truth = np.floor(frames[-1]).astype(np.int64)
    accuracy = {}
    for config_name, arrival in (("on", ArrivalConfig()), ("off", ArrivalConfig(min_cluster=0))):
        decoder = StreamDecoder("temporal", "itoh", TemporalConfig(arrival=arrival))
        *_, result = decode_frames(codes, PARAMS, decoder)
        accuracy[config_name] = float(np.mean(result.winding == truth))
    assert accuracy["on"] > 0.99
    assert accuracy["on"] > accuracy["off"]


@pytest.mark.parametrize(
    ("values", "fragment"),
    [
        ({"change": 0.0}, "change"),
        ({"change": 0.5}, "change"),
        ({"min_cluster": -1}, "min_cluster"),
        ({"margin": -2}, "margin"),
        ({"limit": 1.5}, "limit"),
        ({"moves": 0}, "moves"),
    ],
)
def test_invalid_settings_are_refused_with_their_name(values: dict, fragment: str) -> None:
    with pytest.raises(InvalidInputError, match=fragment):
        ArrivalConfig(**values)
