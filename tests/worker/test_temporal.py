"""Tests of worker/temporal.py: temporal unwrapping, its fallbacks and keyframes."""

from __future__ import annotations

import numpy as np
import pytest

from device.scenes import ProceduralScene
from models.decoders.base import Decoder
from models.decoders.colour import ColourDecoder
from models.decoders.registry import get_decoder
from models.errors import InvalidInputError, OutputOverflowError
from models.formation import SensorParams, encode, quantize, simulate, split_unwrapped
from tests.models.decoders.colour_lamp import colour_lamp
from tests.models.decoders.fixed_planes import FixedPlanesDecoder
from tests.worker.panning import PAN_PARAMS, pan_clip, smooth_scene
from worker.brightness import BrightnessConfig
from worker.crop_vote import CropConfig
from worker.motion import MotionConfig
from worker.stream_state import StreamState
from worker.temporal import StreamDecoder, decode_frames
from worker.temporal_config import TemporalConfig

SIZE = 64
PARAMS = SensorParams(encoding="mantissa", bits=8, alpha=2.0)


def blob(scale: float, shift: float = 0.0) -> np.ndarray:
    """A smooth bright blob (up to 8 * scale wraps of x) on a dim floor: Itoh is exact on it."""
    yy, xx = np.mgrid[0:SIZE, 0:SIZE] - SIZE / 2
    return 0.05 + 8.0 * scale * np.exp(-((yy - shift) ** 2 + xx**2) / 20.0**2)


def slow_clip(frames: int = 12) -> list[np.ndarray]:
    """The blob brightening by 3% and drifting 0.5 px per frame."""
    return [blob(1.03**t, 0.5 * t) for t in range(frames)]


def encoded(x: np.ndarray, params: SensorParams = PARAMS):
    return encode(x, params)


@pytest.fixture
def temporal() -> StreamDecoder:
    return StreamDecoder("temporal", "itoh", TemporalConfig(keyframe_interval=0))


def test_exact_on_a_slowly_varying_clip(temporal: StreamDecoder) -> None:
    state = StreamState()
    for t, x in enumerate(slow_clip()):
        frame = encoded(x)
        result = temporal.decode(frame.codes, PARAMS, state)
        np.testing.assert_array_equal(result.winding, frame.winding)
        assert result.keyframe == ("first" if t == 0 else None)
        if t:
            assert result.paths["temporal"] > 0.95 and result.paths["spatial"] == 0.0
    assert state.frames == 12 and state.last_keyframe == 0


@pytest.mark.parametrize("size", [(64, 64), (37, 53)])
def test_exact_on_a_slowly_panning_clip_only_with_motion_compensation(
    size: tuple[int, int],
) -> None:
    """A 2 px/frame pan over steep smooth content: with motion compensation every frame
    is exact with no spatial decode; the plain per-pixel rule gets some W wrong."""
    frames = pan_clip(10, size=size)
    compensated = StreamDecoder("temporal", "itoh", TemporalConfig(keyframe_interval=0))
    results = list(decode_frames([f.codes for f in frames], PAN_PARAMS, compensated))
    for result, frame in zip(results, frames, strict=True):
        assert result.winding.shape == size
        np.testing.assert_array_equal(result.winding, frame.winding)
    assert all(r.paths["spatial"] == 0.0 for r in results[1:])
    plain = StreamDecoder(  # no cut keyframes either: they would decode it spatially
        "temporal", "itoh",
        TemporalConfig(keyframe_interval=0, motion=MotionConfig(search=0), cut_misfit=0.5),
    )  # fmt: skip
    wrong = sum(
        int((result.winding != frame.winding).sum())
        for result, frame in zip(
            decode_frames([f.codes for f in frames], PAN_PARAMS, plain), frames, strict=True
        )
    )
    assert wrong > 0


