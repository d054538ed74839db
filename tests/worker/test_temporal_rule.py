"""Tests of worker/temporal_rule.py: the temporal prediction, its safety and its bounds."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from worker.temporal_config import TemporalConfig
from worker.temporal_rule import UNBOUNDED, temporal_prediction, window_extreme


@settings(max_examples=50, deadline=None)
@given(
    prev=st.floats(0.0, 20.0),
    change=st.floats(-0.39, 0.39),
    radius=st.integers(0, 2),
)
def test_prediction_is_exact_below_the_margin(prev: float, change: float, radius: int) -> None:
    """Any change smaller than half a wrap minus the margin is unwrapped exactly and safe
    (a uniform frame: every neighbour agrees)."""
    u_now = prev + change
    m = np.full((3, 3, 1), u_now - np.floor(u_now))
    prediction = temporal_prediction(m, np.full((3, 3, 1), prev), TemporalConfig(
        motion_radius=radius))
    assert np.all(prediction.winding == np.floor(u_now)) and prediction.safe.all()


def test_prediction_flags_edges_near_moving_content() -> None:
    """A one-wrap step in the previous frame next to changed pixels is unsafe in its window."""
    prev = np.zeros((5, 5, 1))
    prev[:, 3:] = 1.0
    m = np.full((5, 5, 1), 0.2)
    prediction = temporal_prediction(m, prev, TemporalConfig(motion_radius=1, still=0.05))
    assert not prediction.safe[:, 2:4].any() and prediction.safe[:, 0].all()


def test_steady_pixels_changed_within_the_noise() -> None:
    """A pixel is steady when its change is within ``steady_sigmas`` sigmas of the noise:
    none changed by 0.2 wraps is steady at no noise, all are at sigma 0.1; a pixel
    outside the moved frame never is."""
    prev = np.full((3, 4, 1), 2.3)
    m = np.full((3, 4, 1), 0.5)
    config = TemporalConfig(steady_sigmas=3.0)
    assert not temporal_prediction(m, prev, config).steady.any()
    inside = np.ones((3, 4), bool)
    inside[:, 0] = False
    steady = temporal_prediction(m, prev, config, inside, noise=0.1).steady
    assert steady[:, 1:].all() and not steady[:, 0].any()


@settings(max_examples=50)
@given(
    values=arrays(np.float64, st.tuples(st.integers(1, 6), st.integers(1, 6), st.just(1)),
                  elements=st.floats(-100, 100)),
    radius=st.integers(0, 3),
)
def test_window_extreme_is_the_min_and_max_over_each_window(
    values: np.ndarray, radius: int
) -> None:
    rows, cols = values.shape[:2]
    low = window_extreme(values, radius, np.minimum)
    high = window_extreme(values, radius, np.maximum)
    for r in range(rows):
        for c in range(cols):
            top, left = max(r - radius, 0), max(c - radius, 0)
            window = values[top : r + radius + 1, left : c + radius + 1]
            assert low[r, c, 0] == window.min() and high[r, c, 0] == window.max()


def test_bounds_allow_the_w_that_motion_allows() -> None:
    """Previous u within the window spans [1.2, 2.9]: W + m may lie half a wrap beyond."""
    prev = np.full((3, 3, 1), 1.2)
    prev[0, 0] = 2.9
    m = np.full((3, 3, 1), 0.5)
    lowest, highest = temporal_prediction(m, prev, TemporalConfig(motion_radius=1)).bounds()
    assert lowest[1, 1, 0] == 1 and highest[1, 1, 0] == 2  # 1.5 and 2.5 lie in [0.7, 3.4]


def test_pixels_outside_the_moved_frame_are_unsafe_and_unbounded() -> None:
    m = np.full((4, 4, 1), 0.3)
    inside = np.ones((4, 4), bool)
    inside[:, 0] = False
    prediction = temporal_prediction(m, np.full((4, 4, 1), 2.3), TemporalConfig(), inside)
    assert not prediction.safe[:, 0].any() and prediction.safe[:, 1:].all()
    assert (prediction.hi[:, 0] == UNBOUNDED).all() and (prediction.lo[:, 0] == 0).all()


def test_marking_pixels_outside_leaves_the_previous_frame_alone() -> None:
    """Without a motion window the bounds start as the previous ``u`` itself: marking the
    pixels outside the move sets them on copies, each bound its own."""
    m = np.full((3, 4, 2), 0.3)
    prev = np.full((3, 4, 2), 2.3)
    inside = np.ones((3, 4), bool)
    inside[0] = False
    prediction = temporal_prediction(m, prev, TemporalConfig(motion_radius=0), inside, 0.01)
    np.testing.assert_array_equal(prev, np.full((3, 4, 2), 2.3))
    assert (prediction.lo[0] == 0).all() and (prediction.hi[0] == UNBOUNDED).all()
    assert (prediction.lo[1:] == 2.3).all() and (prediction.hi[1:] == 2.3).all()
    assert (prediction.change[0] == 0.5).all() and not prediction.steady[0].any()
