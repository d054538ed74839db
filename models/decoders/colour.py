"""Colour frames decoded jointly: ``<decoder>+colour`` makes the channels' W agree.

A spatial decoder unwraps each channel of a colour frame on its own, and gets each
channel's hard regions wrong in its own places: the blue channel of a sky crop a
wrap low while red and green are right. On val-256 in colour (the val-256 crops in
RGB, :func:`models.scenes.val256_frames` with ``colour``) 11% of the pixel-channels that
auto-balanced decodes are wrong while the other two channels of the pixel are
right; putting just those right would take it from 20.7 to 25.2 dB (mantissa).

The channels share what the codes say about them through the *chroma*: for channel
``c`` against the reference channel (green, most of the luminance the exposure is set
on)

    q = u_c - u_ref = (W_c - W_ref) + (m_c - m_ref)

is itself a wrapped signal whose wrapped value ``frac(m_c - m_ref)`` the codes give
exactly, and whose winding number is the relative winding ``W_c - W_ref``. Chroma is
smoother than either channel: it keeps no shading, and above saturation the mantissa
encoding makes it a log ratio, ``log_alpha(x_c / x_ref)``, which a brightening
leaves alone. So ``q`` is unwrapped (:func:`relative_winding`) by PUMA's binary
moves (:mod:`models.decoders.graphcut`, reliability-weighted like
:mod:`models.decoders.guided_puma`), started from the decoded channels' relative W.
The codes decide it: the guide is only a starting point, except on *anchor* pixels
(:func:`colour_anchors`: every channel decoded W = 0 and reading below
:data:`ANCHOR_CODE`), which are dark in every channel, hence truly W = 0 in each,
and pin the relative W there to 0 (:data:`ANCHOR_WEIGHT` per pixel and wrap). With
fewer than :data:`MIN_ANCHORS` anchors nothing fixes the relative W's constant, and
it is set as a single channel's is (:func:`models.decoders.base.anchor_winding`): the
channel it gives, the reference's decoded W plus the relative W, has its darkest
pixels (the :data:`models.decoders.base.ANCHOR_PERCENTILE` percentile) at W = 0.
Until 2026-11-26 it followed the guide's most common relative W, which failed where
the guide's channel was wrong in whole tiles: on four venice crops auto-balanced's
blue sky was stitched a wrap high on 58% of the pixels and a wrap low on 39%, few
pixels were dark in every channel, and the join kept the high wrap (bench.colour,
val, balanced mantissa 23.96 -> 24.54 dB, modulo 22.50 -> 24.26 dB with the anchoring
rule; on the tuning set, where it was chosen, auto-fast +0.39 / +0.19 dB, herraez
-0.13 / +0.66 dB, itoh +0.39 / +0.01 dB, balanced +0.00 / +0.02 dB; best unchanged,
its channels leave enough anchors).

Each channel then votes for the reference's W at each pixel, ``W_c - (W_c - W_ref)``;
where at least two votes agree, every channel takes that W plus its relative W
(:func:`harmonise`). A channel decoded wrong where the other two are right is put
right; where two channels are wrong the same way, the third is made wrong too; where
all three votes differ, nothing changes.

It is a decoder's :meth:`models.decoders.base.Decoder.join_channels`: ``auto`` runs it
after its channels at best and, up to 512x512 px, at balanced (:data:`JOINT_COLOUR` in
:mod:`models.decoders.adaptive`: it costs about 2.5 us a pixel), any decoder gets it
as ``<decoder>+colour`` (after a clip is filled in every channel that holds it, when
``<decoder>`` fills clipped blobs: :func:`models.decoders.saturation.fill_shared`), a
refined decoder (``<decoder>+puma``) joins as its guide does, and a colour video's
keyframes are joined (:mod:`worker.temporal`; the frames between them track each
channel). A latency budget (``auto-<N>ms``) joins a colour frame's channels when that
is predicted to take at most half its budget (:mod:`models.decoders.budget`).

Measured (``python -m bench.colour``, 2026-11-26, 2 AMD EPYC cores; the constants
below were chosen on the *tuning* set, 2 crops of each training scene, before the
validation crops were measured), mean PSNR channels alone -> made consistent:
val-256 in colour, mantissa: auto-balanced 20.74 -> 24.54 dB, auto-best 19.86 ->
24.44 dB, herraez 19.84 -> 22.39 dB; modulo: auto-balanced 19.52 -> 24.26 dB,
auto-best 21.53 -> 24.55 dB; tuning set, mantissa: auto-balanced 24.52 -> 25.97 dB,
auto-best 25.34 -> 26.38 dB. It costs 110-170 ms per 256x256 frame. With itoh's
guide it gains nothing on PSNR (a wrong majority spreads): the better the channels'
decoder, the more it gains. How it was found (a per-pixel chroma median, which made
more pixels wrong than right; the anchor and prior weights) is in
``docs/experiments.md``.
"""

