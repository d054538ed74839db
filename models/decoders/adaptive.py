"""``auto``: spend compute only where a scene needs it.

Per tile (see :mod:`models.scene_analysis`), cheapest first:

1. no wrap edge -> pass-through: W is constant (no network);
2. wrap edges but no residue -> exact path integration of the neighbour jumps
   (every classical unwrapper agrees there; O(pixels));
3. residues (the Itoh condition fails somewhere) -> the network tier chosen by
   the quality level (at ``best`` the most accurate one installed), one call per
   group of touching hard tiles, on the group's bounding box plus a context margin
   (one call per tile measured slower and less accurate: val-256 mantissa,
   auto-fast 43 -> 32 ms/frame, 20.78 -> 21.31 dB); without any learned decoder
   installed, the classical ``itoh`` decoder stands in.

A frame with residues is then refined whole by guided graph-cut unwrapping
(:mod:`models.decoders.guided_puma`) from the stitched W, within a min-cut budget per
quality (:data:`models.decoders.adaptive_policy.REFINEMENT`: none at ``fast``, two at
``balanced``, until it converges at ``best``). Refining the whole frame rather than
each network window lets it see across tile borders: on val-256 (mantissa) balanced
measured 21.65 dB with two cuts per network window, against 23.51 dB refined whole
(best: 23.52). Frames refined in windows (over 512x512) skip the windows that hold no
network-decoded pixel. At ``fast`` (no refinement) the network's small regions are
checked against ``itoh`` instead (:meth:`AdaptiveDecoder.check_small_regions`): it
removes the net's false wraps at steep edges of dark frames for the cost of one itoh
decode (2.7 ms at 256x256).

Last, at every quality, compact blobs that read the sensor's clip value behind an
aliased ring (a lamp or the sun brighter than ``max_wraps``) are set to the clip
(:mod:`models.decoders.saturation`; val-256 +0.65-0.8 dB at each quality). No
network and no unwrapper can count those wraps from the codes. A colour frame's clip
is then filled in every channel that holds it, before the channels are joined
(:meth:`AdaptiveDecoder.join_channels`).

A frame with no residue at all is integrated whole. A frame whose hard tiles with
their margins cover enough of it goes whole to the network
(:data:`models.decoders.adaptive_policy.WHOLE_FRAME_COVER`): at ``fast`` and
``balanced`` its whole area, where one call is cheaper (val-256 mantissa, auto-fast:
54 ms against 74 ms median, interleaved at load 1; 20.78 dB against 20.66, W accuracy
84.70% against 85.26%); at ``best`` always up to 512x512, since per-tile routing
trusts tiles whose borders may cross sharp edges (jumps over half a wrap that leave no
residue), which measured about 2 points of winding accuracy below the network alone,
and 30% of a larger frame, which guided PUMA refines in windows anyway: a 1024x1024
frame with a few hard spots is decoded as accurately routed, in a tenth of the time.
Otherwise tiles are stitched into one consistent W by :mod:`models.tile_reconcile`;
the global offset then comes from the anchoring rule (darkest pixels W = 0), taken
over the tiles known to be exact (pass-through, integration) when there are any.
The route of every pixel is reported.

What each quality runs, and the measurements behind each choice (tiers, refinement
budgets, tile and window sizes), are in :mod:`models.decoders.adaptive_policy`.

Tried and dropped (2026-11-25): sending a frame whose hardest tile is ``sparse``
whole to ``itoh`` (below ``best``). On 190 such seeded synthetic frames it measured as
accurate as the nets (32.23 dB against auto-fast's 32.22) and auto-fast ran the
mostly-dark set in 1.9 instead of 9.7 ms, but on real scenes itoh leaves whole regions
a wrap off behind aliased edges that make no residue: 14 sparse-only crops of the
training scenes 44.8 against 49.6 dB (auto-fast), and the sparse-only frames of the
pan/zoom clip (city) 17.0 against 22.6 dB at fast, 19.9 against 24.9 dB (mantissa)
and 29.7 against 36.7 dB (modulo) at balanced, refined or not. The networks see
those edges from context. Refining itoh's answer on crops around the residues
instead cost as much as the network windows (11-13 ms) and fixed no region.
"""

from __future__ import annotations

