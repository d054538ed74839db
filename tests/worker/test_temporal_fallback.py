"""Tests of worker/temporal_fallback.py: the local and spatial fallbacks of temporal decoding."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from worker.temporal_config import TemporalConfig
from worker.temporal_fallback import locally_smooth, merge_spatial, neighbour_fix
from worker.temporal_rule import temporal_prediction


def test_neighbour_fix_settles_unsafe_pixels_from_their_neighbours() -> None:
    """Pixels marked unsafe in a smooth, wrapping ramp take W from settled neighbours,
    even a 3 x 3 block (filled over two passes), and match the truth."""
    u = np.add.outer(np.linspace(0, 3, 12), np.linspace(0, 2, 10))[:, :, None]
    m = u - np.floor(u)
    prediction = temporal_prediction(m, u, TemporalConfig(motion_radius=0))
    wrong = prediction.winding.copy()
    safe = prediction.safe.copy()
    wrong[4:7, 4:7] += 2
    safe[4:7, 4:7] = False
    safe[0, 9] = False
    change = np.abs(wrong + m - u)
    damaged = replace(
        prediction, winding=wrong, safe=safe, hi=prediction.hi + 3, change=change,
        steady=change == 0,
    )
    fixed = neighbour_fix(damaged.channel(0), passes=2)
    np.testing.assert_array_equal(fixed, np.floor(u[:, :, 0]))


def test_neighbour_fix_keeps_a_steady_pixels_own_answer() -> None:
    """An unsafe pixel whose own answer is a wrap off and changed by 0.2 wraps takes its
    neighbours' W, unless its change is steady (within the sensor's noise)."""
    u = np.add.outer(np.linspace(0, 3, 12), np.linspace(0, 2, 10))[:, :, None]
    m = u - np.floor(u)
    prediction = temporal_prediction(m, u, TemporalConfig(motion_radius=0)).channel(0)
    wrong, safe, change = prediction.winding.copy(), prediction.safe.copy(), prediction.change
    wrong[5, 5] += 1
    safe[5, 5] = False
    change = change.copy()
    change[5, 5] = 0.2
    for steady, expected in ((False, np.floor(u[5, 5, 0])), (True, np.floor(u[5, 5, 0]) + 1)):
        flags = prediction.steady.copy()
        flags[5, 5] = steady
        damaged = replace(prediction, winding=wrong, safe=safe, change=change, steady=flags)
        assert neighbour_fix(damaged, passes=1)[5, 5] == expected


def test_locally_smooth_marks_pixels_next_to_a_jump() -> None:
    u = np.zeros((4, 5))
    u[:, 3:] = 1.0
    smooth = locally_smooth(u)
    assert not smooth[:, 2:4].any() and smooth[:, :2].all() and smooth[:, 4].all()


def test_merge_spatial_aligns_the_constant_and_fills_unsafe_pixels() -> None:
    """The spatial answer (off by a constant 3) is aligned to the safe tracked pixels
    and fills the unsafe ones; with no safe pixel there is nothing to align to."""
    u = np.add.outer(np.linspace(0, 3, 12), np.linspace(0, 2, 10))[:, :, None]
    m = u - np.floor(u)
    prediction = temporal_prediction(m, u, TemporalConfig(motion_radius=0)).channel(0)
    safe = prediction.safe.copy()
    safe[2:5, 2:5] = False
    damaged = replace(prediction, safe=safe, hi=prediction.hi + 3)
    merged = merge_spatial(damaged, np.floor(u[:, :, 0]).astype(np.int64) - 3)
    assert merged is not None
    winding, taken = merged
    np.testing.assert_array_equal(winding, np.floor(u[:, :, 0]))
    assert taken[2:5, 2:5].all()
    none_safe = replace(prediction, safe=np.zeros_like(safe))
    assert merge_spatial(none_safe, prediction.winding) is None


def test_neighbour_fix_breaks_a_tie_for_the_first_neighbour() -> None:
    """Two settled neighbours that match an unsafe pixel equally well with different W:
    the first in reading order (the upper-left one here) decides."""
    m = np.full((3, 3, 1), 0.5)
    u = np.full((3, 3, 1), 1.5)
    prediction = temporal_prediction(m, u, TemporalConfig(motion_radius=0)).channel(0)
    winding, safe = prediction.winding.copy(), np.zeros((3, 3), bool)
    winding[0, 0], winding[2, 2] = 2, 0  # u 2.5 and 0.5: each one wrap from 1.5
    safe[0, 0] = safe[2, 2] = True
    change = np.full((3, 3), 0.45)
    damaged = replace(
        prediction, winding=winding, safe=safe, change=change, steady=np.zeros((3, 3), bool),
        lo=np.zeros((3, 3)), hi=np.full((3, 3), 5.0),
    )
    assert neighbour_fix(damaged, passes=1)[1, 1] == 2
