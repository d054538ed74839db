"""What ``auto`` runs at each quality level: its measured routing policy.

:mod:`models.decoders.adaptive` routes each tile of a frame; this module holds the
choices behind that routing, each with the measurement that set it: which network
tier decides hard tiles at each quality (:data:`TIER_LADDER`, or the installed net
whose model card states the best val-256 PSNR, :func:`most_accurate_net`), how far
guided PUMA refines the result (:data:`REFINEMENT`), when a colour frame's channels
are joined (:data:`JOINT_COLOUR`), the small-region check at ``fast`` and the tile
and window sizes.
"""

from __future__ import annotations

import numpy as np

from models.decoders.guided_puma import MAX_MOVES, WHOLE_FRAME_PIXELS
from models.decoders.registry import DecoderSpec, available_decoders
from models.formation import SensorParams

QUALITIES: tuple[str, ...] = ("fast", "balanced", "best")
#: Network tiers tried in order for each quality level; the first installed one runs
#: (``balanced`` and ``best`` first pick by the measured PSNR in the model cards, see
#: :data:`NET_BY_PSNR`). ``fast`` runs the half-resolution tiny net: as accurate as the
#: half-resolution small net and about a third faster. Measured (auto-fast, 2026-11-27,
#: EPYC, tiny-s2d against small-s2d, both with the clip fill's quarter rule): val-256
#: mantissa 22.91 / 22.76 dB, at read noise 0.01 22.85 / 22.67; modulo 22.76 / 22.91,
#: at 0.01 22.65 / 21.98; 28 tuning crops of the training scenes mantissa 24.14 /
#: 24.35, at 0.01 23.85 / 24.34, modulo 24.27 both, at 0.01 23.84 / 24.00; glows 48.48
#: / 48.75; mostly-dark 42.68 / 42.59: a mean difference of -0.02 dB over the ten sets.
#: bench.tradeoff: 9.3 ms a val-256 frame, 107.5 frames/s (with small-s2d 13.4 ms, 02:28
#: UTC). Perceptual metrics split (against small-s2d with the half rule): val-256
#: mantissa PU21-PSNR 25.56 / 25.83 dB and SSIM 0.838 / 0.844, modulo 25.26 / 24.60 dB
#: and 0.838 / 0.836. It gets fewer of the brightest pixels right (val-256 mantissa
#: W = 3: 2.4% against 12.3%); balanced is the level for bright scenes. (On 2026-11-25
#: an earlier tiny-s2d net was 0.1-0.9 dB below small-s2d, and until the clip fill's
#: quarter rule the shipped one left a small lamp's core dark, so small-s2d ran until
#: 2026-11-27.)
TIER_LADDER: dict[str, tuple[str, ...]] = {
    "fast": (
        "mantissanet-tiny-s2d",
        "mantissanet-small-s2d",
        "mantissanet-tiny",
        "mantissanet-small",
    ),
    "balanced": ("mantissanet-small-s2d", "mantissanet-tiny", "mantissanet-small"),
    "best": ("mantissanet-base", "mantissanet-small", "mantissanet-tiny"),
}
#: Qualities that pick the net whose refinement (``<net>+puma``) measured the highest
#: val-256 PSNR on the frame's encoding, among nets of at most this many GFLOPs per
#: 256x256 frame (None: any). Measured (auto-balanced, val-256, 2026-11-25, before guided
#: PUMA weighed pairs by reliability): mantissa with tiny 23.93 dB, small-s2d 23.75, small
#: 23.63; modulo with small-s2d 23.70, small 23.37, tiny 23.35: the same order as the
#: cards' refined PSNR, so balanced follows them too, capped below the base tier's 8
#: GFLOPs. Since that change the cards rank small-s2d first on both encodings, so
#: balanced and best both run it.
NET_BY_PSNR: dict[str, float | None] = {"balanced": 4.0, "best": None}
#: Pixel min-cuts of guided PUMA after the network per quality (0: no refinement; a
#: refinement starts with its region moves, at balanced until they converge: see
#: :mod:`models.decoders.region_moves`). Measured on val-256 (bench.accuracy,
#: 2026-11-25 17:38 UTC, both with the small-s2d net): mantissa balanced 24.02 dB in 52
#: ms, best 24.30 dB in 69 ms; modulo 24.00 against 23.87 dB. Earlier, with the small net in
#: both: balanced 23.72 dB, best 23.52 dB. The route, not the budget, makes that
#: difference: balanced's stitched W refined to convergence measured 23.69 dB, best's
#: whole-frame W with two cuts 23.52 dB (both with the small net). The two
#: routes differ on 7 of 24 frames, by 1.6-2.2 dB either way (a region one wrap off),
#: and best wins on the mostly-dark set (46.12 against 45.97 dB). Neither fewer jumps
#: per frame (23.55 dB) nor a region vote between the two (23.48 dB) picks the right
#: one, so best keeps its route: it equals its net's converged refinement, and
#: :func:`most_accurate_net` picks the net whose refinement measured best (on mantissa
#: small-s2d+puma, 24.30 dB, since guided PUMA weighs pairs by reliability; before that
#: base-noise+puma at 23.99 dB, and before the base net was trained longer tiny+puma at
#: 23.88 dB; ranked by the nets' own PSNR it would run base-noise+puma, 23.92 dB).
REFINEMENT: dict[str, int] = {"fast": 0, "balanced": 2, "best": MAX_MOVES}
#: Qualities that make a colour frame's channels consistent once each is decoded
#: (:func:`models.decoders.colour.harmonise`; see that module for what it gains), each
#: up to frames of this many pixels (None: any size). The join costs about 2.5 us per
#: pixel at every size (0.15 s at 256x256, 0.7 s at 512x512, 2.5 s at 1024x1024 on a
#: synthetic frame whose channels auto-balanced decoded in 0.54 s), so balanced joins
#: frames up to 512x512 and best any frame. Not ``fast``: it would cost more than the
#: channels.
JOINT_COLOUR: dict[str, int | None] = {"balanced": 512 * 512, "best": None}
#: Stand-in for hard tiles when no learned decoder is installed.
CLASSICAL_FALLBACK = "itoh"
#: Without refinement, regions where the stitched W disagrees with this decoder's take
#: its answer when it makes fewer jumps across their border
#: (:func:`models.decoders.region_vote.region_vote`)...
SMALL_REGION_CHECK = "itoh"
#: ...if they cover at most this fraction of the frame. Measured (auto-fast, PSNR,
#: 2026-11-25) without the check / at 0.5% / 1.5% / 6%: val-256 mantissa 21.31 / 21.47
#: / 21.42 / 21.42 dB, modulo 20.94 / 21.02 / 21.02 / 21.04, mostly-dark 28.92 / 44.86
#: / 44.88 / 44.88 (itoh 44.89), 512x512 33.62 / 35.19 / 36.33 / 36.33, 1024x1024
#: 37.96 / 38.17 / 38.17 / 38.17. Unbounded, large regions go to itoh's least-squares
#: answer and val-256 falls to 18.99 dB (itoh 18.60); so a larger region switches only
#: on a decisive vote (:mod:`models.decoders.region_vote`: itoh jumps on at most 5% of
#: its border, the net on at least half; a smooth lamp's core the net left short; since
#: 2026-11-28, glows 48.48 -> 52.24 dB, the other sets unchanged). After a refinement
#: the check changes nothing (balanced, best: within 0.03 dB), so only ``fast`` runs it.
SMALL_REGION_FRACTION = 0.015
#: Share of a frame its hard tiles' network windows (with their margins; overlaps
#: count twice) must cover for the frame to go whole to the network, in one call,
#: refined whole; below it the tiles are routed and the hard ones refined in boxes
#: (:func:`whole_frame_cover`). One call is cheaper once the windows cover the frame
#: (fast and balanced: val-256 mantissa, auto-fast 54 against 74 ms, 20.78 against
#: 20.66 dB). Best decodes frames up to the size guided PUMA refines whole
#: (:data:`models.decoders.guided_puma.WHOLE_FRAME_PIXELS`) whole whenever they have a
#: residue: routed tiles trust borders that may cross sharp edges (jumps over half a
#: wrap that leave no residue), which measured about 2 points of W below the net alone
#: on val-256, and a glows frame whose windows cover 23% of it lost 2.9 dB routed.
#: Larger frames, which guided PUMA refines in windows anyway, are routed below 30%.
#: Measured at best (2026-11-28, dB; frames by the share their windows cover), routing
#: below 30% against 50% against never: val-256 mantissa 25.12 / 25.15 / 25.12 (its two
#: frames at 38%: 42.60 -> 42.61 and 29.67 -> 30.35 dB routed), modulo 24.94 / 24.84 /
#: 24.94 (the same frames 42.70 -> 41.84 and 30.78 -> 29.28); mostly-dark 45.45 / 45.69
#: / 45.45 (a frame at 46%: 30.20 -> 31.64); 1024x1024 (18%) 38.20 / 38.20 / 38.16 dB
#: in 0.50 against 4.8-10.2 s; a 512x512 frame (26%) 33.26 dB either way in a third
#: of the time; glows 52.57 against 52.80 dB (the frame at 23%: 47.43 against 50.30).
#: Routing wherever the windows do not cover the frame (balanced's rule) lost 0.2 dB on
#: val-256 mantissa, 0.6 on the val panoramas and 6.6 on the pan/zoom frames (mantissa).
WHOLE_FRAME_COVER: dict[str, float] = {"fast": 1.0, "balanced": 1.0, "best": 0.3}


