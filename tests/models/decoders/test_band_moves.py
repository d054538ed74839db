"""Tests of models/decoders/band_moves.py: PUMA pixel moves cut on a narrow band."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy import ndimage

from models.decoders import band_moves
from models.decoders.band_moves import (
    BandGraph,
    band_of,
    band_seeds,
    best_band_move,
    cut_band,
)
from models.decoders.graphcut import (
    PumaEnergy,
    best_pixel_move,
    cut_pixels,
    minimise,
    move_capacities,
)
from models.decoders.guided_puma import pair_weights
from models.decoders.region_moves import region_descent


def _hill(size: int, short_by: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``m`` of a smooth hill (peak 3.7 wraps), its true W and a guide that counts at
    most ``3 - short_by`` (a wrap short on the hill's top)."""
    yy, xx = np.mgrid[0:size, 0:size] / size
    u = 0.2 + 3.5 * np.exp(-((xx - 0.5) ** 2 + (yy - 0.5) ** 2) / 0.08)
    truth = np.floor(u).astype(np.int64)
    return u - truth, truth, np.minimum(truth, 3 - short_by)


def test_the_move_is_a_boolean_map_of_the_frame() -> None:
    m, _, guide = _hill(24)
    energy = PumaEnergy(1.0, pair_weights(m), guide, 0.01)
    moved = best_band_move(guide, m, 1, energy)
    assert moved.shape == m.shape and moved.dtype == bool
    assert energy(guide + moved, m) < energy(guide, m)


def test_seeds_are_the_ends_of_jumps() -> None:
    m = np.full((4, 6), 0.3)
    winding = np.zeros((4, 6), np.int64)
    winding[:, 3:] = 1  # u jumps by a wrap between columns 2 and 3
    seeds = band_seeds(winding, m, np.zeros(m.shape))
    expected = np.zeros(m.shape, bool)
    expected[:, 2:4] = True
    np.testing.assert_array_equal(seeds, expected)


def test_seeds_include_pixels_that_gain_by_moving_alone() -> None:
    unary = np.zeros((3, 3))
    unary[1, 1] = -0.01
    seeds = band_seeds(np.zeros((3, 3), np.int64), np.full((3, 3), 0.5), unary)
    assert seeds.sum() == 1 and seeds[1, 1]


def test_the_band_reaches_its_distance_in_every_direction() -> None:
    seeds = np.zeros((11, 11), bool)
    seeds[5, 5] = True
    band = band_of(seeds, 2)
    expected = np.zeros((11, 11), bool)
    expected[3:8, 3:8] = True
    np.testing.assert_array_equal(band, expected)
    np.testing.assert_array_equal(band_of(seeds, 0), seeds)


@settings(max_examples=80, deadline=None)
@given(
    seeds=arrays(bool, st.tuples(st.integers(1, 12), st.integers(1, 12))),
    reach=st.integers(1, 20),
)
def test_the_band_is_the_maximum_filter_of_its_seeds(seeds: np.ndarray, reach: int) -> None:
    """The shifted-slice band is the Chebyshev maximum filter it replaced, reaches past
    the frame's side included."""
    expected = ndimage.maximum_filter(seeds, size=2 * reach + 1, mode="constant")
    np.testing.assert_array_equal(band_of(seeds, reach), expected)


def test_a_frame_that_agrees_with_its_guide_does_not_move() -> None:
    m = np.tile(np.linspace(0.1, 0.4, 8), (6, 1))
    guide = np.zeros(m.shape, np.int64)
    energy = PumaEnergy(1.0, pair_weights(m), guide, 0.01)
    for jump in (1, -1):
        assert not best_band_move(guide, m, jump, energy).any()


def test_a_band_over_the_whole_frame_is_the_pixel_cut() -> None:
    m, _, guide = _hill(20)
    energy = PumaEnergy(1.0, pair_weights(m), guide, 0.01)
    capacities = move_capacities(guide, m, 1, energy)
    np.testing.assert_array_equal(
        cut_band(capacities, np.ones(m.shape, bool)), cut_pixels(capacities)
    )


