"""Narrow-band PUMA pixel moves: the min-cut on the pixels near where the energy can fall.

A pixel move of guided refinement (:func:`models.decoders.graphcut.best_pixel_move`)
cuts a graph over every pixel, and every pixel has a terminal link (the guide's prior
costs something whichever way a pixel moves), so the max-flow touches the whole frame
even when the region moves before it (:mod:`models.decoders.region_moves`) left only
a few borders to settle. Yet a move can lower the energy only through pixels that gain
by moving: the ends of a *jump* (a neighbour pair more than half a wrap apart in
``u = K + m``, whose term falls when one end moves) and pixels below the guide (for a
rise; above it, for a fall). The band move cuts the graph of the pixels within
:data:`BAND_REACH` px (Chebyshev) of those seeds; every other pixel stays put, its
pairs with band pixels folded into their terminal links, so the cut is exact over the
moves that leave the outside alone.

Band moves serve only budgeted refinements
(:class:`models.decoders.guided_puma.GuidedPumaDecoder`, ``auto`` at ``balanced``),
which first run region moves to convergence
(:func:`models.decoders.region_moves.region_descent`). A band cut that moves nothing
is a failed move: no full pixel cut follows it. What a full cut could add there is a
set of pixels far from every seed moving together, a region moving whole, and the
region descent has already tried those moves.

Measured (2026-11-25, AMD EPYC, 2 cores; val-256, the two pixel cuts of auto-balanced
after its two region moves on the small-s2d net's W; medians of 5 interleaved runs):
mantissa 30.3 -> 26.6 ms, modulo 24.1 -> 18.0 ms, the same W on all 48 frames. The
whole of auto-balanced kept its PSNR to 0.001 dB on val-256 (24.015 / 23.997 dB),
the mostly-dark set (42.52), and synthetic 512x512 (36.54) and 1024x1024 frames
(38.18). Reach 8 cut the pixel cuts' time by 30-43% but changed one modulo frame
(val-256 modulo 23.64 dB). Then an empty band cut was followed by the full pixel cut,
so that band moves run to convergence stopped only at the pixel moves' global
minimum: without it, and without region moves first, reach 16 left a large region a
wrap off on a 512x512 frame refined to convergence (36.40 -> 34.01 dB). Converging
with band moves reached the same PSNR everywhere but took longer (val-256 mantissa
103 -> 120 ms, 512x512 1.26 -> 1.82 s), so no refinement converges with them.

Dropping that full cut after the region descent (2026-11-26; auto-balanced, 2 quiet
AMD EPYC cores, medians of 5 interleaved runs): the same W on val-256 (both
encodings), the mostly-dark, glows and colour frames (hash-checked), 512x512 and
1024x1024; mostly-dark 25.5 -> 23.5 ms a frame (the full cut cost 3-4 ms on each
frame with wraps, after a band cut that found nothing), 6 glows frames 51.3 -> 48.7
ms, 12 val-256 frames 78.4 -> 78.9 ms.

The temporal decoder's refinement confines its moves to a fixed band round the pixels
that fell back (:class:`BandGraph`; :meth:`GuidedPumaDecoder.refine_within
<models.decoders.guided_puma.GuidedPumaDecoder.refine_within>`). Its band holds
13-14% of a panning frame's pixels, so its graph is built once, each cut computes the
terms of the pairs that touch the band only, and the moves are compared by the share
of the energy they can change (2026-11-27, pan/zoom with herraez, modulo, cProfile:
8.3 -> 5.2 ms a refinement; the same W on every frame of bench.video's clips). Which
pair gives a term to which node, and the pairs' weights, are then found once for both
cuts (:class:`BandPairs`, :meth:`BandGraph.moves`): 3.87 -> 3.67 ms a refinement
(timeit, one frame, medians of 3 interleaved runs).
Skipping a cut whose band holds no pixel that gains by moving alone (every folded cost
non-negative, so the empty move is the best) was measured and not kept: none of the
110 band cuts of a pan/zoom stream (herraez or auto-fast, either encoding) had one;
each had 290-350 such pixels and moved 70-110.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from models.decoders.graphcut import (
    Edges,
    EnergyValue,
    MoveCapacities,
    MoveSolver,
    PumaEnergy,
    cut_pixels,
    min_cut,
    move_capacities,
    move_terms,
    pair_capacities,
)

#: Pixels within this many pixels (Chebyshev) of a seed join the band's graph.
BAND_REACH = 16
#: Neighbours further apart than this in ``u`` (wraps) form a jump: a pair whose term
#: falls when one end moves by a whole wrap (for the L1 potential, ``|d| > 1/2``).
JUMP_STEP = 0.5


def jump_pairs(u: NDArray[np.float64]) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """The neighbour pairs of ``u`` (wraps) further apart than :data:`JUMP_STEP`: to the
    right neighbour (H x W-1) and to the lower one (H-1 x W)."""
    return np.abs(np.diff(u, axis=1)) > JUMP_STEP, np.abs(np.diff(u, axis=0)) > JUMP_STEP


def band_seeds(
    winding: NDArray[np.int64], m: NDArray[np.float64], unary: NDArray[np.float64]
) -> NDArray[np.bool_]:
    """Pixels (H x W) that can lower the energy by moving: the ends of jumps and the
    pixels whose own move cost ``unary`` is negative."""
    right, down = jump_pairs(winding + m)
    seeds = unary < 0.0
    seeds[:, :-1] |= right
    seeds[:, 1:] |= right
    seeds[:-1] |= down
    seeds[1:] |= down
    return seeds


def band_of(seeds: NDArray[np.bool_], reach: int = BAND_REACH) -> NDArray[np.bool_]:
    """The pixels within ``reach`` px (Chebyshev distance) of a seed: what
    ``scipy.ndimage.maximum_filter(seeds, 2 * reach + 1, mode="constant")`` gives, by
    shifted slices (256x256, 2026-11-27: 0.06 ms at reach 4 and 0.09 at 16, against the
    filter's 0.3)."""
    if reach <= 0 or not seeds.any():
        return seeds
    return _grown_along(_grown_along(seeds, reach, 0), reach, 1)


def _grown_along(mask: NDArray[np.bool_], reach: int, axis: int) -> NDArray[np.bool_]:
    """``mask`` (bool, H x W) grown by ``reach`` px both ways along ``axis``: each pass
    ORs in the mask shifted by up to one more than the reach covered so far, which
    leaves no gap, so ``reach`` takes about log2(reach) + 1 passes."""
    covered = 0
    while covered < reach:
        step = min(covered + 1, reach - covered)
        grown = mask.copy()
        if step < mask.shape[axis]:
            ahead = [slice(None), slice(None)]
            behind = [slice(None), slice(None)]
            ahead[axis], behind[axis] = slice(step, None), slice(None, -step)
            grown[tuple(ahead)] |= mask[tuple(behind)]
            grown[tuple(behind)] |= mask[tuple(ahead)]
        mask, covered = grown, covered + step
    return mask


def _band_unary(capacities: MoveCapacities, band: NDArray[np.bool_]) -> NDArray[np.float64]:
    """Each band pixel's move cost with its pairs to fixed outside pixels folded in: an
    outside neighbour keeps ``delta = 0``, so the edge that is cut when only the band
    pixel moves becomes part of that pixel's cost."""
    unary = np.where(band, capacities.unary, 0.0)
    (forward_right, backward_right), (forward_down, backward_down) = (
        capacities.right, capacities.down
    )
    left_in, right_in = band[:, :-1], band[:, 1:]
    unary[:, :-1] += np.where(left_in & ~right_in, backward_right, 0.0)
    unary[:, 1:] += np.where(right_in & ~left_in, forward_right, 0.0)
    top_in, bottom_in = band[:-1], band[1:]
    unary[:-1] += np.where(top_in & ~bottom_in, backward_down, 0.0)
    unary[1:] += np.where(bottom_in & ~top_in, forward_down, 0.0)
    return unary[band]


def cut_band(capacities: MoveCapacities, band: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """The pixels (H x W) whose K should move: the minimum cut over ``band`` with every
    other pixel kept."""
    count = int(band.sum())
    moved = np.zeros(band.shape, bool)
    if count == 0:
        return moved
    index = np.full(band.shape, -1, np.int64)
    index[band] = np.arange(count)
    (forward_right, backward_right), (forward_down, backward_down) = (
        capacities.right, capacities.down
    )
    right_pairs = band[:, :-1] & band[:, 1:]
    down_pairs = band[:-1] & band[1:]
    edges = (
        (
            index[:, :-1][right_pairs], index[:, 1:][right_pairs],
            forward_right[right_pairs], backward_right[right_pairs],
        ),
        (
            index[:-1][down_pairs], index[1:][down_pairs],
            forward_down[down_pairs], backward_down[down_pairs],
        ),
    )
    moved[band] = min_cut(_band_unary(capacities, band), edges)
    return moved


def best_band_move(
    winding: NDArray[np.int64], m: NDArray[np.float64], jump: int, energy: PumaEnergy
) -> NDArray[np.bool_]:
    """The pixels whose K should grow by ``jump``: the cut of the band around the pixels
    that gain by moving, every other pixel kept (a
    :data:`models.decoders.graphcut.MoveSolver`; nothing when no pixel gains)."""
    capacities = move_capacities(winding, m, jump, energy)
    seeds = band_seeds(winding, m, capacities.unary)
    if not seeds.any():
        # Every pixel's move costs something and no pair gains: staying put is best.
        return seeds
    band = band_of(seeds, BAND_REACH)
    if band.all():
        return cut_pixels(capacities)
    return cut_band(capacities, band)


class Slots(NamedTuple):
    """Entries of a list of pairs (``at``, positions in it) and the band nodes they give
    a term to (``nodes``, one each, none twice)."""

    at: NDArray[np.int64]
    nodes: NDArray[np.int64]

    def add(self, unary: NDArray[np.float64], values: NDArray[np.float64]) -> None:
        """``unary[nodes] += values[at]`` (``values``: one per pair of the list)."""
        unary[self.nodes] += values[self.at]


def _slots(where: NDArray[np.bool_], nodes: NDArray[np.int64]) -> Slots:
    """The :class:`Slots` of the pairs where ``where`` holds, giving to ``nodes``."""
    at = np.flatnonzero(where)
    return Slots(at, nodes[at])


@dataclass(frozen=True)
class BandPairs:
    """The neighbour pairs of one direction (to the right or to the lower neighbour) with
    at least one end in a band, in row-major order of the pair grid: ``first`` /
    ``second`` the flat pixel indices of their ends (left or upper, right or lower) and
    ``pair`` their flat indices into the direction's pair grid (its weights). Which
    pairs give a term to which node, found once for every cut: ``first_end`` /
    ``second_end`` the pairs whose first / second end is in the band (its unary shift),
    ``first_only`` / ``second_only`` those whose other end is outside (the pair folds
    into that node's cost), and ``inner`` those with both ends in (an edge; ``inner``
    gives its first node, ``inner_second`` its second)."""

    first: NDArray[np.int64]
    second: NDArray[np.int64]
    pair: NDArray[np.int64]
    first_end: Slots
    second_end: Slots
    first_only: Slots
    second_only: Slots
    inner: Slots
    inner_second: NDArray[np.int64]

    @classmethod
    def of(cls, band: NDArray[np.bool_], node: NDArray[np.int64], axis: int) -> BandPairs:
        """The pairs along ``axis`` (1: to the right, 0: to the lower neighbour) that
        touch ``band`` (H x W), ``node`` holding each pixel's node number (-1 outside)."""
        pixels = np.arange(band.size).reshape(band.shape)
        first = (slice(None), slice(None, -1)) if axis == 1 else (slice(None, -1), slice(None))
        second = (slice(None), slice(1, None)) if axis == 1 else (slice(1, None), slice(None))
        touching = band[first] | band[second]
        first_node, second_node = node[first][touching], node[second][touching]
        first_in, second_in = first_node >= 0, second_node >= 0
        inner = _slots(first_in & second_in, first_node)
        return cls(
            pixels[first][touching], pixels[second][touching], np.flatnonzero(touching),
            _slots(first_in, first_node), _slots(second_in, second_node),
            _slots(first_in & ~second_in, first_node), _slots(second_in & ~first_in, second_node),
            inner, second_node[inner.at],
        )  # fmt: skip

    def terms(
        self, u: NDArray[np.float64], jump: int, p: float, weights: NDArray[np.float64] | None
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """The pairs' (forward, backward, unary_shift) for the move adding ``jump``
        (:func:`models.decoders.graphcut.pair_capacities`) from the flat ``u`` (wraps),
        the potential's power ``p`` and the pairs' ``weights`` (None: 1): each the value
        :func:`models.decoders.graphcut.move_capacities` gives the pair."""
        c, w = move_terms(u[self.second] - u[self.first], jump, p)
        if weights is not None:
            c, w = c * weights, w * weights
        return pair_capacities(c, w)

    def lengths(
        self, u: NDArray[np.float64], p: float, weights: NDArray[np.float64] | None
    ) -> float:
        """The pairs' share of the clique energy, ``sum w |u_j - u_i| ** p``."""
        lengths = np.abs(u[self.second] - u[self.first]) ** p
        return float(np.sum(lengths if weights is None else weights * lengths))


@dataclass(frozen=True)
class BandGraph:
    """Moves confined to a fixed band, every other pixel kept: for a refinement whose
    errors can only lie near known pixels (the temporal decoder's fallback pixels,
    :mod:`worker.temporal`). Built once for every cut of a refinement: the band's pixels
    (flat indices, row-major: node ``i`` is ``pixels[i]``) and the pairs to the right
    and to the lower neighbour that touch it (:class:`BandPairs`). The solver of
    :meth:`moves` then computes the terms of those pairs only, about a quarter of a
    panning frame's, where :func:`cut_band` takes the whole frame's
    :class:`models.decoders.graphcut.MoveCapacities`: each node's cost and each edge's
    capacities are the same floats :func:`cut_band` gives them, added in the same order,
    so the cut is the same; its energy is the share that such moves can change."""

    shape: tuple[int, int]
    pixels: NDArray[np.int64]
    right: BandPairs
    down: BandPairs

    @classmethod
    def of(cls, band: NDArray[np.bool_]) -> BandGraph:
        """The graph of ``band`` (bool, H x W)."""
        pixels = np.flatnonzero(band)
        node = np.full(band.shape, -1, np.int64)
        node.ravel()[pixels] = np.arange(pixels.size)
        shape = (int(band.shape[0]), int(band.shape[1]))
        return cls(shape, pixels, BandPairs.of(band, node, 1), BandPairs.of(band, node, 0))

    def moves(self, energy: PumaEnergy) -> tuple[MoveSolver, EnergyValue]:
        """For moves of ``energy`` within the band: a move solver (the minimum cut over
        the band with every other pixel kept, what :func:`cut_band` of the whole frame's
        :func:`models.decoders.graphcut.move_capacities` gives) and the share of
        ``energy`` that such moves can change (its pairs that touch the band and its prior
        on the band's pixels; the rest is constant, so comparing this share compares the
        whole energy, at a fraction of its cost, but for the tolerance of
        :func:`models.decoders.graphcut.accepts`, relative to the share: a move gaining
        less than 1e-12 of the whole energy and more than 1e-12 of the share is kept,
        where comparing the whole energy refuses it). The pairs' weights are gathered
        once, so the solver refuses any other energy."""
        directions = (self.right, self.down)
        weights = tuple(
            None if energy.weights is None else grid.ravel()[pairs.pair]
            for grid, pairs in zip(energy.weights or (None, None), directions, strict=True)
        )

        def solve(
            winding: NDArray[np.int64], m: NDArray[np.float64], jump: int, moving: PumaEnergy
        ) -> NDArray[np.bool_]:
            if moving is not energy:
                raise ValueError(
                    "this band solver was made for another energy: make one for this "
                    "energy with BandGraph.moves(energy)"
                )
            return self._cut(winding, m, jump, energy, weights)

        def value(winding: NDArray[np.int64], m: NDArray[np.float64]) -> float:
            u = winding.ravel() + m.ravel()
            total = energy.prior_energy(winding, self.pixels)
            for pairs, pair_weights in zip(directions, weights, strict=True):
                total += pairs.lengths(u, energy.p, pair_weights)
            return total

        return solve, value

    def _cut(
        self,
        winding: NDArray[np.int64],
        m: NDArray[np.float64],
        jump: int,
        energy: PumaEnergy,
        weights: tuple[NDArray[np.float64] | None, ...],
    ) -> NDArray[np.bool_]:
        """The band's minimum cut for the move adding ``jump`` (see :meth:`moves`), with
        the pairs' ``weights`` gathered."""
        moved = np.zeros(self.shape, bool)
        if self.pixels.size == 0:
            return moved
        u = winding.ravel() + m.ravel()
        unary = energy.prior_move_cost(winding, jump, self.pixels)
        directions = (self.right, self.down)
        terms = [
            pairs.terms(u, jump, energy.p, pair_weights)
            for pairs, pair_weights in zip(directions, weights, strict=True)
        ]
        for pairs, (_, _, shift) in zip(directions, terms, strict=True):
            pairs.first_end.add(unary, shift)
            pairs.second_end.add(unary, -shift)
        edges: list[Edges] = []
        for pairs, (forward, backward, _) in zip(directions, terms, strict=True):
            # A pair with one end outside (kept) folds into the inside end's cost, as
            # :func:`_band_unary` folds it.
            pairs.first_only.add(unary, backward)
            pairs.second_only.add(unary, forward)
            at = pairs.inner.at
            edges.append((pairs.inner.nodes, pairs.inner_second, forward[at], backward[at]))
        moved.ravel()[self.pixels] = min_cut(unary, edges)
        return moved


