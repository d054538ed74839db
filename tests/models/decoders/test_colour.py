"""Tests of models/decoders/colour.py: a colour frame's channels made consistent."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray

from models.decoders.adaptive import AdaptiveDecoder
from models.decoders.colour import (
    ANCHOR_CODE,
    MIN_ANCHORS,
    ColourDecoder,
    colour_anchors,
    harmonise,
    has_jumps,
    relative_winding,
)
from models.decoders.guided_puma import GuidedPumaDecoder
from models.decoders.registry import get_decoder, name_patterns, resolve
from models.errors import InvalidInputError
from models.formation import SensorParams, dequantize, encode
from tests.models.decoders.colour_lamp import colour_lamp
from tests.models.decoders.fixed_planes import FixedPlanesDecoder


def colour_scene(
    size: int = 64, peak: float = 12.0, chroma: tuple[float, float] = (0.25, -0.2)
) -> NDArray[np.float64]:
    """A smooth colour scene (H x W x 3, wrap units): a bright hill on a dark floor,
    red and blue tilted from green by smooth log-chroma fields of the given strength
    (natural log)."""
    yy, xx = np.mgrid[0:size, 0:size] / size
    green = 0.05 + peak * np.exp(-((xx - 0.5) ** 2 + (yy - 0.45) ** 2) / 0.06)
    red = green * np.exp(chroma[0] * np.sin(3 * xx + 1))
    blue = green * np.exp(chroma[1] * np.cos(2 * yy))
    return np.stack([red, green, blue], axis=2)


def frame_of(
    scene: NDArray[np.float64], encoding: str = "mantissa"
) -> tuple[NDArray[np.float64], NDArray[np.int64], SensorParams]:
    """(m, true W, params) of ``scene`` at 12 bits."""
    params = SensorParams(encoding=encoding, bits=12)
    frame = encode(scene, params)
    return dequantize(frame.codes, params.bits), frame.winding, params


def test_the_scene_wraps_several_times_in_every_channel() -> None:
    m, truth, _ = frame_of(colour_scene())
    assert m.shape == truth.shape == (64, 64, 3)
    assert all(truth[:, :, c].max() >= 3 for c in range(3))
    assert colour_anchors(m, truth).sum() >= MIN_ANCHORS


def test_a_channel_decoded_a_wrap_off_in_a_region_is_put_right() -> None:
    m, truth, params = frame_of(colour_scene())
    decoded = truth.copy()
    decoded[20:34, 22:40, 2] -= 1
    decoded[38:48, 10:26, 0] += 1
    harmonised, facts = harmonise(m, decoded, params)
    np.testing.assert_array_equal(harmonised, truth)
    assert facts["changed_fraction"] == pytest.approx(np.mean(decoded != truth))
    assert facts["majority_fraction"] == 1.0


def test_the_reference_channel_is_put_right_by_the_other_two() -> None:
    m, truth, params = frame_of(colour_scene())
    decoded = truth.copy()
    decoded[18:30, 25:45, 1] += 1
    np.testing.assert_array_equal(harmonise(m, decoded, params)[0], truth)


def test_two_channels_wrong_the_same_way_make_the_third_wrong_too() -> None:
    """The documented failure mode: the majority decides."""
    m, truth, params = frame_of(colour_scene())
    decoded = truth.copy()
    decoded[20:30, 20:30, :2] += 1
    harmonised, _ = harmonise(m, decoded, params)
    np.testing.assert_array_equal(harmonised[20:30, 20:30], truth[20:30, 20:30] + 1)


@settings(max_examples=15, deadline=None)
@given(
    peak=st.floats(1.5, 60.0),
    red=st.floats(-0.3, 0.3),
    blue=st.floats(-0.3, 0.3),
)
def test_a_right_decode_of_a_smooth_mantissa_scene_stays_right(
    peak: float, red: float, blue: float
) -> None:
    m, truth, params = frame_of(colour_scene(48, peak, (red, blue)))
    harmonised, facts = harmonise(m, truth, params)
    np.testing.assert_array_equal(harmonised, truth)
    assert facts["changed_fraction"] == 0.0


def test_a_right_decode_of_a_modulo_scene_stays_right() -> None:
    m, truth, params = frame_of(colour_scene(peak=4.0), "modulo")
    assert truth.max() >= 3
    np.testing.assert_array_equal(harmonise(m, truth, params)[0], truth)


def test_anchors_are_dark_pixels_decoded_unwrapped_in_every_channel() -> None:
    m = np.full((4, 4, 3), 0.2)
    m[0, 0, 2] = ANCHOR_CODE + 0.1
    winding = np.zeros((4, 4, 3), np.int64)
    winding[1, 1, 0] = 1
    anchors = colour_anchors(m, winding)
    assert not anchors[0, 0] and not anchors[1, 1]
    assert anchors.sum() == 14


def test_without_anchors_the_darkest_pixels_set_the_relative_constant() -> None:
    """No pixel reads dark in every channel (red is lifted above ANCHOR_CODE), and the
    blue channel was decoded a wrap high on most of the frame (as a stitch of tiles can
    leave it): the chroma makes blue consistent, and its constant puts blue's darkest
    pixels at W = 0, as a single channel's anchoring does, not at the decode's most
    common offset."""
    scene = colour_scene()
    scene[:, :, 0] += 0.6
    m, truth, params = frame_of(scene)
    assert colour_anchors(m, truth).sum() == 0
    assert np.mean(truth[:, :, 2] == 0) > 0.3
    decoded = truth.copy()
    decoded[:, :45, 2] += 1
    relative = relative_winding(m, decoded, 2, colour_anchors(m, decoded))
    np.testing.assert_array_equal(relative, truth[:, :, 2] - truth[:, :, 1])
    harmonised, facts = harmonise(m, decoded, params)
    np.testing.assert_array_equal(harmonised, truth)
    assert facts["anchors"] == 0


def test_the_result_stays_in_the_encodings_range() -> None:
    m, truth, _ = frame_of(colour_scene())
    params = SensorParams(encoding="mantissa", bits=12, max_wraps=4.0)
    decoded = np.minimum(truth, 3)
    decoded[:8, :8, 0] = 0
    harmonised, _ = harmonise(m, decoded, params)
    assert harmonised.min() >= 0 and harmonised.max() <= 3
    assert harmonised.dtype == np.int64


def test_the_colour_decoder_fixes_its_inner_decoders_colour_frames() -> None:
    scene = colour_scene()
    params = SensorParams(encoding="mantissa", bits=12)
    frame = encode(scene, params)
    decoded = frame.winding.copy()
    decoded[20:34, 22:40, 2] -= 1
    result = ColourDecoder(FixedPlanesDecoder(decoded)).decode(frame.codes, params)
    np.testing.assert_array_equal(result.winding, frame.winding)
    assert result.info["decoder"] == "fixed+colour"
    assert result.info["colour"]["changed_fraction"] > 0


def test_the_colour_decoder_leaves_grayscale_frames_to_its_inner_decoder() -> None:
    params = SensorParams(encoding="mantissa", bits=12)
    frame = encode(colour_scene()[:, :, 1], params)
    wrong = frame.winding[:, :, None] + 1
    result = ColourDecoder(FixedPlanesDecoder(wrong)).decode(frame.codes, params)
    np.testing.assert_array_equal(result.winding, wrong[:, :, 0])
    assert "colour" not in result.info


def test_names_resolve_and_wrong_ones_say_why() -> None:
    assert resolve("herraez+colour").kind == "colour"
    assert get_decoder("itoh+puma+colour").name == "itoh+puma+colour"
    assert any("+colour" in text for text in name_patterns())
    with pytest.raises(InvalidInputError, match="unknown decoder 'nope'"):
        resolve("nope+colour")


def test_a_refined_decoder_joins_the_channels_as_its_guide_does() -> None:
    """PUMA guided by ``<decoder>+colour`` refines each channel, then makes them
    consistent, as ``<decoder>+puma+colour`` does (the name composes in that order only)."""
    params = SensorParams(encoding="mantissa", bits=12)
    frame = encode(colour_scene(), params)
    first = GuidedPumaDecoder(get_decoder("herraez+colour")).decode(frame.codes, params)
    second = get_decoder("herraez+puma+colour").decode(frame.codes, params)
    np.testing.assert_array_equal(first.winding, second.winding)
    assert "colour" in first.info and "colour" in second.info


@pytest.mark.parametrize(("quality", "joint"), [("fast", False), ("balanced", True)])
def test_auto_makes_colour_frames_consistent_at_balanced_and_best(
    quality: str, joint: bool
) -> None:
    params = SensorParams(encoding="mantissa", bits=12)
    frame = encode(colour_scene(), params)
    result = AdaptiveDecoder(quality).decode(frame.codes, params)
    assert ("colour" in result.info) is joint
    forced = AdaptiveDecoder(quality, joint_colour=not joint).decode(frame.codes, params)
    assert ("colour" in forced.info) is not joint
    gray = AdaptiveDecoder(quality).decode(frame.codes[:, :, 1], params)
    assert "colour" not in gray.info


def test_a_colour_frame_auto_already_made_consistent_is_not_harmonised_twice() -> None:
    params = SensorParams(encoding="mantissa", bits=12)
    frame = encode(colour_scene(), params)
    inner = AdaptiveDecoder("balanced")
    once = inner.decode(frame.codes, params)
    wrapped = ColourDecoder(inner).decode(frame.codes, params)
    np.testing.assert_array_equal(wrapped.winding, once.winding)
    assert wrapped.info["colour"] == once.info["colour"]


def test_channels_that_agree_everywhere_cost_no_min_cut(monkeypatch: pytest.MonkeyPatch) -> None:
    """A guide without a chroma jump is the minimum: no move is searched."""
    m, truth, params = frame_of(colour_scene(peak=8.0))
    assert not has_jumps(np.zeros((3, 3))) and has_jumps(np.array([[0.0, 0.7]]))

    def refuse(*args: object) -> None:
        raise AssertionError("no min-cut should run")

    monkeypatch.setattr("models.decoders.colour.minimise", refuse)
    harmonised, _ = harmonise(m, truth, params)
    np.testing.assert_array_equal(harmonised, truth)


def test_balanced_joins_frames_up_to_its_size_and_says_why_not_beyond() -> None:
    params = SensorParams(encoding="mantissa", bits=12)
    frame = encode(colour_scene(), params)
    decoder = AdaptiveDecoder("balanced")
    assert decoder.join_max_pixels == 512 * 512 and AdaptiveDecoder("best").join_max_pixels is None
    decoder.join_max_pixels = 32 * 32
    result = decoder.decode(frame.codes, params)
    reason = "not joined: frames over 32x32 px are joined at best only"
    assert result.info["colour"] == {"reason": reason}


def test_a_filling_inner_decoder_fills_a_white_lamp_in_every_channel_before_the_join() -> None:
    """auto-fast filled the lamp's core in blue alone; the join's majority then lowered
    blue too (x on the core 0.02 / 0.36 / 3.49 wraps, 16 true)."""
    frame, _, clipped = colour_lamp()
    result = get_decoder("auto-fast+colour").decode(frame.codes, frame.params)
    core = clipped.all(axis=2)
    np.testing.assert_array_equal(result.winding[core], frame.winding[core])
    assert result.info["colour"]["saturation"]["changed_fraction"] > 0
