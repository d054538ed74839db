"""Guided graph-cut refinement: ``<decoder>+puma`` corrects any decoder's W with PUMA.

A winding net's errors come in regions: the rings of a bright light source left
one wrap or more short (the nets never predict W >= 3), a few false wraps on a
dark frame, a whole tile off by one. Along the border of such a region the
decoded ``u = W + m`` jumps by about a wrap where the codes say the scene is
smooth. PUMA alone (:mod:`models.decoders.graphcut`) removes such jumps, but on
real scenes it also removes the true jumps at steep edges, which the nets get
right from context. The refinement keeps both kinds of evidence, minimising

    E(K) = sum over neighbour pairs of w_ij |u_j - u_i| + lam * sum c(K - K_guide)

from ``K = K_guide`` (the guide decoder's W), with

- ``w_ij`` the pair's reliability: ``exp(-(D_i + D_j) / RELIABILITY_SCALE)`` from the
  :func:`curvature` ``D`` of its pixels (Herraez's second differences: about 0 where
  the codes are smooth, large across steps, where the wrapped difference is least
  likely to be the true one), times :data:`RESIDUE_WEIGHT` on pairs within
  :data:`RESIDUE_REACH` pixels of a residue (a 2x2 loop whose wrap jumps do not sum
  to zero: the Itoh condition fails there, so the guide decides);
- a small ``lam`` (:data:`PRIOR_WEIGHT`): the guide's W is evidence about regions,
  not independent pixels. A region of area ``A`` whose border has ``L`` unambiguous
  pairs that disagree with the codes changes when ``L > lam * A`` (a disc of radius
  ``R`` when ``R < 2 / lam``), while a large region bounded by steep edges keeps the
  guide's answer;
- ``c(d) = -d`` below the guide and :data:`ABOVE_FACTOR` ``* d`` above it: the nets
  under-count (they never predict W >= 3), so raising a region costs half as much
  as lowering it.

The reliability factor and the cheaper rise were measured together (2026-11-25, mean
PSNR; 6-10 frames per clip of the video set, 14 training-scene crops per exposure).
Every net's refinement gains on val-256 (the cards' ``val256_refined``): mantissa
small-s2d 23.87 -> 24.30 dB, tiny 23.88 -> 24.13, small 23.60 -> 24.10, base 23.94 ->
24.09, base-noise 23.99 -> 23.92; modulo small-s2d 23.36 -> 23.87, small 23.28 -> 23.70.
Small-s2d thus became the net ``auto`` refines at best and balanced: mantissa best
23.99 -> 24.30 dB, balanced 23.93 -> 24.02; modulo 23.36 -> 23.87 and 23.70 -> 24.00;
the pan/zoom frames (a sky reached only through its cloud contours) 24.6 -> 37.6 dB at
balanced (mantissa); the static noisy clip +1.3 dB at best; mostly-dark frames 46.17 ->
45.30 dB at best and 45.99 -> 45.59 at balanced (small-s2d's guide is worse there than
base-noise's). With the nets ``auto`` used before, each change alone measured less: the
reliability factor alone lost 0.35 dB at balanced on mantissa val-256 (four venice
frames, bright clouds the tiny net under-counts, lost 0.6-2.7 dB) and 0.2-1.0 dB on the
pan/zoom frames; the cheaper rise alone took 25-30% more time per frame for smaller
gains (pan/zoom at best +2.7 dB, modulo val-256 at best +0.18 dB).

W is confined to the encoding's range (0 to :func:`models.formation.max_winding`)
during the moves (:attr:`models.decoders.graphcut.PumaEnergy.bounds`), not clipped
after them: on the pan/zoom clip's first frame, from the tiny net's or itoh's W, the
least energy put the dark ground at W = -1 under the sky at 0, and the clip to 0 then
lowered the sky again (71.6% of W right; confined, 99.96%). Measured with it
(2026-11-28, auto-best / auto-balanced, dB, against lam 0.007 unconfined): val-256
mantissa 25.11 -> 25.12 / 24.92 -> 24.93, modulo 24.91 -> 24.94 / 24.85 -> 24.90;
training-scene crops mantissa 27.93 -> 27.97 / 27.70 -> 27.74, modulo 27.56 -> 27.63 /
26.94 -> 27.20; mostly-dark 45.53 -> 45.45 / 45.80 -> 45.70; glows 35.80 -> 35.70;
pan/zoom mantissa 46.91 -> 48.60 / 40.94 -> 41.03, modulo 47.24 / 42.02 -> 43.81.

The moves keep W within that range but not its constant, so ``<decoder>+puma`` (and a
stream's anchoring keyframe) anchors the refined W as every decoder anchors its own
(:meth:`GuidedPumaDecoder.refine_anchored`: the darkest pixels at W = 0). Raising a
region costs half as much as lowering one, so from itoh's W on the sunrise clip's dark
first frame (half 0, half 1 on a frame that never wraps) the least energy lifted the
whole frame to W = 1 (0.2% of W right). Measured (2026-11-28, dB / % of W right):
itoh+puma val-256 mantissa 19.89 / 57.8 -> 20.46 / 68.1, modulo 19.26 / 59.0 -> 20.02 /
70.3, training-scene crops 20.26 -> 22.17 and 21.89 -> 22.28 dB, six sunrise frames
11.15 -> 18.31 and 13.24 -> 17.93 dB; the nets' refinements never moved (their
guides' W already sits where the frame's darkest pixels are 0), nor did any set of
mostly-dark, glow or pan/zoom frames. The sunrise stream with itoh as spatial decoder:
16.27 -> 40.94 dB (mantissa), 17.72 -> 42.73 dB (modulo). ``auto`` refines its stitched
W (anchored before) without anchoring again: anchored after, it moved only the sunrise
frames at balanced (mantissa 27.17 -> 27.02 dB, W 80.8 -> 81.3%).

All terms are convex, so PUMA's +1/-1 binary moves (one min-cut each) reach the
global minimum of a frame of up to :data:`WHOLE_FRAME_PIXELS`; larger frames are
refined in overlapping :data:`WINDOW`-px windows stitched with integer offsets.
The first :data:`REGION_MOVES` moves are region moves
(:mod:`models.decoders.region_moves`): each consistent region of the guide moves
whole, on a graph 3-70x smaller than the pixel grid, so the pixel moves that follow
start near the minimum and need fewer, cheaper cuts. From the tiny net's W on val-256
(2 quiet AMD EPYC cores, 2026-11-25), a pixel cut costs 14.5 ms at 256x256 and a region
cut 4.3 ms (medians).
A refinement with region moves and a budget below :data:`MAX_MOVES` (``auto`` at
``balanced``) runs its region moves to convergence on one partition
(:func:`models.decoders.region_moves.region_descent`, :data:`DESCENT_MOVES`): two
lift a region by one wrap at most, and a glow's core the net left three wraps short
stayed short. It cuts its pixel moves on a narrow band around the pixels that can gain
(:mod:`models.decoders.band_moves`): its two pixel cuts took 12-25% less time on
val-256 with the same W. Without region moves first the pixel cuts must move whole
regions, which a band cannot: the temporal refinement (two pixel cuts, no region
moves) lost 1.9 dB on the pan/zoom clip with mantissanet-tiny (bench.video), so it
keeps full cuts.
Measured on val-256 (mantissanet-small guide, 2026-11-25): 22.17 -> 23.52 dB; the
converged pixel refinement took about 6 cuts and 106 ms, 2 region + 2 pixel cuts
reach the same 23.52 dB in 43 ms (``max_moves=2``, what ``auto`` runs at balanced).
Earlier runs (bench.tradeoff): mostly-dark frames 23.4 -> 46.1 dB; 512x512 frames
27.9 -> 36.3 dB (itoh 36.3).

Failure modes: a region the guide got wrong whose border is all near residues
(foliage against the sky) keeps the guide's answer; so does a bright, textured region
the guide under-counts (clouds round the sun), whose high curvature weakens its pairs;
a large region bounded by a smooth-looking aliased edge (a jump of about one wrap
everywhere along it) shifts when ``lam`` is too small.
"""