def test_a_pan_under_a_brightness_ramp_needs_both_compensations() -> None:
    """2 px/frame pan while the light grows 5% per frame (up to 0.2 wraps per frame on
    top of the pan's change): exact with motion and brightness compensation, wrong
    with the gain estimate off."""
    frames = pan_clip(8, gain=1.05)
    codes = [f.codes for f in frames]
    both = StreamDecoder("temporal", "itoh", TemporalConfig(keyframe_interval=0))
    for result, frame in zip(decode_frames(codes, PAN_PARAMS, both), frames, strict=True):
        np.testing.assert_array_equal(result.winding, frame.winding)
    motion_only = StreamDecoder("temporal", "itoh", TemporalConfig(
        keyframe_interval=0, brightness=BrightnessConfig(search=0.0), refine_moves=0))
    results = decode_frames(codes, PAN_PARAMS, motion_only)
    assert any((r.winding != f.winding).any() for r, f in zip(results, frames, strict=True))


def test_a_move_that_predicts_worse_than_none_is_dropped() -> None:
    """The live simulator's scene (1 px/frame pan over smooth walls, a moving light, shot
    noise): its texture barely pins the shift and noise picks wrong ones (2-3 px), which
    without the check against the unmoved prediction broke up to 3400 pixels a frame."""
    scene = ProceduralScene()
    frames = [
        simulate(scene.render(i), SensorParams(encoding="modulo", bits=8, gain=1.0,
                                               read_noise=0.002, full_well=20_000.0, seed=i))
        for i in range(60, 72)
    ]
    decoder = StreamDecoder("temporal", "itoh", TemporalConfig(keyframe_interval=0))
    results = decode_frames([f.codes for f in frames], frames[0].params, decoder)
    for result, frame in zip(results, frames, strict=True):
        np.testing.assert_array_equal(result.winding, frame.winding)


def test_discont_during_a_pan_keyframes_and_stays_exact() -> None:
    """A DISCONT mid-pan is decoded spatially; the pan is tracked again right after."""
    frames = pan_clip(6)
    decoder = StreamDecoder("temporal", "itoh", TemporalConfig(keyframe_interval=0))
    state = StreamState()
    for t, frame in enumerate(frames):
        result = decoder.decode(frame.codes, PAN_PARAMS, state, sequence=t, discont=t == 3)
        assert result.keyframe == {0: "first", 3: "discont"}.get(t)
        np.testing.assert_array_equal(result.winding, frame.winding)


def test_falls_back_on_a_fast_change_and_stays_correct(temporal: StreamDecoder) -> None:
    """A light switched on in one corner (x up by 0.5 on a dim floor: up to half a wrap
    of change in one frame, not a global gain) is unsafe: those pixels take the
    fallback, and W is still exact."""
    state = StreamState()
    temporal.decode(encoded(blob(1.0)).codes, PARAMS, state)
    yy, xx = np.mgrid[0:SIZE, 0:SIZE] - SIZE / 2
    light = 0.5 * np.exp(-((yy - 18) ** 2 + (xx + 18) ** 2) / 8.0**2)
    jump = encoded(blob(1.0) + light)
    result = temporal.decode(jump.codes, PARAMS, state)
    assert result.keyframe is None
    assert result.paths["local"] + result.paths["spatial"] > 0.02
    np.testing.assert_array_equal(result.winding, jump.winding)


def spot_frames(pan: int, frames: int = 5) -> list:
    """Modulo frames of the smooth pan scene moving ``pan`` px/frame with a bright spot
    (4 wraps, 4 px sigma) crossing it at 6 px/frame, beyond the safety window."""
    scene = smooth_scene(scale=2.0)
    yy, xx = np.mgrid[0:SIZE, 0:SIZE]
    return [
        encode(
            np.roll(scene, -pan * t, axis=1)[:SIZE, :SIZE]
            + 4.0 * np.exp(-((yy - 32.0) ** 2 + (xx - 16.0 - 6 * t) ** 2) / (2 * 4.0**2)),
            PAN_PARAMS,
        )
        for t in range(frames)
    ]


def test_on_a_pan_unsafe_clusters_are_re_decoded_on_crops() -> None:
    """During a pan, the clusters of unsafe pixels around a fast spot are decoded again
    on crops (spatial share > 0 on temporal frames) and fewer W are wrong than with the
    local fix alone (both without the final refinement); on a still camera the crop
    vote does not run."""
    wrong = {}
    for pan in (2, 0):
        for crop in (CropConfig(limit=1.0), CropConfig(min_cluster=0)):
            config = TemporalConfig(keyframe_interval=0, crop=crop, refine_moves=0)
            decoder, state = StreamDecoder("temporal", "itoh", config), StreamState()
            wrong[pan, crop.min_cluster] = 0
            for t, frame in enumerate(spot_frames(pan)):
                result = decoder.decode(frame.codes, PAN_PARAMS, state)
                wrong[pan, crop.min_cluster] += int((result.winding != frame.winding).sum())
                if t:
                    assert (result.paths["spatial"] > 0) == (pan > 0 and crop.min_cluster > 0)
    assert wrong[2, 64] < 0.8 * wrong[2, 0]
    assert wrong[0, 64] == wrong[0, 0]


