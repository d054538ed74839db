"""The fallbacks of temporal decoding for pixels the temporal rule leaves unsafe.

:mod:`worker.temporal` describes when each is used: the *local* path
(:func:`neighbour_fix`: each unsafe pixel takes the W that best matches a settled
8-neighbour, or keeps its own temporal answer when that is close or *steady*) and the
*spatial* path (:func:`merge_spatial`: a full spatial decode aligned to the tracked
answer by :func:`models.tile_reconcile.common_offset`, winning where it is
:func:`locally_smooth` and the tracked answer is not). Arrays are one channel,
H x W; ``u`` and ``m`` in wraps.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from models.tile_reconcile import common_offset
from worker.temporal_rule import Prediction


def locally_smooth(u: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Pixels (H x W) whose ``u`` is within half a wrap of each 4-neighbour."""
    smooth = np.ones(u.shape, bool)
    step_y = np.abs(np.diff(u, axis=0)) < 0.5
    step_x = np.abs(np.diff(u, axis=1)) < 0.5
    smooth[1:] &= step_y
    smooth[:-1] &= step_y
    smooth[:, 1:] &= step_x
    smooth[:, :-1] &= step_x
    return smooth


def merge_spatial(
    prediction: Prediction, spatial: NDArray[np.int64]
) -> tuple[NDArray[np.int64], NDArray[np.bool_]] | None:
    """Combine one channel's temporal and spatial W (H x W) as the module doc says.

    Returns the merged W and where the spatial answer was taken, or None when no
    pixel is safe (nothing to align the spatial constant to).
    """
    temporal, safe = prediction.winding, prediction.safe
    if not safe.any():
        return None
    aligned = spatial + common_offset(temporal[safe], spatial[safe])
    aligned = np.clip(aligned, *prediction.bounds())
    m = prediction.m
    confident = locally_smooth(aligned + m) & ~locally_smooth(temporal + m)
    take = ~safe | ((temporal != aligned) & confident)
    return np.where(take, aligned, temporal), take


#: The pixel's own temporal answer competes with its neighbours at this many times its
#: change (a neighbour must match more than twice as well to overrule it).
SELF_WEIGHT = 2.0
_NEIGHBOURS = [(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx]


def _best_neighbour(
    u: NDArray[np.float64],
    settled: NDArray[np.bool_],
    sources: NDArray[np.int64],
    m: NDArray[np.float64],
    lowest: NDArray[np.int64],
    highest: NDArray[np.int64],
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """For each open pixel (``m``, wraps, and its W range ``lowest`` to ``highest``), the
    W (clipped into its range) that brings its ``u`` closest to a settled neighbour's
    and that distance (wraps; inf where no neighbour is settled). ``sources``: the
    neighbours' flat indices into the padded ``u`` and ``settled`` (8 x open pixels,
    in :data:`_NEIGHBOURS` order: ties go to the first). All 8 neighbours at once: a
    pan/zoom frame's fix took 0.6 ms looping over them."""
    other = u[sources]
    candidate = np.clip(np.rint(other - m), lowest, highest)
    distance = np.where(settled[sources], np.abs(other - candidate - m), np.inf)
    nearest = np.argmin(distance, axis=0)[None]
    best = np.take_along_axis(distance, nearest, 0)[0]
    return best, np.take_along_axis(candidate, nearest, 0)[0].astype(np.int64)


def neighbour_fix(prediction: Prediction, passes: int) -> NDArray[np.int64]:
    """One channel's W with its unsafe pixels set from their best-matching settled
    8-neighbour or their own temporal answer (see module doc); pixels no settled
    neighbour reaches keep the temporal answer."""
    winding = prediction.winding.copy()
    width = winding.shape[1] + 2
    settled = np.pad(prediction.safe, 1).ravel()
    u = np.pad(winding + prediction.m, 1).ravel()
    rows, cols = np.nonzero(~prediction.safe)
    unsafe = prediction.crop((rows, cols))
    lowest, highest = unsafe.bounds()
    m_open = unsafe.m
    where = (rows + 1) * width + cols + 1
    offsets = np.array([dy * width + dx for dy, dx in _NEIGHBOURS])[:, None]
    own_cost = np.where(unsafe.steady, 0.0, SELF_WEIGHT * unsafe.change)
    own = unsafe.winding
    for _ in range(passes):
        best, choice = _best_neighbour(u, settled, where + offsets, m_open, lowest, highest)
        done = np.isfinite(best)
        choice = np.where(done & (own_cost <= best), own, choice)
        u[where[done]] = choice[done] + m_open[done]
        settled[where[done]] = True
        winding.ravel()[where[done] - width - 1 - 2 * (where[done] // width - 1)] = choice[done]
        keep = ~done
        if not keep.any() or keep.all():
            break
        where, lowest, highest, m_open = where[keep], lowest[keep], highest[keep], m_open[keep]
        own_cost, own = own_cost[keep], own[keep]
    return winding