from __future__ import annotations

import re
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from models.decoders.band_moves import BandGraph, best_band_move
from models.decoders.base import Decoder, anchor_offset, anchor_winding, refuse_empty
from models.decoders.classical import wrap_difference
from models.decoders.graphcut import (
    PairWeights,
    PumaEnergy,
    PumaResult,
    best_pixel_move,
    minimise,
)
from models.decoders.learned import load_cards, stitch_overlapping
from models.decoders.region_moves import best_region_move, region_descent
from models.decoders.registry import DecoderSpec, get_decoder, refuse_budget_inside
from models.decoders.registry import resolve as resolve_guide
from models.decoders.saturation import fill_saturated
from models.errors import InvalidInputError, echo
from models.formation import SensorParams, clip_winding, max_winding
from models.scene_analysis import residue_pixels
from models.tile_reconcile import common_offset

SUFFIX = "+puma"
#: The suffix as the registry finds it in a name (:func:`models.decoders.registry.resolve`).
SUFFIX_PATTERN = rf"{re.escape(SUFFIX)}(?P<moves>[1-9][0-9]*)?"
NAME = re.compile(rf"(?P<guide>.+){SUFFIX_PATTERN}")
#: A name of ``+puma`` followed by something that is not a move count K (``+puma0``,
#: ``+puma-1``, ``+puma02``, ``+pumax``): refused naming K's range (:func:`check_moves`).
BAD_MOVES = re.compile(rf"(?P<guide>.+){re.escape(SUFFIX)}(?P<moves>[^+]+)")
NAME_PATTERNS = (
    "<decoder>+puma (the decoder's W refined by guided graph-cut unwrapping, "
    "e.g. mantissanet-small+puma)",
    "<decoder>+puma<K> (the same with at most K min-cuts, e.g. mantissanet-small+puma2)",
)
#: ``lam``: prior weight per pixel and wrap of disagreement with the guide. Measured
#: (2026-11-28, mean PSNR dB, auto-best / auto-balanced, lam 0.01 -> 0.007): val-256
#: mantissa 25.10 -> 25.11 / 24.82 -> 24.92, modulo 24.94 -> 24.91 / 24.77 -> 24.85; 28
#: crops of the training scenes mantissa 27.68 -> 27.93 / 27.58 -> 27.70, modulo 27.70 ->
#: 27.56 / 26.97 -> 26.94; mostly-dark 45.30 -> 45.53 / 45.59 -> 45.80; glows 35.77 ->
#: 35.80 both; six frames of the pan/zoom clip mantissa 38.79 -> 46.91 / 37.81 -> 40.94,
#: modulo 47.24 both / 36.42 -> 42.02. There the net leaves a sky of 28% of the frame a
#: wrap short; its border is weak evidence (cloud contours, high curvature), and at 0.01
#: the energy of the wrong sky was below the truth's. 0.008 kept half the clip's gain,
#: 0.006 and 0.005 lost 0.13-0.14 dB at best on val-256 (balanced gained up to 0.18).
PRIOR_WEIGHT = 0.007
#: The prior's cost per wrap above the guide, as a fraction of its cost per wrap below
#: (:class:`models.decoders.graphcut.PumaEnergy`): the winding nets under-count W.
ABOVE_FACTOR = 0.5
#: Weight of neighbour pairs near a residue (where the codes do not decide W).
RESIDUE_WEIGHT = 0.1
#: Pairs touching a pixel within this many pixels of a residue get RESIDUE_WEIGHT.
RESIDUE_REACH = 1
#: Scale (wraps) of the reliability factor ``exp(-(D_i + D_j) / scale)`` of each pair
#: (:func:`pair_weights`).
RELIABILITY_SCALE = 1.5
#: The (before, after) neighbours of each line through a pixel, as slices of the frame
#: padded by one: along rows, along columns and along both diagonals.
_OPPOSITE_NEIGHBOURS = (
    ((slice(1, -1), slice(None, -2)), (slice(1, -1), slice(2, None))),
    ((slice(None, -2), slice(1, -1)), (slice(2, None), slice(1, -1))),
    ((slice(None, -2), slice(None, -2)), (slice(2, None), slice(2, None))),
    ((slice(None, -2), slice(2, None)), (slice(2, None), slice(None, -2))),
)
#: Bound on min-cuts per frame (one +1 or -1 move each; a guide short by k wraps needs
#: about 2k, real val-256 frames 4-9).
MAX_MOVES = 100
#: Moves tried in turn: grow K by one wrap, shrink it by one.
JUMPS = (1, -1)
#: Region moves (:mod:`models.decoders.region_moves`) made before the pixel moves: they
#: shift the guide's wrong regions whole at a third of a pixel cut's cost, so the pixel
#: moves start near the minimum. Measured on val-256 (both encodings, small and tiny
#: guides): 2 region + 2 pixel cuts reach the converged pixel refinement's PSNR within
#: 0.01 dB in 40-50 ms, where pixel cuts alone need about 6 cuts and 106-131 ms;
#: region moves alone stop short where a wrong region joins a right one across an
#: aliased edge (tiny guide: 22.0 dB against 23.3).
REGION_MOVES = 2
#: A budgeted refinement (``max_moves`` below :data:`MAX_MOVES`, with region moves) runs
#: its region moves to convergence instead, on one partition, within this many cuts
#: (:func:`models.decoders.region_moves.region_descent`; val-256 frames converge in
#: 5-11): two lift a region by one wrap at most, and a glow's core the net left three
#: wraps short stayed short.
DESCENT_MOVES = 16
#: Frames of up to this many pixels are refined whole. Measured with the small guide:
#: 512x512 whole 3.6 s / 36.34 dB against 6.8 s / 34.32 dB in 256-px windows (the
#: windows' stitching loses regions); 1024x1024 whole 17 s against 13 s in windows,
#: both 38.20 dB.
WHOLE_FRAME_PIXELS = 512 * 512
#: Larger frames are refined in overlapping windows of this side (px), stitched with
#: integer offsets.
WINDOW = 256
WINDOW_OVERLAP = 64
#: Given the pixels whose guide may be wrong (``doubtful``), only boxes around them are
#: refined: each connected group of doubtful pixels grown by this many px of context.
#: Measured with auto-balanced (2026-11-25, one core busy), refining the whole frame
#: against boxes with 16 / 32 px of context: the same PSNR and W to 0.01 on the
#: mostly-dark set (45.99 dB; 42 -> 25 ms), 512x512 (36.52 dB; 312 -> 158 / 234 ms), 12
#: val-256 frames and 15 frames of the pan/zoom clip (whole frames mostly: 80-85 ms).
DOUBTFUL_CONTEXT = 32
#: The counts a refinement reports (summed over its boxes), besides the changed fraction.
REFINEMENT_COUNTS = ("windows", "region_moves", "moves")