def test_the_final_refinement_runs_only_when_the_camera_moved() -> None:
    """On the panning spot clip the refinement leaves fewer W wrong than the crop vote
    alone; on a still camera it does not run, so the answer is the same."""
    wrong = {}
    for pan in (2, 0):
        for moves in (0, 2):
            config = TemporalConfig(keyframe_interval=0, refine_moves=moves)
            decoder, state = StreamDecoder("temporal", "itoh", config), StreamState()
            wrong[pan, moves] = sum(
                int((decoder.decode(f.codes, PAN_PARAMS, state).winding != f.winding).sum())
                for f in spot_frames(pan)
            )
    assert wrong[2, 2] < wrong[2, 0]
    assert wrong[0, 2] == wrong[0, 0]


@pytest.mark.parametrize("every", [0, 1, 4])
def test_the_final_refinement_near_the_fallback_pixels_mends_the_pan(every: int) -> None:
    """Confined to the fallback pixels' surroundings on every frame (0), on none (1:
    the whole frame every time) or between whole frames (4), the refinement leaves
    fewer W wrong on the panning spot clip than none at all."""
    wrong = {}
    for moves in (0, 2):
        config = TemporalConfig(keyframe_interval=0, refine_moves=moves, refine_whole_every=every)
        decoder, state = StreamDecoder("temporal", "itoh", config), StreamState()
        wrong[moves] = sum(
            int((decoder.decode(f.codes, PAN_PARAMS, state).winding != f.winding).sum())
            for f in spot_frames(2)
        )
    assert wrong[2] < wrong[0]


def test_whole_refinements_back_off_while_they_find_nothing_beyond_the_band() -> None:
    """On the panning spot clip the whole-frame refinements change nothing beyond the
    fallback band once the spot has left, so the wait between them doubles up to
    ``refine_whole_max``; an error carried in far from any fallback pixel (a patch of
    the stream's ``u`` a wrap high) is mended by the next whole refinement, which
    starts the waits again."""
    config = TemporalConfig(keyframe_interval=0, refine_whole_every=4, refine_whole_max=16)
    decoder, state = StreamDecoder("temporal", "itoh", config), StreamState()
    waits, wrong = [], []
    for t, frame in enumerate(spot_frames(2, 34)):
        if t == 14:
            assert state.u is not None
            state.u[4:16, 20:36] += 1.0
        result = decoder.decode(frame.codes, PAN_PARAMS, state)
        waits.append(state.whole_interval)
        wrong.append(int((result.winding != frame.winding).sum()))
    assert waits[:4] == [4] * 4 and max(waits[:28]) == 16
    assert wrong[13] == 0 and wrong[14] > 0 and wrong[27] > 0
    assert wrong[28] == 0 and waits[28] == 4


def test_a_global_brightness_jump_is_followed_without_fallback(temporal: StreamDecoder) -> None:
    """x times sqrt 2 everywhere (half a wrap where the log part rules): the brightness
    gain explains it, so no pixel needs the fallback, and W is exact; with the gain
    estimate off, the same frame needs the fallback."""
    state = StreamState()
    temporal.decode(encoded(blob(1.0)).codes, PARAMS, state)
    brighter = encoded(np.sqrt(2.0) * blob(1.0))
    result = temporal.decode(brighter.codes, PARAMS, state)
    assert result.paths["temporal"] == 1.0
    np.testing.assert_array_equal(result.winding, brighter.winding)
    plain = StreamDecoder("temporal", "itoh", TemporalConfig(
        keyframe_interval=0, brightness=BrightnessConfig(search=0.0)))
    state = StreamState()
    plain.decode(encoded(blob(1.0)).codes, PARAMS, state)
    assert plain.decode(brighter.codes, PARAMS, state).paths["temporal"] < 0.95