@settings(max_examples=40, deadline=None)
@given(
    m=arrays(np.float64, (3, 4), elements=st.floats(0.0, 0.999)),
    winding=arrays(np.int64, (3, 4), elements=st.integers(0, 2)),
    prior=arrays(np.int64, (3, 4), elements=st.integers(0, 2)),
    band=arrays(bool, (3, 4)),
    weight=st.floats(0.01, 2.0),
    jump=st.sampled_from([1, -1]),
)
def test_the_band_cut_is_the_best_move_that_keeps_the_outside(
    m: np.ndarray,
    winding: np.ndarray,
    prior: np.ndarray,
    band: np.ndarray,
    weight: float,
    jump: int,
) -> None:
    """Brute force over every subset of the band: the cut finds the least energy among
    moves that leave the pixels outside it alone, and moves nothing outside."""
    energy = PumaEnergy(1.0, pair_weights(m), prior, weight, above_factor=0.5)
    inside = np.flatnonzero(band)
    best = energy(winding, m)
    for subset in itertools.product([False, True], repeat=inside.size):
        moved = np.zeros(m.size, bool)
        moved[inside[np.array(subset, bool)]] = True
        best = min(best, energy(winding + jump * moved.reshape(m.shape), m))
    moved = cut_band(move_capacities(winding, m, jump, energy), band)
    assert not moved[~band].any()
    assert energy(winding + jump * moved, m) <= best + 1e-9