def refinement_boxes(doubtful: NDArray[np.bool_]) -> list[tuple[slice, slice]]:
    """The boxes :meth:`GuidedPumaDecoder.refine` refines for these doubtful pixels (bool,
    H x W): one per connected group of them grown by :data:`DOUBTFUL_CONTEXT` px."""
    grown = ndimage.binary_dilation(doubtful, iterations=DOUBTFUL_CONTEXT)
    return [box for box in ndimage.find_objects(ndimage.label(grown)[0]) if box is not None]


def curvature(m: NDArray[np.float64]) -> NDArray[np.float32]:
    """Herraez's second-difference measure per pixel (H x W, wraps): the root sum of
    squares of the wrapped second differences along rows, columns and both diagonals.
    About 0 where ``m`` is smooth (noise, gentle gradients, clean wrap contours), large
    at steps and aliased edges, where a neighbour's wrapped difference is least likely
    to be the true one. Border pixels see their missing neighbour as themselves."""
    padded = np.pad(m.astype(np.float32), 1, mode="edge")
    centre = padded[1:-1, 1:-1]
    total = np.zeros(m.shape, np.float32)
    for before, after in _OPPOSITE_NEIGHBOURS:
        step = wrap_difference(padded[before] - centre) - wrap_difference(centre - padded[after])
        total += step * step
    return np.sqrt(total)


