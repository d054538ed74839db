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

A budgeted refinement (``auto`` at ``balanced``) runs its region moves to convergence
on one partition (:func:`region_descent`): the guide's regions stay the nodes, each
move cuts the regions the previous successful move changed and their neighbours, and
the moves stop when a wrap up and a wrap down both fail. Two region moves lift a
region by one wrap at most, and the nets under-count bright regions by several: on
val-256 crops with smooth bright glows added (:func:`models.scenes.glows`) auto-balanced
measured 44.20 dB against auto-best's 47.47, with the glows' cores three wraps short.
Measured (2026-11-26, mantissa, auto-balanced, two region moves -> converged): the
tuning crops of the training scenes 26.98 -> 27.39 dB (best 27.50), with glows 43.51
-> 44.43 dB (best 44.38), val-256 with glows 44.20 -> 47.31 dB; val-256 (24.02 dB) and
the mostly-dark set (45.59 dB) unchanged; about 10-15 ms more per val-256 frame.

Since 2026-11-26 (afternoon) a partition's border pairs are grouped into region edges
once (:class:`BorderEdges`) and the prior into (region, offset) groups
(:class:`PriorGroups`), so a cut over a few regions no longer touches every pixel:
the descent of auto-balanced took 47 -> 39 ms a frame on val-256 (mantissa, 8 frames)
and 8.0 -> 5.7 ms on the mostly-dark set, with the same W. On val-256 most of the
rest is the first three cuts: the guide's textured frames hold 24k-31k regions, nearly
all single pixels near residues (their pairs never link), and the first two cuts
move 6k-10k of them each. Linking the pairs near residues too (a lower
:data:`LINK_WEIGHT`; at 0 auto-balanced took 13-17% less time) lost 0.8-2.0 dB on the
tuning crops of the training scenes (at 0.2 / 0.05 / 0: mantissa 27.39 -> 26.08 /
25.71 / 25.36 dB, modulo 26.11 -> 25.31 / 25.08 / 24.73 dB), and leaving the single
pixels out of the descent (to the pixel moves) lost 0.3 dB there (mantissa) and saved
nothing, so neither is done.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from models.decoders.graphcut import (
    PairWeights,
    PumaEnergy,
    PumaResult,
    accepts,
    min_cut,
    move_terms,
    pair_capacities,
)

#: Neighbours are in one region when ``|u_j - u_i|`` is below this (wrap units): the
#: Itoh condition under the current K.
CONSISTENT_STEP = 0.5
#: ... and their pair's weight is above this: the codes decide the pair (it is not next
#: to a residue nor across a sharp step; see :func:`models.decoders.guided_puma.pair_weights`).
LINK_WEIGHT = 0.5
#: :func:`region_descent` cuts every region in its first this many moves; later moves
#: cut only the regions the last successful move changed and their neighbours.
FULL_MOVES = 2


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
    (a :data:`models.decoders.graphcut.MoveSolver`; :meth:`RegionGraph.best_move` on
    the regions of ``winding``, every one of them free to move)."""
    graph = RegionGraph(winding, m, energy)
    everything = np.ones(graph.count, bool)
    return graph.best_move(np.zeros(graph.count, np.int64), jump, everything)[graph.labels]


class BorderEdges:
    """The pixel pairs across region borders (pair ``k`` from region ``tails[k]`` to
    ``heads[k]``, ``count`` regions) grouped into one edge per pair of touching regions,
    from the lower region (``low``) to the higher (``high``). Summing a border's pairs
    into one edge gives the same cut on a graph with 2-3x fewer edges (val-256), which
    cuts faster; the grouping is made once per partition."""

    def __init__(self, tails: NDArray[np.int64], heads: NDArray[np.int64], count: int) -> None:
        self.swap = tails > heads
        low, high = np.where(self.swap, heads, tails), np.where(self.swap, tails, heads)
        keys, self.index = np.unique(low * count + high, return_inverse=True)
        self.low, self.high = keys // count, keys % count

    def merge(
        self, pairs: NDArray[np.bool_], forward: NDArray[np.float64], backward: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Capacities ``low -> high`` and ``high -> low`` of every edge, summed over the
        selected ``pairs`` (bool per pair) with capacities ``forward`` (tail -> head) and
        ``backward`` (one per selected pair); 0 on edges none of them lies on."""
        swap = self.swap[pairs]
        up, down = np.where(swap, backward, forward), np.where(swap, forward, backward)
        index, edges = self.index[pairs], self.low.size
        return np.bincount(index, up, minlength=edges), np.bincount(index, down, minlength=edges)