@pytest.mark.parametrize("reach", [1, 3, band_moves.BAND_REACH])
def test_band_moves_after_a_region_descent_reach_the_pixel_moves_minimum(
    reach: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """As a budgeted refinement runs them: region moves to convergence, then band moves
    (an empty band cut is a failed move) stop at the global minimum of the convex
    energy that full pixel moves reach, even with a band too narrow to move the hill's
    top whole."""
    monkeypatch.setattr(band_moves, "BAND_REACH", reach)
    m, truth, guide = _hill(48, short_by=2)
    energy = PumaEnergy(1.0, pair_weights(m), guide, 0.01, above_factor=0.5)
    pixel = minimise(m, guide, energy, (1, -1), 100, best_pixel_move)
    start = region_descent(guide, m, energy, (1, -1), 16).winding
    band = minimise(m, start, energy, (1, -1), 100, best_band_move)
    assert band.energies[-1] == pytest.approx(pixel.energies[-1], rel=1e-9, abs=1e-9)
    np.testing.assert_array_equal(band.winding, truth)


def test_a_confined_move_keeps_every_pixel_outside_its_band() -> None:
    """The hill's missing top is put back where the band covers it, and only there."""
    m, truth, guide = _hill(32, short_by=1)
    energy = PumaEnergy(1.0, pair_weights(m), guide, 0.01, above_factor=0.5)
    band = np.zeros(m.shape, bool)
    band[:, :16] = True
    moved = BandGraph.of(band).moves(energy)[0](guide, m, 1, energy)
    assert not moved[~band].any()
    assert moved.any()
    np.testing.assert_array_equal((guide + moved)[band], np.where(moved, truth, guide)[band])


@settings(max_examples=60, deadline=None)
@given(
    m=arrays(np.float64, st.tuples(st.integers(1, 7), st.integers(1, 7)),
             elements=st.floats(0.0, 0.999)),
    seed=st.integers(0, 2**32 - 1),
    jump=st.sampled_from([1, -1]),
    per_pixel=st.booleans(),
)  # fmt: skip
def test_a_band_graph_cuts_as_the_whole_frames_capacities_do(
    m: np.ndarray, seed: int, jump: int, per_pixel: bool
) -> None:
    """The band's own terms (the pairs touching it) give the very cut that the whole
    frame's capacities give, bands at the frame's border included."""
    rng = np.random.default_rng(seed)
    winding, prior = rng.integers(0, 3, m.shape), rng.integers(0, 3, m.shape)
    band = rng.random(m.shape) < rng.random()
    weight = rng.random(m.shape) if per_pixel else 0.01
    weights = pair_weights(m) if min(m.shape) > 1 else None
    energy = PumaEnergy(1.0, weights, prior, weight, above_factor=0.5)
    np.testing.assert_array_equal(
        BandGraph.of(band).moves(energy)[0](winding, m, jump, energy),
        cut_band(move_capacities(winding, m, jump, energy), band),
    )


def test_the_band_energy_differs_from_the_whole_by_a_constant() -> None:
    """Under moves that keep every pixel outside the band, the band's share of the energy
    changes exactly as the whole energy does."""
    m, _, guide = _hill(24)
    energy = PumaEnergy(1.0, pair_weights(m), guide, 0.01, above_factor=0.5)
    band = np.zeros(m.shape, bool)
    band[4:15, 6:20] = True
    share = BandGraph.of(band).moves(energy)[1]
    rng = np.random.default_rng(3)
    offset = energy(guide, m) - share(guide, m)
    for _ in range(5):
        moved = guide + rng.integers(-1, 2, m.shape) * band
        assert share(moved, m) + offset == pytest.approx(energy(moved, m), rel=1e-12)


def test_a_band_refinement_compared_by_its_share_reaches_the_whole_energys_answer() -> None:
    """Moves compared by the band's share of the energy make the same moves as moves
    compared by the whole energy when their gains lie far above either's rounding
    tolerance (as on a real frame: see the next test for where they differ)."""
    m, _, guide = _hill(32, short_by=1)
    energy = PumaEnergy(1.0, pair_weights(m), guide, 0.01, above_factor=0.5)
    band = np.zeros(m.shape, bool)
    band[:, :20] = True
    solve, share = BandGraph.of(band).moves(energy)
    whole = minimise(m, guide, energy, (1, -1), 6, solve)
    shared = minimise(m, guide, energy, (1, -1), 6, solve, value=share)
    np.testing.assert_array_equal(shared.winding, whole.winding)
    assert shared.moves == whole.moves
    assert (shared.winding != guide).any()


def test_a_band_solver_refuses_an_energy_it_was_not_made_for() -> None:
    m, _, guide = _hill(12)
    solve, _ = BandGraph.of(np.ones(m.shape, bool)).moves(PumaEnergy(1.0, pair_weights(m)))
    with pytest.raises(ValueError, match="another energy"):
        solve(guide, m, 1, PumaEnergy(1.0, pair_weights(m), guide, 0.01))


def test_a_band_refinement_keeps_a_gain_above_the_rounding_of_its_share() -> None:
    """A move must gain more than 1e-12 of what it is compared by (:func:`accepts`): of
    the band's share, not of the whole energy. A pixel a wrap off inside the band (a
    gain of 4) beside 4e13 of energy outside it (a step of 1e13 wraps) is put right when
    moves are compared by the share and left when by the whole energy: the two W differ
    where a gain lies between the two tolerances."""
    m = np.zeros((4, 10))
    guide = np.zeros(m.shape, np.int64)
    guide[1, 1] = 1
    guide[:, 8:] = 10**13
    band = np.zeros(m.shape, bool)
    band[:, :4] = True
    energy = PumaEnergy(1.0)
    solve, share = BandGraph.of(band).moves(energy)
    whole = minimise(m, guide, energy, (1, -1), 6, solve)
    shared = minimise(m, guide, energy, (1, -1), 6, solve, value=share)
    assert whole.winding[1, 1] == 1 and whole.energies == [energy(guide, m)]
    assert shared.winding[1, 1] == 0 and shared.energies == [4.0, 0.0]