from collections import Counter
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from models.decoders.adaptive_policy import (
    CLASSICAL_FALLBACK,
    DEFAULT_TILE,
    GROUP_TILES,
    JOINT_COLOUR,
    NET_BY_PSNR,
    QUALITIES,
    REFINEMENT,
    SMALL_REGION_CHECK,
    SMALL_REGION_FRACTION,
    TIER_LADDER,
    most_accurate_net,
    whole_frame_cover,
)
from models.decoders.base import Decoder, anchor_winding
from models.decoders.colour import harmonise
from models.decoders.filling import filled_then_joined
from models.decoders.guided_puma import GuidedPumaDecoder, refined_name
from models.decoders.region_vote import region_vote
from models.decoders.registry import DecoderSpec, available_decoders, get_decoder
from models.decoders.saturation import fill_saturated
from models.formation import SensorParams
from models.scene_analysis import FrameAnalysis, RegionAnalysis, analyse
from models.tile_reconcile import Tile, integrate_jumps, stitch

PASS_THROUGH = "pass-through"
INTEGRATION = "integration"


class AdaptiveDecoder(Decoder):
    """Routes each tile to the cheapest decoder that is right for it."""

    name = "auto"
    fills_saturation = True

    def __init__(
        self,
        quality: str = "balanced",
        tile: int = DEFAULT_TILE,
        margin: int = 16,
        group: int = GROUP_TILES,
        joint_colour: bool | None = None,
    ) -> None:
        if quality not in QUALITIES:
            raise ValueError(f"quality must be one of {QUALITIES}, got {quality!r}")
        self.quality = quality
        self.joint_colour = quality in JOINT_COLOUR if joint_colour is None else joint_colour
        self.join_max_pixels = JOINT_COLOUR.get(quality)
        self.tile = tile
        self.margin = margin
        self.group = group
        self.name = f"auto-{quality}"

    def hard_tile_decoder(self, params: SensorParams) -> Decoder:
        """The decoder for tiles with residues (its answer is refined afterwards, see
        :meth:`refiner`): at ``balanced`` and ``best`` the installed winding net (within
        the quality's cost cap, :data:`NET_BY_PSNR`) with the highest measured refined
        val-256 PSNR on the frame's encoding; otherwise (or when no card has that
        figure) the quality's first installed tier that supports the encoding; without
        one, the classical fallback."""
        net = None
        if self.quality in NET_BY_PSNR:
            net = most_accurate_net(params, NET_BY_PSNR[self.quality])
        if net is None:
            installed = {spec.name for spec in available_decoders()}
            net = next(
                (
                    name
                    for name in TIER_LADDER[self.quality]
                    if name in installed and get_decoder(name).supports(params)
                ),
                None,
            )
        if net is None:
            return get_decoder(CLASSICAL_FALLBACK)
        return get_decoder(net)

    def refiner(self, params: SensorParams) -> GuidedPumaDecoder | None:
        """Guided PUMA with the quality's min-cut budget around the hard-tile decoder,
        or None when the quality refines nothing."""
        moves = REFINEMENT[self.quality]
        if not moves:
            return None
        refined = get_decoder(refined_name(self.hard_tile_decoder(params).name, moves))
        assert isinstance(refined, GuidedPumaDecoder)
        return refined

    def predict_winding(self, m: NDArray[np.float64], params: SensorParams) -> NDArray[np.int64]:
        return self.explain_winding(m, params)[0]

    def explain_winding(
        self, m: NDArray[np.float64], params: SensorParams
    ) -> tuple[NDArray[np.int64], dict[str, Any]]:
        return self.explain_analysed(m, params, analyse(m, params, self.tile))

    def join_channels(
        self, planes: NDArray[np.float64], winding: NDArray[np.int64], params: SensorParams
    ) -> tuple[NDArray[np.int64], dict[str, Any]]:
        """A colour frame's clips filled in every channel that holds them
        (:func:`models.decoders.filling.filled_then_joined`), then :meth:`harmonised`."""
        return filled_then_joined(planes, winding, params, self.harmonised)

    def harmonised(
        self, planes: NDArray[np.float64], winding: NDArray[np.int64], params: SensorParams
    ) -> tuple[NDArray[np.int64], dict[str, Any]]:
        """A colour frame's channels made consistent when ``joint_colour`` (by default at
        the qualities of :data:`JOINT_COLOUR`, up to its size), or why they were not."""
        if planes.shape[2] != 3 or not self.joint_colour:
            return winding, {}
        pixels = planes.shape[0] * planes.shape[1]
        if self.join_max_pixels is not None and pixels > self.join_max_pixels:
            side = int(np.sqrt(self.join_max_pixels))
            reason = f"not joined: frames over {side}x{side} px are joined at best only"
            return winding, {"reason": reason}
        return harmonise(planes, winding, params)

    def network_calls(
        self, analysis: FrameAnalysis, shape: tuple[int, int]
    ) -> list[tuple[int, int]]:
        """The shape of each call the hard-tile decoder will get for a frame with this
        analysis: none without residues, one call on the whole frame when the windows
        would cover the quality's :data:`WHOLE_FRAME_COVER` of it, else one per window
        of a group of hard tiles (:meth:`hard_windows`)."""
        if analysis.frame.difficulty in ("none", "smooth"):
            return []
        windows = [
            (rows.stop - rows.start, cols.stop - cols.start)
            for rows, cols, _ in self.hard_windows(analysis, shape)
        ]
        pixels = shape[0] * shape[1]
        whole = whole_frame_cover(self.quality, pixels) * pixels
        return [shape] if sum(h * w for h, w in windows) >= whole else windows

    def network_pixels(self, analysis: FrameAnalysis, shape: tuple[int, int]) -> int:
        """Pixels the hard-tile decoder will see for a frame with this analysis (over all
        :meth:`network_calls`)."""
        return sum(h * w for h, w in self.network_calls(analysis, shape))

    def doubtful_pixels(
        self, analysis: FrameAnalysis, shape: tuple[int, int]
    ) -> NDArray[np.bool_] | None:
        """The pixels the network decides (bool, ``shape``; None: the whole frame), which
        the refinement revisits: those of the hard tiles of a routed frame."""
        calls = self.network_calls(analysis, shape)
        if not calls or calls == [shape]:
            return None
        return _hard_tiles(analysis, shape)

    def hard_windows(
        self, analysis: FrameAnalysis, shape: tuple[int, ...]
    ) -> list[tuple[slice, slice, list[RegionAnalysis]]]:
        """The groups of hard tiles (touching tiles, diagonals included), each with one
        window for the network: the group's bounding box grown by the context margin,
        clipped to the frame. One call per group sees more context than one per tile
        and repeats no margin between neighbouring tiles."""
        hard = [region for region in analysis.tiles if _is_hard(region)]
        row_index = {row: k for k, row in enumerate(sorted({t.row for t in analysis.tiles}))}
        col_index = {col: k for k, col in enumerate(sorted({t.col for t in analysis.tiles}))}
        grid = np.zeros((len(row_index), len(col_index)), np.int32)
        for region in hard:
            grid[row_index[region.row], col_index[region.col]] = 1
        labels, _ = ndimage.label(grid, structure=np.ones((3, 3), int))
        groups: dict[tuple[int, int, int], list[RegionAnalysis]] = {}
        for region in hard:
            row, col = row_index[region.row], col_index[region.col]
            key = (int(labels[row, col]), row // self.group, col // self.group)
            groups.setdefault(key, []).append(region)
        windows = []
        for members in groups.values():
            rows = slice(min(t.row for t in members), max(t.row + t.height for t in members))
            cols = slice(min(t.col for t in members), max(t.col + t.width for t in members))
            windows.append((*self._window(rows, cols, shape), members))
        return windows

    def _window(
        self, rows: slice, cols: slice, shape: tuple[int, ...]
    ) -> tuple[slice, slice]:
        """The tile ``rows x cols`` grown by the context margin, clipped to the frame."""
        top, left = max(rows.start - self.margin, 0), max(cols.start - self.margin, 0)
        bottom = min(rows.stop + self.margin, shape[0])
        return slice(top, bottom), slice(left, min(cols.stop + self.margin, shape[1]))

    def explain_analysed(
        self, m: NDArray[np.float64], params: SensorParams, analysis: FrameAnalysis
    ) -> tuple[NDArray[np.int64], dict[str, Any]]:
        """Decode ``m`` given its scene analysis (tiles of ``self.tile`` px)."""
        along_cols, along_rows = analysis.along_cols, analysis.along_rows
        difficulty = analysis.frame.difficulty
        if difficulty == "none":
            return np.zeros(m.shape, np.int64), _report({PASS_THROUGH: m.size}, "no wrap edge")
        if difficulty == "smooth":
            winding = anchor_winding(integrate_jumps(along_cols, along_rows), params)
            return winding, _report({INTEGRATION: m.size}, "no residue")
        winding, report, doubtful = self._decode_hard(m, params, analysis)
        refiner = self.refiner(params)
        if refiner is not None:
            winding, facts = refiner.refine(m, winding, params, doubtful)
            report["refinement"] = {"decoder": refiner.name, **facts}
        elif self.checks_small_regions(params):
            winding, report["small_regions"] = self.check_small_regions(m, winding, params)
        winding, saturation = fill_saturated(winding, m, params)
        if saturation:
            report["saturation"] = saturation
        return winding, report

    def _whole_reason(self, pixels: int) -> str:
        """Why a frame of ``pixels`` went whole to the hard-tile decoder
        (:func:`models.decoders.adaptive_policy.whole_frame_cover`)."""
        share = whole_frame_cover(self.quality, pixels)
        if share >= 1.0:
            return "the hard tiles with their margins cover the frame"
        if share == 0.0:
            return f"quality {self.quality} decodes frames of this size whole"
        return (
            f"the hard tiles with their margins cover {share:.0%} of the frame or more, "
            f"which quality {self.quality} decodes whole"
        )

    def checks_small_regions(self, params: SensorParams) -> bool:
        """Whether frames with residues get :meth:`check_small_regions`: when the quality
        refines nothing and the hard tiles are not already decoded by that decoder."""
        return (
            not REFINEMENT[self.quality]
            and self.hard_tile_decoder(params).name != SMALL_REGION_CHECK
        )

    def check_small_regions(
        self, m: NDArray[np.float64], winding: NDArray[np.int64], params: SensorParams
    ) -> tuple[NDArray[np.int64], dict[str, Any]]:
        """``winding`` with each region of disagreement with :data:`SMALL_REGION_CHECK`
        of at most :data:`SMALL_REGION_FRACTION` of the frame set to that decoder's W
        when it makes fewer jumps across the region's border; and the facts (decoder,
        fraction of pixels changed)."""
        other = get_decoder(SMALL_REGION_CHECK).predict_winding(m, params)
        largest = int(SMALL_REGION_FRACTION * m.size)
        merged, taken = region_vote(winding, other, m, max_region=largest)
        return merged, {"decoder": SMALL_REGION_CHECK, "changed_fraction": float(taken.mean())}

    def unrefined_winding(
        self, m: NDArray[np.float64], params: SensorParams, analysis: FrameAnalysis
    ) -> tuple[NDArray[np.int64], NDArray[np.bool_] | None]:
        """W of a frame with residues before refinement, and the pixels the network
        decided (None: all); what :meth:`refiner` starts from."""
        winding, _, doubtful = self._decode_hard(m, params, analysis)
        return winding, doubtful

    def _decode_hard(
        self, m: NDArray[np.float64], params: SensorParams, analysis: FrameAnalysis
    ) -> tuple[NDArray[np.int64], dict[str, Any], NDArray[np.bool_] | None]:
        """W of a frame with residues, before refinement: the hard-tile decoder on the
        whole frame (when its windows would cover enough of it, :meth:`network_calls`),
        else per tile, stitched; the report; and the pixels the network decided (None:
        all)."""
        along_cols, along_rows = analysis.along_cols, analysis.along_rows
        difficulty = analysis.frame.difficulty
        hard = self.hard_tile_decoder(params)
        if self.network_calls(analysis, m.shape) == [m.shape]:
            winding, facts = hard.explain_winding(m, params)
            reason = f"{difficulty} wraps; {self._whole_reason(m.size)}"
            report = _report({_decoded_by(hard, facts): m.size}, reason)
            return winding, _with_fallback(report, [facts]), None
        pixels: Counter[str] = Counter()
        calls: list[dict[str, Any]] = []
        tiles: list[Tile] = []
        doubtful = _hard_tiles(analysis, m.shape)
        for region in analysis.tiles:
            if _is_hard(region):
                continue
            rows = slice(region.row, region.row + region.height)
            cols = slice(region.col, region.col + region.width)
            if region.difficulty == "none":
                route, relative = PASS_THROUGH, np.zeros((region.height, region.width), np.int64)
            else:
                route = INTEGRATION
                relative = integrate_jumps(
                    along_cols[rows, cols.start : cols.stop - 1],
                    along_rows[rows.start : rows.stop - 1, cols],
                )
            tiles.append(Tile(rows, cols, relative))
            pixels[route] += region.height * region.width
        for window_rows, window_cols, members in self.hard_windows(analysis, m.shape):
            window, facts = hard.explain_winding(m[window_rows, window_cols], params)
            calls.append(facts)
            for region in members:
                top, left = region.row - window_rows.start, region.col - window_cols.start
                relative = window[top : top + region.height, left : left + region.width]
                rows = slice(region.row, region.row + region.height)
                cols = slice(region.col, region.col + region.width)
                tiles.append(Tile(rows, cols, relative))
                pixels[_decoded_by(hard, facts)] += region.height * region.width
        winding = stitch(tiles, m.shape, along_cols, along_rows)
        # Over the whole frame: the tiles known exact may hold none of the darkest
        # pixels (a dark textured corner is a hard tile), and anchoring on them alone
        # then shifted the whole frame a wrap down; on the benchmark sets both anchors
        # give the same W (docs/experiments.md).
        winding = anchor_winding(winding, params)
        reason = f"{difficulty} wraps; quality {self.quality}"
        return winding, _with_fallback(_report(pixels, reason), calls), doubtful


def _is_hard(region: RegionAnalysis) -> bool:
    """Residues in the tile: the hard-tile decoder decides it."""
    return region.difficulty not in ("none", "smooth")


def _hard_tiles(analysis: FrameAnalysis, shape: tuple[int, ...]) -> NDArray[np.bool_]:
    """The pixels (bool, ``shape``) of the tiles the hard-tile decoder decides; the other
    tiles (pass-through, integration) are exact up to the frame's constant."""
    hard = np.zeros(shape, bool)
    for region in analysis.tiles:
        if _is_hard(region):
            hard[region.row : region.row + region.height,
                 region.col : region.col + region.width] = True  # fmt: skip
    return hard


def _decoded_by(hard: Decoder, facts: dict[str, Any]) -> str:
    """The route of pixels the hard-tile decoder was given: the decoder it handed them
    to (a net hands a frame whose W spans more than its classes to a classical one,
    :meth:`models.decoders.learned.LearnedDecoder.explain_winding`), else its own name."""
    fallback = facts.get("fallback")
    return str(fallback["decoder"]) if fallback else hard.name


def _with_fallback(report: dict[str, Any], calls: list[dict[str, Any]]) -> dict[str, Any]:
    """``report`` with why the hard-tile decoder handed a call on (``fallback``) and
    what it warned of (``warning``; a net's W short of a frame's brightest pixels), the
    first of each over its ``calls``' facts."""
    found = {}
    for key in ("fallback", "warning"):
        said = [facts[key] for facts in calls if facts.get(key)]
        if said:
            found[key] = said[0]
    return {**report, **found}


def _report(pixels: Counter[str] | dict[str, int], reason: str) -> dict[str, Any]:
    total = sum(pixels.values())
    return {
        "routes": {name: count / total for name, count in pixels.items()},
        "reason": reason,
    }


def specs() -> list[DecoderSpec]:
    """``auto`` (balanced) and ``auto-<quality>`` for each quality level."""
    found = [
        DecoderSpec(
            name=f"auto-{quality}",
            kind="adaptive",
            description=f"per-tile routing at quality {quality!r}: pass-through, exact "
            "integration, or a network tier only where wraps are dense",
            factory=lambda quality=quality: AdaptiveDecoder(quality),
        )
        for quality in QUALITIES
    ]
    balanced = found[1]
    return [
        DecoderSpec("auto", "adaptive", balanced.description, balanced.factory),
        *found,
    ]
