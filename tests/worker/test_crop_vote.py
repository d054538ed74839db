"""Tests of worker/crop_vote.py: unsafe clusters re-decoded on crops, kept by region vote."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from models.decoders.registry import get_decoder
from models.errors import InvalidInputError
from models.formation import SensorParams
from worker.crop_vote import GROW, MIN_SIDE, CropConfig, cluster_boxes, crop_vote
from worker.temporal_config import TemporalConfig
from worker.temporal_rule import Prediction, temporal_prediction

PARAMS = SensorParams(encoding="modulo", bits=8)


def ramp_prediction() -> tuple[Prediction, np.ndarray]:
    """An exact prediction of a smooth 64 x 64 ramp of u (0 to 4 wraps) with a 12 x 12
    block marked unsafe, its bounds one wrap wide each way; and the true W."""
    u = np.add.outer(np.linspace(0.0, 2.0, 64), np.linspace(0.0, 2.0, 64))[:, :, None]
    m = u - np.floor(u)
    exact = temporal_prediction(m, u, TemporalConfig(motion_radius=0)).channel(0)
    safe = exact.safe.copy()
    safe[20:32, 30:42] = False
    loose = replace(exact, safe=safe, lo=exact.lo - 1, hi=exact.hi + 1)
    return loose, np.floor(u[:, :, 0]).astype(np.int64)


def itoh(crop: np.ndarray) -> np.ndarray:
    return get_decoder("itoh").predict_winding(crop, PARAMS)


def test_a_wrong_unsafe_cluster_takes_the_spatial_answer() -> None:
    prediction, truth = ramp_prediction()
    fixed = truth.copy()
    fixed[22:30, 32:40] += 1
    merged, taken = crop_vote(prediction, fixed, itoh, CropConfig(min_cluster=64, limit=1.0))
    np.testing.assert_array_equal(merged, truth)
    assert taken.sum() == 64 and taken[22:30, 32:40].all()


def test_off_or_over_budget_nothing_is_decoded() -> None:
    prediction, truth = ramp_prediction()
    fixed = truth.copy()
    fixed[22:30, 32:40] += 1
    calls: list[tuple[int, ...]] = []

    def counted(crop: np.ndarray) -> np.ndarray:
        calls.append(crop.shape)
        return itoh(crop)

    for config in (CropConfig(min_cluster=0), CropConfig(limit=0.1), CropConfig(min_cluster=145)):
        merged, taken = crop_vote(prediction, fixed, counted, config)
        np.testing.assert_array_equal(merged, fixed)
        assert not taken.any()
    assert calls == []


def test_a_right_fixed_answer_is_kept() -> None:
    prediction, truth = ramp_prediction()
    merged, taken = crop_vote(prediction, truth, itoh, CropConfig(limit=1.0))
    np.testing.assert_array_equal(merged, truth)
    assert not taken.any()


def test_boxes_are_widened_inside_the_frame_and_small_clusters_skipped() -> None:
    """Clusters grow by GROW px, then by the margin, to MIN_SIDE px, cut at the frame."""
    assert (GROW, MIN_SIDE) == (2, 32)
    unsafe = np.zeros((100, 120), bool)
    unsafe[2:12, 50:60] = True
    unsafe[70:72, 10:12] = True
    unsafe[60:90, 80:118] = True
    boxes = cluster_boxes(unsafe, CropConfig(min_cluster=50, margin=4, limit=1.0))
    assert boxes == [(slice(54, 96), slice(74, 120)), (slice(0, 23), slice(39, 71))]
    (rows, cols), = cluster_boxes(unsafe, CropConfig(min_cluster=50, margin=0, limit=0.15))
    assert (rows, cols) == (slice(58, 92), slice(78, 120))
    small = cluster_boxes(unsafe[:20, 40:70], CropConfig(min_cluster=50, margin=0, limit=1.0))
    assert small == [(slice(0, 20), slice(0, 30))]


def test_no_unsafe_pixel_no_box() -> None:
    assert cluster_boxes(np.zeros((8, 8), bool), CropConfig()) == []


@pytest.mark.parametrize(
    "bad", [{"min_cluster": -1}, {"margin": -2}, {"limit": 1.5}, {"limit": -0.1}]
)
def test_bad_settings_are_refused(bad: dict) -> None:
    with pytest.raises(InvalidInputError, match="crop"):
        CropConfig(**bad)