class PriorGroups:
    """The per-pixel terms of :class:`models.decoders.graphcut.PumaEnergy` (prior and
    bounds) over regions that move whole: the pixels grouped by (region, offset ``K -
    prior``, ``K``), each group with its pixel count and summed prior weight, so that a
    move's cost and the energy take one entry per group instead of one per pixel (a
    region of the guide's own W spans a few groups, one per wrap level in it)."""

    def __init__(
        self, winding: NDArray[np.int64], labels: NDArray[np.int64], energy: PumaEnergy
    ) -> None:
        self.energy = energy
        if energy.prior is None and energy.bounds is None:
            self.region = self.offset = self.level = np.zeros(0, np.int64)
            self.weight = self.count = np.zeros(0)
            return
        prior = np.zeros_like(winding) if energy.prior is None else energy.prior
        offset, level = (winding - prior).ravel(), winding.ravel()
        # Counted, not sorted: a key per (region, offset, K), few of them (offsets and K
        # span a few wraps), and an argsort of the pixels cost more than the cuts it saved.
        key = labels.ravel()
        lows = []
        for values in (offset, level):
            low = int(values.min())
            span = int(values.max()) - low + 1
            key = key * span + (values - low)
            lows.append((low, span))
        counts = np.bincount(key)
        keys = np.flatnonzero(counts)
        (offset_low, offset_span), (level_low, level_span) = lows
        self.level = keys % level_span + level_low
        self.offset = keys // level_span % offset_span + offset_low
        self.region = keys // (level_span * offset_span)
        self.count = counts[keys].astype(np.float64)
        weighed = 0.0 if energy.prior is None else energy.prior_weight  # no prior, no pull
        weights = np.broadcast_to(weighed, winding.shape).ravel()
        self.weight = np.bincount(key, weights)[keys]

    def _cost(self, groups: NDArray[np.bool_] | slice, moved: NDArray[np.int64]) -> NDArray:
        """Each of ``groups``' per-pixel terms, summed over its pixels, with its region
        moved by ``moved`` wraps (int per group)."""
        cost = self.weight[groups] * self.energy.prior_cost(self.offset[groups] + moved)
        if self.energy.bounds is None:
            return cost
        return cost + self.count[groups] * self.energy.bound_cost(self.level[groups] + moved)

    def energy_of(self, shift: NDArray[np.int64]) -> float:
        """The per-pixel terms with each region moved by its ``shift`` (int per region)."""
        return float(np.sum(self._cost(slice(None), shift[self.region])))

    def move_cost(
        self, shift: NDArray[np.int64], jump: int, active: NDArray[np.bool_]
    ) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        """The ``active`` regions' groups (region per group) and each one's change of the
        per-pixel terms if its region's shift grows by ``jump``."""
        groups = active[self.region]
        region = self.region[groups]
        moved = shift[region]
        return region, self._cost(groups, moved + jump) - self._cost(groups, moved)