def pair_weights(m: NDArray[np.float64]) -> PairWeights:
    """Each neighbour pair's weight: ``exp(-(D_i + D_j) / RELIABILITY_SCALE)`` from the
    :func:`curvature` ``D`` of its two pixels, times :data:`RESIDUE_WEIGHT` for pairs
    touching a residue."""
    near = residue_pixels(m, RESIDUE_REACH)
    reliable = curvature(m).astype(np.float64)
    right = np.exp(-(reliable[:, 1:] + reliable[:, :-1]) / RELIABILITY_SCALE)
    down = np.exp(-(reliable[1:] + reliable[:-1]) / RELIABILITY_SCALE)
    right = np.where(near[:, 1:] | near[:, :-1], RESIDUE_WEIGHT * right, right)
    down = np.where(near[1:] | near[:-1], RESIDUE_WEIGHT * down, down)
    return right, down


class GuidedPumaDecoder(Decoder):
    """A guide decoder's W, refined by the guided PUMA energy (module docstring)."""

    def __init__(
        self,
        guide: Decoder,
        prior_weight: float = PRIOR_WEIGHT,
        max_moves: int = MAX_MOVES,
        region_moves: int = REGION_MOVES,
    ) -> None:
        self.guide = guide
        self.prior_weight = prior_weight
        self.max_moves = max_moves
        self.region_moves = region_moves
        self.budgeted = bool(region_moves) and max_moves < MAX_MOVES
        self.pixel_move = best_band_move if self.budgeted else best_pixel_move
        self.name = refined_name(guide.name, max_moves)  # type: ignore[misc]
        self.version = guide.version
        # A guide that fills clipped blobs (``auto``) gets them filled again after the
        # refinement, whose energy does not know the clip and lowers them.
        self.fills_saturation = guide.fills_saturation  # type: ignore[misc]

    def unwraps(self, params: SensorParams) -> bool:
        return self.guide.unwraps(params)

    def predict_winding(self, m: NDArray[np.float64], params: SensorParams) -> NDArray[np.int64]:
        return self.explain_winding(m, params)[0]

    def join_channels(
        self, planes: NDArray[np.float64], winding: NDArray[np.int64], params: SensorParams
    ) -> tuple[NDArray[np.int64], dict[str, Any]]:
        """The guide's way with a colour frame's channels, after each is refined."""
        return self.guide.join_channels(planes, winding, params)

    def explain_winding(
        self, m: NDArray[np.float64], params: SensorParams
    ) -> tuple[NDArray[np.int64], dict[str, Any]]:
        """Refined W and facts: the guide's details, min-cuts made, pixels changed (and
        the clipped blobs filled again, judged on the guide's W, when the guide fills
        them: ``auto-fast+puma`` on val-256 mantissa 24.43 -> 24.71 dB)."""
        guide, details = self.guide.explain_winding(m, params)
        winding, facts = self.refine_anchored(m, guide, params)
        winding, saturation = self.refilled(m, winding, guide, params)
        if saturation is not None:
            facts["saturation"] = saturation
        return winding, {"guide": self.guide.name, "guide_details": details, **facts}

    def refilled(
        self,
        m: NDArray[np.float64],
        refined: NDArray[np.int64],
        guide: NDArray[np.int64],
        params: SensorParams,
    ) -> tuple[NDArray[np.int64], dict[str, Any] | None]:
        """``refined`` (int W, H x W) with the guide's clipped blobs set to the clip again
        (:func:`models.decoders.saturation.fill_saturated`, judged on ``guide``), and the
        fill's facts; unchanged with None when the guide does not fill clipped blobs."""
        if not self.fills_saturation:
            return refined, None
        return fill_saturated(refined, m, params, guide)

    def refine(
        self,
        m: NDArray[np.float64],
        guide: NDArray[np.int64],
        params: SensorParams,
        doubtful: NDArray[np.bool_] | None = None,
    ) -> tuple[NDArray[np.int64], dict[str, Any]]:
        """``guide`` (int W, H x W) refined on ``m``: W clipped to the encoding's range,
        and facts (windows refined, region and pixel min-cuts made, fraction of pixels
        changed). Up to ``region_moves`` region cuts come first, then pixel cuts up to
        the ``max_moves`` budget.

        ``doubtful`` (bool, H x W; None: everywhere) marks the pixels whose guide may
        be wrong; the others keep the guide. Each connected group of them is refined on
        its own box, grown by :data:`DOUBTFUL_CONTEXT` px of context, whose constant is
        aligned to the guide on the box's other pixels. A frame without pixels is refused.
        """
        refuse_empty(m)
        if doubtful is None or doubtful.all():
            return self._refine_frame(m, guide, params)
        winding = guide.copy()
        boxes: list[dict[str, Any]] = []
        for box in refinement_boxes(doubtful):
            refined, facts = self._refine_frame(m[box], guide[box], params)
            trusted = ~doubtful[box]
            if trusted.any():
                refined = refined + common_offset(guide[box][trusted], refined[trusted])
            refined = clip_winding(refined, params)
            winding[box] = np.where(doubtful[box], refined, guide[box])
            boxes.append(facts)
        totals = {key: sum(facts[key] for facts in boxes) for key in REFINEMENT_COUNTS}
        return winding, _facts(winding, guide, **totals)

    def refine_anchored(
        self, m: NDArray[np.float64], guide: NDArray[np.int64], params: SensorParams
    ) -> tuple[NDArray[np.int64], dict[str, Any]]:
        """``guide`` (int W, H x W, a whole frame's spatial decode) refined whole, then
        anchored as every decoder's W is (:func:`models.decoders.base.anchor_winding`:
        the darkest pixels at W = 0), and :meth:`refine`'s facts with the wraps taken
        off (``anchor_shift``). The moves keep W within the encoding's range but not its
        constant: from a guide whose W is half 0 and half 1 on a frame that never wraps
        (itoh's on a dark frame), they raise the whole frame to 1 at the least energy.
        """
        refined, facts = self.refine(m, guide, params)
        winding = anchor_winding(refined, params)
        counts = _counts(facts)
        return winding, {**_facts(winding, guide, **counts), "anchor_shift": anchor_offset(refined)}

    def refine_within(
        self,
        m: NDArray[np.float64],
        guide: NDArray[np.int64],
        params: SensorParams,
        band: NDArray[np.bool_],
    ) -> tuple[NDArray[np.int64], dict[str, Any]]:
        """``guide`` (int W, H x W) refined by pixel moves confined to ``band`` (bool,
        H x W; :class:`models.decoders.band_moves.BandGraph`): every other pixel keeps
        the guide, and frames of any size are cut whole (the graph is the band's). The
        moves are compared by the share of the energy they can change. Facts as
        :meth:`refine` reports them; a frame without pixels is refused."""
        refuse_empty(m)
        energy = self._energy(m, guide, params)
        solve, value = BandGraph.of(band).moves(energy)
        start = clip_winding(guide, params)
        result = minimise(m, start, energy, JUMPS, self.max_moves, solve, value=value)
        winding = clip_winding(result.winding, params)
        return winding, _facts(winding, guide, windows=1, region_moves=0, moves=result.moves)

    def _refine_frame(
        self, m: NDArray[np.float64], guide: NDArray[np.int64], params: SensorParams
    ) -> tuple[NDArray[np.int64], dict[str, Any]]:
        """:meth:`refine` everywhere: whole, or in overlapping windows when large."""
        moves: list[int] = []
        region_cuts: list[int] = []

        def refine_window(rows: slice, cols: slice) -> NDArray[np.int64]:
            window, prior = m[rows, cols], guide[rows, cols]
            energy = self._energy(window, prior, params)
            start = clip_winding(prior, params)
            if self.region_moves:
                first = self._region_step(window, start, energy)
                start = first.winding
                region_cuts.append(first.moves)
            result = minimise(window, start, energy, JUMPS, self.max_moves, self.pixel_move)
            moves.append(result.moves)
            return result.winding

        side = max(m.shape) if m.size <= WHOLE_FRAME_PIXELS else WINDOW
        refined = stitch_overlapping(m.shape, side, WINDOW_OVERLAP, refine_window)
        winding = clip_winding(refined, params)
        return winding, _facts(
            winding, guide, windows=len(moves), region_moves=sum(region_cuts), moves=sum(moves)
        )

    def _region_step(
        self, m: NDArray[np.float64], guide: NDArray[np.int64], energy: PumaEnergy
    ) -> PumaResult:
        """The region moves that start a refinement: to convergence when budgeted
        (:data:`DESCENT_MOVES`), else :data:`REGION_MOVES` of them."""
        if self.budgeted:
            return region_descent(guide, m, energy, JUMPS, DESCENT_MOVES)
        return minimise(m, guide, energy, JUMPS, self.region_moves, best_region_move)

    def _energy(
        self, m: NDArray[np.float64], guide: NDArray[np.int64], params: SensorParams
    ) -> PumaEnergy:
        """The guided PUMA energy (module doc) of ``m`` (wraps) around ``guide`` (W), W
        confined to the encoding's range (0 to :func:`models.formation.max_winding`)."""
        bounds = (0, max_winding(params))
        return PumaEnergy(1.0, pair_weights(m), guide, self.prior_weight, ABOVE_FACTOR, bounds)