def test_discont_forces_a_keyframe(temporal: StreamDecoder) -> None:
    """After a reconnect the scene is 2 stops brighter (u jumps by 2 wraps): temporally
    ambiguous, but the DISCONT keyframe decodes it spatially and exactly. (The frame
    keeps 6% of its pixels unwrapped, as the spatial decoders' anchoring rule needs.)"""
    state = StreamState()
    temporal.decode(encoded(blob(1.0)).codes, PARAMS, state, sequence=1)
    brighter = encoded(blob(4.0))
    result = temporal.decode(brighter.codes, PARAMS, state, sequence=2, discont=True)
    assert result.keyframe == "discont" and result.paths["spatial"] == 1.0
    np.testing.assert_array_equal(result.winding, brighter.winding)


def test_sequence_gap_and_parameter_change_force_keyframes(temporal: StreamDecoder) -> None:
    state = StreamState()
    codes = encoded(blob(1.0)).codes
    assert temporal.decode(codes, PARAMS, state, sequence=5).keyframe == "first"
    assert temporal.decode(codes, PARAMS, state, sequence=6).keyframe is None
    assert temporal.decode(codes, PARAMS, state, sequence=9).keyframe == "gap"
    other = PARAMS.model_copy(update={"alpha": 3.0})
    assert temporal.decode(codes, other, state, sequence=10).keyframe == "params"
    noisy_seed = other.model_copy(update={"seed": 7})
    assert temporal.decode(codes, noisy_seed, state, sequence=11).keyframe is None
    state.reset()
    assert temporal.decode(codes, PARAMS, state).keyframe == "first"


@pytest.mark.parametrize("sequence", [True, False])
def test_a_frame_past_float64_leaves_the_stream_as_it_was(sequence: bool) -> None:
    """Mantissa alpha 1e6: a plateau at u = 52.2 (x 1.6e307) brightens by 0.3 wraps, past
    float64 (u 52.375), and that frame is refused. The stream had already taken its u,
    so the next frame, the first one again, failed too ("u up to 52.502"), and without
    sequence numbers every later frame did; now it is a gap keyframe (or a temporal step
    from the first frame) and decodes exactly."""
    params = SensorParams(encoding="mantissa", alpha=1e6)
    rows, cols = np.mgrid[0:64, 0:128]
    u = np.clip(0.45 * (rows + cols) - 15.0, 0.05, 52.2)
    truth, m = split_unwrapped(u, params)
    _, brighter = split_unwrapped(u + 0.3, params)
    decoder = StreamDecoder("temporal", "itoh", TemporalConfig(keyframe_interval=0))
    state = StreamState()
    numbers = iter([1, 2, 3] if sequence else [None] * 3)
    decoder.decode(quantize(m, params.bits), params, state, sequence=next(numbers))
    with pytest.raises(OutputOverflowError, match="exceed the float64 limit"):
        decoder.decode(quantize(brighter, params.bits), params, state, sequence=next(numbers))
    again = decoder.decode(quantize(m, params.bits), params, state, sequence=next(numbers))
    assert again.keyframe == ("gap" if sequence else None)
    np.testing.assert_array_equal(again.winding, truth)


@pytest.mark.parametrize("encoding", ["modulo", "mantissa"])
def test_a_scene_cut_anchors_the_stream_anew(encoding: str) -> None:
    """Same sensor, consecutive frames, no DISCONT: the safety checks let about half of
    the new scene's pixels pass with the old scene's W, which the stream carried to the
    next periodic keyframe (W accuracy 0.57 modulo, 0.49 mantissa)."""
    params = SensorParams(encoding=encoding, bits=10)
    first, second = smooth_scene(96, 96, 3.0, 3), smooth_scene(96, 96, 3.0, 7)
    if encoding == "mantissa":
        first, second = 2**first - 0.5, 2**second - 0.5
    decoder, state = StreamDecoder("temporal", "herraez"), StreamState()
    reasons = []
    for sequence, scene in enumerate([first, first, second, second]):
        truth = encode(scene, params)
        result = decoder.decode(truth.codes, params, state, sequence=sequence)
        np.testing.assert_array_equal(result.winding, truth.winding)
        reasons.append(result.keyframe)
    assert reasons == ["first", None, "cut", None]