class RegionGraph:
    """A frame's consistent regions (:func:`consistent_regions` of ``winding + m``) as
    the nodes of PUMA's moves, on a partition fixed for all of them: each region moves
    by a whole number of wraps (``shift``, int per region). Pairs inside a region never
    change, so only the pixel pairs across borders (:class:`BorderEdges`) and the prior
    by region (:class:`PriorGroups`) are kept: a cut restricted to a few regions costs
    in proportion to their borders, not to the frame."""

    def __init__(self, winding: NDArray[np.int64], m: NDArray[np.float64], energy: PumaEnergy):
        self.winding, self.energy = winding, energy
        u = winding + m
        self.count, self.labels = consistent_regions(u, energy.weights)
        labels = self.labels
        tails = np.concatenate([labels[:, :-1].ravel(), labels[:-1].ravel()])
        heads = np.concatenate([labels[:, 1:].ravel(), labels[1:].ravel()])
        diffs = np.concatenate([np.diff(u, axis=1).ravel(), np.diff(u, axis=0).ravel()])
        if energy.weights is None:
            weights = np.ones(diffs.size)
        else:
            weights = np.concatenate([energy.weights[0].ravel(), energy.weights[1].ravel()])
        across = (tails != heads) & (weights > 0.0)
        self.tails, self.heads = tails[across], heads[across]
        self.diffs, self.weights = diffs[across], weights[across]
        self.edges = BorderEdges(self.tails, self.heads, self.count)
        self.prior = PriorGroups(winding, labels, energy)

    def moved(self, shift: NDArray[np.int64]) -> NDArray[np.int64]:
        """The frame's W (H x W) with each region moved by its ``shift``."""
        return self.winding + shift[self.labels]

    def energy_of(self, shift: NDArray[np.int64]) -> float:
        """The PUMA energy of :meth:`moved` up to a constant (the pairs inside regions)."""
        d = self.diffs + shift[self.heads] - shift[self.tails]
        pairs = float(np.sum(self.weights * np.abs(d) ** self.energy.p))
        return pairs + self.prior.energy_of(shift)

    def neighbours(self, regions: NDArray[np.bool_]) -> NDArray[np.bool_]:
        """``regions`` (bool per region) and every region that shares a border with one."""
        grown = regions.copy()
        grown[self.heads[regions[self.tails]]] = True
        grown[self.tails[regions[self.heads]]] = True
        return grown

    def best_move(
        self, shift: NDArray[np.int64], jump: int, active: NDArray[np.bool_]
    ) -> NDArray[np.bool_]:
        """The regions (bool per region) whose shift should grow by ``jump``, among the
        ``active`` ones (the others stay; their pairs with active regions become the
        active ones' unary terms): one min-cut."""
        moved = np.zeros(self.count, bool)
        nodes = int(active.sum())
        if nodes == 0:
            return moved
        node = np.full(self.count, -1, np.int64)
        node[active] = np.arange(nodes)
        near = active[self.tails] | active[self.heads]
        tails, heads = node[self.tails[near]], node[self.heads[near]]
        d = self.diffs[near] + shift[self.heads[near]] - shift[self.tails[near]]
        c, w = move_terms(d, jump, self.energy.p)
        c, w = c * self.weights[near], w * self.weights[near]
        # A pair's energy: A + c (tail moves) - c (head moves) + w (only the head moves).
        both = (tails >= 0) & (heads >= 0)
        tail_only, head_only = (tails >= 0) & ~both, (heads >= 0) & ~both
        forward, backward, pair_shift = pair_capacities(c[both], w[both])
        groups, prior = self.prior.move_cost(shift, jump, active)
        unary = (
            np.bincount(node[groups], prior, minlength=nodes)
            + np.bincount(tails[tail_only], c[tail_only], minlength=nodes)
            + np.bincount(heads[head_only], (w - c)[head_only], minlength=nodes)
            + np.bincount(tails[both], pair_shift, minlength=nodes)
            - np.bincount(heads[both], pair_shift, minlength=nodes)
        )
        pairs = near.copy()
        pairs[near] = both
        up, down = self.edges.merge(pairs, forward, backward)
        kept = active[self.edges.low] & active[self.edges.high]
        edges = (node[self.edges.low[kept]], node[self.edges.high[kept]], up[kept], down[kept])
        moved[active] = min_cut(unary, [edges])
        return moved


def region_descent(
    winding: NDArray[np.int64],
    m: NDArray[np.float64],
    energy: PumaEnergy,
    jumps: tuple[int, ...],
    max_moves: int,
) -> PumaResult:
    """PUMA's moves of whole regions (:class:`RegionGraph`) from ``winding``, the jump
    sizes tried in turn, until every jump size in a row failed or ``max_moves`` cuts:
    the first :data:`FULL_MOVES` cut every region, the later ones the regions the last
    successful move changed and their neighbours (module doc); where such a cut moves
    nothing, moving every region (a change of the prior term only) is tried instead."""
    graph = RegionGraph(winding, m, energy)
    shift = np.zeros(graph.count, np.int64)
    energies = [graph.energy_of(shift)]
    changed = np.zeros(graph.count, bool)
    moves = failed = 0
    while failed < len(jumps) and moves < max_moves:
        active = np.ones(graph.count, bool) if moves < FULL_MOVES else graph.neighbours(changed)
        if not active.any():
            break
        jump = jumps[moves % len(jumps)]
        moves += 1
        moved = graph.best_move(shift, jump, active)
        if not moved.any() and not active.all():
            # Moving every region changes the prior only; a restricted cut cannot.
            moved = np.ones(graph.count, bool)
        candidate = shift + jump * moved.astype(np.int64)
        value = graph.energy_of(candidate)
        if not accepts(value, energies[-1]):
            failed += 1
            continue
        failed = 0
        changed = changed | moved if moves <= FULL_MOVES else moved
        shift = candidate
        energies.append(value)
    return PumaResult(graph.moved(shift), energies, moves)
