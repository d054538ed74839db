"""Tests of models/decoders/region_vote.py: merging two W answers region by region."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from scipy import ndimage

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


def test_regions_larger_than_max_region_switch_only_on_a_decisive_vote() -> None:
    """A large region bounded on one side by a true edge steeper than half a wrap (the
    candidate jumps there too) keeps the kept answer; one the kept answer alone rings
    with jumps (a smooth lamp's core a network left short) takes the candidate's."""
    truth, m = ramp()
    truth[:, 12:] += 3
    kept = truth.copy()
    kept[12:16, 4:12] -= 1
    kept[2:4, 18:22] += 2
    kept[3:9, 2:9] -= 2
    merged, taken = region_vote(kept, truth, m, max_region=8)
    np.testing.assert_array_equal(merged[2:4, 18:22], truth[2:4, 18:22])
    np.testing.assert_array_equal(merged[3:9, 2:9], truth[3:9, 2:9])
    np.testing.assert_array_equal(merged[12:16, 4:12], kept[12:16, 4:12])
    assert taken.sum() == 2 * 4 + 6 * 7


def vote_pixel_by_pixel(kept: np.ndarray, candidate: np.ndarray, m: np.ndarray,
                        eligible: np.ndarray | None, max_region: int | None) -> np.ndarray:
    """The module doc's rule, one neighbour pair at a time (an oracle for the test below):
    the candidate's W per pixel where its region takes it, else the kept one."""
    labels, count = ndimage.label(kept != candidate)
    u_kept, u_candidate = kept + m, candidate + m
    was, now, border = np.zeros(count + 1), np.zeros(count + 1), np.zeros(count + 1)
    rows, cols = kept.shape
    for r in range(rows):
        for c in range(cols):
            for nr, nc in ((r + 1, c), (r, c + 1), (r - 1, c), (r, c - 1)):
                if 0 <= nr < rows and 0 <= nc < cols and labels[r, c] != labels[nr, nc]:
                    was[labels[r, c]] += abs(u_kept[r, c] - u_kept[nr, nc]) > 0.5
                    now[labels[r, c]] += abs(u_candidate[r, c] - u_kept[nr, nc]) > 0.5
                    border[labels[r, c]] += 1
    merged = kept.copy()
    for region in range(1, count + 1):
        inside = labels == region
        decisive = now[region] <= 0.05 * border[region] and was[region] >= 0.5 * border[region]
        if (was[region] > now[region] and (eligible is None or eligible[inside].any())
                and (max_region is None or inside.sum() <= max_region or decisive)):
            merged[inside] = candidate[inside]
    return merged


def shifted(truth: np.ndarray, box: tuple[int, int, int, int], by: int) -> np.ndarray:
    """``truth`` with ``by`` wraps added in ``box`` (top, left, bottom, right; may be empty)."""
    top, left, bottom, right = box
    out = truth.copy()
    out[top:bottom, left:right] += by
    return out


boxes = st.tuples(st.integers(0, 12), st.integers(0, 12), st.integers(0, 12), st.integers(0, 12))


@settings(max_examples=300, deadline=None)
@example(rows=8, cols=8, slope=(0.1, 0.1), kept_box=(3, 0, 12, 12), candidate_box=(0, 0, 0, 0),
         kept_by=1, candidate_by=1, with_eligible=False, max_region=None)
@example(rows=8, cols=8, slope=(0.1, 0.1), kept_box=(0, 0, 5, 12), candidate_box=(0, 0, 0, 0),
         kept_by=1, candidate_by=1, with_eligible=False, max_region=None)
@example(rows=8, cols=8, slope=(0.1, 0.1), kept_box=(0, 5, 12, 12), candidate_box=(0, 0, 0, 0),
         kept_by=1, candidate_by=1, with_eligible=False, max_region=None)
@example(rows=8, cols=8, slope=(0.1, 0.1), kept_box=(0, 0, 12, 3), candidate_box=(0, 0, 0, 0),
         kept_by=1, candidate_by=1, with_eligible=False, max_region=None)
@given(rows=st.integers(1, 12), cols=st.integers(1, 12), slope=st.tuples(
    st.floats(0.0, 0.45), st.floats(0.0, 0.45)), kept_box=boxes, candidate_box=boxes,
    kept_by=st.sampled_from([-1, 1, 2]), candidate_by=st.sampled_from([-1, 1]),
    with_eligible=st.booleans(), max_region=st.none() | st.integers(1, 20))
def test_the_vote_is_the_module_docs_rule_wherever_the_answers_differ(
        rows: int, cols: int, slope: tuple[float, float], kept_box: tuple[int, int, int, int],
        candidate_box: tuple[int, int, int, int], kept_by: int, candidate_by: int,
        with_eligible: bool, max_region: int | None) -> None:
    """Answers a wrap off in two rectangles of a smooth ramp, anywhere (at the frame's
    edges, in a corner, overlapping), are merged as the rule says, neighbour pair by
    neighbour pair. The examples: a region bordered on
    one side only (above, below, left, right), the kept answer a wrap off there."""
    u = np.add.outer(np.arange(rows) * slope[0], np.arange(cols) * slope[1])
    truth = np.floor(u).astype(np.int64)
    m = u - truth
    kept, candidate = shifted(truth, kept_box, kept_by), shifted(truth, candidate_box,
                                                                 candidate_by)
    eligible = np.arange(rows * cols).reshape(rows, cols) % 3 == 0 if with_eligible else None
    merged, taken = region_vote(kept, candidate, m, eligible, max_region)
    expected = vote_pixel_by_pixel(kept, candidate, m, eligible, max_region)
    np.testing.assert_array_equal(merged, expected)
    np.testing.assert_array_equal(taken, merged != kept)