from __future__ import annotations

import re
from typing import Any

import numpy as np
from numpy.typing import NDArray

from models.decoders.band_moves import jump_pairs
from models.decoders.base import Decoder, anchor_offset
from models.decoders.filling import filled_then_joined
from models.decoders.graphcut import PumaEnergy, best_pixel_move, minimise
from models.decoders.guided_puma import JUMPS, pair_weights
from models.decoders.region_moves import best_region_move
from models.decoders.registry import DecoderSpec, get_decoder, refuse_budget_inside
from models.decoders.registry import resolve as resolve_inner
from models.formation import SensorParams, clip_winding

SUFFIX = "+colour"
#: The suffix as the registry finds it in a name (:func:`models.decoders.registry.resolve`).
SUFFIX_PATTERN = re.escape(SUFFIX)
NAME = re.compile(rf"(?P<inner>.+){SUFFIX_PATTERN}")
NAME_PATTERNS = (
    "<decoder>+colour (colour frames: each channel decoded by the decoder, then the "
    "channels' W made consistent through their wrapped chroma, e.g. herraez+colour)",
)
#: The channel the others are unwrapped against: green, which carries most of the
#: luminance the exposure is set on (its W = 0 share is 0.80 on val-256 in colour).
REFERENCE = 1
#: Anchor pixels read codes below this (wrap units) in every channel, besides being
#: decoded W = 0 in every channel.
ANCHOR_CODE = 0.5
#: Prior weight of an anchor pixel (per wrap of relative W away from 0); elsewhere 0.
ANCHOR_WEIGHT = 0.05
#: With fewer anchors the relative W's constant is set by the anchoring rule.
MIN_ANCHORS = 64
#: Region moves, then pixel moves, of the chroma unwrapping. Measured on the
#: training-scene colour crops (auto-balanced guide, mantissa): 8 + 2 gained 1.45 dB,
#: 8 + 0 1.07 dB at half the time; band pixel moves
#: (:mod:`models.decoders.band_moves`) instead of full ones 1.07 dB.
REGION_MOVES = 8
PIXEL_MOVES = 2
#: A pixel no two channels' votes agree on keeps its decoded W.
NO_MAJORITY = np.iinfo(np.int64).min


def colour_anchors(m: NDArray[np.float64], winding: NDArray[np.int64]) -> NDArray[np.bool_]:
    """Pixels (H x W) dark in every channel of ``m`` (H x W x C, wrap units) and decoded
    W = 0 in every channel: their relative W is 0."""
    return (winding == 0).all(axis=2) & (m < ANCHOR_CODE).all(axis=2)


def has_jumps(chroma: NDArray[np.float64]) -> bool:
    """Whether any two neighbours of ``chroma`` (wrap units) differ by over half a wrap
    (:func:`models.decoders.band_moves.jump_pairs`)."""
    return any(pairs.any() for pairs in jump_pairs(chroma))


def relative_winding(
    m: NDArray[np.float64],
    winding: NDArray[np.int64],
    channel: int,
    anchors: NDArray[np.bool_],
) -> NDArray[np.int64]:
    """``W_channel - W_ref`` (H x W) from the unwrapped chroma (module doc), starting from
    the decoded ``winding`` (H x W x C)."""
    difference = m[:, :, channel] - m[:, :, REFERENCE]
    wrapped = difference - np.floor(difference)
    guide = (winding[:, :, channel] - winding[:, :, REFERENCE]) + np.floor(difference)
    guide = guide.astype(np.int64)
    if not has_jumps(guide + wrapped):
        # Every move would add jumps and the anchors already agree: the guide is the
        # minimum (a colour frame whose channels agree everywhere costs no min-cut).
        return guide - np.floor(difference).astype(np.int64)
    energy = PumaEnergy(
        1.0, pair_weights(wrapped), guide, np.where(anchors, ANCHOR_WEIGHT, 0.0), 1.0
    )
    chroma = minimise(wrapped, guide, energy, JUMPS, REGION_MOVES, best_region_move).winding
    chroma = minimise(wrapped, chroma, energy, JUMPS, PIXEL_MOVES, best_pixel_move).winding
    relative = chroma - np.floor(difference).astype(np.int64)
    if anchors.sum() < MIN_ANCHORS:
        relative = relative - anchor_offset(winding[:, :, REFERENCE] + relative)
    return relative


