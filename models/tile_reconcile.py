"""Stitch per-tile relative winding maps into one globally consistent W.

Each tile's winding map is known only up to an integer offset (a classical
unwrapper anchors each tile on its own; a tile with no wrap edge is constant).
Across every border between two tiles, the stored values tell what W should do
(:func:`models.scene_analysis.neighbour_jumps`: ``W_q - W_p = -jump``), so each
pair of border pixels votes for the offset between the two tiles. We keep the
most common vote per border and fix offsets along a maximum spanning tree of
the tile graph, the borders with the most votes beyond their dissent first, so one
bad border (or a border of a few pixels) cannot spoil the rest. W is global: tiles
are reconciled, never blended.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

#: Values (per value counted) a span may hold for :func:`most_common` to count them in a
#: histogram: a wider span is sorted instead, which costs O(n log n) but no memory beyond n.
HISTOGRAM_SPAN = 64


@dataclass(frozen=True)
class Tile:
    """A tile's place in the frame (``rows`` and ``cols`` slices) and its relative W."""

    rows: slice
    cols: slice
    winding: NDArray[np.int64]


@dataclass(frozen=True)
class _Border:
    """The offset vote between tiles ``a`` and ``b``: ``offset_b - offset_a = delta``."""

    a: int
    b: int
    delta: int
    support: float


def most_common(values: NDArray[np.int64]) -> tuple[int, float]:
    """The smallest of the most common integers in ``values``, and its share of them.
    Counted in a histogram (:func:`np.bincount`) when they span at most
    :data:`HISTOGRAM_SPAN` values per value, else by sorting (:func:`np.unique`): a
    stream's tracked W and a spatial W can differ by 5e9 wraps (mantissa, alpha 1 +
    1.6e-11, where a 0.02-stop gain moves u by 9e8 wraps), whose histogram took 39 GiB."""
    flat = values.ravel()
    lowest = int(flat.min())
    if int(flat.max()) - lowest <= HISTOGRAM_SPAN * flat.size:
        counts = np.bincount(flat - lowest)
        best = int(np.argmax(counts))
        return best + lowest, float(counts[best] / flat.size)
    distinct, counts = np.unique(flat, return_counts=True)
    best = int(np.argmax(counts))
    return int(distinct[best]), float(counts[best] / flat.size)


def common_offset(target: NDArray[np.int64], relative: NDArray[np.int64]) -> int:
    """The most common ``target - relative``: the integer that aligns a W known up to a
    constant (``relative``) with ``target`` on the same pixels."""
    return most_common(target - relative)[0]


def _border_vote(
    left: NDArray[np.int64], right: NDArray[np.int64], jumps: NDArray[np.int64]
) -> tuple[int, float]:
    """Most common implied offset between two facing pixel lines, and its support: the
    votes for it beyond all the others. (Its share of the votes put a 1-pixel border's
    single vote level with a 64-pixel border's unanimous one: a frame one pixel past a
    multiple of the tile size took a wrong vote at a residue first and set half the
    frame a wrap off.)"""
    votes = left - jumps - right
    delta, share = most_common(votes)
    return delta, (2.0 * share - 1.0) * votes.size


def _borders(
    tiles: list[Tile],
    along_cols: NDArray[np.int64],
    along_rows: NDArray[np.int64],
) -> list[_Border]:
    """Offset votes across every shared edge of two tiles (4-neighbour pairs)."""
    by_corner = {(t.rows.start, t.cols.start): i for i, t in enumerate(tiles)}
    borders: list[_Border] = []
    for i, tile in enumerate(tiles):
        right = by_corner.get((tile.rows.start, tile.cols.stop))
        if right is not None:
            c = tile.cols.stop - 1
            delta, support = _border_vote(
                tile.winding[:, -1], tiles[right].winding[:, 0], along_cols[tile.rows, c]
            )
            borders.append(_Border(i, right, delta, support))
        below = by_corner.get((tile.rows.stop, tile.cols.start))
        if below is not None:
            r = tile.rows.stop - 1
            delta, support = _border_vote(
                tile.winding[-1, :], tiles[below].winding[0, :], along_rows[r, tile.cols]
            )
            borders.append(_Border(i, below, delta, support))
    return borders


def tile_offsets(
    tiles: list[Tile], along_cols: NDArray[np.int64], along_rows: NDArray[np.int64]
) -> list[int]:
    """Integer offset per tile making borders agree (the first tile of each component: 0)."""
    adjacency: dict[int, list[tuple[float, int, int]]] = {i: [] for i in range(len(tiles))}
    for border in _borders(tiles, along_cols, along_rows):
        adjacency[border.a].append((border.support, border.b, border.delta))
        adjacency[border.b].append((border.support, border.a, -border.delta))
    offsets: list[int | None] = [None] * len(tiles)
    for root in range(len(tiles)):
        if offsets[root] is not None:
            continue
        offsets[root] = 0
        frontier = [(-support, root, nxt, delta) for support, nxt, delta in adjacency[root]]
        heapq.heapify(frontier)
        while frontier:
            _, src, dst, delta = heapq.heappop(frontier)
            if offsets[dst] is not None:
                continue
            offsets[dst] = offsets[src] + delta
            for support, nxt, d in adjacency[dst]:
                if offsets[nxt] is None:
                    heapq.heappush(frontier, (-support, dst, nxt, d))
    return [int(o) for o in offsets if o is not None]


def stitch(
    tiles: list[Tile],
    shape: tuple[int, int],
    along_cols: NDArray[np.int64],
    along_rows: NDArray[np.int64],
) -> NDArray[np.int64]:
    """One relative W map (H x W) from non-overlapping tiles covering the frame."""
    winding = np.zeros(shape, np.int64)
    for tile, offset in zip(tiles, tile_offsets(tiles, along_cols, along_rows), strict=True):
        winding[tile.rows, tile.cols] = tile.winding + offset
    return winding


def integrate_jumps(
    along_cols: NDArray[np.int64], along_rows: NDArray[np.int64]
) -> NDArray[np.int64]:
    """Relative W by path integration of the jumps (down the first column, then along rows).

    Exact (path independent) where the region has no residue.
    """
    first_col = np.concatenate([[0], -np.cumsum(along_rows[:, 0])])
    rows = np.concatenate([np.zeros((along_cols.shape[0], 1), np.int64), -along_cols], axis=1)
    return first_col[:, None] + np.cumsum(rows, axis=1)