def whole_frame_cover(quality: str, pixels: int) -> float:
    """The share of a frame of ``pixels`` its hard windows must cover for ``quality`` to
    decode it whole (:data:`WHOLE_FRAME_COVER`; 0 at best up to the size guided PUMA
    refines whole: any residue)."""
    if quality == "best" and pixels <= WHOLE_FRAME_PIXELS:
        return 0.0
    return WHOLE_FRAME_COVER[quality]
#: Tile side in pixels. 128-px tiles measured more accurate on val-256 (W accuracy, mantissa:
#: fast 87.0% vs 85.3%, balanced 89.9% vs 88.0%; modulo: 87.4% vs 80.2%, 89.4% vs 86.6%) but
#: send more pixels to the network on frames with scattered hard spots (1024x1024 synthetic:
#: 27% vs 8% of pixels, balanced 1.2 s vs 0.56 s per frame, 98.8% vs 99.7%), so 64 stays.
#: Again after guided PUMA weighed pairs by reliability (balanced, 2026-11-25): 128 px
#: 24.30 against 24.02 dB on val-256 mantissa, but 23.85 against 24.00 on modulo, 597
#: against 174 ms at 512x512 and 1.00 against 0.22 s at 1024x1024.
DEFAULT_TILE = 64
#: Touching hard tiles share a network window within blocks of this many tiles a side
#: (4 x 64 px: the nets' 256-px val size). Measured (W accuracy, fast / balanced):
#: val-256 86.8 / 90.4% at every size; 512x512 (2 frames) 97.6 / 99.3% with one tile
#: per window, 98.1 / 99.4% at 4, but 68.3 / 69.7% unbounded and 98.1 / 68.7% at 2:
#: there the spanning tree of :mod:`models.tile_reconcile` followed one wrong border
#: and put 60% of a frame one wrap high. (Offsets at the least L1 disagreement with
#: every border vote fixed that but lost 9-12 points on val-256, where border votes
#: cross aliased edges, so the tree stays.)
GROUP_TILES = 4


