"""Tests of models/tile_reconcile.py: path integration and tile stitching."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from models.formation import SensorParams, split_unwrapped
from models.scene_analysis import neighbour_jumps
from models.tile_reconcile import (
    Tile,
    _border_vote,
    common_offset,
    integrate_jumps,
    most_common,
    stitch,
)

MODULO = SensorParams(encoding="modulo")


def smooth_field(seed: int, height: int, width: int, peak: float) -> np.ndarray:
    """A smooth, non-negative field whose neighbour steps stay below half a wrap."""
    rng = np.random.default_rng(seed)
    rows, cols = np.mgrid[0:height, 0:width] / max(height, width)
    a, b, c = rng.uniform(0.5, 2.0, 3)
    field = peak * (np.sin(a * 3 * rows) ** 2 + np.cos(b * 3 * cols + c) ** 2) / 2
    step = max(np.abs(np.diff(field, axis=0)).max(), np.abs(np.diff(field, axis=1)).max())
    return field * 0.45 / step if step > 0.45 else field


def tiles_of(winding: np.ndarray, size: int, offsets: np.ndarray) -> list[Tile]:
    tiles = []
    k = 0
    for r in range(0, winding.shape[0], size):
        for c in range(0, winding.shape[1], size):
            rows = slice(r, min(r + size, winding.shape[0]))
            cols = slice(c, min(c + size, winding.shape[1]))
            part = winding[rows, cols]
            tiles.append(Tile(rows, cols, part - part.min() + offsets[k]))
            k += 1
    return tiles


def test_integrate_jumps_shape_and_origin() -> None:
    along_cols = np.zeros((3, 4), np.int64)
    along_rows = np.zeros((2, 5), np.int64)
    result = integrate_jumps(along_cols, along_rows)
    assert result.shape == (3, 5)
    assert result[0, 0] == 0 and not result.any()


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), peak=st.floats(0.0, 25.0))
def test_integration_recovers_w_up_to_a_constant(seed: int, peak: float) -> None:
    u = smooth_field(seed, 40, 50, peak)
    winding, m = split_unwrapped(u, MODULO)
    relative = integrate_jumps(*neighbour_jumps(m))
    np.testing.assert_array_equal(relative - relative[0, 0], winding - winding[0, 0])


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), size=st.integers(5, 30))
def test_stitch_undoes_random_tile_offsets(seed: int, size: int) -> None:
    u = smooth_field(seed, 48, 60, 15.0)
    winding, m = split_unwrapped(u, MODULO)
    along_cols, along_rows = neighbour_jumps(m)
    n_tiles = -(-48 // size) * -(-60 // size)
    shuffled = np.random.default_rng(seed).integers(-50, 50, n_tiles)
    stitched = stitch(tiles_of(winding, size, shuffled), m.shape, along_cols, along_rows)
    np.testing.assert_array_equal(stitched - stitched[0, 0], winding - winding[0, 0])


def test_a_minority_of_bad_border_pixels_is_outvoted() -> None:
    u = smooth_field(3, 40, 40, 12.0)
    winding, m = split_unwrapped(u, MODULO)
    along_cols, along_rows = neighbour_jumps(m)
    tiles = tiles_of(winding, 20, np.zeros(4, np.int64))
    corrupted = tiles[1].winding.copy()
    bad_rows = np.arange(0, 20, 3)
    corrupted[bad_rows, 0] += 7
    tiles[1] = Tile(tiles[1].rows, tiles[1].cols, corrupted)
    stitched = stitch(tiles, m.shape, along_cols, along_rows)
    error = stitched - winding - (stitched - winding)[0, 0]
    assert set(np.flatnonzero(error[:, 20])) == set(bad_rows)
    error[bad_rows, 20] = 0
    assert not error.any()


@given(
    st.lists(st.integers(-5, 5), min_size=1, max_size=40),
    st.integers(-1000, 1000),
)
def test_border_vote_is_the_smallest_most_common_offset(votes: list[int], shift: int) -> None:
    left = np.array(votes, np.int64) + shift
    jumps = np.zeros_like(left)
    right = np.full_like(left, shift)
    delta, support = _border_vote(left, right, jumps)
    values, counts = np.unique(votes, return_counts=True)
    assert delta == values[np.argmax(counts)]
    assert support == pytest.approx(counts.max() - (len(votes) - counts.max()))


def test_common_offset_is_the_most_frequent_difference() -> None:
    target = np.array([5, 5, 5, 2, 9])
    relative = np.array([1, 1, 1, 1, 1])
    assert common_offset(target, relative) == 4
    assert common_offset(np.array([-3]), np.array([0])) == -3


@given(st.integers(-50, 50), st.integers(0, 2**31 - 1))
def test_common_offset_aligns_a_shifted_map_with_a_few_errors(shift: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    target = rng.integers(0, 8, (16, 16))
    relative = target - shift
    relative[rng.random(target.shape) < 0.2] += 1
    assert common_offset(target, relative) == shift


@settings(max_examples=100, deadline=None)
@given(
    st.lists(st.integers(-(2**61), 2**61), max_size=40),
    st.lists(st.integers(0, 41), max_size=40),
)
def test_most_common_is_the_smallest_mode_over_a_2_62_span(
    values: list[int], repeats: list[int]
) -> None:
    """Values spanning 2^62 (a tracked W against a spatial one on a mantissa stream
    with alpha 1 + 1e-11, where one gain step moves u by 1e9 wraps): the histogram was
    allocated over the whole span, a MemoryError (39 GiB for a 5e9 span). Every example
    holds both ends, so that no example has a span a histogram could still allocate."""
    values = [-(2**61), *values, 2**61]
    values += [values[i % len(values)] for i in repeats]
    counts = Counter(values)
    top = max(counts.values())
    value, share = most_common(np.array(values, np.int64))
    assert value == min(v for v, n in counts.items() if n == top)
    assert share == pytest.approx(top / len(values))


def test_a_one_pixel_border_does_not_outvote_a_long_one() -> None:
    """Frames one pixel past a multiple of the tile leave 1-pixel strips: their borders'
    single vote had a share of 1, level with a unanimous 64-pixel border, and was taken
    first. Here the strip's 1-pixel border votes +1 (a residue) and the 8-pixel border
    to the same tile votes 0 seven times out of eight: the strip must follow the 8."""
    tiles = [
        Tile(slice(0, 8), slice(0, 8), np.zeros((8, 8), np.int64)),
        Tile(slice(0, 8), slice(8, 9), np.zeros((8, 1), np.int64)),
        Tile(slice(8, 16), slice(0, 8), np.zeros((8, 8), np.int64)),
        Tile(slice(8, 16), slice(8, 9), np.zeros((8, 1), np.int64)),
    ]
    along_cols, along_rows = np.zeros((16, 8), np.int64), np.zeros((15, 9), np.int64)
    along_rows[7, 8] = -1  # tile 1 -> tile 3, its only pair: offset +1
    along_cols[12, 7] = 1  # tile 2 -> tile 3: one pair of eight dissents
    assert stitch(tiles, (16, 9), along_cols, along_rows).tolist() == np.zeros((16, 9)).tolist()
