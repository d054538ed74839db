"""Tests of models/decoders/region_moves.py: PUMA moves over consistent regions."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from models.decoders.graphcut import PumaEnergy, best_pixel_move, minimise
from models.decoders.guided_puma import pair_weights
from models.decoders.region_moves import (
    CONSISTENT_STEP,
    BorderEdges,
    PriorGroups,
    RegionGraph,
    best_region_move,
    consistent_regions,
    region_descent,
)


def test_a_smooth_ramp_is_one_region() -> None:
    u = np.add.outer(np.arange(6) * 0.3, np.arange(8) * 0.2)
    count, labels = consistent_regions(u, None)
    assert count == 1
    assert labels.shape == (6, 8)
    assert labels.dtype == np.int64


def test_a_step_of_half_a_wrap_or_more_splits_regions() -> None:
    u = np.zeros((4, 6))
    u[:, 3:] += CONSISTENT_STEP
    count, labels = consistent_regions(u, None)
    assert count == 2
    assert len(np.unique(labels[:, :3])) == 1 and len(np.unique(labels[:, 3:])) == 1
    assert labels[0, 0] != labels[0, 5]


def test_down_weighted_pairs_do_not_join_pixels() -> None:
    u = np.zeros((3, 3))
    right = np.ones((3, 2))
    down = np.ones((2, 3))
    right[1, :] = 0.1
    down[:, 1] = 0.1
    count, labels = consistent_regions(u, (right, down))
    # The centre pixel's four pairs are all down-weighted: it is a region of its own.
    assert np.sum(labels == labels[1, 1]) == 1
    assert count == 2


ROUGH = (slice(2, 6), slice(2, 6))


def _wrapped_scene(seed: int, size: int = 24) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``m`` of a smooth hill (peak 3.7 wraps) with a rough patch at :data:`ROUGH`
    (residues), its true W, and a guide that never counts above 2 (one wrap short on
    the hill's top)."""
    yy, xx = np.mgrid[0:size, 0:size] / size
    u = 0.2 + 3.5 * np.exp(-((xx - 0.5) ** 2 + (yy - 0.5) ** 2) / 0.08)
    u[ROUGH] += 0.8 * np.random.default_rng(seed).random((4, 4))
    truth = np.floor(u).astype(np.int64)
    return u - truth, truth, np.minimum(truth, 2)


def test_regions_move_whole_and_the_energy_falls() -> None:
    m, _, guide = _wrapped_scene(0)
    energy = PumaEnergy(1.0, pair_weights(m), guide, 0.01)
    moved = best_region_move(guide, m, 1, energy)
    assert moved.shape == m.shape and moved.dtype == bool
    assert moved.any()
    _, labels = consistent_regions(guide + m, energy.weights)
    for label in np.unique(labels):
        assert len(np.unique(moved[labels == label])) == 1
    assert energy(guide + moved, m) < energy(guide, m)


def test_refinement_with_region_moves_restores_the_missing_wrap() -> None:
    m, truth, guide = _wrapped_scene(1)
    assert np.any(truth > guide)
    energy = PumaEnergy(1.0, pair_weights(m), guide, 0.01)
    result = minimise(m, guide, energy, (1, -1), 20, best_region_move)
    smooth = np.ones(m.shape, bool)
    smooth[ROUGH] = False
    np.testing.assert_array_equal(result.winding[smooth], truth[smooth])
    assert result.energies[-1] < result.energies[0]


@settings(max_examples=40, deadline=None)
@given(
    m=arrays(np.float64, (2, 3), elements=st.floats(0.0, 0.999)),
    winding=arrays(np.int64, (2, 3), elements=st.integers(0, 2)),
    prior=arrays(np.int64, (2, 3), elements=st.integers(0, 2)),
    weight=st.floats(0.01, 2.0),
    jump=st.sampled_from([1, -1]),
)
def test_the_region_cut_is_the_best_region_labelling(
    m: np.ndarray, winding: np.ndarray, prior: np.ndarray, weight: float, jump: int
) -> None:
    """Brute force over every subset of regions: the contracted cut finds the least
    energy among moves that keep regions whole, and the pixel cut (exact over all
    labellings) is never worse."""
    energy = PumaEnergy(1.0, pair_weights(m), prior, weight)
    count, labels = consistent_regions(winding + m, energy.weights)
    best = min(
        energy(winding + jump * np.isin(labels, np.flatnonzero(subset)), m)
        for subset in itertools.product([False, True], repeat=count)
    )
    region = energy(winding + jump * best_region_move(winding, m, jump, energy), m)
    pixel = energy(winding + jump * best_pixel_move(winding, m, jump, energy), m)
    assert region <= best + 1e-9
    assert pixel <= region + 1e-9


