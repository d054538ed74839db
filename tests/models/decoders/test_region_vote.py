"""Tests of models/decoders/region_vote.py: merging two W answers region by region."""

from __future__ import annotations

import numpy as np
import pytest

from models.decoders.region_vote import region_vote


def ramp() -> tuple[np.ndarray, np.ndarray]:
    """True W and m of a smooth ramp of u from 0 to 4 wraps over 20 x 24 pixels."""
    u = np.add.outer(np.linspace(0.0, 2.0, 20), np.linspace(0.0, 2.0, 24))
    return np.floor(u).astype(np.int64), u - np.floor(u)


def test_a_region_the_spatial_decoder_got_wrong_keeps_the_tracked_answer() -> None:
    truth, m = ramp()
    spatial = truth.copy()
    spatial[5:10, 6:12] += 1
    merged, taken = region_vote(truth, spatial, m)
    np.testing.assert_array_equal(merged, truth)
    assert not taken.any()


def test_a_region_the_tracking_got_wrong_takes_the_spatial_answer() -> None:
    truth, m = ramp()
    tracked = truth.copy()
    tracked[12:16, 2:9] -= 1
    tracked[2:4, 18:22] += 2
    merged, taken = region_vote(tracked, truth, m)
    np.testing.assert_array_equal(merged, truth)
    assert taken.sum() == 4 * 7 + 2 * 4


def test_mixed_errors_are_judged_region_by_region() -> None:
    truth, m = ramp()
    tracked, spatial = truth.copy(), truth.copy()
    tracked[1:4, 1:4] += 1
    spatial[10:15, 10:15] -= 1
    merged, _ = region_vote(tracked, spatial, m)
    np.testing.assert_array_equal(merged, truth)


@pytest.mark.parametrize("shape", [(1, 9), (9, 1), (2, 2), (7, 5)])
def test_agreeing_answers_of_any_shape_come_back_unchanged(shape: tuple[int, int]) -> None:
    winding = np.arange(np.prod(shape), dtype=np.int64).reshape(shape) % 3
    m = np.full(shape, 0.5)
    merged, taken = region_vote(winding, winding.copy(), m)
    np.testing.assert_array_equal(merged, winding)
    assert merged.shape == shape and not taken.any()
    other = winding.copy()
    other.flat[0] += 1
    merged, taken = region_vote(winding, other, m)
    assert merged.shape == taken.shape == shape


def test_only_regions_touching_an_eligible_pixel_may_switch() -> None:
    truth, m = ramp()
    tracked = truth.copy()
    tracked[12:16, 2:9] -= 1
    tracked[2:4, 18:22] += 2
    eligible = np.zeros(truth.shape, bool)
    eligible[13, 5] = True
    merged, taken = region_vote(tracked, truth, m, eligible)
    np.testing.assert_array_equal(merged[12:16, 2:9], truth[12:16, 2:9])
    np.testing.assert_array_equal(merged[2:4, 18:22], tracked[2:4, 18:22])
    assert taken.sum() == 4 * 7


def test_regions_larger_than_max_region_keep_the_kept_answer() -> None:
    truth, m = ramp()
    kept = truth.copy()
    kept[12:16, 2:9] -= 1
    kept[2:4, 18:22] += 2
    merged, taken = region_vote(kept, truth, m, max_region=8)
    np.testing.assert_array_equal(merged[2:4, 18:22], truth[2:4, 18:22])
    np.testing.assert_array_equal(merged[12:16, 2:9], kept[12:16, 2:9])
    assert taken.sum() == 2 * 4
