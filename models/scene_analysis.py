"""Cheap per-frame and per-tile analysis of a wrapped frame: how hard is it to unwrap?

It looks only at the stored values ``m`` in [0, 1) (wrap units):

- a *wrap edge* is a pair of 4-neighbours whose stored values jump by more than
  half a wrap; with the Itoh condition (true neighbour changes below half a wrap)
  that is exactly where ``W`` changes, by ``-round(m_b - m_a)``;
- a *residue* is a 2x2 loop whose implied integer jumps do not sum to zero. Where
  there are none, integrating the implied jumps is path independent, so every
  classical unwrapper (path following, Itoh's least squares) agrees on one
  answer; residues mark where the Itoh condition certainly fails;
- the encoding, bits and ``max_wraps`` give an upper bound on ``W``.

A frame with no wrap edges has one constant ``W`` (0 by the anchoring rule). The
analysis costs a few array passes (about a millisecond at 256x256).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from models.decoders.base import refuse_empty
from models.formation import SensorParams, max_winding

Difficulty = Literal["none", "smooth", "sparse", "dense"]
#: Edge density (wrap edges per neighbour pair) above which a tile counts as dense.
DENSE_EDGE_DENSITY = 0.02


@dataclass(frozen=True)
class RegionAnalysis:
    """Unwrapping difficulty of a rectangle ``[row:row+height, col:col+width]`` of a frame.

    ``difficulty``: ``none`` (no wrap edge: one constant W), ``smooth`` (edges but
    no residue: classical integration is consistent), ``sparse`` (a few residues),
    ``dense`` (residues and an edge density above :data:`DENSE_EDGE_DENSITY`).
    """

    row: int
    col: int
    height: int
    width: int
    wrap_edges: int
    edge_density: float
    residues: int

    @property
    def difficulty(self) -> Difficulty:
        if self.residues:  # a tile's edges on its border count in no tile; its loops do
            return "dense" if self.edge_density > DENSE_EDGE_DENSITY else "sparse"
        return "smooth" if self.wrap_edges else "none"


@dataclass(frozen=True)
class FrameAnalysis:
    """The whole frame's figures, its tiles, the bound on W (None if unbounded), and the
    neighbour jumps they were computed from (see :func:`neighbour_jumps`)."""

    frame: RegionAnalysis
    tiles: tuple[RegionAnalysis, ...]
    max_winding: int | None
    along_cols: NDArray[np.int64]
    along_rows: NDArray[np.int64]

    @property
    def itoh_likely(self) -> bool:
        """No residue anywhere: classical unwrapping is self-consistent on this frame."""
        return self.frame.residues == 0


def neighbour_jumps(m: NDArray[np.floating]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Integer wrap jumps ``round(m_next - m)`` along columns (axis 1) and rows (axis 0).

    Under the Itoh condition ``W_next - W = -jump``; a non-zero jump is a wrap edge.
    """
    m = np.asarray(m, dtype=np.float64)
    along_cols = np.rint(np.diff(m, axis=1)).astype(np.int64)
    along_rows = np.rint(np.diff(m, axis=0)).astype(np.int64)
    return along_cols, along_rows


def residue_map(
    along_cols: NDArray[np.int64], along_rows: NDArray[np.int64]
) -> NDArray[np.int64]:
    """Circulation of the jumps around each 2x2 loop, shape (H-1, W-1); non-zero = residue."""
    return along_cols[:-1, :] + along_rows[:, 1:] - along_cols[1:, :] - along_rows[:, :-1]


def has_residue(m: NDArray[np.floating]) -> bool:
    """Whether any 2x2 loop of ``m`` (H x W, wraps) is a residue (:func:`residue_map`):
    without one, integrating the neighbour jumps is exact and a learned decoder does not
    run its net (:meth:`models.decoders.learned.LearnedDecoder.explain_winding`)."""
    return bool(residue_map(*neighbour_jumps(m)).any())


def residue_pixels(m: NDArray[np.float64], reach: int) -> NDArray[np.bool_]:
    """Pixels (H x W) within ``reach`` pixels of a residue's 2x2 loop of ``m`` (wraps)."""
    loops = residue_map(*neighbour_jumps(m)) != 0
    near = np.zeros(m.shape, bool)
    for rows in (slice(None, -1), slice(1, None)):
        for cols in (slice(None, -1), slice(1, None)):
            near[rows, cols] |= loops
    return cross_dilation(near, reach) if near.any() else near


def cross_dilation(mask: NDArray[np.bool_], iterations: int) -> NDArray[np.bool_]:
    """``mask`` (bool, H x W) grown ``iterations`` times by its 4-neighbours: for
    ``iterations >= 1`` what ``scipy.ndimage.binary_dilation(mask, iterations=iterations)``
    gives (its default cross, nothing beyond the border), by shifted slices; 0 returns
    ``mask`` itself (scipy's 0 grows it until it no longer changes). On 256x256 masks
    (2026-11-27, AMD EPYC) one step took 0.02 ms against scipy's 0.3-0.6 ms, two 0.03
    against 0.3-1.0."""
    out = mask
    for _ in range(iterations):
        grown = out.copy()
        grown[1:] |= out[:-1]
        grown[:-1] |= out[1:]
        grown[:, 1:] |= out[:, :-1]
        grown[:, :-1] |= out[:, 1:]
        out = grown
    return out


def _region(
    row: int,
    col: int,
    along_cols: NDArray[np.int64],
    along_rows: NDArray[np.int64],
    residues: NDArray[np.int64],
    shape: tuple[int, int],
) -> RegionAnalysis:
    edges = int(np.count_nonzero(along_cols)) + int(np.count_nonzero(along_rows))
    pairs = along_cols.size + along_rows.size
    return RegionAnalysis(
        row=row,
        col=col,
        height=shape[0],
        width=shape[1],
        wrap_edges=edges,
        edge_density=edges / pairs if pairs else 0.0,
        residues=int(np.count_nonzero(residues)),
    )


def analyse(m: NDArray[np.floating], params: SensorParams, tile: int = 64) -> FrameAnalysis:
    """Analyse one channel of stored values ``m`` (H x W, wrap units) in ``tile``-pixel tiles.

    Each tile's figures count the neighbour pairs inside it and the 2x2 loops that touch
    it: a residue on the border between tiles counts in each (in none, the tiles each
    side were integrated, and the frame routed, as if it were not there). A frame
    without pixels is refused (:func:`models.decoders.base.refuse_empty`).
    """
    m = np.asarray(m, dtype=np.float64)
    if m.ndim != 2:
        raise ValueError(f"analyse takes one channel (H x W), got shape {m.shape}")
    refuse_empty(m)
    if tile < 2:
        raise ValueError(f"tile must be at least 2 pixels, got {tile}")
    along_cols, along_rows = neighbour_jumps(m)
    residues = residue_map(along_cols, along_rows)
    height, width = m.shape
    tiles = tuple(
        _region(
            r,
            c,
            along_cols[r : r + tile, c : c + tile - 1],
            along_rows[r : r + tile - 1, c : c + tile],
            residues[max(r - 1, 0) : r + tile, max(c - 1, 0) : c + tile],
            (min(tile, height - r), min(tile, width - c)),
        )
        for r in range(0, height, tile)
        for c in range(0, width, tile)
    )
    frame = _region(0, 0, along_cols, along_rows, residues, (height, width))
    return FrameAnalysis(
        frame=frame,
        tiles=tiles,
        max_winding=max_winding(params),
        along_cols=along_cols,
        along_rows=along_rows,
    )
