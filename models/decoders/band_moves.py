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
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from models.decoders.graphcut import (
    MoveCapacities,
    MoveSolver,
    PumaEnergy,
    cut_pixels,
    min_cut,
    move_capacities,
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
    """The pixels within ``reach`` px (Chebyshev distance) of a seed."""
    if reach <= 0 or not seeds.any():
        return seeds
    return ndimage.maximum_filter(seeds, size=2 * reach + 1, mode="constant")


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


def confined_move(band: NDArray[np.bool_]) -> MoveSolver:
    """A move solver that cuts only ``band`` (bool, H x W), every other pixel kept: for a
    refinement whose errors can only lie near known pixels (the temporal decoder's
    fallback pixels, :mod:`worker.temporal`)."""

    def solve(
        winding: NDArray[np.int64], m: NDArray[np.float64], jump: int, energy: PumaEnergy
    ) -> NDArray[np.bool_]:
        return cut_band(move_capacities(winding, m, jump, energy), band)

    return solve
