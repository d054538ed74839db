"""Tests of worker/temporal_config.py: the temporal decoder's knobs are checked when made."""

from __future__ import annotations

import pytest

from models.errors import InvalidInputError
from worker.crop_vote import CropConfig
from worker.recordings import MAX_RECORDING_SAMPLES
from worker.temporal_config import MAX_KEYFRAME_INTERVAL, MODES, TemporalConfig


def test_defaults_are_valid_and_name_both_modes() -> None:
    config = TemporalConfig()
    assert MODES == ("independent", "temporal")
    assert config.keyframe_interval > 0
    assert 0.0 <= config.margin < 0.5


def test_a_nested_config_is_kept() -> None:
    crop = CropConfig(min_cluster=0)
    assert TemporalConfig(crop=crop).crop is crop


@pytest.mark.parametrize(
    "bad",
    [{"margin": 0.5}, {"motion_radius": -1}, {"keyframe_interval": -2}, {"local_limit": 2.0},
     {"local_passes": 0}, {"still": 0.7}, {"steady_sigmas": -1.0}, {"refine_moves": -1},
     {"refine_reach": -1}, {"refine_whole_every": -2}],
)
def test_bad_settings_are_refused(bad: dict) -> None:
    name = next(iter(bad))
    with pytest.raises(InvalidInputError, match=f"invalid temporal settings.*{name}"):
        TemporalConfig(**bad)


def test_a_keyframe_period_longer_than_any_video_is_refused() -> None:
    """10^30 was accepted and stored with a video job. The bound is the most frames a video
    holds: 2 x 2 frames of the largest MCAM_MAX_VIDEO_SAMPLES (2 x MAX_RECORDING_SAMPLES)."""
    assert MAX_KEYFRAME_INTERVAL == 2 * MAX_RECORDING_SAMPLES // (2 * 2)
    assert TemporalConfig(keyframe_interval=MAX_KEYFRAME_INTERVAL).keyframe_interval > 0
    with pytest.raises(InvalidInputError, match=r"from 0 \(no periodic keyframes\) to 33554432 "
                       r"frames .*got 1000000000000000000000000000000"):
        TemporalConfig(keyframe_interval=10**30)