def test_a_pan_past_the_motion_search_is_a_cut_not_carried_wrong() -> None:
    """8 px a frame (the search reaches 4): a wrong shift was accepted and a quarter of
    the frame's W went wrong (accuracy down to 0.75)."""
    decoder, state = StreamDecoder("temporal", "itoh"), StreamState()
    for frame in pan_clip(12, speed=8):
        result = decoder.decode(frame.codes, PAN_PARAMS, state)
        np.testing.assert_array_equal(result.winding, frame.winding)
    assert state.frames == 12


def test_a_noisy_still_stream_is_not_taken_for_cuts() -> None:
    """Read noise raises every frame's misfit; the cut test rises with it."""
    params = SensorParams(encoding="modulo", bits=10, read_noise=0.08)
    decoder, state = StreamDecoder("temporal", "itoh"), StreamState()
    reasons = [
        decoder.decode(encode(blob(1.0), params.model_copy(update={"seed": t})).codes,
                       params, state, sequence=t).keyframe
        for t in range(6)
    ]
    assert reasons == ["first"] + [None] * 5


def test_periodic_keyframes_keep_the_stream_constant() -> None:
    """Every 4th frame is decoded spatially; its constant follows the tracked W."""
    decoder = StreamDecoder("temporal", "itoh", TemporalConfig(keyframe_interval=4))
    frames = [encoded(x) for x in slow_clip(9)]
    results = list(decode_frames([f.codes for f in frames], PARAMS, decoder))
    assert [r.keyframe for r in results] == ["first", None, None, None, "periodic"] + [None] * 3 + [
        "periodic"
    ]
    for result, frame in zip(results, frames, strict=True):
        np.testing.assert_array_equal(result.winding, frame.winding)


@pytest.mark.parametrize("interval", [0, 3])
def test_a_periodic_keyframe_votes_out_a_tracked_error(interval: int) -> None:
    """A patch of the tracked u one wrap high (a carried error) stays wrong without
    periodic keyframes; the keyframe's region vote gives it the spatial answer."""
    decoder = StreamDecoder("temporal", "itoh", TemporalConfig(keyframe_interval=interval))
    frames = [encoded(x) for x in slow_clip(4)]
    state = StreamState()
    for frame in frames[:2]:
        decoder.decode(frame.codes, PARAMS, state)
    assert state.u is not None
    state.u[28:36, 28:36] += 1.0
    decoder.decode(frames[2].codes, PARAMS, state)
    result = decoder.decode(frames[3].codes, PARAMS, state)
    wrong = int((result.winding != frames[3].winding).sum())
    assert sum(result.paths.values()) == pytest.approx(1.0)
    if interval:
        assert result.keyframe == "periodic" and wrong == 0
        assert result.paths["spatial"] == pytest.approx(64 / SIZE**2)
    else:
        assert result.keyframe is None and wrong == 64


class UnderCounting(Decoder):
    """A spatial decoder that never counts above one wrap (as the nets at high W)."""

    name = "under-counting"  # type: ignore[assignment]

    def predict_winding(self, m: np.ndarray, params: SensorParams) -> np.ndarray:
        return np.minimum(get_decoder("itoh").predict_winding(m, params), 1)


@pytest.mark.parametrize("refine", [True, False])
def test_anchoring_keyframes_are_refined_periodic_ones_are_not(refine: bool) -> None:
    """The first frame's spatial answer, missing the blob's top wraps, is refined to the
    truth (and the stream keeps it) unless refine_keyframes is off; a DISCONT keyframe
    is refined too, independent mode never."""
    config = TemporalConfig(keyframe_interval=0, refine_keyframes=refine)
    decoder = StreamDecoder("temporal", UnderCounting(), config)
    frames = [encoded(x) for x in slow_clip(3)]
    assert frames[0].winding.max() >= 3
    state = StreamState()
    first = decoder.decode(frames[0].codes, PARAMS, state)
    second = decoder.decode(frames[1].codes, PARAMS, state)
    reconnect = decoder.decode(frames[2].codes, PARAMS, state, discont=True)
    assert (first.keyframe, second.keyframe, reconnect.keyframe) == ("first", None, "discont")
    for result, frame in zip((first, second, reconnect), frames, strict=True):
        if refine:
            np.testing.assert_array_equal(result.winding, frame.winding)
        else:
            assert result.winding.max() <= 2 and np.any(result.winding != frame.winding)
    alone = StreamDecoder("independent", UnderCounting(), config)
    assert alone.decode(frames[0].codes, PARAMS, StreamState()).winding.max() == 1


