"""Tests of models/scene_analysis.py: wrap edges, residues, tile difficulty."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy import ndimage

from models.errors import InvalidInputError
from models.formation import SensorParams, encode, split_unwrapped
from models.scene_analysis import (
    DENSE_EDGE_DENSITY,
    analyse,
    cross_dilation,
    neighbour_jumps,
    residue_map,
)

MODULO = SensorParams(encoding="modulo", bits=8)


def ramp(height: int, width: int, peak: float) -> np.ndarray:
    """A smooth diagonal ramp from 0 to ``peak`` wraps."""
    rows, cols = np.mgrid[0:height, 0:width]
    return peak * (rows + cols) / (height + width - 2)


def test_smoke_and_shapes() -> None:
    m = np.random.default_rng(0).random((50, 70))
    result = analyse(m, MODULO, tile=32)
    assert len(result.tiles) == 2 * 3
    assert (result.frame.height, result.frame.width) == (50, 70)
    assert [(t.row, t.col) for t in result.tiles][:3] == [(0, 0), (0, 32), (0, 64)]
    assert result.tiles[-1].height == 18 and result.tiles[-1].width == 6
    cols, rows = neighbour_jumps(m)
    assert cols.shape == (50, 69) and rows.shape == (49, 70)
    assert residue_map(cols, rows).shape == (49, 69)


def test_rejects_bad_shapes() -> None:
    with pytest.raises(ValueError, match="one channel"):
        analyse(np.zeros((4, 4, 3)), MODULO)
    with pytest.raises(ValueError, match="tile"):
        analyse(np.zeros((4, 4)), MODULO, tile=1)


@pytest.mark.parametrize("shape", [(0, 5), (5, 0), (0, 0)])
def test_a_frame_without_pixels_is_refused(shape: tuple[int, int]) -> None:
    """Its analysis had no pixels in its one tile, and ``auto`` divided its routes'
    pixel counts by 0 (ZeroDivisionError)."""
    with pytest.raises(InvalidInputError, match=f"a {shape[0]} x {shape[1]} frame holds no"):
        analyse(np.zeros(shape), MODULO)


def test_unwrapped_frame_has_no_edges() -> None:
    frame = encode(ramp(64, 64, 0.9), MODULO)
    result = analyse((frame.codes + 0.5) / 256, MODULO)
    assert result.frame.wrap_edges == 0
    assert result.frame.difficulty == "none"
    assert all(t.difficulty == "none" for t in result.tiles)


def test_smooth_multiwrap_frame_is_residue_free() -> None:
    frame = encode(ramp(128, 128, 20.0), MODULO)
    result = analyse((frame.codes + 0.5) / 256, MODULO, tile=64)
    assert result.frame.wrap_edges > 0
    assert result.frame.residues == 0
    assert result.itoh_likely
    assert result.frame.difficulty == "smooth"


def test_random_frame_is_dense() -> None:
    m = np.random.default_rng(1).random((64, 64))
    result = analyse(m, MODULO, tile=64)
    assert result.frame.residues > 0
    assert result.frame.edge_density > DENSE_EDGE_DENSITY
    assert result.frame.difficulty == "dense"
    assert not result.itoh_likely


def test_max_winding_bound_from_params() -> None:
    params = SensorParams(encoding="mantissa", alpha=2.0, max_wraps=16)
    assert analyse(np.zeros((4, 4)), params).max_winding == 5
    assert analyse(np.zeros((4, 4)), MODULO).max_winding is None


@settings(max_examples=60, deadline=None)
@given(
    peak=st.floats(0.0, 40.0),
    height=st.integers(2, 40),
    width=st.integers(2, 40),
)
def test_edges_are_exactly_where_w_changes_under_itoh(peak: float, height: int, width: int) -> None:
    """When neighbours differ by < half a wrap, jumps equal minus the change of W."""
    u = ramp(height, width, peak)
    winding, m = split_unwrapped(u, MODULO)
    cols, rows = neighbour_jumps(m)
    if np.abs(np.diff(u, axis=1)).max(initial=0) < 0.5:
        np.testing.assert_array_equal(cols, -np.diff(winding, axis=1))
    if np.abs(np.diff(u, axis=0)).max(initial=0) < 0.5:
        np.testing.assert_array_equal(rows, -np.diff(winding, axis=0))
    assert np.count_nonzero(residue_map(cols, rows)) == 0


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_residues_are_integer_circulations(seed: int) -> None:
    m = np.random.default_rng(seed).random((8, 8))
    cols, rows = neighbour_jumps(m)
    circulation = residue_map(cols, rows)
    assert np.all(np.abs(circulation) <= 2)
    assert int(circulation.sum()) == int(
        cols[0, :].sum() + rows[:, -1].sum() - cols[-1, :].sum() - rows[:, 0].sum()
    )


def test_analysis_carries_the_jumps_it_counted() -> None:
    m = np.random.default_rng(2).random((20, 30))
    result = analyse(m, MODULO, tile=8)
    cols, rows = neighbour_jumps(m)
    np.testing.assert_array_equal(result.along_cols, cols)
    np.testing.assert_array_equal(result.along_rows, rows)
    assert result.frame.wrap_edges == np.count_nonzero(cols) + np.count_nonzero(rows)


def test_a_wrap_edge_is_a_neighbour_jump_of_more_than_half_a_wrap() -> None:
    def wrap_edges(m: np.ndarray) -> int:
        return sum(np.count_nonzero(jumps) for jumps in neighbour_jumps(m))

    assert wrap_edges(np.tile(np.linspace(0.0, 0.99, 64), (3, 1))) == 0
    assert wrap_edges(np.array([[0.2, 0.7]])) == 0  # exactly half a wrap: no jump
    assert wrap_edges(np.array([[0.9], [0.1]])) == 1
    assert wrap_edges(np.zeros((1, 1))) == 0


def test_a_residue_on_a_tile_border_counts_in_the_tiles_it_touches() -> None:
    """Residues only in 2x2 loops across rows 63|64: both tiles they touch hold them, so
    auto sends those to the hard-tile decoder (counted in none, the frame read 'sparse'
    while every tile read none or smooth)."""
    m = np.zeros((128, 128))
    m[63, 40:42] = [0.0, 0.33]
    m[64, 40:42] = [0.99, 0.66]
    loops = np.argwhere(residue_map(*neighbour_jumps(m)))
    assert len(loops) and (loops[:, 0] == 63).all()
    analysis = analyse(m, MODULO, 64)
    hard = [(t.row, t.col) for t in analysis.tiles if t.residues]
    assert hard == [(0, 0), (64, 0)]
    assert all(t.difficulty in ("sparse", "dense") for t in analysis.tiles if t.residues)


@settings(max_examples=60, deadline=None)
@given(
    mask=arrays(bool, st.tuples(st.integers(1, 9), st.integers(1, 9))),
    iterations=st.integers(0, 3),
)
def test_cross_dilation_is_scipys_binary_dilation(mask: np.ndarray, iterations: int) -> None:
    """The shifted-slice dilation grows a mask exactly as ``binary_dilation`` does with its
    default cross, frames of one row or column included."""
    expected = ndimage.binary_dilation(mask, iterations=iterations) if iterations else mask
    np.testing.assert_array_equal(cross_dilation(mask, iterations), expected)
