"""Keyframe merging: per region, keep the tracked or the spatial winding numbers.

At a periodic keyframe both a tracked (temporal) answer and a fresh spatial one
exist. Replacing the tracked answer wholesale throws away regions the spatial
decoder gets wrong (a least-squares decoder shifts whole regions by a wrap around
steep content); keeping it keeps the tracked errors. So the pixels where the two
disagree are split into 4-connected regions, and each region takes the answer
that makes fewer *jumps* (neighbouring ``u`` more than half a wrap apart) across
its boundary with the pixels around it, taken as tracked. A region the spatial
decoder got wrong is bounded by jumps it created; a region the tracking got wrong
is bounded by the jumps of its wrong wrap. Ties keep the tracked answer.

Failure modes: a real edge steeper than half a wrap along a region's boundary
counts as a jump for either answer (it can tip a vote the wrong way); two
adjacent regions are each judged against the other's tracked answer.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage


def _jumps(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """1.0 where ``a`` and ``b`` (u, wraps) are more than half a wrap apart, else 0.0."""
    return (np.abs(a - b) > 0.5).astype(np.float64)


def region_vote(
    tracked: NDArray[np.int64],
    spatial: NDArray[np.int64],
    m: NDArray[np.float64],
    eligible: NDArray[np.bool_] | None = None,
) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
    """Merge one channel's tracked and spatial W (H x W) region by region (module doc);
    with ``eligible`` (H x W), only regions that touch an eligible pixel may switch.

    Returns the merged W and where the spatial answer was taken.
    """
    differ = tracked != spatial
    if not differ.any():
        return tracked, differ
    labels, count = ndimage.label(differ)
    u_tracked, u_spatial = tracked + m, spatial + m
    votes = np.zeros(count + 1)
    for axis in (0, 1):
        near = [slice(None)] * 2
        far = [slice(None)] * 2
        near[axis], far[axis] = slice(None, -1), slice(1, None)
        pair = (tuple(near), tuple(far))
        for side, other in (pair, pair[::-1]):
            own, across = labels[side], labels[other]
            boundary = own != across
            gain = _jumps(u_tracked[side], u_tracked[other]) - _jumps(
                u_spatial[side], u_tracked[other]
            )
            votes += np.bincount(own[boundary], weights=gain[boundary], minlength=count + 1)
    take = votes > 0
    take[0] = False
    if eligible is not None:
        take &= np.bincount(labels[eligible], minlength=count + 1) > 0
    taken = take[labels]
    return np.where(taken, spatial, tracked), taken