def test_independent_mode_is_the_spatial_decoder() -> None:
    frame = encoded(blob(2.0))
    result = StreamDecoder("independent", "itoh").decode(frame.codes, PARAMS, StreamState())
    expected = get_decoder("itoh").decode(frame.codes, PARAMS)
    np.testing.assert_array_equal(result.winding, expected.winding)
    np.testing.assert_allclose(result.irradiance, expected.irradiance)
    assert result.keyframe == "independent" and result.paths["spatial"] == 1.0


def test_colour_frames_keep_their_shape(temporal: StreamDecoder) -> None:
    state = StreamState()
    for x in slow_clip(3):
        rgb = np.stack([x, 0.5 * x, 0.25 * x], axis=2)
        frame = encoded(rgb)
        result = temporal.decode(frame.codes, PARAMS, state)
        assert result.winding.shape == result.irradiance.shape == (SIZE, SIZE, 3)
        np.testing.assert_array_equal(result.winding, frame.winding)


def test_a_colour_keyframe_joins_its_channels_as_a_still_frame_would() -> None:
    """The spatial decoder's channels disagree (blue a wrap low in a region); a colour
    decoder's keyframe makes them consistent, as its still decode does."""
    params = SensorParams(encoding="mantissa", bits=12)
    x = blob(1.0)
    frame = encoded(np.stack([x, 0.8 * x, 0.6 * x], axis=2), params)
    wrong = frame.winding.copy()
    wrong[24:34, 26:40, 2] -= 1
    assert (wrong != frame.winding).any()
    spatial = ColourDecoder(FixedPlanesDecoder(wrong))
    config = TemporalConfig(refine_keyframes=False)
    result = StreamDecoder("temporal", spatial, config).decode(frame.codes, params, StreamState())
    assert result.keyframe == "first"
    np.testing.assert_array_equal(result.winding, frame.winding)


def test_bad_mode_decoder_and_frame_are_refused(temporal: StreamDecoder) -> None:
    with pytest.raises(InvalidInputError, match="unknown mode"):
        StreamDecoder("magic", "itoh")
    with pytest.raises(InvalidInputError, match="unknown decoder"):
        StreamDecoder("temporal", "nope")
    with pytest.raises(InvalidInputError):
        temporal.decode(np.zeros(5, np.uint8), PARAMS, StreamState())
    with pytest.raises(InvalidInputError):
        temporal.decode(np.full((4, 4), 300, np.uint16), PARAMS, StreamState())


@pytest.mark.parametrize("shape", [(1, 9), (9, 1)])
def test_one_pixel_wide_frames_get_a_clear_error(temporal: StreamDecoder, shape: tuple) -> None:
    """A 1 x N frame has no neighbours to unwrap against, in either mode."""
    state = StreamState()
    with pytest.raises(InvalidInputError, match="no neighbours"):
        temporal.decode(np.zeros(shape, np.uint8), PARAMS, state)
    assert state.u is None


@pytest.mark.parametrize("mode", ["independent", "temporal"])
@pytest.mark.parametrize("shape", [(1, 9), (9, 1), (1, 1), (1, 9, 3)])
def test_clip_frames_one_pixel_wide_decode_to_w_0(mode: str, shape: tuple) -> None:
    """A clipped sensor never wraps: its frames of any size with a pixel decode to
    W = 0, frame after frame, as a still clip frame does."""
    params = SensorParams(encoding="clip", bits=8)
    stream, state = StreamDecoder(mode, "itoh"), StreamState()
    for value in (10, 200, 255):
        codes = np.full(shape, value, np.uint8)
        result = stream.decode(codes, params, state)
        still = get_decoder("itoh").decode(codes, params)
        assert not result.winding.any()
        np.testing.assert_array_equal(result.irradiance, still.irradiance)


