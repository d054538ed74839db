"""Region-level PUMA moves: one min-cut over consistent regions instead of pixels.

A guide decoder's errors come as whole regions (a ring of a light left a wrap short,
a tile one wrap high). Inside such a region the guide is self-consistent: neighbours
differ by less than half a wrap in ``u = K + m`` along pairs the codes decide. The
region move contracts every maximal set of pixels linked by such pairs into one node
(pixels near a residue stay single nodes, since their pairs are down-weighted) and
cuts that graph, so a region either moves whole or stays. It is a restriction of
the pixel move of :func:`models.decoders.graphcut.best_pixel_move`: its cut is exact
over region labellings and its energy change equals the pixel energy's, but it cannot
split a consistent region, so it stops at a higher energy when splitting one pays.

How guided refinement uses it (:mod:`models.decoders.guided_puma`; val-256, 2 quiet
AMD EPYC cores, 2026-11-25): the contracted graph has 1k-28k nodes instead of 65k
(forest frames, full of residues, keep the most), and a cut costs about a third of a
pixel cut. Region moves alone are guide-dependent: until convergence they gave
23.57 dB with the small net's guide (pixel moves 23.52) but 22.03 dB with the tiny
net's (pixel moves 23.31), where a wrong region joins a right one across an aliased
edge and cannot be split. So two region moves come first and pixel moves finish:
the converged pixel refinement's PSNR within 0.01 dB for both nets and both
encodings, in 40-50 ms instead of 106-131 ms.

Since 2026-11-25 (evening) the regions are labelled on a doubled pixel grid and the
pixel pairs along each border are summed into one edge: auto-balanced's two region
cuts on val-256 took 23.8 -> 17.4 ms (mantissa) and 18.8 -> 15.7 ms (modulo) with the
same W on all 48 frames.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from models.decoders.graphcut import Edges, PairWeights, PumaEnergy, min_cut, move_capacities

#: Neighbours are in one region when ``|u_j - u_i|`` is below this (wrap units): the
#: Itoh condition under the current K.
CONSISTENT_STEP = 0.5
#: ... and their pair's weight is above this: the codes decide the pair (it is not next
#: to a residue nor across a sharp step; see :func:`models.decoders.guided_puma.pair_weights`).
LINK_WEIGHT = 0.5


def consistent_regions(
    u: NDArray[np.float64], weights: PairWeights
) -> tuple[int, NDArray[np.int64]]:
    """Label the regions of ``u`` (H x W, wrap units): 4-neighbours are joined when
    their pair's weight is above :data:`LINK_WEIGHT` (or there are no weights) and they
    differ by less than :data:`CONSISTENT_STEP`. Returns (number of regions, labels H x W)."""
    height, width = u.shape
    right = np.abs(np.diff(u, axis=1)) < CONSISTENT_STEP
    down = np.abs(np.diff(u, axis=0)) < CONSISTENT_STEP
    if weights is not None:
        right &= weights[0] > LINK_WEIGHT
        down &= weights[1] > LINK_WEIGHT
    # Pixels sit at the even points of a grid twice as fine, each link between them:
    # 4-connected components of that grid are the regions, in raster order of their
    # first pixel (0.8 ms faster at 256x256 than a sparse graph's components).
    grid = np.zeros((2 * height - 1, 2 * width - 1), bool)
    grid[::2, ::2] = True
    grid[::2, 1::2] = right
    grid[1::2, ::2] = down
    labels, count = ndimage.label(grid)
    return int(count), labels[::2, ::2].astype(np.int64) - 1


def best_region_move(
    winding: NDArray[np.int64], m: NDArray[np.float64], jump: int, energy: PumaEnergy
) -> NDArray[np.bool_]:
    """The pixels whose K should grow by ``jump``, moving consistent regions whole:
    the minimum cut of the pixel move's graph with each region contracted to a node
    (a :data:`models.decoders.graphcut.MoveSolver`)."""
    capacities = move_capacities(winding, m, jump, energy)
    count, labels = consistent_regions(winding + m, energy.weights)
    unary = np.bincount(labels.ravel(), capacities.unary.ravel(), minlength=count)
    tails = np.concatenate([labels[:, :-1].ravel(), labels[:-1].ravel()])
    heads = np.concatenate([labels[:, 1:].ravel(), labels[1:].ravel()])
    forward = np.concatenate([capacities.right[0].ravel(), capacities.down[0].ravel()])
    backward = np.concatenate([capacities.right[1].ravel(), capacities.down[1].ravel()])
    # Pairs inside a region cost nothing when the region moves whole, and their
    # t-link shifts cancel in the region's unary sum.
    between = (tails != heads) & ((forward > 0.0) | (backward > 0.0))
    edges = merge_parallel_edges(
        tails[between], heads[between], forward[between], backward[between], count
    )
    return min_cut(unary, [edges])[labels]


def merge_parallel_edges(
    tails: NDArray[np.int64],
    heads: NDArray[np.int64],
    forward: NDArray[np.float64],
    backward: NDArray[np.float64],
    count: int,
) -> Edges:
    """One edge per pair of the ``count`` nodes: the pixel pairs along a border between
    two regions, each an edge ``tail -> head`` of capacity ``forward`` (``backward`` the
    other way), summed into one edge from the lower node to the higher. The cut is the
    same; the graph has 2-3x fewer edges on val-256 and cuts faster."""
    swap = tails > heads
    low, high = np.where(swap, heads, tails), np.where(swap, tails, heads)
    up, down = np.where(swap, backward, forward), np.where(swap, forward, backward)
    keys, index = np.unique(low * count + high, return_inverse=True)
    return (
        keys // count,
        keys % count,
        np.bincount(index, up, minlength=keys.size),
        np.bincount(index, down, minlength=keys.size),
    )
