"""Motion compensation for temporal unwrapping: the previous ``u`` moved onto this frame.

The temporal rule ``W_t = round(u_{t-1} - m_t)`` (:mod:`worker.temporal`) compares a
pixel with the *same* pixel of the previous frame. On a pan or zoom the content
moves by pixels per frame, so at moving edges that comparison sees other content
and can be off by a wrap. This module finds where each block's content came from
and resamples the previous ``u`` there, so the rule compares like with like.

Matching cost
-------------
Blocks are matched on *texture*: the sum of each pixel's differences to its right
and lower neighbours (:func:`texture`), exact from the previous ``u``, wrapped
(:func:`models.decoders.classical.wrap_difference`) from the current ``m``. A
brightness change that adds the same amount to ``u`` across a block (a sunrise,
for the mantissa encoding) leaves texture unchanged, so it is not mistaken for
motion, as matching ``m`` itself would (a shift along a gradient mimics an offset).
The cost of a displacement ``d`` at a pixel ``p`` is the circular distance
(:func:`misfit`, wraps, in [0, 0.5]) between the current texture at ``p`` and the
previous texture at ``p + d``: about 0 where the content matches, about 0.25 where
it does not. Costs are summed over channels and pixels.

Estimate
--------
1. A global integer shift, searched over ``[-search, search]^2`` on every
   ``stride``-th pixel of the frame's interior (a pan moves everything alike); it
   is kept only if its mean misfit is at most ``accept``, else (0, 0).
2. Only if that shift is not (0, 0) (the camera moved): per ``block x block``
   block (on every other row and column), the integer displacement within one
   pixel of the global shift with the least misfit; it replaces the global shift
   only when its cost is below ``switch`` times the global shift's and at most
   ``accept`` per pixel (so noise alone does not move a block). On a still camera
   the refinement is skipped: the safety window of :mod:`worker.temporal` already
   allows ``motion_radius`` px of motion, which is all a one-pixel refinement
   could add, and a still frame then costs only the global search.
3. The previous ``u`` is taken at ``p + d`` (whole pixels: a sub-pixel fit and
   bilinear resampling measured no better on the pan/zoom clip, at twice the
   cost). Pixels whose source lies outside the previous frame (content entering at
   the border) are flagged: nothing predicts them.

Cost per frame: the texture of both frames, ``(2 search + 1)^2`` comparisons of
``(H / stride) (W / stride)`` pixels, and when the camera moved nine comparisons
of a quarter of the frame and one gather; numpy-vectorised in float32 (no Python
loop over pixels or blocks). Measured on a 256 x 256 frame, 2 shared cores (best
of 40): 0.8-1.3 ms on a still frame and 2.7-3.5 ms on a pan, against 6-8 ms for
the cheapest spatial decoder (itoh); a whole temporal step on a pan is then about
1.5x itoh's cost (0.9x on a still frame), and 0.1-0.4x that of the others.

Failure modes
-------------
- Motion beyond ``search`` px/frame globally, or local motion more than about one
  pixel from the global shift (a fast object on a still background, such as the
  moving-light clip's 9 px/frame light; a fast zoom's corners; a zoom without a
  pan, where the global shift is 0), is not followed: those pixels keep a wrong
  prediction, and the temporal rule's safety checks and spatial fallback must
  catch them.
- A displacement can match by accident (a circular distance is small for any
  change near a whole number of wraps); ``accept`` and ``switch`` make that rare
  on blocks of ``block^2`` pixels but cannot rule it out on a block of a few.
- Flat or periodic blocks match many displacements; any of them predicts ``u``
  equally well there, so a wrong choice costs little. But texture is blind to
  *smooth* content (a linear ramp of ``u`` has the same texture everywhere), where
  a wrong shift does change ``u``: on smooth, noisy frames the global shift can be
  wrong by pixels. :meth:`worker.temporal.StreamDecoder.predict` therefore keeps a
  move only if it predicts ``m`` itself better than no move.
- Motion is followed to the nearest whole pixel: up to half a pixel of residual
  motion remains, so a moving edge steeper than one wrap per pixel can still
  alias; the safety window of :mod:`worker.temporal` catches most of it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from models.decoders.classical import wrap_difference
from worker.config_checks import refuse_invalid

#: Integer displacements of the block refinement around the global shift, as (dy, dx).
_STEPS = ((-1, 0), (0, -1), (0, 0), (0, 1), (1, 0), (-1, -1), (-1, 1), (1, -1), (1, 1))
_CENTRE = _STEPS.index((0, 0))


@dataclass(frozen=True)
class MotionConfig:
    """Knobs of the motion estimate: ``search`` (px/frame, 0 disables compensation),
    ``block`` (px), ``stride`` (px between the pixels the global search samples),
    ``switch`` (relative cost a block's own displacement must beat), ``accept`` (the
    largest mean misfit per pixel, wraps, of a displacement taken as a match)."""

    search: int = 4
    block: int = 16
    stride: int = 16
    switch: float = 0.8
    accept: float = 0.1

    def __post_init__(self) -> None:
        refuse_invalid(
            "motion",
            {
                "motion search must be >= 0": self.search >= 0,
                "motion block must be an even number >= 2": self.block >= 2 and self.block % 2 == 0,
                "motion stride must be >= 1": self.stride >= 1,
                "motion switch must be in (0, 1]": 0.0 < self.switch <= 1.0,
                "motion accept must be in (0, 0.5]": 0.0 < self.accept <= 0.5,
            },
        )


@dataclass(frozen=True)
class Compensated:
    """The previous ``u`` moved onto the current frame.

    ``u``: H x W x C (wraps); ``inside``: H x W, where its source lay within the
    previous frame; ``shift``: the global shift (dy, dx) in pixels; ``moved``: the
    fraction of blocks whose integer displacement differs from the global shift.
    """

    u: NDArray[np.float64]
    inside: NDArray[np.bool_]
    shift: tuple[int, int]
    moved: float


def misfit(prev_u: NDArray[np.floating], m: NDArray[np.floating]) -> NDArray[np.floating]:
    """``|W + m - prev_u|`` for the ``W = round(prev_u - m)`` the temporal rule picks
    (wraps, in [0, 0.5]): the circular distance between ``m`` and ``prev_u``'s ``m``
    (of any two arrays: their difference's distance to the nearest integer)."""
    return np.abs(wrap_difference(prev_u - m))


def _shifted(padded: NDArray, pad: int, shape: tuple[int, ...], dy: int, dx: int) -> NDArray:
    """The H x W x C window of the ``pad``-padded array displaced by ``(dy, dx)`` px."""
    return padded[pad + dy : pad + dy + shape[0], pad + dx : pad + dx + shape[1]]


def global_shift(
    before: NDArray[np.float32], now: NDArray[np.float32], pad: int, config: MotionConfig
) -> tuple[int, int]:
    """The integer shift (dy, dx) with the least misfit between the current texture
    ``now`` (at every other row and column) and the ``pad``-padded previous one
    ``before`` (every pixel) on every ``stride``-th interior pixel (ties go to the
    smallest shift), or (0, 0) when its mean misfit exceeds ``accept``."""
    rows, cols = before.shape[0] - 2 * pad, before.shape[1] - 2 * pad
    channels = now.shape[2]
    edge = config.search
    if rows <= 2 * edge + 1 or cols <= 2 * edge + 1:
        return 0, 0
    start, step = edge + edge % 2, 2 * max(config.stride // 2, 1)
    ys, xs = np.arange(start, rows - edge, step), np.arange(start, cols - edge, step)
    width = before.shape[1]
    base = ((ys[:, None] + pad) * width + xs[None, :] + pad).ravel()
    shifts = sorted(
        ((dy, dx) for dy in range(-edge, edge + 1) for dx in range(-edge, edge + 1)),
        key=lambda d: d[0] ** 2 + d[1] ** 2,
    )
    offsets = np.array([dy * width + dx for dy, dx in shifts])
    sample = now[ys[:, None] // 2, xs[None, :] // 2].reshape(-1, channels)
    previous = before.reshape(-1, channels)[offsets[:, None] + base[None, :]]
    costs = misfit(previous, sample[None]).sum(axis=(1, 2))
    best = int(np.argmin(costs))
    return shifts[best] if costs[best] <= config.accept * sample.size else (0, 0)


def block_sums(values: NDArray, block: int) -> NDArray:
    """Sums of an H x W x C array over ``block x block`` blocks and channels (the last
    row / column of blocks may be smaller)."""
    flat = values.sum(axis=2) if values.ndim == 3 else values
    starts_y = np.arange(0, flat.shape[0], block)
    starts_x = np.arange(0, flat.shape[1], block)
    return np.add.reduceat(np.add.reduceat(flat, starts_y, axis=0), starts_x, axis=1)


def block_costs(
    before: NDArray[np.float32],
    now: NDArray[np.float32],
    pad: int,
    shift: tuple[int, int],
    block: int,
) -> NDArray:
    """Misfit between the current texture ``now`` (every other row and column) and the
    padded previous one ``before`` per block (len(_STEPS) x blocks_y x blocks_x), for
    each step around ``shift``."""
    shape = (before.shape[0] - 2 * pad, before.shape[1] - 2 * pad)
    return np.stack(
        [
            block_sums(
                misfit(_shifted(before, pad, shape, shift[0] + dy, shift[1] + dx)[::2, ::2], now),
                block // 2,
            )
            for dy, dx in _STEPS
        ]
    )


def block_steps(costs: NDArray, pixels: NDArray, config: MotionConfig) -> NDArray[np.int64]:
    """Per block, the index into :data:`_STEPS` of its displacement around the global
    shift: the least misfit, if below ``switch`` times the shift's own and at most
    ``accept`` per pixel, else the shift itself (see module doc, step 2)."""
    best = np.argmin(costs, axis=0)
    least = np.take_along_axis(costs, best[None], 0)[0]
    taken = (least < config.switch * costs[_CENTRE]) & (least <= config.accept * pixels)
    return np.where(taken, best, _CENTRE)


def resample(
    padded: NDArray[np.float64], pad: int, shape: tuple[int, int], offsets: NDArray[np.int64],
    block: int,
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """The ``pad``-padded previous ``u`` at ``(y + dy, x + dx)`` for every pixel of an
    H x W (``shape``) frame, ``(dy, dx)`` constant per ``block x block`` block
    (``offsets``: blocks_y x blocks_x x 2, px, at most ``pad``); and where that
    source lies within the previous frame."""
    rows, cols = shape
    width = padded.shape[1]
    # Each block's offset repeated over its pixels: 0.20 ms against 0.31 for indexing
    # the blocks by each pixel's row and column (256x256, 2026-11-27).
    per_pixel = np.repeat(np.repeat(offsets, block, axis=0)[:rows], block, axis=1)[:, :cols]
    src_y = np.arange(rows)[:, None] + per_pixel[:, :, 0]
    src_x = np.arange(cols)[None, :] + per_pixel[:, :, 1]
    inside = (src_y >= 0) & (src_y < rows) & (src_x >= 0) & (src_x < cols)
    index = ((src_y + pad) * width + src_x + pad).ravel()
    flat = padded.reshape(-1, padded.shape[2])
    return flat.take(index, axis=0).reshape(rows, cols, -1), inside


def texture(values: NDArray[np.float32], wrapped: bool, step: int = 1) -> NDArray[np.float32]:
    """The sum of each pixel's differences to its right and lower neighbours (0 past
    the last column / row) of an H x W x C array, at every ``step``-th row and column;
    differences of ``m`` are ``wrapped``. A brightness offset in ``u`` leaves it unchanged."""
    here = values[::step, ::step]
    out = np.zeros_like(here)
    below, right = values[1::step, ::step], values[::step, 1::step]
    rows, cols = below.shape[0], right.shape[1]
    pairs = ((below - here[:rows], out[:rows]), (right - here[:, :cols], out[:, :cols]))
    for diff, target in pairs:
        target += wrap_difference(diff) if wrapped else diff
    return out


def compensate(
    prev_u: NDArray[np.float64], m: NDArray[np.float64], config: MotionConfig
) -> Compensated:
    """The previous ``u`` (H x W x C, wraps) resampled where each block of the current
    frame ``m`` (H x W x C) came from (see module doc)."""
    rows, cols = m.shape[:2]
    if config.search == 0:
        return Compensated(prev_u, np.ones((rows, cols), bool), (0, 0), 0.0)
    pad = config.search + 1
    margins = ((pad, pad), (pad, pad), (0, 0))
    before = np.pad(texture(prev_u.astype(np.float32), wrapped=False), margins, mode="edge")
    now = texture(m.astype(np.float32), wrapped=True, step=2)
    shift = global_shift(before, now, pad, config)
    if shift == (0, 0):
        return Compensated(prev_u, np.ones((rows, cols), bool), shift, 0.0)
    costs = block_costs(before, now, pad, shift, config.block)
    pixels = block_sums(np.ones(now.shape, np.float32), config.block // 2)
    steps = block_steps(costs, pixels, config)
    offsets = np.array(_STEPS)[steps] + np.array(shift)
    padded = np.pad(prev_u, margins, mode="edge")
    warped, inside = resample(padded, pad, (rows, cols), offsets, config.block)
    return Compensated(warped, inside, shift, float(np.mean(steps != _CENTRE)))