def _counts(facts: dict[str, Any]) -> dict[str, int]:
    """The :data:`REFINEMENT_COUNTS` of a refinement's facts."""
    return {key: facts[key] for key in REFINEMENT_COUNTS}


def _facts(
    winding: NDArray[np.int64], guide: NDArray[np.int64], **counts: int
) -> dict[str, Any]:
    """A refinement's facts: its :data:`REFINEMENT_COUNTS` and the fraction of pixels it
    changed from ``guide``."""
    return {**counts, "changed_fraction": float(np.mean(winding != guide))}


def refined_name(guide_name: str, max_moves: int = MAX_MOVES) -> str:
    """``<guide>+puma``, with the move budget appended when it is not the default."""
    return f"{guide_name}{SUFFIX}{max_moves if max_moves != MAX_MOVES else ''}"


def _spec(guide_name: str, max_moves: int = MAX_MOVES) -> DecoderSpec:
    budget = "" if max_moves == MAX_MOVES else f", at most {max_moves} min-cuts"
    return DecoderSpec(
        name=refined_name(guide_name, max_moves),
        kind="refined",
        description=(
            f"{guide_name}, refined by guided graph-cut unwrapping (PUMA with the "
            f"decoder's W as prior{budget}; fixes whole regions left a wrap off; "
            "about 0.1 s more per 256x256 frame)"
        ),
        factory=lambda: GuidedPumaDecoder(get_decoder(guide_name), max_moves=max_moves),
    )


