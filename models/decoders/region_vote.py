"""Merging two W answers region by region: keep one, or take the other's.

Where two decoders disagree, replacing one answer wholesale keeps the other's
errors. So the pixels where ``kept`` and ``candidate`` disagree are split into
4-connected regions, and each region takes the answer that makes fewer *jumps*
(neighbouring ``u`` more than half a wrap apart) across its boundary with the
pixels around it, taken as ``kept``. A region ``candidate`` got wrong is bounded by
jumps it created; a region ``kept`` got wrong is bounded by the jumps of its wrong
wrap. Ties keep ``kept``.

Uses: a temporal keyframe merges the tracked answer (kept) with a fresh spatial one
(:mod:`worker.temporal`, :mod:`worker.crop_vote`); ``auto`` at quality ``fast``
checks a network's small regions against ``itoh`` (:mod:`models.decoders.adaptive`,
``max_region``: a jump count favours the smoothest answer, right for a network's
small false wraps on a dark frame but not for large regions bounded by steep true
edges, where the network's context is the better evidence). A larger region switches
only on a *decisive* vote: the candidate jumps on at most :data:`DECISIVE_CANDIDATE`
of its border and the kept answer on at least :data:`DECISIVE_KEPT` (a smooth lamp's
core that a network left wraps short, ringed by its own jumps, which ``itoh``
integrates exactly). Measured (auto-fast, mean PSNR, 2026-11-28): the glows set 48.48
-> 52.24 dB; val-256 (read noise 0 and 0.01, both encodings), the mostly-dark set and
three synthetic 512x512 frames unchanged to 0.001 dB; thresholds of 0.1 / 0.3
(candidate / kept) gave the same.

Failure modes: a real edge steeper than half a wrap along a region's boundary
counts as a jump for either answer (it can tip a vote the wrong way); two
adjacent regions are each judged against the other's ``kept`` answer.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

#: A region larger than ``max_region`` takes the candidate only if the candidate jumps
#: on at most this share of its border...
DECISIVE_CANDIDATE = 0.05
#: ...and the kept answer on at least this share (module doc).
DECISIVE_KEPT = 0.5


def _jumps(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.int64]:
    """1 where ``a`` and ``b`` (u, wraps) are more than half a wrap apart, else 0."""
    return (np.abs(a - b) > 0.5).astype(np.int64)


def border_jumps(
    labels: NDArray[np.int32], count: int, u_kept: NDArray[np.float64],
    u_candidate: NDArray[np.float64],
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
    """Per label (0..count): the kept answer's jumps across the region's border, the
    candidate's (each side against the neighbour's kept ``u``, wraps) and the border's
    length (neighbour pairs)."""
    kept_jumps, candidate_jumps, length = (np.zeros(count + 1, np.int64) for _ in range(3))
    for near, far in (
        ((slice(None, -1), slice(None)), (slice(1, None), slice(None))),
        ((slice(None), slice(None, -1)), (slice(None), slice(1, None))),
    ):
        boundary = labels[near] != labels[far]
        own = (labels[near][boundary], labels[far][boundary])
        kept_u = (u_kept[near][boundary], u_kept[far][boundary])
        candidate_u = (u_candidate[near][boundary], u_candidate[far][boundary])
        for side, other in ((0, 1), (1, 0)):
            for total, weights in (
                (kept_jumps, _jumps(kept_u[side], kept_u[other])),
                (candidate_jumps, _jumps(candidate_u[side], kept_u[other])),
                (length, None),
            ):
                total += np.bincount(own[side], weights=weights, minlength=count + 1).astype(
                    np.int64
                )
    return kept_jumps, candidate_jumps, length


def region_vote(
    kept: NDArray[np.int64],
    candidate: NDArray[np.int64],
    m: NDArray[np.float64],
    eligible: NDArray[np.bool_] | None = None,
    max_region: int | None = None,
) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
    """Merge one channel's ``kept`` and ``candidate`` W (H x W) region by region (module
    doc). With ``eligible`` (H x W), only regions that touch an eligible pixel may
    switch; with ``max_region``, regions of more pixels only on a decisive vote.

    Returns the merged W and where the candidate's answer was taken.
    """
    differ = kept != candidate
    if not differ.any():
        return kept, differ
    labels, count = ndimage.label(differ)
    kept_jumps, candidate_jumps, length = border_jumps(labels, count, kept + m, candidate + m)
    take = kept_jumps > candidate_jumps
    take[0] = False
    if eligible is not None:
        take &= np.bincount(labels[eligible], minlength=count + 1) > 0
    if max_region is not None:
        decisive = (candidate_jumps <= DECISIVE_CANDIDATE * length) & (
            kept_jumps >= DECISIVE_KEPT * length
        )
        take &= (np.bincount(labels.ravel(), minlength=count + 1) <= max_region) | decisive
    taken = take[labels]
    return np.where(taken, candidate, kept), taken
