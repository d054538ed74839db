"""Unsafe clusters of a temporal step re-decoded spatially on a crop, kept by region vote.

The *local* path of :mod:`worker.temporal` settles unsafe pixels from their
neighbours (:func:`worker.temporal_fallback.neighbour_fix`): right for a thin band
along a moving edge whose content changes slowly, wrong where neighbouring
pixels differ by about half a wrap or more (steep edges of a pan or zoom, content
entering at the border) and beyond ``local_passes`` px from a safe pixel. So each
connected cluster of unsafe pixels (grown by ``GROW`` px) of at least
``min_cluster`` unsafe pixels is decoded again by the spatial decoder on its
bounding box widened by ``margin`` px (and to ``MIN_SIDE`` px a side, cut at the
frame's border); the crop's constant is aligned to the fixed answer on the crop's
safe pixels (:func:`models.tile_reconcile.common_offset`) and its W clipped into
the range motion allows (:meth:`worker.temporal_rule.Prediction.bounds`); then each
region where the two disagree and that touches an unsafe pixel takes the answer
with fewer jumps across its boundary (:func:`models.decoders.region_vote.region_vote`, as
at a keyframe). Largest clusters first, crops are decoded while their total area
stays within ``limit`` of the frame, so the step stays cheaper than a full
spatial decode.

Measured (bench.video, 256 x 256, 60 frames): on the pan/zoom clip herraez gains
about 1 dB over the local fix alone, the learned decoders 0.1-0.3 dB, itoh nothing
(its least-squares answer on a crop is no better than the local fix); the
moving-light clip is unchanged. :mod:`worker.temporal` uses it only when the
camera moved: on a still camera it cost the static and sunrise clips up to 5 dB.

Failure modes: the clip to the motion bounds keeps a wrong crop region from
entering (without it, the moving-light clip took wrong crop regions and its wrap
flicker rose 5-8x) but also keeps out the right answer for content that moved
much further than motion compensation followed (a fast light: only its rim is
fixed); a spatial decoder sees less context on a crop than on the frame; a cluster
with no safe pixel in its crop is left as fixed; the vote's own failure modes
(:mod:`models.decoders.region_vote`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from models.decoders.region_vote import region_vote
from models.scene_analysis import cross_dilation
from models.tile_reconcile import common_offset
from worker.config_checks import refuse_invalid
from worker.temporal_rule import Prediction

#: Unsafe pixels closer than this many px to each other form one cluster.
GROW = 2
#: The smallest side of a crop handed to the spatial decoder (px).
MIN_SIDE = 32


@dataclass(frozen=True)
class CropConfig:
    """Knobs of the crop vote: ``min_cluster`` (px, 0 turns it off), ``margin`` (px of
    context around a cluster), ``limit`` (the largest share of the frame decoded)."""

    min_cluster: int = 64
    margin: int = 16
    limit: float = 0.25

    def __post_init__(self) -> None:
        refuse_invalid(
            "crop vote",
            {
                "crop min_cluster must be >= 0": self.min_cluster >= 0,
                "crop margin must be >= 0": self.margin >= 0,
                "crop limit must be in [0, 1]": 0.0 <= self.limit <= 1.0,
            },
        )


def widened(span: slice, margin: int, size: int) -> slice:
    """``span`` grown by ``margin`` each side, to at least ``MIN_SIDE``, inside ``[0, size)``."""
    start, stop = span.start - margin, span.stop + margin
    short = MIN_SIDE - (stop - start)
    if short > 0:
        start, stop = start - short // 2, stop + short - short // 2
    start, stop = max(start, 0), min(stop, size)
    return slice(start, stop)


def cluster_boxes(
    unsafe: NDArray[np.bool_], config: CropConfig
) -> list[tuple[slice, slice]]:
    """Crops (row, column slices) around the clusters of ``unsafe`` (H x W) worth a
    spatial decode, largest first, while their total area stays within ``limit``."""
    if config.min_cluster == 0 or not unsafe.any():
        return []
    labels, count = ndimage.label(cross_dilation(unsafe, GROW))
    # Unsafe pixels per cluster, counted on the unsafe pixels alone (0.01 ms against
    # 0.25 for a bincount weighted over the whole frame, 256x256).
    sizes = np.bincount(labels[unsafe], minlength=count + 1)
    boxes, budget = [], config.limit * unsafe.size
    for index, found in enumerate(ndimage.find_objects(labels), start=1):
        if found is None or sizes[index] < config.min_cluster:
            continue
        rows = widened(found[0], config.margin, unsafe.shape[0])
        cols = widened(found[1], config.margin, unsafe.shape[1])
        boxes.append((sizes[index], (rows, cols)))
    chosen = []
    for _, (rows, cols) in sorted(boxes, key=lambda box: -box[0]):
        area = (rows.stop - rows.start) * (cols.stop - cols.start)
        if area <= budget:
            chosen.append((rows, cols))
            budget -= area
    return chosen


def crop_vote(
    prediction: Prediction,
    fixed: NDArray[np.int64],
    decode: Callable[[NDArray[np.float64]], NDArray[np.int64]],
    config: CropConfig,
) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
    """One channel's ``fixed`` W (H x W) with its unsafe clusters re-decoded on crops by
    ``decode`` (m of a crop -> its W) and kept region by region (module doc).

    Returns the merged W and where the spatial answer was taken.
    """
    merged, taken = fixed.copy(), np.zeros(fixed.shape, bool)
    for box in cluster_boxes(~prediction.safe, config):
        safe = prediction.safe[box]
        if not safe.any():
            continue
        spatial = np.asarray(decode(prediction.m[box]), np.int64)
        aligned = spatial + common_offset(merged[box][safe], spatial[safe])
        aligned = np.clip(aligned, *prediction.crop(box).bounds())
        merged[box], took = region_vote(merged[box], aligned, prediction.m[box], ~safe)
        taken[box] |= took
    return merged, taken
