"""Tests of models/video_metrics.py: per-frame averages, temporal consistency, wrap flicker."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from models.errors import InvalidInputError
from models.metrics import PSNR_CAP, psnr
from models.video_metrics import (
    clip_metrics,
    mean_psnr,
    temporal_consistency,
    wrap_flicker,
)


def clip(frames: int = 4, size: int = 8) -> np.ndarray:
    rng = np.random.default_rng(frames)
    return rng.uniform(0.01, 10.0, (frames, size, size))


def test_identical_clips_are_perfect() -> None:
    ref = clip()
    winding = np.floor(ref).astype(np.int64)
    result = clip_metrics(ref, ref, winding, winding)
    assert result == {
        "psnr": PSNR_CAP,
        "pu21_psnr": PSNR_CAP,
        "winding_accuracy": 1.0,
        "temporal_consistency": 0.0,
        "wrap_flicker": 0.0,
    }


def test_mean_psnr_is_the_mean_of_frames() -> None:
    ref = clip()
    est = ref * np.array([1.1, 1.0, 0.9, 1.2])[:, None, None]
    expected = np.mean([min(psnr(e, r), PSNR_CAP) for e, r in zip(est, ref, strict=True)])
    assert mean_psnr(est, ref) == pytest.approx(expected)


def test_a_steady_error_is_consistent_but_flicker_is_not() -> None:
    """An error that is the same in every frame changes nothing over time; one that
    comes and goes does."""
    ref = np.repeat(clip(1), 4, axis=0)
    steady = ref * 2.0
    flicker = ref * np.array([1.0, 2.0, 1.0, 2.0])[:, None, None]
    assert temporal_consistency(steady, ref) == pytest.approx(0.0, abs=1e-15)
    assert temporal_consistency(flicker, ref) > 0.05
    assert mean_psnr(steady, ref) < mean_psnr(flicker, ref)


def test_wrap_flicker_counts_only_spurious_changes() -> None:
    truth = np.array([[[0, 1]], [[0, 2]], [[0, 2]]])
    decoded = np.array([[[0, 1]], [[1, 2]], [[0, 3]]])
    # transitions: pixel 0 flips twice (truth never), pixel 1 flips twice (truth once)
    assert wrap_flicker(decoded, truth) == pytest.approx(3 / 4)


@settings(max_examples=30, deadline=None)
@given(arrays(np.int64, (3, 2, 2), elements=st.integers(0, 4)))
def test_wrap_flicker_is_a_fraction(winding: np.ndarray) -> None:
    assert wrap_flicker(winding, winding) == 0.0
    value = wrap_flicker(winding, np.zeros_like(winding))
    assert 0.0 <= value <= 1.0


@pytest.mark.parametrize(
    ("est", "ref"),
    [(clip(4), clip(3)), (clip(1), clip(1)), (np.ones(5), np.ones(5))],
    ids=["mismatch", "one-frame", "not-a-clip"],
)
def test_bad_clips_are_refused(est: np.ndarray, ref: np.ndarray) -> None:
    with pytest.raises(InvalidInputError):
        temporal_consistency(est, ref)


def test_float_winding_is_refused() -> None:
    with pytest.raises(InvalidInputError, match="integers"):
        wrap_flicker(np.zeros((2, 2, 2)), np.zeros((2, 2, 2), np.int64))
