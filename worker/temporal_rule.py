"""The per-pixel temporal rule: each pixel's W predicted from the previous frame's ``u``.

``W_t = round(u_{t-1} - m_t)`` is exact when the pixel's true change is below half a
wrap. A pixel is *safe* (keeps this answer) when every previous value within
``motion_radius`` px predicts the same W with ``margin`` wraps to spare, or when its
whole window barely changed (``still``). :mod:`worker.temporal` describes the rule,
what decides the unsafe pixels and its failure modes; this module computes the
prediction, its safety and the range of W that motion allows.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from worker.motion import misfit

if TYPE_CHECKING:
    from worker.temporal_config import TemporalConfig


@dataclass(frozen=True)
class Prediction:
    """The temporal answer for a frame (arrays H x W x C, or H x W for one channel).

    ``winding``: ``round(u_{t-1} - m_t)``; ``safe``: where it is kept; ``lo`` / ``hi``:
    the least / greatest previous ``u`` within ``motion_radius``; ``m``: the frame;
    ``change``: ``|W_t + m_t - u_{t-1}|`` of the pixel itself (wraps); ``steady``: where
    that change is within the sensor's noise (``steady_sigmas`` sigmas of it), so the
    pixel's own answer is as good as the codes can tell.
    """

    winding: NDArray[np.int64]
    safe: NDArray[np.bool_]
    lo: NDArray[np.float64]
    hi: NDArray[np.float64]
    m: NDArray[np.float64]
    change: NDArray[np.float64]
    steady: NDArray[np.bool_]

    def channel(self, c: int) -> Prediction:
        """The prediction of channel ``c`` (H x W arrays)."""
        return Prediction(*(part[:, :, c] for part in self._parts()))

    def crop(self, index: Any) -> Prediction:
        """The prediction at ``index`` (a boolean mask or an index tuple of the arrays)."""
        return Prediction(*(part[index] for part in self._parts()))

    def _parts(self) -> tuple[NDArray[Any], ...]:
        return (self.winding, self.safe, self.lo, self.hi, self.m, self.change, self.steady)

    def bounds(self) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """The range of W that motion within ``motion_radius`` allows: ``W + m`` within
        half a wrap of ``[lo, hi]`` (W >= 0); a fallback answer is clipped into it."""
        lowest = np.ceil(self.lo - 0.5 - self.m)
        highest = np.maximum(np.floor(self.hi + 0.5 - self.m), 0)
        return lowest.astype(np.int64), highest.astype(np.int64)


def _edge_padded(values: NDArray, radius: int, axis: int) -> NDArray:
    """``values`` with its first / last ``radius`` lines along ``axis`` repeated outwards."""
    first = np.take(values, [0] * radius, axis=axis)
    last = np.take(values, [values.shape[axis] - 1] * radius, axis=axis)
    return np.concatenate([first, values, last], axis=axis)


def window_extreme(values: NDArray[np.float64], radius: int, pick: np.ufunc) -> NDArray:
    """Min or max (``pick``) over the ``(2r+1)^2`` window of each pixel of an H x W x C
    array, edges repeated (separable, by shifted slices: cheaper than a filter call)."""
    out = values
    for axis in (0, 1):
        size = out.shape[axis]
        padded = _edge_padded(out, radius, axis)
        lines = [slice(None)] * padded.ndim
        for start in range(2 * radius + 1):
            lines[axis] = slice(start, start + size)
            out = padded[tuple(lines)] if start == 0 else pick(out, padded[tuple(lines)])
    return out


#: ``hi`` of pixels nothing predicts (content entering the frame): no upper bound on W.
UNBOUNDED = 2.0**40


def temporal_prediction(
    m: NDArray[np.float64],
    prev_u: NDArray[np.float64],
    config: TemporalConfig,
    inside: NDArray[np.bool_] | None = None,
    noise: float = 0.0,
) -> Prediction:
    """Predict W of the frame ``m`` (H x W x C) from the previous ``u`` moved onto it
    (see module doc); pixels outside ``inside`` (H x W) are unpredicted: unsafe, unbounded.
    ``noise``: the sigma (wraps) that sensor noise gives a pixel's frame-to-frame change
    (0: none, only an unchanged pixel is steady)."""
    winding = np.rint(prev_u - m)
    u = winding + m
    change = misfit(prev_u, m)
    limit = 0.5 - config.margin
    safe = change <= limit
    steady = change <= config.steady_sigmas * noise
    lo, hi = prev_u, prev_u
    if config.motion_radius > 0:
        lo = window_extreme(prev_u, config.motion_radius, np.minimum)
        hi = window_extreme(prev_u, config.motion_radius, np.maximum)
        still = window_extreme(change, config.motion_radius, np.maximum) <= config.still
        safe &= still | ((u - lo <= limit) & (hi - u <= limit))
    if inside is not None and not inside.all():
        # Set in place on the few pixels outside (the strip a pan brings in): 0.2 ms a
        # frame less than five whole-frame ``where``s (2026-11-27, 256x256).
        outside = np.nonzero(~inside)
        lo, hi = lo.copy() if lo is prev_u else lo, hi.copy() if hi is prev_u else hi
        safe[outside], steady[outside] = False, False
        lo[outside], hi[outside], change[outside] = 0.0, UNBOUNDED, 0.5
    return Prediction(winding.astype(np.int64), safe, lo, hi, m, change, steady)
