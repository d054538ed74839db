"""Bright content arriving in a still view, found by its misfit and unwrapped on a crop.

A light moving faster than ``motion_radius`` px per frame (or switched on, or an
object entering) raises pixels by whole wraps from one frame to the next. The
temporal rule of :mod:`worker.temporal` then aliases: ``round(u_{t-1} - m_t)``
keeps the old W, and for about 80% of those pixels the misfit
``|W_t + m_t - u_{t-1}|`` lands inside the safe band, so they pass as safe and
stay wrong until a keyframe. What gives them away is that they come in clusters:
a tracked pixel whose content did not change has a misfit near zero (read noise;
under a brightness ramp the gain is undone first), so a connected cluster of at
least ``min_cluster`` pixels with misfit above ``change`` wraps is content that
changed. On the moving-light clip (bench.video, mantissa, mantissanet-tiny) 70%
of the newly wrong safe pixels have a misfit above 0.1 wraps and 0.3% of the right
ones do, scattered. The threshold is at least ``NOISE_SIGMAS`` times the pixel's
noise (:func:`models.formation.unwrapped_noise_sigma`: bright modulo pixels with
shot noise move by 0.1 wraps on their own), and a cluster counts only if the
median misfit around it reaches ``ALIASED_MEDIAN``: with neither, the static and
sunrise modulo clips refined noise and flickered 1.5-2.5x more.

Each such cluster's bounding box (widened by ``margin`` px, see
:func:`worker.crop_vote.cluster_boxes`) is refined by guided graph-cut unwrapping
from the tracked W (at most ``moves`` min-cuts): a region whose W disagrees with the
codes along its border (the rings of a light all left at the old W) is moved by whole
wraps. Only the pixels within ``REACH`` px of a changed one may move
(:meth:`models.decoders.guided_puma.GuidedPumaDecoder.refine_within`); the rest of
the crop is context that keeps the tracked W (graph cuts there would move real edges
steeper than half a wrap), so the cuts are as small as the arrivals.

Until 2026-11-26 the whole crop was refined and only the pixels near a changed one
took the result, its constant aligned to the tracked W on the unchanged pixels. Cut
on those pixels alone instead (bench.video clips, temporal, 4 decoders x 2
encodings), the moving light's temporal frames fell from 16-33 to 11-15 ms (below
independent decoding's 17-33 ms with every decoder but itoh) at -0.06 to +0.06 dB;
the sunrise moved by -0.74 (itoh, modulo; still 4.2 dB above independent) to +0.37 dB
(auto-fast, mantissa), the static clip not at all. A band of 2 or 3 px round the
changed pixels measured +0.09 to +0.12 dB on the moving light with the networks but
lost 1.65 dB on the mantissa sunrise with auto-fast (13 bright pixels a wrap off from
frame 25 on, carried to the end).

Failure modes: content that arrives with a sharp edge steeper than half a wrap
(a lamp switched on behind a hard shade) cannot be unwrapped from its border, so
the crop keeps what graph cuts make of it; a slow change that stays under
``change`` wraps per frame is not seen here (the temporal rule decides it
exactly); a cluster that covers its whole crop has no context to hold it and is
left as tracked.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from models.decoders.guided_puma import GuidedPumaDecoder
from models.formation import SensorParams, unwrapped_noise_sigma
from models.scene_analysis import cross_dilation
from worker.config_checks import refuse_invalid
from worker.crop_vote import CropConfig, cluster_boxes

#: A pixel has changed when its misfit exceeds this many sigmas of its sensor noise.
NOISE_SIGMAS = 6.0
#: Refined W is taken up to this many px from a changed pixel.
REACH = 1
#: A cluster is refined when the median misfit around its changed pixels reaches this
#: (wraps): aliased content spreads its misfit evenly over [0, 0.5], noise and an
#: imperfect brightness gain leave most neighbours of a changed pixel near zero.
ALIASED_MEDIAN = 0.11


@dataclass(frozen=True)
class ArrivalConfig:
    """Knobs of arrival refinement: ``change`` (wraps of misfit that mark a changed
    pixel), ``min_cluster`` (changed px of a cluster worth refining; 0 turns it off),
    ``margin`` (px of context around a cluster), ``limit`` (the largest share of the
    frame refined) and ``moves`` (min-cuts per crop)."""

    change: float = 0.1
    min_cluster: int = 32
    margin: int = 8
    limit: float = 0.25
    moves: int = 8

    def __post_init__(self) -> None:
        refuse_invalid(
            "arrival",
            {
                "arrival change must be in (0, 0.5)": 0.0 < self.change < 0.5,
                "arrival min_cluster must be >= 0": self.min_cluster >= 0,
                "arrival margin must be >= 0": self.margin >= 0,
                "arrival limit must be in [0, 1]": 0.0 <= self.limit <= 1.0,
                "arrival moves must be >= 1": self.moves >= 1,
            },
        )

    def crops(self) -> CropConfig:
        """The same cluster and crop rules as the crop vote uses."""
        return CropConfig(min_cluster=self.min_cluster, margin=self.margin, limit=self.limit)


def refine_arrivals(
    m: NDArray[np.float64],
    winding: NDArray[np.int64],
    change: NDArray[np.float64],
    params: SensorParams,
    refiner: GuidedPumaDecoder,
    config: ArrivalConfig,
) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
    """One channel's W (H x W) with its arrival clusters refined (module doc).

    ``m``: the frame (wraps); ``winding``: the tracked W; ``change``: each pixel's
    misfit to the previous frame (wraps). Returns the W and where it was refined.
    """
    merged, taken = winding.copy(), np.zeros(winding.shape, bool)
    changed = change > config.change
    if changed.sum() < max(config.min_cluster, 1):
        return merged, taken
    noise = unwrapped_noise_sigma(merged[changed] + m[changed], params)
    changed[changed] = change[changed] > NOISE_SIGMAS * noise
    if changed.sum() < max(config.min_cluster, 1):
        return merged, taken
    for box in cluster_boxes(changed, config.crops()):
        around = cross_dilation(changed[box], REACH)
        if changed[box].all() or np.median(change[box][around]) < ALIASED_MEDIAN:
            continue
        refined, _ = refiner.refine_within(m[box], merged[box], params, around)
        take = refined != merged[box]
        merged[box] = refined
        taken[box] |= take
    return merged, taken
