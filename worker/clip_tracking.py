"""Clipped lamps in a stream: filled where they move to, decoded spatially where they left.

A lamp brighter than the sensor's clip (``max_wraps``) is a plateau of pixels that
all read ``u_max`` (:mod:`models.decoders.saturation`), ringed by wraps too steep to
count. An anchoring keyframe fills it (``auto``); when it moves faster than the
temporal rule of :mod:`worker.temporal` follows, two things go wrong, which the
independent decoding of ``auto`` (filling each frame afresh) does not suffer:

- where it *arrives*, pixels jump by many wraps in one frame; the rule aliases and
  leaves them low (moving-light clip, modulo, auto-fast: 1,470 of the lamp's 2,500
  clipped pixels a median 13 wraps short from frame 6 on);
- where it *leaves*, its filled core and its steep rim fall by many wraps; the rule
  keeps them high, and the trail grows frame after frame.

So in every temporal step, once the rule and its fallbacks have run, per channel:

1. *Continuing blobs* are filled, ``W = round(u_max - m)``: the solid blobs of pixels
   reading the clip (:func:`models.decoders.saturation.solid_blobs`) with half their
   pixels within ``reach`` px of a pixel that was at the clip in the previous frame
   (the previous ``u`` within the clip's tolerance of ``u_max``, where it was, not
   moved), whose new pixels (not at the clip before) have a mean misfit of at
   least ``misfit`` wraps (content that jumped: a pixel the rule tracked has a misfit
   at its noise), and that an aliased ring cuts off
   (:func:`models.decoders.saturation.ringed`). The misfit test is what keeps a
   sunrise apart: there, wrap contours reading the clip's code (mantissa: code 0)
   sweep past the clipped sun and are tracked exactly (without it the mantissa
   sunrise fell from 36.48 to 31.46 dB, auto-fast).
2. *The zone the lamp left* is decoded spatially: the pixels within ``zone`` px of
   the clusters (of at least ``MIN_PIXELS``) that were at the clip and no longer read
   it, and, while there are such clusters, the pixels of the lamp's wake: within
   ``wake`` px of a clipped blob (before or now) where the rule's misfit averages
   ``misfit`` wraps or more over a ``WINDOW``-px window (the rim fell by more than
   half a wrap and the rule aliased; a pixel the rule tracked has a misfit at its
   noise). Outside the filled blobs, they take the spatial decoder's answer on a crop
   round them (``margin`` px of context), its constant aligned to the tracked W on the
   rest of the crop (:func:`models.tile_reconcile.common_offset`). Only pixels that
   left the clip start a zone: on a sunrise the clip grows, and a zone round every
   clipped pixel took the spatial decoder's answer into the tracked rim (mantissa
   sunrise 36.48 -> 26.91 dB). Without the wake, the rim pixels a lamp passed were
   decoded only in the frame they left the clip and aliased again in the next ones (a
   lamp moving 12 px a frame: its old core all wrong three frames on).

Measured (2026-11-26, 60-frame clips, temporal auto-fast, mean PSNR mantissa /
modulo; independent decoding 17.29 / 17.02 dB on the moving light): moving light
15.87 / 13.69 -> 17.40 / 17.08 dB, sunrise 36.48 / 25.81 -> 36.48 / 26.50 dB, static
noise and pan/zoom unchanged (23.84 / 16.20 and 46.43 / 45.77 dB). A crop decode costs
the moving light's frames about 7 ms; in a still view :mod:`worker.temporal` runs clip
tracking before arrival refinement, which then leaves the pixels it set alone (8 ms
less a frame than refining the wake first, at the same PSNR). Growing a mask by
``binary_dilation`` one pixel at a time cost 3 ms more a frame than the maximum filter
(:func:`models.decoders.band_moves.band_of`: Chebyshev distance). The knobs were set on
those clips (there is no separate tuning set of videos).

Failure modes: a lamp that arrives within ``reach`` px of nothing clipped (switched
on) waits for the next keyframe, as before; a small lamp (under ``MIN_PIXELS``) is
not tracked; the zone is only as right as the spatial decoder on it; a clipped blob
whose new pixels happen to be tracked with small misfits is not filled. Wrap flicker
on the moving light rises (auto-fast, mantissa: 0.0021 -> 0.0032, 5.9x below
independent decoding): the clipped core's code sits at a wrap boundary (code 0 for
``u_max`` 5 or 16), so read noise flips its W at an unchanged ``u``, and the wake's
crop decodes vary from frame to frame.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from models.decoders.band_moves import band_of
from models.decoders.saturation import (
    MIN_PIXELS,
    clip_tolerance,
    clip_winding_of,
    clipped_value,
    grown_box,
    reads_clip,
    ringed,
    solid_blobs,
)
from models.formation import SensorParams
from models.tile_reconcile import common_offset
from worker.config_checks import refuse_invalid
from worker.crop_vote import widened

#: Side (px) of the window over which the misfit is averaged in a lamp's wake.
WINDOW = 5


@dataclass(frozen=True)
class ClipTrackConfig:
    """Knobs of clip tracking (module doc): ``reach`` (px; 0 turns it off), ``misfit``
    (wraps), ``zone``, ``wake`` and ``margin`` (px)."""

    reach: int = 8
    misfit: float = 0.15
    zone: int = 6
    wake: int = 16
    margin: int = 16

    def __post_init__(self) -> None:
        refuse_invalid(
            "clip tracking",
            {
                "clip reach must be >= 0": self.reach >= 0,
                "clip misfit must be in [0, 0.5]": 0.0 <= self.misfit <= 0.5,
                "clip zone must be >= 0": self.zone >= 0,
                "clip wake must be >= 0": self.wake >= 0,
                "clip margin must be >= 0": self.margin >= 0,
            },
        )


def continuing_blobs(
    m: NDArray[np.float64],
    was_clipped: NDArray[np.bool_],
    change: NDArray[np.float64],
    reads: NDArray[np.bool_],
    config: ClipTrackConfig,
) -> NDArray[np.bool_]:
    """The pixels (H x W) of the blobs of ``reads`` (pixels reading the clip) that
    continue a clipped blob of the previous frame (``was_clipped``) and jumped there
    (``change``: the temporal rule's misfit, wraps); module doc, step 1."""
    labels, count, sizes, keep = solid_blobs(reads)
    if not keep.any():
        return np.zeros(m.shape, bool)
    near = band_of(was_clipped, config.reach)
    close = np.bincount(labels[near], minlength=count + 1)
    new = reads & ~was_clipped
    fresh = np.bincount(labels[new], minlength=count + 1)
    jumped = np.bincount(labels[new], weights=change[new], minlength=count + 1)
    keep &= (2 * close >= sizes) & (jumped >= config.misfit * np.maximum(fresh, 1))
    return ringed(labels, keep, m, count)


def left_zone(
    was_clipped: NDArray[np.bool_],
    reads: NDArray[np.bool_],
    filled: NDArray[np.bool_],
    change: NDArray[np.float64],
    config: ClipTrackConfig,
) -> NDArray[np.bool_]:
    """The pixels (H x W) within ``zone`` px of the clusters (of at least
    :data:`MIN_PIXELS`) that were at the clip and no longer read it, and those within
    ``wake`` px of a clipped blob (before or now) where the rule's misfit averages
    ``misfit`` wraps or more over ``WINDOW`` px (aliased: the lamp's rim moved by more
    than half a wrap); outside ``filled`` (module doc, step 2)."""
    gone = was_clipped & ~reads
    labels, count = ndimage.label(gone)
    large = np.bincount(labels.ravel(), minlength=count + 1) >= MIN_PIXELS
    large[0] = False
    gone = large[labels]
    if not gone.any():
        return gone
    zone = band_of(gone, config.zone)
    near = band_of(was_clipped | filled, config.wake)
    aliased = ndimage.uniform_filter(change, WINDOW) >= config.misfit
    return (zone | (near & aliased)) & ~filled


def decoded_zone(
    m: NDArray[np.float64],
    winding: NDArray[np.int64],
    zone: NDArray[np.bool_],
    decode: Callable[[NDArray[np.float64]], NDArray[np.int64]],
    margin: int,
) -> NDArray[np.int64]:
    """``winding`` (H x W) with ``zone`` taken from ``decode`` (m of a crop -> its W) on
    the zone's bounding box widened by ``margin`` px, aligned to ``winding`` on the
    crop's other pixels (left as it is if the crop has none)."""
    rows, cols = grown_box(zone, 0)
    box = (widened(rows, margin, m.shape[0]), widened(cols, margin, m.shape[1]))
    context = ~zone[box]
    if not context.any():
        return winding
    spatial = np.asarray(decode(m[box]), np.int64)
    aligned = np.maximum(spatial + common_offset(winding[box][context], spatial[context]), 0)
    result = winding.copy()
    result[box] = np.where(zone[box], aligned, winding[box])
    return result


def track_clip(
    m: NDArray[np.float64],
    winding: NDArray[np.int64],
    previous_u: NDArray[np.float64],
    change: NDArray[np.float64],
    params: SensorParams,
    decode: Callable[[NDArray[np.float64]], NDArray[np.int64]],
    config: ClipTrackConfig,
) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
    """One channel's tracked ``winding`` (H x W) with its moving clipped blobs filled and
    the zone they left decoded by ``decode`` (module doc); and where W was set here.

    ``previous_u``: the previous frame's ``u`` (wraps) as it was decoded, neither moved
    nor brightened (brightened, a sunrise's rim rose past the clip and counted as
    clipped); ``change``: the rule's misfit (wraps). Nothing changes without a clip,
    with ``reach = 0`` or where nothing was clipped in the previous frame.
    """
    unchanged = np.zeros(m.shape, bool)
    u_max = clipped_value(params)
    if u_max is None or config.reach == 0:
        return winding, unchanged
    was_clipped = previous_u >= u_max - clip_tolerance(params, u_max)
    if not was_clipped.any():
        return winding, unchanged
    reads = reads_clip(m, params, u_max)
    filled = continuing_blobs(m, was_clipped, change, reads, config)
    result = np.where(filled, clip_winding_of(m, params, u_max), winding)
    zone = left_zone(was_clipped, reads, filled, change, config)
    if zone.any():
        result = decoded_zone(m, result, zone, decode, config.margin)
    return result, filled | zone