def _cut_cost(
    edges: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray], sink: np.ndarray
) -> float:
    """What the edges cost when the nodes in ``sink`` are cut from the others."""
    tails, heads, forward, backward = edges
    return float(
        np.sum(forward * (~sink[tails] & sink[heads]))
        + np.sum(backward * (sink[tails] & ~sink[heads]))
    )


@settings(max_examples=60, deadline=None)
@given(
    pairs=st.lists(
        st.tuples(st.integers(0, 4), st.integers(0, 4), st.floats(0, 3), st.floats(0, 3)),
        min_size=1,
        max_size=12,
    ).filter(lambda pairs: all(tail != head for tail, head, _, _ in pairs)),
    selected=arrays(bool, 12),
    sink=arrays(bool, 5),
)
def test_merged_border_edges_cost_the_same_for_every_cut(
    pairs: list[tuple[int, int, float, float]], selected: np.ndarray, sink: np.ndarray
) -> None:
    """Merged, the selected pairs cost what they cost one by one; one edge per pair of
    regions, from the lower region to the higher."""
    tails, heads, forward, backward = (np.array(column) for column in zip(*pairs, strict=True))
    chosen = selected[: tails.size]
    edges = BorderEdges(tails, heads, 5)
    up, down = edges.merge(chosen, forward[chosen], backward[chosen])
    assert np.all(edges.low < edges.high)
    assert len(set(zip(edges.low, edges.high, strict=True))) == edges.low.size
    merged = (edges.low, edges.high, up, down)
    single = (tails[chosen], heads[chosen], forward[chosen], backward[chosen])
    assert _cut_cost(merged, sink) == pytest.approx(_cut_cost(single, sink), abs=1e-9)


@settings(max_examples=60, deadline=None)
@given(
    winding=arrays(np.int64, (3, 4), elements=st.integers(-2, 3)),
    prior=arrays(np.int64, (3, 4), elements=st.integers(-2, 3)),
    labels=arrays(np.int64, (3, 4), elements=st.integers(0, 2)),
    weight=st.one_of(
        st.floats(0.01, 2.0), arrays(np.float64, (3, 4), elements=st.floats(0.0, 2.0))
    ),
    shift=arrays(np.int64, 3, elements=st.integers(-2, 2)),
    jump=st.sampled_from([1, -1]),
    active=arrays(bool, 3),
    bounds=st.one_of(
        st.none(), st.tuples(st.integers(-1, 1), st.one_of(st.none(), st.integers(1, 3)))
    ),
    with_prior=st.booleans(),
)
def test_the_prior_by_region_is_the_prior_by_pixel(
    winding: np.ndarray,
    prior: np.ndarray,
    labels: np.ndarray,
    weight: float | np.ndarray,
    shift: np.ndarray,
    jump: int,
    active: np.ndarray,
    bounds: tuple[int, int | None] | None,
    with_prior: bool,
) -> None:
    """Grouped by (region, offset, K), the per-pixel terms (prior and bounds) and each
    active region's move cost are the pixel sums of :class:`PumaEnergy`'s."""
    energy = PumaEnergy(1.0, None, prior if with_prior else None, weight, 0.5, bounds)
    groups = PriorGroups(winding, labels, energy)
    moved = winding + shift[labels]
    expected = energy.prior_energy(moved)
    assert groups.energy_of(shift) == pytest.approx(expected, rel=1e-12, abs=1e-9)
    region, cost = groups.move_cost(shift, jump, active)
    by_pixel = np.bincount(labels.ravel(), energy.prior_move_cost(moved, jump).ravel(), 3)
    by_group = np.bincount(region, cost, 3)
    np.testing.assert_allclose(by_group[active], by_pixel[active], rtol=1e-12, atol=1e-9)
    assert not np.any(by_group[~active])


def test_a_frame_without_a_prior_has_no_prior_groups() -> None:
    groups = PriorGroups(np.zeros((2, 2), np.int64), np.zeros((2, 2), np.int64), PumaEnergy())
    assert groups.energy_of(np.zeros(1, np.int64)) == 0.0
    region, cost = groups.move_cost(np.zeros(1, np.int64), 1, np.ones(1, bool))
    assert region.size == 0 and cost.size == 0


def test_regions_of_a_single_row_and_a_single_pixel() -> None:
    u = np.array([[0.1, 0.2, 0.9, 1.0]])
    count, labels = consistent_regions(u, None)
    assert count == 2
    np.testing.assert_array_equal(labels, [[0, 0, 1, 1]])
    count, labels = consistent_regions(np.zeros((1, 1)), None)
    assert count == 1 and labels.tolist() == [[0]]