def test_a_still_stream_keeps_a_clipped_lamp_filled() -> None:
    """auto fills the lamp's clipped core; the anchoring keyframe's refinement would lower
    it again, so the stream fills it after refining and carries it on."""
    params = SensorParams(encoding="mantissa", bits=8, max_wraps=16.0, read_noise=0.002)
    yy, xx = np.mgrid[0:64, 0:64].astype(np.float64)
    texture = 0.6 + 0.5 * np.sin(xx / 3.0) * np.cos(yy / 5.0)
    scene = texture + 2000.0 * np.exp(-((yy - 32) ** 2 + (xx - 32) ** 2) / 32.0)
    frames = [encode(scene, params.model_copy(update={"seed": t})) for t in range(4)]
    decoder = StreamDecoder("temporal", "auto-balanced")
    decoded = list(decode_frames([f.codes for f in frames], params, decoder))
    assert decoded[0].keyframe == "first" and all(d.keyframe is None for d in decoded[1:])
    for frame, result in zip(frames, decoded, strict=True):
        clipped = frame.irradiance >= 16.0
        assert clipped.sum() > 100
        np.testing.assert_array_equal(result.winding[clipped], frame.winding[clipped])


@pytest.mark.parametrize("spatial", ["itoh", "auto-fast"])
def test_a_colour_stream_keeps_a_white_lamp_white(spatial: str) -> None:
    """Each channel's keyframe filled the lamp on its own, and the stream carried the
    tint on: with itoh blue stayed short (x 1.0 on the core, 16 true), with auto-fast
    red and green did."""
    frame, _, clipped = colour_lamp()
    codes = [frame.codes] * 3
    decoded = list(decode_frames(codes, frame.params, StreamDecoder("temporal", spatial)))
    core = clipped.all(axis=2)
    for result in decoded:
        np.testing.assert_array_equal(result.winding[core], frame.winding[core])


def test_a_whole_refinement_on_a_pan_keeps_a_filled_lamp_filled() -> None:
    """The moving camera's whole-frame refinement lowered 407 of a clipped lamp's 666
    pixels 1-4 wraps (its energy does not know the clip), and nothing filled them again
    until the lamp left the frame."""
    rows, cols = np.mgrid[0:64, 0:256].astype(np.float64)
    scene = smooth_scene(64, 256, 2.0, 3) + 3000.0 * np.exp(
        -((rows - 32) ** 2 + (cols - 30) ** 2) / 40.0
    )
    params = SensorParams(encoding="mantissa", bits=8, max_wraps=16.0, read_noise=0.002)
    frames = [
        simulate(np.roll(scene, -3 * t, axis=1)[:, :80], params.model_copy(update={"seed": t}))
        for t in range(10)
    ]
    decoder = StreamDecoder("temporal", "auto-fast", TemporalConfig(keyframe_interval=0))
    state = StreamState()
    wrong = [
        int(((decoder.decode(f.codes, params, state, sequence=t).winding != f.winding)
             & (f.irradiance >= 16.0)).sum())
        for t, f in enumerate(frames)
    ]
    assert wrong == [0] * 10


def test_an_anchoring_keyframe_is_anchored_after_its_refinement() -> None:
    """A first frame that never wraps, decoded by a spatial decoder one wrap high on its
    right half (itoh on the sunrise clip's dark first frame): the keyframe's refinement
    lifts the whole frame to W = 1 at the least energy (raising is cheaper than
    lowering), and the stream carried that on (sunrise with itoh: 16.27 dB). The
    refined keyframe is anchored as a spatial decode is: its darkest pixels at W = 0."""
    params = SensorParams(encoding="mantissa")
    yy, xx = np.mgrid[0:64, 0:64] / 64
    frame = encode(0.1 + 0.7 * np.exp(-((xx - 0.5) ** 2 + (yy - 0.5) ** 2) / 0.1), params)
    assert not frame.winding.any()
    lifted = np.zeros((64, 64, 1), np.int64)
    lifted[:, 32:] = 1
    spatial = FixedPlanesDecoder(lifted)
    result = StreamDecoder("temporal", spatial, TemporalConfig()).decode(
        frame.codes, params, StreamState()
    )
    assert result.keyframe == "first"
    np.testing.assert_array_equal(result.winding, frame.winding)