def resolve(name: str) -> DecoderSpec | None:
    """The spec of ``<decoder>+puma`` or ``<decoder>+puma<K>`` when ``<decoder>`` is a
    known decoder (a clear error otherwise); None for any other name."""
    check_moves(name)
    match = NAME.fullmatch(name)
    if match is None:
        return None
    guide_name = match.group("guide")
    refuse_budget_inside(
        "+puma", resolve_guide(guide_name), "+puma refines after it, past the budget"
    )
    moves = match.group("moves")
    return _spec(guide_name, int(moves) if moves else MAX_MOVES)


def check_moves(name: str) -> None:
    """Refuse ``<decoder>+puma<K>`` whose K is not a whole number of at least 1
    (:data:`BAD_MOVES`): it was an "unknown decoder" listing every decoder, without a
    word on K."""
    match = BAD_MOVES.fullmatch(name)
    if match is None or NAME.fullmatch(name) is not None:
        return
    guide = match.group("guide")
    raise InvalidInputError(
        f"decoder {echo(name)}: the K of <decoder>+puma<K>, the most min-cuts to run, must "
        f"be a whole number of at least 1 (e.g. {echo(guide + SUFFIX + '2')}), not "
        f"{echo(match.group('moves'))}; or leave K out ({echo(guide + SUFFIX)}: at most "
        f"{MAX_MOVES})"
    )


def specs() -> list[DecoderSpec]:
    """The refined version of each installed float winding net (noise-aware ones
    included: ``auto`` at best may run one), ``mantissanet-<tier>+puma``; other guides
    resolve by name."""
    tiers = dict.fromkeys(
        card["decoder"]
        for card in load_cards()
        if card["family"] == "mantissanet" and "quantization" not in card
    )
    return [_spec(name) for name in tiers]