def _glow(short: int, size: int = 40) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``m`` of a smooth glow (peak 5.7 wraps) beside a rough patch, its true W, and a
    guide that leaves every pixel at W >= 2 ``short`` wraps short (never below 2), as
    the nets leave a bright glow's core."""
    yy, xx = np.mgrid[0:size, 0:size] / size
    u = 0.2 + 5.5 * np.exp(-((xx - 0.5) ** 2 + (yy - 0.5) ** 2) / 0.15)
    u[ROUGH] += 0.8 * np.random.default_rng(2).random((4, 4))
    truth = np.floor(u).astype(np.int64)
    guide = np.where(truth >= 2, np.maximum(truth - short, 2), truth)
    return u - truth, truth, guide


def test_region_descent_lifts_a_core_several_wraps_short() -> None:
    """Two region moves lift a region by one wrap at most; the descent converges."""
    m, truth, guide = _glow(short=3)
    energy = PumaEnergy(1.0, pair_weights(m), guide, 0.01, 0.5)
    two = minimise(m, guide, energy, (1, -1), 2, best_region_move)
    result = region_descent(guide, m, energy, (1, -1), 32)
    smooth = np.ones(m.shape, bool)
    smooth[ROUGH] = False
    assert np.any(two.winding[smooth] != truth[smooth])
    np.testing.assert_array_equal(result.winding[smooth], truth[smooth])
    assert result.winding.dtype == np.int64 and result.winding.shape == m.shape
    assert all(b < a for a, b in itertools.pairwise(result.energies))
    assert result.moves <= 32


def test_region_descent_stops_at_once_where_nothing_pays() -> None:
    """From its own answer (with the same prior) no move pays: two cuts, no change."""
    m, _, guide = _glow(short=3)
    energy = PumaEnergy(1.0, pair_weights(m), guide, 0.01, 0.5)
    settled = region_descent(guide, m, energy, (1, -1), 32).winding
    again = region_descent(settled, m, energy, (1, -1), 32)
    np.testing.assert_array_equal(again.winding, settled)
    assert again.moves == 2 and len(again.energies) == 1


@settings(max_examples=40, deadline=None)
@given(
    m=arrays(np.float64, (3, 4), elements=st.floats(0.0, 0.999)),
    winding=arrays(np.int64, (3, 4), elements=st.integers(0, 3)),
    prior=arrays(np.int64, (3, 4), elements=st.integers(0, 3)),
    weight=st.floats(0.01, 2.0),
    moves=st.integers(1, 8),
)
def test_region_descent_never_raises_the_pixel_energy(
    m: np.ndarray, winding: np.ndarray, prior: np.ndarray, weight: float, moves: int
) -> None:
    """Its energies (pairs across borders + prior) fall move by move and differ from the
    pixel energy by a constant, the pairs inside regions; regions move whole."""
    energy = PumaEnergy(1.0, pair_weights(m), prior, weight, 0.5)
    result = region_descent(winding, m, energy, (1, -1), moves)
    assert result.moves <= moves
    assert energy(result.winding, m) <= energy(winding, m) + 1e-9
    inside = energy(winding, m) - result.energies[0]
    assert energy(result.winding, m) - result.energies[-1] == pytest.approx(inside, abs=1e-9)
    _, labels = consistent_regions(winding + m, energy.weights)
    for label in np.unique(labels):
        assert len(np.unique((result.winding - winding)[labels == label])) == 1


@settings(max_examples=40, deadline=None)
@given(
    m=arrays(np.float64, (2, 3), elements=st.floats(0.0, 0.999)),
    winding=arrays(np.int64, (2, 3), elements=st.integers(0, 2)),
    prior=arrays(np.int64, (2, 3), elements=st.integers(0, 2)),
    jump=st.sampled_from([1, -1]),
    active=st.integers(0, 2**6 - 1),
)
def test_a_restricted_region_move_is_the_best_over_its_active_regions(
    m: np.ndarray, winding: np.ndarray, prior: np.ndarray, jump: int, active: int
) -> None:
    """Brute force over every subset of the active regions (the others stay)."""
    energy = PumaEnergy(1.0, pair_weights(m), prior, 0.3, 0.5)
    graph = RegionGraph(winding, m, energy)
    allowed = np.array([(active >> k) & 1 for k in range(graph.count)], bool)
    shift = np.zeros(graph.count, np.int64)
    moved = graph.best_move(shift, jump, allowed)
    assert not np.any(moved & ~allowed)
    candidates = np.flatnonzero(allowed)
    best = min(
        graph.energy_of(shift + jump * np.isin(np.arange(graph.count), candidates[list(pick)]))
        for size in range(len(candidates) + 1)
        for pick in itertools.combinations(range(len(candidates)), size)
    )
    assert graph.energy_of(shift + jump * moved) <= best + 1e-9
