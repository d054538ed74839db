"""Decoding a wrapped video: frame by frame (``independent``) or along time (``temporal``).

``independent`` runs a spatial decoder (:func:`models.decoders.get_decoder`) on each
frame, as the paper does. ``temporal`` unwraps each pixel along time from the
previous frame's unwrapped value ``u_{t-1} = W_{t-1} + m_{t-1}`` (wraps):

    W_t = round(u_{t-1} - m_t)

which is exact when the pixel's true change ``|u_t - u_{t-1}|`` is below half a wrap.
What each step below measured, and the variants tried and dropped, are in
``docs/temporal-decoding.md``.

Motion and brightness
---------------------
On a pan or zoom the content moves by pixels per frame, so ``u_{t-1}`` is first moved
onto the current frame by :func:`worker.motion.compensate` (a global shift of up to
``motion.search`` px plus a one-pixel refinement per block, matched on texture, which
a brightness change leaves alone); the rule and the checks below compare each pixel
with where its content was. Pixels whose content entered the frame (no source in the
previous frame) are unsafe and unbounded: the fallback decides them.

Then a global brightness change is undone: the moved ``u_{t-1}`` is brightened by the
gain that best explains ``m_t`` (:mod:`worker.brightness`; under a sunrise ramp a
bright modulo pixel moves by more than half a wrap per frame). Motion is estimated
first because texture matching does not mind a brightness change, while a gain fitted
to unaligned content can match by accident. A move is kept only if, with its gain, it
predicts ``m_t`` better than the unmoved frame does (mean misfit below
``motion.switch`` times the unmoved one's): on smooth, noisy content texture barely
pins the shift, and a wrong one would alias. ``TemporalConfig.motion`` and
``TemporalConfig.brightness`` hold the knobs (``search = 0`` turns either off).

The rule, per pixel (and channel)
---------------------------------
(Computed by :mod:`worker.temporal_rule`; this module runs the stream around it.)
A pixel is *safe* when every (motion-compensated) previous value within
``motion_radius`` pixels (a ``(2r+1)^2`` window, so that motion up to ``r`` px/frame
beyond what compensation followed stays decidable) gives the same ``W_t`` with at
least ``margin`` wraps to spare: ``|W_t + m_t - u_{t-1}(q)| <= 0.5 - margin`` for
every q in the window. Safe pixels keep the temporal answer. Unsafe pixels fall back
(:mod:`worker.temporal_fallback`):

- few unsafe pixels (at most ``local_limit`` of the frame): a cheap local fix, no
  spatial decoder (the *local* path): each unsafe pixel takes the W (within the range
  motion allows) that brings its ``u`` closest to a settled 8-neighbour's ``u``,
  growing inwards from the safe pixels for up to ``local_passes`` passes, unless its
  own temporal answer is closer than the best match divided by ``SELF_WEIGHT`` (so a
  static edge does not flip with noise) or its own change is *steady*: within
  ``steady_sigmas`` sigmas of the frame-to-frame noise the sensor can give any level
  up to the frame's brightest (:func:`models.formation.largest_noise_sigma`; the
  bound, not the noise at the pixel's own ``u``, since an unsafe pixel's ``u`` may be
  whole wraps wrong). Then, only when the camera moved (a global shift was kept),
  each large cluster of unsafe pixels is decoded again by the spatial decoder on a
  crop around it, and each region where the two answers disagree (and that touches an
  unsafe pixel) takes the one with fewer jumps across its boundary
  (:mod:`worker.crop_vote`; ``crop`` holds its knobs, its pixels count as
  *spatial*). The crops' total area is capped, so the step stays cheaper than a full
  spatial decode. On a still camera the unsafe clusters are noise or a brightness
  change, where the tracked answer is the better one;
- more: one full spatial decode of the frame, its unknown constant set to the most
  common difference to the temporal answer on safe pixels (*spatial* path). There,
  where the spatial answer disagrees with a safe temporal one, the spatial one wins
  when it is *confident* (its ``u`` is within half a wrap of all four neighbours) and
  the temporal one is not.

After the fallbacks
-------------------
When the camera moved (a global shift was kept) and any pixel fell back, the frame is
refined by guided graph-cut unwrapping (:mod:`models.decoders.guided_puma`, pixel
moves only, at most ``refine_moves`` min-cuts) from the merged answer: a region whose
W disagrees with the codes along most of its border (a fallback seam, an error carried
in with the content) is moved by whole wraps. The moves are confined to the fallback
pixels and ``refine_reach`` px round them
(:meth:`models.decoders.guided_puma.GuidedPumaDecoder.refine_within`), and now and
then the whole frame is refined, for errors far from any fallback pixel: after
``refine_whole_every`` frames, a wait that doubles (up to ``refine_whole_max``) each
time a whole refinement changes no W beyond that reach, and starts again at
``refine_whole_every`` when one does or an anchoring keyframe restarts the stream. (On
the pan/zoom clip only mantissanet-tiny's whole refinements found anything: a sky a
wrap off from its keyframe, which its refinement now raises since guided PUMA confines
W to the encoding's range; the other decoders' PSNR was the same with none at all.)
A still camera is not refined this way (it cost the sunrise clip 4.5 dB).

Otherwise (a still camera, or nothing fell back), clusters of safe pixels whose misfit
is far above their sensor noise (a light moving faster than ``motion_radius``, a lamp
switched on) are refined by guided graph cuts on a crop around them
(:mod:`worker.arrivals`, ``arrival`` holds its knobs).

A stream fills clipped blobs (:mod:`models.decoders.saturation`) whatever its spatial
decoder: one that does not (itoh, herraez, a net alone) is wrapped to
(:class:`models.decoders.filling.FillingDecoder`), as ``auto`` does. With itoh,
herraez or mantissanet-tiny a stream had kept its keyframe's W on a lamp's clipped
core as the lamp moved, 0.05-0.54 dB below decoding each frame alone (bench.video,
moving_light); filled, it measured 16.41-17.50 dB against 13.76-14.17, and 0.13-0.70 dB
above each frame decoded alone and filled, but for herraez on mantissa (0.18 dB below).
Every temporal step also runs clip tracking (:mod:`worker.clip_tracking`, ``clip``
holds its knobs; in a still view before arrival refinement, after a moving camera's
refinement, whose energy does not know the clip): a clipped blob that continues one
of the previous frame and jumped there is filled, and the zone a clipped blob left is
decoded spatially on a crop.

Keyframes
---------
Whole frames are decoded spatially (*keyframes*) for: the first frame of a stream, a
frame flagged DISCONT (device reconnect), a sequence gap, a change of shape or sensor
parameters, a *cut*, and every ``keyframe_interval`` frames (0: never) so that errors
cannot persist. A cut is a frame the previous one, moved and brightened, does not
explain: its mean misfit over the pixels the move covers is above ``cut_misfit`` (0.1
wraps; above ``cut_sigmas`` sigmas of the sensor's frame-to-frame noise when that is
more). Scene cuts (0.26 wraps), pans past the motion search (0.16-0.24 at 8-12 px a
frame) and jumps in light past the brightness search are; the bench clips' frames stay
below 0.025. The safety checks alone let 41-53% of a cut's pixels pass by chance, and
the stream carried their wrong W to the next periodic keyframe. All but the periodic
(:data:`ANCHOR_KEYFRAMES`) anchor the stream, which carries
their errors on, so their spatial answer is refined by guided PUMA to convergence
(``refine_keyframes``; one refinement per stream start, 20-100 ms at 256x256),
anchored again as a spatial decode is (the darkest pixels at W = 0: from itoh's W on
the sunrise clip's dark first frame the refinement lifted the whole frame a wrap, and
the stream carried it, 16.27 dB against 40.94 anchored) and filled again, each blob
judged on the spatial answer (the refinement's energy does not know the clip and
lowers the blobs).

A periodic keyframe first makes the temporal step as usual (with its fallbacks), then
decodes the frame spatially and shifts that answer by its most common difference to
the tracked one, so a scene that is bright everywhere (where "darkest pixels have W =
0" is wrong) keeps its tracked winding numbers. Where the two disagree, each connected
region of disagreement takes the answer that makes fewer jumps across its boundary
(:func:`models.decoders.region_vote.region_vote`), so neither a spatial decoder's
wrong region nor a tracked one survives the keyframe. Periodic keyframes are not
refined.

A keyframe of a colour stream then goes through the spatial decoder's
:meth:`models.decoders.base.Decoder.join_channels`, as a still frame would: a clip is
filled in every channel that holds it (:func:`models.decoders.saturation.fill_shared`;
each channel's keyframe had filled a white lamp on its own, and the stream carried
the tint on), then ``auto`` at balanced and best and ``<decoder>+colour`` make the
channels consistent (:mod:`models.decoders.colour`); the temporal steps between
keyframes track each channel on its own.

Failure modes
-------------
- Aliasing: a true change above half a wrap within one frame (a fast edge, a light
  switched on) that happens to land within the safe band gives a wrong W silently;
  the window check catches motion up to ``motion_radius`` px/frame beyond what
  compensation followed, not more (see :mod:`worker.motion` for what it misses:
  fast local motion, a fast zoom's corners). Errors persist until the local fix
  or a keyframe decodes the pixel again.
- Fallback quality: unsafe pixels are only as right as the spatial decoder (and a
  crop sees less context than the full frame). At a steep scene edge that a pan moves
  across, an unsafe pixel matched to the neighbour across the edge can be a wrap off
  for a frame and right again in the next: most of the pan/zoom clip's remaining wrap
  flicker.
- An error carried in far from every fallback pixel lasts until the next whole
  refinement: up to ``refine_whole_max`` frames once the waits have grown.
- A wrong constant at a first/DISCONT keyframe (the anchor rule failing) persists
  through periodic keyframes until the next DISCONT.
- A lamp brighter than the clip: no decoder but ``auto`` knows the clip, and with the
  others the stream's clipped core can end up darker than a fresh spatial decode's.

A :class:`worker.stream_state.StreamState` holds what the method remembers (previous
``u``, frame index, last keyframe, sequence number); the worker keeps one per device
stream. Every :class:`worker.stream_state.FrameDecode` reports the fraction of pixels
that took each path. The knobs named above are fields of
:class:`worker.temporal_config.TemporalConfig`.
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Iterator
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from models.decoders.base import Decoder, check_frame_shape
from models.decoders.filling import filling
from models.decoders.guided_puma import GuidedPumaDecoder
from models.decoders.region_vote import region_vote
from models.decoders.registry import get_decoder
from models.errors import InvalidInputError
from models.formation import (
    SensorParams,
    dequantize,
    from_unwrapped,
    largest_noise_sigma,
    max_winding,
)
from models.tile_reconcile import common_offset
from worker.arrivals import refine_arrivals
from worker.brightness import brighten, frame_gain
from worker.clip_tracking import track_clip
from worker.crop_vote import CropConfig, crop_vote
from worker.motion import Compensated, compensate
from worker.plane_refinement import grown, refined_planes
from worker.stream_state import FrameDecode, StreamState, path_shares
from worker.temporal_config import MODES, TemporalConfig
from worker.temporal_fallback import merge_spatial, neighbour_fix
from worker.temporal_rule import Prediction, temporal_prediction

#: Keyframes that anchor a stream (its start, a reconnect, a gap, new sensor parameters):
#: their spatial answer is refined by guided PUMA to convergence, since the stream
#: carries its errors on (see the module doc); periodic keyframes are not.
ANCHOR_KEYFRAMES: tuple[str, ...] = ("first", "discont", "gap", "params", "cut")


class Predicted(NamedTuple):
    """:meth:`StreamDecoder.predict`'s answer: the prediction, the global shift (dy, dx)
    px of the move, the mean misfit (wraps) of the moved, brightened previous frame over
    the pixels the move covers, and the sigma (wraps) of a pixel's frame-to-frame change
    from sensor noise."""

    prediction: Prediction
    shift: tuple[int, int]
    misfit: float
    noise: float


def _planes(codes: NDArray[Any], params: SensorParams) -> NDArray[np.float64]:
    """``m`` of a frame as H x W x C (one plane per channel)."""
    codes = np.asarray(codes)
    check_frame_shape(codes, params)
    m = dequantize(codes, params.bits)
    return m[:, :, None] if m.ndim == 2 else m


class StreamDecoder:
    """Decodes frames of one or many streams in ``mode`` with spatial decoder ``decoder``."""

    def __init__(
        self, mode: str, decoder: str | Decoder, config: TemporalConfig | None = None
    ) -> None:
        if mode not in MODES:
            raise InvalidInputError(f"unknown mode {mode!r}; choose one of: {', '.join(MODES)}")
        self.mode = mode
        spatial = get_decoder(decoder) if isinstance(decoder, str) else decoder
        # Along time clipped blobs are filled whatever the spatial decoder (module doc);
        # decoded alone, each frame is the spatial decoder's own answer.
        self.spatial = filling(spatial) if mode == "temporal" else spatial
        self.config = config or TemporalConfig()
        moves = self.config.refine_moves
        # Pixel moves only (region_moves=0): region moves first cost pan/zoom up to
        # 6.2 dB (docs/temporal-decoding.md).
        self.refiner = (
            GuidedPumaDecoder(self.spatial, max_moves=moves, region_moves=0) if moves else None
        )
        self.keyframe_refiner = (
            GuidedPumaDecoder(self.spatial) if self.config.refine_keyframes else None
        )
        arrival = self.config.arrival
        self.arrival_refiner = (
            GuidedPumaDecoder(self.spatial, max_moves=arrival.moves, region_moves=0)
            if arrival.min_cluster
            else None
        )

    def decode(
        self,
        codes: NDArray[Any],
        params: SensorParams,
        state: StreamState,
        *,
        sequence: int | None = None,
        discont: bool = False,
    ) -> FrameDecode:
        """Decode the next frame of the stream ``state``, which takes the frame's ``u``
        only once it has decoded: after a refused frame (an ``x`` past float64, say) the
        next one follows the last frame that decoded."""
        start = time.perf_counter_ns()
        m = _planes(codes, params)
        keyframe = self.keyframe_reason(state, m, params, sequence, discont)
        predicted = None
        if keyframe is None:
            assert state.u is not None
            predicted = self.predict(m, state.u, params)
            keyframe = "cut" if self.is_cut(predicted) else None
        if predicted is not None and keyframe is None:
            winding, paths = self._temporal_step(m, params, state, predicted)
        else:
            winding, paths = self._keyframe_step(m, params, state, keyframe)
        limit = max_winding(params)
        winding = np.clip(winding, 0, limit)
        u = winding + m
        squeeze = np.asarray(codes).ndim == 2
        irradiance = from_unwrapped(u[:, :, 0] if squeeze else u, params)
        state.u, state.params, state.sequence = u, params, sequence
        if keyframe is not None:
            state.last_keyframe = state.frames
        if keyframe in ANCHOR_KEYFRAMES:
            state.whole_interval = self.config.refine_whole_every
            state.next_whole = state.frames + state.whole_interval
        state.frames += 1
        return FrameDecode(
            winding=winding[:, :, 0] if squeeze else winding,
            irradiance=irradiance,
            keyframe=keyframe,
            paths=paths,
            timings_ns={"total": time.perf_counter_ns() - start},
        )

    def keyframe_reason(
        self,
        state: StreamState,
        m: NDArray[np.float64],
        params: SensorParams,
        sequence: int | None,
        discont: bool,
    ) -> str | None:
        """Why this frame must be decoded whole, or None for a temporal step."""
        if self.mode == "independent" or params.encoding == "clip":
            return "independent"
        if state.u is None or state.params is None:
            return "first"
        if discont:
            return "discont"
        if sequence is not None and state.sequence is not None and sequence != state.sequence + 1:
            return "gap"
        if state.u.shape != m.shape or state.params.differences(params):
            return "params"
        interval = self.config.keyframe_interval
        if interval and state.frames - state.last_keyframe >= interval:
            return "periodic"
        return None

    def is_cut(self, predicted: Predicted) -> bool:
        """Whether the moved, brightened previous frame fails to explain this one: a
        scene cut, a pan past the motion search or a jump in light past the brightness
        search, which the safety checks let through (module doc)."""
        limit = max(self.config.cut_misfit, self.config.cut_sigmas * predicted.noise)
        return predicted.misfit > limit

    def predict(
        self, m: NDArray[np.float64], prev_u: NDArray[np.float64], params: SensorParams
    ) -> Predicted:
        """The temporal answer for ``m`` from ``prev_u`` moved onto it (:mod:`worker.motion`)
        and brightened by the frame's gain (:mod:`worker.brightness`), with the global
        shift (dy, dx) px of the move and how well it explains ``m``; the move is kept
        only if it predicts ``m`` better than the unmoved ``prev_u`` (module doc)."""
        moved = compensate(prev_u, m, self.config.motion)
        gain, cost = frame_gain(moved.u, m, params, self.config.brightness)
        if moved.shift != (0, 0):
            still_gain, still_cost = frame_gain(prev_u, m, params, self.config.brightness)
            if not cost < self.config.motion.switch * still_cost:
                moved = Compensated(prev_u, np.ones(m.shape[:2], bool), (0, 0), 0.0)
                gain = still_gain
        previous = brighten(moved.u, gain, params)
        noise = np.sqrt(2.0) * largest_noise_sigma(float(previous.max()), params)
        prediction = temporal_prediction(m, previous, self.config, moved.inside, noise)
        # The changes where the move has a source, gathered as ``change[inside]`` orders
        # them (by ``compress``: 2x faster than a 2-D mask on an H x W x C array).
        channels = prediction.change.shape[2]
        seen = np.compress(moved.inside.ravel(), prediction.change.reshape(-1, channels), 0)
        misfit = float(seen.mean()) if seen.size else 0.5
        return Predicted(prediction, moved.shift, misfit, noise)

    def _spatial_planes(self, m: NDArray[np.float64], params: SensorParams) -> NDArray[np.int64]:
        if params.encoding == "clip":
            return np.zeros(m.shape, np.int64)
        return np.stack(
            [self.spatial.predict_winding(m[:, :, c], params) for c in range(m.shape[2])], axis=2
        ).astype(np.int64)

    def _keyframe_step(
        self, m: NDArray[np.float64], params: SensorParams, state: StreamState, reason: str
    ) -> tuple[NDArray[np.int64], dict[str, float]]:
        spatial = self._spatial_planes(m, params)
        if reason in ANCHOR_KEYFRAMES and self.keyframe_refiner is not None:
            spatial = refined_planes(
                self.keyframe_refiner, m, spatial, params, refill=True, anchor=True
            )
        spatial = self.spatial.join_channels(m, spatial, params)[0]
        if reason != "periodic" or state.u is None:
            return spatial, {"temporal": 0.0, "local": 0.0, "spatial": 1.0}
        tracked, local, fell_back = self._tracked(m, params, state, spatial)
        for c in range(m.shape[2]):
            offset = common_offset(tracked[:, :, c], spatial[:, :, c])
            aligned = np.maximum(spatial[:, :, c] + offset, 0)
            tracked[:, :, c], taken = region_vote(tracked[:, :, c], aligned, m[:, :, c])
            local[:, :, c] &= ~taken
            fell_back[:, :, c] |= taken
        return tracked, path_shares(local, fell_back)

    def _temporal_step(
        self, m: NDArray[np.float64], params: SensorParams, state: StreamState,
        predicted: Predicted,
    ) -> tuple[NDArray[np.int64], dict[str, float]]:
        winding, local, spatial = self._tracked(m, params, state, predicted=predicted)
        return winding, path_shares(local, spatial)

    def _tracked(
        self,
        m: NDArray[np.float64],
        params: SensorParams,
        state: StreamState,
        whole_frame: NDArray[np.int64] | None = None,
        predicted: Predicted | None = None,
    ) -> tuple[NDArray[np.int64], NDArray[np.bool_], NDArray[np.bool_]]:
        """The temporal rule's W for ``m`` and where it took the local and the spatial
        fallback (module doc). ``whole_frame``: the frame's spatial W (H x W x C) when a
        keyframe already decoded it, so the whole-frame fallback does not decode it again;
        ``predicted``: :meth:`predict`'s answer when the caller has it."""
        assert state.u is not None
        prediction, shift, _, _ = predicted or self.predict(m, state.u, params)
        crop = self.config.crop if shift != (0, 0) else CropConfig(min_cluster=0)
        winding = prediction.winding.copy()
        local = np.zeros(m.shape, bool)
        spatial = np.zeros(m.shape, bool)
        for c in range(m.shape[2]):
            plane, channel = m[:, :, c], prediction.channel(c)
            if channel.safe.all():
                continue
            unsafe = ~channel.safe
            if unsafe.mean() <= self.config.local_limit:
                fixed = neighbour_fix(channel, self.config.local_passes)
                fixed, took = crop_vote(
                    channel, fixed, lambda crop: self.spatial.predict_winding(crop, params),
                    crop,
                )
                winding[:, :, c], local[:, :, c], spatial[:, :, c] = fixed, unsafe & ~took, took
                continue
            whole = (
                whole_frame[:, :, c]
                if whole_frame is not None
                else self.spatial.predict_winding(plane, params).astype(np.int64)
            )
            merged = merge_spatial(channel, whole)
            winding[:, :, c], spatial[:, :, c] = merged or (whole, np.ones(whole.shape, bool))
        if self.refiner is not None and shift != (0, 0) and (local | spatial).any():
            winding = self._refine_moving(m, params, state, winding, local | spatial)
            self._track_clips(m, params, state.u, prediction, winding, (local, spatial))
            return winding, local, spatial
        # In a still view clip tracking goes first, and arrival refinement leaves what it
        # set alone: on the moving light (auto-fast) the same PSNR within 0.02 dB, and
        # 8 ms less a frame than refining the lamp's wake before decoding it again.
        clipped = self._track_clips(m, params, state.u, prediction, winding, (local, spatial))
        if self.arrival_refiner is not None:
            for c in range(m.shape[2]):
                winding[:, :, c], took = refine_arrivals(
                    m[:, :, c], winding[:, :, c],
                    np.where(clipped[:, :, c], 0.0, prediction.change[:, :, c]), params,
                    self.arrival_refiner, self.config.arrival,
                )  # fmt: skip
                local[:, :, c] &= ~took
                spatial[:, :, c] |= took
        return winding, local, spatial

    def _refine_moving(
        self,
        m: NDArray[np.float64],
        params: SensorParams,
        state: StreamState,
        winding: NDArray[np.int64],
        fallback: NDArray[np.bool_],
    ) -> NDArray[np.int64]:
        """A moving camera's W (H x W x C) refined within ``refine_reach`` px of the
        ``fallback`` pixels, or whole when due; a whole refinement that changes nothing
        beyond that band doubles the wait for the next one (up to
        ``refine_whole_max`` frames), one that does resets it (module doc)."""
        band = grown(fallback, self.config.refine_reach)
        every = self.config.refine_whole_every
        if not every or state.frames < state.next_whole:
            return refined_planes(self.refiner, m, winding, params, band)
        # Refilled as anchoring keyframes are: the refinement's energy does not know the
        # clip and lowered a filled lamp 1-4 wraps (407 of its 666 pixels, for 9 frames).
        refined = refined_planes(self.refiner, m, winding, params, refill=True)
        beyond = bool(((refined != winding) & ~band).any())
        state.whole_interval = (
            every if beyond else min(2 * state.whole_interval, self.config.refine_whole_max)
        )
        state.next_whole = state.frames + state.whole_interval
        return refined

    def _track_clips(
        self,
        m: NDArray[np.float64],
        params: SensorParams,
        previous_u: NDArray[np.float64],
        prediction: Prediction,
        winding: NDArray[np.int64],
        paths: tuple[NDArray[np.bool_], NDArray[np.bool_]],
    ) -> NDArray[np.bool_]:
        """Clip tracking (:mod:`worker.clip_tracking`) on each plane of ``winding`` (H x W
        x C, changed in place); the pixels it set count as spatial in ``paths`` (local,
        spatial; changed in place). Returns them."""
        local, spatial = paths
        taken = np.zeros(m.shape, bool)
        for c in range(m.shape[2]):
            winding[:, :, c], taken[:, :, c] = track_clip(
                m[:, :, c], winding[:, :, c], previous_u[:, :, c], prediction.change[:, :, c],
                params, lambda crop: self.spatial.predict_winding(crop, params), self.config.clip,
            )  # fmt: skip
        local &= ~taken
        spatial |= taken
        return taken


def decode_frames(
    frames: Iterable[NDArray[Any]],
    params: SensorParams,
    decoder: StreamDecoder,
    state: StreamState | None = None,
) -> Iterator[FrameDecode]:
    """Decode a sequence of frames (codes, DN) of one stream, in order."""
    state = state or StreamState()
    for codes in frames:
        yield decoder.decode(codes, params, state)