def measured_psnr(spec: DecoderSpec, encoding: str, refined: bool = False) -> float | None:
    """The val-256 PSNR (dB, no read noise) on ``encoding`` from a decoder's model cards;
    with ``refined``, that of ``<decoder>+puma`` (guided PUMA to convergence)."""
    val256 = spec.figures.get(encoding, {}).get("val256_refined" if refined else "val256", {})
    psnr = val256.get("read_noise_0", {}).get("psnr")
    return float(psnr) if psnr is not None else None


def net_gflops(spec: DecoderSpec, encoding: str) -> float:
    """GFLOPs per 256x256 frame of a learned decoder's model for ``encoding`` (from its
    card; infinite when it has no model for that encoding)."""
    return float(spec.figures.get(encoding, {}).get("gflops_256", np.inf))


def most_accurate_net(params: SensorParams, max_gflops: float | None = None) -> str | None:
    """The installed ``mantissanet-*`` decoder (of at most ``max_gflops`` per 256x256
    frame, when given) whose refinement (``<net>+puma``, what ``best`` runs) measured the
    highest val-256 PSNR on the frame's encoding; ranked by the nets' own PSNR when no
    card states a refined one (None when no card states either). The two rankings
    differ: on mantissa the tiny net alone is 0.7 dB below the small one, refined it is
    0.28 dB above."""
    nets = [
        spec
        for spec in available_decoders()
        if spec.name.startswith("mantissanet-")
        and (max_gflops is None or net_gflops(spec, params.encoding) <= max_gflops)
    ]
    for refined in (True, False):
        scored = [
            (psnr, spec.name)
            for spec in nets
            if (psnr := measured_psnr(spec, params.encoding, refined)) is not None
        ]
        if scored:
            return max(scored)[1]
    return None