def harmonise(
    m: NDArray[np.float64], winding: NDArray[np.int64], params: SensorParams
) -> tuple[NDArray[np.int64], dict[str, Any]]:
    """The decoded ``winding`` (H x W x 3) of a colour frame ``m`` (H x W x 3, wrap units)
    with the channels made consistent (module doc), and facts: anchor pixels, the
    fraction of pixels with a majority, and of pixel-channels changed."""
    anchors = colour_anchors(m, winding)
    relative = np.zeros_like(winding)
    for channel in range(winding.shape[2]):
        if channel != REFERENCE:
            relative[:, :, channel] = relative_winding(m, winding, channel, anchors)
    votes = winding - relative
    first, second, third = votes[:, :, 0], votes[:, :, 1], votes[:, :, 2]
    majority = np.where(
        (first == second) | (first == third), first, np.where(second == third, second, NO_MAJORITY)
    )
    agreed = majority != NO_MAJORITY
    harmonised = np.where(agreed[:, :, None], majority[:, :, None] + relative, winding)
    harmonised = clip_winding(harmonised, params)
    return harmonised, {
        "anchors": int(anchors.sum()),
        "majority_fraction": float(agreed.mean()),
        "changed_fraction": float(np.mean(harmonised != winding)),
    }


class ColourDecoder(Decoder):
    """``inner`` on each channel, then :func:`harmonise` on colour frames (grayscale
    frames are ``inner``'s answer unchanged). ``inner``'s own :meth:`join_channels` is
    not run, so a colour frame is made consistent once."""

    def __init__(self, inner: Decoder) -> None:
        self.inner = inner
        self.name = f"{inner.name}{SUFFIX}"  # type: ignore[misc]
        self.version = inner.version

    def unwraps(self, params: SensorParams) -> bool:
        return self.inner.unwraps(params)

    def predict_winding(self, m: NDArray[np.float64], params: SensorParams) -> NDArray[np.int64]:
        return self.inner.predict_winding(m, params)

    def explain_winding(
        self, m: NDArray[np.float64], params: SensorParams
    ) -> tuple[NDArray[np.int64], dict[str, Any]]:
        return self.inner.explain_winding(m, params)

    def join_channels(
        self, planes: NDArray[np.float64], winding: NDArray[np.int64], params: SensorParams
    ) -> tuple[NDArray[np.int64], dict[str, Any]]:
        """:func:`harmonise` on a colour frame, after its clips are filled in every channel
        that holds them (:func:`models.decoders.filling.filled_then_joined`) when
        ``inner`` fills clipped blobs."""
        if planes.shape[2] != 3:
            return winding, {}
        if self.inner.fills_saturation:
            return filled_then_joined(planes, winding, params, harmonise)
        return harmonise(planes, winding, params)


def resolve(name: str) -> DecoderSpec | None:
    """The spec of ``<decoder>+colour`` when ``<decoder>`` is a known decoder (a clear
    error otherwise); None for any other name."""
    match = NAME.fullmatch(name)
    if match is None:
        return None
    inner = match.group("inner")
    refuse_budget_inside("+colour", resolve_inner(inner), "+colour gives it to each channel")
    return DecoderSpec(
        name=name,
        kind="colour",
        description=(
            f"{inner} on each channel, then the channels' winding numbers made consistent "
            "through their wrapped chroma (colour frames only)"
        ),
        factory=lambda: ColourDecoder(get_decoder(inner)),
    )


def specs() -> list[DecoderSpec]:
    """No fixed names: ``<decoder>+colour`` is resolved from the name (:func:`resolve`)."""
    return []
